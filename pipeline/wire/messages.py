"""The JSON wire formats: targets, tracks and health (UTF-8 JSON objects, byte layouts in
docs/wire-formats.md). One writer per format: :func:`encode_targets_batch` writes the
targets of B frames and :meth:`TargetsMsg.to_json` is it called with one frame. Every
failure is a :class:`WireError` naming the field (and, when decoding, the source)."""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np

from pipeline.errors import WireError
from pipeline.wire.frames import FrameHeaders, check_sensor_id, int_field

JSON_VERSION = 1
TARGET_FIELDS = ("range_m", "angle_deg", "x_m", "y_m", "amplitude")
#: significant digits of a target value in the JSON (%.9g: 0.1 µm at 10 m, far below a
#: range bin; float32 holds 7): a quarter of the time ``repr``'s 17 digits take to write
TARGET_DIGITS = 9
#: per-target fields a target may carry (older recordings do not)
OPTIONAL_TARGET_FIELDS = ("statistic_db",)
#: the columns of a frame's target values in :func:`encode_targets_batch`
_TARGET_COLUMNS = TARGET_FIELDS + OPTIONAL_TARGET_FIELDS


def _target(t: dict) -> dict[str, float]:
    """A target's fields as finite floats (the optional ones when present)."""
    try:
        out = {f: float(t[f]) for f in TARGET_FIELDS}
        out.update({f: float(t[f]) for f in OPTIONAL_TARGET_FIELDS if t.get(f) is not None})
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise WireError(f"target {t!r}: missing or bad field ({exc!r})") from None
    bad = [f for f, v in out.items() if not math.isfinite(v)]
    if bad:
        raise WireError(f"target field {bad[0]}={out[bad[0]]} is not finite")
    return out


def _uint(obj: dict, name: str, bits: int = 64) -> int:
    """A JSON integer field in [0, 2**bits)."""
    v = obj[name]
    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < 2**bits:
        raise WireError(f"{name}={v!r} must be an integer in [0, 2**{bits})")
    return v


@dataclass(frozen=True)
class TargetColumns:
    """The targets of B frames as (B, K) float arrays, one per field of TARGET_FIELDS and
    OPTIONAL_TARGET_FIELDS (NaN ``statistic_db`` = not given), and ``present`` (B, K) bool:
    what :func:`encode_targets_batch` reads (pipeline.dsp.localize.Detections has the same fields)."""

    range_m: np.ndarray
    angle_deg: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    amplitude: np.ndarray
    statistic_db: np.ndarray
    present: np.ndarray

    @classmethod
    def of(cls, targets: list[dict]) -> "TargetColumns":
        """One frame's targets (dicts, as :class:`TargetsMsg` holds them) as (1, K) columns."""
        rows = [_target(t) for t in targets]
        values = np.array([[r.get(f, np.nan) for f in _TARGET_COLUMNS] for r in rows], dtype=float)
        values = values.reshape(len(rows), len(_TARGET_COLUMNS)).T[:, None, :]  # (fields, 1, K)
        return cls(*values, present=np.ones((1, len(rows)), dtype=bool))


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
        """Compact JSON; each target value with TARGET_DIGITS significant digits
        (:func:`encode_targets_batch` of this one frame)."""
        headers = FrameHeaders([self.sensor_id], [self.seq], [self.timestamp_ns], [self.config_id])
        return encode_targets_batch(headers, TargetColumns.of(self.targets), self.algo, self.k, self.source,
                                    self.published_ns, self.auto_k)[0]


@lru_cache(maxsize=256)
def _targets_template(has_statistic: tuple[bool, ...]) -> tuple[str, tuple[int, ...]]:
    """The JSON list of targets whose ``statistic_db`` is (True) or is not given, as a
    %-template of floats (TARGET_DIGITS significant digits), and the columns of the values
    (target j, field f -> j * 6 + f) it takes, in order."""
    parts, columns = [], []
    width = len(_TARGET_COLUMNS)
    for j, stat in enumerate(has_statistic):
        fields = TARGET_FIELDS + (OPTIONAL_TARGET_FIELDS if stat else ())
        parts.append("{" + ",".join(f'"{f}":%.{TARGET_DIGITS}g' for f in fields) + "}")
        columns += [j * width + _TARGET_COLUMNS.index(f) for f in fields]
    return "[" + ",".join(parts) + "]", tuple(columns)


