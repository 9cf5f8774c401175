#!/usr/bin/env python3
"""Cost of the continuous-range decoder (cml) against PBP and qiht on the same frames, in
the same process: 1-bit dithered frames (M = 512) of off-grid scenes (ranges uniform over
3-150 m, |theta| <= 60 deg), K = 2, decoded in batches, each decoder told K, and pbp and
cml also deciding the count (K auto, at most 4). The decoders take turns for
``--seconds`` (default 60), so a busy machine slows them alike; the figure to compare
across machines is the ratio to PBP. Each step is meant to run in a fresh process:

    .venv/bin/python benchmarks/bench_cml.py [--seconds 60] [--batch 256] [--K 2]

Prints one JSON object: ms per frame (median over the rounds) for each decoder, the
ratio to PBP, how many 20-frames/s sensors one core decodes with cml, and the cost of cml's
default model (a phase step between ramps) over its static one (``cml_static``,
``cml_static_auto``: ``DecoderConfig(motion=False)``, taking turns with the others) and what
the targets' uncertainty and p-values cost (``cml_positions``, ``cml_positions_auto``:
``DecoderConfig(uncertainty=False)``, positions only, what cml computed before them), and
the motion model's cost with positions only (``cml_static_positions``, ``..._auto``).
"""

from __future__ import annotations

import argparse
import time
from functools import partial

import numpy as np

from harness import emit, machine, take_turns
from pipeline.dsp.decode import Decoder, DecoderConfig
from experiments.montecarlo import SceneSpec, draw_scenes
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from radar_driver.model import RadarConfig, simulate_frames

ALGOS = ("pbp", "qiht", "cml")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=60.0, help="how long the decoders take turns")
    ap.add_argument("--batch", type=int, default=256, help="frames per call")
    ap.add_argument("--K", type=int, default=2)
    ap.add_argument("--max-targets", type=int, default=4, help="the most targets of the K auto runs")
    args = ap.parse_args()

    cfg = RadarConfig()
    rng = np.random.default_rng(0)
    scene = SceneSpec(ranges="continuous", max_angle_deg=60.0, min_amplitude=0.1)
    _, _, r, a, x = draw_scenes(args.batch, args.K, rng, cfg, scene=scene)
    q = quantize_frames(simulate_frames(r, a, x, cfg), QuantizerConfig(alpha=1.0), np.arange(args.batch))
    z, xi = q.values(), q.dither()
    # each decoder told K, and pbp and cml deciding the count (K auto, at most --max-targets)
    runs = {algo: (DecoderConfig(algo=algo), args.K) for algo in ALGOS}
    runs |= {f"{algo}_auto": (DecoderConfig(algo=algo, auto_k=True), args.max_targets) for algo in ("pbp", "cml")}
    # cml's static model (no phase step between ramps), K given and K auto: what the motion model costs
    runs |= {"cml_static": (DecoderConfig(algo="cml", motion=False), args.K),
             "cml_static_auto": (DecoderConfig(algo="cml", auto_k=True, motion=False), args.max_targets)}
    # positions only (no uncertainty, no p-values): what they cost
    runs |= {"cml_positions": (DecoderConfig(algo="cml", uncertainty=False), args.K),
             "cml_positions_auto": (DecoderConfig(algo="cml", auto_k=True, uncertainty=False), args.max_targets),
             # ... and the motion model's cost with positions only
             "cml_static_positions": (DecoderConfig(algo="cml", motion=False, uncertainty=False), args.K),
             "cml_static_positions_auto": (DecoderConfig(algo="cml", auto_k=True, motion=False, uncertainty=False),
                                           args.max_targets)}
    # each decoder held across calls, as the localizer node holds it (its tables built once)
    calls = {label: partial(Decoder(decoder).decode, z, xi, q.delta, 1, cfg, k) for label, (decoder, k) in runs.items()}
    times = take_turns(calls, args.seconds, "bench_cml", clock=time.process_time, warmup=1)
    ms = {algo: float(np.median(v)) / args.batch * 1e3 for algo, v in times.items()}
    emit({
        "machine": machine(),
        "batch": args.batch, "K": args.K, "max_targets_auto": args.max_targets, "rounds": len(times["pbp"]), "seconds": args.seconds,
        "ms_per_frame": {k: round(v, 4) for k, v in ms.items()},
        "ratio_to_pbp": {k: round(v / ms["pbp"], 1) for k, v in ms.items()},
        "cml_sensors_per_core_at_20_fps": int(1000.0 / ms["cml"] / 20.0),
        "cml_auto_sensors_per_core_at_20_fps": int(1000.0 / ms["cml_auto"] / 20.0),
        "motion_over_static": {"cml": round(ms["cml"] / ms["cml_static"], 3),
                               "cml_auto": round(ms["cml_auto"] / ms["cml_static_auto"], 3),
                               "cml_positions": round(ms["cml_positions"] / ms["cml_static_positions"], 3),
                               "cml_positions_auto": round(ms["cml_positions_auto"] / ms["cml_static_positions_auto"],
                                                           3)},
        "uncertainty_share": {"cml": round(1 - ms["cml_positions"] / ms["cml"], 3),
                              "cml_auto": round(1 - ms["cml_positions_auto"] / ms["cml_auto"], 3)},
    }, indent=1)


if __name__ == "__main__":
    main()
