"""The input queue of a processing node: one FIFO per sensor, served round-robin, bounded
per sensor (frames), in all (frames) and in bytes.

A flooding sensor fills its own FIFO and then loses its own newest frames; when the
whole queue is full (frames or bytes), room is made by dropping the newest frame of the
sensor with the most bytes waiting, so the others keep their share. The worker takes one
frame from each waiting sensor in turn. Every drop is returned to the caller, which
counts it against the sensor that lost the frame.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any, Hashable

from pipeline.errors import ParameterError


class FairQueue:
    """Bounded per-sensor FIFOs served round-robin; thread-safe.

    max_frames: frames in all; max_frames_per_sensor: frames of one sensor;
    max_bytes: payload bytes in all (as given to :meth:`put`)."""

    def __init__(self, max_frames: int, max_frames_per_sensor: int | None = None, max_bytes: int = 64 << 20):
        per = max_frames if max_frames_per_sensor is None else max_frames_per_sensor
        if max_frames < 1 or per < 1 or max_bytes < 1:
            raise ParameterError(f"queue bounds {max_frames} frames, {per} per sensor, {max_bytes} bytes "
                                 "must all be >= 1")
        self.max_frames, self.max_per_sensor, self.max_bytes = max_frames, min(per, max_frames), max_bytes
        self._fifos: dict[Hashable, deque] = {}
        self._bytes_of: dict[Hashable, int] = {}
        self._ring: deque = deque()  # sensors with frames waiting, in serving order
        self._frames = 0
        self._bytes = 0
        self._cond = threading.Condition()
        #: the frame counts the getters now waiting want to be woken at (1: a first frame; a
        #: lingering getter: its full batch); put wakes them at the least, not at every frame
        self._wants: list[int] = []
        self._wake_at = 0  # min(_wants), 0 with no getter waiting
        self._last_put = 0.0  # time.monotonic() of the last frame queued

    def __len__(self) -> int:
        return self._frames

    @property
    def nbytes(self) -> int:
        return self._bytes

    def empty(self) -> bool:
        return self._frames == 0

    def put(self, sensor: Hashable, item: Any, nbytes: int) -> list[Hashable]:
        """Queue ``item`` of ``sensor``; returns the sensors whose frames were dropped to
        keep the bounds (the new frame's own sensor when it was refused), one per frame."""
        dropped: list[Hashable] = []
        with self._cond:
            fifo = self._fifos.get(sensor)
            if nbytes > self.max_bytes or (fifo is not None and len(fifo) >= self.max_per_sensor):
                return [sensor]
            while self._frames >= self.max_frames or self._bytes + nbytes > self.max_bytes:
                victim = max(self._ring, key=self._bytes_of.__getitem__)
                if victim == sensor or self._bytes_of[victim] <= self._bytes_of.get(sensor, 0) + nbytes:
                    return dropped + [sensor]  # the newcomer's sensor would hold the most: it loses its frame
                _, vb = self._fifos[victim].pop()  # the largest sensor's newest
                self._account(victim, -1, -vb)
                dropped.append(victim)
            if fifo is None:
                fifo = self._fifos[sensor] = deque()
                self._bytes_of[sensor] = 0
            if not fifo:
                self._ring.append(sensor)
            fifo.append((item, nbytes))
            self._account(sensor, 1, nbytes)
            self._last_put = time.monotonic()
            if self._wake_at and self._frames >= self._wake_at:  # a getter wants to look now
                self._cond.notify_all()
        return dropped

    def _wait(self, want: int, timeout_s: float) -> None:
        """Wait (holding the condition) up to ``timeout_s``, woken early once ``want`` frames wait."""
        self._wants.append(want)
        self._wake_at = min(self._wants)
        try:
            self._cond.wait(timeout_s)
        finally:
            self._wants.remove(want)
            self._wake_at = min(self._wants) if self._wants else 0

    def _account(self, sensor: Hashable, frames: int, nbytes: int) -> None:
        self._frames += frames
        self._bytes += nbytes
        self._bytes_of[sensor] += nbytes
        if not self._fifos[sensor]:
            del self._fifos[sensor], self._bytes_of[sensor]
            try:
                self._ring.remove(sensor)
            except ValueError:
                pass

    def get_batch(self, max_items: int, timeout_s: float, per_sensor: int | None = None,
                  linger_s: float = 0.0, lull_s: float = 0.001) -> list[Any]:
        """Up to ``max_items`` frames, one per waiting sensor in turn, at most ``per_sensor``
        of one sensor (a flooding sensor cannot fill a batch and so delay the others' next
        frames by a whole batch); waits at most ``timeout_s`` for the first; [] if none came.
        ``linger_s``: once a frame waits, wait up to this long for ``max_items`` while
        frames keep coming (a lull of ``lull_s`` without one ends the wait), so frames of
        sensors sending at their own times share one vectorized call and a lone sensor
        waits at most ``lull_s``."""
        deadline = time.monotonic() + timeout_s
        out: list[Any] = []
        with self._cond:
            while not self._frames:
                left = deadline - time.monotonic()
                if left <= 0:
                    return out
                self._wait(1, left)
            if linger_s > 0 and self._frames < max_items:
                # not woken by each frame (a thread switch each): by a full batch, or at the end of
                # a lull (lull_s since the later of the linger's start and the last frame) or of the linger
                start = time.monotonic()
                until = start + linger_s
                while self._frames < max_items:
                    now = time.monotonic()
                    quiet = now - max(start, self._last_put)
                    if now >= until or quiet >= lull_s:  # the linger is over, or a lull: no one else is sending now
                        break
                    self._wait(max_items, min(until - now, lull_s - quiet))
            taken: dict[Hashable, int] = {}
            full: list[Hashable] = []  # sensors whose share of this batch is taken
            while self._ring and len(out) < max_items:
                sensor = self._ring.popleft()
                fifo = self._fifos[sensor]
                item, nbytes = fifo.popleft()
                out.append(item)
                self._frames -= 1
                self._bytes -= nbytes
                self._bytes_of[sensor] -= nbytes
                taken[sensor] = n = taken.get(sensor, 0) + 1
                if not fifo:
                    del self._fifos[sensor], self._bytes_of[sensor]
                elif per_sensor is not None and n >= per_sensor:
                    full.append(sensor)
                else:
                    self._ring.append(sensor)
            self._ring.extend(full)  # after the sensors still waiting their turn
        return out
