"""MCAP files of qradar traffic: schemas, channels, tolerant reading and recovery.

One channel per zenoh key (``radar/<sensor>/<topic>``) with one schema per message type;
binary frames use the message encoding ``qradar/wire-v1`` (schema data: the byte layout,
docs/wire-formats.md), targets, tracks and health are ``json`` with a JSON schema. Targets also
go to ``<prefix>/<sensor>/pointcloud`` as ``foxglove.PointCloud`` (JSON), so Foxglove
shows them without plugins.

Reading goes record by record, so a file cut short (no footer, a chunk half written)
yields every message of its complete chunks and reports that it was truncated.

Writing is unbuffered below the MCAP writer (each write is a whole record group), so a
write error (a full disk, EFBIG, EIO) leaves nothing pending: :meth:`McapSink.abort`
cuts the file back to its last flushed chunk and, if the disk takes ~50 more bytes,
ends it with a footer (a complete MCAP without an index; ``qradar recover`` indexes it).
"""

from __future__ import annotations

import base64
import errno
import json
import os
import struct
from collections import Counter
from pathlib import Path
from typing import Iterator

import numpy as np
from mcap.exceptions import McapError
from mcap.data_stream import RecordBuilder
from mcap.records import Channel, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
from zstandard import ZstdError

from pipeline.wire import OPTIONAL_TARGET_FIELDS, TARGET_FIELDS, TOPICS, TRACK_FIELDS, TargetsMsg

from .errors import NotMcapError, RecordingExists, ReplayError
from .outputs import own_folder

WIRE_ENCODING = "qradar/wire-v1"
DOCS = Path(__file__).resolve().parents[1] / "docs" / "wire-formats.md"

#: JSON schema of the targets JSON (docs/wire-formats.md): MCAP channels and the Foxglove view
TARGETS_SCHEMA = {
    "type": "object", "title": "qradar.Targets",
    "properties": {"version": {"type": "integer"}, "type": {"const": "targets"}, "sensor_id": {"type": "string"},
                   "seq": {"type": "integer"}, "timestamp_ns": {"type": "integer"},
                   "config_id": {"type": "integer"}, "algo": {"type": "string"}, "K": {"type": "integer"},
                   "K_auto": {"type": "boolean"}, "source": {"type": "string"}, "published_ns": {"type": "integer"},
                   "targets": {"type": "array", "items": {"type": "object", "properties": {
                       f: {"type": "number"} for f in TARGET_FIELDS + OPTIONAL_TARGET_FIELDS},
                       "required": list(TARGET_FIELDS)}}},
    "required": ["version", "type", "sensor_id", "seq", "timestamp_ns", "targets"],
}
#: JSON schema of the tracks JSON (docs/wire-formats.md, pipeline.dsp.track)
TRACKS_SCHEMA = {
    "type": "object", "title": "qradar.Tracks",
    "properties": {"version": {"type": "integer"}, "type": {"const": "tracks"}, "sensor_id": {"type": "string"},
                   "seq": {"type": "integer"}, "timestamp_ns": {"type": "integer"},
                   "published_ns": {"type": "integer"},
                   "tracks": {"type": "array", "items": {"type": "object", "properties": {
                       f: {"type": "integer" if f in ("track_id", "hits") else "boolean" if f == "static"
                           else "number"} for f in TRACK_FIELDS},
                       "required": list(TRACK_FIELDS)}}},
    "required": ["version", "type", "sensor_id", "seq", "timestamp_ns", "published_ns", "tracks"],
}
_HEALTH_SCHEMA = {
    "type": "object", "title": "qradar.Health",
    "properties": {"version": {"type": "integer"}, "type": {"const": "health"}, "node": {"type": "string"},
                   "sensor_id": {"type": "string"}, "timestamp_ns": {"type": "integer"},
                   "frames_in": {"type": "integer"}, "frames_out": {"type": "integer"}, "drops": {"type": "integer"},
                   "decode_errors": {"type": "integer"}, "latency_ms": {"type": "object"},
                   "bytes_in_per_s": {"type": "number"}, "bytes_out_per_s": {"type": "number"},
                   "extra": {"type": "object"}},
    "required": ["version", "type", "node", "sensor_id", "timestamp_ns"],
}
# foxglove.PointCloud, JSON flavour (https://docs.foxglove.dev/docs/visualization/message-schemas/point-cloud)
FOXGLOVE_POINTCLOUD_SCHEMA = {
    "title": "foxglove.PointCloud", "type": "object",
    "properties": {
        "timestamp": {"type": "object", "properties": {"sec": {"type": "integer", "minimum": 0},
                                                        "nsec": {"type": "integer", "minimum": 0}}},
        "frame_id": {"type": "string"},
        "pose": {"type": "object", "properties": {
            "position": {"type": "object", "properties": {a: {"type": "number"} for a in "xyz"}},
            "orientation": {"type": "object", "properties": {a: {"type": "number"} for a in "xyzw"}}}},
        "point_stride": {"type": "integer", "minimum": 0},
        "fields": {"type": "array", "items": {"type": "object", "properties": {
            "name": {"type": "string"}, "offset": {"type": "integer", "minimum": 0},
            "type": {"type": "integer", "description": "foxglove.NumericType; 7 = FLOAT32"}}}},
        "data": {"type": "string", "contentEncoding": "base64"},
    },
}
FLOAT32 = 7  # foxglove.NumericType.FLOAT32


