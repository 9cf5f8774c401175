"""MCAP files of qradar traffic: schemas, channels, writing, and recovery.

One channel per zenoh key (``radar/<sensor>/<topic>``) with one schema per message type;
binary frames use the message encoding ``qradar/wire-v1`` (schema data: their byte layout as
JSON, :func:`frame_schema`), targets, tracks and health are ``json`` with a JSON schema made
from the one definition of their fields (:mod:`pipeline.wire.fields`). Every schema comes
from the package's code, so a recording's bytes do not depend on how qradar was installed.
The recorder derives channels beside a sensor's messages (:data:`DERIVED`), so Foxglove
shows them without plugins: ``<prefix>/<sensor>/pointcloud`` (``foxglove.PointCloud``, JSON:
the targets), ``<prefix>/<sensor>/scene`` (``foxglove.SceneUpdate``, JSON: the tracks'
and targets' uncertainty ellipses) and ``<prefix>/<sensor>/profile`` (``qradar.RangeProfile``:
the range profile per receiver, for a Plot panel). Every chunk defines the channels of its messages again (MCAP
allows identical channel records anywhere before their messages), so a damaged chunk in a
file without a summary loses its own messages only.

Reading (:class:`McapFile`, :mod:`replay.mcapread`) checks every chunk's CRC: a damaged
chunk is named and its messages counted lost, never returned; a file cut short (no
footer, a chunk half written) yields every message of its complete chunks and reports
that it was truncated. :func:`recover` writes what reads into a new, complete file.

Writing checks each message's times and channel before mcap's Writer packs any byte of
it, and reads back what each flush wrote (:meth:`McapSink.flush`). It is unbuffered below
the MCAP writer (each write is a whole record group), so a write error (a full disk,
EFBIG, EIO) leaves nothing pending: :meth:`McapSink.abort` cuts the file back to its last
flushed chunk and, if the disk takes ~50 more bytes, ends it with a footer (a complete
MCAP without an index; ``qradar recover`` indexes it).
"""

from __future__ import annotations

import errno
import itertools
import json
import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.data_stream import RecordBuilder
from mcap.records import Channel, DataEnd, Footer
from mcap.writer import CompressionType, Writer

from pipeline.keys import DERIVED_TOPICS
from pipeline.wire import COMMON_DTYPE, COMMON_FIELDS, QUANT_DTYPE, QUANT_EXT_FIELDS, TOPICS
from pipeline.wire import MAGIC as FRAME_MAGIC
from pipeline.wire.fields import HEALTH, PROFILE, TARGETS, TRACKS, json_schema
from pipeline.wire.foxglove import POINTCLOUD_SCHEMA, SCENE_UPDATE_SCHEMA, pointcloud_json, profile_json, scene_json

from .errors import RecordingExists, ReplayError, UnwritableMessage
from .outputs import check_file_kind, check_not_input, own_folder
from .mcapcheck import MAGIC, METADATA_CRC_KEY, metadata_crc, read_summary, written_counts
from .mcapread import DamagedChunk, McapFile, check_mcap

__all__ = ["DamagedChunk", "McapFile", "McapSink", "pointcloud_json", "profile_json", "qradar_channels", "recover",
           "scene_json", "topic_of"]

WIRE_ENCODING = "qradar/wire-v1"

#: JSON Schemas of the JSON channels, made from the one definition of their fields (pipeline.wire.fields)
TARGETS_SCHEMA = json_schema(TARGETS)
TRACKS_SCHEMA = json_schema(TRACKS)
HEALTH_SCHEMA = json_schema(HEALTH)
PROFILE_SCHEMA = json_schema(PROFILE)
FOXGLOVE_POINTCLOUD_SCHEMA = POINTCLOUD_SCHEMA
#: the channels the recorder derives from a sensor's messages, beside them: topic -> (schema name, JSON Schema)
DERIVED = {"pointcloud": ("foxglove.PointCloud", POINTCLOUD_SCHEMA),
           "scene": ("foxglove.SceneUpdate", SCENE_UPDATE_SCHEMA), "profile": (PROFILE.title, PROFILE_SCHEMA)}
