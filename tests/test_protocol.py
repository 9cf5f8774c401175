import time

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from radar_driver.errors import RadarError
from radar_driver.profile import DEFAULT_PROFILE, profile_from_dict, resolve_profile
from radar_driver.protocol import (
    PREFIX_LEN,
    Done,
    Gbye,
    Gnfd,
    Init,
    OtherMessage,
    ProtocolError,
    Radc,
    Resp,
    StreamDecoder,
    decode,
    decode_payload,
    encode,
)


LAYOUT = DEFAULT_PROFILE.radc


def _words(seed=0):
    """Words of one RADC in the default profile: (receivers 2, chirps 1, samples 256, I/Q)."""
    return np.random.default_rng(seed).integers(0, 4096, (2, 1, 256, 2)).astype(np.uint16)


def test_exact_bytes_of_commands_and_answers():
    assert encode(Init(3)) == b"INIT\x04\x00\x00\x00\x03\x00\x00\x00"
    assert encode(Gnfd(0x01)) == b"GNFD\x04\x00\x00\x00\x01\x00\x00\x00"
    assert encode(Gbye()) == b"GBYE\x00\x00\x00\x00"
    # RESP: 1-byte payload, length 1, padded to 4 with zeros as the K-MD2 does
    assert encode(Resp(2)) == b"RESP\x01\x00\x00\x00\x02\x00\x00\x00"
    assert encode(Resp(2), pad=False) == b"RESP\x01\x00\x00\x00\x02"
    assert encode(Done(0x01020304)) == b"DONE\x04\x00\x00\x00\x04\x03\x02\x01"


def test_radc_layout_of_the_default_profile():
    # for each receiver 256 I words then 256 Q words, uint16 little-endian
    w = np.full((2, 1, 256, 2), 2048, np.uint16)
    w[0, 0, 0, 0], w[0, 0, 0, 1], w[1, 0, 255, 0], w[1, 0, 1, 1] = 1, 2, 3, 4095
    b = encode(Radc(w))
    assert b[:8] == b"RADC\x00\x08\x00\x00" and len(b) == 8 + 2048
    p = b[8:]
    assert p[0:2] == b"\x01\x00"  # rx1 I[0]
    assert p[512:514] == b"\x02\x00"  # rx1 Q[0]
    assert p[1024 + 510 : 1024 + 512] == b"\x03\x00"  # rx2 I[255]
    assert p[1536 + 2 : 1536 + 4] == b"\xff\x0f"  # rx2 Q[1]
    assert LAYOUT.payload_len == 2048
    assert decode(b).words.shape == (2, 1, 256, 2)
    assert_array_equal(decode(b).words, w)


def test_radc_layout_of_the_cube_profile():
    # 3 receivers x 256 chirps x 256 samples, I and Q interleaved, uint16 little-endian
    cube = resolve_profile("kmd2-cube256")
    lay = cube.radc
    assert lay.payload_len == 786_432
    w = np.full(lay.words_shape, 2048, np.uint16)
    w[0, 0, 0] = (1, 2)  # rx1 chirp 0 sample 0: I, Q
    w[2, 255, 255, 1] = 4095  # rx3 last chirp last sample Q
    w[1, 3, 7, 0] = 9
    b = encode(Radc(w, lay))
    p = b[8:]
    assert p[0:4] == b"\x01\x00\x02\x00"
    assert p[-2:] == b"\xff\x0f"
    assert p[((1 * 256 + 3) * 256 + 7) * 4 : ((1 * 256 + 3) * 256 + 7) * 4 + 2] == b"\x09\x00"
    assert decode(b, cube) == Radc(w, lay)
    d = StreamDecoder(cube)
    assert d.feed(encode(Resp(0)) + b + encode(Done(3))) == [Resp(0), Radc(w, lay), Done(3)]
    # a RADC of one profile is garbage to the other
    assert StreamDecoder().feed(b + encode(Done(4))) == [Done(4)]


