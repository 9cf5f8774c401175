"""The wire bytes do not change: every encoder (single-frame and batch) writes exactly the
stored bytes of tests/golden/wire_vectors.json for the stored inputs, and the decoders
read those bytes back to the inputs (tests/golden/make_wire_vectors.py wrote the file)."""

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.dsp.localize import Detections
from pipeline.dsp.quantize import QuantizedFrames
from pipeline.wire import (FrameHeaders, HealthMsg, TracksMsg, decode_health, decode_quantized, decode_quantized_batch,
                           decode_raw, decode_raw_batch, decode_targets, decode_tracks, encode_quantized,
                           encode_quantized_batch, encode_raw, encode_raw_batch, encode_targets_batch)

GOLDEN = Path(__file__).parent / "golden"
VECTORS = json.loads((GOLDEN / "wire_vectors.json").read_text())
_spec = importlib.util.spec_from_file_location("make_wire_vectors", GOLDEN / "make_wire_vectors.py")
make = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(make)


def vectors(kind):
    return [(v["input"], bytes.fromhex(v["hex"])) for v in VECTORS[kind]]


def headers(inputs):
    return FrameHeaders([d["sensor_id"] for d in inputs], [d["seq"] for d in inputs],
                        [d["timestamp_ns"] for d in inputs], [d["config_id"] for d in inputs])


def test_the_file_covers_every_format_and_bit_depth():
    assert {k: len(v) for k, v in VECTORS.items()} == {"raw": 3, "quantized": 16, "targets": 4, "tracks": 2,
                                                         "health": 2}
    assert sorted(d["bits"] for d, _ in vectors("quantized")) == list(range(1, 17))
    assert {d["generator"] for d, _ in vectors("quantized")} == {"seedseq", "counter"}
    stats = [["statistic_db" in t for t in d["targets"]] for d, _ in vectors("targets")]
    assert [] in stats and [False, False] in stats and [True, False, True] in stats


@pytest.mark.parametrize("i", range(3))
def test_raw_bytes(i):
    d, want = vectors("raw")[i]
    msg = make.raw_msg(d)
    assert encode_raw(msg) == want
    assert encode_raw_batch(headers([d]), msg.data[None]) == [want]
    assert decode_raw(want) == msg
    (group,), errors = decode_raw_batch([want], ["golden"])
    assert not errors and group.messages() == [msg] and group.data.dtype == np.complex64


def test_raw_batch_of_one_m_is_the_frames_bytes():
    (d0, b0), (d1, b1) = vectors("raw")[1], vectors("raw")[1]
    data = np.stack([make.raw_msg(d0).data, make.raw_msg(d1).data])
    assert encode_raw_batch(headers([d0, d1]), data) == [b0, b1]


@pytest.mark.parametrize("bits", range(1, 17))
def test_quantized_bytes(bits):
    d, want = vectors("quantized")[bits - 1]
    assert d["bits"] == bits
    msg = make.quantized_msg(d)
    assert encode_quantized(msg) == want
    q = QuantizedFrames(msg.codes[None], np.array([d["delta"]]), bits, d["alpha"], d["dither_seed"],
                        np.array([d["seq"]], dtype=np.uint64), d["generator"])
    assert encode_quantized_batch(headers([d]), q) == [want]
    back = decode_quantized(want)
    assert back.header() == (d["sensor_id"], d["seq"], d["timestamp_ns"], d["config_id"], bits,
                             float(np.float32(d["alpha"])), float(np.float32(d["delta"])), d["dither_seed"],
                             d["generator"])
    np.testing.assert_array_equal(back.codes, msg.codes)
    (group,), errors = decode_quantized_batch([want], ["golden"])
    assert not errors and group.messages() == [back]


def test_quantized_batch_of_every_depth_decodes_to_its_groups():
    payloads = [b for _, b in vectors("quantized")]
    groups, errors = decode_quantized_batch(payloads, ["golden"] * len(payloads))
    assert not errors and [g.frames.bits for g in groups] == list(range(1, 17))
    for g, (d, _) in zip(groups, vectors("quantized")):
        np.testing.assert_array_equal(g.frames.codes[0], d["codes"])


@pytest.mark.parametrize("i", range(4))
def test_targets_bytes(i):
    d, want = vectors("targets")[i]
    msg = make.targets_msg(d)
    assert msg.to_json() == want
    back = decode_targets(want)
    assert back == msg
    # the batch writer: the frame's targets as (1, K) arrays of a Detections, one slot absent
    k = len(d["targets"]) + 1
    cols = {f: np.full((1, k), np.nan) for f in ("range_m", "angle_deg", "x_m", "y_m", "amplitude", "statistic_db")}
    for j, t in enumerate(d["targets"]):
        for f, v in t.items():
            cols[f][0, j + 1] = v
    present = np.arange(k)[None] > 0
    det = Detections(**cols, bin=np.zeros((1, k), dtype=int), present=present)
    assert encode_targets_batch(headers([d]), det, d["algo"], d["k"], d["source"], d["published_ns"],
                                d["auto_k"]) == [want]


@pytest.mark.parametrize("i", range(2))
def test_tracks_bytes(i):
    d, want = vectors("tracks")[i]
    assert TracksMsg(**d).to_json() == want
    assert decode_tracks(want) == TracksMsg(**d)


@pytest.mark.parametrize("i", range(2))
def test_health_bytes(i):
    d, want = vectors("health")[i]
    assert HealthMsg(**d).to_json() == want
    back = decode_health(want)
    assert back.to_json() == want and back.node == d["node"] and back.refused == d.get("refused", 0)
