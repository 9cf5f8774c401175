"""A qradar recording from Python, read lazily by chunk (:func:`open_recording`, the
:class:`Recording` it returns; docs/api.md): opening reads the summary and metadata, each
accessor the chunks that hold its sensor's topic in the window, every one CRC-checked."""

from __future__ import annotations

import json
import logging
from collections import Counter
from copy import copy
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.nodes.counters import DEFAULT_SEQ_RATE_HZ, judge_seq
from pipeline.wire import (COMMON, MAGIC, TARGET_FIELDS, TOPICS, TRACK_FIELDS, HealthMsg, WireError, decode_health,
                           decode_quantized_batch, decode_raw_batch, decode_targets, decode_tracks, load_json,
                           quantized_batch)
from radar_driver.model import RadarConfig
from radar_driver.scene import SimScene, scene_from_dict
from replay.errors import ReplayError
from replay.mcapinfo import describe
from replay.mcapio import McapFile, topic_of
from replay.mcapread import DamagedChunk

from .streams import (TABLE_TOPICS, Frames, Quantized, Targets, Tracks, empty_table, frames_table, health_table,
                      joined, targets_table, tracks_table)

log = logging.getLogger("qradar.api")

#: the topics a recording holds per sensor (``<prefix>/<sensor>/<topic>``)
RECORDED_TOPICS = TOPICS + ("pointcloud",)


class Findings:
    """What the reads of a recording found, merged: damaged chunks by offset (a chunk counts
    the same each time it is read: the window's messages of every topic, it is lost whole),
    messages lost apart from them (channels whose definition was lost, statistics short),
    problems. Each is logged once."""

    def __init__(self) -> None:
        self.damage: dict[int, DamagedChunk] = {}
        self.lost_apart: dict[str, int] = {}
        self.problems: list[str] = []
        self.topic = str

    def merge(self, f: McapFile, path: Path) -> None:
        self.topic = f.topic
        in_chunks: Counter = Counter()
        new = []
        for d in f.damaged:
            in_chunks.update(d.lost_by_channel)
            if d.offset not in self.damage:
                self.damage[d.offset] = copy(d)
                new.append(d.describe(f.topic))
        for cid, n in (f.lost_by_channel - in_chunks).items():
            self.lost_apart[f.topic(cid)] = self.lost_apart.get(f.topic(cid), 0) + n
        new += [p for p in f.problems if p not in self.problems]
        self.problems += [p for p in f.problems if p not in self.problems]
        for line in new:
            log.warning("%s: %s (its messages are not returned)", path, line)

    def lines(self) -> list[str]:
        return [d.describe(self.topic) for _, d in sorted(self.damage.items())] + list(self.problems)

    def lost(self) -> dict[str, int]:
        out = dict(self.lost_apart)
        for d in self.damage.values():
            for cid, n in d.lost_by_channel.items():
                if n:
                    out[self.topic(cid)] = out.get(self.topic(cid), 0) + n
        return out


def _ordered(seq: list[int]) -> np.ndarray:
    """Indices putting the frames in sequence order (a recording keeps arrival order)."""
    return np.argsort(np.asarray(seq, dtype=np.uint64), kind="stable")


def _key(topic: str) -> tuple[str, str] | None:
    """(sensor id, topic) of a channel's key ``<prefix>/<sensor>/<topic>``, else None."""
    kind = topic_of(topic)
    parts = topic.rsplit("/", 2)
    return None if kind is None or len(parts) < 3 else (parts[-2], kind)


