"""The one definition of the JSON formats' fields: targets, tracks, health and range
profiles, each a :class:`Format` of :class:`Field` (name, JSON type, unit, meaning,
optional or not), from which the rest is produced:

- the writers and the readers' checks (:mod:`pipeline.wire.messages`: a target's or a
  track's fields written in this order, each checked when read by its type);
- the JSON Schemas of the MCAP channels (:func:`json_schema`, :mod:`replay.mcapio`) and of
  the live view's JSON topics (:mod:`qradar.view`);
- the Foxglove point of a target (:func:`point_fields`: every number of a target as a
  float32 field, :mod:`pipeline.wire.foxglove`);
- the web page's targets event (:mod:`qradar.web.events`: every field a target carries);
- the field tables of docs/wire-formats.md (:func:`field_table`; tests/test_formats.py
  checks the tables there against it).

A new per-target quantity is one line in :data:`TARGET_ITEM` (``optional=True`` when older
messages lack it: a reader then leaves it out of the target's dict, a writer writes it
where its value is finite); tests/test_formats.py adds one to a copy and follows it
through. No I/O here (:func:`with_tables` takes and returns text).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

#: JSON types a field may have (JSON Schema's names)
JSON_TYPES = ("number", "integer", "boolean", "string", "object", "array")


@dataclass(frozen=True)
class Field:
    """One field of a JSON message: ``name``, its JSON ``type`` (one of JSON_TYPES), its
    ``unit`` ("" when it has none), what it is (``doc``, one sentence for the docs' table),
    ``optional`` (may be absent: older recordings, or not computed), ``default`` (what a
    reader takes for an absent optional field with a default; None: left out), ``minimum``
    (integers: the least value a reader takes), ``items`` (arrays: the JSON type of each
    element), ``const`` (a fixed value) and ``decimals`` (numbers written rounded to so many
    decimals; else with TARGET_DIGITS significant digits, or as Python writes them).

    An optional boolean or object is written when true or not empty, an optional number
    without a default when finite; other optional fields (with a default) always."""

    name: str
    type: str
    unit: str = ""
    doc: str = ""
    optional: bool = False
    default: object = None
    minimum: int | None = None
    items: str | None = None
    const: object = None
    decimals: int | None = None

    def __post_init__(self) -> None:
        if self.type not in JSON_TYPES:
            raise ValueError(f"field {self.name}: type {self.type!r} must be one of {JSON_TYPES}")


@dataclass(frozen=True)
class Format:
    """A JSON message: its ``type`` (the ``"type"`` field), its schema ``title``, the
    top-level ``fields`` in the order written, and, for a message carrying a list of items
    (targets, tracks), the list's name ``items`` and the ``item_fields`` of each item."""

    type: str
    title: str
    fields: tuple[Field, ...]
    items: str | None = None
    item_fields: tuple[Field, ...] = ()

    def field(self, name: str) -> Field:
        for f in self.fields + self.item_fields:
            if f.name == name:
                return f
        raise KeyError(name)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields)

    @property
    def item_names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.item_fields)

    def with_item(self, field: Field) -> "Format":
        """This format with one more item field (at the end)."""
        return replace(self, item_fields=self.item_fields + (field,))

    def with_field(self, field: Field) -> "Format":
        """This format with one more top-level field (at the end)."""
        return replace(self, fields=self.fields + (field,))


def _envelope(kind: str) -> tuple[Field, ...]:
    """The fields every JSON message starts with."""
    return (Field("version", "integer", doc="format version: 1", const=1),
            Field("type", "string", doc=f'"{kind}"', const=kind))


_SENSOR = Field("sensor_id", "string", doc="the sensor's id: 1-16 characters of [A-Za-z0-9_-]")
_SEQ = Field("seq", "integer", doc="sequence number of the frame (per sensor, from 0)", minimum=0)
_STAMP = Field("timestamp_ns", "integer", "ns", "sensor timestamp of the frame, since the Unix epoch")
_PUBLISHED = Field("published_ns", "integer", "ns", "wall clock of the node when it published the message")
_CONFIG = Field("config_id", "integer", doc="radar config id of the frame (docs: common header)", minimum=0)