def pointcloud_json(msg: TargetsMsg, frame_id: str = "radar") -> bytes:
    """foxglove.PointCloud of the targets: fields x, y (m) and amplitude, float32 each."""
    pts = np.array([[t["x_m"], t["y_m"], t["amplitude"]] for t in msg.targets], dtype="<f4").reshape(-1, 3)
    obj = {
        "timestamp": {"sec": msg.timestamp_ns // 1_000_000_000, "nsec": msg.timestamp_ns % 1_000_000_000},
        "frame_id": frame_id,
        "pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
        "point_stride": 12,
        "fields": [{"name": "x", "offset": 0, "type": FLOAT32}, {"name": "y", "offset": 4, "type": FLOAT32},
                   {"name": "amplitude", "offset": 8, "type": FLOAT32}],
        "data": base64.b64encode(pts.tobytes()).decode("ascii"),
    }
    return json.dumps(obj, separators=(",", ":")).encode()


def topic_of(key: str) -> str | None:
    """``raw`` / ``quantized`` / ``targets`` / ``tracks`` / ``health`` / ``pointcloud`` of a qradar key, else None."""
    last = key.rsplit("/", 1)[-1]
    return last if last in TOPICS + ("pointcloud",) else None


def describe_os_error(exc: BaseException) -> str:
    """``No space left on device (ENOSPC)``: an OSError's text and errno name."""
    if isinstance(exc, OSError) and exc.errno is not None:
        return f"{exc.strerror or exc} ({errno.errorcode.get(exc.errno, exc.errno)})"
    return str(exc) or type(exc).__name__


class _RecordFile:
    """The file below an MCAP Writer: each ``write`` goes to the OS at once (no user-space
    buffer), and ``pos`` is the byte count the OS took, so after a write error the file
    can be cut back to a record boundary with nothing left behind in a buffer."""

    def __init__(self, path: Path, overwrite: bool = False):
        mode = os.O_TRUNC if overwrite else os.O_EXCL  # exclusive: FileExistsError if the path exists
        self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | mode | os.O_CLOEXEC, 0o644)
        self.pos = 0

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        done = 0
        while done < len(view):  # a short write (the disk filling up) is followed by an OSError
            n = os.write(self.fd, view[done:])
            if n <= 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            done += n
            self.pos += n
        return done

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        """Nothing to do: every write already went to the OS."""

    def close(self) -> None:
        if self.fd >= 0:
            fd, self.fd = self.fd, -1
            os.close(fd)


def _tail() -> bytes:
    """DataEnd, a Footer without a summary section, and the closing magic (50 bytes)."""
    builder = RecordBuilder()
    DataEnd(data_section_crc=0).write(builder)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(builder)
    return bytes(builder.end()) + b"\x89MCAP0\r\n"


