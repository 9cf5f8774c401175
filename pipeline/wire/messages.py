"""The JSON wire formats: targets, tracks and health (UTF-8 JSON objects, docs/wire-formats.md).
Their fields are defined once, in :mod:`pipeline.wire.fields`; the writers and readers here
take them from there (each writer and reader takes the format as ``fmt``, the definition by
default). One writer per format: :func:`encode_targets_batch` writes the targets of B frames
and :meth:`TargetsMsg.to_json` is it called with one frame. Every failure is a
:class:`WireError` naming the field (and, when decoding, the source)."""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np

from pipeline.errors import WireError
from pipeline.wire.fields import HEALTH, HEALTH_LOSS_FIELDS, TARGETS, TRACKS, Field, Format
from pipeline.wire.frames import FrameHeaders, check_sensor_id, int_field

__all__ = ["HEALTH_LOSS_FIELDS", "HealthMsg", "TargetColumns", "TargetsMsg", "TracksMsg", "decode_health",
           "decode_targets", "decode_tracks", "encode_targets_batch", "load_json", "read_item", "read_value"]

JSON_VERSION = 1
#: a target's fields (pipeline.wire.fields.TARGET_ITEM, the one definition): the required ones, then the optional
TARGET_FIELDS = tuple(f.name for f in TARGETS.item_fields if not f.optional)
#: significant digits of a target value in the JSON (%.9g: 0.1 µm at 10 m, far below a
#: range bin; float32 holds 7): a quarter of the time ``repr``'s 17 digits take to write
TARGET_DIGITS = 9
#: per-target fields a target may carry (older recordings do not)
OPTIONAL_TARGET_FIELDS = tuple(f.name for f in TARGETS.item_fields if f.optional)


def _integer(v, f: Field, what: str) -> int:
    """A JSON integer of field ``f``: in [minimum, 2**64) when it has a minimum (a count, an
    id), else any (a time: the reader that keeps it checks its range, e.g. a recording's)."""
    if isinstance(v, bool) or not isinstance(v, int):
        raise WireError(f"{what} field {f.name}={_short(v)} must be an integer")
    if f.minimum is not None and not f.minimum <= v < 2**64:
        raise WireError(f"{what} field {f.name}={v!r} must be an integer in [{f.minimum}, 2**64)")
    return v


def read_value(v, f: Field, what: str):
    """One JSON value of field ``f``, checked by its type: a finite float, an integer in
    range, a boolean, a string, an object (dict) or an array (list)."""
    if f.type == "number":
        try:
            if isinstance(v, (bool, str)):  # float() would take true and "1.5"; JSON's numbers only
                raise TypeError
            x = float(v)
        except (TypeError, ValueError):
            raise WireError(f"{what} field {f.name}={_short(v)} is not a number") from None
        if not math.isfinite(x):
            raise WireError(f"{what} field {f.name}={x} is not finite")
        return x
    if f.type == "integer":
        return _integer(v, f, what)
    if f.type == "boolean":
        if not isinstance(v, bool):
            raise WireError(f"{what} field {f.name}={_short(v)} must be true or false")
        return v
    kinds = {"string": str, "object": dict, "array": list}
    if not isinstance(v, kinds[f.type]):
        raise WireError(f"{what} field {f.name}={_short(v)} must be a JSON {f.type}")
    return v


def _short(value, limit: int = 80) -> str:
    """``repr(value)``, cut to ``limit`` characters (an error line names a value, not a message)."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def read_item(t, fields: tuple[Field, ...], what: str) -> dict:
    """An item's fields (a target's, a track's) in the definition's order, each checked by
    :func:`read_value`; an absent optional field is left out (or takes its default)."""
    if not isinstance(t, dict):
        raise WireError(f"{what} {_short(t)}: not a JSON object")
    out = {}
    for f in fields:
        v = t.get(f.name)
        if v is None:
            if not f.optional:
                raise WireError(f"{what} {_short(t)}: missing field {f.name}")
            if f.default is not None:
                out[f.name] = f.default
            continue
        out[f.name] = read_value(v, f, what)
    return out


def write_value(v, f: Field) -> str:
    """One value of field ``f`` as JSON text: numbers with TARGET_DIGITS significant digits
    (or ``decimals``), integers and booleans as they are, the rest as json.dumps writes them."""
    if f.type == "number":
        return repr(round(float(v), f.decimals)) if f.decimals is not None else "%.*g" % (TARGET_DIGITS, v)
    if f.type == "integer":
        return "%d" % v
    if f.type == "boolean":
        return "true" if v else "false"
    return json.dumps(v, separators=(",", ":"))


def written(v, f: Field) -> bool:
    """Whether an optional field's value is written (fields.Field's rule)."""
    if not f.optional:
        return True
    if f.type in ("boolean", "object") or f.default is None:
        return bool(v) if f.type != "number" else v is not None and math.isfinite(v)
    return True


def _target(t: dict, fmt: Format = TARGETS) -> dict[str, float]:
    """A target's fields as finite floats (the optional ones when present)."""
    return read_item(t, fmt.item_fields, "target")