def test_adc_conversion_is_unit_full_scale():
    w = np.full((2, 1, 256, 2), 2048, np.uint16)
    w[0, 0, 5, 0] = 4095  # rx1 I[5]
    w[1, 0, 7, 1] = 0  # rx2 Q[7]
    s = LAYOUT.to_complex(w)
    assert s.shape == (1, 256, 2)
    assert s[0, 5, 0] == pytest.approx(2047 / 2048)
    assert s[0, 7, 1] == pytest.approx(-1j)
    assert_array_equal(LAYOUT.from_complex(s), w)
    x = np.random.default_rng(1).uniform(-0.9, 0.9, (3, 256, 2)) * np.exp(1j)
    assert_allclose(LAYOUT.to_complex(LAYOUT.from_complex(x)), x, atol=np.sqrt(2) * 0.5 / 2048 * 1.0001)  # half an LSB on I and on Q
    assert_array_equal(LAYOUT.round_trip(x), LAYOUT.to_complex(LAYOUT.from_complex(x)))
    assert LAYOUT.from_complex(np.full((1, 256, 2), 5 + 5j)).max() == 4095  # clipped


@pytest.mark.parametrize("msg", [Init(4), Gnfd(5), Gbye(), Resp(6), Done(2**32 - 1), Radc(_words()),
                                 OtherMessage(b"PDAT", b"\x01\x02\x03\x04\x05")])
def test_round_trip(msg):
    assert decode(encode(msg)) == msg
    assert decode(encode(msg, pad=False)) == msg
    d = StreamDecoder()
    assert d.feed(encode(msg)) == [msg]


def test_length_counting_the_padding_is_tolerated():
    assert decode(b"RESP\x04\x00\x00\x00\x05\x00\x00\x00") == Resp(5)
    d = StreamDecoder()
    assert d.feed(b"RESP\x04\x00\x00\x00\x05\x00\x00\x00" + encode(Done(9))) == [Resp(5), Done(9)]
    assert d.stats.skipped_bytes == 0


@pytest.mark.parametrize(
    "data, fragment",
    [
        (b"RESP\x01", "shorter than the 8-byte header"),
        (b"ABCD\x00\x00\x00\x00", "unknown header"),
        (b"DONE\x04\x00\x00\x00\x01", "declares 4 payload bytes, 1 present"),
        (b"DONE\x08\x00\x00\x00" + bytes(8), "payload of 8 bytes; expected 4..4"),
        (b"RADC\x00\x08\x00\x00" + b"\xff" * 2048, r"RADC word 0 is 65535, beyond the 12-bit ADC range \[0, 4095\]"),
        (b"RESP\x01\x00\x00\x00\x00\x07", "not padding"),
    ],
)
def test_decode_errors_say_what_and_where(data, fragment):
    with pytest.raises(ProtocolError, match=fragment) as info:
        decode(data)
    assert isinstance(info.value, RadarError)


def test_stream_decoder_any_chunking():
    msgs = [Resp(0), Radc(_words(1)), Done(1), Resp(0), Radc(_words(2)), Done(2)]
    stream = b"".join(encode(m) for m in msgs)
    rng = np.random.default_rng(0)
    for _ in range(20):
        d = StreamDecoder()
        out, i = [], 0
        while i < len(stream):
            n = int(rng.integers(1, 300))
            out += d.feed(stream[i : i + n])
            i += n
        assert out == msgs and d.stats.skipped_bytes == 0 and d.pending() == 0


def test_garbage_is_skipped_counted_and_the_next_message_is_intact():
    d = StreamDecoder()
    garbage = b"\x13\x37noise RAD\x00\xffDON"
    out = d.feed(garbage + encode(Radc(_words(3))) + b"xyz" + encode(Done(4)))
    assert out == [Radc(_words(3)), Done(4)]
    assert d.stats.skipped_bytes == len(garbage) + 3
    assert d.stats.resyncs == 2


def test_truncated_message_is_dropped_and_the_next_one_decoded():
    whole = encode(Radc(_words(4)))
    d = StreamDecoder()
    out = d.feed(whole[:700] + encode(Done(5)) + encode(Resp(0)) + whole + encode(Done(6)))
    # the cut RADC swallows what follows until its length is reached, fails the 12-bit
    # check, and the decoder resyncs on the headers inside it
    assert out == [Done(5), Resp(0), Radc(_words(4)), Done(6)]
    assert d.stats.invalid == 1 and d.stats.skipped_bytes == 700


def test_implausible_lengths_are_garbage():
    d = StreamDecoder()
    assert d.feed(b"RADC\x10\x00\x00\x00" + encode(Done(1))) == [Done(1)]
    assert d.stats.skipped_bytes == 8


def test_memory_is_bounded_on_endless_garbage():
    d = StreamDecoder()
    rng = np.random.default_rng(5)
    for _ in range(200):
        d.feed(rng.integers(0, 256, 5000, dtype=np.uint8).tobytes())
        assert d.pending() <= 8 + 2048 + 3
    assert d.feed(b"\x00" * 16 + encode(Done(3)))[-1] == Done(3)


