import json
import struct
from collections import Counter

import numpy as np
import pytest

from pipeline.errors import PipelineError
from pipeline.dsp.localize import Detections
from pipeline.dsp.quantize import (DITHER_COUNTER, DITHER_SEEDSEQ, QuantizedFrames, QuantizerConfig, quantize_frames,
                               unit_dither)
from pipeline.wire import (
    COMMON,
    COMMON_DTYPE,
    FLAG_DITHERED,
    HEADER_LEN,
    QUANT_DTYPE,
    QUANT_EXT,
    QUANT_HEADER_LEN,
    FrameHeaders,
    HealthMsg,
    QuantizedFrameMsg,
    RawFrameMsg,
    TargetsMsg,
    WireError,
    decode_health,
    decode_quantized,
    decode_quantized_batch,
    decode_raw,
    decode_raw_batch,
    decode_targets,
    encode_quantized,
    encode_quantized_batch,
    encode_raw,
    encode_raw_batch,
    encode_targets_batch,
    quantized_batch,
)


def raw_msg(m=512, seed=0):
    rng = np.random.default_rng(seed)
    data = (rng.standard_normal((m, 2)) + 1j * rng.standard_normal((m, 2))).astype(np.complex64)
    return RawFrameMsg("kmd2-0", 41, 1_700_000_000_123_456_789, 0xDEADBEEF, data)


