#!/usr/bin/env python3
"""Per-frame cost of the dither generators and of the frame codecs, single against batch.

- ``unit_dither``: the counter generator against the SeedSequence one, M = 512, at
  batch sizes 1, 16, 64, 512 (frames of distinct sensors: one seed per frame);
- ``quantize_frames`` (1 bit, alpha 1, auto delta) with each generator;
- ``decode_quantized_batch`` of B payloads against B calls of ``decode_quantized``;
- ``encode_targets_batch`` (K = 2) against ``TargetsMsg(...).to_json()`` per frame;
- the fixed cost of the codecs: each batch codec at B = 1, 16, 256 and the single-frame
  calls, against the floor of a codec in Python (``struct`` for the 48-byte header,
  ``tobytes`` / ``frombuffer`` for the body) and, with ``--against REV``, the same
  codecs of git revision REV (pipeline/wire and radar_driver/limits.py of REV, loaded
  beside these in this process).

Best of ``--repeat`` runs, us per frame; ratios are taken in the same process (the
machine may be shared, so absolute figures drift more than ratios).

    .venv/bin/python benchmarks/bench_wire.py [--repeat 7] [--against REV]

After the tables, the same figures as one JSON object (``harness.emit``); ``b<N>``: a batch
of N frames.
"""

from __future__ import annotations

import argparse
import struct
import subprocess
import sys
import types

import numpy as np

import pipeline.wire as wire
import radar_driver
from harness import ROOT, best_time, emit
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


def _module(name: str, package: str, source: str, replace: dict[str, types.ModuleType]) -> types.ModuleType:
    """A module run from ``source`` while ``replace`` stands in for the modules it imports."""
    saved = {k: sys.modules[k] for k in replace}
    sys.modules.update(replace)
    if "radar_driver.limits" in replace:
        radar_driver.limits = replace["radar_driver.limits"]
    try:
        mod = sys.modules[name] = types.ModuleType(name)  # (dataclasses look their module up)
        mod.__package__ = package
        exec(compile(source, f"{name}.py", "exec"), mod.__dict__)
    finally:
        sys.modules.update(saved)
        radar_driver.limits = saved.get("radar_driver.limits", radar_driver.limits)
    return mod


def wire_at(rev: str) -> types.SimpleNamespace:
    """The frame and targets codecs of git revision ``rev`` (its pipeline/wire/frames.py,
    messages.py and radar_driver/limits.py), beside the ones of this tree."""
    def show(path: str) -> str:
        return subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:{path}"], capture_output=True, text=True,
                              check=True).stdout

    limits = _module("rev_limits", "radar_driver", show("radar_driver/limits.py"), {})
    frames = _module("rev_frames", "pipeline.wire", show("pipeline/wire/frames.py"), {"radar_driver.limits": limits})
    messages = _module("rev_messages", "pipeline.wire", show("pipeline/wire/messages.py"),
                       {"pipeline.wire.frames": frames})
    return types.SimpleNamespace(**{**vars(frames), **vars(messages)})


def codec_cases(w, b: int) -> dict:
    """Calls of each codec of ``w`` (a module or namespace of the wire names) on B = ``b``
    frames of M = 512 (targets: K = 2); the single-frame calls too when ``b`` is 1."""
    rng = np.random.default_rng(1)
    heads = w.FrameHeaders([f"s{i % 16}" for i in range(b)], np.arange(b, dtype=np.uint64), np.arange(b) + 10**18,
                           np.full(b, 7))
    data = (rng.standard_normal((b, M, 2)) + 1j * rng.standard_normal((b, M, 2))).astype(np.complex64)
    q = quantize_frames(data, QuantizerConfig(), heads.seq, sensor_dither_seeds(0, heads.sensor_id))
    raw, quant = w.encode_raw_batch(heads, data), w.encode_quantized_batch(heads, q)
    keys = [f"radar/{s}/raw" for s in heads.sensor_id]
    f = lambda: rng.uniform(1, 50, (b, 2))  # noqa: E731
    det = Detections(f(), f(), f(), f(), f(), np.zeros((b, 2), int), f())
    cases = {"encode_raw": lambda: w.encode_raw_batch(heads, data), "decode_raw": lambda: w.decode_raw_batch(raw, keys),
             "encode_quantized": lambda: w.encode_quantized_batch(heads, q),
             "decode_quantized": lambda: w.decode_quantized_batch(quant, keys),
             "encode_targets": lambda: w.encode_targets_batch(heads, det, "pbp", 2, "quantized", 10**18)}
    if b == 1:
        rmsg, (qmsg,) = w.decode_raw(raw[0]), w.decode_quantized_batch(quant, keys)[0][0].messages()
        tmsg = w.TargetsMsg("s0", 1, 2, 3, "pbp", 2, "quantized", det.frame(0), 10**18)
        cases.update({"encode_raw single": lambda: w.encode_raw(rmsg),
                      "decode_raw single": lambda: w.decode_raw(raw[0]),
                      "encode_quantized single": lambda: w.encode_quantized(qmsg),
                      "decode_quantized single": lambda: w.decode_quantized(quant[0]),
                      "TargetsMsg.to_json": tmsg.to_json})
    return cases


