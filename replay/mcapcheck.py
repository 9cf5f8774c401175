"""Checked reading of MCAP records: the framing of every record, every chunk's checksum,
damage named.

What the checksums of an MCAP file cover: a chunk's ``uncompressed_crc`` (CRC32 of its
records: its messages, and the schemas and channels defined in it) and the footer's
``summary_crc`` (the summary section: channels, statistics, chunk and metadata indexes).
qradar adds ``qradar.crc32`` to each metadata record it writes (CRC32 of its entries,
:func:`metadata_crc`). The header, the message index records and the metadata of other
writers carry none.

:func:`frame` reads one record's opcode and length and never trusts a length past the
end of what was read; :func:`open_chunk` parses a chunk record, checks its size and CRC
and splits it into its records; :func:`read_summary` reads a file's summary section
after checking its CRC; :func:`written_counts` re-reads what a writer just wrote.
Every failure is a :class:`Damage` naming where and why. This module does no file I/O
of its own: it reads bytes it is given (a file's memory map, a range read back).
"""

from __future__ import annotations

import io
import json
import struct
import zlib
from collections import Counter
from dataclasses import dataclass, field

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, ChunkIndex, Message, MessageIndex, Metadata, MetadataIndex, Schema, Statistics
from mcap.summary import Summary
from zstandard import ZstdDecompressor, ZstdError, frame_content_size

from .errors import Damage

MAGIC = b"\x89MCAP0\r\n"
#: a record's opcode (uint8) and the length of what follows (uint64)
RECORD_HEAD = struct.Struct("<BQ")
#: a message's fixed fields: channel id, sequence, log time, publish time
MESSAGE_HEAD = struct.Struct("<HIQQ")
#: a chunk's fixed fields before its compression name: start and end time, uncompressed size and CRC
CHUNK_HEAD = struct.Struct("<QQQI")
#: the footer record: opcode, length (20), summary start, summary offset start, summary CRC
FOOTER = struct.Struct("<BQQQI")
FOOTER_LEN = FOOTER.size  # 29
KNOWN_OPCODES = frozenset(int(op) for op in Opcode)
#: the largest chunk (uncompressed) a reader opens, bytes: a corrupted size must not allocate more
MAX_CHUNK_BYTES = 1 << 31
COMPRESSIONS = ("", "zstd", "lz4")
#: the metadata entry holding the CRC32 of a qradar metadata record's other entries
METADATA_CRC_KEY = "qradar.crc32"
#: what mcap's record parsers raise on bytes that are not the record they expect
PARSE_ERRORS = (McapError, struct.error, ValueError, OverflowError, MemoryError, UnicodeDecodeError)


def frame(buf, pos: int, end: int) -> tuple[int, int] | None:
    """(opcode, end of the record) of the record at ``pos`` in ``buf[:end]``; None when its
    head is cut short or its length runs past ``end``."""
    if pos + RECORD_HEAD.size > end:
        return None
    opcode, length = RECORD_HEAD.unpack_from(buf, pos)
    stop = pos + RECORD_HEAD.size + length
    return None if stop > end else (opcode, stop)


def plausible_opcode(opcode: int) -> bool:
    """An opcode of the MCAP specification, or of its user range (0x80-0xFF)."""
    return opcode in KNOWN_OPCODES or opcode >= 0x80


def _stream(body: bytes) -> ReadDataStream:
    return ReadDataStream(io.BytesIO(body))


def parse_record(cls, body: bytes, what: str):
    """``cls.read`` of a record's body; a :class:`Damage` if the body is not one."""
    try:
        return cls.read(_stream(body))
    except PARSE_ERRORS as exc:
        raise Damage(f"{what} does not parse ({type(exc).__name__}: {exc})") from None


@dataclass
class ChunkHead:
    """A chunk record's fields (before decompression) and where its compressed data lie
    in the record's body."""

    start_ns: int
    end_ns: int
    uncompressed_size: int
    uncompressed_crc: int
    compression: str
    data_start: int
    data_end: int