@dataclass
class Recording:
    """A qradar recording (MCAP), read lazily by chunk: opening reads its summary and
    metadata; each accessor (:meth:`raw`, :meth:`targets`, ...) reads, once, only the
    chunks that hold its sensor's topic in the window (the chunk index gives each chunk's
    log time range and channels), so memory follows the window and the topics asked for.

    ``sensors``: the sensor ids with frames, targets or tracks; ``metadata``: the file's
    metadata records (name -> dict); ``radar``: its radar configuration (``qradar.radar``
    metadata, else the default K-MD2's); ``start_ns`` / ``end_ns``: the log times of its
    first and last message (``t_s`` = 0 at ``start_ns``); ``start_s`` / ``end_s`` and
    ``topics``: the selection it was opened with; ``truncated``: the file was cut short (a
    file without a summary is read whole at open: its complete chunks). Messages that do
    not parse are counted in ``unparsed`` (topic -> count), not raised. Every chunk read is
    CRC-checked: the messages of a damaged chunk are never returned, those in the selection
    are counted in ``lost`` (key -> count) and each damaged chunk is named in ``damaged``
    (offset, log time range, topics; also logged as a warning): what the reads so far
    found (``qradar info --check`` reads every chunk)."""

    path: Path
    metadata: dict[str, dict[str, str]]
    sensors: list[str]
    truncated: bool
    start_ns: int | None = None
    end_ns: int | None = None
    start_s: float | None = None
    end_s: float | None = None
    topics: tuple[str, ...] = RECORDED_TOPICS
    unparsed: dict[str, int] = field(default_factory=dict)
    _file: McapFile | None = field(default=None, repr=False)
    _keys: set[tuple[str, str]] = field(default_factory=set, repr=False)  # (sensor, topic) in the file
    _loaded: set[tuple[str, str]] = field(default_factory=set, repr=False)
    _payloads: dict[tuple[str, str], list[bytes]] = field(default_factory=dict, repr=False)
    _log_ns: dict[tuple[str, str], list[int]] = field(default_factory=dict, repr=False)  # each message's log time
    _found: Findings = field(default_factory=Findings, repr=False)

    @property
    def radar(self) -> RadarConfig:
        md = self.metadata.get("qradar.radar")
        if not md:
            return RadarConfig()
        values = {k: json.loads(v) for k, v in md.items() if k != "config_id"}
        return RadarConfig.from_dict(values)

    @property
    def damaged(self) -> list[str]:
        """One line per damaged chunk the reads so far met (offset, log times, the messages
        of the window it lost, by topic, why), then one per problem."""
        return self._found.lines()

    @property
    def lost(self) -> dict[str, int]:
        """Messages of the window the reads so far found lost, by key (:class:`Findings`)."""
        return self._found.lost()

    def info(self) -> dict:
        """What the file holds, as ``qradar info --json`` prints it (:func:`replay.mcapinfo.describe`)."""
        return describe(self.path)

    def scene(self) -> SimScene:
        """The simulated scene it was recorded from (``qradar.scene`` metadata): its targets'
        truth with ``.truth(t_s)`` or ``.arrays(t_s)``. A recording of a real sensor has none
        (ReplayError): give the reflectors' positions as a scene file (:func:`load_scene`)."""
        md = self.metadata.get("qradar.scene")
        if md is None or "scene" not in md:
            raise ReplayError(f"{self.path} holds no ground truth (no qradar.scene metadata: a real sensor's?); "
                              "load the reflectors' positions with qradar.load_scene(TOML)")
        return scene_from_dict(json.loads(md["scene"]), f"{self.path}: qradar.scene metadata")

    # -- reading -----------------------------------------------------------------------------
    def _window_ns(self) -> tuple[int | None, int | None]:
        if self.start_ns is None:
            return None, None
        return (None if self.start_s is None else self.start_ns + round(self.start_s * 1e9),
                None if self.end_s is None else self.start_ns + round(self.end_s * 1e9))

    def _take(self, key: tuple[str, str], data, log_ns: int) -> None:
        self._payloads.setdefault(key, []).append(bytes(data))
        self._log_ns.setdefault(key, []).append(log_ns)

    def _load(self, keys: set[tuple[str, str]]) -> None:
        """Read the messages of ``keys`` (sensor, topic) in the window, once: the chunks that hold them."""
        missing = keys - self._loaded
        if not missing or self._file is None:
            return
        start_ns, end_ns = self._window_ns()
        for ch, msg in self._file.messages(start_ns, end_ns, lambda ch: _key(ch.topic) in missing):
            self._take(_key(ch.topic), msg.data, msg.log_time)
        self._found.merge(self._file, self.path)
        self._loaded |= missing

    def _selected(self, topic: str) -> None:
        if topic not in self.topics:
            raise ReplayError(f"{self.path} was opened with topics={list(self.topics)}: open it again with "
                              f"{topic!r} among them")

    def _sensor(self, topic: str, sensor: str | None) -> str:
        """``sensor``, or the first sensor by name with ``topic`` messages."""
        self._selected(topic)
        have = sorted(s for s, t in self._keys if t == topic)
        if sensor is None:
            if not have:
                raise ReplayError(f"{self.path} holds no {topic} messages (its sensors: {self.sensors or 'none'})")
            return have[0]
        if sensor not in have:
            raise ReplayError(f"{self.path} has no {topic} messages of sensor {sensor!r}; "
                              f"sensors with {topic}: {have}")
        return sensor

    def _t_s(self, log_ns) -> np.ndarray:
        return (np.asarray(log_ns, dtype=np.int64) - (self.start_ns or 0)) / 1e9

    def _messages(self, topic: str, sensor: str | None, decode_fn) -> tuple[str, list, list[int]]:
        """The decoded messages of ``sensor``'s ``topic`` in the window (file order) and their log times."""
        sensor = self._sensor(topic, sensor)
        self._load({(sensor, topic)})
        payloads = self._payloads.get((sensor, topic), [])
        log_ns = self._log_ns.get((sensor, topic), [])
        source = f"{self.path}:{sensor}/{topic}"
        out, times = [], []
        if decode_fn is decode_quantized_batch:  # the binary frames: all in one call
            groups, errors = decode_fn(payloads, [source] * len(payloads))
            for g in groups:
                out += g.messages()
                times += [log_ns[i] for i in g.index]
            if errors:
                self.unparsed[topic] = self.unparsed.get(topic, 0) + len(errors)
        else:
            for p, t in zip(payloads, log_ns):
                try:
                    out.append(decode_fn(p, source))
                    times.append(t)
                except WireError:
                    self.unparsed[topic] = self.unparsed.get(topic, 0) + 1
        if not out:
            self._none(topic, sensor, len(payloads))
        return sensor, out, times

    def _none(self, topic: str, sensor: str, n: int):
        """ReplayError: no message of ``sensor``'s ``topic`` in the window, or none that parses."""
        if n:
            raise ReplayError(f"{self.path}: none of the {n} {topic} messages of {sensor!r} parse")
        raise ReplayError(f"{self.path} has no {topic} messages of sensor {sensor!r} in {self._window_text()}"
                          f"{' (some were lost: see .damaged)' if self.lost else ''}")

    def _window_text(self) -> str:
        if self.start_s is None and self.end_s is None:
            return "the recording"
        return f"the window {self.start_s or 0:g}-{'end' if self.end_s is None else f'{self.end_s:g}'} s"

    def raw(self, sensor: str | None = None) -> Frames:
        """The raw frames of ``sensor`` (the first sensor by name if None), in sequence order."""
        sensor = self._sensor("raw", sensor)
        self._load({(sensor, "raw")})
        payloads, log_ns = self._payloads.get((sensor, "raw"), []), self._log_ns.get((sensor, "raw"), [])
        groups, errors = decode_raw_batch(payloads, [f"{self.path}:{sensor}/raw"] * len(payloads))
        if errors:
            self.unparsed["raw"] = self.unparsed.get("raw", 0) + len(errors)
        if not groups:
            self._none("raw", sensor, len(payloads))
        if len({g.data.shape[1] for g in groups}) != 1:
            raise ReplayError(f"{self.path}: the raw frames of {sensor} change M mid-recording; split the file")
        seq = np.concatenate([g.headers.seq for g in groups])
        order = _ordered(seq)
        data = groups[0].data[order] if len(groups) == 1 else np.concatenate([g.data for g in groups])[order]
        times = np.take(log_ns, np.concatenate([g.index for g in groups])[order])
        return Frames(sensor, seq[order].astype(np.uint64),
                      np.concatenate([g.headers.timestamp_ns for g in groups])[order].astype(np.int64),
                      self._t_s(times), int(groups[0].headers.config_id[0]), data)

    def quantized(self, sensor: str | None = None) -> Quantized:
        """The quantized frames of ``sensor`` as the stream carried them, in sequence order."""
        sensor, msgs, times = self._messages("quantized", sensor, decode_quantized_batch)
        order = _ordered([m.seq for m in msgs])
        msgs = [msgs[i] for i in order]
        return Quantized(sensor, np.array([m.seq for m in msgs], np.uint64),
                         np.array([m.timestamp_ns for m in msgs], np.int64), self._t_s(np.take(times, order)),
                         msgs[0].config_id, quantized_batch(msgs))

    def targets(self, sensor: str | None = None) -> Targets:
        """The targets the localizer published for ``sensor``, in sequence order."""
        sensor, msgs, times = self._messages("targets", sensor, decode_targets)
        order = _ordered([m.seq for m in msgs])
        msgs = [msgs[i] for i in order]
        f, k = len(msgs), max(1, max(len(m.targets) for m in msgs))
        cols = {name: np.full((f, k), np.nan) for name in TARGET_FIELDS}
        for i, m in enumerate(msgs):
            for j, t in enumerate(m.targets):
                for name in cols:
                    cols[name][i, j] = t[name]
        return Targets(sensor, np.array([m.seq for m in msgs], np.uint64),
                       np.array([m.timestamp_ns for m in msgs], np.int64), self._t_s(np.take(times, order)),
                       np.array([m.published_ns for m in msgs], np.int64),
                       np.array([len(m.targets) for m in msgs]), cols["range_m"], cols["angle_deg"],
                       cols["x_m"], cols["y_m"], cols["amplitude"], msgs[0].algo)

    def tracks(self, sensor: str | None = None) -> Tracks:
        """The confirmed tracks the tracker published for ``sensor`` (recordings of ``qradar
        run --track``), one row per track per message, messages in sequence order."""
        sensor, msgs, times = self._messages("tracks", sensor, decode_tracks)
        order = _ordered([m.seq for m in msgs])
        msgs = [msgs[i] for i in order]
        rows = [(i, t) for i, m in enumerate(msgs) for t in m.tracks]
        col = {name: np.array([t.get(name, np.nan) for _, t in rows],  # an optional field absent: NaN
                              dtype=np.int64 if name in ("track_id", "hits") else bool if name == "static" else float)
               for name in TRACK_FIELDS}
        return Tracks(sensor, np.array([m.seq for m in msgs], np.uint64),
                      np.array([m.timestamp_ns for m in msgs], np.int64), self._t_s(np.take(times, order)),
                      np.array([m.published_ns for m in msgs], np.int64), np.array([len(m.tracks) for m in msgs]),
                      np.array([i for i, _ in rows], dtype=np.int64), **col)

    def losses(self, topic: str = "raw", sensor: str | None = None, rate_hz: float | None = None) -> dict[str, int]:
        """What the sequence numbers of ``sensor``'s (the first by name if None) ``topic``
        messages (raw, quantized, targets or tracks) in the window say was lost, judged in file
        order on their log times as the nodes judge them live
        (:func:`pipeline.nodes.counters.judge_seq`): ``messages`` (with a sequence number),
        ``frames_missing`` (gaps the elapsed time allows at ``rate_hz``), ``seq_resets``
        (restarts of the count), ``implausible_seq`` (numbers out of line: forged or
        replayed). ``rate_hz``: the sensor's frame rate (default: the simulated scene's,
        else the nodes' bound, DEFAULT_SEQ_RATE_HZ)."""
        if topic not in ("raw", "quantized", "targets", "tracks"):
            raise ReplayError(f"topic {topic!r} carries no sequence numbers: raw, quantized, targets or tracks")
        sensor = self._sensor(topic, sensor)
        self._load({(sensor, topic)})
        if rate_hz is None:
            rate_hz = float(self.metadata.get("qradar.scene", {}).get("rate_hz") or DEFAULT_SEQ_RATE_HZ)
        out = {"messages": 0, "frames_missing": 0, "seq_resets": 0, "implausible_seq": 0}
        track = None
        for payload, log_ns in zip(self._payloads.get((sensor, topic), []), self._log_ns.get((sensor, topic), [])):
            seq = _seq_of(topic, payload)
            if seq is None:
                continue
            track, verdict = judge_seq(track, seq, log_ns / 1e9, rate_hz)
            out["messages"] += 1
            out["frames_missing"] += verdict.missing
            out["seq_resets"] += verdict.resets
            out["implausible_seq"] += verdict.implausible
        return out

    def _health(self) -> list[tuple[HealthMsg, int]]:
        """Every health message in the window with its log time, in time order."""
        self._selected("health")
        keys = {k for k in self._keys if k[1] == "health"}
        self._load(keys)
        out = []
        for key in sorted(keys):
            for p, t in zip(self._payloads.get(key, []), self._log_ns.get(key, [])):
                try:
                    out.append((decode_health(p, f"{self.path}:{key[0]}/health"), t))
                except (WireError, ValueError):
                    self.unparsed["health"] = self.unparsed.get("health", 0) + 1
        return sorted(out, key=lambda h: h[0].timestamp_ns)

    def health(self) -> list[HealthMsg]:
        """Every health message of the window (all nodes and sensors), in time order."""
        return [h for h, _ in self._health()]

    # -- tables ------------------------------------------------------------------------------
    def table(self, topic: str = "targets", sensor: str | None = None) -> dict[str, np.ndarray]:
        """``topic``'s messages in the window as columns of equal length (what
        ``pandas.DataFrame`` takes), rows in time order, of every sensor (a ``sensor_id``
        column) or of ``sensor``: a row per target, per track and message, per frame (raw,
        quantized: their header fields) or per health message (:mod:`qradar.streams`)."""
        if topic not in TABLE_TOPICS:
            raise ReplayError(f"no table of {topic!r}: {', '.join(TABLE_TOPICS)}")
        if topic == "health":
            rows = [h for h in self._health() if sensor is None or h[0].sensor_id == sensor]
            return health_table([h for h, _ in rows], self._t_s([t for _, t in rows]))
        self._selected(topic)
        sensors = [self._sensor(topic, sensor)] if sensor is not None else sorted(
            s for s, t in self._keys if t == topic)
        self._load({(s, topic) for s in sensors})
        of = {"raw": lambda s: frames_table(self.raw(s)), "quantized": lambda s: frames_table(self.quantized(s)),
              "targets": lambda s: targets_table(self.targets(s)), "tracks": lambda s: tracks_table(self.tracks(s))}
        parts = [of[topic](s) for s in sensors if self._payloads.get((s, topic))]
        return joined(parts) if parts else empty_table(topic)

    def to_pandas(self, topic: str = "targets", sensor: str | None = None):
        """:meth:`table` as a ``pandas.DataFrame`` (pandas is an optional extra:
        ``pip install -e '.[pandas]'``)."""
        try:
            import pandas
        except ImportError:
            raise ReplayError("to_pandas needs pandas, an optional extra: pip install -e '.[pandas]' (or "
                              "pip install pandas); rec.table() gives the same columns as numpy arrays") from None
        return pandas.DataFrame(self.table(topic, sensor))