def _quoted(value: object, name: str) -> str:
    """``value`` as JSON, escaped for a %-template."""
    try:
        return json.dumps(value).replace("%", "%%")
    except (TypeError, ValueError) as exc:
        raise WireError(f"{name}={value!r} is not writable as JSON ({exc})") from None


#: a sensor id JSON writes as it is, between quotes (a valid id always is one)
_PLAIN_ID = re.compile(r"[A-Za-z0-9_-]+")


def _quoted_id(sensor_id: str) -> str:
    """A sensor id as :func:`_quoted` writes it (a valid id without json.dumps: a quarter of the time)."""
    return '"%s"' % sensor_id if _PLAIN_ID.fullmatch(sensor_id) else _quoted(sensor_id, "sensor_id")


@lru_cache(maxsize=64)
def _targets_head(algo: str, k: int, auto_k: bool, source: str) -> str:
    """The targets JSON up to its list of targets, as a %-template of (sensor id quoted, seq,
    timestamp_ns, config_id, published_ns)."""
    return ('{"version":%d,"type":"targets","sensor_id":%%s,"seq":%%d,"timestamp_ns":%%d,"config_id":%%d,'
            % JSON_VERSION + '"algo":' + _quoted(algo, "algo") + ',"K":%d' % k
            + (',"K_auto":true' if auto_k else "") + ',"source":' + _quoted(source, "source")
            + ',"published_ns":%d,"targets":')


def encode_targets_batch(headers: FrameHeaders, det, algo: str, k: int, source: str, published_ns,
                         auto_k: bool = False) -> list[bytes]:
    """Targets JSON of B frames, one payload each. ``det``: (B, K) arrays of the fields of
    :class:`TargetColumns` (e.g. pipeline.dsp.localize.Detections): a target is written where
    ``present``, its ``statistic_db`` when finite. ``published_ns``: one int or (B,).
    A present target with a non-finite field is a WireError naming the field."""
    b = len(headers)
    cols = [np.asarray(getattr(det, f), dtype=float) for f in _TARGET_COLUMNS]
    present = np.asarray(det.present, dtype=bool)
    if present.ndim != 2 or present.shape[0] != b or any(c.shape != present.shape for c in cols):
        raise WireError(f"detections must be ({b}, K) arrays for {b} frames, got {present.shape}")
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)):
        raise WireError(f"K={k!r} must be an integer")
    values = np.array(cols).transpose(1, 2, 0)  # (B, K, 6)
    finite = np.isfinite(values[..., :len(TARGET_FIELDS)])
    bad = present[..., None] & ~finite
    if bad.any():
        i, j, f = np.argwhere(bad)[0]
        raise WireError(f"target field {TARGET_FIELDS[f]}={float(values[i, j, f])} is not finite")
    has_stat = present & np.isfinite(cols[-1])
    if not (present[:, :-1] >= present[:, 1:]).all():  # the present targets of each frame first, in order
        order = np.argsort(~present, axis=1, kind="stable")
        values = np.take_along_axis(values, order[..., None], axis=1)
        has_stat = np.take_along_axis(has_stat, order, axis=1)
    values = values.reshape(b, -1)
    count = present.sum(axis=1)
    if type(published_ns) is int and -2**63 <= published_ns < 2**63:  # the node's one clock reading
        published = [published_ns] * b
    else:
        published = int_field([published_ns] * b if np.ndim(published_ns) == 0 else published_ns, "published_ns",
                              "int64", b).tolist()
    quoted = {sid: _quoted_id(sid) for sid in set(headers.sensor_id)}
    head = (_targets_head(algo, int(k), bool(auto_k), source) if type(algo) is str and type(source) is str
            else _targets_head.__wrapped__(algo, int(k), bool(auto_k), source))
    by_pattern: dict[tuple, list[int]] = {}  # (count, has_stat of the present targets) -> frames
    if b > 1 and (count == count[0]).all() and (has_stat == has_stat[0]).all():  # the usual batch: one pattern
        c = int(count[0])
        by_pattern[(c, *has_stat[0, :c].tolist())] = list(range(b))
    else:
        for i, (c, stats) in enumerate(zip(count.tolist(), has_stat.tolist())):
            by_pattern.setdefault((c, *stats[:c]), []).append(i)
    out: list[bytes] = [b""] * b
    seqs, stamps, configs = headers.seq.tolist(), headers.timestamp_ns.tolist(), headers.config_id.tolist()
    for pattern, frames in by_pattern.items():
        targets, columns = _targets_template(tuple(bool(x) for x in pattern[1:]))
        template = head + targets + "}"
        rows = (values if len(frames) == b else values.take(frames, axis=0)).take(columns, axis=1).tolist() \
            if columns else [[]] * len(frames)
        for i, row in zip(frames, rows):
            out[i] = (template % (quoted[headers.sensor_id[i]], seqs[i], stamps[i], configs[i], published[i],
                                  *row)).encode()
    return out


