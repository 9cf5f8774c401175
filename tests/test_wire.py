import json
from collections import Counter

import numpy as np
import pytest

from pipeline.errors import PipelineError
from pipeline.wire import (
    FLAG_DITHERED,
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


def targets_msg():
    return TargetsMsg("kmd2-0", 3, 10, 7, "pbp", 2, "quantized",
                      [{"range_m": 4.8, "angle_deg": -20.0, "x_m": 4.5, "y_m": -1.6, "amplitude": 0.06}], 99)


def health_msg():
    return HealthMsg("quantize", "kmd2-0", 5, 10, 9, 1, 2, {"p50": 1.5, "p99": 3.0}, 100.0, 50.0)


DECODERS = {decode_raw: RawFrameMsg, decode_quantized: QuantizedFrameMsg, decode_targets: TargetsMsg,
            decode_health: HealthMsg}


def canonical(payload: bytes, kind: str) -> bytes:
    """The bytes an encoder writes for what the decoder read from ``payload``: the binary
    decoders do not look at the raw header's bits byte (6) nor at the flag bits other than
    "dithered" (byte 7), so the encoder writes those as the format says (bits 0 for raw, no
    other flag set); every other byte must come back as it was."""
    if kind == "raw":
        return payload[:6] + b"\0\0" + payload[8:]
    if kind == "quantized":
        return payload[:7] + bytes([payload[7] & FLAG_DITHERED]) + payload[8:]
    raise AssertionError(kind)


@pytest.mark.parametrize(
    "decoder, field, spelling",
    [(decode_targets, b'"seq":3', b'"seq":1e999'), (decode_health, b'"drops":1', b'"drops":Infinity')],
)
def test_json_integers_out_of_range_are_wire_errors(decoder, field, spelling):
    good = (targets_msg() if decoder is decode_targets else health_msg()).to_json()
    assert field in good
    with pytest.raises(WireError, match="radar/a/x"):
        decoder(good.replace(field, spelling), "radar/a/x")


def mutate(payload: bytes, rng, digits_only: bool) -> bytes:
    """Three bytes of ``payload`` changed: any byte to any value, or (``digits_only``) a
    decimal digit to another digit, which keeps JSON well formed."""
    b = bytearray(payload)
    where = [i for i, c in enumerate(b) if chr(c).isdigit()] if digits_only else range(len(b))
    for _ in range(3):
        i = where[int(rng.integers(0, len(where)))]
        b[i] = ord(str(int(rng.integers(0, 10)))) if digits_only else int(rng.integers(0, 256))
    return bytes(b)


def test_garbage_never_raises_anything_but_wire_errors():
    """Random bytes, and good payloads of every format with three bytes changed, through
    every decoder: each returns a message of its own type or raises a WireError naming the
    source; any other exception fails the test. Random bytes are always rejected; some
    mutated payloads still decode, and what decodes re-encodes to the same bytes (binary
    formats, up to the header bytes the decoder does not read, see ``canonical``) or to the
    same JSON value (JSON bytes are not canonical: 0.60 comes back as 0.6)."""
    rng = np.random.default_rng(0)
    source = "radar/a/raw"
    good = {"raw": encode_raw(raw_msg(64)), "quantized": encode_quantized(quant_msg(1, 64)),
            "targets": targets_msg().to_json(), "health": health_msg().to_json()}
    kinds = list(good)
    own = {"raw": decode_raw, "quantized": decode_quantized, "targets": decode_targets, "health": decode_health}
    outcomes = Counter()  # (payload kind, mutation, decoder, "ok" / "rejected")
    same_bytes = Counter()  # decoded mutated payloads whose re-encoding is byte-identical
    for i in range(2000):
        if i % 2:
            kind, how = "random", "random"
            b = rng.integers(0, 256, int(rng.integers(0, 600)), dtype=np.uint8).tobytes()
        else:
            kind = kinds[i // 2 % len(kinds)]
            how = "digits" if kind in ("targets", "health") and i // 8 % 2 else "bytes"
            b = mutate(good[kind], rng, how == "digits")
        for dec, msg_type in DECODERS.items():
            try:
                msg = dec(b, source)
            except WireError as exc:
                assert source in str(exc), f"{dec.__name__} does not name the source: {exc}"
                outcomes[kind, how, dec.__name__, "rejected"] += 1
                continue
            assert type(msg) is msg_type, f"{dec.__name__} returned a {type(msg).__name__}"
            assert kind != "random", f"{dec.__name__} accepted random bytes {b!r}"
            outcomes[kind, how, dec.__name__, "ok"] += 1
            if dec is decode_raw:
                again = encode_raw(msg)
                assert again == canonical(b, "raw"), f"{b!r} re-encodes as {again!r}"
            elif dec is decode_quantized:
                again = encode_quantized(msg)
                assert again == canonical(b, "quantized"), f"{b!r} re-encodes as {again!r}"
            else:
                again = msg.to_json()
                assert json.loads(again) == json.loads(b) and dec(again, source) == msg
            same_bytes[kind] += again == b

    # random bytes: 1000 payloads, each refused by all four decoders
    for dec in DECODERS:
        assert outcomes["random", "random", dec.__name__, "rejected"] == 1000
    # a mutated payload is accepted by its own decoder only
    assert {(k, d) for k, _, d, o in outcomes if o == "ok"} <= {(k, own[k].__name__) for k in kinds}
    # of each kind, some mutated payloads decode (changed samples, codes, seq, numbers ...) and some do not
    # (changed magic, version, kind, M, sensor id ...; random bytes in JSON)
    tally = {(kind, how): (outcomes[kind, how, own[kind].__name__, "ok"],
                           outcomes[kind, how, own[kind].__name__, "rejected"])
             for kind, how in [("raw", "bytes"), ("quantized", "bytes"), ("targets", "digits"), ("health", "digits")]}
    for (kind, how), (ok, rejected) in tally.items():
        assert ok >= 25 and rejected >= 5, (kind, how, ok, rejected, dict(outcomes))
    # re-encoding gives back the very bytes in nearly every case (binary: all but the ignored header bytes)
    for kind in kinds:
        ok = sum(n for (k, _, _, o), n in outcomes.items() if k == kind and o == "ok")
        assert same_bytes[kind] >= 0.8 * ok, (kind, same_bytes[kind], ok)


def test_encoder_rejects_bad_messages():
    with pytest.raises(WireError, match="sensor_id"):
        encode_raw(RawFrameMsg("radar/*", 0, 0, 0, np.zeros((4, 2), np.complex64)))
    with pytest.raises(WireError, match="shape"):
        encode_raw(RawFrameMsg("a", 0, 0, 0, np.zeros((4, 3), np.complex64)))