def chunk_head(body: bytes) -> ChunkHead:
    """The fields of a chunk record's ``body``, their lengths checked against it."""
    if len(body) < CHUNK_HEAD.size + 4:
        raise Damage(f"a chunk record of {len(body)} bytes is shorter than its fixed fields")
    start, end, usize, crc = CHUNK_HEAD.unpack_from(body, 0)
    (clen,) = struct.unpack_from("<I", body, CHUNK_HEAD.size)
    p = CHUNK_HEAD.size + 4
    if clen > 16 or p + clen + 8 > len(body):
        raise Damage(f"a chunk's compression name of {clen} bytes does not fit its record")
    try:
        compression = body[p:p + clen].decode("ascii")
    except UnicodeDecodeError:
        raise Damage(f"a chunk's compression name {bytes(body[p:p + clen])!r} is not ASCII") from None
    if compression not in COMPRESSIONS:
        raise Damage(f"a chunk's compression {compression!r} is none of {COMPRESSIONS}")
    p += clen
    (dlen,) = struct.unpack_from("<Q", body, p)
    p += 8
    if p + dlen > len(body):
        raise Damage(f"a chunk's {dlen} bytes of data run past its record ({len(body)} bytes)")
    if usize > MAX_CHUNK_BYTES:
        raise Damage(f"a chunk claims {usize} bytes uncompressed (more than {MAX_CHUNK_BYTES})")
    return ChunkHead(start, end, usize, crc, compression, p, p + dlen)


def _decompress(head: ChunkHead, data: bytes) -> bytes:
    try:
        if head.compression == "zstd":
            size = frame_content_size(data)  # checked before it sizes an allocation
            if size != -1 and size != head.uncompressed_size:
                raise Damage(f"its zstd frame says {size} bytes, its record {head.uncompressed_size}")
            return ZstdDecompressor().decompress(data, max_output_size=head.uncompressed_size)
        if head.compression == "lz4":
            import lz4.frame  # the writer's optional dependency: only for lz4 chunks

            return lz4.frame.decompress(data)
        return bytes(data)
    except (ZstdError, RuntimeError, ValueError, MemoryError, OverflowError, ImportError) as exc:
        raise Damage(f"its {head.compression} data do not decompress ({type(exc).__name__}: {exc})") from None


@dataclass
class ChunkRecords:
    """What a chunk holds: its schemas, channels and messages in order. ``error``: the
    records stop parsing there (the checksum matched: the records before it are what the
    writer wrote); ``checked``: the chunk carried a CRC and it matched."""

    start_ns: int
    end_ns: int
    schemas: list[Schema] = field(default_factory=list)
    channels: list[Channel] = field(default_factory=list)
    messages: list[Message] = field(default_factory=list)
    error: str | None = None
    checked: bool = True


def _chunk_data(body: bytes) -> tuple[ChunkHead, bytes]:
    """A chunk record's head and its records, decompressed, their size and CRC checked."""
    head = chunk_head(body)
    data = _decompress(head, body[head.data_start:head.data_end])
    if len(data) != head.uncompressed_size:
        raise Damage(f"it decompresses to {len(data)} bytes, its record says {head.uncompressed_size}")
    if head.uncompressed_crc:
        crc = zlib.crc32(data)
        if crc != head.uncompressed_crc:
            raise Damage(f"CRC mismatch (records {crc:#010x}, recorded {head.uncompressed_crc:#010x})")
    return head, data


def count_chunk_messages(body: bytes) -> tuple[Counter, str | None]:
    """The messages of a chunk record's ``body`` by channel id (its size and CRC checked:
    :class:`Damage`), and where its records stop framing (None: they frame to its end);
    no message is copied."""
    _, data = _chunk_data(body)
    counts: Counter = Counter()
    pos, end = 0, len(data)
    while pos < end:
        rec = frame(data, pos, end)
        if rec is None or not plausible_opcode(rec[0]) or (
                rec[0] == Opcode.MESSAGE and rec[1] - pos - RECORD_HEAD.size < MESSAGE_HEAD.size):
            return counts, f"the record at byte {pos} of its {end} bytes does not frame"
        if rec[0] == Opcode.MESSAGE:
            counts[struct.unpack_from("<H", data, pos + RECORD_HEAD.size)[0]] += 1
        pos = rec[1]
    return counts, None


def open_chunk(body: bytes) -> ChunkRecords:
    """A chunk record's ``body`` decompressed, its size and CRC checked (:class:`Damage`
    when either is wrong: none of its records is returned), split into its records."""
    head, data = _chunk_data(body)
    out = ChunkRecords(head.start_ns, head.end_ns, checked=head.uncompressed_crc != 0)
    pos, end = 0, len(data)
    while pos < end:
        rec = frame(data, pos, end)
        if rec is None:
            out.error = f"a record at byte {pos} of its {end} bytes runs past its end"
            break
        opcode, stop = rec
        body_start = pos + RECORD_HEAD.size
        try:
            if opcode == Opcode.MESSAGE:
                if stop - body_start < MESSAGE_HEAD.size:
                    raise Damage(f"a message record of {stop - body_start} bytes")
                cid, seq, log_ns, pub_ns = MESSAGE_HEAD.unpack_from(data, body_start)
                out.messages.append(Message(channel_id=cid, sequence=seq, log_time=log_ns, publish_time=pub_ns,
                                            data=data[body_start + MESSAGE_HEAD.size:stop]))
            elif opcode == Opcode.CHANNEL:
                out.channels.append(parse_record(Channel, data[body_start:stop], "a channel record"))
            elif opcode == Opcode.SCHEMA:
                out.schemas.append(parse_record(Schema, data[body_start:stop], "a schema record"))
            elif not plausible_opcode(opcode):
                raise Damage(f"opcode {opcode:#04x}")
        except Damage as exc:
            out.error = f"the record at byte {pos} of its {end} bytes does not parse: {exc}"
            break
        pos = stop
    return out


