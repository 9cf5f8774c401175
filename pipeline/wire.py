"""Wire formats of the zenoh stream (byte layouts in docs/wire-formats.md).

Raw and quantized frames are compact binary, little-endian, behind one 48-byte common
header; targets, tracks and health are UTF-8 JSON objects. Every message carries the format
version, the sensor id, the sequence number, the sensor timestamp (ns) and the radar
configuration id. Decoders check everything and raise :class:`WireError` naming what
is wrong and where (the ``source``, e.g. the zenoh key).

The version of a quantized frame names its dither generator (pipeline.quantize): 1 =
``"seedseq"`` (every recording made before version 2), 2 = ``"counter"``. Raw frames are
written as version 1 and read as 1 or 2 (the layout is the same).

Batches: :func:`decode_quantized_batch` / :func:`decode_raw_batch` parse many payloads
at once (grouped by length, headers read through a structured numpy dtype, every field
checked vectorized, the codes of a group unpacked in one call) into groups of one M (and
one bit depth), and :func:`encode_quantized_batch`, :func:`encode_raw_batch`,
:func:`encode_targets_batch` write many frames; the single-frame codecs are batches of one.
"""

from __future__ import annotations

import json
import re
import struct
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, Sequence

import numpy as np

from .errors import ParameterError, WireError
from .quantize import (DITHER_COUNTER, DITHER_SEEDSEQ, MAX_BITS, MAX_DELTA, QuantizedFrames, as_int_array,
                       check_alpha, check_bits, check_generator, check_uint64, pack_codes, unpack_codes)

MAGIC = b"QRDR"
#: format version of each dither generator (quantized frames); raw frames are written as 1
GENERATOR_VERSIONS = {DITHER_SEEDSEQ: 1, DITHER_COUNTER: 2}
VERSIONS = (1, 2)  # what the decoders read
RAW_VERSION = 1
KIND_RAW = 1
KIND_QUANTIZED = 2
FLAG_DITHERED = 0x01

