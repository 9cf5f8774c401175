"""The binary wire formats: raw and quantized frames (byte layouts in docs/wire-formats.md).

Compact, little-endian, behind one 48-byte common header (magic, version, kind, bits,
flags, seq, timestamp_ns, config_id, M, sensor_id). One writer and one reader per format,
both for batches: :func:`encode_raw_batch` / :func:`encode_quantized_batch` write B frames,
:func:`decode_raw_batch` / :func:`decode_quantized_batch` parse many payloads at once
(grouped by length, headers read through a structured numpy dtype, every field checked
vectorized, the codes of a group unpacked in one call); the single-frame codecs
(:func:`encode_raw`, :func:`decode_raw`, ...) are these called with one frame.

Checked once, at the edge: a decoder checks every header field and the length where
bytes become arrays and returns typed batches (:class:`FrameHeaders` with
:class:`RawGroup` / :class:`QuantizedGroup`); :class:`FrameHeaders` checks what it is
built from; code downstream trusts them. Every failure is a :class:`WireError`.

The version of a quantized frame names its dither generator (pipeline.dsp.quantize): 1 =
``"seedseq"``, 2 = ``"counter"``. Raw frames are written as version 1 and read as 1 or 2.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from functools import lru_cache
from typing import Sequence

import numpy as np

from radar_driver import limits
from radar_driver.limits import MAX_BITS, SENSOR_ID_MAX, bits_bad, sensor_id_fields_bad

from pipeline.errors import ParameterError, WireError
from pipeline.dsp.quantize import (DITHER_COUNTER, DITHER_SEEDSEQ, MAX_DELTA, QuantizedFrames, as_int_array, check_alpha,
                       check_generator, check_uint64, pack_codes_unchecked, unpack_codes_unchecked)

MAGIC = b"QRDR"
#: format version of each dither generator (quantized frames); raw frames are written as 1
GENERATOR_VERSIONS = {DITHER_SEEDSEQ: 1, DITHER_COUNTER: 2}
_GENERATOR_OF_VERSION = {v: g for g, v in GENERATOR_VERSIONS.items()}
VERSIONS = (1, 2)  # what the decoders read
RAW_VERSION = 1
KIND_RAW = 1
KIND_QUANTIZED = 2
FLAG_DITHERED = 0x01

#: the frame layout table (docs/wire-formats.md): each header field's name, struct code and
#: numpy dtype, in order; COMMON, QUANT_EXT and the decoders' dtypes all come from it
COMMON_FIELDS = (("magic", "4s", ("u1", (4,))), ("version", "B", "u1"), ("kind", "B", "u1"), ("bits", "B", "u1"),
                 ("flags", "B", "u1"), ("seq", "Q", "<u8"), ("timestamp_ns", "q", "<i8"), ("config_id", "I", "<u4"),
                 ("m", "I", "<u4"), ("sensor_id", "16s", ("u1", (16,))))
#: the quantized frame's extension of the common header
QUANT_EXT_FIELDS = (("dither_seed", "Q", "<u8"), ("alpha", "f", "<f4"), ("delta", "f", "<f4"))
#: common header: magic, version, kind, bits, flags, seq, timestamp_ns, config_id, M, sensor_id
COMMON = struct.Struct("<" + "".join(code for _, code, _ in COMMON_FIELDS))
#: quantized extension: dither_seed, alpha, delta
QUANT_EXT = struct.Struct("<" + "".join(code for _, code, _ in QUANT_EXT_FIELDS))
#: the same headers as numpy structured dtypes (packed, little-endian)
COMMON_DTYPE = np.dtype([(name, dt) for name, _, dt in COMMON_FIELDS])
QUANT_DTYPE = np.dtype([(name, dt) for name, _, dt in COMMON_FIELDS + QUANT_EXT_FIELDS])
assert all(struct.calcsize("<" + code) == np.dtype(dt).itemsize for _, code, dt in COMMON_FIELDS + QUANT_EXT_FIELDS)
assert (COMMON_DTYPE.itemsize, QUANT_DTYPE.itemsize) == (COMMON.size, COMMON.size + QUANT_EXT.size)
HEADER_LEN = COMMON.size  # 48
QUANT_HEADER_LEN = COMMON.size + QUANT_EXT.size  # 64
MAX_M = 1 << 20
#: where a frame's sequence number is, from the layout table (what :func:`peek_seq` reads)
SEQ_OFFSET = COMMON_DTYPE.fields["seq"][1]
_SEQ = struct.Struct("<" + dict((name, code) for name, code, _ in COMMON_FIELDS)["seq"])


def peek_seq(payload) -> int | None:
    """The sequence number of a frame's bytes, read before the frame is decoded (an
    intake's count of gaps), at the header field the layout table places; None when
    ``payload`` does not start with a frame header. The one other reading of a header
    than the decoders' (:func:`decode_raw_batch`, ...), from the same table."""
    if len(payload) < HEADER_LEN or payload[:4] != MAGIC:
        return None
    return _SEQ.unpack_from(payload, SEQ_OFFSET)[0]


