#!/usr/bin/env python3
"""What ``--alpha auto`` costs the quantizer: per-frame time of ``quantize_frames`` (1 bit,
auto delta, M = 512, frames of distinct sensors) with a fixed alpha against alpha auto
(the per-sensor :class:`pipeline.dsp.noise.NoiseTracker` update -- the noise estimate -- plus
the quantization with each frame's alpha), at batch sizes 1, 16, 64, 512; and the estimate
alone. Best of ``--repeat`` runs, us per frame; the ratio is taken in the same process
(the machine may be shared, so absolute figures drift more than ratios).

    .venv/bin/python benchmarks/bench_noise.py [--repeat 7]

After the table, the same figures as one JSON object (``harness.emit``), each keyed by
batch size (``b1``, ``b16`` ...).
"""

from __future__ import annotations

import argparse

import numpy as np

from bench_wire import per_frame_us
from harness import emit
from pipeline.dsp.noise import NoiseTracker, estimate_noise_sigma
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames, sensor_dither_seeds

M, N = 512, 256


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    fixed, auto = QuantizerConfig(alpha=0.45), QuantizerConfig(alpha="auto")
    print(f"{'batch':>6} {'fixed alpha':>12} {'alpha auto':>12} {'ratio':>7} {'estimate':>10}   (us per frame)")
    fig: dict = {name: {} for name in ("fixed_alpha_us_per_frame", "alpha_auto_us_per_frame",
                                       "ratio_auto_to_fixed", "estimate_us_per_frame")}
    for b in (1, 16, 64, 512):
        frames = 0.3 * (rng.standard_normal((b, M, 2)) + 1j * rng.standard_normal((b, M, 2)))
        ids = [f"s{i}" for i in range(b)]
        seeds, seq = sensor_dither_seeds(0, ids), np.arange(b)
        tracker = NoiseTracker(N)
        calls = max(1, 256 // b)

        def run_fixed():
            quantize_frames(frames, fixed, seq, dither_seed=seeds)

        def run_auto():
            quantize_frames(frames, auto, seq, dither_seed=seeds, noise_sigma=tracker.update(ids, frames))

        tf = per_frame_us(run_fixed, b, args.repeat, calls)
        ta = per_frame_us(run_auto, b, args.repeat, calls)
        te = per_frame_us(lambda: estimate_noise_sigma(frames, N), b, args.repeat, calls)
        print(f"{b:>6} {tf:>12.1f} {ta:>12.1f} {ta / tf:>6.2f}x {te:>10.1f}")
        for name, v in zip(fig, (tf, ta, ta / tf, te)):
            fig[name][f"b{b}"] = round(v, 3)
    emit(fig)


if __name__ == "__main__":
    main()
