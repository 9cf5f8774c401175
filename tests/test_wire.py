import json

import numpy as np
import pytest

from pipeline.errors import PipelineError
from pipeline.wire import (
    HEADER_LEN,
    QUANT_HEADER_LEN,
    HealthMsg,
    QuantizedFrameMsg,
    RawFrameMsg,
    TargetsMsg,
    WireError,
    decode_health,
    decode_quantized,
    decode_raw,
    decode_targets,
    encode_quantized,
    encode_raw,
)


def raw_msg(m=512, seed=0):
    rng = np.random.default_rng(seed)
    data = (rng.standard_normal((m, 2)) + 1j * rng.standard_normal((m, 2))).astype(np.complex64)
    return RawFrameMsg("kmd2-0", 41, 1_700_000_000_123_456_789, 0xDEADBEEF, data)


def quant_msg(bits=1, m=512, alpha=0.5):
    codes = np.random.default_rng(1).integers(0, 1 << bits, (m, 2, 2)).astype(np.uint8)
    return QuantizedFrameMsg("kmd2-0", 41, 1_700_000_000_123_456_789, 0xDEADBEEF, bits, alpha, 0.75, 2**40 + 3, codes)


def test_raw_round_trip_and_layout():
    msg = raw_msg()
    b = encode_raw(msg)
    assert len(b) == HEADER_LEN + 512 * 2 * 8 == 48 + 8192
    assert b[:4] == b"QRDR" and b[4] == 1 and b[5] == 1  # magic, version, kind raw
    assert int.from_bytes(b[8:16], "little") == 41
    assert int.from_bytes(b[16:24], "little") == 1_700_000_000_123_456_789
    assert int.from_bytes(b[24:28], "little") == 0xDEADBEEF
    assert int.from_bytes(b[28:32], "little") == 512
    assert b[32:48] == b"kmd2-0".ljust(16, b"\0")
    assert np.frombuffer(b[48:56], "<f4").tolist() == [msg.data[0, 0].real, msg.data[0, 0].imag]
    assert decode_raw(b) == msg


@pytest.mark.parametrize("bits", [1, 2, 4, 8, 12])
def test_quantized_round_trip(bits):
    msg = quant_msg(bits)
    out = decode_quantized(encode_quantized(msg))
    assert out == msg and out.dithered


def test_one_bit_frame_is_256_bytes_of_codes_plus_64_of_header():
    b = encode_quantized(quant_msg(1))
    assert QUANT_HEADER_LEN == 64
    assert len(b) == 64 + 256


def test_json_messages_round_trip():
    t = TargetsMsg("kmd2-0", 3, 10, 7, "pbp", 2, "quantized",
                   [{"range_m": 4.8, "angle_deg": -20.0, "x_m": 4.5, "y_m": -1.6, "amplitude": 0.06}], 99)
    assert decode_targets(t.to_json()) == t
    obj = json.loads(t.to_json())
    assert obj["version"] == 1 and obj["type"] == "targets" and obj["targets"][0]["range_m"] == 4.8
    h = HealthMsg("quantize", "kmd2-0", 5, 10, 9, 1, 2, {"p50": 1.5, "p99": 3.0}, 100.0, 50.0)
    assert decode_health(h.to_json()) == h


@pytest.mark.parametrize(
    "mutate, fragment",
    [
        (lambda b: b[:20], "shorter than the 48-byte header"),
        (lambda b: b"XXXX" + b[4:], "magic b'XXXX'"),
        (lambda b: b[:4] + b"\x07" + b[5:], "format version 7 unsupported"),
        (lambda b: b[:-1], "8239 bytes, expected 8240 for M=512"),
        (lambda b: b[:5] + b"\x02" + b[6:], "message kind 2, expected 1"),
        (lambda b: b[:32] + b"bad id!".ljust(16, b"\0") + b[48:], "sensor id"),
    ],
)
def test_bad_raw_payloads(mutate, fragment):
    with pytest.raises(WireError, match=fragment) as info:
        decode_raw(mutate(encode_raw(raw_msg())), "radar/kmd2-0/raw")
    assert "radar/kmd2-0/raw" in str(info.value)
    assert isinstance(info.value, PipelineError)


@pytest.mark.parametrize(
    "mutate, fragment",
    [
        (lambda b: b[:60], "shorter than its 64-byte header"),
        (lambda b: b[:-3], "317 bytes, expected 320"),
        (lambda b: b[:6] + b"\x00" + b[7:], "bits=0"),
        (lambda b: b[:7] + b"\x00" + b[8:], "contradicts alpha"),
    ],
)
def test_bad_quantized_payloads(mutate, fragment):
    with pytest.raises(WireError, match=fragment):
        decode_quantized(mutate(encode_quantized(quant_msg())), "radar/kmd2-0/quantized")


@pytest.mark.parametrize(
    "payload, fragment",
    [
        (b"\xff\xfe", "not UTF-8 JSON"),
        (b"[1, 2]", "expected a JSON object"),
        (b'{"version": 2, "type": "targets"}', "format version 2 unsupported"),
        (b'{"version": 1, "type": "health"}', "type 'health', expected 'targets'"),
        (b'{"version": 1, "type": "targets", "sensor_id": "a"}', "missing or bad field"),
    ],
)
def test_bad_json_payloads(payload, fragment):
    with pytest.raises(WireError, match=fragment):
        decode_targets(payload, "radar/a/targets")


def test_garbage_never_raises_anything_but_wire_errors():
    rng = np.random.default_rng(0)
    good = [encode_raw(raw_msg(64)), encode_quantized(quant_msg(1, 64))]
    for i in range(2000):
        if i % 2:
            b = rng.integers(0, 256, int(rng.integers(0, 600)), dtype=np.uint8).tobytes()
        else:
            b = bytearray(good[i % 4 // 2])
            for _ in range(3):
                b[int(rng.integers(0, len(b)))] = int(rng.integers(0, 256))
            b = bytes(b)
        for dec in (decode_raw, decode_quantized, decode_targets, decode_health):
            try:
                dec(b)
            except WireError:
                pass


def test_encoder_rejects_bad_messages():
    with pytest.raises(WireError, match="sensor_id"):
        encode_raw(RawFrameMsg("radar/*", 0, 0, 0, np.zeros((4, 2), np.complex64)))
    with pytest.raises(WireError, match="shape"):
        encode_raw(RawFrameMsg("a", 0, 0, 0, np.zeros((4, 3), np.complex64)))
