#!/usr/bin/env python3
"""Memory of a localizer before, while and after many short-lived sensors (issue 28).

A LocalizeNode on a real zenoh session (an isolated embedded peer, in this process, glibc's
arenas capped at 2 as every ``qradar`` command does) gets one valid quantized frame from
each of ``--ids`` distinct sensor ids (``--rounds`` times, new ids each round, put at
``--rate`` frames/s so its queue never overflows), with ``--expiry`` s of sensor expiry.
Per round: RSS (VmRSS) before, when the last targets are out, and once every sensor is
forgotten and its publishers undeclared (plus one expiry sweep); with ``--trace`` the
Python heap (tracemalloc, which slows the node ~5x and whose own tables distort RSS) too.

    .venv/bin/python benchmarks/bench_expiry.py [--ids 10000] [--rounds 3] [--trace]

One JSON line before the rounds and one a round, then the summary (``harness.emit``, one line).
"""

from __future__ import annotations

import argparse
import gc
import json
import time
import tracemalloc

from qradar.cli import limit_malloc_arenas

import numpy as np

from harness import emit, rss_mb
from pipeline.nodes.budget import IntakeBudget
from pipeline.bus.session import BusConfig
from pipeline.nodes.counters import NO_SENSOR
from pipeline.nodes.stream import LocalizeNode, LocalizerConfig
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames, sensor_dither_seeds
from pipeline.wire import FrameHeaders, encode_quantized_batch
from radar_driver.scene import resolve_scene


def frames(ids: list[str]) -> list[tuple[str, bytes]]:
    """(key, payload): one valid 1-bit frame of each sensor (the project's quantizer)."""
    scene = resolve_scene("single")
    clean = np.tile(scene.clean_ramp(0.0), (scene.radar.ramps_per_frame, 1))
    out = []
    for lo in range(0, len(ids), 500):
        part = ids[lo:lo + 500]
        b = len(part)
        h = FrameHeaders(part, np.zeros(b, np.uint64), np.full(b, time.time_ns(), np.int64),
                         np.full(b, scene.radar.config_id(), np.uint32))
        q = quantize_frames(np.broadcast_to(clean, (b,) + clean.shape).astype(complex), QuantizerConfig(alpha=1.0),
                            h.seq, dither_seed=sensor_dither_seeds(0, h.sensor_id))
        out += [(f"radar/{s}/quantized", p) for s, p in zip(part, encode_quantized_batch(h, q))]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ids", type=int, default=10000, help="distinct sensor ids a round")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--rate", type=float, default=500.0, help="frames put a second")
    ap.add_argument("--expiry", type=float, default=1.0, help="sensor expiry, s")
    ap.add_argument("--trace", action="store_true", help="also the Python heap (tracemalloc)")
    args = ap.parse_args()
    limit_malloc_arenas()  # before any thread allocates: as `qradar localize` runs
    bus = BusConfig()
    session = bus.open()
    # new ids admitted at the rate they are put (the default --admit-rate, 100/s, would make a round of 10 000 last 100 s)
    intake = IntakeBudget(new_sensors_per_s=max(args.rate, 1.0))
    node = LocalizeNode(bus, LocalizerConfig(k=1), session=session, sensor_expiry_s=args.expiry, intake=intake).start()

    def forgotten() -> bool:
        with node._lock:
            return not (set(node.stats) - {NO_SENSOR}) and not node._publishers and not node._retiring

    def one_frame_each(msgs: list[tuple[str, bytes]]) -> float:
        done = lambda: (t := node.totals())["frames_out"] + t["drops"] + t["refused"]  # noqa: E731 (counted, not lost)
        total = done() + len(msgs)
        t0 = time.monotonic()
        for i, (key, payload) in enumerate(msgs):
            session.put(key, payload)
            if (d := t0 + (i + 1) / args.rate - time.monotonic()) > 0:
                time.sleep(d)
        msgs.clear()
        while done() < total and time.monotonic() - t0 < 600:
            time.sleep(0.05)
        peak = round(rss_mb(), 1)
        while not forgotten() and time.monotonic() - t0 < 900:
            time.sleep(0.1)
        time.sleep(node.health_period_s + 0.2)  # one more sweep: the publishers' undeclaring and the trim
        gc.collect()
        return peak

    try:
        one_frame_each(frames([f"w{i}" for i in range(200)]))  # warm-up: the decoder's and zenoh's caches
        if args.trace:
            tracemalloc.start()
        base = {"rss_mb": round(rss_mb(), 1)}
        if args.trace:
            base["python_mb"] = round(tracemalloc.get_traced_memory()[0] / 2**20, 2)
        print(json.dumps({"ids": args.ids, "expiry_s": args.expiry, "before": base}), flush=True)
        rounds = []
        for r in range(args.rounds):
            msgs = frames([f"r{r}x{i}" for i in range(args.ids)])
            t0 = time.monotonic()
            peak = one_frame_each(msgs)
            out = {"round": r, "rss_mb_targets_out": peak, "rss_mb_forgotten": round(rss_mb(), 1),
                   "seconds": round(time.monotonic() - t0, 1)}
            if args.trace:
                out["python_mb_forgotten"] = round(tracemalloc.get_traced_memory()[0] / 2**20 - base["python_mb"], 2)
            with node._lock:
                out["left"] = {"stats": len(node.stats) - (NO_SENSOR in node.stats), "publishers": len(node._publishers),
                               "key_cache": len(node._key_info)}
            t = node.totals()
            out["totals"] = {k: t[k] for k in ("frames_in", "frames_out", "drops", "refused", "sensors_expired")}
            print(json.dumps(out), flush=True)
            rounds.append(out)
    finally:
        node.stop()
        session.close()
    emit(summary(args, base, rounds), indent=None)


def summary(args, base: dict, rounds: list[dict]) -> dict:
    """The rounds' figures, two levels: RSS before, its peak and where it ends, per-round lists,
    and what the node still held and had counted after the last round."""
    last = rounds[-1] if rounds else {}
    fig = {"ids": args.ids, "expiry_s": args.expiry, "rounds": len(rounds),
           "rss_mb": {"before": base["rss_mb"],
                      "targets_out_max": max((r["rss_mb_targets_out"] for r in rounds), default=None),
                      "forgotten_last": last.get("rss_mb_forgotten"),
                      "forgotten_last_minus_before": None if not rounds else
                      round(last["rss_mb_forgotten"] - base["rss_mb"], 1)},
           "per_round": {"rss_mb_targets_out": [r["rss_mb_targets_out"] for r in rounds],
                         "rss_mb_forgotten": [r["rss_mb_forgotten"] for r in rounds],
                         "seconds": [r["seconds"] for r in rounds]},
           "left_after_last_round": last.get("left"), "totals_after_last_round": last.get("totals")}
    if "python_mb" in base:
        fig["python_mb"] = {"before": base["python_mb"], "forgotten_last_above_before": last.get("python_mb_forgotten")}
    return fig


if __name__ == "__main__":
    main()