def _uint(obj: dict, name: str, bits: int = 64) -> int:
    """A JSON integer field in [0, 2**bits)."""
    v = obj[name]
    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < 2**bits:
        raise WireError(f"{name}={v!r} must be an integer in [0, 2**{bits})")
    return v


class TargetColumns:
    """The targets of B frames as (B, K) float arrays, one per target field of the
    definition (NaN in an optional field = not given), read as attributes (``range_m``,
    ...), and ``present`` (B, K) bool: what :func:`encode_targets_batch` reads
    (pipeline.dsp.localize.Detections has the same fields)."""

    def __init__(self, columns: dict[str, np.ndarray], present: np.ndarray):
        self.columns = columns
        self.present = present

    def __getattr__(self, name: str) -> np.ndarray:
        try:
            return self.__dict__["columns"][name]
        except KeyError:
            raise AttributeError(name) from None

    @classmethod
    def of(cls, targets: list[dict], fmt: Format = TARGETS) -> "TargetColumns":
        """One frame's targets (dicts, as :class:`TargetsMsg` holds them) as (1, K) columns."""
        rows = [read_item(t, fmt.item_fields, "target") for t in targets]
        return cls({f.name: np.array([[r.get(f.name, np.nan) for r in rows]], dtype=float).reshape(1, len(rows))
                    for f in fmt.item_fields}, np.ones((1, len(rows)), dtype=bool))


@dataclass(frozen=True)
class TargetsMsg:
    """Targets of one frame: each a dict of the target fields (the optional ones when
    known); ``published_ns`` is the localizer's wall clock when it published them;
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

    def to_json(self, fmt: Format = TARGETS) -> bytes:
        """Compact JSON; each target value with TARGET_DIGITS significant digits
        (:func:`encode_targets_batch` of this one frame)."""
        headers = FrameHeaders([self.sensor_id], [self.seq], [self.timestamp_ns], [self.config_id])
        return encode_targets_batch(headers, TargetColumns.of(self.targets, fmt), self.algo, self.k, self.source,
                                    self.published_ns, self.auto_k, fmt)[0]


@lru_cache(maxsize=256)
def _targets_template(fmt: Format, given: tuple[int, ...]) -> tuple[str, tuple[int, ...]]:
    """The JSON list of targets whose optional fields are given as the bit masks ``given``
    say (target j: bit i set = its i-th optional field is written), as a %-template of
    floats (TARGET_DIGITS significant digits), and the columns of the values (target j,
    field f -> j * fields + f) it takes, in order."""
    parts, columns = [], []
    width = len(fmt.item_fields)
    for j, mask in enumerate(given):
        fields, opt = [], 0
        for c, f in enumerate(fmt.item_fields):
            if f.optional:
                opt += 1
                if not mask >> (opt - 1) & 1:
                    continue
            fields.append(f.name)
            columns.append(j * width + c)
        parts.append("{" + ",".join(f'"{f}":%.{TARGET_DIGITS}g' for f in fields) + "}")
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


#: the top-level fields of the targets JSON, in the order :func:`_targets_head` writes them
TARGETS_HEAD = ("version", "type", "sensor_id", "seq", "timestamp_ns", "config_id", "algo", "K", "K_auto", "source",
                "published_ns", "targets")
assert TARGETS_HEAD == TARGETS.names, "the targets writer's head and pipeline.wire.fields.TARGETS disagree"


@lru_cache(maxsize=64)
def _targets_head(algo: str, k: int, auto_k: bool, source: str) -> str:
    """The targets JSON up to its list of targets, as a %-template of (sensor id quoted, seq,
    timestamp_ns, config_id, published_ns)."""
    return ('{"version":%d,"type":"targets","sensor_id":%%s,"seq":%%d,"timestamp_ns":%%d,"config_id":%%d,'
            % JSON_VERSION + '"algo":' + _quoted(algo, "algo") + ',"K":%d' % k
            + (',"K_auto":true' if auto_k else "") + ',"source":' + _quoted(source, "source")
            + ',"published_ns":%d,"targets":')


def _column(det, f: Field, shape: tuple) -> np.ndarray:
    """The (B, K) float values of target field ``f`` in ``det`` (an optional one it lacks: NaN)."""
    v = getattr(det, f.name, None)
    if v is None:
        if f.optional:
            return np.full(shape, np.nan)
        raise WireError(f"detections lack the target field {f.name}")
    return np.asarray(v, dtype=float)


def _target_values(det, b: int, fmt: Format) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(B, K, fields) float values of the detections ``det`` (an optional field it lacks:
    NaN), ``present`` (B, K) and the (B, K) bit masks of the optional fields given (finite)."""
    present = np.asarray(det.present, dtype=bool)
    cols = [_column(det, f, present.shape) for f in fmt.item_fields]
    if present.ndim != 2 or present.shape[0] != b or any(c.shape != present.shape for c in cols):
        raise WireError(f"detections must be ({b}, K) arrays for {b} frames, got {present.shape}")
    values = np.array(cols).transpose(1, 2, 0) if cols else np.zeros(present.shape + (0,))  # (B, K, fields)
    required = [i for i, f in enumerate(fmt.item_fields) if not f.optional]
    bad = present[..., None] & ~np.isfinite(values[..., required])
    if bad.any():
        i, j, f = np.argwhere(bad)[0]
        name = fmt.item_fields[required[f]].name
        raise WireError(f"target field {name}={float(values[i, j, required[f]])} is not finite")
    given = np.zeros(present.shape, dtype=np.int64)
    for bit, i in enumerate(i for i, f in enumerate(fmt.item_fields) if f.optional):
        given |= (present & np.isfinite(values[..., i])).astype(np.int64) << bit
    return values, present, given