def check_sensor_id(sensor_id: str) -> str:
    """Sensor ids: 1-16 ASCII characters from [A-Za-z0-9_-] (they are zenoh key chunks);
    the rule of :mod:`radar_driver.limits`, failing as a WireError."""
    return limits.check_sensor_id(sensor_id, WireError)


@dataclass(frozen=True, eq=False)
class RawFrameMsg:
    """A full-resolution frame Gamma: ``data`` (M, 2) complex64, full-scale units."""

    sensor_id: str
    seq: int
    timestamp_ns: int
    config_id: int
    data: np.ndarray

    def __eq__(self, other: object) -> bool:
        return (isinstance(other, RawFrameMsg) and self.header() == other.header()
                and np.array_equal(self.data, other.data))

    def header(self) -> tuple:
        return (self.sensor_id, self.seq, self.timestamp_ns, self.config_id)


@dataclass(frozen=True, eq=False)
class QuantizedFrameMsg:
    """A b-bit quantized frame: ``codes`` (M, 2, 2) unsigned (measurement, antenna, I/Q),
    step ``delta``, dither scale ``alpha``, ``dither_seed`` and the dither ``generator``
    (the dither of frame ``seq`` is reproducible from them, see pipeline.dsp.quantize; the
    format version says the generator)."""

    sensor_id: str
    seq: int
    timestamp_ns: int
    config_id: int
    bits: int
    alpha: float
    delta: float
    dither_seed: int
    codes: np.ndarray
    generator: str = DITHER_COUNTER

    @property
    def dithered(self) -> bool:
        return self.alpha > 0

    def dither(self) -> np.ndarray | None:
        """The dither xi = alpha delta u this frame was quantized with, regenerated from
        (dither_seed, seq): (M, 2) complex; None when the frame is not dithered."""
        xi = quantized_batch([self]).dither()
        return None if xi is None else xi[0]

    def __eq__(self, other: object) -> bool:
        return (isinstance(other, QuantizedFrameMsg) and self.header() == other.header()
                and np.array_equal(self.codes, other.codes))

    def header(self) -> tuple:
        return (self.sensor_id, self.seq, self.timestamp_ns, self.config_id, self.bits, self.alpha,
                self.delta, self.dither_seed, self.generator)


def int_field(values, name: str, dtype: str, n: int | None) -> np.ndarray:
    """A header field of B frames as a (B,) array of ``dtype`` (an integer type); every
    value must fit in it."""
    if type(values) is list and (n is None or len(values) == n) and all(type(x) is int for x in values):
        try:  # the usual case: Python ints (the checks below when one does not fit)
            return np.array(values, dtype=dtype)
        except OverflowError:
            pass
    a = as_int_array(values)
    if a.ndim != 1 or (n is not None and a.shape[0] != n):
        raise WireError(f"{name} must have shape ({'B' if n is None else n},), got {a.shape}")
    if a.dtype == dtype:
        return a
    info = _iinfo(dtype)
    if a.dtype.kind not in "iu":
        bad = [x for x in a.tolist()
               if isinstance(x, bool) or not isinstance(x, (int, np.integer)) or not info.min <= x <= info.max]
    elif a.size and (a.min() < info.min or a.max() > info.max):
        bad = a[(a < info.min) | (a > info.max)].tolist()
    else:
        bad = []
    if bad:
        raise WireError(f"{name}={bad[0]!r} does not fit in {dtype}")
    return a.astype(dtype)


