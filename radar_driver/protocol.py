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
it resynchronizes by scanning for a known header whose length is plausible for that
header and whose payload is valid (a RADC payload holds ADC-range words only), and
counts the bytes it skipped; it never raises on input.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Iterator, Union

import numpy as np

from .errors import ProtocolError, RespCode
from .profile import DEFAULT_PROFILE, RadcLayout, SensorProfile

HEADER_LEN = 4
PREFIX_LEN = 8  # header + uint32 length


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
@dataclass
class DecoderStats:
    messages: int = 0
    bytes_in: int = 0
    skipped_bytes: int = 0
    resyncs: int = 0
    invalid: int = 0  # plausible header whose payload failed validation
    last_error: str = ""


@dataclass
class StreamDecoder:
    """Incremental decoder: ``feed(chunk)`` returns the messages completed by ``chunk``.

    Garbage is skipped up to the next known header with a plausible length; each run of
    skipped bytes counts one resync. Memory is bounded by the largest plausible message.
    ``profile``: the sensor's conventions (RADC layout, other frames' lengths).
    """

    profile: SensorProfile = DEFAULT_PROFILE
    stats: DecoderStats = field(default_factory=DecoderStats)
    _buf: bytearray = field(default_factory=bytearray)
    _pad: int = 0  # zero padding that may follow the last message
    _skipping: bool = False

    def __post_init__(self) -> None:
        self._lengths = self.profile.plausible_length()
        self._headers = tuple(self._lengths)

    def feed(self, chunk: bytes) -> list[Message]:
        self._buf += chunk
        self.stats.bytes_in += len(chunk)
        return list(self._drain())

    def wanted(self) -> int:
        """Fewest further bytes that can complete the next message (at least 1): what a
        reader may block for without stalling the stream."""
        buf = self._buf
        if len(buf) < PREFIX_LEN:
            return PREFIX_LEN - len(buf)
        lo, hi = self._lengths.get(bytes(buf[:4]), (1, 0))
        (length,) = struct.unpack_from("<I", buf, 4)
        if lo <= length <= hi:
            return max(1, PREFIX_LEN + length - len(buf))
        return 1

    def pending(self) -> int:
        """Bytes held, waiting for the rest of a message."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget buffered bytes (after a reconnect); the counters stay."""
        self._buf.clear()
        self._pad = 0
        self._skipping = False

    def _drain(self) -> Iterator[Message]:
        buf = self._buf
        while True:
            if self._pad:
                n = 0
                while n < self._pad and n < len(buf) and buf[n] == 0:
                    n += 1
                if n < self._pad and n == len(buf):
                    return  # maybe more padding to come
                del buf[:n]
                self._pad = 0
            if len(buf) < PREFIX_LEN:
                head = bytes(buf[:HEADER_LEN])
                if buf and not any(h.startswith(head) for h in self._headers):
                    self._skip(1)
                    continue
                return  # wait for the length
            header = bytes(buf[:4])
            (length,) = struct.unpack_from("<I", buf, 4)
            lo, hi = self._lengths.get(header, (1, 0))
            if not lo <= length <= hi:
                self._skip(1)
                continue
            if len(buf) < PREFIX_LEN + length:
                return  # wait for the payload
            try:
                msg = decode_payload(header, bytes(buf[PREFIX_LEN : PREFIX_LEN + length]), self.profile)
            except ProtocolError as exc:
                self.stats.invalid += 1
                self.stats.last_error = str(exc)
                self._skip(1)
                continue
            del buf[: PREFIX_LEN + length]
            self._pad = (-length) % 4
            self._skipping = False
            self.stats.messages += 1
            yield msg

    def _skip(self, n: int) -> None:
        """Drop ``n`` bytes and then everything up to the next possible header start."""
        buf = self._buf
        if not self._skipping:
            self.stats.resyncs += 1
            self._skipping = True
        starts = [i for i in (buf.find(h, n) for h in self._headers) if i >= 0]
        if starts:
            cut = min(starts)
        else:
            # keep a tail that could be the start of a header split across chunks
            cut = max(n, len(buf) - (HEADER_LEN - 1))
            while cut < len(buf) and not any(h.startswith(bytes(buf[cut:])) for h in self._headers):
                cut += 1
        self.stats.skipped_bytes += cut
        del buf[:cut]