assert tuple(DERIVED) == DERIVED_TOPICS
_JSON_SCHEMAS = {"targets": TARGETS_SCHEMA, "tracks": TRACKS_SCHEMA, "health": HEALTH_SCHEMA}


def frame_schema(topic: str) -> tuple[str, bytes]:
    """The schema (name, data) of the raw or quantized channels: their byte layout as JSON,
    made from the frame layout table (pipeline.wire.frames.COMMON_FIELDS, QUANT_EXT_FIELDS;
    docs/wire-formats.md says the same in prose): the header fields (name, offset, numpy
    type) and what follows them."""
    fields = COMMON_FIELDS + (QUANT_EXT_FIELDS if topic == "quantized" else ())
    dtype = QUANT_DTYPE if topic == "quantized" else COMMON_DTYPE
    header = [{"name": name, "offset": dtype.fields[name][1],
               "type": np.dtype(dt).str if isinstance(dt, str) else f"{np.dtype(dt[0]).str}[{dt[1][0]}]"}
              for name, _, dt in fields]
    body = ("codes: bits bits each, most significant bit first, C order of (M, 2, 2) (measurement, antenna, "
            "I/Q), the last byte zero-padded; a code c stands for delta * (c - 2**(bits - 1) + 1/2)"
            if topic == "quantized" else "frame: (M, 2) complex64, little-endian, C order (measurement, antenna); "
            "ADC full scale")
    name = "qradar.QuantizedFrame" if topic == "quantized" else "qradar.RawFrame"
    layout = {"encoding": WIRE_ENCODING, "byte_order": "little", "magic": FRAME_MAGIC.decode(),
              "header_bytes": dtype.itemsize, "header": header, "body": body}
    return name, json.dumps(layout, separators=(",", ":")).encode()


def topic_of(key: str) -> str | None:
    """``raw`` / ``quantized`` / ``targets`` / ``tracks`` / ``health`` or a derived channel
    (``pointcloud``, ``scene``, ``profile``) of a qradar key, else None."""
    last = key.rsplit("/", 1)[-1]
    return last if last in TOPICS or last in DERIVED else None


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
        # exclusive: FileExistsError if the path exists; replacing: never through a link (ELOOP)
        mode = os.O_TRUNC | os.O_NOFOLLOW if overwrite else os.O_EXCL
        self.fd = os.open(path, os.O_RDWR | os.O_CREAT | mode | os.O_CLOEXEC, 0o644)
        self.pos = 0

    def pread(self, offset: int, n: int) -> bytes:
        """``n`` bytes from ``offset`` (what was written there), read back from the OS."""
        parts, done = [], 0
        while done < n:
            part = os.pread(self.fd, n - done, offset + done)
            if not part:
                raise OSError(errno.EIO, f"read back {done} of {n} bytes at {offset}")
            parts.append(part)
            done += len(part)
        return b"".join(parts)

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
    return bytes(builder.end()) + MAGIC


#: the most channels a file can hold: MCAP's channel ids are uint16 (0 is no channel)
MAX_FILE_CHANNELS = 65535
#: the times an MCAP record holds, and qradar's timestamps: integer ns in [0, 2**63)
MAX_TIME_NS = 2**63


