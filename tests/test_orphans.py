"""Nothing qradar starts outlives its parent: a driver process ends by itself (GBYE to
its sensor) once the process that started it is gone, however it died (SIGKILL of the
run, of its whole process group, the OOM killer)."""

from __future__ import annotations

import fcntl
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from radar_driver.scene import resolve_scene
from radar_driver.simulator import SimulatorServer
from zenoh_helpers import QRADAR, RUNTIME_DECODER



def cmdline(pid: int) -> list[str]:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        return []


def child_config(pid: int) -> dict:
    """The ``--config-json`` a qradar child was started with ({} without one)."""
    import json

    cmd = cmdline(pid)
    return json.loads(cmd[cmd.index("--config-json") + 1]) if "--config-json" in cmd else {}


def parent_of(pid: int) -> int | None:
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return None


def children_of(parent_pid: int, command: str | None = None) -> list[int]:
    """Pids of the ``qradar`` processes (of ``command``, if given) whose parent is ``parent_pid``."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit() and parent_of(int(entry)) == parent_pid:
            cmd = cmdline(int(entry))
            if "qradar" in cmd and (command is None or command in cmd[cmd.index("qradar") + 1:][:1]):
                out.append(int(entry))
    return out


def drivers_of(parent_pid: int) -> list[int]:
    """Pids of the ``qradar drive`` processes ``parent_pid`` started (it hands each its
    config, its own pid in it, as ``--config-json``)."""
    return children_of(parent_pid, "drive")


def alive(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def wait_for(cond, timeout_s: float, step_s: float = 0.05):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = cond()
        if value:
            return value
        time.sleep(step_s)
    return cond()


def kill_all(pids) -> None:
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


@pytest.mark.parametrize("how", ["process", "group"])
def test_a_killed_run_leaves_no_driver_behind(how, tmp_path):
    tmp = tempfile.mkdtemp(prefix="qro-", dir="/tmp")  # its run directory there (short: a unix socket's path)
    run = subprocess.Popen([*QRADAR, "run", *RUNTIME_DECODER, "--duration", "60", "--no-record", "--json",
                            "--sensors", "2"],
                           stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                           start_new_session=True, cwd=tmp_path, env={**os.environ, "TMPDIR": tmp})
    drivers: list[int] = []
    try:
        drivers = wait_for(lambda: (d := drivers_of(run.pid)) and len(d) == 2 and d, 30.0)
        assert drivers and len(drivers) == 2, "qradar run started no driver processes"
        assert wait_for(lambda: unix_listeners(tmp), 30.0), "the run's zenoh socket does not listen"
        assert all(alive(p) for p in drivers), "a driver ended before the run was killed"
        if how == "group":
            os.killpg(run.pid, signal.SIGKILL)
        else:
            run.kill()
        run.wait(10)
        t0 = time.monotonic()
        left = wait_for(lambda: not any(alive(p) for p in drivers), 30.0, step_s=0.01)
        gone_s = time.monotonic() - t0
        assert left, f"driver processes {[p for p in drivers if alive(p)]} outlived the SIGKILLed run"
        assert gone_s < 10.0, f"drivers gone {gone_s:.3f} s after the run's SIGKILL (held: 0.11-0.28 s)"
        assert not unix_listeners(tmp), "a unix socket of the run still listens"
    finally:
        kill_all([run.pid, *drivers])
        run.wait(10)
        shutil.rmtree(tmp, ignore_errors=True)


def unix_listeners(fragment: str) -> list[str]:
    """Paths of the unix sockets listening now whose path holds ``fragment`` (/proc/net/unix)."""
    out = []
    for line in Path("/proc/net/unix").read_text().splitlines()[1:]:
        cols = line.split()
        if len(cols) >= 8 and cols[5] == "01" and fragment in cols[7]:  # state LISTEN
            out.append(cols[7])
    return out


def test_the_next_run_removes_the_directory_of_a_sigkilled_one():
    """A SIGKILLed run cannot remove its directory (pty links, the zenoh socket); the next
    ``qradar run`` removes it when it starts, leaves alone a live run's (its lock held) and
    one it cannot judge (no lock file: made before, or by other means), and removes its
    own at its end."""
    tmp = tempfile.mkdtemp(prefix="qro-", dir="/tmp")  # short: a unix socket's path has 107 bytes at most
    env = {**os.environ, "TMPDIR": tmp}
    live_dir, legacy_dir = Path(tmp) / "qradar-run-live", Path(tmp) / "qradar-run-legacy"
    live_dir.mkdir()
    legacy_dir.mkdir()
    lock = os.open(live_dir / "owner.lock", os.O_CREAT | os.O_RDWR, 0o600)
    fcntl.flock(lock, fcntl.LOCK_EX)
    run = subprocess.Popen([*QRADAR, "run", *RUNTIME_DECODER, "--duration", "60", "--no-record", "--json"],
                           stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                           start_new_session=True, env=env)
    drivers: list[int] = []
    try:
        drivers = wait_for(lambda: drivers_of(run.pid), 30.0)
        mine = [p for p in Path(tmp).glob("qradar-run-*") if p not in (live_dir, legacy_dir)]
        assert len(mine) == 1 and (mine[0] / "owner.lock").is_file() and (mine[0] / "zenoh.sock").exists()
        os.killpg(run.pid, signal.SIGKILL)
        run.wait(10)
        assert wait_for(lambda: not any(alive(p) for p in drivers), 30.0)
        assert mine[0].is_dir()  # nothing could remove it
        nxt = subprocess.run([*QRADAR, "run", *RUNTIME_DECODER, "--frames", "3", "--no-record", "--json"],
                             stdin=subprocess.DEVNULL,
                             capture_output=True, text=True, timeout=120, env=env)
        assert nxt.returncode == 0, nxt.stderr[-2000:]
        assert sorted(p.name for p in Path(tmp).iterdir()) == ["qradar-run-legacy", "qradar-run-live"]
    finally:
        kill_all([run.pid, *drivers])
        run.wait(10)
        os.close(lock)
        shutil.rmtree(tmp, ignore_errors=True)


def test_a_driver_whose_parent_dies_says_gbye_and_exits(tmp_path):
    """The driver's parent is a small process we SIGKILL: the driver notices, says GBYE
    to the (in-process) simulated sensor and exits 0 with its counters."""
    sim = SimulatorServer(resolve_scene("chamber"), link_path=tmp_path / "kmd2", rate_hz=20.0)
    sim.start()
    out, err = tmp_path / "drive.out", tmp_path / "drive.err"
    drive_cmd = [*QRADAR, "drive", "--port", str(tmp_path / "kmd2"), "--no-publish", "--json", "--quiet"]
    parent = subprocess.Popen([sys.executable, "-c", (
        "import os, subprocess, sys, time\n"
        f"p = subprocess.Popen({drive_cmd!r} + ['--parent-pid', str(os.getpid())], stdin=subprocess.DEVNULL, "
        f"stdout=open({str(out)!r}, 'w'), stderr=open({str(err)!r}, 'w'))\n"
        "print(p.pid, flush=True)\n"
        "time.sleep(120)\n")], stdout=subprocess.PIPE, text=True)
    drive_pid = None
    try:
        drive_pid = int(parent.stdout.readline())
        dev = sim.devices[0]
        assert wait_for(lambda: dev.radcs_sent >= 10, 60.0), "the driver read no frames"
        assert dev.event_counts["GBYE"] == 0
        parent.kill()
        parent.wait(5)
        t0 = time.monotonic()
        assert wait_for(lambda: not alive(drive_pid), 30.0), "the driver outlived its parent"
        assert time.monotonic() - t0 < 10.0
        assert "parent process" in err.read_text() and "is gone" in err.read_text()
        assert '"frames"' in out.read_text().splitlines()[-1]
        assert dev.event_counts["GBYE"] == 1
    finally:
        kill_all([parent.pid] + ([drive_pid] if drive_pid else []))
        parent.wait(5)
        sim.stop()


def test_a_killed_monte_carlo_leaves_no_worker_behind(tmp_path):
    """``qradar montecarlo``'s worker processes (spawned by its pool) end once it is SIGKILLed:
    each watches its parent (radar_driver.lifetime.watch_parent), where they waited for work for good."""
    proc = subprocess.Popen([*QRADAR, "montecarlo", "--K", "1", "--runs", "400000", "--workers", "2", "--no-plots",
                             "--quiet", "--out", str(tmp_path / "mc")], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        workers: list[int] = []
        deadline = time.monotonic() + 60
        while len(workers) < 2 and time.monotonic() < deadline and proc.poll() is None:
            workers = [p for p in (int(e) for e in os.listdir("/proc") if e.isdigit())
                       if parent_of(p) == proc.pid and any("spawn_main" in a for a in cmdline(p))]
            time.sleep(0.1)
        assert len(workers) == 2, "the Monte Carlo's two workers did not start"
        proc.kill()
        proc.wait(10)
        deadline = time.monotonic() + 15
        while any(cmdline(p) for p in workers) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not [p for p in workers if cmdline(p)], "a Monte Carlo worker outlived its parent"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
