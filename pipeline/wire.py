"""Wire formats of the zenoh stream (byte layouts in docs/wire-formats.md).

Raw and quantized frames are compact binary, little-endian, behind one 48-byte common
header; targets and health are UTF-8 JSON objects. Every message carries the format
version, the sensor id, the sequence number, the sensor timestamp (ns) and the radar
configuration id. Decoders check everything and raise :class:`WireError` naming what
is wrong and where (the ``source``, e.g. the zenoh key).
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import WireError
from .quantize import QuantizedFrames, check_alpha, check_bits, pack_codes, packed_size, unpack_codes

MAGIC = b"QRDR"
VERSION = 1
KIND_RAW = 1
KIND_QUANTIZED = 2
FLAG_DITHERED = 0x01

#: common header: magic, version, kind, bits, flags, seq, timestamp_ns, config_id, M, sensor_id
COMMON = struct.Struct("<4sBBBBQqII16s")
#: quantized extension: dither_seed, alpha, delta
QUANT_EXT = struct.Struct("<Qff")
HEADER_LEN = COMMON.size  # 48
QUANT_HEADER_LEN = COMMON.size + QUANT_EXT.size  # 64
MAX_M = 1 << 20
SENSOR_ID_MAX = 16
JSON_VERSION = 1
#: the topics of a sensor's keys ``<prefix>/<sensor>/<topic>``; this is the one list of them
TOPICS = ("raw", "quantized", "targets", "health")


def check_sensor_id(sensor_id: str) -> str:
    """Sensor ids: 1-16 ASCII characters from [A-Za-z0-9_-] (they are zenoh key chunks)."""
    ok = isinstance(sensor_id, str) and 1 <= len(sensor_id) <= SENSOR_ID_MAX and all(
        c.isascii() and (c.isalnum() or c in "_-") for c in sensor_id)
    if not ok:
        raise WireError(f"sensor_id={sensor_id!r} must be 1-{SENSOR_ID_MAX} characters of [A-Za-z0-9_-]")
    return sensor_id


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
    step ``delta``, dither scale ``alpha`` and ``dither_seed`` (the dither of frame
    ``seq`` is reproducible from them, see pipeline.quantize)."""

    sensor_id: str
    seq: int
    timestamp_ns: int
    config_id: int
    bits: int
    alpha: float
    delta: float
    dither_seed: int
    codes: np.ndarray

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
                self.delta, self.dither_seed)


def _common(kind: int, bits: int, flags: int, sensor_id: str, seq: int, ts: int, config_id: int, m: int) -> bytes:
    check_sensor_id(sensor_id)
    if not 0 <= seq < 2**64:
        raise WireError(f"seq={seq} does not fit in uint64")
    if not 0 <= config_id < 2**32:
        raise WireError(f"config_id={config_id} does not fit in uint32")
    if not 1 <= m <= MAX_M:
        raise WireError(f"M={m} must be in [1, {MAX_M}]")
    return COMMON.pack(MAGIC, VERSION, kind, bits, flags, seq, ts, config_id, m, sensor_id.encode("ascii"))


def encode_raw(msg: RawFrameMsg) -> bytes:
    data = np.asarray(msg.data)
    if data.ndim != 2 or data.shape[1] != 2:
        raise WireError(f"raw frame data must have shape (M, 2), got {data.shape}")
    head = _common(KIND_RAW, 0, 0, msg.sensor_id, msg.seq, msg.timestamp_ns, msg.config_id, data.shape[0])
    return head + data.astype("<c8", copy=False).tobytes()


def encode_quantized(msg: QuantizedFrameMsg) -> bytes:
    codes = np.asarray(msg.codes)
    bits = check_bits(msg.bits)
    check_alpha(msg.alpha)
    if codes.ndim != 3 or codes.shape[1:] != (2, 2):
        raise WireError(f"codes must have shape (M, 2, 2), got {codes.shape}")
    if not (np.isfinite(msg.delta) and msg.delta > 0):
        raise WireError(f"delta={msg.delta!r} must be finite and > 0")
    if not 0 <= msg.dither_seed < 2**64:
        raise WireError(f"dither_seed={msg.dither_seed} does not fit in uint64")
    flags = FLAG_DITHERED if msg.alpha > 0 else 0
    head = _common(KIND_QUANTIZED, bits, flags, msg.sensor_id, msg.seq, msg.timestamp_ns, msg.config_id,
                   codes.shape[0])
    ext = QUANT_EXT.pack(msg.dither_seed, msg.alpha, msg.delta)
    return head + ext + pack_codes(codes[None], bits)[0].tobytes()