@lru_cache(maxsize=None)
def _iinfo(dtype: str) -> np.iinfo:
    return np.iinfo(dtype)


@dataclass(frozen=True, eq=False)
class FrameHeaders:
    """The per-frame header fields of B frames: ``sensor_id`` (B strings), ``seq`` (B,)
    uint64, ``timestamp_ns`` (B,) int64 (sensor time, ns since the epoch), ``config_id``
    (B,) uint32. Built from any integer sequences and checked when built (each distinct
    sensor id once); a value out of range is a WireError. The decoders build them from
    fields they checked already (:meth:`checked`), and :meth:`take` subsets without checks."""

    sensor_id: list[str]
    seq: np.ndarray
    timestamp_ns: np.ndarray
    config_id: np.ndarray

    def __post_init__(self) -> None:
        ids = list(self.sensor_id)
        for sid in set(ids):
            check_sensor_id(sid)
        object.__setattr__(self, "sensor_id", ids)
        object.__setattr__(self, "seq", int_field(self.seq, "seq", "uint64", len(ids)))
        object.__setattr__(self, "timestamp_ns", int_field(self.timestamp_ns, "timestamp_ns", "int64", len(ids)))
        object.__setattr__(self, "config_id", int_field(self.config_id, "config_id", "uint32", len(ids)))

    @classmethod
    def checked(cls, sensor_id: list[str], seq: np.ndarray, timestamp_ns: np.ndarray,
                config_id: np.ndarray) -> "FrameHeaders":
        """Headers of fields already checked (valid ids, arrays of the field dtypes)."""
        h = object.__new__(cls)
        for name, value in zip(("sensor_id", "seq", "timestamp_ns", "config_id"),
                               (sensor_id, seq, timestamp_ns, config_id)):
            object.__setattr__(h, name, value)
        return h

    def __len__(self) -> int:
        return len(self.sensor_id)

    def take(self, index) -> "FrameHeaders":
        """The headers of the frames ``index`` (an int index array or a (B,) bool mask)."""
        idx = np.asarray(index)
        idx = np.flatnonzero(idx) if idx.dtype == bool else idx.astype(np.intp).ravel()
        return FrameHeaders.checked([self.sensor_id[i] for i in idx.tolist()], self.seq[idx],
                                    self.timestamp_ns[idx], self.config_id[idx])


def _each(value, n: int) -> list:
    """One value for the batch or (n,) values, as a list of n Python values."""
    if isinstance(value, str) or np.ndim(value) == 0:
        return [value.item() if isinstance(value, np.generic) else value] * n
    return np.asarray(value).tolist()


@dataclass(frozen=True, eq=False)
class QuantizedGroup:
    """Decoded quantized frames of one M and one bit depth: ``index`` (B,) are their
    positions in the list of payloads given to the decoder."""

    headers: FrameHeaders
    frames: QuantizedFrames
    index: np.ndarray

    def messages(self) -> list[QuantizedFrameMsg]:
        h, q, n = self.headers, self.frames, len(self.headers)
        return [QuantizedFrameMsg(sid, seq, ts, cid, q.bits, alpha, delta, seed, codes, gen)
                for sid, seq, ts, cid, alpha, delta, seed, codes, gen in zip(
                    h.sensor_id, h.seq.tolist(), h.timestamp_ns.tolist(), h.config_id.tolist(), _each(q.alpha, n),
                    q.delta.tolist(), _each(np.asarray(q.dither_seed, dtype=np.uint64), n), q.codes,
                    _each(q.generator, n))]


