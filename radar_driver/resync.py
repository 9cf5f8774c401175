"""The search and validation behind :class:`~.protocol.StreamDecoder`: where a message may
start in a byte buffer, and whether its payload is valid, in a sensor profile's
conventions. Pure functions of the bytes given; the decoder keeps the state.

A *candidate* is a known header with a plausible length for that header. Its payload is
valid when a RADC's words lie in the ADC range, a RESP's padding is zero, and a frame
the driver does not interpret (RMRD, PDAT, TDAT) holds no other candidate before its
declared end. Positions are stream offsets; ``base`` is the stream offset of ``buf[0]``.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .profile import SensorProfile

HEADER_LEN = 4
PREFIX_LEN = 8  # header + uint32 length

# How the payload of a candidate is validated:
FIXED, RESP, RADC, OPAQUE = 0, 1, 2, 3  # any payload / zero padding / ADC range / no candidate inside
FIXED_HEADERS = (b"INIT", b"GNFD", b"GBYE", b"DONE")
# What a candidate would be at the head of the stream:
PEND, OK, REJ = 0, 1, 2  # undecided (more bytes needed) / a message / garbage
NONE = np.iinfo(np.int64).max  # no position
ODD = 1 << 61  # added to odd positions to sort them after the even ones
#: new bytes searched for headers with bytes.find up to this many, with numpy beyond
FIND_BYTES = 512


class HeaderTable:
    """The headers of a profile, their plausible lengths and validation kinds, indexed for
    a search in Python (``bytes.find``) and in numpy (``searchsorted`` on uint32 codes)."""

    def __init__(self, profile: SensorProfile):
        lengths = profile.plausible_length()
        self.headers = tuple(lengths)
        lay = self.layout = profile.radc
        limits = np.iinfo(np.dtype(lay.dtype))
        radc_checked = lay.min_word > limits.min or lay.max_word < limits.max  # 16-bit words: no check
        # header index: the order of the headers' uint32 codes (for numpy's searchsorted)
        codes = [int.from_bytes(h, "little") for h in self.headers]
        self.names = [h for _, h in sorted(zip(codes, self.headers))]
        self.codes = np.array(sorted(codes) + [0xFFFFFFFF], np.uint32)  # a sentinel no header has
        self.index = {h: i for i, h in enumerate(self.names)}
        self.bounds = [lengths[h] for h in self.names]
        self.lo = np.array([b[0] for b in self.bounds] + [1], np.int64)
        self.hi = np.array([b[1] for b in self.bounds] + [0], np.int64)
        self.kinds = [FIXED if h in FIXED_HEADERS else RESP if h == b"RESP"
                      else RADC if h == b"RADC" and radc_checked else OPAQUE for h in self.names]
        self.kind = np.array(self.kinds)
        self.first2 = np.zeros(1 << 16, bool)  # the first two bytes of the headers, as uint16 LE
        self.first2[[h[0] | h[1] << 8 for h in self.headers]] = True
        self.max_len = max(b[1] for b in self.bounds)
        self.prefixes = {h[:i] for h in self.headers for i in range(1, HEADER_LEN + 1)}
        self.radc_len = lay.payload_len
        # unsigned words with a 0 minimum and a 2^b - 1 maximum, b >= 8: a word is out of
        # range iff its high byte exceeds max >> 8 (checked on bytes, without numpy)
        self.hi_off = None
        if lay.word in ("uint16le", "uint16be") and lay.min_word == 0 and lay.adc_bits >= 8:
            self.hi_off = 1 if lay.word == "uint16le" else 0
            self.hi_max = lay.max_word >> 8
            self.badmap = bytes(int(b > self.hi_max) for b in range(256))

    # -- the search ----------------------------------------------------------------------------
    def search(self, buf: bytearray, s0: int, base: int, end: int) -> tuple:
        """Candidates starting in [s0, end - 8] (``end - s0 >= 8``): positions, header
        indices, lengths (lists, or int64 arrays)."""
        m = end - s0 - PREFIX_LEN + 1  # positions searched
        if m <= FIND_BYTES:
            return self._find(buf, s0 - base, m, base)
        # uint16 and uint32 at every byte offset (unaligned views): the first two bytes of a
        # header, then the length (most garbage fails here) and the header, one gather each
        u2 = np.ndarray((m,), "<u2", buf, s0 - base, (1,))
        idx = np.flatnonzero(np.take(self.first2, u2))
        u4 = np.ndarray((m + HEADER_LEN,), "<u4", buf, s0 - base, (1,))
        n = u4[idx + HEADER_LEN]
        short = np.flatnonzero(n <= self.max_len)
        idx, n = idx[short], n[short].astype(np.int64)
        h = u4[idx]
        k = np.searchsorted(self.codes, h)
        ok = np.flatnonzero((self.codes[k] == h) & (self.lo[k] <= n) & (n <= self.hi[k]))
        return idx[ok] + s0, k[ok], n[ok]

    def _find(self, buf: bytearray, lo: int, m: int, base: int) -> tuple:
        """The search of ``m`` positions from buffer index ``lo`` with bytes.find."""
        found = []
        hi = lo + m + HEADER_LEN - 1
        for h in self.headers:
            i = buf.find(h, lo, hi)
            while i >= 0:
                n = int.from_bytes(buf[i + HEADER_LEN : i + PREFIX_LEN], "little")
                k = self.index[h]
                if self.bounds[k][0] <= n <= self.bounds[k][1]:
                    found.append((i + base, k, n))
                i = buf.find(h, i + 1, hi)
        found.sort()
        return [f[0] for f in found], [f[1] for f in found], [f[2] for f in found]

    def tail_start(self, buf: bytearray, lo: int, base: int, end: int) -> int:
        """First position in [lo, end) whose bytes so far begin a header, or ``end``."""
        for p in range(lo, end):
            if bytes(buf[p - base : p - base + HEADER_LEN]) in self.prefixes:
                return p
        return end

    # -- validation ------------------------------------------------------------------------------
    def first_bad_word(self, buf: bytearray, base: int, start: int, stop: int) -> int:
        """Index of the first word in [start, stop) out of the ADC range, or -1."""
        if self.hi_off is not None:
            o = self.hi_off - base
            return buf[start + o : stop - 1 + o : 2].translate(self.badmap).find(1)
        bad = self.bad_words(np.frombuffer(buf, np.uint8, stop - start, start - base))[::2]
        return int(bad.argmax()) if bad[bad.argmax()] else -1

    def bad_words(self, a: np.ndarray) -> np.ndarray:
        """Whether the word starting at each byte of ``a`` (all but the last) is out of the
        ADC range of the profile, (len(a) - 1,) bool."""
        lay = self.layout
        if self.hi_off is not None:
            return a[self.hi_off : len(a) - 1 + self.hi_off] > self.hi_max
        lo, hi = a[:-1].astype(np.uint16), a[1:].astype(np.uint16)
        v = (lo << 8 | hi) if lay.word == "uint16be" else (lo | hi << 8)
        if lay.word == "int16le":
            v = v.view(np.int16)
        return (v < lay.min_word) | (v > lay.max_word)

    def decide_many(self, buf: bytearray, pos, k, n, every: np.ndarray, lo: int, base: int, end: int,
                    tail_start: Callable[[int], int]) -> tuple:
        """Decide many candidates at once: (status, why) int arrays and the bytes scanned.
        ``every``: the positions of all candidates, sorted; ``lo``: the first byte of the
        candidates' payloads; ``tail_start(x)``: the first position from x of the last,
        unsearched bytes that may still start a header."""
        kind = self.kind[k]
        stop = pos + PREFIX_LEN + n
        st = (stop <= end).astype(np.int8)  # OK if whole, else PEND: right for FIXED
        why = np.full(pos.size, -1, np.int64)
        scanned = 0
        count = np.bincount(kind, minlength=4)
        view = np.frombuffer(buf, np.uint8)  # released on return: the buffer resizes later
        if count[RESP]:  # zero padding after the code: the payload's bytes 1 to 3 that it has
            m = np.flatnonzero((kind == RESP) & (st == OK))
            at = np.minimum(pos[m, None] + (PREFIX_LEN + 1 + np.arange(3)), end - 1) - base
            padded = (view[at] != 0) & (np.arange(1, 4) < n[m, None])
            st[m[padded.any(axis=1)]] = REJ
        if count[RADC] and end - lo >= 2:  # the first word out of the ADC range
            scanned = end - lo
            m = np.flatnonzero(kind == RADC)
            first = pos[m] + PREFIX_LEN  # first word of each
            first_bad = self._first_bad_words(view[lo - base :], lo, first)
            refused = first_bad < first + self.radc_len
            st[m[refused]] = REJ
            why[m[refused]] = first_bad[refused]
        if count[OPAQUE]:  # refused if another candidate starts inside
            m = np.flatnonzero(kind == OPAQUE)
            j = np.searchsorted(every, pos[m] + PREFIX_LEN)
            inside = np.where(j < every.size, every[np.minimum(j, every.size - 1)], NONE)
            refused = inside < stop[m]
            st[m[refused]] = REJ
            why[m[refused]] = inside[refused]
            for i in m[~refused & (st[m] == OK)]:  # whole: the last 7 bytes may start a header yet
                if tail_start(int(pos[i]) + PREFIX_LEN) < stop[i]:
                    st[i] = PEND
        return st, why, scanned

    def _first_bad_words(self, a: np.ndarray, lo: int, first: np.ndarray) -> np.ndarray:
        """For RADC payloads starting at stream offsets ``first``, the first bad word at or
        after each (>= ODD - 1: none); ``a``: the bytes from stream offset ``lo``."""
        bad = self.bad_words(a)  # words starting at lo, lo + 1, ...
        shift = (first & 1) * ODD  # a RADC's words have the parity of its first
        # the bad words, keyed by parity: the even ones, then the odd ones + ODD, in order
        e = lo & 1  # index in ``bad`` of the first even position
        keys = np.concatenate((np.flatnonzero(bad[e::2]) * 2 + (lo + e),
                               np.flatnonzero(bad[1 - e :: 2]) * 2 + (lo + 1 - e + ODD), [NONE]))
        return keys[np.searchsorted(keys, first + shift)] - shift

    def why(self, buf: bytearray, base: int, q: int, k: int, n: int, w: int) -> str:
        """One line on why the candidate at stream offset ``q`` was refused (``w``: its
        first bad word, or the candidate inside it)."""
        name = self.names[k].decode("ascii")
        kind = self.kinds[k]
        if kind == RADC:
            lay = self.layout
            value = int(np.frombuffer(bytes(buf[w - base : w - base + 2]), lay.dtype)[0])
            return (f"RADC word {(w - q - PREFIX_LEN) // 2} is {value}, beyond the {lay.adc_bits}-bit ADC range "
                    f"[{lay.min_word}, {lay.max_word}] of this profile (stream byte {q})")
        if kind == OPAQUE:
            other = bytes(buf[w - base : w - base + HEADER_LEN]).decode("ascii", "replace")
            return (f"{name} declares {n} payload bytes but a {other} header starts {w - q - PREFIX_LEN} bytes "
                    f"into them: a stray header (stream byte {q})")
        payload = bytes(buf[q + PREFIX_LEN - base : q + PREFIX_LEN + n - base])
        return f"{name} padding is not zero: {payload.hex()} (stream byte {q})"
