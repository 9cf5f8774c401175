"""Frame assembly: the K-MD2's messages in, frames and the counters of what was lost out.

No port and no threads: :class:`FrameAssembler` takes the bytes a link delivered
(:meth:`~FrameAssembler.decode`, through the codec's :class:`~.protocol.StreamDecoder`)
and the messages decoded from them (:meth:`~FrameAssembler.take`). Each ``GNFD`` is
answered by ``RESP``, the selected ``RADC`` and ``DONE``. In the default profile a
``RADC`` is one ramp and ``ramps_per_frame`` consecutive ones (by the ``DONE`` counter)
make a frame of M = ramps x 256; in a profile of many chirps per ``RADC`` one ``RADC``
makes a frame of ``ramps_per_frame`` of its chirps (``chirp_select``). A counter gap
counts the sensor frames lost (``dropped``) and discards the partial frame.

Timestamps: K-MD2 frames carry no clock, so a frame's ``timestamp_ns`` is the host's
clock (``time.time_ns()``) when the ``DONE`` of its first RADC arrived.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from enum import Enum
from typing import Callable

import numpy as np

from .errors import SensorResponseError, SensorTimeout
from .profile import SensorProfile
from .protocol import Done, Message, Radc, Resp, RespCode, StreamDecoder
from .source import RawFrame


@dataclass
class DriverCounters:
    """What a session has seen. ``dropped``: sensor frames lost (the DONE counter's gaps
    and the partial frames they broke, in frames); ``dropped_radcs``: the gaps in RADCs
    (ramps in the default profile); ``incomplete``: RADCs that never arrived whole;
    ``discarded_ramps``: RADCs thrown away with a partial frame; ``timeouts``: GNFDs sent
    again after ``timeout_s`` of silence; ``repeated``: answers with the last counter
    again (not a new measurement: skipped); ``wrong_device``: reconnect attempts refused
    because the port's path now names another device than the one first opened;
    ``link_losses``: times the link was lost (a reconnect began); ``down_ms``: time without
    a link, from each loss to its reconnect (or to the stop); ``link_down``: 1 while it is
    lost (at the end: the sensor was not back)."""

    frames: int = 0
    ramps: int = 0
    bytes: int = 0
    resyncs: int = 0
    skipped_bytes: int = 0
    dropped: int = 0
    dropped_radcs: int = 0
    reconnects: int = 0
    incomplete: int = 0
    discarded_ramps: int = 0
    timeouts: int = 0
    resp_errors: int = 0
    repeated: int = 0
    wrong_device: int = 0
    link_losses: int = 0
    down_ms: int = 0
    link_down: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class Taken(Enum):
    """What one message did: nothing for the poller, answered a GNFD (a DONE), or
    answered one and completed a frame (then :meth:`FrameAssembler.frame` builds it)."""

    NOTHING = 0
    ANSWER = 1
    FRAME = 2


class FrameAssembler:
    """Messages -> :class:`~.source.RawFrame`, counting into ``counters``.

    ``source`` names the link in error messages. ``clock``: the host's clock in ns,
    read at each DONE (a frame's ``timestamp_ns``)."""

    MAX_INCOMPLETE_IN_A_ROW = 8

    def __init__(self, profile: SensorProfile, ramps_per_frame: int = 2, chirp_select: str = "first",
                 sensor_id: str = "kmd2", source: str = "the sensor", counters: DriverCounters | None = None,
                 clock: Callable[[], int] = time.time_ns):
        self.profile = profile
        self.ramps_per_frame = ramps_per_frame
        self.sensor_id = sensor_id
        self.source = source
        self.counters = DriverCounters() if counters is None else counters
        self.decoder = StreamDecoder(profile)
        self._clock = clock
        lay = profile.radc
        self.radcs_per_frame = ramps_per_frame if lay.chirps == 1 else 1
        self._chirps = lay.chirp_indices(ramps_per_frame, chirp_select) if lay.chirps > 1 else None
        self._config_id = profile.radar(ramps_per_frame, chirp_select).config_id()
        self._pending: Radc | None = None  # the RADC of the answer under way
        self._last_counter: int | None = None
        self._radcs: list[tuple[int, int, np.ndarray]] = []  # (counter, t_ns, words) of a partial frame
        self._lost_radcs = 0  # lost RADCs not yet a whole frame in ``dropped``
        self._incomplete_in_a_row = 0
        self.seq = 0  # the next frame's

    @property
    def held(self) -> int:
        """RADCs of the partial frame in hand."""
        return len(self._radcs)

    def decode(self, data: bytes) -> list[Message]:
        """The messages ``data`` completes, counting bytes, resyncs and skipped bytes."""
        st, c = self.decoder.stats, self.counters
        before = (st.resyncs, st.skipped_bytes)
        out = self.decoder.feed(data)
        c.bytes += len(data)
        c.resyncs += st.resyncs - before[0]
        c.skipped_bytes += st.skipped_bytes - before[1]
        return out

    def restart(self) -> None:
        """After a (re)connect: forget buffered bytes and the answer under way, and
        discard the partial frame (counted); the DONE counter stays, so that a gap
        across the reconnect counts."""
        self.decoder.reset()
        self._pending = None
        self._discard()

    def take(self, m: Message) -> Taken:
        """Account for one message. Raises SensorResponseError on a RESP error and
        SensorTimeout after MAX_INCOMPLETE_IN_A_ROW answers without a whole RADC."""
        if isinstance(m, Radc):
            if self._pending is not None:
                self.counters.incomplete += 1
            self._pending = m
            return Taken.NOTHING
        if isinstance(m, Done):
            return self._done(m)
        if isinstance(m, Resp) and m.code != RespCode.OK:
            self.counters.resp_errors += 1
            raise SensorResponseError("GNFD", m.code)
        return Taken.NOTHING

    def _done(self, m: Done) -> Taken:
        c = self.counters
        radc, self._pending = self._pending, None
        if m.frame_counter == self._last_counter:  # the same RADC again (a sensor that answers
            c.repeated += 1                        # a queued GNFD at once): not a new measurement
            return Taken.ANSWER
        self._note_counter(m.frame_counter)
        t_ns = self._clock()
        if radc is None:
            c.incomplete += 1
            self._discard()
            self._incomplete_in_a_row += 1
            if self._incomplete_in_a_row >= self.MAX_INCOMPLETE_IN_A_ROW:
                self._incomplete_in_a_row = 0
                raise SensorTimeout(f"{self.MAX_INCOMPLETE_IN_A_ROW} GNFD answers in a row from "
                                    f"{self.source} lacked a whole RADC")
            return Taken.ANSWER
        self._incomplete_in_a_row = 0
        c.ramps += 1
        self._radcs.append((m.frame_counter, t_ns, radc.words))
        return Taken.FRAME if len(self._radcs) >= self.radcs_per_frame else Taken.ANSWER

    def frame(self) -> RawFrame:
        """The frame of the RADCs in hand (after :attr:`Taken.FRAME`)."""
        radcs, self._radcs = self._radcs, []
        lay = self.profile.radc
        data = np.empty((self.ramps_per_frame, lay.samples, 2), dtype=np.complex64)  # the frame, written in place
        if self._chirps is None:  # one chirp per RADC: ramp i is RADC i's
            for i, (_, _, w) in enumerate(radcs):
                lay.to_complex(w[:, :1], np.complex64, lay.azimuth, out=data[i:i + 1])
        else:  # R of one RADC's chirps
            for i, c in enumerate(self._chirps.tolist()):
                lay.to_complex(radcs[0][2][:, c:c + 1], np.complex64, lay.azimuth, out=data[i:i + 1])
        frame = RawFrame(
            sensor_id=self.sensor_id,
            seq=self.seq,
            timestamp_ns=radcs[0][1],
            data=data.reshape(self.ramps_per_frame * lay.samples, 2),  # a view: made once, in place
            counters=tuple(c for c, _, _ in radcs),
            config_id=self._config_id,
        )
        self.seq += 1
        self.counters.frames += 1
        return frame

    def feed(self, data: bytes) -> list[RawFrame]:
        """The frames ``data`` completes (decode, take, build), for a reader with no poller."""
        return [self.frame() for m in self.decode(data) if self.take(m) is Taken.FRAME]

    def _note_counter(self, counter: int) -> None:
        last = self._last_counter
        if last is not None:
            gap = (counter - last - 1) & 0xFFFFFFFF
            if 0 < gap < 0x80000000:
                self.counters.dropped_radcs += gap
                self._lost_radcs += gap
                self._discard()
        self._last_counter = counter

    def _discard(self) -> None:
        """Throw the partial frame away; whole frames of lost RADCs count in ``dropped``."""
        n = len(self._radcs)
        self.counters.discarded_ramps += n
        self._lost_radcs += n
        self._radcs = []
        whole, self._lost_radcs = divmod(self._lost_radcs, self.radcs_per_frame)
        self.counters.dropped += whole
