#!/usr/bin/env python3
"""Reading a long recording: ``qradar info`` and ``open_recording`` windows.

On a one-hour recording of one simulated sensor (``bench_record.py --long``: made in a
temporary folder and removed after, unless ``--file`` gives one):

- ``info``: :func:`replay.mcapinfo.describe` in this process (the summary and metadata
  only), and the ``qradar info FILE`` command's wall time beside ``qradar --version``'s
  (the command's imports), each the median of ``--repeat`` runs;
- windows: for each ``--windows`` length (s), in a fresh process each: ``open_recording(FILE,
  start=T, end=T + W)`` then ``raw()``, ``quantized()``, ``targets()`` and ``health()``
  (T: the recording's middle), its wall time, the process's peak RSS above its RSS before
  opening, and the peak of Python's allocations (tracemalloc, a second pass);
- ``targets of the whole hour``: ``open_recording(FILE, topics="targets").targets()``, the
  same in a fresh process (every chunk holds targets: each is read, only the targets kept).

    .venv/bin/python benchmarks/bench_reading.py [--file FILE | --minutes 60] [--windows 10 60]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

from harness import emit, rss_mb

ROOT = Path(__file__).resolve().parents[1]


def peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM), MB: its own, not its parent's (getrusage's
    ru_maxrss starts at the parent's peak in a process made by fork and exec)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmHWM in /proc/self/status")


def reset_peak_rss() -> None:
    """Start VmHWM again from the resident memory now (Linux >= 4.0)."""
    Path("/proc/self/clear_refs").write_text("5")


def child(path: str, start: float | None, end: float | None, topics: str | None) -> dict:
    """One reading in this (fresh) process: time, peak RSS above the start, tracemalloc peak."""
    import qradar.api as api

    def read():
        rec = api.open_recording(path, topics=topics, start=start, end=end)
        if topics == "targets":
            return len(rec.targets())
        raw, q, tg, h = rec.raw(), rec.quantized(), rec.targets(), rec.health()
        assert len(raw) == len(q) == len(tg) and raw.t_s.min() >= start and raw.t_s.max() < end
        return len(raw) + len(q) + len(tg) + len(h)

    reset_peak_rss()
    rss0 = rss_mb()
    t0 = time.perf_counter()
    n = read()
    wall = time.perf_counter() - t0
    peak_rss = peak_rss_mb() - rss0
    t1 = time.perf_counter()
    read()
    again = time.perf_counter() - t1
    tracemalloc.start()
    read()
    traced = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return {"messages": n, "seconds": round(wall, 3), "seconds_again": round(again, 3),
            "peak_rss_above_start_mb": round(peak_rss, 1), "tracemalloc_peak_mb": round(traced / 1e6, 1)}


def in_child(path: Path, start, end, topics=None) -> dict:
    cmd = [sys.executable, __file__, "--child", str(path), "--start", str(start), "--end", str(end)]
    if topics:
        cmd += ["--topics", topics]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=True)
    return json.loads(out.stdout)


def wall(cmd: list[str], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run(cmd, capture_output=True, timeout=120, check=True)
        times.append(time.perf_counter() - t0)
    return round(statistics.median(times), 3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--file", type=Path, default=None, help="a long recording (default: make one, then remove it)")
    ap.add_argument("--minutes", type=float, default=60.0, help="the recording made without --file")
    ap.add_argument("--windows", type=float, nargs="+", default=[10.0, 60.0], help="window lengths, s")
    ap.add_argument("--repeat", type=int, default=5, help="runs of each timing")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--start", type=float, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--end", type=float, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--topics", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.start, args.end, args.topics)))
        return
    from bench_record import write_long_recording
    from replay.mcapinfo import describe

    with tempfile.TemporaryDirectory(prefix="qradar-bench-reading-") as tmp:
        out: dict = {}
        path = args.file
        if path is None:
            path = Path(tmp) / "hour.mcap"
            out["made"] = write_long_recording(path, args.minutes * 60, progress=True)
        info = describe(path)
        out["recording"] = {"path": str(path), "bytes": info["bytes"], "duration_s": info["duration_s"],
                            "messages": info["messages"], "chunks": info["chunks"]}
        times = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            describe(path)
            times.append(time.perf_counter() - t0)
        qradar = [str(Path(sys.executable).with_name("qradar"))]
        out["info"] = {"describe_in_process_s": round(statistics.median(times), 4),
                       "qradar_info_command_s": wall(qradar + ["info", str(path)], args.repeat),
                       "qradar_version_command_s": wall(qradar + ["--version"], args.repeat)}
        middle = info["duration_s"] / 2
        out["windows"] = {f"{w:g} s": in_child(path, middle, middle + w) for w in args.windows}
        if len(args.windows) >= 2:
            a, b = sorted(args.windows)[:2]
            ra, rb = out["windows"][f"{a:g} s"], out["windows"][f"{b:g} s"]
            slope = (rb["tracemalloc_peak_mb"] - ra["tracemalloc_peak_mb"]) / (b - a)
            out["memory_per_window_second_mb"] = round(slope, 3)
            out["memory_at_zero_window_mb"] = round(ra["tracemalloc_peak_mb"] - slope * a, 1)
        out["targets_of_the_whole_recording"] = in_child(path, 0, info["duration_s"] + 1, "targets")
    # two levels: each window's figures as "window_<seconds>s" ("window_10s", "window_0_5s")
    for label, figures in out.pop("windows").items():
        out["window_" + label.replace(" ", "").replace(".", "_")] = figures
    emit(out)


if __name__ == "__main__":
    main()