def message_index_count(body: bytes, start_ns: int | None = None, end_ns: int | None = None) -> tuple[int, int]:
    """(channel id, messages) of a message index record's body: those logged in
    [``start_ns``, ``end_ns``) when either is given."""
    idx = parse_record(MessageIndex, body, "a message index record")
    if start_ns is None and end_ns is None:
        return idx.channel_id, len(idx.records)
    return idx.channel_id, sum(1 for t, _ in idx.records
                               if (start_ns is None or t >= start_ns) and (end_ns is None or t < end_ns))


def metadata_crc(entries: dict[str, str]) -> str:
    """The CRC32 qradar writes into a metadata record (under METADATA_CRC_KEY): of its other
    entries as sorted, compact JSON (UTF-8), in hex."""
    text = json.dumps({k: v for k, v in entries.items() if k != METADATA_CRC_KEY}, sort_keys=True,
                      separators=(",", ":"), ensure_ascii=False)
    return f"{zlib.crc32(text.encode()):08x}"


def check_metadata(md: Metadata) -> str | None:
    """Why a metadata record's qradar CRC does not match its entries (None: it matches, or
    the record carries none)."""
    want = md.metadata.get(METADATA_CRC_KEY)
    if want is None:
        return None
    got = metadata_crc(md.metadata)
    return None if got == want else f"metadata {md.name!r}: CRC {got}, recorded {want}"


@dataclass
class SummaryRead:
    """A file's summary section, read only when its CRC matched: ``summary`` (None when the
    file has none, or it cannot be trusted) and ``problem`` (why not, when there is one);
    ``data_end``: where its data section ends (the summary's start), or None."""

    summary: Summary | None
    problem: str | None = None
    data_end: int | None = None


def read_summary(buf, size: int) -> SummaryRead:
    """The summary of the MCAP file in ``buf[:size]``: a file without the closing magic
    (cut short) or without a summary has none, without a problem; a footer or summary that
    does not check out is a problem (the file is then read record by record)."""
    if size < 2 * len(MAGIC) + FOOTER_LEN or buf[size - len(MAGIC):size] != MAGIC:
        return SummaryRead(None)
    fpos = size - len(MAGIC) - FOOTER_LEN
    opcode, length, start, offset_start, crc = FOOTER.unpack_from(buf, fpos)
    if opcode != Opcode.FOOTER or length != FOOTER_LEN - RECORD_HEAD.size:
        return SummaryRead(None, f"the footer at byte {fpos} is damaged (opcode {opcode:#04x}, length {length})")
    if start == 0:
        return SummaryRead(None)
    if not len(MAGIC) <= start <= fpos or (offset_start and not start <= offset_start <= fpos):
        return SummaryRead(None, f"the footer points outside the file (summary at byte {start}, file {size} bytes)")
    if crc:
        got = zlib.crc32(buf[start:fpos + FOOTER.size - 4])
        if got != crc:
            return SummaryRead(None, f"the summary (bytes {start}-{fpos}) fails its CRC "
                                     f"({got:#010x}, recorded {crc:#010x})", start)
    summary = Summary()
    pos = start
    try:
        while pos < fpos:
            rec = frame(buf, pos, fpos)
            if rec is None:
                raise Damage(f"a record at byte {pos} runs past the footer")
            opcode, stop = rec
            body = buf[pos + RECORD_HEAD.size:stop]
            if opcode == Opcode.SCHEMA:
                s = parse_record(Schema, body, "a schema record")
                summary.schemas[s.id] = s
            elif opcode == Opcode.CHANNEL:
                c = parse_record(Channel, body, "a channel record")
                summary.channels[c.id] = c
            elif opcode == Opcode.STATISTICS:
                summary.statistics = parse_record(Statistics, body, "the statistics record")
            elif opcode == Opcode.CHUNK_INDEX:
                summary.chunk_indexes.append(parse_record(ChunkIndex, body, "a chunk index record"))
            elif opcode == Opcode.METADATA_INDEX:
                summary.metadata_indexes.append(parse_record(MetadataIndex, body, "a metadata index record"))
            pos = stop
    except Damage as exc:
        return SummaryRead(None, f"the summary does not parse: {exc}", start)
    for ci in summary.chunk_indexes:
        if not len(MAGIC) <= ci.chunk_start_offset < ci.chunk_start_offset + ci.chunk_length <= start:
            return SummaryRead(None, f"a chunk index points outside the data section (byte {ci.chunk_start_offset})",
                               start)
    return SummaryRead(summary, None, start)