#: a target's fields, in the order written (pipeline.dsp.localize.Detections has them as columns)
TARGET_ITEM = (
    Field("range_m", "number", "m", "range R"),
    Field("angle_deg", "number", "deg", "angle θ, positive when the phase on antenna 2 leads antenna 1"),
    Field("x_m", "number", "m", "R cos θ, along boresight"),
    Field("y_m", "number", "m", "R sin θ, across boresight"),
    Field("amplitude", "number", "frame units", "joint magnitude over both antennas divided by √2"),
    Field("statistic_db", "number", "dB", "detection statistic, capped at ±300 dB", optional=True),
    Field("p_value", "number", "", "the chance that noise alone makes a statistic this large in the frame's "
          "range gate: pbp, the largest of its bins' joint energy over their mean, white Gaussian noise; cml, a "
          "score test of the frame given the other targets, conservative for codes", optional=True),
    Field("sigma_range_m", "number", "m", "standard deviation of range_m, from the Fisher information of the "
          "frame's codes at the estimate (cml)", optional=True),
    Field("sigma_angle_deg", "number", "deg", "standard deviation of angle_deg, likewise", optional=True),
    Field("cov_range_angle", "number", "m·deg", "covariance of range_m and angle_deg, likewise", optional=True),
    Field("radial_velocity_mps", "number", "m/s",
          "radial velocity, + = away, from the phase step between the frame's ramps: known modulo the "
          "ambiguity interval V = c / (2 f_c Δt) (f_c mid-sweep, Δt the ramp spacing: 0.249 m/s for 25 ms) "
          "and given in [−V/2, V/2); cml only", optional=True),
)

TARGETS = Format("targets", "qradar.Targets", _envelope("targets") + (
    _SENSOR, _SEQ, _STAMP, _CONFIG,
    Field("algo", "string", doc="the decoder: pbp, qiht or cml"),
    Field("K", "integer", doc="targets asked for (with K_auto: the most allowed)", minimum=0),
    Field("K_auto", "boolean", doc="the localizer decided the count (written only when true)", optional=True,
          default=False),
    Field("source", "string", doc='frames localized: "quantized" or "raw"'),
    Field("published_ns", "integer", "ns", "wall clock of the localizer when it published them", optional=True,
          default=0),
    Field("targets", "array", doc="the targets, strongest first (fields below)", items="object"),
), items="targets", item_fields=TARGET_ITEM)

#: a track's fields, in the order written (pipeline.dsp.track)
TRACK_ITEM = (
    Field("track_id", "integer", doc="id, unique per sensor for the life of the localizer", minimum=0),
    Field("range_m", "number", "m", "range of the position"),
    Field("angle_deg", "number", "deg", "angle of the position"),
    Field("x_m", "number", "m", "position along boresight"),
    Field("y_m", "number", "m", "position across boresight"),
    Field("vx_mps", "number", "m/s", "velocity along x"),
    Field("vy_mps", "number", "m/s", "velocity along y"),
    Field("sigma_m", "number", "m", "position standard deviation (RMS of the two axes)"),
    Field("age_s", "number", "s", "time since the track's first target (sensor time)"),
    Field("hits", "integer", doc="frames whose target the track took", minimum=0),
    Field("static", "boolean", doc="the velocity is consistent with zero (χ² test)"),
    Field("radial_velocity_mps", "number", "m/s", "radial velocity, + = away, from the Doppler of the targets "
          "the track took, its ambiguity (a whole number of V) resolved over their ranges; absent until it is, "
          "and with a decoder without Doppler (pbp, qiht)", optional=True),
)

TRACKS = Format("tracks", "qradar.Tracks", _envelope("tracks") + (
    _SENSOR, _SEQ, _STAMP, _PUBLISHED,
    Field("tracks", "array", doc="the confirmed tracks, in the order of their ids (fields below)", items="object"),
), items="tracks", item_fields=TRACK_ITEM)


def _counter(name: str, doc: str, optional: bool = True) -> Field:
    return Field(name, "integer", doc=doc, optional=optional, default=0 if optional else None, minimum=0)


HEALTH = Format("health", "qradar.Health", _envelope("health") + (
    Field("node", "string", doc="the node's name"),
    Field("sensor_id", "string", doc="the sensor (`_unknown`: the senders a node could not put on a sensor)"),
    Field("timestamp_ns", "integer", "ns", "wall clock of the node when it published the message"),
    _counter("frames_in", "frames received", optional=False),
    _counter("frames_out", "frames (or messages) sent", optional=False),
    _counter("drops", "frames a bounded queue refused (the driver: sensor frames lost)", optional=False),
    _counter("decode_errors", "payloads that do not parse", optional=False),
    Field("latency_ms", "object", "ms", "p50 and p99 of the latency from the sensor (null before the first)"),
    Field("bytes_in_per_s", "number", "B/s", "bytes received a second, over the last period", decimals=1),
    Field("bytes_out_per_s", "number", "B/s", "bytes sent a second, over the last period", decimals=1),
    _counter("invalid_frames", "frames refused for contradicting the announced radar configuration"),
    _counter("processing_errors", "frames whose maths or publication failed"),
    _counter("frames_missing", "frames a gap in the sequence numbers says were lost upstream"),
    _counter("seq_resets", "restarts of a sender's count"),
    _counter("worker_restarts", "restarts of the node's worker thread"),
    _counter("over_budget", "frames dropped on arrival beyond the key's intake budget"),
    _counter("refused", "frames of sensor ids the node did not admit"),
    _counter("implausible_seq", "sequence numbers out of line that nothing followed on from"),
    _counter("denied_puts", "messages not sent: the access policy denies the node's identity their key"),
    Field("extra", "object", doc="node-specific (written only when not empty)", optional=True),
))

