"""A small Monte Carlo of the paper's protocol from Python (off-grid ranges, 1-bit with
dither, PBP against cml), and an alpha sweep of a recording, with the result objects the
commands write.

    .venv/bin/python examples/montecarlo_sweep.py [OUT_DIR]
"""

import sys
import tempfile
from pathlib import Path

import qradar

result = qradar.montecarlo(ks=(1,), runs=400, schemes=("dither_m512",), algos=("pbp", "cml"), off_grid=True, seed=1,
                           workers=1)
for name, row in result.summary["K1"].items():  # "<scheme>" (PBP) and "<scheme>@<decoder>"
    print(f"Monte Carlo K = 1 {name}: median position error {row['median_m']:.3f} m over {result.summary['runs']} runs")

out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="qradar-sweep-"))
sweep = qradar.alpha_sweep("recordings/chamber.mcap", out, alphas=(0.25, 0.5, 0.75), algos=("pbp", "cml"))
for algo, row in sweep.summary["by_algo"].items():
    print(f"alpha sweep {algo}: best alpha {row['best_alpha']:.2f}, error there {row['error_at_best_m']:.3f} m")
print(f"written: {', '.join(p.name for p in sweep.written)} in {out}")