class McapSink:
    """A Writer with one schema per message type and one channel per key.

    ``kept_bytes`` / ``kept_messages``: what the file holds up to its last :meth:`flush`
    (what survives a write error); ``pending_by_topic``: messages written since, by topic.
    Writing methods raise OSError on a write error; then :meth:`abort` closes the file.

    The file is created exclusively: an existing ``path`` is a :class:`RecordingExists`
    (qradar does not overwrite a recording), unless ``overwrite`` (for qradar's own
    outputs in a folder of its own, e.g. ``reprocess --out``)."""

    def __init__(self, path: Path, chunk_size: int = 1 << 20, overwrite: bool = False):
        self.path = Path(path)
        own_folder(self.path.parent, self.path)  # the recording's own folder, never the folders above it
        try:
            self._fh = _RecordFile(self.path, overwrite)
        except FileExistsError:
            raise RecordingExists.at(self.path) from None
        except OSError as exc:
            raise ReplayError(f"cannot write {self.path}: {describe_os_error(exc)}") from None
        self.writer = Writer(self._fh, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        try:
            self.writer.start(profile="", library="qradar")
        except OSError as exc:
            self._fh.close()
            self.path.unlink(missing_ok=True)
            raise ReplayError(f"cannot write {self.path}: {describe_os_error(exc)}") from None
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._topics: dict[int, str] = {}  # channel id -> topic (or "other"), for the counts
        self.messages = 0
        self.kept_bytes = 0
        self.kept_messages = 0
        self.pending_by_topic: Counter[str] = Counter()  # written since the last flush, by topic
        self.by_topic: Counter[str] = Counter()  # flushed, by topic
        self.removed = False
        self.closed = False

    @property
    def size(self) -> int:
        """Bytes written to the file so far."""
        return self._fh.pos

    def _schema(self, topic: str) -> int:
        if topic not in self._schemas:
            if topic in ("raw", "quantized"):
                name = "qradar.RawFrame" if topic == "raw" else "qradar.QuantizedFrame"
                data = DOCS.read_bytes() if DOCS.exists() else b"qradar wire format v1"
                sid = self.writer.register_schema(name, WIRE_ENCODING, data)
            elif topic == "pointcloud":
                sid = self.writer.register_schema("foxglove.PointCloud", "jsonschema",
                                                  json.dumps(FOXGLOVE_POINTCLOUD_SCHEMA).encode())
            else:
                schema = {"targets": TARGETS_SCHEMA, "tracks": TRACKS_SCHEMA}.get(topic, _HEALTH_SCHEMA)
                sid = self.writer.register_schema(schema["title"], "jsonschema", json.dumps(schema).encode())
            self._schemas[topic] = sid
        return self._schemas[topic]

    def channel(self, key: str) -> int:
        cid = self._channels.get(key)
        if cid is None:
            topic = topic_of(key) or "raw"
            encoding = WIRE_ENCODING if topic in ("raw", "quantized") else "json"
            cid = self.writer.register_channel(key, encoding, self._schema(topic))
            self._channels[key] = cid
            self._topics[cid] = topic_of(key) or "other"
        return cid

    def write(self, key: str, data: bytes, log_time_ns: int, publish_time_ns: int, sequence: int) -> None:
        cid = self.channel(key)
        self.writer.add_message(cid, log_time=log_time_ns, data=data,
                                publish_time=publish_time_ns, sequence=sequence & 0xFFFFFFFF)
        self.messages += 1
        self.pending_by_topic[self._topics[cid]] += 1

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self.writer.add_metadata(name, {k: str(v) for k, v in data.items()})

    def flush(self) -> None:
        """Close the chunk in progress and push it to the file (readable after a kill).
        OSError also when the file was removed meanwhile (it would fill the disk unseen)."""
        self.writer.flush()
        if os.fstat(self._fh.fd).st_nlink == 0:
            self.removed = True
            raise OSError(errno.ENOENT, "the file was removed while being written")
        self.kept_bytes, self.kept_messages = self._fh.pos, self.messages
        self.by_topic.update(self.pending_by_topic)
        self.pending_by_topic.clear()

    def close(self) -> None:
        """Finish the file (summary and index). OSError on a write error: then :meth:`abort`."""
        if self.closed:
            return
        self.writer.finish()
        self.closed = True
        self._fh.close()

    def abort(self) -> dict:
        """After a write error: cut the file back to its last flushed chunk, end it with a
        footer if the disk takes it, close it. Never raises. Returns {"path", "bytes",
        "messages" (kept), "lost" (written after the last flush, or all when the file was
        removed), "lost_by_topic", "footer"}."""
        if self.removed:  # nothing is kept; free its space
            self.kept_bytes, self.kept_messages = 0, 0
            self.pending_by_topic.update(self.by_topic)
        out = {"path": str(self.path), "bytes": self.kept_bytes, "messages": self.kept_messages,
               "lost": self.messages - self.kept_messages, "lost_by_topic": dict(self.pending_by_topic),
               "footer": False}
        if self.closed:
            return out
        self.closed = True
        fd = self._fh.fd
        try:
            os.ftruncate(fd, self.kept_bytes)  # shrinking needs no space
            if self.removed:
                raise OSError(errno.ENOENT, "removed")
            tail = _tail()
            try:
                out["footer"] = os.pwrite(fd, tail, self.kept_bytes) == len(tail)
            except OSError:
                pass
            if out["footer"]:
                out["bytes"] += len(tail)
            else:
                os.ftruncate(fd, self.kept_bytes)  # a tail half written is worse than none
        except OSError:
            pass  # EIO: what the file holds stays as it is; the reader stops at the first bad record
        try:
            self._fh.close()
        except OSError:
            pass
        return out


#: What mcap's StreamReader raises on a file cut short or corrupted (measured on real
#: recordings cut at every record boundary and with header and random bytes overwritten):
#: McapError (EndOfFile, RecordLengthLimitExceeded, InvalidMagic), struct.error (a field
#: cut short), ValueError (UnicodeDecodeError in a string field), OverflowError and
#: MemoryError (a corrupted length the read tries to allocate), ZstdError (a zstd chunk),
#: RuntimeError (what lz4.frame raises for an lz4 chunk).
_CUT_SHORT = (McapError, struct.error, ValueError, OverflowError, MemoryError, ZstdError, RuntimeError)


class McapFile:
    """Tolerant sequential reader. :meth:`messages` yields (channel, message) for every
    message of the file's complete chunks, in file order; schemas, channels and metadata
    fill in as they are met. When the file was cut short, iteration ends quietly and
    ``truncated`` / ``truncation_reason`` say so. Not MCAP: NotMcapError."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.metadata: list[Metadata] = []
        self.truncated = False
        self.truncation_reason = ""

    def messages(self) -> Iterator[tuple[Channel, Message]]:
        self.schemas, self.channels, self.metadata = {}, {}, []
        self.truncated, self.truncation_reason = False, ""
        try:
            fh = open(self.path, "rb")
        except OSError as exc:
            raise ReplayError(f"cannot open {self.path}: {exc.strerror or exc}") from None
        with fh:
            magic = fh.read(8)
            if magic != b"\x89MCAP0\r\n":
                raise NotMcapError(f"{self.path} is not an MCAP file (it starts with {magic!r})")
            fh.seek(0)
            records = StreamReader(fh, record_size_limit=1 << 30).records
            while True:
                try:
                    rec = next(records)
                except StopIteration:
                    return
                except _CUT_SHORT as exc:
                    self.truncated = True
                    self.truncation_reason = f"{type(exc).__name__}: {exc}".rstrip(": ")
                    return
                if isinstance(rec, Schema):
                    self.schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    self.channels[rec.id] = rec
                elif isinstance(rec, Metadata):
                    self.metadata.append(rec)
                elif isinstance(rec, Message):
                    ch = self.channels.get(rec.channel_id)
                    if ch is not None:
                        yield ch, rec
                elif isinstance(rec, Footer):
                    return

    def scan(self) -> int:
        """Read the whole file (filling channels and metadata); returns the message count."""
        return sum(1 for _ in self.messages())

    def metadata_dict(self) -> dict[str, dict[str, str]]:
        return {md.name: dict(md.metadata) for md in self.metadata}


def qradar_channels(channels: dict[int, Channel]) -> dict[int, Channel]:
    """Channels whose topic is a qradar key (``.../<sensor>/raw|quantized|targets|health``)."""
    return {cid: ch for cid, ch in channels.items() if topic_of(ch.topic) in TOPICS}


def recover(src: str | Path, dst: str | Path, overwrite: bool = False) -> dict:
    """Write a complete, indexed MCAP from whatever ``src`` holds (e.g. after SIGKILL), a new
    file unless ``overwrite``. Returns {"messages", "truncated", "reason"}."""
    if Path(src).resolve() == Path(dst).resolve():
        raise ReplayError(f"recover reads {src} and writes a new file: give another output than the file itself")
    f = McapFile(src)
    sink = McapSink(Path(dst), overwrite=overwrite)
    n = 0
    try:
        for ch, msg in f.messages():
            sink.write(ch.topic, msg.data, msg.log_time, msg.publish_time, msg.sequence)
            n += 1
        for md in f.metadata:
            sink.metadata(md.name, dict(md.metadata))
        sink.close()
    except OSError as exc:
        kept = sink.abort()
        raise ReplayError(f"cannot write {dst}: {describe_os_error(exc)} (it holds {kept['messages']} messages "
                          f"of {src})") from None
    finally:
        if not sink.closed:  # src was not MCAP: dst ends empty but valid
            try:
                sink.close()
            except OSError:
                sink.abort()
    return {"messages": n, "truncated": f.truncated, "reason": f.truncation_reason}
