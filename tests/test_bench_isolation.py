"""benchmarks/bench_isolation.py end to end, short: a router, quantize and localize
processes, an honest `qradar source` and a flooding client over 127.0.0.1; every frame the
flood sent is counted at the node it hits, and the honest sensor loses nothing."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.measure

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_isolation.py"


def test_a_short_flood_beside_an_honest_sensor_is_accounted_for(tmp_path):
    proc = subprocess.run([sys.executable, str(BENCH), "--case", "quantized", "--seconds", "2", "--warmup", "1.5",
                           "--rate", "1000", "--logdir", str(tmp_path)], capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-2000:]
    row = json.loads(next(line for line in proc.stdout.splitlines() if line.startswith("{")))
    assert row["flood_sent"] > 500 and row["honest_sent"] > 50  # (the rates a busy host reaches)
    assert row["honest_lost"] == 0 and row["unaccounted"] == 0 and row["node_balance"] == 0, row
    # at 1 000/s against 100/s per key (and a second's burst), most of the flood is over budget
    assert row["node_totals"]["over_budget"] > row["flood_sent"] // 2
    assert "| quantized |" in proc.stdout  # the table