@dataclass(frozen=True, eq=False)
class RawGroup:
    """Decoded raw frames of one M, the typed raw batch: ``data`` (B, M, 2) complex64;
    ``index`` (B,) are their positions in the list of payloads given to the decoder."""

    headers: FrameHeaders
    data: np.ndarray
    index: np.ndarray

    def messages(self) -> list[RawFrameMsg]:
        h = self.headers
        return [RawFrameMsg(sid, seq, ts, cid, data) for sid, seq, ts, cid, data in zip(
            h.sensor_id, h.seq.tolist(), h.timestamp_ns.tolist(), h.config_id.tolist(), self.data)]


def _one_header(msg) -> FrameHeaders:
    return FrameHeaders([msg.sensor_id], [msg.seq], [msg.timestamp_ns], [msg.config_id])


# -- encoding ---------------------------------------------------------------------------------
def _payloads(headers: FrameHeaders, dtype: np.dtype, kind: int, bits: int, version, m: int, body: np.ndarray):
    """B frames of M = ``m``: returns their (B, length) bytes, header of ``dtype`` then
    ``body`` (B, n) uint8, and the header records (B,) over them, the fields every frame
    has written."""
    if not 1 <= m <= MAX_M:
        raise WireError(f"M={m} must be in [1, {MAX_M}]")
    b, head_len = len(headers), dtype.itemsize
    out = np.empty((b, head_len + body.shape[1]), dtype=np.uint8)
    out[:, :head_len] = 0
    out[:, head_len:] = body
    rec = out.reshape(-1).view(_padded(dtype, out.shape[1]))
    rec["magic"] = _MAGIC_WORD
    rec["version"] = version
    rec["kind"] = kind
    rec["bits"] = bits
    rec["m"] = m
    rec["seq"] = headers.seq
    rec["timestamp_ns"] = headers.timestamp_ns
    rec["config_id"] = headers.config_id
    rec["sensor_id"] = np.array(headers.sensor_id, dtype=f"S{SENSOR_ID_MAX}").view(np.uint8).reshape(-1, SENSOR_ID_MAX)
    return out, rec


def _split(out: np.ndarray) -> list[bytes]:
    """One payload per row of (B, length) bytes."""
    buf, n = out.tobytes(), out.shape[1]
    return [buf] if out.shape[0] == 1 else [buf[i:i + n] for i in range(0, len(buf), n)]


def encode_raw_batch(headers: FrameHeaders, data: np.ndarray) -> list[bytes]:
    """Raw frame payloads (format version 1) of B frames: ``data`` (B, M, 2) complex
    (written as complex64)."""
    data = np.asarray(data)
    if data.ndim != 3 or data.shape[2] != 2 or data.shape[0] != len(headers):
        raise WireError(f"raw frame data must have shape ({len(headers)}, M, 2), got {data.shape}")
    body = np.ascontiguousarray(data, dtype="<c8").reshape(len(headers), -1).view(np.uint8)
    return _split(_payloads(headers, COMMON_DTYPE, KIND_RAW, 0, RAW_VERSION, data.shape[1], body)[0])


def encode_raw(msg: RawFrameMsg) -> bytes:
    """One raw frame payload: :func:`encode_raw_batch` of one frame."""
    data = np.asarray(msg.data)
    if data.ndim != 2:
        raise WireError(f"raw frame data must have shape (M, 2), got {data.shape}")
    return encode_raw_batch(_one_header(msg), data[None])[0]


def _per_frame_floats(values, name: str, n: int) -> np.ndarray:
    """One float or one per frame as a () or (B,) float array."""
    if isinstance(values, (bool, str, bytes)):
        raise WireError(f"{name}={values!r} must be a number or one per frame")
    try:
        a = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise WireError(f"{name}={values!r} must be a number or one per frame") from None
    if a.ndim > 1 or (a.ndim == 1 and a.shape[0] != n):
        raise WireError(f"{name} must be one value or one per frame ({n}), got shape {a.shape}")
    return a