def test_fuzz_random_and_mutated_streams():
    """Thousands of random and mutated streams in random chunks: the streaming decoder
    never raises and never stalls, decode() raises nothing but ProtocolError."""
    rng = np.random.default_rng(2026)
    valid = [encode(m) for m in (Resp(0), Radc(_words(7)), Done(11), Init(1), Gnfd(1), Gbye(), Resp(3))]
    t0 = time.monotonic()
    cases = 0
    while cases < 3000 and time.monotonic() - t0 < 60:
        kind = cases % 3
        if kind == 0:
            stream = rng.integers(0, 256, int(rng.integers(0, 3000)), dtype=np.uint8).tobytes()
        else:
            parts = [valid[i] for i in rng.integers(0, len(valid), int(rng.integers(1, 6)))]
            stream = bytearray(b"".join(parts))
            for _ in range(int(rng.integers(1, 8))):  # flips, inserts, deletes
                op, pos = int(rng.integers(0, 3)), int(rng.integers(0, max(1, len(stream))))
                if op == 0 and stream:
                    stream[pos] ^= 1 << int(rng.integers(0, 8))
                elif op == 1:
                    stream[pos:pos] = rng.integers(0, 256, int(rng.integers(1, 16)), dtype=np.uint8).tobytes()
                else:
                    del stream[pos : pos + int(rng.integers(1, 32))]
            stream = bytes(stream)
        d = StreamDecoder()
        i = 0
        while i < len(stream):
            n = int(rng.integers(1, 512))
            for m in d.feed(stream[i : i + n]):
                assert type(m) in (Resp, Radc, Done, Init, Gnfd, Gbye, OtherMessage)
            i += n
        assert d.pending() <= 8 + 2048 + 3
        try:
            decode(stream)
        except ProtocolError:
            pass
        cases += 1
    assert cases >= 1000, f"only {cases} fuzz cases ran in 60 s"


# -- resync: every accepted payload validated, linear work -------------------------------------------
def _ramps(count, seed=0):
    """(messages, bytes) of ``count`` ramps as the sensor answers GNFD: RADC then DONE."""
    msgs = []
    for i in range(count):
        msgs += [Radc(_words(seed + i)), Done(i)]
    return msgs, b"".join(encode(m) for m in msgs)


def _feed(decoder, data, chunk=None):
    """All messages of ``data`` fed in pieces of ``chunk`` bytes (None: at once)."""
    step = chunk or max(1, len(data))
    return [m for i in range(0, len(data), step) for m in decoder.feed(data[i : i + step])]


@pytest.mark.parametrize("chunk", [None, 1, 7, 64, 4096])
def test_a_stray_rmrd_claiming_16_kib_does_not_swallow_the_ramps_after_it(chunk):
    msgs, ramps = _ramps(10)
    d = StreamDecoder()
    out = _feed(d, b"RMRD" + (16384).to_bytes(4, "little") + ramps, chunk)
    assert out == msgs  # all 10 ramps, not 3
    assert d.stats.invalid == 1 and d.stats.skipped_bytes == 8 and d.stats.resyncs == 1 and d.pending() == 0
    assert d.stats.last_error.startswith("RMRD declares 16384 payload bytes but a RADC header starts 0 bytes")


@pytest.mark.parametrize("chunk", [None, 5, 4096])
@pytest.mark.parametrize("prefix", [b"ZZZZ" + (1 << 31).to_bytes(4, "little"),  # unknown header, huge length
                                    b"PDAT" + (4096).to_bytes(4, "little") + b"\x01\x02\x03",  # known, uninterpreted
                                    b"TDAT" + (40).to_bytes(4, "little"),  # ends inside the first RADC
                                    b"RADC" + (2048).to_bytes(4, "little")])  # refused at its first word
def test_a_header_that_claims_the_frames_after_it_does_not_swallow_them(prefix, chunk):
    msgs, ramps = _ramps(10, seed=20)
    d = StreamDecoder()
    assert _feed(d, prefix + ramps, chunk) == msgs
    assert d.stats.skipped_bytes == len(prefix) and d.pending() == 0


