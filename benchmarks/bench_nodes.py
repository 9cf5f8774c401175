#!/usr/bin/env python3
"""Per-frame cost of the processing nodes, in one process, against bare zenoh.

For each node (quantize: raw -> 1-bit frames; localize with each decoder: 1-bit frames
-> targets) a real zenoh session (an isolated embedded peer, nothing listening) carries
``--frames`` frames of ``--sensors`` sensors put as fast as possible; the figure is the
node's CPU time per frame (process CPU while the node works, the putting included) and
the ratio to the CPU per message of a bare subscriber that only copies the payload, run
in the same process just before (so a loaded machine shifts both). Frames come in
bursts of one frame per sensor, so the node's batches span many sensors, as in a live
chain of many sensors.

    .venv/bin/python benchmarks/bench_nodes.py [--sensors 500] [--frames 20000] [--algos pbp qiht cml]

After the table, the same figures as one JSON object (``harness.emit``), each keyed by node
(``quantize``, ``localize_pbp`` ...).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time

import numpy as np

from harness import emit
from pipeline.bus.session import BusConfig
from pipeline.nodes.intake import QueueConfig
from pipeline.nodes.stream import LocalizeNode, LocalizerConfig, QuantizeNode
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames, sensor_dither_seeds
from pipeline.wire import FrameHeaders, encode_quantized_batch, encode_raw_batch
from radar_driver.scene import resolve_scene


def payloads(sensors: int, frames: int, topic: str) -> list[tuple[str, bytes]]:
    """(key, payload) in bursts of one frame per sensor, chamber scene with noise."""
    scene = resolve_scene("chamber")
    rng = np.random.default_rng(0)
    clean = np.tile(scene.clean_ramp(0.0), (scene.radar.ramps_per_frame, 1))
    ids = [f"n{i}" for i in range(sensors)]
    out = []
    for k in range(-(-frames // sensors)):
        b = min(sensors, frames - k * sensors)
        data = (clean[None] + scene.noise_std * (rng.standard_normal((b,) + clean.shape)
                                                 + 1j * rng.standard_normal((b,) + clean.shape))).astype(np.complex64)
        h = FrameHeaders(ids[:b], np.full(b, k, np.uint64), np.full(b, time.time_ns(), np.int64),
                         np.full(b, scene.radar.config_id(), np.uint32))
        if topic == "raw":
            out += [(f"radar/{s}/raw", p) for s, p in zip(h.sensor_id, encode_raw_batch(h, data))]
        else:
            q = quantize_frames(data.astype(complex), QuantizerConfig(alpha=1.0), h.seq,
                                dither_seed=sensor_dither_seeds(0, h.sensor_id))
            out += [(f"radar/{s}/quantized", p) for s, p in zip(h.sensor_id, encode_quantized_batch(h, q))]
    return out


def cpu() -> float:
    return time.process_time()


def bare(session, msgs) -> float:
    """CPU s per message of a subscriber that copies each payload."""
    got = []
    done = threading.Event()
    n = len(msgs)

    def on(sample):
        got.append(sample.payload.to_bytes())
        if len(got) == n:
            done.set()
    sub = session.declare_subscriber("radar/*/*", on)
    c0 = cpu()
    for k, p in msgs:
        session.put(k, p)
    done.wait(60)
    c = cpu() - c0
    sub.undeclare()
    return c / n


def node_cost(session, node, msgs, out_topic: str) -> tuple[float, dict]:
    n = len(msgs)
    out = [0]
    done = threading.Event()

    def on(sample):
        out[0] += 1
        if out[0] == n:
            done.set()
    sub = session.declare_subscriber(f"radar/*/{out_topic}", on)
    node.start()
    time.sleep(0.3)
    c0, t0 = cpu(), time.perf_counter()
    for k, p in msgs:
        session.put(k, p)
    done.wait(300)
    c, t = cpu() - c0, time.perf_counter() - t0
    totals = node.totals()
    node.stop()
    sub.undeclare()
    return c / n, {"wall_s": round(t, 2), "out": out[0], **{k: totals[k] for k in ("drops", "processing_errors")}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sensors", type=int, default=500)
    ap.add_argument("--frames", type=int, default=20000)
    ap.add_argument("--algos", nargs="+", default=["pbp", "qiht", "cml"])
    args = ap.parse_args()
    bus = BusConfig()
    session = bus.open()
    rows = []
    big = dict(queue=QueueConfig(queue_size=1 << 17, sensor_queue_size=1 << 12, queue_bytes=1 << 31))
    try:
        for what in ["quantize"] + [f"localize-{a}" for a in args.algos]:
            topic = "raw" if what == "quantize" else "quantized"
            n = args.frames if what in ("quantize", "localize-pbp") else min(args.frames, 4000)
            msgs = payloads(args.sensors, n, topic)
            base = bare(session, msgs)
            if what == "quantize":
                node = QuantizeNode(bus, QuantizerConfig(alpha=1.0), session=session, **big)
                per, info = node_cost(session, node, msgs, "quantized")
            else:
                node = LocalizeNode(bus, LocalizerConfig(k=2, algo=what.split("-")[1]), session=session, **big)
                per, info = node_cost(session, node, msgs, "targets")
            row = {"node": what, "frames": n, "cpu_us_per_frame": round(per * 1e6, 1),
                   "bare_zenoh_us_per_msg": round(base * 1e6, 1), "ratio_to_bare": round(per / base, 2), **info}
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    finally:
        session.close()
    print("| node | frames | CPU per frame (µs) | bare zenoh per message (µs) | ratio |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['node']} | {r['frames']} | {r['cpu_us_per_frame']} | {r['bare_zenoh_us_per_msg']} | "
              f"{r['ratio_to_bare']} |")
    fig: dict = {"sensors": args.sensors}
    for name, key in (("frames", "frames"), ("cpu_us_per_frame", "cpu_us_per_frame"),
                      ("bare_zenoh_us_per_msg", "bare_zenoh_us_per_msg"), ("ratio_to_bare", "ratio_to_bare"),
                      ("wall_s", "wall_s"), ("frames_out", "out"), ("drops", "drops"),
                      ("processing_errors", "processing_errors")):
        fig[name] = {r["node"].replace("-", "_"): r[key] for r in rows}
    emit(fig)


if __name__ == "__main__":
    main()