def encode_quantized_batch(headers: FrameHeaders, q: QuantizedFrames) -> list[bytes]:
    """Quantized frame payloads of B frames (the quantizer's output for them): each of
    format version 1 or 2 after its dither generator."""
    b = len(headers)
    codes = np.asarray(q.codes)
    try:
        bits = limits.check_bits(q.bits, WireError)
        if codes.ndim != 4 or codes.shape[0] != b or codes.shape[2:] != (2, 2):
            raise WireError(f"codes must have shape ({b}, M, 2, 2), got {codes.shape}")
        if not np.issubdtype(codes.dtype, np.integer):
            raise WireError(f"codes must be integers, got dtype {codes.dtype}")
        alpha = _per_frame_floats(q.alpha, "alpha", b)
        ok = (alpha >= 0) & (alpha <= 1)
        if np.count_nonzero(ok) != ok.size:
            check_alpha(float(alpha[~ok][0]))
        delta = _per_frame_floats(q.delta, "delta", b)
        with np.errstate(over="ignore"):
            d32 = delta.astype(np.float32)
        ok = (d32 > 0) & (d32 <= MAX_DELTA)  # (NaN is not)
        if np.count_nonzero(ok) != ok.size:
            raise WireError(f"delta={float(delta[~ok][0])!r} must be in (0, {MAX_DELTA:g}] (as a float32)")
        seeds = check_uint64(q.dither_seed, "dither_seed")
        generator = check_generator(q.generator, b)
    except ParameterError as exc:
        raise WireError(str(exc)) from None
    if seeds.size not in (1, b):
        raise WireError(f"dither_seed has {seeds.size} values, expected 1 or one per frame ({b})")
    if isinstance(generator, str):
        version = GENERATOR_VERSIONS[generator]
    else:
        version = np.where(generator == DITHER_SEEDSEQ, GENERATOR_VERSIONS[DITHER_SEEDSEQ],
                           GENERATOR_VERSIONS[DITHER_COUNTER])
    out, head = _payloads(headers, QUANT_DTYPE, KIND_QUANTIZED, bits, version, codes.shape[1],
                          pack_codes_unchecked(codes, bits))
    head["flags"] = np.where(alpha > 0, FLAG_DITHERED, 0)
    head["dither_seed"] = seeds
    head["alpha"] = alpha
    head["delta"] = d32
    return _split(out)


def encode_quantized(msg: QuantizedFrameMsg) -> bytes:
    """One quantized frame payload: :func:`encode_quantized_batch` of one frame."""
    codes = np.asarray(msg.codes)
    if codes.ndim != 3:
        raise WireError(f"codes must have shape (M, 2, 2), got {codes.shape}")
    frame = QuantizedFrames(codes[None], msg.delta, msg.bits, msg.alpha, msg.dither_seed, msg.seq, msg.generator)
    return encode_quantized_batch(_one_header(msg), frame)[0]


# -- decoding ---------------------------------------------------------------------------------
_NAMES = {KIND_RAW: "raw frame", KIND_QUANTIZED: "quantized frame"}
_MAGIC_WORD = np.frombuffer(MAGIC, dtype="<u4")[0]
_VERSION_BAD = np.ones(256, dtype=bool)
_VERSION_BAD[list(VERSIONS)] = False


def frame_size(kind: int, m, bits=0):
    """The length of a frame of ``kind`` with M = ``m`` (and ``bits``), bytes: scalars or
    (n,) arrays."""
    if kind == KIND_RAW:
        return HEADER_LEN + m * 16
    return QUANT_HEADER_LEN + (m * 4 * bits + 7) // 8


