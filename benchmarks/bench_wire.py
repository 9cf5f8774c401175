#!/usr/bin/env python3
"""Per-frame cost of the dither generators and of the frame codecs, single against batch.

- ``unit_dither``: the counter generator against the SeedSequence one, M = 512, at
  batch sizes 1, 16, 64, 512 (frames of distinct sensors: one seed per frame);
- ``quantize_frames`` (1 bit, alpha 1, auto delta) with each generator;
- ``decode_quantized_batch`` of B payloads against B calls of ``decode_quantized``;
- ``encode_targets_batch`` (K = 2) against ``TargetsMsg(...).to_json()`` per frame.

Best of ``--repeat`` runs, us per frame; ratios are taken in the same process (the
machine may be shared, so absolute figures drift more than ratios).

    .venv/bin/python benchmarks/bench_wire.py [--repeat 7]
"""

from __future__ import annotations

import argparse

import numpy as np

from harness import best_time
from pipeline.dsp.localize import Detections
from pipeline.dsp.quantize import (DITHER_COUNTER, DITHER_SEEDSEQ, QuantizerConfig, quantize_frames,
                               sensor_dither_seeds, unit_dither)
from pipeline.wire import (FrameHeaders, TargetsMsg, decode_quantized, decode_quantized_batch,
                           encode_quantized_batch, encode_targets_batch)

M = 512


def per_frame_us(fn, frames: int, repeat: int, calls: int = 1) -> float:
    """Best of ``repeat`` runs of ``calls`` calls of fn, in us per frame."""
    def run() -> None:
        for _ in range(calls):
            fn()

    return best_time(run, repeat) / calls / frames * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    r = args.repeat
    rng = np.random.default_rng(0)
    print(f"us per frame, M = {M}, best of {r}")
    for b in (1, 16, 64, 512):
        ids = [f"s{i}" for i in range(b)]
        seeds, seqs = sensor_dither_seeds(0, ids), np.arange(b, dtype=np.uint64) + np.uint64(2**40)
        calls = max(1, 256 // b)
        c = per_frame_us(lambda: unit_dither(seeds, seqs, M, DITHER_COUNTER), b, r, calls)
        s = per_frame_us(lambda: unit_dither(seeds, seqs, M, DITHER_SEEDSEQ), b, r, max(1, calls // 4))
        g = 0.3 * (rng.standard_normal((b, M, 2)) + 1j * rng.standard_normal((b, M, 2)))
        qc = per_frame_us(lambda: quantize_frames(g, QuantizerConfig(), seqs, seeds, DITHER_COUNTER), b, r, calls)
        qs = per_frame_us(lambda: quantize_frames(g, QuantizerConfig(), seqs, seeds, DITHER_SEEDSEQ), b, r,
                          max(1, calls // 4))
        print(f"B={b:4d}  unit_dither counter {c:6.2f}  seedseq {s:6.2f}  (seedseq/counter {s / c:4.1f}x)   "
              f"quantize_frames counter {qc:6.2f}  seedseq {qs:6.2f}")

    b = 64
    ids = [f"s{i % 16}" for i in range(b)]
    heads = FrameHeaders(ids, np.arange(b, dtype=np.uint64) + np.uint64(2**64 - 100), np.arange(b) + 10**18, np.full(b, 7))
    g = 0.3 * (rng.standard_normal((b, M, 2)) + 1j * rng.standard_normal((b, M, 2)))
    q = quantize_frames(g, QuantizerConfig(), heads.seq, sensor_dither_seeds(0, ids))
    payloads = encode_quantized_batch(heads, q)
    keys = [f"radar/{s}/quantized" for s in ids]
    batch = per_frame_us(lambda: decode_quantized_batch(payloads, keys), b, r, 4)
    single = per_frame_us(lambda: [decode_quantized(p, k) for p, k in zip(payloads, keys)], b, r, 4)
    enc = per_frame_us(lambda: encode_quantized_batch(heads, q), b, r, 4)
    print(f"B={b}  decode_quantized_batch {batch:6.2f}  decode_quantized {single:6.2f}  "
          f"(single/batch {single / batch:4.1f}x)   encode_quantized_batch {enc:6.2f}")

    k = 2
    f = lambda: rng.uniform(1, 50, (b, k))  # noqa: E731
    det = Detections(f(), f(), f(), f(), f(), np.zeros((b, k), int), f())
    pub = 10**18 + 12345
    tb = per_frame_us(lambda: encode_targets_batch(heads, det, "pbp", k, "quantized", pub), b, r, 4)

    def to_json():
        for i in range(b):
            TargetsMsg(heads.sensor_id[i], int(heads.seq[i]), int(heads.timestamp_ns[i]), int(heads.config_id[i]),
                       "pbp", k, "quantized", det.frame(i), pub).to_json()
    tj = per_frame_us(to_json, b, r, 4)
    print(f"B={b}, K={k}  encode_targets_batch {tb:6.2f}  TargetsMsg(det.frame(i)).to_json {tj:6.2f}  "
          f"(to_json/batch {tj / tb:4.1f}x)")


if __name__ == "__main__":
    main()