def _reject_constant(name: str):
    raise json.JSONDecodeError(f"{name} is not a number JSON allows", name, 0)


#: the largest JSON message a reader parses (bytes): a health message with every extra is
#: a few kB, targets of 100 targets ~15 kB
MAX_JSON_BYTES = 1 << 20
#: the deepest nesting of arrays and objects a reader parses (targets: 3, health: 5)
MAX_JSON_DEPTH = 32
#: a JSON string, whose brackets do not nest
_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"')
_OPENS, _CLOSES = np.zeros(256, np.int8), np.zeros(256, np.int8)
_OPENS[[ord("["), ord("{")]] = 1
_CLOSES[[ord("]"), ord("}")]] = 1


def json_depth(data: bytes) -> int:
    """How deep arrays and objects nest in JSON text ``data``, without parsing it: the
    number of opening brackets when that is at most MAX_JSON_DEPTH (a bound of the depth),
    else the deepest nesting, a running sum over the text with its strings taken out."""
    if data.count(b"[") + data.count(b"{") <= MAX_JSON_DEPTH:
        return data.count(b"[") + data.count(b"{")
    codes = np.frombuffer(_JSON_STRING.sub(b'""', data), np.uint8)
    steps = _OPENS[codes].astype(np.int64) - _CLOSES[codes]
    return int(np.cumsum(steps).max(initial=0))


def load_json(payload: bytes, what: str, max_bytes: int = MAX_JSON_BYTES, max_depth: int = MAX_JSON_DEPTH):
    """UTF-8 JSON of at most ``max_bytes`` bytes nested at most ``max_depth`` deep, parsed
    (NaN and Infinity refused); anything else is a WireError naming ``what``, never an
    exception of the parser (a RecursionError of a deep nesting, a MemoryError of a huge
    one)."""
    data = bytes(payload)
    if len(data) > max_bytes:
        raise WireError(f"{what}: {len(data)} bytes of JSON, more than the {max_bytes} a reader takes")
    depth = json_depth(data)
    if depth > max_depth:
        raise WireError(f"{what}: JSON nested {depth} deep, more than the {max_depth} a reader takes")
    try:
        return json.loads(data.decode("utf-8"), parse_constant=_reject_constant)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise WireError(f"{what}: not UTF-8 JSON ({exc})") from None


def _load_json(payload: bytes, source: str, kind: str) -> dict[str, Any]:
    obj = load_json(payload, f"{kind} from {source}")
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
    except (KeyError, TypeError, ValueError, OverflowError) as exc:  # WireError is a ValueError
        raise WireError(f"targets from {source}: missing or bad field ({exc})") from None