def _patterns(count: np.ndarray, given: np.ndarray) -> dict[tuple, list[int]]:
    """Frames by the pattern of their targets: (count, optional-field masks of the present targets)."""
    b = len(count)
    if b > 1 and (count == count[0]).all() and (given == given[0]).all():  # the usual batch: one pattern
        c = int(count[0])
        return {(c, *given[0, :c].tolist()): list(range(b))}
    by_pattern: dict[tuple, list[int]] = {}
    for i, (c, masks) in enumerate(zip(count.tolist(), given.tolist())):
        by_pattern.setdefault((c, *masks[:c]), []).append(i)
    return by_pattern


def encode_targets_batch(headers: FrameHeaders, det, algo: str, k: int, source: str, published_ns,
                         auto_k: bool = False, fmt: Format = TARGETS) -> list[bytes]:
    """Targets JSON of B frames, one payload each. ``det``: (B, K) arrays of the target
    fields of ``fmt`` (e.g. pipeline.dsp.localize.Detections, :class:`TargetColumns`): a
    target is written where ``present``, each optional field where finite (a field ``det``
    lacks: never). ``published_ns``: one int or (B,). A present target with a non-finite
    required field is a WireError naming the field."""
    b = len(headers)
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)):
        raise WireError(f"K={k!r} must be an integer")
    values, present, given = _target_values(det, b, fmt)
    if not (present[:, :-1] >= present[:, 1:]).all():  # the present targets of each frame first, in order
        order = np.argsort(~present, axis=1, kind="stable")
        values = np.take_along_axis(values, order[..., None], axis=1)
        given = np.take_along_axis(given, order, axis=1)
    values = values.reshape(b, -1)
    if type(published_ns) is int and -2**63 <= published_ns < 2**63:  # the node's one clock reading
        published = [published_ns] * b
    else:
        published = int_field([published_ns] * b if np.ndim(published_ns) == 0 else published_ns, "published_ns",
                              "int64", b).tolist()
    quoted = {sid: _quoted_id(sid) for sid in set(headers.sensor_id)}
    head = (_targets_head(algo, int(k), bool(auto_k), source) if type(algo) is str and type(source) is str
            else _targets_head.__wrapped__(algo, int(k), bool(auto_k), source))
    out: list[bytes] = [b""] * b
    seqs, stamps, configs = headers.seq.tolist(), headers.timestamp_ns.tolist(), headers.config_id.tolist()
    for pattern, frames in _patterns(present.sum(axis=1), given).items():
        targets, columns = _targets_template(fmt, tuple(int(x) for x in pattern[1:]))
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


