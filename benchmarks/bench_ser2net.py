#!/usr/bin/env python3
"""The GNFD round trip (one ramp: GNFD -> RESP, RADC, DONE) through ser2net, with and
without ``tcp(nodelay)``, against the simulated K-MD2's pty opened directly.

The simulated K-MD2 runs in its own process (``qradar sim --rate 0``: it answers at
once), ser2net with the YAML of docs/chamber.md (tests/ser2net_helpers.py) on 127.0.0.1,
and this process times a ``SensorSession``'s frames of one ramp after a warm-up (its
reader keeps one GNFD outstanding, so a frame's time is one round trip). Raw TCP at 115200
(a socket cannot switch the speed), RFC 2217 at 2 000 000 with ``?ign_set_control``.
A pty has no line rate: these are the latencies of the software path, not of a UART.

    .venv/bin/python benchmarks/bench_ser2net.py [--ramps 200] [--warmup 20]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from harness import ROOT, tests_module, time_calls
from radar_driver.session import SensorSession, SessionConfig

_S2N = tests_module("ser2net_helpers")  # the tests' ser2net wrapper
Ser2net, require_ser2net = _S2N.Ser2net, _S2N.require_ser2net


def time_ramps(url: str, baud: int, ramps: int, warmup: int) -> tuple[list[float], float]:
    """Seconds per frame of one ramp for ``ramps`` ramps after ``warmup`` untimed ones, and the
    CPU seconds this process spent on them (all threads: pyserial's RFC 2217 client
    reads in a thread of its own)."""
    with SensorSession(SessionConfig(url, baud=baud, ramps_per_frame=1, reconnect=False, timeout_s=2.0)) as s:
        frames = s.frames()
        t = time_calls(lambda: next(frames), ramps, warmup)
    return t.wall_s.tolist(), float(t.cpu_s.sum())


def summary(name: str, dt: list[float], cpu_s: float) -> dict:
    ms = sorted(1e3 * d for d in dt)
    q = statistics.quantiles(ms, n=10)
    return {"path": name, "ramps": len(ms), "median_ms": round(statistics.median(ms), 3),
            "p10_ms": round(q[0], 3), "p90_ms": round(q[-1], 3), "max_ms": round(ms[-1], 3),
            "ramps_per_s": round(len(ms) / sum(dt), 1), "cpu_ms_per_ramp": round(1e3 * cpu_s / len(ms), 3)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ramps", type=int, default=200)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--json", action="store_true", help="one JSON object per line instead of a table")
    args = ap.parse_args()
    require_ser2net()

    paths = [  # (name, kind or None for the pty itself, nodelay, chardelay, baud)
        ("pty, direct", None, None, None, 2_000_000),
        ("raw, tcp(nodelay)", "raw", True, None, 115_200),
        ("raw, tcp", "raw", False, None, 115_200),
        ("raw, tcp(nodelay), chardelay off", "raw", True, False, 115_200),
        ("rfc2217, tcp(nodelay)", "rfc2217", True, None, 2_000_000),
        ("rfc2217, tcp", "rfc2217", False, None, 2_000_000),
        ("rfc2217, tcp(nodelay), chardelay off", "rfc2217", True, False, 2_000_000),
    ]
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-ser2net-") as tmp:
        link = Path(tmp) / "kmd2"
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        sim = subprocess.Popen([sys.executable, "-m", "qradar", "sim", "--rate", "0", "--link", str(link)],
                               env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            deadline = time.monotonic() + 20
            while not link.exists():
                if sim.poll() is not None or time.monotonic() > deadline:
                    raise SystemExit(f"the simulated K-MD2 did not come up on {link}")
                time.sleep(0.05)
            for name, kind, nodelay, chardelay, baud in paths:
                if kind is None:
                    dt, cpu = time_ramps(str(link), baud, args.ramps, args.warmup)
                else:
                    with Ser2net(link, kind, tmp, nodelay=nodelay, chardelay=chardelay) as s2n:
                        dt, cpu = time_ramps(s2n.url, baud, args.ramps, args.warmup)
                row = summary(name, dt, cpu)
                rows.append(row)
                if args.json:
                    print(json.dumps(row), flush=True)
        finally:
            sim.terminate()
            try:
                sim.wait(5)
            except subprocess.TimeoutExpired:
                sim.kill()
    if not args.json:
        print(f"GNFD round trip, {args.ramps} ramps each after {args.warmup} warm-up ramps "
              f"(simulated K-MD2 at rate 0 in its own process, 127.0.0.1)")
        print(f"{'path (ser2net unless direct)':38s} {'median ms':>9s} {'p10 ms':>7s} {'p90 ms':>7s} "
              f"{'max ms':>7s} {'ramps/s':>8s} {'CPU ms/ramp':>11s}")
        for r in rows:
            print(f"{r['path']:38s} {r['median_ms']:9.2f} {r['p10_ms']:7.2f} {r['p90_ms']:7.2f} "
                  f"{r['max_ms']:7.2f} {r['ramps_per_s']:8.1f} {r['cpu_ms_per_ramp']:11.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