@pytest.mark.parametrize("chunk", [None, 3, 100])
def test_frames_the_driver_does_not_interpret_are_passed_on_whole(chunk):
    """An RMRD or PDAT whose payload holds no plausible header is a message, header-like
    bytes with implausible lengths included; so is one that ends just before the next."""
    rmrd = OtherMessage(b"RMRD", bytes(range(256)) * 16 + b"DONE\xff\xff\xff\xffRADC\x00\x00\x01\x00")
    pdat = OtherMessage(b"PDAT", b"RES")  # unpadded length 3, zero padding
    msgs, ramps = _ramps(3, seed=30)
    stream = encode(rmrd) + ramps[:2068] + encode(pdat) + ramps[2068:]
    d = StreamDecoder()
    assert _feed(d, stream, chunk) == [rmrd] + msgs[:2] + [pdat] + msgs[2:]
    assert d.stats.skipped_bytes == 0 and d.stats.invalid == 0


def test_a_valid_radc_holding_header_like_words_is_taken_whole():
    """With 15-bit words a RADC may hold the bytes of a DONE header with a plausible length:
    the RADC's own validation decides, the header inside it does not."""
    prof = profile_from_dict({"name": "wide", "radc": {"adc_bits": 15, "offset": 16384}})
    words = np.full(prof.radc.words_shape, 16384, np.uint16)
    words[0, 0, 10:16, 0] = np.frombuffer(encode(Done(7)), "<u2")  # I words "DO", "NE", 4, 0, 7, 0: all < 2^15
    radc = Radc(words, prof.radc)
    assert encode(Done(7)) in encode(radc)
    stream = encode(radc) + encode(Done(8))
    for prefix, chunk in ((b"", None), (b"xx", None), (b"garbage RAD", 1), (b"", 64)):
        d = StreamDecoder(prof)
        assert _feed(d, prefix + stream, chunk) == [radc, Done(8)]
        assert d.stats.skipped_bytes == len(prefix)