def _faults(f: dict, kind: int, size: int):
    """The checks of the headers ``f`` (fields by name as (n,) arrays, with ``magic_bad``
    and ``sensor_id_bad`` computed) of frames of length ``size``, in the order they apply:
    yields (n,) bools 'bad'. The number of a check (from 1) selects its message in
    :func:`_fault_text`; a quantized frame shorter than its header yields no checks of the
    extension."""
    m = f["m"]  # uint32; every check an (n,) array
    yield f["magic_bad"]
    yield _VERSION_BAD.take(f["version"])
    yield f["kind"] != kind
    yield m - 1 >= MAX_M  # (M = 0 wraps to 2**32 - 1)
    yield f["sensor_id_bad"]
    if kind == KIND_RAW:
        yield size != frame_size(kind, m)
        return
    yield np.full(m.shape, size < QUANT_HEADER_LEN)
    if size < QUANT_HEADER_LEN:
        return
    bits, alpha, delta = f["bits"], f["alpha"], f["delta"]
    yield bits_bad(bits)
    yield ~((delta > 0) & (delta <= MAX_DELTA) & (alpha >= 0) & (alpha <= 1))  # NaN: bad
    yield ((f["flags"] & FLAG_DITHERED) != 0) != (alpha > 0)
    yield size != frame_size(kind, m, bits)


def _fault_text(number: int, f: dict, kind: int, size: int, source: str) -> str:
    """The message of check ``number`` of :func:`_faults` failing for one frame (fields as
    Python scalars; magic and sensor_id as bytes)."""
    name = _NAMES[kind]
    texts = [f"magic {f['magic']!r}, expected {MAGIC!r} (not a qradar frame)",
             f"format version {f['version']} unsupported (this build reads {' and '.join(map(str, VERSIONS))})",
             f"message kind {f['kind']}, expected {kind}",
             f"M={f['m']} outside [1, {MAX_M}]",
             f"sensor id {f['sensor_id']!r} is not valid"]
    if kind == KIND_RAW:
        texts.append(f"{size} bytes, expected {frame_size(kind, f['m'])} for M={f['m']}")
    else:
        texts.append(f"{size} bytes, shorter than its {QUANT_HEADER_LEN}-byte header")
        if number > len(texts):
            bits, alpha, delta = f["bits"], float(f["alpha"]), float(f["delta"])
            texts += [f"bits={bits} outside [1, {MAX_BITS}]",
                      f"delta={delta!r} or alpha={alpha!r} out of range (0 < delta <= {MAX_DELTA:g}, "
                      f"0 <= alpha <= 1)",
                      f"dithered flag {f['flags'] & FLAG_DITHERED} contradicts alpha={alpha}",
                      f"{size} bytes, expected {frame_size(kind, f['m'], bits)} "
                      f"for M={f['m']} and {bits} bits"]
    return f"{name} from {source}: {texts[number - 1]}"


def _short(kind: int, source: str, size: int) -> WireError:
    return WireError(f"{_NAMES[kind]} from {source}: {size} bytes, shorter than the {HEADER_LEN}-byte header")


def _by_length(payloads: Sequence[bytes], sources: Sequence[str]):
    """Payloads grouped by length: yields (length, positions (n,) in the list, (n, length)
    uint8 array of their bytes)."""
    if len(sources) != len(payloads):
        raise WireError(f"{len(payloads)} payloads but {len(sources)} sources")
    lengths = list(map(len, payloads))
    if not lengths:
        return
    if min(lengths) == max(lengths):  # the usual case: one length, the payloads in order
        yield lengths[0], _positions(len(lengths)), np.frombuffer(b"".join(payloads), dtype=np.uint8).reshape(
            len(lengths), lengths[0])
        return
    lengths = np.array(lengths, dtype=np.int64)
    order = np.argsort(lengths, kind="stable")
    sizes, starts = np.unique(lengths[order], return_index=True)
    for size, idx in zip(sizes.tolist(), np.split(order, starts[1:])):
        buf = np.frombuffer(b"".join([payloads[i] for i in idx.tolist()]), dtype=np.uint8)
        yield size, idx, buf.reshape(idx.size, size)


@lru_cache(maxsize=16)
def _positions(n: int) -> np.ndarray:
    """0 ... n-1, read-only (the positions of a batch of one length)."""
    idx = np.arange(n)
    idx.flags.writeable = False
    return idx


