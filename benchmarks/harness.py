"""What the benchmark scripts share: timing loops (best of rounds after a warm-up, or
decoders taking turns for a while), a free port and a wait for one, a process's RSS and CPU, the
machine's description, JSON output and a progress bar on stderr.

A script's own folder is on ``sys.path`` and the project is installed (editable) in the
venv, so ``import harness`` and ``import pipeline`` work from any working directory.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import shlex
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Timings", "best_rate", "best_time", "cpu_s", "emit", "free_port", "machine", "rss_mb", "run_record", "take_turns",
           "tests_module", "time_calls", "wait_port"]

ROOT = Path(__file__).resolve().parents[1]
Clock = Callable[[], float]


# -- timing -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Timings:
    """Seconds of each timed call: wall (``perf_counter``) and this process's CPU, all its
    threads (``process_time``); shapes (calls,)."""

    wall_s: np.ndarray
    cpu_s: np.ndarray


def time_calls(fn: Callable[[], object], calls: int, warmup: int = 0) -> Timings:
    """Call ``fn`` ``warmup`` times untimed, then ``calls`` times, each timed."""
    for _ in range(warmup):
        fn()
    wall, cpu = np.empty(calls), np.empty(calls)
    for i in range(calls):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        cpu[i], wall[i] = time.process_time() - c0, time.perf_counter() - t0
    return Timings(wall, cpu)


def best_time(fn: Callable[[], object], repeat: int = 5, warmup: int = 0, clock: Clock = time.perf_counter) -> float:
    """Seconds (of ``clock``) of the fastest of ``repeat`` calls of ``fn``, after ``warmup``
    calls that are not timed."""
    for _ in range(warmup):
        fn()
    best = float("inf")
    for _ in range(max(1, repeat)):
        t0 = clock()
        fn()
        best = min(best, clock() - t0)
    return best


def best_rate(fn: Callable[[], object], items: int, repeat: int = 5, warmup: int = 0,
              clock: Clock = time.perf_counter) -> float:
    """Items per second of the fastest of ``repeat`` calls of ``fn`` (each handles ``items``)."""
    return items / best_time(fn, repeat, warmup, clock)


def take_turns(fns: Mapping[str, Callable[[], object]], seconds: float, label: str = "bench",
               clock: Clock = time.process_time, warmup: int = 0, progress: bool = True) -> dict[str, list[float]]:
    """Call every function in turn, round after round, for ``seconds`` of wall time (one
    round at least), so a busy machine slows them alike: the ``clock`` seconds of each call,
    by name, one per round. ``warmup`` untimed rounds first; a progress bar on stderr."""
    from replay.progress import Progress  # here: bench_decoders.py imports pipeline from another tree

    for _ in range(warmup):
        for fn in fns.values():
            fn()
    times: dict[str, list[float]] = {name: [] for name in fns}
    deadline = time.monotonic() + seconds
    with Progress(int(seconds), label, unit="s", enabled=progress) as bar:
        done = 0
        while True:
            for name, fn in fns.items():
                t0 = clock()
                fn()
                times[name].append(clock() - t0)
            now = int(seconds - max(0.0, deadline - time.monotonic()))
            bar.update(now - done)
            done = now
            if time.monotonic() >= deadline:
                return times


# -- processes and ports ------------------------------------------------------------------------
def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port on ``host`` that was free a moment ago."""
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def wait_port(port: int, host: str = "127.0.0.1", timeout_s: float = 30.0, alive: Callable[[], bool] | None = None,
              what: str = "the process") -> None:
    """Until something accepts TCP connections on ``host:port``; RuntimeError after
    ``timeout_s`` s, or as soon as ``alive()`` (the process meant to listen) is false."""
    deadline = time.monotonic() + timeout_s
    for _ in range(int(timeout_s / 0.1) + 2):
        if alive is not None and not alive():
            raise RuntimeError(f"{what} ended before listening on {host}:{port}")
        with socket.socket() as s:
            s.settimeout(0.5)
            if s.connect_ex((host, port)) == 0:
                return
        if time.monotonic() >= deadline:
            break
        time.sleep(0.1)
    raise RuntimeError(f"nothing listens on {host}:{port} after {timeout_s} s")


def rss_mb(pid: int | str = "self") -> float | None:
    """Resident memory (VmRSS) of process ``pid`` (default this one), MB; None once it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def cpu_s(pid: int | str = "self") -> float | None:
    """CPU time (user + system) process ``pid`` has used, s; None once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # fields 14, 15 of stat(5)
    except (OSError, ValueError, IndexError):
        return None


# -- output ---------------------------------------------------------------------------------
def machine() -> dict[str, Any]:
    """The host's cores and the Python and numpy versions, for a benchmark's JSON."""
    return {"cpus": os.cpu_count(), "python": platform.python_version(), "numpy": np.__version__}


#: the folder where ``emit`` also writes its script's result file, with the run's date, host and
#: command (``benchmarks/suite.py`` sets it; docs/benchmarks.md's current figures come from there)
RESULTS_ENV = "QRADAR_BENCH_RESULTS"


def run_record(figures: Mapping[str, Any]) -> dict[str, Any]:
    """A benchmark's figures with what says where they come from: the script, its command line,
    the date (UTC, ISO 8601), the host (name, cores, 1-min load average at the end, Python, numpy)
    and the commit of the checkout (``git describe``; None outside a git checkout)."""
    try:
        commit = subprocess.run(["git", "-C", str(ROOT), "describe", "--always", "--dirty"], capture_output=True,
                                text=True, timeout=10, check=True).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        commit = None
    script = Path(sys.argv[0]).name
    return {
        "script": script,
        "command": shlex.join(["benchmarks/" + script, *sys.argv[1:]]),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "host": {"name": platform.node(), "load_1min": round(os.getloadavg()[0], 2), **machine()},
        "commit": commit,
        "figures": dict(figures),
    }


def emit(figures: Mapping[str, Any], indent: int | None = 2, path: str | Path | None = None) -> None:
    """Print the figures as one JSON object (and write them to ``path`` if given). With
    ``$QRADAR_BENCH_RESULTS`` set (the suite sets it), also write ``<that folder>/<script>.json``:
    the figures inside ``run_record``'s description of the run."""
    text = json.dumps(figures, indent=indent)
    print(text, flush=True)
    if path is not None:
        Path(path).write_text(text + "\n")
    folder = os.environ.get(RESULTS_ENV)
    if folder:
        out = Path(folder) / (Path(sys.argv[0]).stem + ".json")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(run_record(figures), indent=1) + "\n")


def tests_module(name: str):
    """A helper module of tests/ (e.g. ``ser2net_helpers``): tests/ is put on ``sys.path``."""
    import importlib

    tests = str(ROOT / "tests")
    if tests not in sys.path:
        sys.path.append(tests)
    return importlib.import_module(name)