def _parse_common(payload: bytes, source: str, kind: int):
    name = {KIND_RAW: "raw frame", KIND_QUANTIZED: "quantized frame"}[kind]
    if len(payload) < HEADER_LEN:
        raise WireError(f"{name} from {source}: {len(payload)} bytes, shorter than the {HEADER_LEN}-byte header")
    magic, version, got_kind, bits, flags, seq, ts, config_id, m, sid = COMMON.unpack_from(payload)
    if magic != MAGIC:
        raise WireError(f"{name} from {source}: magic {magic!r}, expected {MAGIC!r} (not a qradar frame)")
    if version != VERSION:
        raise WireError(f"{name} from {source}: format version {version} unsupported (this build reads {VERSION})")
    if got_kind != kind:
        raise WireError(f"{name} from {source}: message kind {got_kind}, expected {kind}")
    if not 1 <= m <= MAX_M:
        raise WireError(f"{name} from {source}: M={m} outside [1, {MAX_M}]")
    try:
        sensor_id = check_sensor_id(sid.rstrip(b"\0").decode("ascii"))
    except (UnicodeDecodeError, WireError):
        raise WireError(f"{name} from {source}: sensor id {sid!r} is not valid") from None
    return bits, flags, seq, ts, config_id, m, sensor_id


def decode_raw(payload: bytes, source: str = "<bytes>") -> RawFrameMsg:
    payload = bytes(payload)
    _, _, seq, ts, config_id, m, sensor_id = _parse_common(payload, source, KIND_RAW)
    need = HEADER_LEN + m * 2 * 8
    if len(payload) != need:
        raise WireError(f"raw frame from {source}: {len(payload)} bytes, expected {need} for M={m}")
    data = np.frombuffer(payload, dtype="<c8", offset=HEADER_LEN).reshape(m, 2).astype(np.complex64)
    return RawFrameMsg(sensor_id, seq, ts, config_id, data)


def decode_quantized(payload: bytes, source: str = "<bytes>") -> QuantizedFrameMsg:
    payload = bytes(payload)
    bits, flags, seq, ts, config_id, m, sensor_id = _parse_common(payload, source, KIND_QUANTIZED)
    if len(payload) < QUANT_HEADER_LEN:
        raise WireError(f"quantized frame from {source}: {len(payload)} bytes, shorter than its "
                        f"{QUANT_HEADER_LEN}-byte header")
    if not 1 <= bits <= 16:
        raise WireError(f"quantized frame from {source}: bits={bits} outside [1, 16]")
    seed, alpha, delta = QUANT_EXT.unpack_from(payload, HEADER_LEN)
    if not (np.isfinite(delta) and delta > 0) or not (0.0 <= alpha <= 1.0):
        raise WireError(f"quantized frame from {source}: delta={delta!r} or alpha={alpha!r} out of range")
    if bool(flags & FLAG_DITHERED) != (alpha > 0):
        raise WireError(f"quantized frame from {source}: dithered flag {flags & FLAG_DITHERED} "
                        f"contradicts alpha={alpha}")
    n_codes = m * 4
    need = QUANT_HEADER_LEN + packed_size(n_codes, bits)
    if len(payload) != need:
        raise WireError(f"quantized frame from {source}: {len(payload)} bytes, expected {need} "
                        f"for M={m} and {bits} bits")
    packed = np.frombuffer(payload, dtype=np.uint8, offset=QUANT_HEADER_LEN)[None]
    codes = unpack_codes(packed, bits, n_codes)[0].reshape(m, 2, 2)
    return QuantizedFrameMsg(sensor_id, seq, ts, config_id, bits, float(alpha), float(delta), seed, codes)


def quantized_batch(msgs: list[QuantizedFrameMsg]) -> QuantizedFrames:
    """Frames of one M and one bit depth as one batch (B = len(msgs)) for the decoders;
    alpha and dither_seed may differ per frame (frames of several sensors)."""
    if not msgs or len({(m.codes.shape, m.bits) for m in msgs}) != 1:
        raise WireError("a batch needs at least one frame, all of one M and one bit depth")
    return QuantizedFrames(
        codes=np.stack([m.codes for m in msgs]), delta=np.array([m.delta for m in msgs]), bits=msgs[0].bits,
        alpha=np.array([m.alpha for m in msgs]), dither_seed=np.array([m.dither_seed for m in msgs], dtype=np.uint64),
        seq=np.array([m.seq for m in msgs], dtype=np.uint64))


# -- JSON messages ---------------------------------------------------------------------------
TARGET_FIELDS = ("range_m", "angle_deg", "x_m", "y_m", "amplitude")
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
        obj = {"version": JSON_VERSION, "type": "targets", "sensor_id": self.sensor_id, "seq": self.seq,
               "timestamp_ns": self.timestamp_ns, "config_id": self.config_id, "algo": self.algo,
               "K": self.k, **({"K_auto": True} if self.auto_k else {}), "source": self.source,
               "published_ns": self.published_ns, "targets": [_target(t) for t in self.targets]}
        return json.dumps(obj, separators=(",", ":")).encode()


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


#: health counters added in this version of the JSON (0 when a message lacks them)
HEALTH_LOSS_FIELDS = ("invalid_frames", "processing_errors", "frames_missing", "seq_resets", "worker_restarts")


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
