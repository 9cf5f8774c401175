"""Reading MCAP files of qradar traffic with every checksum checked (:class:`McapFile`):
a damaged chunk is named and its messages counted lost, never returned as data.

A file with a summary whose CRC matches is read through its chunk index (a damaged chunk
cannot hide the next ones), and a selection (a log time window, some channels) reads only
the chunks that hold it; any other file (cut short by a kill, its summary damaged or
absent) record by record, going on after records that do not frame at the next record
that provably starts one (:func:`replay.mcapcheck.resync`). A file cut short yields
every message of its complete chunks and says it was truncated. :meth:`McapFile.read_index`
reads the summary and the metadata alone (no chunk), for what a file holds at a glance.
"""

from __future__ import annotations

import logging
import mmap
import os
import time
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

from mcap.opcode import Opcode
from mcap.records import Channel, ChunkIndex, Message, Metadata, Schema
from mcap.summary import Summary

from .errors import Damage, NotMcapError, ReplayError
from .mcapcheck import (MAGIC, MESSAGE_HEAD, METADATA_CRC_KEY, RECORD_HEAD, check_metadata, chunk_head, frame,
                        message_index_count, open_chunk, parse_record, plausible_opcode, read_summary, resync,
                         SummaryRead)


def _log_time(ns: int | None) -> str:
    if ns is None:
        return "?"
    if ns >= 10**15:  # ns since the epoch: UTC to the millisecond
        return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(ns // 10**9)) + f".{ns // 10**6 % 1000:03d}Z"
    return f"{ns} ns"


@dataclass
class DamagedChunk:
    """A chunk (or a stretch of records) of a file that does not read: at byte ``offset``,
    ``length`` bytes, its messages' log times ``start_ns`` to ``end_ns`` (None: unknown),
    ``lost_by_channel`` the messages it held that were not returned (channel id -> count,
    from the message index records after it; ``counted``: the count is complete), ``reason``."""

    offset: int
    length: int
    start_ns: int | None
    end_ns: int | None
    lost_by_channel: Counter
    counted: bool
    reason: str

    def to_dict(self, topic) -> dict:
        """JSON-ready, channel ids named by ``topic(channel id)``."""
        lost: dict[str, int] = {}
        for cid, n in sorted(self.lost_by_channel.items()):
            lost[topic(cid)] = lost.get(topic(cid), 0) + n
        return {"offset": self.offset, "length": self.length, "start_ns": self.start_ns, "end_ns": self.end_ns,
                "lost": sum(lost.values()), "lost_by_topic": lost, "counted": self.counted, "reason": self.reason}

    def describe(self, topic) -> str:
        d = self.to_dict(topic)
        what = "chunk" if self.start_ns is not None else "records"
        n = f"{d['lost']} messages" if self.counted else (f"at least {d['lost']} messages" if d["lost"] else
                                                          "an unknown number of messages")
        topics = ", ".join(f"{t} ({c})" for t, c in d["lost_by_topic"].items()) or "topics unknown"
        return (f"{what} at byte {self.offset} ({self.length} bytes, log time {_log_time(self.start_ns)} to "
                f"{_log_time(self.end_ns)}): {self.reason}; {n} lost, not returned: {topics}")


class ReadFindings:
    """What reading an MCAP file found (the base of :class:`McapFile`): ``read`` messages
    returned, ``damaged`` chunks, ``lost_by_channel`` (damaged chunks, channels whose
    definition was lost, statistics short), ``problems`` (one line each), ``truncated``
    and ``truncation_reason``, ``complete`` (the whole file was read). Channel ids are
    named through ``channels``, which the reader fills."""

    channels: dict[int, Channel]

    def _reset_findings(self) -> None:
        self.truncated = False
        self.truncation_reason = ""
        self.damaged: list[DamagedChunk] = []
        self.problems: list[str] = []
        self.lost_by_channel: Counter[int] = Counter()
        self.unchecked_chunks = 0  # chunks written without a CRC (other writers may)
        self.read = 0  # messages returned
        self._read_by_channel: Counter[int] = Counter()
        self._statistics = None
        self.complete = False

    def _damage(self, d: DamagedChunk, read: Counter) -> None:
        d.lost_by_channel = d.lost_by_channel - read  # the messages of a chunk cut inside that were returned
        self.damaged.append(d)
        self.lost_by_channel.update(d.lost_by_channel)

    def _account(self) -> None:
        """After the whole file: the summary's statistics against what was read and what
        damaged chunks held; the difference, by channel, is lost too (after a selection of
        channels, theirs; not after a time window)."""
        whole = self.start_ns is None and self.end_ns is None
        stats = self._statistics if whole else None
        if stats is not None:
            short = counted = 0
            for cid, n in stats.channel_message_counts.items():
                if self._channel is not None and not self._selected(cid):
                    continue
                counted += n
                missing = n - self._read_by_channel[cid] - self.lost_by_channel[cid]
                if missing > 0:
                    self.lost_by_channel[cid] += missing
                    short += missing
            if short:
                of = "" if self._channel is None else " on the channels read"
                self.problems.append(f"the summary's statistics count {counted} messages{of}; {self.read} "
                                     f"read and {self.lost - short} in damaged chunks: {short} more are in no "
                                     "readable record (lost)")
            for d in self.damaged:
                d.counted = True  # the statistics complete every count
        orphans = sum(n for cid, n in self.lost_by_channel.items() if cid not in self.channels)
        if orphans:
            self.problems.append(f"{orphans} messages are on channels whose definition was in a damaged chunk (lost)")
        if self.unchecked_chunks:
            self.problems.append(f"{self.unchecked_chunks} chunks carry no CRC: their messages are read unchecked")

    # -- what was found ----------------------------------------------------------------------
    def topic(self, channel_id: int) -> str:
        ch = self.channels.get(channel_id)
        return ch.topic if ch is not None else f"channel {channel_id}"

    @property
    def lost(self) -> int:
        """Messages the file was written with that are not returned (damaged chunks, lost
        channels, statistics short)."""
        return sum(self.lost_by_channel.values())

    @property
    def lost_by_topic(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for cid, n in self.lost_by_channel.items():
            if n:
                out[self.topic(cid)] = out.get(self.topic(cid), 0) + n
        return out

    @property
    def intact(self) -> bool:
        """Read whole: nothing damaged, nothing lost, not cut short, no problem."""
        return not (self.damaged or self.lost or self.problems or self.truncated)

    def damage_lines(self) -> list[str]:
        """One line per damaged chunk and per problem (empty when the file read whole)."""
        return [d.describe(self.topic) for d in self.damaged] + list(self.problems)

    def report(self) -> dict:
        """What reading found, JSON-ready: messages read, lost (by topic), damaged chunks,
        problems, truncation."""
        return {"file": str(self.path), "intact": self.intact, "messages": self.read, "lost": self.lost,
                "lost_by_topic": self.lost_by_topic,
                "damaged_chunks": [d.to_dict(self.topic) for d in self.damaged], "problems": list(self.problems),
                "truncated": self.truncated, "truncation_reason": self.truncation_reason}

    def warn(self, log: logging.Logger, what: str) -> None:
        """Log one warning line per damaged chunk and problem, saying ``what`` was done."""
        for line in self.damage_lines():
            log.warning("%s: %s (%s)", self.path, line, what)


#: a selection of channels: True for the channels to read
ChannelFilter = Callable[[Channel], bool]


def _release(buf: mmap.mmap, start: int, end: int) -> None:
    """Drop the pages of the file's bytes [start, end) from the process's resident memory
    once a chunk was copied out of them (they stay in the page cache): a whole read of a
    large file then keeps a chunk's pages mapped at a time, not the file's."""
    lo = start - start % mmap.PAGESIZE
    try:
        buf.madvise(mmap.MADV_DONTNEED, lo, end - lo)
    except (AttributeError, ValueError, OSError):  # no madvise here: the pages stay mapped, as before
        pass


@contextmanager
def _mapped(path: Path):
    """The bytes of the file ``path``: (buf, size, its (size, mtime) stamp); ReplayError,
    NotMcapError."""
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise ReplayError(f"cannot open {path}: {exc.strerror or exc}") from None
    with fh:
        magic = fh.read(len(MAGIC))
        if magic != MAGIC:
            raise NotMcapError(f"{path} is not an MCAP file (it starts with {magic!r})")
        st = os.fstat(fh.fileno())
        with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as buf:
            yield buf, st.st_size, (st.st_size, st.st_mtime_ns)


def check_mcap(path: str | Path) -> None:
    """A ReplayError (NotMcapError) unless ``path`` opens and starts as an MCAP file (a file cut
    short passes: what it holds is read later)."""
    with _mapped(Path(path)):
        pass


def indexed_metadata(buf, size: int, summary: Summary) -> tuple[list[Metadata], list[str]]:
    """The metadata records the summary indexes, and one line per record that does not read."""
    out, problems = [], []
    for mi in summary.metadata_indexes:
        rec = frame(buf, mi.offset, min(size, mi.offset + mi.length))
        try:
            if rec is None or rec[0] != Opcode.METADATA:
                raise Damage("not a metadata record")
            md = parse_record(Metadata, buf[mi.offset + RECORD_HEAD.size:rec[1]], "it")
        except Damage as exc:
            problems.append(f"the metadata record {mi.name!r} at byte {mi.offset} does not read ({exc})")
            continue
        why = check_metadata(md)
        if why:
            problems.append(f"{why}: its entries are damaged; not used")
        else:
            out.append(md)
    return out, problems


class Selection:
    """What a read selects: the messages logged in [``start_ns``, ``end_ns``) (None: no
    bound) on the channels ``channel`` accepts (None: all); the channels are named through
    ``channels``, which the reader fills."""

    channels: dict[int, Channel]

    def _select(self, start_ns: int | None, end_ns: int | None, channel: ChannelFilter | None) -> None:
        self.start_ns, self.end_ns, self._channel = start_ns, end_ns, channel

    @property
    def selective(self) -> bool:
        """The last read was of a selection (a window or some channels), not the whole file."""
        return self.start_ns is not None or self.end_ns is not None or self._channel is not None

    def _in_window(self, log_ns: int) -> bool:
        return (self.start_ns is None or log_ns >= self.start_ns) and (self.end_ns is None or log_ns < self.end_ns)

    def _selected(self, cid: int) -> bool | None:
        """Whether channel ``cid`` is selected (None: its definition is unknown)."""
        ch = self.channels.get(cid)
        if ch is None:
            return None
        return self._channel is None or bool(self._channel(ch))

    def _verdict(self, cid: int, log_ns: int) -> str:
        """What to do with a message: "take" it, count it "lost" (its channel's definition
        was lost; only when every channel is selected) or "skip" it (not selected)."""
        if not self._in_window(log_ns):
            return "skip"
        selected = self._selected(cid)
        if selected is None:
            return "lost" if self._channel is None else "skip"
        return "take" if selected else "skip"

    def _chunk_selected(self, ci: ChunkIndex) -> bool:
        """Whether the chunk of ``ci`` may hold selected messages (its log times, its channels)."""
        if self.end_ns is not None and ci.message_start_time >= self.end_ns:
            return False
        if self.start_ns is not None and ci.message_end_time < self.start_ns:
            return False
        return self._channel is None or any(self._selected(cid) for cid in ci.message_index_offsets)


class McapFile(ReadFindings, Selection):
    """Checked sequential reader. :meth:`messages` yields (channel, message) for every
    message of the file's chunks that read whole, in file order; schemas, channels and
    metadata fill in as they are met.

    Every chunk's CRC is checked before any of its messages is returned. A chunk that fails
    (its CRC, its size, its compression, its framing) is named in ``damaged``
    (:class:`DamagedChunk`: offset, log time range, the topics and counts of its messages,
    which are ``lost``), and reading goes on at the next chunk: through the summary's chunk
    index when the file has a summary whose CRC matches, else record by record (after a
    record that does not frame, at the next chunk whose CRC matches). Messages on a
    channel whose definition was lost are counted lost too. When the summary's statistics
    count more messages than were read, the difference is lost as well (``problems``
    says so): a writer that counted a message it did not write whole. When the file was
    cut short (no footer, its last record half written), iteration ends quietly and
    ``truncated`` / ``truncation_reason`` say so. Not MCAP: NotMcapError.

    A selection (``messages(start_ns, end_ns, channel)``) yields the messages logged in
    [start_ns, end_ns) on the channels ``channel`` accepts; through the chunk index only the
    chunks that hold some are read (their CRC checked), and a damaged one counts lost the
    messages it held in the window, of every channel (its message index records' log times:
    the chunk is lost whole, whatever was selected). ``indexed``: the last read went through
    the chunk index. The summary (its CRC checked) is read once and kept while the file's
    size and modification time stay the same."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._kept: tuple[tuple[int, int], SummaryRead, list[Metadata], list[str]] | None = None
        self._reset()

    def _reset(self, start_ns: int | None = None, end_ns: int | None = None,
               channel: ChannelFilter | None = None) -> None:
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.metadata: list[Metadata] = []
        self.indexed = False
        self._select(start_ns, end_ns, channel)
        self._reset_findings()

    # -- reading ----------------------------------------------------------------------------
    def _summary(self, buf, size: int, stamp: tuple[int, int]) -> Summary | None:
        """The file's summary when it can be trusted and indexes chunks (then its metadata
        records, read through their index, are in ``metadata``); None: read record by record."""
        if self._kept is None or self._kept[0] != stamp:
            found = read_summary(buf, size)
            metadata, problems = [], []
            if found.summary is not None and found.summary.chunk_indexes:
                metadata, problems = indexed_metadata(buf, size, found.summary)
            self._kept = (stamp, found, metadata, problems)
        _, found, metadata, problems = self._kept
        if found.problem:
            self.problems.append(found.problem)
        summary = found.summary
        if summary is not None:
            self._statistics = summary.statistics
            self.schemas.update(summary.schemas)
            self.channels.update(summary.channels)
        if summary is None or not summary.chunk_indexes:
            return None
        self.metadata += metadata
        self.problems += problems
        self.indexed = True
        return summary

    def read_index(self) -> Summary | None:
        """Read the summary section and the metadata records alone (no chunk): the file's
        summary (channels, statistics, chunk indexes; filling ``channels``, ``schemas``,
        ``metadata``) when it has one whose CRC matches and that indexes its chunks, else
        None (cut short, its summary damaged (``problems`` says so) or absent: then only a
        whole read, :meth:`messages`, tells what it holds)."""
        self._reset()
        with _mapped(self.path) as (buf, size, stamp):
            return self._summary(buf, size, stamp)

    def messages(self, start_ns: int | None = None, end_ns: int | None = None,
                 channel: ChannelFilter | None = None) -> Iterator[tuple[Channel, Message]]:
        """Every message that reads, in file order; with ``start_ns`` / ``end_ns`` only those
        logged in [start_ns, end_ns), with ``channel`` only those on the channels it accepts."""
        self._reset(start_ns, end_ns, channel)
        with _mapped(self.path) as (buf, size, stamp):
            summary = self._summary(buf, size, stamp)
            if summary is not None:
                yield from self._indexed(buf, size, summary)
            else:
                yield from self._sequential(buf, size)
        self._account()
        self.complete = True

    def _chunk(self, body: bytes, offset: int, length: int, start_ns, end_ns):
        """Open one chunk; its messages (those on known channels), or a DamagedChunk when it
        does not read. Returns (messages, damage or None, read by channel)."""
        try:
            chunk = open_chunk(body)
        except Damage as exc:
            return [], DamagedChunk(offset, length, start_ns, end_ns, Counter(), False, str(exc)), Counter()
        if not chunk.checked:
            self.unchecked_chunks += 1
        for s in chunk.schemas:
            self.schemas[s.id] = s
        for c in chunk.channels:
            self.channels[c.id] = c
        if chunk.messages:
            lo, hi = min(m.log_time for m in chunk.messages), max(m.log_time for m in chunk.messages)
            said = {(chunk.start_ns, chunk.end_ns)} | ({(start_ns, end_ns)} if start_ns is not None else set())
            if said != {(lo, hi)}:
                self.problems.append(f"the chunk at byte {offset} says its messages' log times span "
                                     f"{' and '.join(f'{a}-{b}' for a, b in sorted(said))} ns, they span {lo}-{hi} ns")
        out, read = [], Counter()  # read: the messages in the window that read (selected or not)
        for m in chunk.messages:
            verdict = self._verdict(m.channel_id, m.log_time)
            if verdict != "skip" or (self._in_window(m.log_time) and m.channel_id in self.channels):
                read[m.channel_id] += 1
            if verdict == "lost":
                self.lost_by_channel[m.channel_id] += 1
            elif verdict == "take":
                out.append((self.channels[m.channel_id], m))
        damage = None
        if chunk.error:
            damage = DamagedChunk(offset, length, chunk.start_ns, chunk.end_ns, Counter(), False, chunk.error)
        return out, damage, read

    def _yield(self, pairs):
        for ch, m in pairs:
            self.read += 1
            self._read_by_channel[m.channel_id] += 1
            yield ch, m

    def _indexed(self, buf, size: int, summary) -> Iterator[tuple[Channel, Message]]:
        for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
            if not self._chunk_selected(ci):
                continue
            off, length = ci.chunk_start_offset, ci.chunk_length
            rec = frame(buf, off, off + length)
            if rec is None or rec[0] != Opcode.CHUNK or rec[1] != off + length:
                pairs, damage, read = [], DamagedChunk(off, length, None, None, Counter(), False,
                                                       "the chunk index points at no chunk of its length"), Counter()
            else:
                pairs, damage, read = self._chunk(buf[off + RECORD_HEAD.size:off + length], off, length,
                                                  ci.message_start_time, ci.message_end_time)
                _release(buf, off, off + length)
            yield from self._yield(pairs)
            if damage is not None:
                damage.start_ns, damage.end_ns = ci.message_start_time, ci.message_end_time  # CRC-checked times
                damage.counted = True
                for cid, moff in ci.message_index_offsets.items():
                    rec = frame(buf, moff, size)
                    try:
                        if rec is None or rec[0] != Opcode.MESSAGE_INDEX:
                            raise Damage("no message index record there")
                        cid, n = message_index_count(buf[moff + RECORD_HEAD.size:rec[1]], self.start_ns, self.end_ns)
                        damage.lost_by_channel[cid] += n
                    except Damage:
                        damage.counted = False
                self._damage(damage, read)

    def _sequential(self, buf, size: int) -> Iterator[tuple[Channel, Message]]:
        """Record by record from the start. A chunk that does not read, or a record that
        stands where one was and is none (message index records after a record that is no
        readable chunk), is damaged; the message index records after it count what it held.
        After records that do not frame, reading goes on at the next record that provably
        starts one: a chunk whose CRC matches, message index records, the data section's end."""
        pos = len(MAGIC)
        pending: tuple[DamagedChunk, Counter] | None = None  # damage whose message indexes may follow
        after_chunk = False  # the records since the last record other than a message index began with a chunk
        prev = (pos, pos, 0)  # the last record other than a message index: (offset, end, opcode)
        while pos < size:
            rec = frame(buf, pos, size)
            if rec is None or not plausible_opcode(rec[0]):
                if pending is not None:
                    self._damage(*pending)
                nxt, pending = self._unframed(buf, pos, size, rec)
                if pending is None:  # cut short there
                    return
                after_chunk = True  # message index records right after it count what it held
                if nxt is None:
                    break
                pos = nxt
                continue
            opcode, stop = rec
            body = buf[pos + RECORD_HEAD.size:stop]
            if opcode == Opcode.MESSAGE_INDEX:
                try:
                    cid, n = message_index_count(body, self.start_ns, self.end_ns)
                except Damage as exc:
                    if pending is None:
                        pending = (DamagedChunk(pos, stop - pos, None, None, Counter(), False, str(exc)), Counter())
                    after_chunk = True
                    pos = stop
                    continue
                if pending is None and not after_chunk:  # the record before these indexes was their chunk
                    p0, p1, op = prev
                    pending = (DamagedChunk(p0, p1 - p0, None, None, Counter(), True,
                                            f"a record of opcode {op:#04x} stands where the chunk of the message "
                                            "index records after it should be"), Counter())
                    after_chunk = True
                if pending is not None:
                    pending[0].lost_by_channel[cid] += n
                    pending[0].counted = True
                pos = stop
                continue
            if pending is not None:
                self._damage(*pending)
                pending = None
            prev, after_chunk = (pos, stop, opcode), opcode == Opcode.CHUNK
            if opcode == Opcode.CHUNK:
                pairs, damage, read = self._chunk(body, pos, stop - pos, None, None)
                _release(buf, pos, stop)
                yield from self._yield(pairs)
                if damage is not None:
                    try:
                        head = chunk_head(body)
                        damage.start_ns, damage.end_ns = head.start_ns, head.end_ns
                    except Damage:
                        pass
                    pending = (damage, read)
            elif opcode == Opcode.MESSAGE:
                yield from self._message_record(body)
            elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.METADATA):
                self._info_record(opcode, body, pos)
            elif opcode in (Opcode.DATA_END, Opcode.FOOTER):  # the summary (if any) follows: read apart
                if buf[size - len(MAGIC):size] != MAGIC:
                    self.truncated = True
                    self.truncation_reason = (f"cut short after its data section (byte {pos}; its summary or footer "
                                              "is incomplete): every message was read")
                break
            pos = stop
        if pending is not None:
            self._damage(*pending)
        if pos >= size:  # records up to the end, no footer
            self.truncated = True
            self.truncation_reason = f"no footer: it ends after its last whole record (byte {pos})"

    def _unframed(self, buf, pos: int, size: int, rec) -> tuple[int | None, tuple[DamagedChunk, Counter] | None]:
        """Records at ``pos`` that do not frame (``rec``: the record there, None: half
        written): the next record that provably starts one (None: none) and the damage there,
        whose message indexes may follow; (None, None) when the file is cut short there."""
        nxt = resync(buf, pos + 1, size)
        if nxt is None and buf[size - len(MAGIC):size] != MAGIC:
            self.truncated = True
            self.truncation_reason = (f"cut short at byte {pos} of {size}: " +
                                      ("its last record is half written" if rec is None else
                                       f"opcode {rec[0]:#04x} is no record's"))
            return None, None
        stop = size if nxt is None else nxt
        why = "the records there do not frame" + ("; nothing after them reads" if nxt is None else "")
        return nxt, (DamagedChunk(pos, stop - pos, None, None, Counter(), False, why), Counter())

    def _message_record(self, body) -> Iterator[tuple[Channel, Message]]:
        """A message record outside any chunk: taken, counted lost, or passed over by its verdict."""
        if len(body) >= MESSAGE_HEAD.size:
            cid, seq, log_ns, pub_ns = MESSAGE_HEAD.unpack_from(body)
            msg = Message(channel_id=cid, sequence=seq, log_time=log_ns, publish_time=pub_ns,
                          data=body[MESSAGE_HEAD.size:])
            verdict = self._verdict(cid, log_ns)
            if verdict == "lost":
                self.lost_by_channel[cid] += 1
            elif verdict == "take":
                yield from self._yield([(self.channels[cid], msg)])

    def _info_record(self, opcode: int, body, pos: int) -> None:
        """A schema, channel or metadata record at byte ``pos``, kept; a damaged one is a problem."""
        cls = {Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel, Opcode.METADATA: Metadata}[opcode]
        try:
            r = parse_record(cls, body, f"the {cls.__name__.lower()} record at byte {pos}")
        except Damage as exc:
            self.problems.append(str(exc))
            return
        if opcode == Opcode.SCHEMA:
            self.schemas[r.id] = r
        elif opcode == Opcode.CHANNEL:
            self.channels[r.id] = r
        else:
            self._metadata(r)

    def _metadata(self, md: Metadata) -> None:
        why = check_metadata(md)
        if why:
            self.problems.append(f"{why}: its entries are damaged; not used")
            return
        self.metadata.append(md)

    def scan(self) -> int:
        """Read the whole file (filling channels and metadata); returns the message count."""
        return sum(1 for _ in self.messages())

    def metadata_dict(self) -> dict[str, dict[str, str]]:
        return {md.name: {k: v for k, v in md.metadata.items() if k != METADATA_CRC_KEY} for md in self.metadata}
