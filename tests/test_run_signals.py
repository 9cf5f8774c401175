"""Ctrl-C (SIGINT) and SIGTERM are the normal end of a live ``qradar run``: the same
summary as ``--duration`` (``"interrupted": true`` in ``--json``), status 0; a second
signal while it stops (more than 0.5 s after the first: sooner, it is the same one delivered
twice) exits at once with 130, one line and no traceback."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest

from test_orphans import alive, child_config, drivers_of, kill_all, wait_for
from zenoh_helpers import QRADAR, RUNTIME_DECODER


def start_run(tmp_path, *extra) -> subprocess.Popen:
    return subprocess.Popen([*QRADAR, "run", *RUNTIME_DECODER, "--duration", "60", "--no-record", *extra],
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=tmp_path)


def wait_for_targets(proc: subprocess.Popen, stream) -> list[str]:
    """Lines of ``stream`` up to the first live targets line (bounded: 60 lines)."""
    seen = []
    for _ in range(60):
        line = stream.readline()
        seen.append(line)
        if " targets " in line or not line:
            break
    assert any(" targets " in line for line in seen), seen
    return seen


def second_signal(proc: subprocess.Popen) -> None:
    """SIGINT to ``proc``, then, once its stderr says it took it (the run's "stopping"
    line: on a loaded host, well after it was sent), a second SIGINT more than SAME_SIGNAL_S
    after that: not the same interrupt delivered twice. The wait for the line is bounded."""
    proc.send_signal(signal.SIGINT)
    seen, took = [], threading.Event()

    def read():
        for line in iter(proc.stderr.readline, ""):
            seen.append(line)
            if "stopping (again to force)" in line:
                took.set()
                return

    threading.Thread(target=read, daemon=True).start()
    assert took.wait(60), seen
    time.sleep(0.6)  # later than SAME_SIGNAL_S after the run took the first
    proc.send_signal(signal.SIGINT)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_ends_the_run_with_its_summary(tmp_path, sig):
    proc = start_run(tmp_path, "--json")
    try:
        wait_for_targets(proc, proc.stderr)
        time.sleep(1.0)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err[-2000:]
        objects = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
        assert len(objects) == 1 and len(out.strip().splitlines()) == 1
        summary = objects[0]
        assert summary["interrupted"] is True and "error" not in summary
        assert summary["frames_raw"] > 0 and summary["frames_targets"] > 0
        assert "drops_detail" in summary and summary["driver"]["kmd2-0"]["frames"] > 0
        assert "Traceback" not in err
    finally:
        proc.kill()
        proc.wait(10)


def test_the_text_summary_says_it_was_interrupted(tmp_path):
    proc = start_run(tmp_path)
    try:
        wait_for_targets(proc, proc.stdout)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err[-2000:]
        assert "ended by Ctrl-C / SIGTERM" in out and "frames      raw" in out
    finally:
        proc.kill()
        proc.wait(10)


@pytest.fixture
def frozen_sensor_run(tmp_path):
    """A run on a ``qradar sim`` of its own process, which the test freezes (SIGSTOP) before
    it stops the run: a sensor that hangs, so that the run's stop (the driver's GBYE, its
    counters) takes seconds and a second signal comes while it stops. Yields (run, sim,
    its drivers' pids, the run's temporary directory); everything ends with the test."""
    link = tmp_path / "kmd2"
    sim = subprocess.Popen([*QRADAR, "sim", "--link", str(link)], stdin=subprocess.DEVNULL,
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    proc, drivers = None, []
    try:
        assert "simulated K-MD2" in sim.stdout.readline()
        proc = start_run(tmp_path, "--json", "--sensor", f"{link},id=kmd2-0")
        wait_for_targets(proc, proc.stderr)
        drivers = drivers_of(proc.pid)
        sock = next(a for d in drivers for a in child_config(d)["zenoh"]["connect"] if a.startswith("unixsock-stream/"))
        run_dir = Path(sock.removeprefix("unixsock-stream/")).parent
        assert drivers and run_dir.is_dir()
        os.kill(sim.pid, signal.SIGSTOP)  # the sensor hangs
        yield proc, sim, drivers, run_dir
    finally:
        os.kill(sim.pid, signal.SIGCONT)
        kill_all([*([proc.pid] if proc else []), *drivers, sim.pid])
        for p in (proc, sim):
            if p is not None:
                p.wait(10)


def test_a_second_signal_forces_the_exit(frozen_sensor_run):
    proc, _, drivers, _ = frozen_sensor_run
    second_signal(proc)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 130
    assert "again while stopping: exiting at once" in err and "Traceback" not in err
    assert wait_for(lambda: not any(alive(p) for p in drivers), 30.0)  # its driver stopped by itself


def test_a_forced_exit_leaves_no_temporary_directory_and_says_so_in_json(frozen_sensor_run):
    """The second SIGINT comes while the run stops: with --json the run still ends its
    output with one JSON object (the error, status 130), and its temporary directory (the
    zenoh socket) is gone with it."""
    proc, _, drivers, run_dir = frozen_sensor_run
    second_signal(proc)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err[-2000:]
    assert [json.loads(line) for line in out.splitlines()] == [
        {"error": "interrupted", "exit_code": 130, "command": "run"}]
    assert err.count("again while stopping: exiting at once") == 1 and "Traceback" not in err
    assert not run_dir.exists()
    assert wait_for(lambda: not any(alive(p) for p in drivers), 30.0)


def test_the_simulators_own_lateness_is_reported_apart_from_the_drivers_losses(monkeypatch):
    """A simulated sensor of the run writes one RADC 600 ms late (its thread not scheduled,
    as on a busy host; 6 RADC periods at 5 frames/s, a drop without the held clock): it
    holds its device clock, so the driver loses nothing, and the summary names the
    lateness as the simulator's. (At 5 frames/s the driver, two GNFDs in flight, may be
    200 ms late before it loses a frame itself; at 20 frames/s, 50 ms: a loaded host's.)"""
    import qradar.run as run_module
    from qradar.run import RunConfig, format_summary, run
    from radar_driver.simulator import SimulatorServer

    class LateSimulator(SimulatorServer):
        def start(self):
            dev = self.devices[0]
            measure = dev.measure
            dev.measure = lambda index: (time.sleep(0.6) if index == 10 else None, measure(index))[1]
            return super().start()

    monkeypatch.setattr(run_module, "SimulatorServer", LateSimulator)
    summary = run(RunConfig(frames=12, rate_hz=5.0, duration_s=120.0, record=None), live=None)
    assert summary["simulator"]["late_writes"] >= 1 and 0.2 < summary["simulator"]["late_s"] < 5.0
    assert summary["drops_detail"]["sensor_frames"] == 0 and summary["frames_raw"] == 12
    assert "late writes" in format_summary(summary) and "no frame lost" in format_summary(summary)