def quant_msg(bits=1, m=512, alpha=0.5, generator=DITHER_COUNTER, seq=41, sensor="kmd2-0", seed=2**40 + 3):
    codes = np.random.default_rng(bits * m + seq % 1000).integers(0, 1 << bits, (m, 2, 2))
    codes = codes.astype(np.uint8 if bits <= 8 else np.uint16)
    return QuantizedFrameMsg(sensor, seq, 1_700_000_000_123_456_789, 0xDEADBEEF, bits, alpha, 0.75, seed, codes,
                             generator)


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
    other flag set), and raw frames of version 2 as version 1; every other byte must come
    back as it was."""
    if kind == "raw":  # raw frames are read as version 1 or 2, written as 1
        return payload[:4] + b"\x01" + payload[5:6] + b"\0\0" + payload[8:]
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


# -- format versions, the header dtype, batch codecs -------------------------------------------
def test_header_dtype_agrees_with_the_struct_layout():
    rng = np.random.default_rng(3)
    for _ in range(20):
        fields = [rng.bytes(4), *rng.integers(0, 256, 4).tolist(), int(rng.integers(0, 2**63)) * 2 + 1,
                  -int(rng.integers(0, 2**62)), int(rng.integers(0, 2**32)), int(rng.integers(0, 2**32)),
                  rng.bytes(16)]
        ext = [int(rng.integers(0, 2**63)) * 2, float(np.float32(rng.random())), float(np.float32(rng.random()))]
        rec = np.frombuffer(COMMON.pack(*fields) + QUANT_EXT.pack(*ext), dtype=QUANT_DTYPE)[0]
        got = [rec[n].tobytes() if rec[n].shape else rec[n].item() for n in QUANT_DTYPE.names]
        assert got == fields + ext
    assert COMMON_DTYPE.itemsize == HEADER_LEN and QUANT_DTYPE.itemsize == QUANT_HEADER_LEN


def test_format_version_names_the_dither_generator():
    for gen, version in ((DITHER_SEEDSEQ, 1), (DITHER_COUNTER, 2)):
        msg = quant_msg(generator=gen)
        b = encode_quantized(msg)
        assert b[4] == version
        out = decode_quantized(b)
        assert out == msg and out.generator == gen
    assert quant_msg().generator == DITHER_COUNTER  # the default
    # raw frames: written as version 1, read as 1 or 2, other versions refused
    b = encode_raw(raw_msg())
    assert b[4] == 1 and decode_raw(b[:4] + b"\x02" + b[5:]) == raw_msg()
    for payload, decoder in ((b, decode_raw), (encode_quantized(quant_msg()), decode_quantized)):
        for version in (0, 3, 255):
            with pytest.raises(WireError, match=f"format version {version} unsupported \\(this build reads 1 and 2\\)"):
                decoder(payload[:4] + bytes([version]) + payload[5:], "radar/a/x")
    # the dither a decoder regenerates is the one of the frame's generator
    g = np.random.default_rng(0).standard_normal((1, 512, 2)) * (1 + 1j)
    for gen in (DITHER_SEEDSEQ, DITHER_COUNTER):
        q = quantize_frames(g, QuantizerConfig(alpha=1.0), [7], dither_seed=5, generator=gen)
        msg = decode_quantized(encode_quantized(QuantizedFrameMsg("a", 7, 0, 1, 1, q.alpha, float(q.delta[0]), 5,
                                                                  q.codes[0], gen)))
        np.testing.assert_array_equal(msg.dither(), q.dither()[0])


def bad_payloads():
    """(payload, kind) of every error the frame decoders report."""
    q, r = encode_quantized(quant_msg()), encode_raw(raw_msg(64))

    def at(b, offset, value: bytes):
        return b[:offset] + value + b[offset + len(value):]

    return [
        (q[:20], "short"), (at(q, 0, b"XXXX"), "magic"), (at(q, 4, b"\x07"), "version"), (at(q, 5, b"\x01"), "kind"),
        (at(q, 28, (0).to_bytes(4, "little")), "M=0"), (at(q, 28, (2**21).to_bytes(4, "little")), "M large"),
        (at(q, 28, (2**32 - 1).to_bytes(4, "little")), "M huge"),
        (at(q, 32, b"bad id!"), "sensor id"), (at(q, 32, b"\0" * 16), "empty id"), (at(q, 34, b"\0"), "NUL inside"),
        (at(q, 32, b"\xff"), "non-ASCII id"), (q[:60], "short ext"), (at(q, 6, b"\x00"), "bits=0"),
        (at(q, 6, b"\x11"), "bits=17"), (at(q, 60, struct.pack("<f", np.nan)), "delta NaN"),
        (at(q, 60, struct.pack("<f", np.inf)), "delta inf"), (at(q, 60, struct.pack("<f", -1.0)), "delta < 0"),
        (at(q, 60, struct.pack("<f", 1e30)), "delta huge"),
        (at(q, 56, struct.pack("<f", 2.0)), "alpha > 1"), (at(q, 56, struct.pack("<f", np.nan)), "alpha NaN"),
        (at(q, 7, b"\x00"), "flag"), (q[:-1], "length"), (q + b"\0", "longer"),
        (r[:47], "raw short"), (at(r, 0, b"QRDX"), "raw magic"), (at(r, 4, b"\x03"), "raw version"),
        (at(r, 5, b"\x02"), "raw kind"), (at(r, 32, b"a b"), "raw id"), (r[:-8], "raw length"),
        (at(r, 28, (2**32 - 1).to_bytes(4, "little")), "raw M huge"),
    ]


def good_quantized():
    """Quantized payloads of several sensors, M, bit depths, generators, alpha 0, seqs near 2**64."""
    out = []
    for i in range(24):
        gen = (DITHER_SEEDSEQ, DITHER_COUNTER)[i % 2]
        bits, m = ((1, 512), (2, 256), (12, 64), (1, 64))[i // 2 % 4]  # M=512 1 bit and M=256 2 bits: both 256 bytes
        out.append(encode_quantized(quant_msg(bits, m, 0.0 if i % 5 == 0 else 0.25, gen, 2**64 - 1 - i, f"s{i % 3}",
                                              2**64 - 1 - i % 4)))
    return out


def assert_batch_matches_single(payloads, batch, single, msg_type):
    sources = [f"radar/s{i}/x" for i in range(len(payloads))]
    groups, errors = batch(payloads, sources)
    seen = {}
    for g in groups:
        msgs = g.messages()
        assert len(msgs) == len(g.index) == len(g.headers)
        seen.update(zip(g.index.tolist(), msgs))
    for i, exc in errors:
        seen[i] = exc
    assert sorted(seen) == list(range(len(payloads)))
    n_ok = 0
    for i, p in enumerate(payloads):
        try:
            want = single(p, sources[i])
        except WireError as exc:
            assert isinstance(seen[i], WireError) and str(seen[i]) == str(exc), (i, str(seen[i]), str(exc))
            continue
        got = seen[i]
        assert type(got) is msg_type and got == want, i
        if msg_type is QuantizedFrameMsg:
            assert got.generator == want.generator and got.codes.dtype == want.codes.dtype
        n_ok += 1
    return groups, errors, n_ok


def test_quantized_batch_decoder_equals_the_single_one():
    good, bad = good_quantized(), [p for p, _ in bad_payloads()]
    rng = np.random.default_rng(4)
    mutated = [mutate(good[int(rng.integers(len(good)))], rng, False) for _ in range(200)]
    payloads = [x for pair in zip(good, bad) for x in pair] + good[len(bad):] + bad[len(good):] + mutated
    groups, errors, n_ok = assert_batch_matches_single(payloads, decode_quantized_batch, decode_quantized,
                                                       QuantizedFrameMsg)
    assert n_ok >= len(good) and len(errors) >= len(bad)
    for g in groups:  # one M and one bit depth a group; the frames are what quantized_batch makes of the messages
        ref = quantized_batch(g.messages())
        f = g.frames
        assert f.codes.shape[1:] == ref.codes.shape[1:] and f.bits == ref.bits
        for name in ("codes", "delta", "alpha", "dither_seed", "seq", "generator"):
            a, b = np.asarray(getattr(f, name)), np.asarray(getattr(ref, name))
            if name == "generator" and a.ndim == 0:  # one name for a group of one generator, both ways
                assert b.ndim == 0, name
            assert a.dtype.kind == b.dtype.kind and np.array_equal(a, b), name
        assert f.seq.dtype == np.uint64 and f.dither_seed.dtype == np.uint64
    mixed = [g for g in groups if len(set(np.asarray(g.frames.generator).tolist())) == 2]
    assert mixed  # versions 1 and 2 in one group: each frame keeps its generator
    f = mixed[0].frames
    u = unit_dither(f.dither_seed, f.seq, f.codes.shape[1], f.generator)
    for j, m in enumerate(mixed[0].messages()):
        one = m.dither()
        assert (one is None) == (m.alpha == 0)
        assert one is None or np.array_equal(one, (f.alpha[j] * f.delta[j]) * u[j])


def test_raw_batch_decoder_equals_the_single_one():
    good = [encode_raw(RawFrameMsg(f"s{i % 3}", 2**64 - 1 - i, -i, i, raw_msg((64, 512)[i % 2], i).data))
            for i in range(10)]
    good.append(good[0][:4] + b"\x02" + good[0][5:])  # raw version 2
    bad = [p for p, kind in bad_payloads() if kind.startswith("raw")] + [b"", b"QRDR"]
    rng = np.random.default_rng(5)
    mutated = [mutate(good[int(rng.integers(len(good)))], rng, False) for _ in range(100)]
    groups, errors, n_ok = assert_batch_matches_single(good + bad + mutated + [encode_quantized(quant_msg())],
                                                       decode_raw_batch, decode_raw, RawFrameMsg)
    assert n_ok >= len(good) and len(errors) >= len(bad) + 1
    assert all(g.data.dtype == np.complex64 and len({m.data.shape for m in g.messages()}) == 1 for g in groups)


def test_every_kind_of_bad_payload_gets_its_own_message():
    expected = {"short": "shorter than the 48-byte header", "magic": "magic b'XXXX'", "version": "format version 7",
                "kind": "message kind 1, expected 2", "M=0": "M=0 outside", "M large": "M=2097152 outside",
                "M huge": "M=4294967295 outside", "sensor id": "sensor id b'bad id!", "empty id": "sensor id b'\\\\x00",
                "NUL inside": "sensor id b'km\\\\x00", "non-ASCII id": "sensor id b'\\\\xff",
                "short ext": "shorter than its 64-byte header", "bits=0": "bits=0 outside",
                "bits=17": "bits=17 outside", "delta NaN": "delta=nan", "delta inf": "delta=inf",
                "delta < 0": "delta=-1.0",
                "delta huge": "delta=1.0000000150474662e\\+30 or alpha=0.5 out of range \\(0 < delta <= 1000", "alpha > 1": "alpha=2.0 out of range", "alpha NaN": "alpha=nan",
                "flag": "dithered flag 0 contradicts alpha=0.5", "length": "319 bytes, expected 320",
                "longer": "321 bytes, expected 320 for M=512 and 1 bits", "raw short": "47 bytes, shorter",
                "raw magic": "magic b'QRDX'", "raw version": "format version 3", "raw kind": "message kind 2",
                "raw id": "sensor id", "raw length": "1064 bytes, expected 1072 for M=64",
                "raw M huge": "M=4294967295 outside"}
    cases = bad_payloads()
    assert {k for _, k in cases} == set(expected)
    for payload, kind in cases:
        decoder, batch = (decode_raw, decode_raw_batch) if kind.startswith("raw") else \
            (decode_quantized, decode_quantized_batch)
        with pytest.raises(WireError, match=expected[kind]) as info:
            decoder(payload, "radar/k/x")
        assert "radar/k/x" in str(info.value) and "\n" not in str(info.value)
        groups, errors = batch([payload], ["radar/k/x"])
        assert not groups and str(errors[0][1]) == str(info.value)


def test_batch_encoders_write_the_bytes_of_the_single_ones():
    b, m = 6, 64
    ids = [f"s{i % 4}" for i in range(b)]
    heads = FrameHeaders(ids, [2**64 - 1, 0, 5, 6, 7, 2**63], [-5, 0, 1, 2, 3, 2**63 - 1], [0, 1, 2, 3, 4, 2**32 - 1])
    rng = np.random.default_rng(6)
    data = (rng.standard_normal((b, m, 2)) + 1j * rng.standard_normal((b, m, 2))).astype(np.complex64)
    raw = encode_raw_batch(heads, data)
    assert raw == [encode_raw(RawFrameMsg(ids[i], int(heads.seq[i]), int(heads.timestamp_ns[i]),
                                          int(heads.config_id[i]), data[i])) for i in range(b)]
    for bits in (1, 3, 12):
        gens = np.array([DITHER_SEEDSEQ, DITHER_COUNTER] * 3)
        q = QuantizedFrames(rng.integers(0, 1 << bits, (b, m, 2, 2)).astype(np.uint16), rng.random(b) + 0.1, bits,
                            np.array([0.0, 0.5, 1.0, 0.25, 0.0, 0.75]), np.arange(b, dtype=np.uint64) * np.uint64(2**61),
                            heads.seq, gens)
        out = encode_quantized_batch(heads, q)
        want = [encode_quantized(m_) for m_ in
                [QuantizedFrameMsg(ids[i], int(heads.seq[i]), int(heads.timestamp_ns[i]), int(heads.config_id[i]),
                                   bits, float(q.alpha[i]), float(q.delta[i]), int(q.dither_seed[i]), q.codes[i],
                                   str(gens[i])) for i in range(b)]]
        assert out == want
        one_gen = encode_quantized_batch(heads, QuantizedFrames(q.codes, q.delta, bits, 0.5, 3, heads.seq))
        assert all(p[4] == 2 for p in one_gen)  # one generator (counter) and one seed for the batch
    with pytest.raises(WireError, match="sensor_id='a/b'"):
        encode_raw_batch(FrameHeaders(["a/b"], [0], [0], [0]), data[:1])
    with pytest.raises(WireError, match="seq=-1 does not fit in uint64"):
        FrameHeaders(["a"], [-1], [0], [0])
    with pytest.raises(WireError, match="config_id=4294967296 does not fit in uint32"):
        FrameHeaders(["a", "b"], [0, 1], [0, 0], [0, 2**32])
    with pytest.raises(WireError, match="delta=1e\\+300 must be in \\(0, 1000\\]"):
        encode_quantized_batch(heads.take([0]), QuantizedFrames(q.codes[:1], np.array([1e300]), bits, 0.5, 3, [0]))
    with pytest.raises(WireError, match="alpha=1.5"):
        encode_quantized_batch(heads.take([0]), QuantizedFrames(q.codes[:1], np.array([1.0]), bits, 1.5, 3, [0]))


def test_frame_headers_take():
    h = FrameHeaders(["a", "b", "c"], [1, 2, 2**64 - 1], [4, 5, 6], [7, 8, 9])
    assert len(h) == 3
    for index in ([2, 0], np.array([False, True, True])):
        t = h.take(index)
        want = [i for i in range(3) if (index[i] if isinstance(index, np.ndarray) else i in index)]
        if isinstance(index, list):
            want = index
        assert t.sensor_id == [h.sensor_id[i] for i in want] and t.seq.tolist() == [h.seq[i] for i in want]
        assert t.seq.dtype == np.uint64 and t.timestamp_ns.dtype == np.int64 and t.config_id.dtype == np.uint32


def detections(b, k, rng):
    f = lambda: rng.uniform(-50, 50, (b, k))  # noqa: E731
    stat = f()
    stat[rng.random((b, k)) < 0.3] = np.nan  # absent statistics
    present = rng.random((b, k)) < 0.7
    present[0] = False  # a frame without targets
    return Detections(f(), f(), f(), f(), f(), np.zeros((b, k), int), stat, present)


@pytest.mark.parametrize("auto_k", [False, True])
def test_targets_batch_writes_what_to_json_writes(auto_k):
    rng = np.random.default_rng(7)
    b, k = 40, 3
    det = detections(b, k, rng)
    heads = FrameHeaders([f"s-{i % 5}" for i in range(b)], np.arange(b, dtype=np.uint64) + np.uint64(2**64 - 20),
                         np.arange(b) * 7 - 3, np.full(b, 0xDEADBEEF))
    for published in (1_795_000_000_000_000_000, np.arange(b) + 10**18):
        out = encode_targets_batch(heads, det, "cml", k, "quantized", published, auto_k)
        for i in range(b):
            pub = int(np.broadcast_to(published, (b,))[i])
            want = TargetsMsg(heads.sensor_id[i], int(heads.seq[i]), int(heads.timestamp_ns[i]),
                              int(heads.config_id[i]), "cml", k, "quantized", det.frame(i), pub, auto_k)
            assert out[i] == want.to_json()
            assert decode_targets(out[i]) == decode_targets(want.to_json())
    assert json.loads(out[0])["targets"] == []
    assert any("statistic_db" not in t for p in out for t in json.loads(p)["targets"])


def test_target_values_are_written_with_nine_significant_digits():
    values = {"range_m": 15.103920892263679, "angle_deg": -20.0, "x_m": 1e-5, "y_m": 123456789012.5,
              "amplitude": 0.30073023850161784, "statistic_db": -0.0}
    raw = TargetsMsg("s", 0, 0, 0, "pbp", 1, "quantized", [values]).to_json()
    assert raw.endswith(b'"targets":[{"range_m":15.1039209,"angle_deg":-20,"x_m":1e-05,"y_m":1.23456789e+11,'
                        b'"amplitude":0.300730239,"statistic_db":-0}]}')
    back = decode_targets(raw).targets[0]
    assert back == pytest.approx(values, rel=1e-8)  # json reads every one of them
    assert all(isinstance(v, float) for v in back.values())


def test_targets_batch_refuses_non_finite_present_targets():
    rng = np.random.default_rng(8)
    det = detections(4, 2, rng)
    heads = FrameHeaders(["a"] * 4, range(4), range(4), [1] * 4)
    det.present[2] = [True, True]
    det.y_m[2, 1] = np.inf
    det.x_m[3, 0] = np.nan
    det.present[3, 0] = False  # absent: its NaN does not matter
    with pytest.raises(ValueError, match="target field y_m=inf is not finite"):
        encode_targets_batch(heads, det, "pbp", 2, "raw", 0)
    with pytest.raises(ValueError, match="target field y_m=inf is not finite"):
        TargetsMsg("a", 2, 2, 1, "pbp", 2, "raw", det.frame(2)).to_json()
    det.y_m[2, 1] = 1.0
    assert len(encode_targets_batch(heads, det, "pbp", 2, "raw", 0)) == 4


def test_sensor_id_rule_is_one_rule():
    """The byte-level checks of a header's sensor id (single frame: bytes; batch: arrays)
    agree with check_sensor_id on the NUL-stripped text, for ids of random bytes."""
    from pipeline.wire import check_sensor_id
    from radar_driver.limits import sensor_id_fields_bad as _sensor_id_bad

    rng = np.random.default_rng(9)
    alphabet = np.frombuffer(b"\0\0\0aZ9_-./ \xff\x80", dtype=np.uint8)
    fields = alphabet[rng.integers(0, alphabet.size, (3000, 16))]
    valid = np.frombuffer(b"aZ9_-", dtype=np.uint8)
    fields[::2] = valid[rng.integers(0, valid.size, (1500, 16))]  # half of them of valid bytes, NUL-padded
    fields[::2][np.arange(16) >= rng.integers(0, 17, (1500, 1))] = 0
    batch = _sensor_id_bad(fields)
    for field, bad in zip(fields, batch):
        raw = field.tobytes()
        try:
            check_sensor_id(raw.rstrip(b"\0").decode("ascii"))
            want = False
        except (UnicodeDecodeError, WireError):
            want = True
        assert _sensor_id_bad(raw) == bad == want, raw
    assert 1000 < int((~batch).sum()) < 2000


def test_a_group_of_one_generator_names_it_once():
    """Frames that all have one dither generator decode with that one name (dither() then
    regenerates the batch in one call); its dither is bit for bit the per-frame one."""
    for gen in (DITHER_COUNTER, DITHER_SEEDSEQ):
        msgs = [quant_msg(1, 512, 0.5, gen, 40 + i, f"s{i}", 2**40 + i) for i in range(5)]
        groups, errors = decode_quantized_batch([encode_quantized(m) for m in msgs], [f"k{i}" for i in range(5)])
        assert not errors and len(groups) == 1 and groups[0].frames.generator == gen
        want = np.stack([QuantizedFrames(m.codes[None], np.array([m.delta]), 1, np.array([m.alpha]),
                                         np.array([m.dither_seed], dtype=np.uint64),
                                         np.array([m.seq], dtype=np.uint64), np.array([gen])).dither()[0]
                         for m in msgs])
        assert np.array_equal(groups[0].frames.dither(), want)
    mixed = [quant_msg(1, 512, 0.5, (DITHER_COUNTER, DITHER_SEEDSEQ)[i % 2], 40 + i, f"s{i}") for i in range(4)]
    groups, _ = decode_quantized_batch([encode_quantized(m) for m in mixed], [f"k{i}" for i in range(4)])
    assert np.asarray(groups[0].frames.generator).tolist() == [m.generator for m in mixed]