def _seq_of(topic: str, payload: bytes) -> int | None:
    """The sequence number of a message (None when it has none that reads)."""
    if topic in ("raw", "quantized"):
        if len(payload) < COMMON.size or payload[:4] != MAGIC:
            return None
        return int(COMMON.unpack_from(payload)[5])
    try:
        seq = load_json(payload, topic).get("seq")
    except (WireError, AttributeError):
        return None
    return seq if type(seq) is int and 0 <= seq < 2**64 else None


def _topics(topics) -> tuple[str, ...]:
    """``open_recording``'s ``topics``, checked: None (all), a name or names of RECORDED_TOPICS."""
    if topics is None:
        return RECORDED_TOPICS
    names = (topics,) if isinstance(topics, str) else tuple(topics)
    bad = [t for t in names if t not in RECORDED_TOPICS]
    if bad or not names:
        raise ReplayError(f"topics={list(names)!r}: each one of {', '.join(RECORDED_TOPICS)}")
    return names


def _seconds(name: str, value) -> float | None:
    if value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ReplayError(f"{name}={value!r} must be seconds from the recording's start (a number)") from None
    if not np.isfinite(v) or v < 0:
        raise ReplayError(f"{name}={value!r} must be seconds from the recording's start, >= 0")
    return v


def open_recording(path: str | Path, topics=None, start: float | None = None,
                   end: float | None = None) -> Recording:
    """Open a qradar MCAP recording: its summary and metadata now, its messages when asked
    for (see :class:`Recording`). ``topics``: the topics to read (names of
    ``RECORDED_TOPICS``: "raw", "quantized", "targets", "tracks", "health", "pointcloud";
    default all); ``start`` / ``end``: a window, s from the recording's start (its first
    message's log time), the messages logged in [start, end). A file without a summary (cut
    short by a kill, its summary damaged) is read whole now, keeping only the selection
    (``qradar recover`` writes an indexed copy)."""
    wanted = _topics(topics)
    start_s, end_s = _seconds("start", start), _seconds("end", end)
    if start_s is not None and end_s is not None and end_s <= start_s:
        raise ReplayError(f"end={end_s:g} s must come after start={start_s:g} s")
    f = McapFile(path)
    summary = f.read_index()
    rec = Recording(Path(path), {}, [], False, start_s=start_s, end_s=end_s, topics=wanted, _file=f)
    if summary is not None:
        stats = summary.statistics
        if stats is not None and stats.message_count:
            rec.start_ns, rec.end_ns = stats.message_start_time, stats.message_end_time
        else:  # the chunk index has the times too
            rec.start_ns = min(c.message_start_time for c in summary.chunk_indexes)
            rec.end_ns = max(c.message_end_time for c in summary.chunk_indexes)
        rec._keys = {k for k in map(_key, (c.topic for c in f.channels.values())) if k is not None}
    else:  # no index: one pass over the file now, the first message fixing the start
        for ch, msg in f.messages():
            key = _key(ch.topic)
            if rec.start_ns is None:
                rec.start_ns = msg.log_time
            rec.end_ns = msg.log_time if rec.end_ns is None else max(rec.end_ns, msg.log_time)
            if key is None:
                continue
            rec._keys.add(key)
            lo, hi = rec._window_ns()
            if key[1] in wanted and (lo is None or msg.log_time >= lo) and (hi is None or msg.log_time < hi):
                rec._take(key, msg.data, msg.log_time)
        rec._found.merge(f, rec.path)
        rec._loaded = set(rec._keys)
        rec.truncated = f.truncated
    rec.metadata = f.metadata_dict()
    rec.sensors = sorted({s for s, t in rec._keys if t != "health"})
    rec._keys = {k for k in rec._keys if k[1] in wanted}
    return rec
