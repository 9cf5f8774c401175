"""A recording played into the web view (``qradar view --web PORT --recording REC.mcap``),
with play, pause and seek from the page.

The player reads the recording in time (:func:`replay.source.recorded_messages`, as
``qradar replay`` does) and puts its targets, tracks, quantized frames and health into the
view's in-memory transport, so the view shows them as it shows a live stream. It paces
the messages by their recorded (log) times; a pause holds the next message; a seek
restarts the reading at the new position (the reader is sequential: a seek re-reads the
file up to there) and, while paused, shows the quarter of a second after it. At the end
it pauses at the last position; play starts again from the start."""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Callable

from pipeline.bus.session import BusConfig
from pipeline.nodes.transport import Transport
from radar_driver.model import RadarConfig
from radar_driver.scene import SimScene
from replay.errors import NoQradarChannelsError, ReplayError
from replay.mcapinfo import named_clock_ns, truth_clocks
from replay.mcapio import McapFile
from replay.mcapread import check_mcap
from replay.source import recorded_messages

log = logging.getLogger("qradar.web")

#: the recorded topics the view shows
SHOWN_TOPICS = ("targets", "tracks", "quantized", "health")
#: the player's state goes to the pages this often while it plays (s)
STATE_PERIOD_S = 0.25
#: after a seek while paused, the messages of this long after the position are shown (s)
PREVIEW_S = 0.25


def _shown(topic: str) -> bool:
    return topic.rsplit("/", 1)[-1] in SHOWN_TOPICS


class RecordingPlayer:
    """Plays ``path`` into ``transport`` under ``bus``'s prefix; ``on_state`` gets the
    state (:meth:`state`) while it plays and at each change, ``on_seek`` the state after a
    seek (the pages forget what they showed). Opening reads the file once (its length,
    metadata, radar configuration and truth)."""

    def __init__(self, path: str | Path, transport: Transport, bus: BusConfig,
                 on_state: Callable[[dict], None] = lambda s: None, on_seek: Callable[[dict], None] = lambda s: None):
        from ..api import Recording  # its reading of a recording's metadata

        self.path, self.transport, self.bus = Path(path), transport, bus
        self.on_state, self.on_seek = on_state, on_seek
        check_mcap(self.path)  # missing, a folder, empty, not MCAP: one line saying which
        f = McapFile(self.path)
        first = last = None
        sensors: dict[str, int] = {}  # each sensor's first log time
        for ch, msg in recorded_messages(f, None, threading.Event(), topic=_shown):
            first = msg.log_time if first is None else first
            last = msg.log_time
            sensors.setdefault(ch.topic.rsplit("/", 2)[-2], msg.log_time)
        if first is None:
            raise NoQradarChannelsError(f"{self.path} holds no targets, tracks, quantized frames or health to show")
        self.first_log_ns = first
        self.duration_s = (last - first) / 1e9
        self.truncated = f.truncated
        metadata = f.metadata_dict()
        #: when each sensor's truth clock began (ns): the one the file names, as re-processing reads
        #: it (the live run's start, or a later file's first raw frame); else the file's start
        clocks = truth_clocks(metadata)
        self.truth_t0_ns = {sid: self.first_log_ns if (t0 := named_clock_ns(clocks, sid, at)) is None else t0
                            for sid, at in sensors.items()}
        info = Recording(self.path, metadata, [], f.truncated)
        self.radar: RadarConfig = info.radar
        try:
            self.truth: SimScene | None = info.scene()
        except ReplayError:  # a real sensor's recording: no truth
            self.truth = None
        self._cond = threading.Condition()
        self._playing = True
        self._position_s = 0.0
        self._generation = 0
        self._preview_until: float | None = None
        self._closed = False
        self._interrupt = threading.Event()
        self._thread: threading.Thread | None = None
        self.published = 0

    def state(self) -> dict:
        with self._cond:
            return {"name": self.path.name, "playing": self._playing, "position_s": round(self._position_s, 3),
                    "duration_s": round(self.duration_s, 3), "truncated": self.truncated}

    # -- control (the server's threads) ---------------------------------------------------------
    def control(self, action, position_s=None) -> dict:
        """``play``, ``pause`` or ``seek`` (to ``position_s``, s from the start; clamped to
        the recording); the new state. ValueError for anything else."""
        if action not in ("play", "pause", "seek"):
            raise ValueError(f"action {action!r} must be play, pause or seek")
        if action == "seek":
            if isinstance(position_s, bool) or not isinstance(position_s, (int, float)) or position_s != position_s:
                raise ValueError(f"seek needs position_s, a number of seconds, got {position_s!r}")
            with self._cond:
                self._position_s = min(max(float(position_s), 0.0), self.duration_s)
                self._generation += 1
                self._preview_until = None if self._playing else self._position_s + PREVIEW_S
                self._interrupt.set()
                self._cond.notify_all()
            self.on_seek(self.state())
        else:
            with self._cond:
                if action == "play" and not self._playing and self._position_s >= self.duration_s:
                    self._position_s = 0.0  # at the end: from the start again
                    self._generation += 1
                    self._interrupt.set()
                self._playing = action == "play"
                self._cond.notify_all()
        state = self.state()
        self.on_state(state)
        return state

    # -- the player's thread ------------------------------------------------------------------------
    def start(self) -> "RecordingPlayer":
        self._thread = threading.Thread(target=self._run, name="recording-player", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        with self._cond:
            self._closed = True
            self._interrupt.set()
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _run(self) -> None:
        try:
            while True:
                with self._cond:
                    while not (self._closed or self._playing or self._preview_until is not None):
                        self._cond.wait()
                    if self._closed:
                        return
                    generation, start_s = self._generation, self._position_s
                    self._interrupt = threading.Event()
                if self._play_from(generation, start_s):  # the end reached
                    with self._cond:
                        if generation == self._generation:
                            self._playing, self._position_s, self._preview_until = False, self.duration_s, None
                    self.on_state(self.state())
        except Exception:  # say why, once; the view goes on without its recording
            log.exception("the recording player of %s failed", self.path)

    def _play_from(self, generation: int, start_s: float) -> bool:
        """Put the messages from ``start_s`` on, each at its time; False when a seek or
        the end of the view interrupted it, True at the end of the recording."""
        t_wall, pos0 = time.monotonic(), start_s
        next_state = 0.0
        for ch, msg in recorded_messages(McapFile(self.path), None, self._interrupt, start_s or None, topic=_shown):
            rel_s = (msg.log_time - self.first_log_ns) / 1e9
            while True:  # until it is due (the pause holds it)
                with self._cond:
                    if self._closed or generation != self._generation:
                        return False
                    if not self._playing:
                        if self._preview_until is not None and rel_s <= self._preview_until:
                            break
                        self._preview_until = None
                        self._cond.wait(STATE_PERIOD_S)
                        t_wall, pos0 = time.monotonic(), self._position_s  # a resume goes on from here
                        continue
                    delay = t_wall + (rel_s - pos0) - time.monotonic()
                    if delay <= 0:
                        break
                    self._cond.wait(min(delay, STATE_PERIOD_S))
                if time.monotonic() >= next_state:
                    next_state = time.monotonic() + STATE_PERIOD_S
                    self.on_state(self.state())
            sensor, topic = ch.topic.rsplit("/", 2)[-2:]
            self.transport.put(self.bus.key(sensor, topic), bytes(msg.data))
            self.published += 1
            with self._cond:
                if generation == self._generation:
                    self._position_s = rel_s
        return not self._interrupt.is_set()