def check_time(name: str, value) -> int:
    """``value`` as an int in [0, 2**63) (ns), else :class:`UnwritableMessage` naming it."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 0 <= value < MAX_TIME_NS:
        raise UnwritableMessage("time", f"{name}={value!r} is not a time a recording holds (integer ns in "
                                        f"[0, 2**63))")
    return int(value)


@dataclass
class FlushCheck:
    """What a flush wrote, read back: ``readable`` messages by topic (they are in the file,
    in chunks whose CRC matches), ``unreadable`` by topic (written, not readable back: an
    error), ``problems`` one line each."""

    readable: Counter = field(default_factory=Counter)
    unreadable: Counter = field(default_factory=Counter)
    problems: list[str] = field(default_factory=list)


class McapSink:
    """A Writer with one schema per message type and one channel per key.

    ``kept_bytes`` / ``kept_messages``: what the file holds up to its last :meth:`flush`
    (what survives a write error); ``pending_by_topic``: messages written since, by topic.
    Writing methods raise OSError on a write error; then :meth:`abort` closes the file.
    Before any byte of a message goes to mcap's Writer its times, sequence and channel are
    checked (:class:`UnwritableMessage`): a record the Writer cannot pack whole would leave
    the chunk it was packed into unreadable. Each :meth:`flush` reads back what it wrote and
    returns what is readable (:class:`FlushCheck`); :meth:`close` checks the summary's
    statistics against it (``problems``).

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
        # every chunk defines the channels of its messages (mcap's Writer defines each once, in the chunk where
        # it was registered: that chunk damaged, a file without a summary would lose the channel's every message)
        self._chunk_builder = getattr(self.writer, "_Writer__chunk_builder", None)
        self._writer_channels = getattr(self.writer, "_Writer__channels", None)
        self._writer_stats = getattr(self.writer, "_Writer__statistics", None)
        self._chunk_no = -1
        self._in_chunk: set[int] = set()  # channels defined in the chunk being built
        self._channel_records: dict[int, bytes] = {}  # each channel's record, as written (~80 B each)
        self.messages = 0
        self.kept_bytes = self._fh.pos  # the magic and the header
        self.kept_messages = 0
        self.pending_by_topic: Counter[str] = Counter()  # written since the last flush, by topic
        self._pending_by_channel: Counter[int] = Counter()
        self.by_topic: Counter[str] = Counter()  # flushed and readable back, by topic
        self.readable = 0  # messages read back after the flushes
        self.problems: list[str] = []  # what did not read back (flushes, the summary at close)
        self.removed = False
        self.closed = False

    @property
    def size(self) -> int:
        """Bytes written to the file so far."""
        return self._fh.pos

    @property
    def n_channels(self) -> int:
        return len(self._channels)

    def keys(self) -> list[str]:
        """The keys with a channel in this file."""
        return list(self._channels)

    def _schema(self, topic: str) -> int:
        if topic not in self._schemas:
            if topic in ("raw", "quantized"):
                name, data = frame_schema(topic)
                sid = self.writer.register_schema(name, WIRE_ENCODING, data)
            else:
                name, schema = DERIVED.get(topic) or (None, _JSON_SCHEMAS.get(topic, HEALTH_SCHEMA))
                sid = self.writer.register_schema(name or schema["title"], "jsonschema", json.dumps(schema).encode())
            self._schemas[topic] = sid
        return self._schemas[topic]

    def channel(self, key: str) -> int:
        cid = self._channels.get(key)
        if cid is None:
            if len(self._channels) >= MAX_FILE_CHANNELS:
                raise UnwritableMessage("channels", f"{self.path} holds {MAX_FILE_CHANNELS} channels, the most an "
                                                    f"MCAP file can: no channel for {key}")
            topic = topic_of(key) or "raw"
            encoding = WIRE_ENCODING if topic in ("raw", "quantized") else "json"
            cid = self.writer.register_channel(key, encoding, self._schema(topic))
            self._channels[key] = cid
            self._topics[cid] = topic_of(key) or "other"
            self._new_chunk()
            self._in_chunk.add(cid)  # register_channel defined it in the chunk being built
        return cid

    def _new_chunk(self) -> bool:
        """Whether mcap's Writer started a chunk since the last call (then no channel is
        defined in it yet)."""
        n = -1 if self._writer_stats is None else self._writer_stats.chunk_count
        if n == self._chunk_no:
            return False
        self._chunk_no = n
        self._in_chunk.clear()
        return True

    def _define_in_chunk(self, cid: int) -> None:
        """Define channel ``cid`` in the chunk being built, if it is not yet (MCAP allows a
        channel record again, identical, anywhere before the messages that use it)."""
        self._new_chunk()
        if cid in self._in_chunk or self._chunk_builder is None or self._writer_channels is None:
            return
        record = self._channel_records.get(cid)
        if record is None:
            builder = RecordBuilder()
            self._writer_channels[cid].write(builder)
            record = self._channel_records[cid] = bytes(builder.end())
        self._chunk_builder.record_writer.write(record)
        self._in_chunk.add(cid)

    def write(self, key: str, data: bytes, log_time_ns: int, publish_time_ns: int, sequence: int) -> None:
        """One message; :class:`UnwritableMessage` (nothing written) when its times are not
        integer ns in [0, 2**63) or the file has no channel left for a new key. The
        sequence is kept modulo 2**32 (MCAP's is uint32)."""
        log_time_ns = check_time("log time", log_time_ns)
        publish_time_ns = check_time("publish time", publish_time_ns)
        if isinstance(sequence, bool) or not isinstance(sequence, (int, np.integer)):
            raise UnwritableMessage("shape", f"sequence {sequence!r} is not an integer")
        cid = self.channel(key)
        self._define_in_chunk(cid)
        self.writer.add_message(cid, log_time=log_time_ns, data=data, publish_time=publish_time_ns,
                                sequence=int(sequence) & 0xFFFFFFFF)
        self.messages += 1
        self.pending_by_topic[self._topics[cid]] += 1
        self._pending_by_channel[cid] += 1

    def metadata(self, name: str, data: dict[str, str]) -> None:
        """A metadata record of ``data`` (values as text), with its CRC (:func:`metadata_crc`)."""
        entries = {k: str(v) for k, v in data.items() if k != METADATA_CRC_KEY}
        entries[METADATA_CRC_KEY] = metadata_crc(entries)
        self.writer.add_metadata(name, entries)

    def flush(self) -> FlushCheck:
        """Close the chunk in progress and push it to the file (readable after a kill), then
        read back what went to the file since the last flush: every chunk's CRC and every
        message of each channel counted (:class:`FlushCheck`). OSError also when the file was
        removed meanwhile (it would fill the disk unseen)."""
        self.writer.flush()
        if os.fstat(self._fh.fd).st_nlink == 0:
            self.removed = True
            raise OSError(errno.ENOENT, "the file was removed while being written")
        start, end = self.kept_bytes, self._fh.pos
        check = FlushCheck()
        if self._pending_by_channel or end > start:
            got = written_counts(self._fh.pread(start, end - start), start)
            check.problems = got.problems
            for cid, n in self._pending_by_channel.items():
                ok = min(n, got.messages.get(cid, 0))
                topic = self._topics[cid]
                check.readable[topic] += ok
                if n > ok:
                    check.unreadable[topic] += n - ok
            extra = sum(got.messages.values()) - sum(check.readable.values())
            if extra:
                check.problems.append(f"{extra} messages read back that were not written")
            if check.unreadable and not check.problems:
                check.problems.append(f"messages written and not read back: {dict(check.unreadable)}")
            if check.problems:
                self.problems += [f"{self.path}: {p}" for p in check.problems]
        self.kept_bytes, self.kept_messages = end, self.messages
        self.by_topic.update(check.readable)
        self.readable += sum(check.readable.values())
        self.pending_by_topic.clear()
        self._pending_by_channel.clear()
        return check

    def close(self) -> FlushCheck:
        """Finish the file (summary and index) and check it: the chunks written since the
        last flush read back, and the summary's statistics count what was read back (a
        mismatch goes to ``problems``). OSError on a write error: then :meth:`abort`."""
        if self.closed:
            return FlushCheck()
        check = self.flush()
        self.writer.finish()
        self.closed = True
        try:
            size = self._fh.pos
            summary = read_summary(self._fh.pread(0, size), size)
            stats = None if summary.summary is None else summary.summary.statistics
            if stats is None:
                why = summary.problem or "no summary"
                self.problems.append(f"{self.path}: its summary does not read back ({why})")
            elif stats.message_count != self.readable:
                self.problems.append(f"{self.path}: its statistics count {stats.message_count} messages, "
                                     f"{self.readable} read back")
        finally:
            self._fh.close()
        return check

    def abort(self) -> dict:
        """After a write error: cut the file back to its last flushed chunk, end it with a
        footer if the disk takes it, close it. Never raises. Returns {"path", "bytes",
        "messages" (kept), "lost" (written after the last flush, or all when the file was
        removed), "lost_by_topic", "flushed_lost_by_topic" (those of them that a flush had
        read back: all of the file's when it was removed), "footer"}."""
        flushed_lost: Counter[str] = Counter()
        if self.removed:  # nothing is kept; free its space
            self.kept_bytes, self.kept_messages = 0, 0
            flushed_lost = Counter(self.by_topic)
            self.pending_by_topic.update(self.by_topic)
        out = {"path": str(self.path), "bytes": self.kept_bytes, "messages": self.kept_messages,
               "lost": self.messages - self.kept_messages, "lost_by_topic": dict(self.pending_by_topic),
               "flushed_lost_by_topic": dict(flushed_lost), "footer": False}
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


