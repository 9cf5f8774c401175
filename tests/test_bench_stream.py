"""benchmarks/bench_stream.py end to end in its quick mode: fresh node processes, a sink
process, the figures of every step (not whether this machine passes the p99 bar)."""

import json
import math
import os
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np
import pytest
from streamlib import BUSY_LOOP

pytestmark = pytest.mark.measure

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks" / "bench_stream.py"


def run_quick(tmp_path: Path, *args: str) -> dict:
    out = tmp_path / "bench.json"
    r = subprocess.run([sys.executable, str(BENCH), "--quick", "--json", str(out), *args], capture_output=True,
                       text=True, cwd=ROOT, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr[-2000:]
    assert "| case / send / decoder |" in r.stdout  # the Markdown table
    return json.loads(out.read_text())


def check_step(step: dict, nodes: set[str], player: bool = False) -> None:
    assert step["sensors"] == 5 and step["sent"] == 5 * 100  # (2 s warm-up + 3 s) x 20 frames/s
    assert step["received"] == step["sent"] and step["lost"] == 0 and step["duplicates"] == 0
    assert math.isfinite(step["p50_ms"]) and math.isfinite(step["p99_ms"]) and 0 < step["p50_ms"] <= step["p99_ms"]
    assert set(step["nodes"]) == nodes | {"sink", "source"}
    for name, node in step["nodes"].items():
        assert node["cpu_pct"] is not None and node["cpu_pct"] > 0, name
        if name != "sink" and not (player and name == "source"):  # a player is no node: no node counters
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


@pytest.mark.slow
def test_quick_edge_premade(tmp_path):
    """--premade: the frames are made before the step and a player sends them; the step
    passes through the same localizer and sink, every frame accounted for, and the
    pre-made file is deleted afterwards."""
    before = set(Path(tempfile.gettempdir()).glob("qr-premade-*"))
    res = run_quick(tmp_path, "--case", "edge", "--premade")
    (step,) = res["steps"]
    check_step(step, {"localize0"}, player=True)
    assert step["nodes"]["source"]["frames_out"] == step["sent"]
    assert res["summary"][0]["label"] == "edge/burst/pbp premade"
    assert set(Path(tempfile.gettempdir()).glob("qr-premade-*")) == before


@pytest.mark.slow
def test_quick_edge_on_a_busy_host(tmp_path):
    """--busy 1: a spinning process runs through the step and is gone after it."""
    res = run_quick(tmp_path, "--case", "edge", "--busy", "1")
    (step,) = res["steps"]
    check_step(step, {"localize0"})
    assert step["busy"] == 1 and res["summary"][0]["label"] == "edge/burst/pbp +1 busy"
    spinning = subprocess.run(["pgrep", "-f", BUSY_LOOP], capture_output=True, text=True).stdout.split()
    assert not spinning


def test_premade_refuses_the_central_case(tmp_path):
    r = subprocess.run([sys.executable, str(BENCH), "--quick", "--case", "central", "--premade"], capture_output=True,
                       text=True, cwd=ROOT, timeout=60, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 2 and "--premade sends 1-bit frames: use it with --case edge" in r.stderr
    r = subprocess.run([sys.executable, str(BENCH), "--quick", "--case", "edge", "--premade", "--source-args",
                        "--scene empty"], capture_output=True, text=True, cwd=ROOT, timeout=60,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 2 and "--source-args would be ignored" in r.stderr


def test_premade_frames_are_what_an_edge_source_publishes(tmp_path, bus, zenoh_session):
    """make_premade's frames are byte for byte the 1-bit frames `qradar source --quantized
    --rate 0` publishes (the same simulation, noise, dither seeds and quantizer), but for
    the timestamp, which the player rewrites at sending."""
    from pipeline.nodes.stream import SourceNode, run_nodes
    from pipeline.dsp.quantize import QuantizerConfig
    from pipeline.wire import COMMON_DTYPE
    from radar_driver.scene import resolve_scene
    from radar_driver.source import SimSourceConfig, SimulatedSource
    from zenoh_helpers import Collector, stop_when

    import streamlib

    path = streamlib.make_premade(tmp_path / "frames.npy", "chamber", sensors=3, frames=4, alpha=1.0, bits=1,
                                  id_prefix="b")
    premade = np.load(path)
    assert premade.shape == (4, 3, streamlib.frame_sizes(streamlib.StepSpec("edge", "burst", "pbp", 3, 0.0))[
        "quantized"])
    col = Collector(zenoh_session, "radar/*/quantized")
    src = SimulatedSource(SimSourceConfig(resolve_scene("chamber"), sensors=3, rate_hz=0.0, frames=4, id_prefix="b"))
    node = SourceNode(bus, src, session=zenoh_session, quantizer=QuantizerConfig(bits=1, alpha=1.0))
    stop = threading.Event()
    threading.Thread(target=stop_when, args=(lambda: len(col.items) >= 12, stop, 20), daemon=True).start()
    run_nodes([node], 30, stop)
    with col.lock:
        published = list(col.items)
    assert len(published) == 12
    ts = slice(COMMON_DTYPE.fields["timestamp_ns"][1], COMMON_DTYPE.fields["timestamp_ns"][1] + 8)
    for key, payload in published:
        sensor = int(key.split("/")[1][1:])
        seq = int.from_bytes(payload[COMMON_DTYPE.fields["seq"][1]:][:8], "little")
        row = premade[seq, sensor].tobytes()
        assert row[:ts.start] == payload[:ts.start] and row[ts.stop:] == payload[ts.stop:], (key, seq)


@pytest.mark.slow
def test_bench_receive_counts_every_message_in_each_hand_off():
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_receive.py"), "--messages", "1500",
                        "--rate", "3000", "--rounds", "1"], capture_output=True, text=True, cwd=ROOT, timeout=180,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr[-2000:]
    rows = [json.loads(line) for line in r.stderr.splitlines() if line.startswith("{")]
    assert [row["mode"] for row in rows] == ["poll", "notify", "fifo"]
    for row in rows:
        assert row["complete"] and row["received"] >= 1500 and row["cpu_us_per_msg"] > 0, row
    assert "| 0 | fifo |" in r.stdout


def test_bench_localize_steps_times_every_step():
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_localize_steps.py"), "--frames", "64",
                        "--batches", "1,16", "--passes", "1"], capture_output=True, text=True, cwd=ROOT, timeout=120,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr[-2000:]
    rows = [line.split("|")[1:-1] for line in r.stdout.splitlines() if line.startswith("| 1")]
    assert [int(row[0]) for row in rows] == [1, 16]
    for row in rows:
        steps = [float(c) for c in row[1:7]]
        assert all(v >= 0 for v in steps) and steps[2] > 0  # decode takes time
        assert abs(sum(steps) - float(row[7])) <= 6  # the batch is the sum of its steps (rounding)


def test_benchmark_helpers_refuse_what_they_cannot_measure_in_one_line(tmp_path):
    """A player whose file holds fewer frames than asked, and a batch larger than the
    frames, exit with one line naming the numbers (no traceback, no session opened)."""
    np.save(tmp_path / "f.npy", np.zeros((3, 2, 320), dtype=np.uint8))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "streamlib.py"), "player", "--connect",
                        "tcp/127.0.0.1:9", "--file", str(tmp_path / "f.npy"), "--sensors", "2", "--frames", "5",
                        "--id-prefix", "b"], capture_output=True, text=True, cwd=ROOT, timeout=60, env=env)
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines() == [f"player: {tmp_path / 'f.npy'} holds 2 sensors x 3 frames, fewer than "
                                             "--sensors 2 x --frames 5"]
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_localize_steps.py"), "--frames", "8",
                        "--batches", "16"], capture_output=True, text=True, cwd=ROOT, timeout=60, env=env)
    assert r.returncode == 1 and r.stderr.strip().splitlines()[-1] == "--frames 8 is fewer than a batch of 16"