@dataclass
class WrittenCounts:
    """What a range of a file holds, re-read: messages by channel id in its chunks that
    check out, and one line per problem (a chunk that does not, a record that does not frame)."""

    messages: Counter = field(default_factory=Counter)
    problems: list[str] = field(default_factory=list)


def written_counts(buf: bytes, base: int) -> WrittenCounts:
    """Re-read the records a writer just wrote (``buf``: the file's bytes from offset ``base``,
    a whole number of records): count the messages of each chunk that checks out."""
    out = WrittenCounts()
    pos, end = 0, len(buf)
    while pos < end:
        rec = frame(buf, pos, end)
        if rec is None or not plausible_opcode(rec[0]):
            out.problems.append(f"the records at byte {base + pos} do not frame")
            break
        opcode, stop = rec
        if opcode == Opcode.CHUNK:
            try:
                counts, error = count_chunk_messages(buf[pos + RECORD_HEAD.size:stop])
            except Damage as exc:
                out.problems.append(f"the chunk at byte {base + pos}: {exc}")
            else:
                out.messages.update(counts)
                if error:
                    out.problems.append(f"the chunk at byte {base + pos}: {error}")
        elif opcode == Opcode.MESSAGE:
            if stop - pos - RECORD_HEAD.size >= MESSAGE_HEAD.size:
                out.messages[MESSAGE_HEAD.unpack_from(buf, pos + RECORD_HEAD.size)[0]] += 1
        elif opcode == Opcode.METADATA:
            try:
                why = check_metadata(parse_record(Metadata, buf[pos + RECORD_HEAD.size:stop], "a metadata record"))
            except Damage as exc:
                why = str(exc)
            if why:
                out.problems.append(f"at byte {base + pos}: {why}")
        pos = stop
    return out


#: the first bytes of a DataEnd record (opcode, length 4): where a resync may land
_DATA_END_HEAD = RECORD_HEAD.pack(Opcode.DATA_END, 4)


def message_index_chain(buf, pos: int, size: int) -> bool:
    """Whether a message index record provably starts at ``pos``: it frames, its array's
    length is its record's, a whole number of entries, and a record frames after it."""
    rec = frame(buf, pos, size)
    if rec is None or rec[0] != Opcode.MESSAGE_INDEX or rec[1] - pos < RECORD_HEAD.size + 6:
        return False
    (n,) = struct.unpack_from("<I", buf, pos + RECORD_HEAD.size + 2)
    if n % 16 or n != rec[1] - pos - RECORD_HEAD.size - 6:
        return False
    nxt = frame(buf, rec[1], size)
    return rec[1] == size or (nxt is not None and plausible_opcode(nxt[0]))


def resync(buf, start: int, size: int) -> int | None:
    """After records that do not frame: the offset of the next record that provably
    starts one, at or after ``start`` (the message index records after a chunk, a chunk
    whose CRC matches, the data section's end); None when none follows."""
    data_end = buf.find(_DATA_END_HEAD, start)
    limit = size if data_end < 0 else data_end
    chunk = None
    pos = start
    while chunk is None:
        pos = buf.find(b"\x06", pos, limit)
        if pos < 0:
            break
        rec = frame(buf, pos, size)
        if rec is not None and rec[1] - pos > RECORD_HEAD.size + CHUNK_HEAD.size + 12:
            body = buf[pos + RECORD_HEAD.size:rec[1]]
            try:
                chunk_head(body)
                open_chunk(body)
                chunk = pos
            except Damage:
                pass
        pos += 1
    limit = limit if chunk is None else chunk
    pos = start
    while True:
        pos = buf.find(b"\x07", pos, limit)
        if pos < 0:
            break
        if message_index_chain(buf, pos, size):
            return pos
        pos += 1
    if chunk is not None:
        return chunk
    return None if data_end < 0 else data_end
