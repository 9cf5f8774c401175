#!/usr/bin/env python3
"""Decoder throughput on the same 1-bit dithered frames (M = 512, K = 2), in batch and
frame by frame, in one process: PBP on the FFT path (fold + inverse FFT), PBP on the
dense Phi^H Z path, PBP with ``--K auto`` (its count test on residuals), and the
dither-aware decoder (QIHT + likelihood on the support).
Prints one JSON object; the ratios are what to compare across machines.

    .venv/bin/python benchmarks/bench_pbp.py [--batch 4096] [--single 300] [--repeat 5]
"""

from __future__ import annotations

import argparse
import os
import platform

import numpy as np

from harness import best_rate, emit
from pipeline.dsp.decode import DecoderConfig, decode

QIHT = DecoderConfig(algo="qiht")
from pipeline.dsp.localize import localize, localize_frame
from experiments.montecarlo import draw_scenes
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from radar_driver.model import RadarConfig, simulate_frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=4096, help="frames in the batch")
    ap.add_argument("--single", type=int, default=300, help="frames localized one by one")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--K", type=int, default=2)
    args = ap.parse_args()

    cfg = RadarConfig()
    rng = np.random.default_rng(0)
    _, _, r, a, x = draw_scenes(args.batch, args.K, rng, cfg)
    q = quantize_frames(simulate_frames(r, a, x, cfg), QuantizerConfig(alpha=1.0), np.arange(args.batch))
    z, xi = q.values(), q.dither()
    ramp_indices = np.arange(cfg.n_measurements) % cfg.samples_per_ramp  # same frequencies, dense path

    fft_det = localize(z, cfg, args.K)
    dense_det = localize(z, cfg, args.K, indices=ramp_indices)
    assert np.array_equal(fft_det.bin, dense_det.bin), "paths disagree on the support"

    single = z[: args.single]
    results = {
        "fft_batch_fps": best_rate(lambda: localize(z, cfg, args.K), args.batch, args.repeat),
        "dense_batch_fps": best_rate(lambda: localize(z, cfg, args.K, indices=ramp_indices), args.batch, args.repeat),
        "fft_single_fps": best_rate(lambda: [localize_frame(f, cfg, args.K) for f in single], len(single), args.repeat),
        "dense_single_fps": best_rate(
            lambda: [localize_frame(f, cfg, args.K, indices=ramp_indices) for f in single], len(single), args.repeat
        ),
    }
    # --K auto (pfa 1e-3, at most K + 2): each target tested on the residual of the ones before it
    # (pipeline.dsp.residual), against the count given, in the same process
    ab, kmax = min(args.batch, 1024), args.K + 2
    results["auto_batch_fps"] = best_rate(lambda: localize(z[:ab], cfg, kmax, pfa=1e-3), ab, args.repeat)
    results["auto_single_fps"] = best_rate(lambda: [localize(f[None], cfg, kmax, pfa=1e-3) for f in single],
                                           len(single), args.repeat)
    results["auto_batch_ms_per_frame"] = 1e3 / results["auto_batch_fps"]
    results["auto_single_ms_per_frame"] = 1e3 / results["auto_single_fps"]
    results["given_over_auto_batch"] = results["fft_batch_fps"] / results["auto_batch_fps"]
    results["given_over_auto_single"] = results["fft_single_fps"] / results["auto_single_fps"]
    qb = min(args.batch, 1024)
    results["qiht_batch_fps"] = best_rate(lambda: decode(z[:qb], xi[:qb], q.delta[:qb], 1, cfg, args.K, QIHT), qb,
                                          max(1, args.repeat // 2))
    ns = min(len(single), 100)
    results["qiht_single_fps"] = best_rate(
        lambda: [decode(z[i:i + 1], xi[i:i + 1], q.delta[i:i + 1], 1, cfg, args.K, QIHT) for i in range(ns)], ns,
        max(1, args.repeat // 2))
    results["qiht_batch_ms_per_frame"] = 1e3 / results["qiht_batch_fps"]
    results["qiht_single_ms_per_frame"] = 1e3 / results["qiht_single_fps"]
    results["pbp_over_qiht_batch"] = results["fft_batch_fps"] / results["qiht_batch_fps"]
    results["fft_over_dense_batch"] = results["fft_batch_fps"] / results["dense_batch_fps"]
    results["fft_over_dense_single"] = results["fft_single_fps"] / results["dense_single_fps"]
    results["batch_over_single_fft"] = results["fft_batch_fps"] / results["fft_single_fps"]
    results = {k: round(v, 3) for k, v in results.items()}
    results.update(
        M=cfg.n_measurements, N=cfg.samples_per_ramp, K=args.K, batch=args.batch, single=len(single),
        numpy=np.__version__, python=platform.python_version(), cpus=os.cpu_count(),
    )
    emit(results)


if __name__ == "__main__":
    main()