def floor_costs(repeat: int) -> dict[str, float]:
    """us of the least a codec in Python does for one raw frame (M = 512): the header
    through ``struct``, the body through ``tobytes`` / ``frombuffer``."""
    data = np.zeros((M, 2), np.complex64)
    head = wire.COMMON.pack(wire.MAGIC, 1, wire.KIND_RAW, 0, 0, 1, 2, 3, M, b"s0")
    payload = head + data.tobytes()

    def decode():
        wire.COMMON.unpack_from(payload)
        np.frombuffer(payload, "<c8", offset=wire.HEADER_LEN).reshape(M, 2).copy()

    return {"encode": per_frame_us(lambda: wire.COMMON.pack(wire.MAGIC, 1, wire.KIND_RAW, 0, 0, 1, 2, 3, M, b"s0")
                                   + data.tobytes(), 1, repeat, 256),
            "decode": per_frame_us(decode, 1, repeat, 256)}


def _key(name: str) -> str:
    """A codec case's name as a figure's key ("encode_raw single" -> "encode_raw_single")."""
    return {"TargetsMsg.to_json": "targets_msg_to_json"}.get(name, name.replace(" ", "_"))


def fixed_cost(repeat: int, against: str | None) -> dict:
    """Prints the table of :func:`codec_costs` at B = 1, 16, 256 (and against ``against``);
    returns its figures."""
    floor = floor_costs(repeat)
    figures: dict = {"fixed_floor_us_per_frame": {k: round(v, 3) for k, v in floor.items()},
                     "fixed_us_per_frame": {}}
    if against:
        figures |= {"against": against, "fixed_against_us_per_frame": {}, "ratio_now_to_against": {}}
    print(f"\nfixed cost: us per frame, M = {M}; the floor of a Python codec (struct header + body bytes): "
          f"encode {floor['encode']:.2f}, decode {floor['decode']:.2f}")
    old = wire_at(against) if against else None
    for b in (1, 16, 256):
        now = codec_cases(wire, b)
        then = codec_cases(old, b) if old else {}
        calls = max(1, 256 // b)
        for name, fn in now.items():
            us = old_us = float("inf")
            for _ in range(repeat):  # the two take turns: the load of the machine moves
                us = min(us, per_frame_us(fn, b, 1, calls))
                if then:
                    old_us = min(old_us, per_frame_us(then[name], b, 1, calls))
            line = f"B={b:4d}  {name:24s} {us:8.2f}"
            key = f"{_key(name)}_b{b}"
            figures["fixed_us_per_frame"][key] = round(us, 3)
            if then:
                line += f"   {against} {old_us:8.2f}   now/{against} {us / old_us:5.2f}x"
                figures["fixed_against_us_per_frame"][key] = round(old_us, 3)
                figures["ratio_now_to_against"][key] = round(us / old_us, 3)
            print(line)
    return figures


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--against", metavar="REV", help="also time the codecs of this git revision, in this process")
    ap.add_argument("--only-fixed", action="store_true", help="only the fixed-cost table")
    args = ap.parse_args()
    r = args.repeat
    if args.only_fixed:
        emit(fixed_cost(r, args.against))
        return
    rng = np.random.default_rng(0)
    print(f"us per frame, M = {M}, best of {r}")
    fig: dict = {name: {} for name in ("dither_counter_us_per_frame", "dither_seedseq_us_per_frame",
                                       "ratio_dither_seedseq_to_counter", "quantize_counter_us_per_frame",
                                       "quantize_seedseq_us_per_frame")}
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
        for name, v in (("dither_counter_us_per_frame", c), ("dither_seedseq_us_per_frame", s),
                        ("ratio_dither_seedseq_to_counter", s / c), ("quantize_counter_us_per_frame", qc),
                        ("quantize_seedseq_us_per_frame", qs)):
            fig[name][f"b{b}"] = round(v, 3)

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
    fig["quantized_codec_b64_us_per_frame"] = {"decode_quantized_batch": round(batch, 3),
                                               "decode_quantized_single": round(single, 3),
                                               "encode_quantized_batch": round(enc, 3)}
    fig["ratio_decode_quantized_single_to_batch_b64"] = round(single / batch, 3)

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
    fig["targets_b64_k2_us_per_frame"] = {"encode_targets_batch": round(tb, 3), "targets_msg_to_json": round(tj, 3)}
    fig["ratio_targets_to_json_to_batch_b64"] = round(tj / tb, 3)
    fig |= fixed_cost(r, args.against)
    emit(fig)


if __name__ == "__main__":
    main()