@lru_cache(maxsize=64)
def _padded(dtype: np.dtype, itemsize: int) -> np.dtype:
    """``dtype`` followed by padding up to ``itemsize`` bytes, its magic read as one
    little-endian word (compared with one call)."""
    formats = [np.dtype("<u4") if n == "magic" else dtype.fields[n][0] for n in dtype.names]
    return np.dtype({"names": dtype.names, "formats": formats,
                     "offsets": [dtype.fields[n][1] for n in dtype.names], "itemsize": itemsize})


def _parse_batch(payloads: Sequence[bytes], sources: Sequence[str], kind: int):
    """Frames grouped by length, every check applied vectorized: returns the list
    (position, WireError) of the bad frames, and (positions (n,), (n,) header records,
    (n, length) bytes) of the good frames of each length."""
    errors: list[tuple[int, WireError]] = []
    good = []
    for size, idx, rows in _by_length(payloads, sources):
        if size < HEADER_LEN:
            errors += [(i, _short(kind, sources[i], size)) for i in idx.tolist()]
            continue
        dtype = QUANT_DTYPE if kind == KIND_QUANTIZED and size >= QUANT_HEADER_LEN else COMMON_DTYPE
        rec = rows.reshape(-1).view(_padded(dtype, size))
        # m and bits unsigned: a frame size that overflows uint32 is one whose M is out of range already
        f = {name: rec[name] for name in ("version", "kind", "bits", "flags", "m", "alpha", "delta")
             if name in dtype.names}
        f["magic_bad"] = rec["magic"] != _MAGIC_WORD
        f["sensor_id_bad"] = sensor_id_fields_bad(rec["sensor_id"])
        faults = np.array(list(_faults(f, kind, size)))  # (checks, n)
        if not np.count_nonzero(faults):  # the usual case: all good
            good.append((idx, rec, rows))
            continue
        bad = faults.any(axis=0)
        fail = np.flatnonzero(bad)
        first = faults[:, fail].argmax(axis=0) + 1  # the first check each bad frame fails
        for j, number in zip(fail.tolist(), first.tolist()):
            one = {name: rec[name][j].item() for name in dtype.names if name not in ("magic", "sensor_id")}
            one.update(magic=rows[j, :4].tobytes(), sensor_id=rows[j, 32:32 + SENSOR_ID_MAX].tobytes())
            errors.append((int(idx[j]), WireError(_fault_text(number, one, kind, size, sources[idx[j]]))))
        ok = ~bad
        if ok.any():
            good.append((idx[ok], rec[ok], rows[ok]))
    errors.sort(key=lambda e: e[0])
    return errors, good


def _headers_of(rec: np.ndarray) -> FrameHeaders:
    ids = [sid.decode("ascii") for sid in rec["sensor_id"].copy().view(f"S{SENSOR_ID_MAX}").ravel().tolist()]
    return FrameHeaders.checked(ids, rec["seq"].copy(), rec["timestamp_ns"].copy(), rec["config_id"].copy())


def decode_raw_batch(payloads: Sequence[bytes], sources: Sequence[str]) -> tuple[list[RawGroup], list[tuple[int, WireError]]]:
    """Raw frame payloads (bytes-like) with the source of each (e.g. its zenoh key): the
    good frames in groups of one M, and (position, WireError) of each bad payload."""
    errors, good = _parse_batch(payloads, sources, KIND_RAW)
    groups = []
    for idx, rec, rows in good:
        m = (rows.shape[1] - HEADER_LEN) // 16
        data = rows[:, HEADER_LEN:].copy().view("<c8").reshape(-1, m, 2)  # aligned, writable complex64
        groups.append(RawGroup(_headers_of(rec), data, idx))
    groups.sort(key=lambda g: g.index[0])
    return groups, errors