#: the frame layout table (docs/wire-formats.md): each header field's name, struct code and
#: numpy dtype, in order; COMMON, QUANT_EXT and the batch decoders' dtypes all come from it
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
SENSOR_ID_MAX = 16
JSON_VERSION = 1
#: the topics of a sensor's keys ``<prefix>/<sensor>/<topic>``; this is the one list of them
TOPICS = ("raw", "quantized", "targets", "tracks", "health")
#: bytes a sensor id may hold
_ID_BYTES = np.zeros(256, dtype=bool)
_ID_BYTES[list(b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_-")] = True


#: valid sensor ids seen lately (checked once each; cleared when it holds _KNOWN_IDS_MAX)
_known_ids: set[str] = set()
_KNOWN_IDS_MAX = 1 << 16


def check_sensor_id(sensor_id: str) -> str:
    """Sensor ids: 1-16 ASCII characters from [A-Za-z0-9_-] (they are zenoh key chunks)."""
    if type(sensor_id) is str and sensor_id in _known_ids:
        return sensor_id
    ok = isinstance(sensor_id, str) and 1 <= len(sensor_id) <= SENSOR_ID_MAX and all(
        c.isascii() and (c.isalnum() or c in "_-") for c in sensor_id)
    if not ok:
        raise WireError(f"sensor_id={sensor_id!r} must be 1-{SENSOR_ID_MAX} characters of [A-Za-z0-9_-]")
    if len(_known_ids) >= _KNOWN_IDS_MAX:
        _known_ids.clear()
    _known_ids.add(sensor_id)
    return sensor_id


def forget_sensor_id(sensor_id: str) -> None:
    """Drop a sensor id from the cache of checked ids (a node forgot the sensor): the
    next :func:`check_sensor_id` of it checks it again, and an expired id is not kept."""
    _known_ids.discard(sensor_id)


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
    (the dither of frame ``seq`` is reproducible from them, see pipeline.quantize; the
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


def _int_field(values, name: str, dtype: str, n: int | None) -> np.ndarray:
    """A header field of B frames as a (B,) array of ``dtype`` (an integer type); every
    value must fit in it."""
    a = as_int_array(values)
    if a.ndim != 1 or (n is not None and a.shape[0] != n):
        raise WireError(f"{name} must have shape ({'B' if n is None else n},), got {a.shape}")
    if a.dtype == dtype:
        return a
    info = np.iinfo(dtype)
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


@dataclass(frozen=True, eq=False)
class FrameHeaders:
    """The per-frame header fields of B frames: ``sensor_id`` (B strings), ``seq`` (B,)
    uint64, ``timestamp_ns`` (B,) int64 (sensor time, ns since the epoch), ``config_id``
    (B,) uint32. Built from any integer sequences; a value out of range is a WireError."""

    sensor_id: list[str]
    seq: np.ndarray
    timestamp_ns: np.ndarray
    config_id: np.ndarray

    def __post_init__(self) -> None:
        ids = list(self.sensor_id)
        object.__setattr__(self, "sensor_id", ids)
        object.__setattr__(self, "seq", _int_field(self.seq, "seq", "uint64", len(ids)))
        object.__setattr__(self, "timestamp_ns", _int_field(self.timestamp_ns, "timestamp_ns", "int64", len(ids)))
        object.__setattr__(self, "config_id", _int_field(self.config_id, "config_id", "uint32", len(ids)))

    def __len__(self) -> int:
        return len(self.sensor_id)

    def take(self, index) -> "FrameHeaders":
        """The headers of the frames ``index`` (an int index array or a (B,) bool mask)."""
        idx = np.asarray(index)
        idx = np.flatnonzero(idx) if idx.dtype == bool else idx.astype(np.intp).ravel()
        return FrameHeaders([self.sensor_id[i] for i in idx.tolist()], self.seq[idx], self.timestamp_ns[idx],
                            self.config_id[idx])

    def check_ids(self) -> None:
        """Raise a WireError if a sensor id is not valid (each distinct id checked once)."""
        for sid in set(self.sensor_id):
            check_sensor_id(sid)


@dataclass(frozen=True, eq=False)
class QuantizedGroup:
    """Decoded quantized frames of one M and one bit depth: ``index`` (B,) are their
    positions in the list of payloads given to the decoder."""

    headers: FrameHeaders
    frames: QuantizedFrames
    index: np.ndarray

    def messages(self) -> list[QuantizedFrameMsg]:
        h, q = self.headers, self.frames
        gens = np.broadcast_to(np.asarray(q.generator), (len(h),)).tolist()
        return [QuantizedFrameMsg(sid, seq, ts, cid, q.bits, alpha, delta, seed, codes, gen)
                for sid, seq, ts, cid, alpha, delta, seed, codes, gen in zip(
                    h.sensor_id, h.seq.tolist(), h.timestamp_ns.tolist(), h.config_id.tolist(),
                    np.broadcast_to(q.alpha, (len(h),)).tolist(), q.delta.tolist(),
                    np.broadcast_to(np.asarray(q.dither_seed, dtype=np.uint64), (len(h),)).tolist(), q.codes, gens)]


@dataclass(frozen=True, eq=False)
class RawGroup:
    """Decoded raw frames of one M: ``data`` (B, M, 2) complex64; ``index`` (B,) are their
    positions in the list of payloads given to the decoder."""

    headers: FrameHeaders
    data: np.ndarray
    index: np.ndarray

    def messages(self) -> list[RawFrameMsg]:
        h = self.headers
        return [RawFrameMsg(sid, seq, ts, cid, data) for sid, seq, ts, cid, data in zip(
            h.sensor_id, h.seq.tolist(), h.timestamp_ns.tolist(), h.config_id.tolist(), self.data)]


# -- encoding ---------------------------------------------------------------------------------
def _headers(headers: FrameHeaders, dtype: np.dtype, kind: int, bits: int, version, m: int) -> np.ndarray:
    """The binary headers of B frames as a (B,) structured array of ``dtype``."""
    headers.check_ids()
    if not 1 <= m <= MAX_M:
        raise WireError(f"M={m} must be in [1, {MAX_M}]")
    rec = np.zeros(len(headers), dtype=dtype)
    rec["magic"] = np.frombuffer(MAGIC, dtype=np.uint8)
    rec["version"] = version
    rec["kind"] = kind
    rec["bits"] = bits
    rec["seq"] = headers.seq
    rec["timestamp_ns"] = headers.timestamp_ns
    rec["config_id"] = headers.config_id
    rec["m"] = m
    rec["sensor_id"] = np.array(headers.sensor_id, dtype=f"S{SENSOR_ID_MAX}").view(np.uint8).reshape(-1, SENSOR_ID_MAX)
    return rec


def _split(head: np.ndarray, body: np.ndarray) -> list[bytes]:
    """One payload per frame: header records (B,) then body bytes (B, n)."""
    rows = np.concatenate([head.view(np.uint8).reshape(head.shape[0], -1), body.reshape(body.shape[0], -1)], axis=1)
    buf, n = rows.tobytes(), rows.shape[1]
    return [buf[i:i + n] for i in range(0, len(buf), n)]


def encode_raw_batch(headers: FrameHeaders, data: np.ndarray) -> list[bytes]:
    """Raw frame payloads (format version 1) of B frames: ``data`` (B, M, 2) complex
    (written as complex64)."""
    data = np.asarray(data)
    if data.ndim != 3 or data.shape[2] != 2 or data.shape[0] != len(headers):
        raise WireError(f"raw frame data must have shape ({len(headers)}, M, 2), got {data.shape}")
    head = _headers(headers, COMMON_DTYPE, KIND_RAW, 0, RAW_VERSION, data.shape[1])
    return _split(head, data.astype("<c8", copy=False).view(np.uint8))


def _common(kind: int, version: int, bits: int, flags: int, sensor_id: str, seq: int, ts: int, config_id: int,
            m: int) -> bytes:
    """The common header of one frame (the single-frame encoders)."""
    check_sensor_id(sensor_id)
    if not 0 <= seq < 2**64:
        raise WireError(f"seq={seq} does not fit in uint64")
    if not -2**63 <= ts < 2**63:
        raise WireError(f"timestamp_ns={ts} does not fit in int64")
    if not 0 <= config_id < 2**32:
        raise WireError(f"config_id={config_id} does not fit in uint32")
    if not 1 <= m <= MAX_M:
        raise WireError(f"M={m} must be in [1, {MAX_M}]")
    return COMMON.pack(MAGIC, version, kind, bits, flags, seq, ts, config_id, m, sensor_id.encode("ascii"))


def encode_raw(msg: RawFrameMsg) -> bytes:
    """One raw frame payload (format version 1); :func:`encode_raw_batch` for many."""
    data = np.asarray(msg.data)
    if data.ndim != 2 or data.shape[1] != 2:
        raise WireError(f"raw frame data must have shape (M, 2), got {data.shape}")
    head = _common(KIND_RAW, RAW_VERSION, 0, 0, msg.sensor_id, msg.seq, msg.timestamp_ns, msg.config_id,
                   data.shape[0])
    return head + data.astype("<c8", copy=False).tobytes()


def _per_frame_floats(values, name: str, n: int) -> np.ndarray:
    """One float or one per frame as a (B,) float array."""
    a = np.asarray(values, dtype=float)
    if a.ndim > 1 or (a.ndim == 1 and a.shape[0] != n):
        raise WireError(f"{name} must be one value or one per frame ({n}), got shape {a.shape}")
    return np.broadcast_to(a, (n,))


def encode_quantized_batch(headers: FrameHeaders, q: QuantizedFrames) -> list[bytes]:
    """Quantized frame payloads of B frames (the quantizer's output for them): each of
    format version 1 or 2 after its dither generator."""
    b = len(headers)
    codes = np.asarray(q.codes)
    try:
        bits = check_bits(q.bits)
        if codes.ndim != 4 or codes.shape[0] != b or codes.shape[2:] != (2, 2):
            raise WireError(f"codes must have shape ({b}, M, 2, 2), got {codes.shape}")
        alpha = _per_frame_floats(q.alpha, "alpha", b)
        bad = alpha[~((alpha >= 0) & (alpha <= 1))]
        if bad.size:
            check_alpha(float(bad[0]))
        delta = _per_frame_floats(q.delta, "delta", b)
        with np.errstate(over="ignore"):
            d32 = delta.astype(np.float32)
        bad = delta[~(np.isfinite(d32) & (d32 > 0) & (d32 <= MAX_DELTA))]
        if bad.size:
            raise WireError(f"delta={float(bad[0])!r} must be in (0, {MAX_DELTA:g}] (as a float32)")
        seeds = check_uint64(q.dither_seed, "dither_seed")
        generator = check_generator(q.generator, b)
        packed = pack_codes(codes, bits)
    except ParameterError as exc:
        raise WireError(str(exc)) from None
    if seeds.size not in (1, b):
        raise WireError(f"dither_seed has {seeds.size} values, expected 1 or one per frame ({b})")
    if isinstance(generator, str):
        version = GENERATOR_VERSIONS[generator]
    else:
        version = np.where(generator == DITHER_SEEDSEQ, GENERATOR_VERSIONS[DITHER_SEEDSEQ],
                           GENERATOR_VERSIONS[DITHER_COUNTER])
    head = _headers(headers, QUANT_DTYPE, KIND_QUANTIZED, bits, version, codes.shape[1])
    head["flags"] = np.where(alpha > 0, FLAG_DITHERED, 0)
    head["dither_seed"] = seeds
    head["alpha"] = alpha
    head["delta"] = d32
    return _split(head, packed)


def encode_quantized(msg: QuantizedFrameMsg) -> bytes:
    """One quantized frame payload, format version 1 or 2 after ``msg.generator``;
    :func:`encode_quantized_batch` for many."""
    codes = np.asarray(msg.codes)
    try:
        bits = check_bits(msg.bits)
        check_alpha(msg.alpha)
        version = GENERATOR_VERSIONS[check_generator(msg.generator)]
    except ParameterError as exc:
        raise WireError(str(exc)) from None
    if codes.ndim != 3 or codes.shape[1:] != (2, 2):
        raise WireError(f"codes must have shape (M, 2, 2), got {codes.shape}")
    with np.errstate(over="ignore"):
        d32 = np.float32(msg.delta)
    if not (np.isfinite(d32) and 0 < d32 <= MAX_DELTA):
        raise WireError(f"delta={msg.delta!r} must be in (0, {MAX_DELTA:g}] (as a float32)")
    if not 0 <= msg.dither_seed < 2**64:
        raise WireError(f"dither_seed={msg.dither_seed} does not fit in uint64")
    flags = FLAG_DITHERED if msg.alpha > 0 else 0
    head = _common(KIND_QUANTIZED, version, bits, flags, msg.sensor_id, msg.seq, msg.timestamp_ns, msg.config_id,
                   codes.shape[0])
    ext = QUANT_EXT.pack(msg.dither_seed, msg.alpha, msg.delta)
    return head + ext + pack_codes(codes[None], bits)[0].tobytes()


# -- decoding ---------------------------------------------------------------------------------
# One list of checks and messages serves the single-frame decoders (header fields as Python
# scalars, read with struct) and the batch decoders (fields as (n,) arrays, read through the
# structured dtypes): the checks use only operators both understand.
_NAMES = {KIND_RAW: "raw frame", KIND_QUANTIZED: "quantized frame"}
_MAGIC_BYTES = np.frombuffer(MAGIC, dtype=np.uint8)
_VERSION_BAD = np.ones(256, dtype=bool)
_VERSION_BAD[list(VERSIONS)] = False
#: a valid NUL-padded sensor id field (the rule of :func:`check_sensor_id`, in bytes)
_SENSOR_ID_FIELD = re.compile(rb"[A-Za-z0-9_-]{1,16}\0*")


def _sensor_id_bad(sid) -> bool | np.ndarray:
    """Whether a NUL-padded 16-byte sensor id field is not a valid id: bytes, or (n, 16)
    uint8 -> (n,) bool (valid: 1-16 bytes of [A-Za-z0-9_-], then NULs only)."""
    if isinstance(sid, bytes):
        return _SENSOR_ID_FIELD.fullmatch(sid) is None
    nonzero = sid != 0
    length = np.where(nonzero.any(axis=1), SENSOR_ID_MAX - np.argmax(nonzero[:, ::-1], axis=1), 0)
    inside = np.arange(SENSOR_ID_MAX) < length[:, None]
    return (length < 1) | np.any(~_ID_BYTES[sid] & inside, axis=1)


def _faults(f: dict, kind: int, size: int):
    """The checks of a frame's header ``f`` (fields by name: scalars, or (n,) arrays for a
    batch, with ``magic_bad`` and ``sensor_id_bad`` computed) and length ``size``, in the
    order they apply: yields 'bad' (a bool, or (n,) bools). The number of a check (from 1)
    selects its message in :func:`_fault_text`; a quantized frame shorter than its header
    yields no checks of the extension."""
    m = f["m"]
    yield f["magic_bad"]
    yield _VERSION_BAD[f["version"]]
    yield f["kind"] != kind
    yield (m < 1) | (m > MAX_M)
    yield f["sensor_id_bad"]
    if kind == KIND_RAW:
        yield size != HEADER_LEN + m * 16
        return
    yield size < QUANT_HEADER_LEN
    if size < QUANT_HEADER_LEN:
        return
    bits, alpha, delta = f["bits"], f["alpha"], f["delta"]
    yield (bits < 1) | (bits > MAX_BITS)
    yield (delta != delta) | (delta <= 0) | (delta > MAX_DELTA) | (alpha != alpha) | (alpha < 0) | (alpha > 1)
    yield ((f["flags"] & FLAG_DITHERED) != 0) != (alpha > 0)
    yield size != QUANT_HEADER_LEN + (m * 4 * bits + 7) // 8


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
        texts.append(f"{size} bytes, expected {HEADER_LEN + f['m'] * 16} for M={f['m']}")
    else:
        texts.append(f"{size} bytes, shorter than its {QUANT_HEADER_LEN}-byte header")
        if number > len(texts):
            bits, alpha, delta = f["bits"], float(f["alpha"]), float(f["delta"])
            texts += [f"bits={bits} outside [1, {MAX_BITS}]",
                      f"delta={delta!r} or alpha={alpha!r} out of range (0 < delta <= {MAX_DELTA:g}, "
                      f"0 <= alpha <= 1)",
                      f"dithered flag {f['flags'] & FLAG_DITHERED} contradicts alpha={alpha}",
                      f"{size} bytes, expected {QUANT_HEADER_LEN + (f['m'] * 4 * bits + 7) // 8} "
                      f"for M={f['m']} and {bits} bits"]
    return f"{name} from {source}: {texts[number - 1]}"


def _short(kind: int, source: str, size: int) -> WireError:
    return WireError(f"{_NAMES[kind]} from {source}: {size} bytes, shorter than the {HEADER_LEN}-byte header")


def _parse_one(payload: bytes, source: str, kind: int) -> dict:
    """The header fields of one frame as Python scalars, every check passed."""
    size = len(payload)
    if size < HEADER_LEN:
        raise _short(kind, source, size)
    names = [n for n, _, _ in COMMON_FIELDS]
    f = dict(zip(names, COMMON.unpack_from(payload)))
    if kind == KIND_QUANTIZED and size >= QUANT_HEADER_LEN:
        f.update(zip([n for n, _, _ in QUANT_EXT_FIELDS], QUANT_EXT.unpack_from(payload, HEADER_LEN)))
    f["magic_bad"], f["sensor_id_bad"] = f["magic"] != MAGIC, _sensor_id_bad(f["sensor_id"])
    for number, bad in enumerate(_faults(f, kind, size), 1):
        if bad:
            raise WireError(_fault_text(number, f, kind, size, source))
    f["sensor_id"] = f["sensor_id"].rstrip(b"\0").decode("ascii")
    return f


def decode_raw(payload: bytes, source: str = "<bytes>") -> RawFrameMsg:
    payload = bytes(payload)
    f = _parse_one(payload, source, KIND_RAW)
    data = np.frombuffer(payload, dtype="<c8", offset=HEADER_LEN).reshape(f["m"], 2).astype(np.complex64)
    return RawFrameMsg(f["sensor_id"], f["seq"], f["timestamp_ns"], f["config_id"], data)


def decode_quantized(payload: bytes, source: str = "<bytes>") -> QuantizedFrameMsg:
    payload = bytes(payload)
    f = _parse_one(payload, source, KIND_QUANTIZED)
    m, bits = f["m"], f["bits"]
    packed = np.frombuffer(payload, dtype=np.uint8, offset=QUANT_HEADER_LEN)[None]
    codes = unpack_codes(packed, bits, m * 4)[0].reshape(m, 2, 2)
    return QuantizedFrameMsg(f["sensor_id"], f["seq"], f["timestamp_ns"], f["config_id"], bits, float(f["alpha"]),
                             float(f["delta"]), f["dither_seed"], codes, _GENERATOR_OF_VERSION[f["version"]])


_GENERATOR_OF_VERSION = {v: g for g, v in GENERATOR_VERSIONS.items()}


def _by_length(payloads: Sequence[bytes], sources: Sequence[str]):
    """Payloads grouped by length: yields (length, positions (n,) in the list, (n, length)
    uint8 array of their bytes)."""
    if len(sources) != len(payloads):
        raise WireError(f"{len(payloads)} payloads but {len(sources)} sources")
    lengths = np.fromiter(map(len, payloads), dtype=np.int64, count=len(payloads))
    if not lengths.size:
        return
    if lengths.min() == lengths.max():  # the usual case: one length
        split = [(int(lengths[0]), np.arange(lengths.size))]
    else:
        order = np.argsort(lengths, kind="stable")
        sizes, starts = np.unique(lengths[order], return_index=True)
        split = zip(sizes.tolist(), np.split(order, starts[1:]))
    for size, idx in split:
        buf = np.frombuffer(b"".join([payloads[i] for i in idx.tolist()]), dtype=np.uint8)
        yield size, idx, buf.reshape(idx.size, size)


@lru_cache(maxsize=64)
def _padded(dtype: np.dtype, itemsize: int) -> np.dtype:
    """``dtype`` followed by padding up to ``itemsize`` bytes."""
    return np.dtype({"names": dtype.names, "formats": [dtype.fields[n][0] for n in dtype.names],
                     "offsets": [dtype.fields[n][1] for n in dtype.names], "itemsize": itemsize})


def _parse_batch(payloads: Sequence[bytes], sources: Sequence[str], kind: int):
    """Frames grouped by length, every check applied vectorized: yields (positions (n,),
    (n,) header records, (n, length) bytes) of the good frames of each length; the bad
    ones go to the list ``errors`` (position, WireError) returned first."""
    errors: list[tuple[int, WireError]] = []
    good = []
    for size, idx, rows in _by_length(payloads, sources):
        if size < HEADER_LEN:
            errors += [(i, _short(kind, sources[i], size)) for i in idx.tolist()]
            continue
        dtype = QUANT_DTYPE if kind == KIND_QUANTIZED and size >= QUANT_HEADER_LEN else COMMON_DTYPE
        rec = rows.reshape(-1).view(_padded(dtype, size))
        f = {name: rec[name].astype(np.int64) for name in ("version", "kind", "bits", "flags", "m")}  # no overflow
        f.update({name: rec[name] for name in ("alpha", "delta") if name in dtype.names})
        f["magic_bad"] = np.any(rec["magic"] != _MAGIC_BYTES, axis=1)
        f["sensor_id_bad"] = _sensor_id_bad(rec["sensor_id"])
        failed = np.zeros(idx.size, dtype=np.int64)
        for number, bad in enumerate(_faults(f, kind, size), 1):
            failed[(failed == 0) & bad] = number
        for j in np.flatnonzero(failed).tolist():
            one = {name: rec[name][j].tobytes() if name in ("magic", "sensor_id") else rec[name][j].item()
                   for name in dtype.names}
            errors.append((int(idx[j]), WireError(_fault_text(int(failed[j]), one, kind, size, sources[idx[j]]))))
        ok = failed == 0
        if ok.any():
            good.append((idx[ok], rec[ok], rows[ok]))
    errors.sort(key=lambda e: e[0])
    return errors, good


def _headers_of(rec: np.ndarray) -> FrameHeaders:
    ids = rec["sensor_id"].copy().view(f"S{SENSOR_ID_MAX}").ravel().astype(f"U{SENSOR_ID_MAX}").tolist()
    return FrameHeaders(ids, rec["seq"].copy(), rec["timestamp_ns"].copy(), rec["config_id"].copy())


def decode_raw_batch(payloads: Sequence[bytes], sources: Sequence[str]) -> tuple[list[RawGroup], list[tuple[int, WireError]]]:
    """Raw frame payloads (bytes-like) with the source of each (e.g. its zenoh key): the
    good frames in groups of one M (decoded as :func:`decode_raw` decodes each), and
    (position, WireError) of each bad payload, the error :func:`decode_raw` raises for it."""
    errors, good = _parse_batch(payloads, sources, KIND_RAW)
    groups = []
    for idx, rec, rows in good:
        m = (rows.shape[1] - HEADER_LEN) // 16
        data = rows[:, HEADER_LEN:].copy().view("<c8").reshape(-1, m, 2).astype(np.complex64, copy=False)
        groups.append(RawGroup(_headers_of(rec), data, idx))
    groups.sort(key=lambda g: g.index[0])
    return groups, errors


def decode_quantized_batch(payloads: Sequence[bytes],
                           sources: Sequence[str]) -> tuple[list[QuantizedGroup], list[tuple[int, WireError]]]:
    """Quantized frame payloads (bytes-like) with the source of each: the good frames in
    groups of one M and one bit depth (each frame's dither generator from its format
    version; decoded as :func:`decode_quantized` decodes each), and (position, WireError)
    of each bad payload, the error :func:`decode_quantized` raises for it."""
    errors, good = _parse_batch(payloads, sources, KIND_QUANTIZED)
    groups = []
    for idx, rec, rows in good:
        # frames of one length may still differ in (M, bits): one group, one unpack call, each
        keys = rec["m"].astype(np.int64) * (MAX_BITS + 1) + rec["bits"]
        for key in ([int(keys[0])] if keys.min() == keys.max() else np.unique(keys).tolist()):
            sel = np.flatnonzero(keys == key)
            m, bits = divmod(key, MAX_BITS + 1)
            r = rec[sel]
            codes = unpack_codes(rows[sel, QUANT_HEADER_LEN:], bits, 4 * m).reshape(sel.size, m, 2, 2)
            generator = np.where(r["version"] == GENERATOR_VERSIONS[DITHER_SEEDSEQ], DITHER_SEEDSEQ, DITHER_COUNTER)
            frames = QuantizedFrames(codes, r["delta"].astype(float), bits, r["alpha"].astype(float),
                                     r["dither_seed"].copy(), r["seq"].copy(), generator)
            groups.append(QuantizedGroup(_headers_of(r), frames, idx[sel]))
    groups.sort(key=lambda g: g.index[0])
    return groups, errors


def quantized_batch(msgs: list[QuantizedFrameMsg]) -> QuantizedFrames:
    """Frames of one M and one bit depth as one batch (B = len(msgs)) for the decoders;
    alpha, dither_seed and the generator may differ per frame (frames of several sensors,
    recordings of either version)."""
    if not msgs or len({(m.codes.shape, m.bits) for m in msgs}) != 1:
        raise WireError("a batch needs at least one frame, all of one M and one bit depth")
    return QuantizedFrames(
        codes=np.stack([m.codes for m in msgs]), delta=np.array([m.delta for m in msgs]), bits=msgs[0].bits,
        alpha=np.array([m.alpha for m in msgs]), dither_seed=np.array([m.dither_seed for m in msgs], dtype=np.uint64),
        seq=np.array([m.seq for m in msgs], dtype=np.uint64), generator=np.array([m.generator for m in msgs]))


# -- JSON messages ---------------------------------------------------------------------------
TARGET_FIELDS = ("range_m", "angle_deg", "x_m", "y_m", "amplitude")
#: significant digits of a target value in the JSON (%.9g: 0.1 µm at 10 m, far below a
#: range bin; float32 holds 7): a quarter of the time ``repr``'s 17 digits take to write
TARGET_DIGITS = 9
#: per-target fields a target may carry (older recordings do not)
OPTIONAL_TARGET_FIELDS = ("statistic_db",)


def _target(t: dict) -> dict[str, float]:
    """A target's fields as finite floats (the optional ones when present)."""
    out = {f: float(t[f]) for f in TARGET_FIELDS}
    out.update({f: float(t[f]) for f in OPTIONAL_TARGET_FIELDS if t.get(f) is not None})
    bad = [f for f, v in out.items() if not np.isfinite(v)]
    if bad:
        raise ValueError(f"target field {bad[0]}={out[bad[0]]} is not finite")
    return out


def _uint(obj: dict, name: str, bits: int = 64) -> int:
    """A JSON integer field in [0, 2**bits)."""
    v = obj[name]
    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < 2**bits:
        raise ValueError(f"{name}={v!r} must be an integer in [0, 2**{bits})")
    return v


@dataclass(frozen=True)
class TargetsMsg:
    """Targets of one frame: each a dict with TARGET_FIELDS (and OPTIONAL_TARGET_FIELDS
    when known); ``published_ns`` is the localizer's wall clock when it published them;
    ``auto_k``: the localizer decided the count (``k`` is then the most it allows)."""

    sensor_id: str
    seq: int
    timestamp_ns: int
    config_id: int
    algo: str
    k: int
    source: str  # "quantized" or "raw"
    targets: list[dict[str, float]]
    published_ns: int = 0
    auto_k: bool = False

    def to_json(self) -> bytes:
        """Compact JSON; each target value with TARGET_DIGITS significant digits."""
        obj = {"version": JSON_VERSION, "type": "targets", "sensor_id": self.sensor_id, "seq": self.seq,
               "timestamp_ns": self.timestamp_ns, "config_id": self.config_id, "algo": self.algo,
               "K": self.k, **({"K_auto": True} if self.auto_k else {}), "source": self.source,
               "published_ns": self.published_ns}
        targets = ",".join("{" + ",".join(f'"{f}":{v:.{TARGET_DIGITS}g}' for f, v in _target(t).items()) + "}"
                           for t in self.targets)
        return (json.dumps(obj, separators=(",", ":"))[:-1] + ',"targets":[' + targets + "]}").encode()


#: the columns of a frame's target values in :func:`encode_targets_batch`
_TARGET_COLUMNS = TARGET_FIELDS + OPTIONAL_TARGET_FIELDS


@lru_cache(maxsize=256)
def _targets_template(has_statistic: tuple[bool, ...]) -> tuple[str, tuple[int, ...]]:
    """The JSON list of targets whose ``statistic_db`` is (True) or is not given, as a
    %-template of floats (TARGET_DIGITS significant digits, as to_json writes them), and the columns of the values
    (target j, field f -> j * 6 + f) it takes, in order."""
    parts, columns = [], []
    width = len(_TARGET_COLUMNS)
    for j, stat in enumerate(has_statistic):
        fields = TARGET_FIELDS + (OPTIONAL_TARGET_FIELDS if stat else ())
        parts.append("{" + ",".join(f'"{f}":%.{TARGET_DIGITS}g' for f in fields) + "}")
        columns += [j * width + _TARGET_COLUMNS.index(f) for f in fields]
    return "[" + ",".join(parts) + "]", tuple(columns)


def encode_targets_batch(headers: FrameHeaders, det, algo: str, k: int, source: str, published_ns,
                         auto_k: bool = False) -> list[bytes]:
    """Targets JSON of B frames: the bytes ``TargetsMsg(..., det.frame(i), ...).to_json()``
    writes for each frame i. ``det``: pipeline.localize.Detections of (B, K) arrays (a
    target is written where ``present``; its ``statistic_db`` when finite).
    ``published_ns``: one int or (B,). A present target with a non-finite field is a
    ValueError naming the field, as in :meth:`TargetsMsg.to_json`."""
    b = len(headers)
    cols = [np.asarray(getattr(det, f), dtype=float) for f in _TARGET_COLUMNS]
    present = np.asarray(det.present, dtype=bool)
    if present.ndim != 2 or present.shape[0] != b or any(c.shape != present.shape for c in cols):
        raise WireError(f"detections must be ({b}, K) arrays for {b} frames, got {present.shape}")
    values = np.stack(cols, axis=-1)  # (B, K, 6)
    finite = np.isfinite(values[..., :len(TARGET_FIELDS)])
    bad = present[..., None] & ~finite
    if bad.any():
        i, j, f = np.argwhere(bad)[0]
        raise ValueError(f"target field {TARGET_FIELDS[f]}={float(values[i, j, f])} is not finite")
    # the present targets of each frame first, in order
    order = np.argsort(~present, axis=1, kind="stable")
    values = np.take_along_axis(values, order[..., None], axis=1).reshape(b, -1)
    has_stat = np.take_along_axis(present & np.isfinite(cols[-1]), order, axis=1)
    count = present.sum(axis=1)
    published = _int_field(np.broadcast_to(np.asarray(published_ns), (b,)), "published_ns", "int64", b).tolist()
    quoted = {sid: json.dumps(sid).replace("%", "%%") for sid in set(headers.sensor_id)}
    head = ('{"version":%d,"type":"targets","sensor_id":%%s,"seq":%%d,"timestamp_ns":%%d,"config_id":%%d,'
            % JSON_VERSION + '"algo":' + json.dumps(algo).replace("%", "%%") + ',"K":%d' % int(k)
            + (',"K_auto":true' if auto_k else "") + ',"source":' + json.dumps(source).replace("%", "%%")
            + ',"published_ns":%d,"targets":')
    by_pattern: dict[tuple, list[int]] = {}  # (count, has_stat of the present targets) -> frames
    for i, (c, stats) in enumerate(zip(count.tolist(), has_stat.tolist())):
        by_pattern.setdefault((c, *stats[:c]), []).append(i)
    out: list[bytes] = [b""] * b
    seqs, stamps, configs = headers.seq.tolist(), headers.timestamp_ns.tolist(), headers.config_id.tolist()
    for pattern, frames in by_pattern.items():
        targets, columns = _targets_template(tuple(bool(x) for x in pattern[1:]))
        template = head + targets + "}"
        rows = values[np.ix_(frames, columns)].tolist() if columns else [[]] * len(frames)
        for i, row in zip(frames, rows):
            out[i] = (template % (quoted[headers.sensor_id[i]], seqs[i], stamps[i], configs[i], published[i],
                                  *row)).encode()
    return out


def _reject_constant(name: str):
    raise json.JSONDecodeError(f"{name} is not a number JSON allows", name, 0)


def _load_json(payload: bytes, source: str, kind: str) -> dict[str, Any]:
    try:
        obj = json.loads(bytes(payload).decode("utf-8"), parse_constant=_reject_constant)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise WireError(f"{kind} from {source}: not UTF-8 JSON ({exc})") from None
    if not isinstance(obj, dict):
        raise WireError(f"{kind} from {source}: expected a JSON object, got {type(obj).__name__}")
    if obj.get("version") != JSON_VERSION:
        raise WireError(f"{kind} from {source}: format version {obj.get('version')!r} unsupported "
                        f"(this build reads {JSON_VERSION})")
    if obj.get("type") != kind:
        raise WireError(f"{kind} from {source}: type {obj.get('type')!r}, expected {kind!r}")
    return obj


def decode_targets(payload: bytes, source: str = "<bytes>") -> TargetsMsg:
    obj = _load_json(payload, source, "targets")
    try:
        targets = [_target(t) for t in obj["targets"]]
        return TargetsMsg(check_sensor_id(obj["sensor_id"]), _uint(obj, "seq"), int(obj["timestamp_ns"]),
                          _uint(obj, "config_id", 32), str(obj["algo"]), int(obj["K"]), str(obj["source"]), targets,
                          int(obj.get("published_ns", 0)), bool(obj.get("K_auto", False)))
    except (KeyError, TypeError, ValueError, OverflowError, WireError) as exc:
        raise WireError(f"targets from {source}: missing or bad field ({exc})") from None


#: the fields of a track in the tracks JSON (pipeline.track), in order; ``track_id`` and
#: ``hits`` are integers, ``static`` a boolean, the others numbers
TRACK_FIELDS = ("track_id", "range_m", "angle_deg", "x_m", "y_m", "vx_mps", "vy_mps", "sigma_m", "age_s", "hits",
                "static")
_TRACK_FLOATS = ("range_m", "angle_deg", "x_m", "y_m", "vx_mps", "vy_mps", "sigma_m", "age_s")


def _track(t: dict) -> dict:
    """A track's fields, checked: integers >= 0, finite floats, a boolean."""
    out = {"track_id": _uint(t, "track_id"), **{f: float(t[f]) for f in _TRACK_FLOATS}, "hits": _uint(t, "hits")}
    bad = [f for f in _TRACK_FLOATS if not np.isfinite(out[f])]
    if bad:
        raise ValueError(f"track field {bad[0]}={out[bad[0]]} is not finite")
    if not isinstance(t["static"], bool):
        raise ValueError(f"static={t['static']!r} must be true or false")
    out["static"] = t["static"]
    return {f: out[f] for f in TRACK_FIELDS}


@dataclass(frozen=True)
class TracksMsg:
    """The confirmed tracks of one sensor after frame ``seq`` (pipeline.track): each a dict
    with TRACK_FIELDS; ``published_ns`` is the tracker's wall clock when it published them."""

    sensor_id: str
    seq: int
    timestamp_ns: int
    tracks: list[dict]
    published_ns: int = 0

    def to_json(self) -> bytes:
        """Compact JSON; each float with TARGET_DIGITS significant digits."""
        head = json.dumps({"version": JSON_VERSION, "type": "tracks", "sensor_id": check_sensor_id(self.sensor_id),
                           "seq": self.seq, "timestamp_ns": self.timestamp_ns, "published_ns": self.published_ns},
                          separators=(",", ":"))
        items = []
        for t in self.tracks:
            t = _track(t)
            items.append('{"track_id":%d,' % t["track_id"]
                         + ",".join(f'"{f}":{t[f]:.{TARGET_DIGITS}g}' for f in _TRACK_FLOATS)
                         + ',"hits":%d,"static":%s}' % (t["hits"], "true" if t["static"] else "false"))
        return (head[:-1] + ',"tracks":[' + ",".join(items) + "]}").encode()


def decode_tracks(payload: bytes, source: str = "<bytes>") -> TracksMsg:
    obj = _load_json(payload, source, "tracks")
    try:
        if not isinstance(obj["tracks"], list):
            raise ValueError(f"tracks must be a list, got {type(obj['tracks']).__name__}")
        tracks = [_track(t) for t in obj["tracks"]]
        ts, pub = obj["timestamp_ns"], obj["published_ns"]
        if isinstance(ts, bool) or not isinstance(ts, int) or isinstance(pub, bool) or not isinstance(pub, int):
            raise ValueError("timestamp_ns and published_ns must be integers")
        return TracksMsg(check_sensor_id(obj["sensor_id"]), _uint(obj, "seq"), ts, tracks, pub)
    except (KeyError, TypeError, ValueError, OverflowError, AttributeError, WireError) as exc:
        raise WireError(f"tracks from {source}: missing or bad field ({exc})") from None


#: health counters added in this version of the JSON (0 when a message lacks them)
HEALTH_LOSS_FIELDS = ("invalid_frames", "processing_errors", "frames_missing", "seq_resets", "worker_restarts",
                      "over_budget", "refused")


@dataclass
class HealthMsg:
    """1 Hz counters of one node for one sensor."""

    node: str
    sensor_id: str
    timestamp_ns: int
    frames_in: int = 0
    frames_out: int = 0
    drops: int = 0
    decode_errors: int = 0
    latency_ms: dict[str, float | None] = field(default_factory=lambda: {"p50": None, "p99": None})
    bytes_in_per_s: float = 0.0
    bytes_out_per_s: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)
    # failures by kind and lost frames (absent from older recordings: 0)
    invalid_frames: int = 0
    processing_errors: int = 0
    frames_missing: int = 0
    seq_resets: int = 0
    worker_restarts: int = 0
    over_budget: int = 0
    refused: int = 0

    def to_json(self) -> bytes:
        obj = {"version": JSON_VERSION, "type": "health", "node": self.node, "sensor_id": self.sensor_id,
               "timestamp_ns": self.timestamp_ns, "frames_in": self.frames_in, "frames_out": self.frames_out,
               "drops": self.drops, "decode_errors": self.decode_errors, "latency_ms": self.latency_ms,
               "bytes_in_per_s": round(self.bytes_in_per_s, 1), "bytes_out_per_s": round(self.bytes_out_per_s, 1),
               **{k: getattr(self, k) for k in HEALTH_LOSS_FIELDS},
               **({"extra": self.extra} if self.extra else {})}
        return json.dumps(obj, separators=(",", ":")).encode()


def decode_health(payload: bytes, source: str = "<bytes>") -> HealthMsg:
    obj = _load_json(payload, source, "health")
    try:
        return HealthMsg(str(obj["node"]), str(obj["sensor_id"]), int(obj["timestamp_ns"]), int(obj["frames_in"]),
                         int(obj["frames_out"]), int(obj["drops"]), int(obj["decode_errors"]),
                         dict(obj["latency_ms"]), float(obj["bytes_in_per_s"]), float(obj["bytes_out_per_s"]),
                         dict(obj.get("extra", {})), **{k: int(obj.get(k, 0)) for k in HEALTH_LOSS_FIELDS})
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise WireError(f"health from {source}: missing or bad field ({exc!r})") from None
