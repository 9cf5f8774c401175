"""RFbeam K-MD2 serial protocol: bytes <-> messages, with no I/O.

A message is a 4-character ASCII header, a uint32 little-endian payload length, then
the payload; multi-byte fields are little-endian. The K-MD2 pads payloads to a
multiple of 4 bytes: the decoder tolerates both a length that counts the padding and
zero padding after an unpadded length.

What the public documents do not say is assumed, and every assumption sits in a
sensor profile (:mod:`.profile`: the ``RADC`` layout, the baud codes, the ``GNFD`` bits,
the plausible lengths of other frames), so that a capture from a real sensor can
correct them in one TOML file. The codec takes a profile; without one it uses
:data:`~.profile.DEFAULT_PROFILE`.

:class:`StreamDecoder` takes arbitrary chunks of bytes and yields messages. On garbage
it resynchronizes on the next known header whose length is plausible for that header
and whose payload is valid (a RADC payload holds ADC-range words only; a frame the
driver does not interpret holds no other such header before its declared end), and
counts the bytes it skipped; it never raises on input, and its work is linear in the
bytes fed, however they are cut.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Union

import numpy as np

from .errors import ProtocolError, RespCode
from .profile import DEFAULT_PROFILE, RadcLayout, SensorProfile
from .resync import HEADER_LEN, NONE as _NONE, OK as _OK, OPAQUE as _OPAQUE, PEND as _PEND, PREFIX_LEN
from .resync import RADC as _RADC, REJ as _REJ, RESP as _RESP, HeaderTable


#: Line speed of a sensor after power-up and after GBYE (every shipped profile's startup_baud).
DEFAULT_BAUD = DEFAULT_PROFILE.startup_baud
#: Seconds the host waits after ``RESP`` to ``INIT`` before switching its own rate.
BAUD_SWITCH_SETTLE_S = 0.075


# -- messages ------------------------------------------------------------------------------
@dataclass(frozen=True)
class Init:
    """Host -> sensor: start a session and switch to the profile's ``baud_codes[baud_code]``."""

    baud_code: int = 0
    header = b"INIT"

    def payload(self) -> bytes:
        return struct.pack("<I", self.baud_code)


@dataclass(frozen=True)
class Gnfd:
    """Host -> sensor: send the next frame(s) selected by ``mask`` (the profile's gnfd_bits), then DONE."""

    mask: int = DEFAULT_PROFILE.gnfd_bits["RADC"]
    header = b"GNFD"

    def payload(self) -> bytes:
        return struct.pack("<I", self.mask)


@dataclass(frozen=True)
class Gbye:
    """Host -> sensor: end the session; the sensor returns to 115200 baud."""

    header = b"GBYE"

    def payload(self) -> bytes:
        return b""


@dataclass(frozen=True)
class Resp:
    """Sensor -> host: answer to every command (``code``: RespCode value)."""

    code: int = RespCode.OK
    header = b"RESP"

    def payload(self) -> bytes:
        return struct.pack("<B", self.code)


@dataclass(frozen=True)
class Done:
    """Sensor -> host: end of a GNFD answer, with the sensor's frame counter."""

    frame_counter: int
    header = b"DONE"

    def payload(self) -> bytes:
        return struct.pack("<I", self.frame_counter)


@dataclass(frozen=True, eq=False)
class Radc:
    """Sensor -> host: one RADC of raw ADC words, shape (receivers, chirps, samples, 2
    (I, Q)) in the ``layout`` of a sensor profile (one ramp in the default profile)."""

    words: np.ndarray
    layout: RadcLayout = DEFAULT_PROFILE.radc
    header = b"RADC"

    def payload(self) -> bytes:
        return self.layout.payload_from_words(self.words)

    def samples(self) -> np.ndarray:
        """Complex samples in units of full scale, shape (chirps, samples, receivers)."""
        return self.layout.to_complex(self.words)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Radc) and self.layout == other.layout and np.array_equal(self.words, other.words)


@dataclass(frozen=True)
class OtherMessage:
    """A known header whose payload this driver does not interpret (RMRD, PDAT, TDAT)."""

    header: bytes
    data: bytes = b""

    def payload(self) -> bytes:
        return self.data


Message = Union[Init, Gnfd, Gbye, Resp, Done, Radc, OtherMessage]


