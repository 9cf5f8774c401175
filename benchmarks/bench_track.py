#!/usr/bin/env python3
"""Cost of the tracker (pipeline/dsp/track.py) against the localizer's, per frame, in the same
process: the `walker` scene (a moving reflector beside a static one), 1-bit dithered frames
(M = 512), decoded by the default decoder (cml, K = 2, the live default range gate) in
batches of ``--batch`` frames as the localizer node decodes them, and tracked frame by
frame as the node tracks them (track_batch: association, filter, the tracks JSON). The
two take turns for ``--seconds``, so a busy host slows them alike; the figure is the
ratio. The integration of static tracks (one cml decode of ``--integrate`` seconds of
frames, at most every Integration.every_s = 1 s) is measured apart: its cost per refinement and per frame.

    .venv/bin/python benchmarks/bench_track.py [--seconds 30] [--batch 4] [--integrate 1]

Prints one JSON object: ms per frame (medians over the rounds) of the localizer, of the
tracker without integration, the ratio, and the integration's cost.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from harness import emit, take_turns
from pipeline.dsp.decode import Decoder, DecoderConfig, decode_batch
from pipeline.dsp.gate import RangeGate
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from pipeline.dsp.track import TrackerConfig
from pipeline.nodes.tracker import Integration, Tracker, track_batch
from pipeline.wire import FrameHeaders
from radar_driver.scene import ramp_time_s, resolve_scene

RATE_HZ = 20.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=30.0, help="how long the two take turns")
    ap.add_argument("--batch", type=int, default=4, help="frames a localizer batch (live: 1 to a few)")
    ap.add_argument("--frames", type=int, default=200, help="frames of the scene (10 s at 20 Hz)")
    ap.add_argument("--integrate", type=float, default=1.0, help="seconds of frames a refinement decodes")
    args = ap.parse_args()

    scene = resolve_scene("walker")
    radar, n = scene.radar, args.frames
    rpf = radar.ramps_per_frame
    t = ramp_time_s(np.arange(n * rpf), RATE_HZ * rpf)
    frames = scene.ramps(t, np.random.default_rng(1)).reshape(n, rpf * radar.samples_per_ramp, 2)
    q = quantize_frames(frames, QuantizerConfig(), np.arange(n, dtype=np.uint64), dither_seed=3)
    gate = RangeGate.default(radar)
    decoder = DecoderConfig(gate=gate)
    headers = FrameHeaders(["walk0"] * n, np.arange(n, dtype=np.uint64),
                           (np.arange(n) * (1e9 / RATE_HZ)).astype(np.int64), np.zeros(n, dtype=np.uint32))
    det = decode_batch(q, radar, 2, decoder)  # the tracker's input (the same each round)
    batches = [np.arange(s, min(s + args.batch, n)) for s in range(0, n, args.batch)]

    held = Decoder(decoder)  # as the localizer node holds it

    def localize() -> None:
        for idx in batches:
            held.decode_batch(q.take(idx), radar, 2)

    times = take_turns({"loc": localize, "trk": lambda: track_batch(Tracker(TrackerConfig(integrate_s=0)), headers, det,
                                                                    radar=radar)},
                       args.seconds, "bench_track", clock=time.perf_counter)
    loc_ms, trk_ms = (np.asarray(times[k]) / n * 1e3 for k in ("loc", "trk"))

    tracker = Tracker(TrackerConfig(integrate_s=args.integrate), Integration(2, gate, None))
    t0 = time.perf_counter()
    track_batch(tracker, headers, det, q, radar)
    with_integration_ms = (time.perf_counter() - t0) / n * 1e3
    loc, trk = float(np.median(loc_ms)), float(np.median(trk_ms))
    emit({
        "scene": "walker", "frames": n, "batch": args.batch, "rounds": len(loc_ms),
        "localizer_ms_per_frame": round(loc, 4), "tracker_ms_per_frame": round(trk, 4),
        "tracker_over_localizer": round(trk / loc, 4),
        "integration": {"seconds": args.integrate, "refinements": tracker.refinements,
                        "ms_per_refinement": round(tracker.refine_s / max(tracker.refinements, 1) * 1e3, 2),
                        "tracker_with_integration_ms_per_frame": round(with_integration_ms, 3),
                        "over_localizer": round(with_integration_ms / loc, 3)},
        "host": {"cpus": os.cpu_count(), "python": platform.python_version(), "load1": round(os.getloadavg()[0], 2)},
    }, indent=None)


if __name__ == "__main__":
    main()
