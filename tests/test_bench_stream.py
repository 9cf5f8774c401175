"""benchmarks/bench_stream.py end to end in its quick mode: fresh node processes, a sink
process, the figures of every step (not whether this machine passes the p99 bar)."""

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks" / "bench_stream.py"


def run_quick(tmp_path: Path, *args: str) -> dict:
    out = tmp_path / "bench.json"
    r = subprocess.run([sys.executable, str(BENCH), "--quick", "--json", str(out), *args], capture_output=True,
                       text=True, cwd=ROOT, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr[-2000:]
    assert "| case / send / decoder |" in r.stdout  # the Markdown table
    return json.loads(out.read_text())


def check_step(step: dict, nodes: set[str]) -> None:
    assert step["sensors"] == 5 and step["sent"] == 5 * 100  # (2 s warm-up + 3 s) x 20 frames/s
    assert step["received"] == step["sent"] and step["lost"] == 0 and step["duplicates"] == 0
    assert math.isfinite(step["p50_ms"]) and math.isfinite(step["p99_ms"]) and 0 < step["p50_ms"] <= step["p99_ms"]
    assert set(step["nodes"]) == nodes | {"sink", "source"}
    for name, node in step["nodes"].items():
        assert node["cpu_pct"] is not None and node["cpu_pct"] > 0, name
        if name != "sink":
            assert node["drops"] == 0 and node["frames_missing"] == 0, name
    assert step["nodes"]["localize0"]["frames_out"] == step["sent"]
    assert step["late_ticks"] is not None
    assert step["window_s"] > 2.0 and len(step["loadavg_start"]) == 3


@pytest.mark.slow
def test_quick_central(tmp_path):
    res = run_quick(tmp_path, "--case", "central", "--baseline", "--baseline-seconds", "1")
    (step,) = res["steps"]
    check_step(step, {"quantize0", "localize0"})
    assert step["nodes"]["quantize0"]["frames_out"] == step["sent"]
    bare = step["bare"]
    assert bare["sent"] == bare["received"] == 5 * 20 * 3 and bare["sizes"] == "8240,320,330"
    assert res["summary"][0]["label"] == "central/burst/pbp"


@pytest.mark.slow
def test_quick_edge(tmp_path):
    res = run_quick(tmp_path, "--case", "edge")
    (step,) = res["steps"]
    check_step(step, {"localize0"})