#: the health counters added after the first version (absent from older recordings: read as 0)
HEALTH_LOSS_FIELDS = tuple(f.name for f in HEALTH.fields if f.type == "integer" and f.optional)

PROFILE = Format("profile", "qradar.RangeProfile", _envelope("profile") + (
    _SENSOR, _SEQ, _STAMP, _CONFIG,
    Field("bits", "integer", doc="bits per code of the frame", minimum=1),
    Field("alpha", "number", doc="dither scale of the frame"),
    Field("delta", "number", "full scale", "quantizer step of the frame"),
    Field("range_m", "array", "m", "range of each value (a bin, or the first of the bins it covers)",
          items="number"),
    Field("profile_db", "array", "dB full scale", "joint magnitude √((|U1|² + |U2|²) / 2) per range",
          items="number"),
    Field("antenna1_db", "array", "dB full scale", "|U1| per range, receiver 1", items="number"),
    Field("antenna2_db", "array", "dB full scale", "|U2| per range, receiver 2", items="number"),
))

FORMATS = {f.type: f for f in (TARGETS, TRACKS, HEALTH, PROFILE)}


# -- produced from the definition ---------------------------------------------------------------
def _field_schema(f: Field) -> dict:
    out: dict = {"const": f.const} if f.const is not None else {"type": f.type}
    if f.items is not None and f.items != "object":
        out["items"] = {"type": f.items}
    if f.minimum is not None:
        out["minimum"] = f.minimum
    doc = f.doc + (f" ({f.unit})" if f.unit else "")
    if doc:
        out["description"] = doc
    return out


def json_schema(fmt: Format) -> dict:
    """The JSON Schema of a format (what MCAP channels and Foxglove's JSON topics carry)."""
    props = {f.name: _field_schema(f) for f in fmt.fields}
    if fmt.items is not None:
        props[fmt.items] = {**props[fmt.items], "items": {
            "type": "object", "properties": {f.name: _field_schema(f) for f in fmt.item_fields},
            "required": [f.name for f in fmt.item_fields if not f.optional]}}
    return {"type": "object", "title": fmt.title, "properties": props,
            "required": [f.name for f in fmt.fields if not f.optional]}


def point_fields(fmt: Format = TARGETS) -> tuple[str, ...]:
    """The float32 fields of a target's Foxglove point: x, y, z (m, in the sensor's frame),
    then every number of a target but its x_m and y_m, in the format's order."""
    return ("x", "y", "z") + tuple(f.name for f in fmt.item_fields
                                   if f.type == "number" and f.name not in ("x_m", "y_m"))


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def field_table(fmt: Format, items: bool = False) -> str:
    """The Markdown table of a format's fields (``items``: of each item's), as
    docs/wire-formats.md holds it."""
    rows = ["| field | type | unit | optional | what |", "|---|---|---|---|---|"]
    for f in fmt.item_fields if items else fmt.fields:
        kind = f"{f.type} of {f.items}s" if f.items else f.type
        opt = "" if not f.optional else ("yes" if f.default is None else f"yes ({f.default!r} when absent)")
        rows.append(f"| `{f.name}` | {kind} | {_cell(f.unit)} | {opt} | {_cell(f.doc)} |")
    return "\n".join(rows)


def docs_tables() -> dict[str, str]:
    """Every table docs/wire-formats.md holds, by the name of its marker
    (``<!-- fields:NAME -->`` ... ``<!-- /fields:NAME -->``)."""
    return {"targets": field_table(TARGETS), "target": field_table(TARGETS, items=True),
            "tracks": field_table(TRACKS), "track": field_table(TRACKS, items=True),
            "health": field_table(HEALTH), "profile": field_table(PROFILE)}


def with_tables(text: str) -> str:
    """``text`` (docs/wire-formats.md) with each block between ``<!-- fields:NAME -->`` and
    ``<!-- /fields:NAME -->`` replaced by :func:`docs_tables`' table NAME (a block it does not
    know is left as it is). tests/test_formats.py checks that the docs are their own result;
    ``python -m pipeline.wire.fields FILE`` rewrites FILE so."""
    import re

    tables = docs_tables()

    def table(m: re.Match) -> str:
        name = m.group(1)
        return m.group(0) if name not in tables else f"<!-- fields:{name} -->\n{tables[name]}\n<!-- /fields:{name} -->"

    return re.sub(r"<!-- fields:([a-z]+) -->\n.*?<!-- /fields:\1 -->", table, text, flags=re.S)


if __name__ == "__main__":  # python -m pipeline.wire.fields docs/wire-formats.md
    import sys
    from pathlib import Path

    for name in sys.argv[1:]:
        path = Path(name)
        path.write_text(with_tables(path.read_text()))
