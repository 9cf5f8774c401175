"""Writes tests/golden/wire_vectors.json: the bytes every wire encoder produces for a fixed
set of frames (raw; quantized at 1..16 bits; targets with and without ``statistic_db``;
tracks; health), beside the inputs they were made from. tests/test_wire_golden.py
re-encodes the inputs and compares with the stored bytes, and decodes the bytes back.

Run it only when a wire format changes on purpose: ``python tests/golden/make_wire_vectors.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.wire import (HealthMsg, QuantizedFrameMsg, RawFrameMsg, TargetsMsg, TracksMsg, encode_quantized,
                           encode_raw)

OUT = Path(__file__).with_name("wire_vectors.json")

#: (sensor id, seq, timestamp_ns, config_id) of the frames, edge values included
HEADERS = [("kmd2", 0, 0, 0), ("abcdefghijklmnop", 2**64 - 1, -2**63, 2**32 - 1),
           ("A-z_9", 41, 1_700_000_000_123_456_789, 0xDEADBEEF)]


def raw_inputs() -> list[dict]:
    """Raw frames of M = 1, 5 and 3 with values exact in float32 (data as [re, im] pairs)."""
    out = []
    for (sid, seq, ts, cid), m in zip(HEADERS, (1, 5, 3)):
        k = np.arange(2 * m, dtype=float).reshape(m, 2)
        re, im = (k - m) / 64.0, (3.5 - k) / 8.0 * (-1) ** k
        out.append({"sensor_id": sid, "seq": seq, "timestamp_ns": ts, "config_id": cid,
                    "data": np.stack([re, im], axis=-1).tolist()})
    return out


def quantized_inputs() -> list[dict]:
    """Quantized frames of M = 5 (an odd code count: padded bits) at 1..16 bits, both
    generators, dithered (alpha > 0) and not, one delta that float32 rounds."""
    out = []
    for bits in range(1, 17):
        sid, seq, ts, cid = HEADERS[bits % 3]
        codes = (np.arange(20) * 7919 + bits * 31) % (1 << bits)
        out.append({"sensor_id": sid, "seq": seq, "timestamp_ns": ts, "config_id": cid, "bits": bits,
                    "alpha": [0.0, 0.5, 1.0, 0.25][bits % 4], "delta": [0.75, 0.1, 2.0 ** -10][bits % 3],
                    "dither_seed": [0, 2**64 - 1, 2**40 + 3][bits % 3],
                    "generator": "seedseq" if bits % 5 == 0 else "counter",
                    "codes": codes.reshape(5, 2, 2).tolist()})
    return out


def targets_inputs() -> list[dict]:
    """Targets: none; two without statistic_db; three with it on some only; K_auto; text
    needing JSON escapes."""
    t = [{"range_m": 1.25, "angle_deg": -12.5, "x_m": 1.2203, "y_m": -0.27064, "amplitude": 0.031},
         {"range_m": 3.0000001, "angle_deg": 45.0, "x_m": 2.1213203, "y_m": 2.1213203, "amplitude": 1e-9},
         {"range_m": 0.1, "angle_deg": 0.0, "x_m": 0.1, "y_m": 0.0, "amplitude": 123456.789}]
    base = {"algo": "pbp", "k": 2, "source": "quantized", "published_ns": 1_700_000_000_500_000_000, "auto_k": False}
    return [{**base, "sensor_id": "kmd2", "seq": 0, "timestamp_ns": 0, "config_id": 0, "targets": []},
            {**base, "sensor_id": "kmd2", "seq": 7, "timestamp_ns": 1_700_000_000_123_456_789, "config_id": 3,
             "targets": t[:2]},
            {**base, "sensor_id": "A-z_9", "seq": 2**64 - 1, "timestamp_ns": -5, "config_id": 2**32 - 1,
             "algo": "cml", "k": 3, "auto_k": True, "source": "raw",
             "targets": [{**t[0], "statistic_db": 17.25}, t[1], {**t[2], "statistic_db": -3.0625}]},
            {**base, "sensor_id": "x", "seq": 1, "timestamp_ns": 1, "config_id": 1, "algo": 'a"%b\\c',
             "targets": [{**t[2], "statistic_db": 0.5}]}]


def tracks_inputs() -> list[dict]:
    tr = {"track_id": 3, "range_m": 2.5, "angle_deg": 10.0, "x_m": 2.462, "y_m": 0.434, "vx_mps": -0.125,
          "vy_mps": 0.0625, "sigma_m": 0.05, "age_s": 1.5, "hits": 12, "static": False}
    return [{"sensor_id": "kmd2", "seq": 0, "timestamp_ns": 0, "tracks": [], "published_ns": 0},
            {"sensor_id": "A-z_9", "seq": 99, "timestamp_ns": 1_700_000_000_123_456_789,
             "tracks": [tr, {**tr, "track_id": 2**64 - 1, "hits": 0, "static": True, "x_m": 1e-7}],
             "published_ns": 1_700_000_000_200_000_000}]


def health_inputs() -> list[dict]:
    return [{"node": "quantizer", "sensor_id": "kmd2", "timestamp_ns": 1},
            {"node": "localizer-1", "sensor_id": "A-z_9", "timestamp_ns": 1_700_000_000_123_456_789,
             "frames_in": 100, "frames_out": 98, "drops": 2, "decode_errors": 1,
             "latency_ms": {"p50": 1.5, "p99": 12.25}, "bytes_in_per_s": 1234.56, "bytes_out_per_s": 0.04,
             "extra": {"queue": 3, "note": "é"}, "invalid_frames": 1, "processing_errors": 2, "frames_missing": 3,
             "seq_resets": 4, "worker_restarts": 5, "over_budget": 6, "refused": 7, "implausible_seq": 8,
             "denied_puts": 9}]


def raw_msg(d: dict) -> RawFrameMsg:
    data = np.asarray(d["data"], dtype=float)
    return RawFrameMsg(d["sensor_id"], d["seq"], d["timestamp_ns"], d["config_id"],
                       (data[..., 0] + 1j * data[..., 1]).astype(np.complex64))


def quantized_msg(d: dict) -> QuantizedFrameMsg:
    codes = np.asarray(d["codes"], dtype=np.uint8 if d["bits"] <= 8 else np.uint16)
    return QuantizedFrameMsg(d["sensor_id"], d["seq"], d["timestamp_ns"], d["config_id"], d["bits"], d["alpha"],
                             d["delta"], d["dither_seed"], codes, d["generator"])


def targets_msg(d: dict) -> TargetsMsg:
    return TargetsMsg(d["sensor_id"], d["seq"], d["timestamp_ns"], d["config_id"], d["algo"], d["k"], d["source"],
                      d["targets"], d["published_ns"], d["auto_k"])


def main() -> None:
    vectors = {"raw": [{"input": d, "hex": encode_raw(raw_msg(d)).hex()} for d in raw_inputs()],
               "quantized": [{"input": d, "hex": encode_quantized(quantized_msg(d)).hex()} for d in quantized_inputs()],
               "targets": [{"input": d, "hex": targets_msg(d).to_json().hex()} for d in targets_inputs()],
               "tracks": [{"input": d, "hex": TracksMsg(**d).to_json().hex()} for d in tracks_inputs()],
               "health": [{"input": d, "hex": HealthMsg(**d).to_json().hex()} for d in health_inputs()]}
    OUT.write_text(json.dumps(vectors, indent=1) + "\n")
    print(f"wrote {OUT}: " + ", ".join(f"{k} {len(v)}" for k, v in vectors.items()))


if __name__ == "__main__":
    main()