# -- encoding ---------------------------------------------------------------------------------
def encode(message: Message, pad: bool = True) -> bytes:
    """Bytes of one message: header, uint32 LE payload length (unpadded), payload, and
    with ``pad`` zero bytes up to a multiple of 4 (as the K-MD2 sends)."""
    payload = message.payload()
    header = message.header
    if len(header) != HEADER_LEN:
        raise ProtocolError(f"header {header!r} is not 4 bytes")
    out = header + struct.pack("<I", len(payload)) + payload
    if pad and len(payload) % 4:
        out += bytes(4 - len(payload) % 4)
    return out


def decode_payload(header: bytes, payload: bytes, profile: SensorProfile = DEFAULT_PROFILE) -> Message:
    """The message of a header and its payload (padding allowed after the fields), in the
    conventions of ``profile``. Raises ProtocolError naming the header and what is wrong."""
    lo, hi = profile.plausible_length().get(header, (None, None))
    if lo is None:
        raise ProtocolError(f"unknown header {header!r}")
    if not lo <= len(payload) <= hi:
        raise ProtocolError(f"{header.decode('ascii')} payload of {len(payload)} bytes; expected {lo}..{hi}")
    if header == b"INIT":
        return Init(struct.unpack_from("<I", payload)[0])
    if header == b"GNFD":
        return Gnfd(struct.unpack_from("<I", payload)[0])
    if header == b"GBYE":
        return Gbye()
    if header == b"RESP":
        if any(payload[1:]):
            raise ProtocolError(f"RESP padding is not zero: {payload.hex()}")
        return Resp(payload[0])
    if header == b"DONE":
        return Done(struct.unpack_from("<I", payload)[0])
    if header == b"RADC":
        return Radc(profile.radc.words_from_payload(payload), profile.radc)
    return OtherMessage(header, bytes(payload))


def decode(data: bytes, profile: SensorProfile = DEFAULT_PROFILE) -> Message:
    """Decode exactly one message (with optional trailing zero padding)."""
    if len(data) < PREFIX_LEN:
        raise ProtocolError(f"message of {len(data)} bytes is shorter than the 8-byte header and length")
    header = bytes(data[:4])
    (length,) = struct.unpack_from("<I", data, 4)
    body = data[PREFIX_LEN:]
    if len(body) < length:
        raise ProtocolError(f"{header!r} declares {length} payload bytes, {len(body)} present")
    if any(body[length:]) or len(body) - length > 3:
        raise ProtocolError(f"{header!r}: {len(body) - length} bytes after the payload are not padding")
    return decode_payload(header, bytes(body[:length]), profile)


# -- streaming decoder -----------------------------------------------------------------------
_EMPTY = np.zeros(0, np.int64)
#: new candidates of one feed decided one by one in Python up to this many, with numpy beyond
_FEW = 16


@dataclass
class DecoderStats:
    """Counters of a :class:`StreamDecoder` since it was made (``reset`` keeps them)."""

    messages: int = 0
    bytes_in: int = 0
    skipped_bytes: int = 0
    resyncs: int = 0
    invalid: int = 0  # plausible header whose payload failed validation
    last_error: str = ""
    #: bytes the decoder examined (the header search, the ADC words behind RADC headers):
    #: its work, a small multiple of ``bytes_in`` whatever the input and its chunking
    scanned_bytes: int = 0


def _next_candidate(x: int, every: np.ndarray | None, cands: list[list[int]]) -> int:
    """Position of the first candidate at or after stream offset x, or _NONE: in ``every``
    (all positions, sorted) if given, else among ``cands``."""
    if every is not None:
        i = int(np.searchsorted(every, x))
        return int(every[i]) if i < every.size else _NONE
    return next((c[0] for c in cands if c[0] >= x), _NONE)


class _Tally:
    """What a :class:`StreamDecoder` counts in ``stats``: messages, runs of skipped bytes
    (a resync each) and refused candidates (the reason of the latest in ``last_error``)."""

    def __init__(self, stats: DecoderStats, table: HeaderTable):
        self.stats, self._t = stats, table
        self.skipping = False
        self.err_at = -1  # stream offset of the candidate last_error names

    def message(self) -> None:
        self.stats.messages += 1
        self.skipping = False

    def skipped(self, start: int, stop: int, bulk: tuple, buf: bytearray, base: int) -> None:
        """Count the bytes [start, stop) as skipped and the refused candidates among them
        that were decided in bulk (``bulk``; the others are counted as the walk meets them)."""
        if stop <= start:
            return
        self.stats.skipped_bytes += stop - start
        if not self.skipping:
            self.stats.resyncs += 1
            self.skipping = True
        r = bulk[0]
        if r.size:
            i, j = int(np.searchsorted(r, start)), int(np.searchsorted(r, stop))
            if j > i:
                self.refused(buf, base, *(int(a[j - 1]) for a in bulk), count=j - i)

    def refused(self, buf: bytearray, base: int, q: int, k: int, n: int, why: int, count: int = 1) -> None:
        """Count ``count`` refused candidates, the last at stream offset ``q``."""
        self.stats.invalid += count
        if q > self.err_at:
            self.stats.last_error, self.err_at = self._t.why(buf, base, q, k, n, why), q

    def failed(self, q: int, exc: Exception) -> None:
        """A candidate that passed the checks and still did not decode."""
        self.stats.invalid += 1
        self.stats.last_error, self.err_at = f"{exc} (stream byte {q})", q