def _generators(version: np.ndarray) -> str | np.ndarray:
    """The dither generator of frames of format ``version`` (n,): one name when they all
    have the same (the usual batch: QuantizedFrames.dither then regenerates the batch's
    dither in one call, no per-generator masks and copies), else (n,) names."""
    seedseq = version == GENERATOR_VERSIONS[DITHER_SEEDSEQ]
    if not seedseq.any():
        return DITHER_COUNTER
    return DITHER_SEEDSEQ if seedseq.all() else np.where(seedseq, DITHER_SEEDSEQ, DITHER_COUNTER)


def decode_quantized_batch(payloads: Sequence[bytes],
                           sources: Sequence[str]) -> tuple[list[QuantizedGroup], list[tuple[int, WireError]]]:
    """Quantized frame payloads (bytes-like) with the source of each: the good frames in
    groups of one M and one bit depth (each frame's dither generator from its format
    version: one name for the group when its frames share it), and (position, WireError) of each bad payload."""
    errors, good = _parse_batch(payloads, sources, KIND_QUANTIZED)
    groups = []
    for idx, rec, rows in good:
        # frames of one length may still differ in (M, bits): one group, one unpack call, each
        keys = rec["m"].astype(np.int64) * (MAX_BITS + 1) + rec["bits"] if len(rec) > 1 else None
        if keys is None or (keys == keys[0]).all():  # the usual case: one (M, bits)
            split = [(int(rec["m"][0]) * (MAX_BITS + 1) + int(rec["bits"][0]), slice(None))]
        else:
            split = [(key, np.flatnonzero(keys == key)) for key in np.unique(keys).tolist()]
        for key, sel in split:
            m, bits = divmod(key, MAX_BITS + 1)
            r, body = rec[sel], rows[sel, QUANT_HEADER_LEN:]
            codes = unpack_codes_unchecked(body, bits, 4 * m).reshape(len(body), m, 2, 2)
            generator = _generators(r["version"])
            frames = QuantizedFrames(codes, r["delta"].astype(float), bits, r["alpha"].astype(float),
                                     r["dither_seed"].copy(), r["seq"].copy(), generator)
            groups.append(QuantizedGroup(_headers_of(r), frames, idx[sel]))
    groups.sort(key=lambda g: g.index[0])
    return groups, errors


def _decode_one(decoder, payload: bytes, source: str):
    """The one message of ``payload`` through a batch decoder; its WireError when bad."""
    groups, errors = decoder([bytes(payload)], [source])
    if errors:
        raise errors[0][1]
    return groups[0].messages()[0]


def decode_raw(payload: bytes, source: str = "<bytes>") -> RawFrameMsg:
    """One raw frame: :func:`decode_raw_batch` of one payload."""
    return _decode_one(decode_raw_batch, payload, source)


def decode_quantized(payload: bytes, source: str = "<bytes>") -> QuantizedFrameMsg:
    """One quantized frame: :func:`decode_quantized_batch` of one payload."""
    return _decode_one(decode_quantized_batch, payload, source)


def quantized_batch(msgs: list[QuantizedFrameMsg]) -> QuantizedFrames:
    """Frames of one M and one bit depth as one batch (B = len(msgs)) for the decoders;
    alpha, dither_seed and the generator may differ per frame (frames of several sensors,
    recordings of either version). One generator for every frame is one name (as the
    batch decoder gives it: the dither is then regenerated in one call)."""
    if not msgs or len({(m.codes.shape, m.bits) for m in msgs}) != 1:
        raise WireError("a batch needs at least one frame, all of one M and one bit depth")
    gens = [m.generator for m in msgs]
    return QuantizedFrames(
        codes=np.stack([m.codes for m in msgs]), delta=np.array([m.delta for m in msgs]), bits=msgs[0].bits,
        alpha=np.array([m.alpha for m in msgs]), dither_seed=np.array([m.dither_seed for m in msgs], dtype=np.uint64),
        seq=np.array([m.seq for m in msgs], dtype=np.uint64),
        generator=gens[0] if gens.count(gens[0]) == len(gens) else np.array(gens))
