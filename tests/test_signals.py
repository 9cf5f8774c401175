"""The live commands besides ``run`` share its rule for SIGINT and SIGTERM: the first
ends them normally, with what they print at their normal end; a second one while they
stop exits at once with status 130 and one line. Real processes and real signals;
every wait is bounded."""

from __future__ import annotations

import json
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest

from radar_driver.scene import resolve_scene
from radar_driver.simulator import SimulatorServer
from zenoh_helpers import QRADAR, Collector, free_port, wait_until

ROOT = Path(__file__).resolve().parents[1]


def test_ctrl_c_ends_a_replay_which_says_what_it_published(connect_when_ready):
    """``qradar replay --loop`` stopped by Ctrl-C prints its counters (as record, quantize,
    localize, view, source, drive and sim do), with ``"interrupted": true``."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen([*QRADAR, "replay", str(ROOT / "recordings" / "chamber.mcap"),
                             "--loop", "--rate", "4", "--listen", endpoint], cwd=ROOT, stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        col = Collector(connect_when_ready(endpoint, timeout_s=60), "radar/**")
        wait_until(lambda: len(col.items) >= 20 or proc.poll() is not None, 60, "20 replayed messages")
        assert proc.poll() is None
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    result = json.loads(out.strip().splitlines()[-1])
    assert result["interrupted"] is True and result["published"] >= 20 and "Traceback" not in err


def test_a_second_signal_while_a_driver_stops_exits_at_once(tmp_path):
    """``qradar drive --linger-stdin`` (how ``run`` starts its drivers) stopped by SIGTERM
    says GBYE, prints its counters and keeps its zenoh session open until stdin closes;
    a second SIGTERM meanwhile ends it at once with status 130 and one line."""
    link = tmp_path / "kmd2"
    with SimulatorServer(resolve_scene("single"), link_path=link, rate_hz=20) as sim:
        drive = subprocess.Popen([*QRADAR, "drive", "--port", str(link), "--json", "--quiet",
                                  "--linger-stdin"], cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        try:
            wait_until(lambda: sim.devices[0].event_counts["GNFD"] >= 10 or drive.poll() is not None, 60,
                       "the driver polling")
            drive.send_signal(signal.SIGTERM)
            counters = json.loads(drive.stdout.readline())  # after its stop: it lingers now
            # the driver took the first signal before it printed these (on a loaded host, well after it
            # was sent): a second one within SAME_SIGNAL_S of *that* would be the same signal
            t_first = time.monotonic()
            assert counters["frames"] >= 1 and drive.poll() is None
            time.sleep(max(0.0, 0.6 - (time.monotonic() - t_first)))
            drive.send_signal(signal.SIGTERM)
            drive.wait(timeout=10)  # before stdin closes: its end would end the lingering driver normally
            out, err = drive.communicate(timeout=10)
        finally:
            if drive.poll() is None:
                drive.kill()
                drive.communicate(timeout=10)
        assert sim.devices[0].event_counts["GBYE"] >= 1  # the first signal's stop, in order
    assert drive.returncode == 130, err
    assert [ln for ln in err.splitlines() if "while stopping" in ln] == [
        "qradar drive: SIGTERM again while stopping: exiting at once (status 130)"]
    assert "Traceback" not in err and out == ""


@pytest.fixture
def own_signals():
    """StopOnSignals made in this test: the process's handlers and wakeup fd restored after."""
    from qradar.cli.common import StopOnSignals

    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield StopOnSignals
    finally:
        for s, h in saved.items():
            signal.signal(s, h)
        signal.set_wakeup_fd(-1)
        StopOnSignals._current = None


@pytest.mark.parametrize("handled_apart_s, forced", [(0.6, True), (0.0, False)])
def test_two_signals_read_together_are_two_when_they_came_apart(own_signals, monkeypatch, handled_apart_s, forced):
    """The watcher thread reads the signals' bytes when it runs: on a busy host two signals
    0.6 s apart are read together, and a second that was not a duplicate was taken for one (a
    driver ended 0, not 130). The main thread's handler dates them as they come: apart, the
    second forces the exit; one signal delivered twice (the handler runs once) stays one."""
    stops = own_signals(threading.Event(), "test")
    calls = []
    monkeypatch.setattr(stops, "force", calls.append)
    now = time.monotonic()
    stops._handled_s = (now - handled_apart_s, now)
    stops._on_signal("SIGTERM")
    stops._on_signal("SIGTERM")  # read at once after the first
    assert calls == (["SIGTERM"] if forced else []) and stops.stop.is_set()
