"""benchmarks/bench_multihost.py for a few seconds: frames cross three network namespaces
(sensor host, router, localizer host) that the benchmark creates, and none is left."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks" / "bench_multihost.py"


def netns_list() -> set[str]:
    out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, timeout=20).stdout
    return {line.split()[0] for line in out.splitlines() if line.strip()}


@pytest.mark.slow
@pytest.mark.skipif(os.geteuid() != 0, reason="network namespaces need root")
@pytest.mark.skipif(shutil.which("ip") is None, reason="needs the `ip` command (iproute2)")
def test_multihost_quick(tmp_path):
    before = netns_list()
    out = tmp_path / "mh.json"
    r = subprocess.run([sys.executable, str(BENCH), "--case", "edge",
                        "--sensors", "5", "--seconds", "1.5", "--warmup", "1", "--localizers", "1", "2",
                        "--json", str(out)], capture_output=True, text=True, cwd=ROOT, timeout=150,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(out.read_text())
    assert res["namespaces_left"] == [] and netns_list() == before
    ran = res["steps"]
    assert [s["localizers"] for s in ran] == [1, 2]
    for s in ran:
        assert len(s["namespaces"]) == 3 and not set(s["namespaces"]) & before
        # 5 sensors at 20 frames/s for the 1 s warm-up and the 1.5 s measured
        assert s["sent"] == 5 * 50 and s["received"] == s["sent"] and s["lost"] == 0, s["reasons"]
        assert s["hub"] == "router" and s["nodes"]["router"]["cpu_pct"] > 0
        for i in range(s["localizers"]):
            assert s["nodes"][f"localize{i}"]["cpu_pct"] > 0
        assert sum(s["nodes"][f"localize{i}"]["frames_out"] for i in range(s["localizers"])) == s["sent"]
