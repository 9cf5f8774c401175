#!/usr/bin/env python3
"""The flooding fake sensor of benchmarks/soak.py: a zenoh client that publishes, at up to
``--rate`` messages per second in all, a mix of

- ``valid``: raw frames of the scene on ``<prefix>/<sensor>/raw`` (a small pool of
  simulated frames, re-encoded with a new sequence number each; the scene's config id);
- ``nan``: the same with one NaN sample (refused as ``invalid_frames``);
- ``badcfg``: the right length with a config id no configuration has (``invalid_frames``);
- ``short``: 1-199 random bytes on the sensor's key (a length no configuration has);
- ``junk``: one byte on ``<prefix>/junk<i>/raw``, ``i`` drawn from ``--junk-ids`` ids.

valid, nan and badcfg frames take the sensor's next sequence number (0, 1, ...), so a
receiver that loses one sees a gap. Stopped by SIGTERM (or ``--duration``), it prints one
JSON line: messages sent by kind, the last sequence number, put failures, the rate
achieved. Its puts block when the network is full (``CongestionControl.BLOCK``): the
flood loses nothing on its own side, so every message it sent is the run's to count.

    .venv/bin/python benchmarks/soak_flood.py --connect tcp/127.0.0.1:7447 [--rate 2000] \\
        [--mix valid=0.3,nan=0.15,badcfg=0.1,short=0.15,junk=0.3]
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time

import numpy as np

import zenoh

from pipeline.bus.session import BusConfig
from pipeline.wire import RawFrameMsg, encode_raw
from radar_driver.scene import resolve_scene
from radar_driver.source import SimSourceConfig, SimulatedSource

KINDS = ("valid", "nan", "badcfg", "short", "junk")
#: kinds that take a sequence number of the flooding sensor
SEQ_KINDS = ("valid", "nan", "badcfg")
DEFAULT_MIX = "valid=0.3,nan=0.15,badcfg=0.1,short=0.15,junk=0.3"
#: the flood waits for the network rather than losing its own messages on the way, so that
#: every message it sent reaches the run and the run's counters can be checked against it
BLOCK = zenoh.CongestionControl.BLOCK
POOL = 8  # distinct frames (a recorder's zstd chunks compress the repeats)
BURST_MAX = 200  # messages sent before the clock is read again


def parse_mix(text: str) -> dict[str, float]:
    """``kind=share,...`` -> shares summing to 1 (kinds in KINDS, shares >= 0)."""
    mix: dict[str, float] = {}
    for part in text.split(","):
        kind, _, share = part.partition("=")
        kind = kind.strip()
        if kind not in KINDS:
            raise ValueError(f"--mix: kind {kind!r} is not one of {KINDS}")
        try:
            mix[kind] = float(share)
        except ValueError:
            raise ValueError(f"--mix: share {share!r} of {kind} is not a number") from None
        if not mix[kind] >= 0:
            raise ValueError(f"--mix: share {mix[kind]} of {kind} must be >= 0")
    total = sum(mix.values())
    if not total > 0:
        raise ValueError(f"--mix {text!r}: the shares sum to {total}, must be > 0")
    return {k: v / total for k, v in mix.items()}


class Flood:
    """The messages and the paced loop; ``counts`` by kind, ``seq`` the next sequence number."""

    def __init__(self, session: zenoh.Session, bus: BusConfig, sensor: str, scene: str, mix: dict[str, float],
                 junk_ids: int, seed: int):
        sc = resolve_scene(scene)
        src = SimulatedSource(SimSourceConfig(sc, rate_hz=0.0, frames=POOL, seed=seed))
        self.pool = [f.data for f in src.frames()]
        self.config_id = sc.radar.config_id()
        self.nan_frame = self.pool[0].copy()
        self.nan_frame[len(self.nan_frame) // 2, 1] = np.nan
        self.session, self.bus, self.sensor = session, bus, sensor
        self.kinds = list(mix)
        self.p = np.array([mix[k] for k in self.kinds])
        self.junk_ids = junk_ids
        self.rng = np.random.default_rng(seed)
        self.pub = session.declare_publisher(bus.key(sensor, "raw"), congestion_control=BLOCK)
        self.counts = {k: 0 for k in KINDS}
        self.put_errors = 0
        self.seq = 0

    def send(self, kind: str) -> None:
        if kind == "junk":
            self.session.put(self.bus.key(f"junk{int(self.rng.integers(self.junk_ids))}", "raw"), b"\x00",
                             congestion_control=BLOCK)
        elif kind == "short":
            self.pub.put(self.rng.bytes(int(self.rng.integers(1, 200))))
        else:
            data = self.nan_frame if kind == "nan" else self.pool[self.seq % POOL]
            cid = self.config_id ^ 0x5A5A5A5A if kind == "badcfg" else self.config_id
            self.pub.put(encode_raw(RawFrameMsg(self.sensor, self.seq, time.time_ns(), cid, data)))
            self.seq += 1

    def run(self, rate_hz: float, stop: threading.Event, duration_s: float | None) -> float:
        """Send until ``stop`` or ``duration_s``; returns the seconds it ran."""
        t0 = time.monotonic()
        sent = 0
        while not stop.is_set():
            now = time.monotonic()
            if duration_s is not None and now - t0 >= duration_s:
                break
            n = min(int(rate_hz * (now - t0)) - sent, BURST_MAX)
            if n <= 0:
                stop.wait(0.002)
                continue
            for kind in self.rng.choice(self.kinds, size=n, p=self.p):
                try:
                    self.send(str(kind))
                    self.counts[str(kind)] += 1
                except zenoh.ZError:
                    self.put_errors += 1
                    if kind in SEQ_KINDS:
                        self.seq += 1  # the number is used: a receiver sees a gap
            sent += n
        return time.monotonic() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--connect", action="append", required=True, metavar="ENDPOINT")
    ap.add_argument("--prefix", default="radar")
    ap.add_argument("--sensor", default="evil", help="the flooding sensor's id (default evil)")
    ap.add_argument("--rate", type=float, default=2000.0, help="messages per second in all (default 2000)")
    ap.add_argument("--mix", default=DEFAULT_MIX, help=f"shares of each kind (default {DEFAULT_MIX})")
    ap.add_argument("--junk-ids", type=int, default=1000, help="distinct junk<i> sensor ids (default 1000)")
    ap.add_argument("--scene", default="chamber")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration", type=float, default=None, help="stop after S seconds (default: SIGTERM)")
    args = ap.parse_args()
    if not args.rate > 0 or args.junk_ids < 1:
        ap.error(f"--rate {args.rate} must be > 0 and --junk-ids {args.junk_ids} >= 1")
    try:
        mix = parse_mix(args.mix)
    except ValueError as exc:
        ap.error(str(exc))
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    bus = BusConfig(mode="client", connect=tuple(args.connect), prefix=args.prefix)
    with bus.open() as session:
        flood = Flood(session, bus, args.sensor, args.scene, mix, args.junk_ids, args.seed)
        print(json.dumps({"ready": True}), flush=True)
        seconds = flood.run(args.rate, stop, args.duration)
        sent = sum(flood.counts.values())
        out = {"node": "flood", "sensor": args.sensor, "seconds": round(seconds, 2), "sent": sent,
               "sent_by_kind": flood.counts, "seq_next": flood.seq, "put_errors": flood.put_errors,
               "rate_achieved_hz": round(sent / seconds, 1) if seconds > 0 else None,
               "rate_hz": args.rate, "mix": mix, "junk_ids": args.junk_ids}
    print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