def _garbage_kinds(size, seed=0):
    """Adversarial garbage of ``size`` bytes, by name: header-like everywhere, nothing valid."""
    def rep(unit):
        return (unit * (size // len(unit) + 1))[:size]

    rng = np.random.default_rng(seed)
    return {
        "random": rng.integers(0, 256, size, dtype=np.uint8).tobytes(),
        "radc headers": rep(b"RADC\x00\x08\x00\x00"),  # plausible length, payload fails at once
        "radc failing late": rep(b"RADC\x00\x08\x00\x00" + bytes(2040) + b"\xff\xff"),
        "rmrd headers": rep(b"RMRD\x00\x40\x00\x00"),  # stray headers inside each other
        "resp bad padding": rep(b"RESP\x04\x00\x00\x00\x00\xff\xff\xff"),
        "truncated headers": rep(b"RADRESDONGNFDONRMRPDATDA"),
        "all headers": rep(b"".join(DEFAULT_PROFILE.plausible_length())),
        "implausible lengths": rep(b"DONE\xff\xff\xff\xff"),
    }


def test_resync_work_is_linear_in_the_bytes_fed():
    """The bytes examined (stats.scanned_bytes) grow like the bytes fed, at once or in 4 KiB
    chunks: 1 MiB costs 16 times 64 KiB, not 256 times (the old resync rescanned the
    buffer per skipped byte: minutes per MiB)."""
    small, big = _garbage_kinds(64 << 10), _garbage_kinds(1 << 20)
    for name in small:
        for chunk in (None, 4096):
            work = []
            for data in (small[name], big[name]):
                d = StreamDecoder()
                _feed(d, data, chunk)
                assert d.stats.bytes_in == len(data) and d.pending() <= PREFIX_LEN + 2048 + 3
                assert d.stats.skipped_bytes + d.pending() == len(data), name
                assert d.stats.scanned_bytes <= 3 * len(data) + 64, (name, chunk)
                work.append(d.stats.scanned_bytes)
            assert work[1] / work[0] <= 16 * 1.1, (name, chunk, work)


def test_waiting_for_a_long_payload_does_not_rescan_it():
    """A cube RADC (768 KiB) and a 16 KiB RMRD fed in small pieces: each new byte is
    examined a bounded number of times, not the whole pending payload per piece."""
    cube = resolve_profile("kmd2-cube256")
    w = np.random.default_rng(3).integers(0, 4096, cube.radc.words_shape).astype(np.uint16)
    rmrd = OtherMessage(b"RMRD", bytes(16384))
    for prof, msgs, chunk in ((cube, [Radc(w, cube.radc), Done(1)], 4096), (DEFAULT_PROFILE, [rmrd, Done(2)], 64)):
        data = b"xyz" + b"".join(encode(m) for m in msgs)
        d = StreamDecoder(prof)
        assert _feed(d, data, chunk) == msgs
        assert d.stats.scanned_bytes <= 3 * len(data), prof.name


def test_fuzz_garbage_then_valid_frames():
    """Seeded, bounded: random and adversarial garbage (random bytes, headers with random
    lengths, cut and mutated frames), 16 zero bytes, then valid frames, in random chunks:
    the decoder never raises and decodes every valid frame after the garbage."""
    rng = np.random.default_rng(12)
    names = list(DEFAULT_PROFILE.plausible_length()) + [b"ZZZZ", b"RAD", b"DON"]
    t0 = time.monotonic()
    cases = 0
    while cases < 300 and time.monotonic() - t0 < 60:
        parts = []
        for _ in range(int(rng.integers(1, 12))):
            kind = int(rng.integers(0, 4))
            if kind == 0:
                parts.append(rng.integers(0, 256, int(rng.integers(1, 300)), dtype=np.uint8).tobytes())
            elif kind == 1:  # a header with a length of any size, plausible or not
                n = int(rng.choice([rng.integers(0, 8), rng.integers(0, 20000), 2048, 16384, rng.integers(0, 2**32)]))
                parts.append(names[int(rng.integers(0, len(names)))] + n.to_bytes(4, "little"))
            else:  # a valid frame, cut or mutated
                b = bytearray(encode([Radc(_words(cases)), Done(cases), Resp(1), OtherMessage(b"PDAT", b"abc")]
                                     [int(rng.integers(0, 4))]))
                if kind == 2:
                    b = b[: int(rng.integers(1, len(b)))]
                else:
                    b[int(rng.integers(0, len(b)))] ^= 1 << int(rng.integers(0, 8))
                parts.append(bytes(b))
        frames = _ramps(2, seed=cases)[0] + [Resp(0), OtherMessage(b"TDAT", bytes(range(40)))]
        stream = b"".join(parts) + bytes(16) + b"".join(encode(m) for m in frames)
        d = StreamDecoder()
        out, i = [], 0
        while i < len(stream):
            n = int(rng.integers(1, 3000))
            out += d.feed(stream[i : i + n])
            i += n
        assert out[-len(frames):] == frames, cases
        assert d.pending() == 0 and d.stats.scanned_bytes <= 3 * len(stream) + 64
        cases += 1
    assert cases >= 100, f"only {cases} fuzz cases ran in 60 s"


def _reference_decode(data, prof):
    """The decoder's rules, by brute force on a whole stream: (messages, skipped bytes,
    refused candidates, resyncs, bytes pending)."""
    lengths, lay = prof.plausible_length(), prof.radc
    limits = np.iinfo(np.dtype(lay.dtype))
    radc_checked = lay.min_word > limits.min or lay.max_word < limits.max
    prefixes = {h[:i] for h in lengths for i in range(1, 5)}
    end = len(data)
    cands = [(p, data[p : p + 4], int.from_bytes(data[p + 4 : p + 8], "little")) for p in range(end - 7)]
    cands = [(p, h, n) for p, h, n in cands if h in lengths and lengths[h][0] <= n <= lengths[h][1]]

    def status(p, h, n):
        stop = p + 8 + n
        if h == b"RADC" and radc_checked:
            words = np.frombuffer(data, lay.dtype, max(0, (min(stop, p + 8 + lay.payload_len, end) - p - 8) // 2), p + 8)
            if ((words < lay.min_word) | (words > lay.max_word)).any():
                return "refused"
        elif h == b"RESP" and stop <= end and any(data[p + 9 : stop]):
            return "refused"
        elif h not in (b"INIT", b"GNFD", b"GBYE", b"DONE", b"RESP"):  # uninterpreted: no candidate inside
            if any(p + 8 <= q < stop for q, _, _ in cands):
                return "refused"
            if any(data[q : q + 4] in prefixes for q in range(max(p + 8, end - 7), min(stop, end))):
                return "waiting"  # the last bytes may start a header yet
        return "ok" if stop <= end else "waiting"

    out, cursor, stats, head = [], 0, [0, 0, 0], None  # skipped, refused, resyncs
    skipping = False
    for p, h, n in cands:
        if p < cursor:
            continue
        st = status(p, h, n)
        if st == "refused":
            stats[1] += 1
            continue
        if st == "waiting":
            head = p
            break
        if p > cursor:
            stats[0] += p - cursor
            stats[2] += not skipping
        skipping = False
        out.append(decode_payload(h, data[p + 8 : p + 8 + n], prof))
        cursor = p + 8 + n
        pad = (-n) % 4
        while pad and cursor < end and data[cursor] == 0:
            cursor, pad = cursor + 1, pad - 1
    if head is None:
        head = next((q for q in range(max(cursor, end - 7), end) if data[q : q + 4] in prefixes), end)
    if head > cursor:
        stats[0] += head - cursor
        stats[2] += not skipping
    return out, stats[0], stats[1], stats[2], end - head


def test_decoding_equals_the_rules_by_brute_force_however_the_bytes_are_cut():
    """Seeded, bounded: random streams of frames, stray headers with plausible lengths,
    cut frames, zeros and noise, in five profiles (12-bit blocks, 15-bit, 16-bit signed:
    a RADC it cannot check is treated like an uninterpreted frame, big-endian with an
    extra frame, 6-bit), fed at once, in small and random pieces: the messages and the
    counters equal a brute-force application of the rules."""
    profiles = [DEFAULT_PROFILE,
                profile_from_dict({"name": "w15", "radc": {"adc_bits": 15, "offset": 16384, "samples": 16}}),
                profile_from_dict({"name": "s16", "radc": {"adc_bits": 16, "word": "int16le", "offset": 0,
                                                           "samples": 16}}),
                profile_from_dict({"name": "be", "radc": {"word": "uint16be", "samples": 16},
                                   "lengths": {"RMRD": [4, 64], "PDAT": [0, 40], "XY12": [2, 30]}}),
                profile_from_dict({"name": "b6", "radc": {"adc_bits": 6, "offset": 32, "samples": 8}})]
    rng = np.random.default_rng(7)
    t0, cases = time.monotonic(), 0
    while cases < 250 and time.monotonic() - t0 < 60:
        prof = profiles[cases % len(profiles)]
        lay, lengths = prof.radc, prof.plausible_length()
        heads = list(lengths)
        opaque = [h for h in heads if h not in (b"INIT", b"GNFD", b"GBYE", b"RESP", b"DONE", b"RADC")]
        parts = []
        for _ in range(int(rng.integers(1, 25 if cases % 4 else 120))):
            r = int(rng.integers(0, 7))
            if r == 0:
                parts.append(rng.integers(0, 256, int(rng.integers(1, 40)), dtype=np.uint8).tobytes())
            elif r == 1:  # a header, mostly with a plausible length
                h = heads[int(rng.integers(0, len(heads)))]
                lo, hi = lengths[h]
                n = int(rng.integers(lo, min(hi, 3000) + 1)) if rng.random() < 0.8 else int(rng.integers(0, 2**32))
                parts.append(h + n.to_bytes(4, "little"))
            elif r == 2:
                parts.append(encode(Radc(rng.integers(lay.min_word, lay.max_word + 1, lay.words_shape), lay)))
            elif r == 3:
                m = [Done(int(rng.integers(0, 9))), Resp(int(rng.integers(0, 3))), Gbye(), Init(1)][int(rng.integers(0, 4))]
                parts.append(encode(m, pad=bool(rng.random() < 0.7)))
            elif r == 4:
                data = rng.integers(0, 256, int(rng.integers(4, 30)), dtype=np.uint8).tobytes()
                parts.append(encode(OtherMessage(opaque[int(rng.integers(0, len(opaque)))], data)))
            elif r == 5:
                parts.append(bytes(int(rng.integers(1, 6))))
            else:  # the last parts, cut
                b = b"".join(parts[-2:]) or b"RADC"
                parts.append(b[: int(rng.integers(0, len(b)))])
        stream = b"".join(parts)
        expected = _reference_decode(stream, prof)
        for chunk in (None, 1, 3, 17, 200, 0):
            d = StreamDecoder(prof)
            if chunk == 0:  # random pieces
                out, i = [], 0
                while i < len(stream):
                    n = int(rng.integers(1, 600))
                    out += d.feed(stream[i : i + n])
                    i += n
            else:
                out = _feed(d, stream, chunk)
            st = d.stats
            assert (out, st.skipped_bytes, st.invalid, st.resyncs, d.pending()) == expected, (cases, prof.name, chunk)
        cases += 1
    assert cases >= 100, f"only {cases} cases ran in 60 s"