def qradar_channels(channels: dict[int, Channel]) -> dict[int, Channel]:
    """Channels whose topic is a qradar key (``.../<sensor>/raw|quantized|targets|health``)."""
    return {cid: ch for cid, ch in channels.items() if topic_of(ch.topic) in TOPICS}


#: damaged chunks described in a recovered file's ``qradar.recovery`` metadata (the rest counted)
RECOVERY_LISTED = 100


def recover(src: str | Path, dst: str | Path, overwrite: bool = False) -> dict:
    """Write a complete, indexed MCAP from whatever ``src`` holds (e.g. after SIGKILL): every
    message that reads back, never one of a damaged chunk (each named, with its messages
    counted lost, in the result and in the new file's ``qradar.recovery`` metadata).
    A new file unless ``overwrite``. Returns :meth:`McapFile.report` (``messages``: those copied)."""
    check_not_input(dst, (src,), "recover's output")  # by any name: a link too
    check_file_kind(dst, "recover's output")  # a folder or a link (to another file): said as such
    check_mcap(src)  # a missing, empty or foreign file: refused before an output exists
    f = McapFile(src)
    messages = f.messages()
    first = next(messages, None)
    if first is None:  # nothing that reads back: no output that looks like a recovery
        raise ReplayError(f"{src} holds no complete message to recover ({os.path.getsize(src)} bytes); "
                          f"{dst} not written")
    sink = McapSink(Path(dst), overwrite=overwrite)
    try:
        for ch, msg in itertools.chain((first,), messages):
            sink.write(ch.topic, msg.data, msg.log_time, msg.publish_time, msg.sequence)
        for md in f.metadata:
            sink.metadata(md.name, dict(md.metadata))
        if not f.intact:
            lines = f.damage_lines()
            sink.metadata("qradar.recovery", {
                "source": str(src), "messages": str(f.read), "lost": str(f.lost),
                "lost_by_topic": json.dumps(f.lost_by_topic), "truncated": str(f.truncated).lower(),
                "damage": json.dumps(lines[:RECOVERY_LISTED] + ([f"... {len(lines) - RECOVERY_LISTED} more"]
                                                                if len(lines) > RECOVERY_LISTED else []))})
        sink.close()
    except OSError as exc:
        kept = sink.abort()
        raise ReplayError(f"cannot write {dst}: {describe_os_error(exc)} (it holds {kept['messages']} messages "
                          f"of {src})") from None
    finally:
        if not sink.closed:  # src stopped reading: dst ends with what it read, valid
            try:
                sink.close()
            except OSError:
                sink.abort()
    out = f.report()
    out["reason"] = f.truncation_reason
    if sink.problems:
        out["problems"] = out["problems"] + sink.problems
    return out