@dataclass
class StreamDecoder:
    """Incremental decoder: ``feed(chunk)`` returns the messages completed by ``chunk``.

    A *candidate* is a known header with a plausible length. Where the stream is not a
    message, the decoder skips to the next candidate whose payload is valid: a RADC's
    words lie in the ADC range; a RESP's padding is zero; a frame the driver does not
    interpret (RMRD, PDAT, TDAT) holds no other candidate before its declared end (a
    stray header claiming 16 KiB does not swallow the frames after it). Each run of
    skipped bytes counts one resync, each refused candidate one ``invalid``.

    Three paths, each a section below: the *step* takes messages that follow each other
    from the head without a search; elsewhere the *search* finds each new byte's
    candidates once and *decides* each once (with numpy when there are many; the
    search and the validation live in :class:`~.resync.HeaderTable`), and the *walk*
    emits the decided messages in order and counts the garbage between them.

    The work is linear in the bytes fed, whatever they are and however they are cut
    (``stats.scanned_bytes`` counts it); a candidate waiting for a long payload is
    re-examined on the new bytes only. Memory is bounded by the largest plausible
    message plus the chunk being fed. ``profile``: the sensor's conventions (RADC
    layout, other frames' lengths).
    """

    profile: SensorProfile = DEFAULT_PROFILE
    stats: DecoderStats = field(default_factory=DecoderStats)

    def __post_init__(self) -> None:
        self._t = HeaderTable(self.profile)
        self._buf = bytearray()
        self._restart(0)

    def _restart(self, base: int) -> None:
        self._base = base  # stream offset of _buf[0]; all positions are stream offsets
        self._scan = base  # positions below were searched for candidates
        self._pad = 0  # zero padding that may follow the last message
        self._tally = _Tally(self.stats, self._t)
        # candidates from _base on, by position: [position, header index, declared length,
        # status, why refused (the first bad RADC word, the candidate inside an opaque
        # frame), the next RADC word to check]
        self._cands: list[list[int]] = []
        # refused candidates decided in bulk (numpy): position, header index, length, why
        self._bulk = (_EMPTY, _EMPTY, _EMPTY, _EMPTY)

    def feed(self, chunk: bytes) -> list[Message]:
        self._buf += chunk
        self.stats.bytes_in += len(chunk)
        out: list[Message] = []
        if not self._in_step(out):
            self._classify()
            out += self._walk()
        return out

    def wanted(self) -> int:
        """Fewest further bytes that can complete the next message (at least 1): what a
        reader may block for without stalling the stream."""
        buf = self._buf
        if len(buf) < PREFIX_LEN:
            return PREFIX_LEN - len(buf)
        if not self._cands or self._cands[0][0] != self._base:
            return 1
        k, n = self._cands[0][1:3]
        need = PREFIX_LEN + n - len(buf)
        if self._t.kinds[k] == _OPAQUE:  # a header in the next bytes may decide it sooner
            need = min(need, PREFIX_LEN)
        return max(1, need)

    def pending(self) -> int:
        """Bytes held, waiting for the rest of a message."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget buffered bytes (after a reconnect); the counters stay."""
        base = self._base + len(self._buf)
        self._buf.clear()
        self._restart(base)

    # -- in step: message after message, no search ---------------------------------------------
    def _in_step(self, out: list[Message]) -> bool:
        """Take the messages that follow each other from the head while each is a fixed-size
        frame, a RESP or a valid RADC, never searching the bytes they span; wait for an
        incomplete one (checking a RADC's words as they come). False when anything else
        is at the head: the search decides then (the bytes of a RADC refused here were
        never searched, so each byte is examined at most twice)."""
        buf = self._buf
        while True:
            base = self._base
            if self._pad:
                at = self._eat_padding(base, base + len(buf))
                del buf[: at - base]
                self._base = base = at
                if self._pad:
                    return True  # all zeros so far
            end = base + len(buf)
            c = self._step_head(base, end)
            if isinstance(c, bool):
                return c
            _, k, n = c[:3]
            stop = base + PREFIX_LEN + n
            radc = self._t.kinds[k] == _RADC
            if stop > end:  # wait for the rest; a RADC's words are checked as they come
                if radc and (bad := self._check_words(c, base, end)) >= 0:
                    c[3], c[4] = _REJ, bad
                    return self._hand_over(c)
                self._hand_over(c)
                return True
            try:
                msg = decode_payload(self._t.names[k], bytes(buf[PREFIX_LEN : PREFIX_LEN + n]), self.profile)
            except ProtocolError:  # a RADC word out of range, a RESP's padding
                c[3], c[4] = _REJ, self._check_words(c, base, end) if radc else -1
                return self._hand_over(c)
            out.append(msg)
            self._tally.message()
            self._pad = (-n) % 4
            del buf[: stop - base]
            self._base = stop
            self._cands = []
            self._scan = max(self._scan, stop)

    def _step_head(self, base: int, end: int) -> list[int] | bool:
        """The candidate at the head that the step may take, or, when there is none, what
        :meth:`_in_step` returns (True: no bytes to decide; False: the search decides)."""
        if self._bulk[0].size or len(self._cands) > 1:
            return False
        if self._cands:  # one waiting candidate at the head
            c = self._cands[0]
            return c if c[0] == base and c[3] == _PEND and self._t.kinds[c[1]] != _OPAQUE else False
        buf = self._buf
        if end - base < PREFIX_LEN:
            return not buf
        k = self._t.index.get(bytes(buf[:HEADER_LEN]))
        if k is None or self._t.kinds[k] == _OPAQUE:
            return False
        n = int.from_bytes(buf[HEADER_LEN:PREFIX_LEN], "little")
        lo, hi = self._t.bounds[k]
        return [base, k, n, _PEND, -1, base + PREFIX_LEN] if lo <= n <= hi else False

    def _hand_over(self, c: list[int]) -> bool:
        """Keep the head candidate ``c`` for the search (which starts after it); False."""
        if not self._cands:
            self._cands = [c]
            self._scan = max(self._scan, c[0] + 1)
        return False

    # -- the search: candidates among the new bytes, each decided once ----------------------------
    def _classify(self) -> None:
        """Find the candidates among the new bytes and decide what the bytes so far decide
        of them and of the undecided ones."""
        base, end = self._base, self._base + len(self._buf)
        s0 = max(self._scan, base)
        pos, k, n = self._search(s0, end)
        undecided = [c for c in self._cands if c[3] == _PEND]
        few = len(pos) <= _FEW
        every = None  # positions of all candidates, sorted (for the opaque frames)
        if few:
            if not isinstance(pos, list):
                pos, k, n = pos.tolist(), k.tolist(), n.tolist()
            new = [[p, kk, nn, _PEND, -1, p + PREFIX_LEN] for p, kk, nn in zip(pos, k, n)]
            self._cands += new
            undecided += new
        else:  # the kept candidates all lie before the new ones
            pos, k, n = (np.asarray(a, np.int64) for a in (pos, k, n))
            kept = sorted([c[0] for c in self._cands] + self._bulk[0].tolist())
            every = np.concatenate((np.array(kept, np.int64), pos)) if kept else pos
        if undecided:
            if every is None and self._bulk[0].size:
                every = np.array(sorted([c[0] for c in self._cands] + self._bulk[0].tolist()), np.int64)
            for c in undecided:
                self._decide(c, base, end, every)
        if not few:
            self._decide_many(pos, k, n, every, s0 + PREFIX_LEN, base, end)

    def _search(self, s0: int, end: int) -> tuple:
        """Candidates starting in [s0, end - 8] (where all 8 bytes of a header and its length
        are present): positions, header indices, lengths (lists, or int64 arrays)."""
        if end - s0 < PREFIX_LEN:
            return [], [], []
        self._scan = end - PREFIX_LEN + 1
        self.stats.scanned_bytes += end - s0
        return self._t.search(self._buf, s0, self._base, end)

    def _decide(self, c: list[int], base: int, end: int, every: np.ndarray | None) -> None:
        """Decide one candidate from the bytes so far, if they decide it."""
        p, k, n = c[0], c[1], c[2]
        stop = p + PREFIX_LEN + n
        kind = self._t.kinds[k]
        if kind == _RADC:
            bad = self._check_words(c, base, end)
            if bad >= 0:
                c[3], c[4] = _REJ, bad
            elif stop <= end:
                c[3] = _OK
        elif kind == _OPAQUE:
            inside = _next_candidate(p + PREFIX_LEN, every, self._cands)
            if inside < stop:
                c[3], c[4] = _REJ, inside
            elif stop <= end and self._tail_start(p + PREFIX_LEN, base, end) >= stop:
                c[3] = _OK
        elif stop <= end:
            c[3] = _REJ if kind == _RESP and any(self._buf[p + PREFIX_LEN + 1 - base : stop - base]) else _OK

    def _check_words(self, c: list[int], base: int, end: int) -> int:
        """Range-check the words of RADC candidate ``c`` that came since its last check:
        the position of the first word out of the ADC range, or -1."""
        start, stop = c[5], min(c[0] + PREFIX_LEN + self._t.radc_len, end)
        if stop - start < 2:
            return -1
        self.stats.scanned_bytes += stop - start
        i = self._t.first_bad_word(self._buf, base, start, stop)
        if i >= 0:
            return start + 2 * i
        c[5] = start + (stop - start) // 2 * 2
        return -1

    def _decide_many(self, pos, k, n, every, lo, base, end) -> None:
        """Decide many new candidates at once (numpy); the refused ones go to _bulk, the
        others to _cands. ``every``: the positions of all candidates, sorted; ``lo``: the
        first byte of the new candidates' payloads."""
        st, why, scanned = self._t.decide_many(self._buf, pos, k, n, every, lo, base, end,
                                               lambda x: self._tail_start(x, base, end))
        self.stats.scanned_bytes += scanned
        rej = st == _REJ
        if rej.any():
            new = (pos[rej], k[rej], n[rej], why[rej])
            old = self._bulk
            self._bulk = tuple(np.concatenate(ab) for ab in zip(old, new)) if old[0].size else new
            keep = np.flatnonzero(~rej)
            pos, k, n, st = pos[keep], k[keep], n[keep], st[keep]
        nr, kinds = self._t.radc_len, self._t.kinds
        for p, kk, nn, s in zip(pos.tolist(), k.tolist(), n.tolist(), st.tolist()):
            checked = p + PREFIX_LEN  # the next RADC word to check, if undecided
            if s == _PEND and kinds[kk] == _RADC:
                checked += (min(p + PREFIX_LEN + nr, end) - checked) // 2 * 2
            self._cands.append([p, kk, nn, s, -1, checked])

    def _tail_start(self, lo: int, base: int, end: int) -> int:
        """First position from ``lo`` among the last, unsearched bytes that may still start a
        header (its bytes so far begin one), or ``end``."""
        return self._t.tail_start(self._buf, max(lo, self._scan, base), base, end)

    # -- the walk: messages in order, garbage counted --------------------------------------------
    def _walk(self) -> list[Message]:
        """Emit the messages of the candidates decided _OK, from the head on, and skip what
        lies between them; stop at the first undecided candidate."""
        buf, base = self._buf, self._base
        end = base + len(buf)
        out: list[Message] = []
        cursor = self._eat_padding(base, end) if self._pad else base
        head = -1
        for c in self._cands:
            q, k, n, st = c[:4]
            if q < cursor:
                continue  # inside a message just taken
            if st == _PEND:
                head = q
                break
            if st == _REJ:
                self._tally.refused(buf, base, q, k, n, c[4])
                continue
            try:
                msg = decode_payload(self._t.names[k], bytes(buf[q + PREFIX_LEN - base : q + PREFIX_LEN + n - base]),
                                     self.profile)
            except ProtocolError as exc:  # not expected after the checks; refused all the same
                self._tally.failed(q, exc)
                continue
            self._tally.skipped(cursor, q, self._bulk, buf, base)
            out.append(msg)
            self._tally.message()
            self._pad = (-n) % 4
            cursor = q + PREFIX_LEN + n
            if self._pad:
                cursor = self._eat_padding(cursor, end)
        if head < 0:
            head = self._tail_start(cursor, base, end)
        self._tally.skipped(cursor, head, self._bulk, buf, base)
        del buf[: head - base]
        self._base = head
        if self._cands and self._cands[0][0] < head:
            self._cands = [c for c in self._cands if c[0] >= head]
        if self._bulk[0].size:
            i = int(np.searchsorted(self._bulk[0], head))
            self._bulk = tuple(a[i:] for a in self._bulk)
        return out

    def _eat_padding(self, at: int, end: int) -> int:
        """Skip up to ``_pad`` zero bytes from stream offset ``at``; the offset after them."""
        buf, base = self._buf, self._base
        n = 0
        while n < self._pad and at + n < end and buf[at + n - base] == 0:
            n += 1
        self._pad = self._pad - n if at + n == end else 0  # more padding may come
        return at + n
