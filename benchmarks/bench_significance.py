#!/usr/bin/env python3
"""What each cml target's p-value costs (:mod:`pipeline.dsp.significance`) against the decode
and the targets' uncertainty it follows, taking turns in one process (a busy machine slows
them alike): per frame, frame by frame (``--batch 1``, a live node's) or in batches.

Off-grid scenes of 2 targets (amplitude 0.5, 5-140 m, +-50 deg) in noise 0.1, 1 bit at the
default alpha, K = 2 in the live gate.

    .venv/bin/python benchmarks/bench_significance.py [--seconds 60] [--batch 1] [--frames 64]
"""

from __future__ import annotations

import argparse

import numpy as np

from harness import emit, machine, take_turns
from pipeline.dsp.decode import Decoder, DecoderConfig
from pipeline.dsp.gate import RangeGate
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from pipeline.dsp.significance import target_p_values
from pipeline.dsp.uncertainty import target_uncertainty
from radar_driver.model import RadarConfig, simulate_frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=60.0, help="how long the three take turns (default 60)")
    ap.add_argument("--batch", type=int, default=1, help="frames a call (default 1: a live node's)")
    ap.add_argument("--frames", type=int, default=64, help="frames of the scenes (default 64)")
    args = ap.parse_args()

    radar, k = RadarConfig(), 2
    rng = np.random.default_rng(1)
    n = max(args.frames, args.batch)
    shape = (n, radar.n_measurements, 2)
    g = simulate_frames(rng.uniform(5, 140, (n, k)), rng.uniform(-50, 50, (n, k)), np.full((n, k), 0.5), radar)
    q = quantize_frames(g + 0.1 * (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)), QuantizerConfig(),
                        np.arange(n))
    gate = RangeGate.default(radar)
    cml = Decoder(DecoderConfig(algo="cml", gate=gate)).cml(radar)
    batches = [np.arange(s, min(s + args.batch, n)) for s in range(0, n, args.batch)]
    parts = [(q.codes[i], q.dither()[i], np.broadcast_to(q.delta, (n,))[i]) for i in batches]
    results = [cml.decode(z, xi, d, 1, k, gate=gate) for z, xi, d in parts]

    def decode() -> None:
        for z, xi, d in parts:
            cml.decode(z, xi, d, 1, k, gate=gate)

    def uncertainty() -> None:
        for (z, xi, d), r in zip(parts, results):
            target_uncertainty(r.range_m, r.amplitudes, r.present, radar, r.sigma_eff, xi, d, 1,
                               phase_step_rad=r.phase_step_rad)

    def p_values() -> None:
        for (z, xi, d), r in zip(parts, results):
            target_p_values(r.range_m, r.amplitudes, r.phase_step_rad, r.present, r.sigma_eff, z, xi, d, 1, radar, gate)

    times = take_turns({"decode": decode, "uncertainty": uncertainty, "p_values": p_values}, args.seconds,
                       "bench_significance", warmup=1)
    ms = {name: float(np.median(t)) / n * 1e3 for name, t in times.items()}
    emit({"batch": args.batch, "frames": n, "rounds": len(times["decode"]),
          "ms_per_frame": {name: round(v, 4) for name, v in ms.items()},
          "p_values_over_decode": round(ms["p_values"] / ms["decode"], 3),
          "p_values_over_uncertainty": round(ms["p_values"] / ms["uncertainty"], 3),
          "host": machine()}, indent=None)


if __name__ == "__main__":
    main()