def decode_targets(payload: bytes, source: str = "<bytes>", fmt: Format = TARGETS) -> TargetsMsg:
    obj = _load_json(payload, source, "targets")
    try:
        if not isinstance(obj["targets"], list):
            raise WireError(f"targets must be a list, got {type(obj['targets']).__name__}")
        targets = [read_item(t, fmt.item_fields, "target") for t in obj["targets"]]
        return TargetsMsg(check_sensor_id(obj["sensor_id"]), _uint(obj, "seq"), int(obj["timestamp_ns"]),
                          _uint(obj, "config_id", 32), str(obj["algo"]), int(obj["K"]), str(obj["source"]), targets,
                          int(obj.get("published_ns", 0)), bool(obj.get("K_auto", False)))
    except (KeyError, TypeError, ValueError, OverflowError) as exc:  # WireError is a ValueError
        raise WireError(f"targets from {source}: missing or bad field ({exc})") from None


#: the fields of a track in the tracks JSON (pipeline.wire.fields.TRACK_ITEM), in order
TRACK_FIELDS = TRACKS.item_names


@dataclass(frozen=True)
class TracksMsg:
    """The confirmed tracks of one sensor after frame ``seq`` (pipeline.dsp.track): each a dict
    with TRACK_FIELDS; ``published_ns`` is the tracker's wall clock when it published them."""

    sensor_id: str
    seq: int
    timestamp_ns: int
    tracks: list[dict]
    published_ns: int = 0

    def to_json(self, fmt: Format = TRACKS) -> bytes:
        """Compact JSON; each float with TARGET_DIGITS significant digits."""
        head = json.dumps({"version": JSON_VERSION, "type": "tracks", "sensor_id": check_sensor_id(self.sensor_id),
                           "seq": self.seq, "timestamp_ns": self.timestamp_ns, "published_ns": self.published_ns},
                          separators=(",", ":"))
        items = []
        for t in self.tracks:
            t = read_item(t, fmt.item_fields, "track")
            items.append("{" + ",".join(f'"{f.name}":{write_value(t[f.name], f)}' for f in fmt.item_fields
                                        if f.name in t and written(t[f.name], f)) + "}")
        return (head[:-1] + ',"tracks":[' + ",".join(items) + "]}").encode()


def decode_tracks(payload: bytes, source: str = "<bytes>", fmt: Format = TRACKS) -> TracksMsg:
    obj = _load_json(payload, source, "tracks")
    try:
        if not isinstance(obj["tracks"], list):
            raise WireError(f"tracks must be a list, got {type(obj['tracks']).__name__}")
        tracks = [read_item(t, fmt.item_fields, "track") for t in obj["tracks"]]
        ts, pub = obj["timestamp_ns"], obj["published_ns"]
        if isinstance(ts, bool) or not isinstance(ts, int) or isinstance(pub, bool) or not isinstance(pub, int):
            raise WireError("timestamp_ns and published_ns must be integers")
        return TracksMsg(check_sensor_id(obj["sensor_id"]), _uint(obj, "seq"), ts, tracks, pub)
    except (KeyError, TypeError, ValueError, OverflowError, AttributeError) as exc:  # WireError is a ValueError
        raise WireError(f"tracks from {source}: missing or bad field ({exc})") from None


@dataclass
class HealthMsg:
    """1 Hz counters of one node for one sensor: the fields of pipeline.wire.fields.HEALTH
    (tests/test_wire.py checks that this class has each of them, and no other)."""

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

    def to_json(self, fmt: Format = HEALTH) -> bytes:
        """Compact JSON of the format's fields, in its order (``extra`` when not empty)."""
        parts = ['"version":%d,"type":"health"' % JSON_VERSION]
        try:
            for f in fmt.fields[2:]:
                v = getattr(self, f.name)
                if written(v, f):
                    parts.append(f'"{f.name}":{write_value(v, f)}')
        except (TypeError, ValueError) as exc:
            raise WireError(f"health of node {self.node!r}: not writable as JSON ({exc})") from None
        return ("{" + ",".join(parts) + "}").encode()


def decode_health(payload: bytes, source: str = "<bytes>", fmt: Format = HEALTH) -> HealthMsg:
    obj = _load_json(payload, source, "health")
    try:
        return HealthMsg(**read_item(obj, fmt.fields[2:], "health"))
    except WireError as exc:
        raise WireError(f"health from {source}: {exc}") from None