#: the fields of a track in the tracks JSON (pipeline.dsp.track), in order; ``track_id`` and
#: ``hits`` are integers, ``static`` a boolean, the others numbers
TRACK_FIELDS = ("track_id", "range_m", "angle_deg", "x_m", "y_m", "vx_mps", "vy_mps", "sigma_m", "age_s", "hits",
                "static")
_TRACK_FLOATS = ("range_m", "angle_deg", "x_m", "y_m", "vx_mps", "vy_mps", "sigma_m", "age_s")


def _track(t: dict) -> dict:
    """A track's fields, checked: integers >= 0, finite floats, a boolean."""
    try:
        out = {"track_id": _uint(t, "track_id"), **{f: float(t[f]) for f in _TRACK_FLOATS}, "hits": _uint(t, "hits")}
        static = t["static"]
    except (KeyError, TypeError, ValueError, OverflowError, AttributeError) as exc:
        raise WireError(f"track: missing or bad field ({exc!r})") from None
    bad = [f for f in _TRACK_FLOATS if not np.isfinite(out[f])]
    if bad:
        raise WireError(f"track field {bad[0]}={out[bad[0]]} is not finite")
    if not isinstance(static, bool):
        raise WireError(f"static={static!r} must be true or false")
    out["static"] = static
    return {f: out[f] for f in TRACK_FIELDS}


@dataclass(frozen=True)
class TracksMsg:
    """The confirmed tracks of one sensor after frame ``seq`` (pipeline.dsp.track): each a dict
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
            raise WireError(f"tracks must be a list, got {type(obj['tracks']).__name__}")
        tracks = [_track(t) for t in obj["tracks"]]
        ts, pub = obj["timestamp_ns"], obj["published_ns"]
        if isinstance(ts, bool) or not isinstance(ts, int) or isinstance(pub, bool) or not isinstance(pub, int):
            raise WireError("timestamp_ns and published_ns must be integers")
        return TracksMsg(check_sensor_id(obj["sensor_id"]), _uint(obj, "seq"), ts, tracks, pub)
    except (KeyError, TypeError, ValueError, OverflowError, AttributeError) as exc:  # WireError is a ValueError
        raise WireError(f"tracks from {source}: missing or bad field ({exc})") from None


#: health counters added in this version of the JSON (0 when a message lacks them)
HEALTH_LOSS_FIELDS = ("invalid_frames", "processing_errors", "frames_missing", "seq_resets", "worker_restarts",
                      "over_budget", "refused", "implausible_seq", "denied_puts")


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
    implausible_seq: int = 0
    denied_puts: int = 0

    def to_json(self) -> bytes:
        obj = {"version": JSON_VERSION, "type": "health", "node": self.node, "sensor_id": self.sensor_id,
               "timestamp_ns": self.timestamp_ns, "frames_in": self.frames_in, "frames_out": self.frames_out,
               "drops": self.drops, "decode_errors": self.decode_errors, "latency_ms": self.latency_ms,
               "bytes_in_per_s": round(self.bytes_in_per_s, 1), "bytes_out_per_s": round(self.bytes_out_per_s, 1),
               **{k: getattr(self, k) for k in HEALTH_LOSS_FIELDS},
               **({"extra": self.extra} if self.extra else {})}
        try:
            return json.dumps(obj, separators=(",", ":")).encode()
        except (TypeError, ValueError) as exc:
            raise WireError(f"health of node {self.node!r}: not writable as JSON ({exc})") from None


def decode_health(payload: bytes, source: str = "<bytes>") -> HealthMsg:
    obj = _load_json(payload, source, "health")
    try:
        return HealthMsg(str(obj["node"]), str(obj["sensor_id"]), int(obj["timestamp_ns"]), int(obj["frames_in"]),
                         int(obj["frames_out"]), int(obj["drops"]), int(obj["decode_errors"]),
                         dict(obj["latency_ms"]), float(obj["bytes_in_per_s"]), float(obj["bytes_out_per_s"]),
                         dict(obj.get("extra", {})), **{k: int(obj.get(k, 0)) for k in HEALTH_LOSS_FIELDS})
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise WireError(f"health from {source}: missing or bad field ({exc!r})") from None
