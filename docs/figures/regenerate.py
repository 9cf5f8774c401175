#!/usr/bin/env python3
"""Regenerate the deterministic figures of docs/ (``make docs-figures``): the re-processing
of the committed chamber recording (docs/recording.md: its table and the two plots
``chamber_alpha_sweep.png`` and ``chamber_reconstructions.png``). Seeded, so the same code
gives the same numbers; ``tests/test_doc_figures.py`` compares the table in the docs with a
fresh run of the command written above it.

    .venv/bin/python docs/figures/regenerate.py [--out out/docs-figures]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: the command docs/recording.md writes above its table (run from the repository's root)
REPROCESS = "qradar reprocess recordings/chamber.mcap --alpha 0:1:0.05 --algos pbp qiht cml"
NAMES = {"pbp": "PBP", "qiht": "`qiht`", "cml": "`cml`"}


def table_rows(results: dict) -> dict[str, list[float]]:
    """Per decoder, the numbers of its row in docs/recording.md's table: best alpha, mean
    error at it, at alpha 0, 0.45 and 1, the weak and the strong reflector's at the best."""
    alphas = [round(a, 6) for a in results["alphas"]]
    rows = {}
    for algo, r in results["by_algo"].items():
        best = alphas.index(round(r["best_alpha"], 6))
        weak, strong = r["mean_error_m"].values()  # the truth's order: the near, weak reflector first
        rows[algo] = [r["best_alpha"], r["error_at_best_m"], r["mean_error_all_m"][0],
                      r["mean_error_all_m"][alphas.index(0.45)], r["mean_error_all_m"][-1], weak[best], strong[best]]
    return rows


def run_reprocess(out: Path) -> dict:
    cmd = REPROCESS.split()
    cmd = [str(Path(sys.executable).parent / "qradar"), *cmd[1:], "--out", str(out), "--quiet"]
    subprocess.run(cmd, cwd=ROOT, check=True, stdin=subprocess.DEVNULL, timeout=900)
    return json.loads((out / "results.json").read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "docs-figures")
    args = ap.parse_args()
    results = run_reprocess(args.out)
    figures = ROOT / "docs" / "figures"
    shutil.copyfile(args.out / "alpha_sweep.png", figures / "chamber_alpha_sweep.png")
    shutil.copyfile(args.out / "reconstructions.png", figures / "chamber_reconstructions.png")
    print(f"`{REPROCESS}`:\n")
    print("| decoder | best α | mean error at best α | at α = 0 | at α = 0.45 | at α = 1 | weak reflector at best α "
          "| strong reflector |\n|---|---|---|---|---|---|---|---|")
    for algo, v in table_rows(results).items():
        print(f"| {NAMES.get(algo, algo)} | {v[0]:.2f} | " + " | ".join(f"{x:#.3g} m" for x in v[1:]) + " |")
    print(f"\nwrote docs/figures/chamber_alpha_sweep.png, chamber_reconstructions.png (from {args.out})")


if __name__ == "__main__":
    main()
