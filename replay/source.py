"""Reading a recording in time: :func:`recorded_messages` yields the qradar messages of
an MCAP file at their recorded pace (the player publishes them all), and
:class:`RecordingSource` is a recording as a source of raw frames: its
``<prefix>/<sensor>/raw`` messages as :class:`~radar_driver.source.RawFrame` objects
(:class:`~radar_driver.source.FrameSource`).

Frames come in file order, as fast as they are read, or at their recorded pace scaled
by ``rate``. A frame that does not decode is counted (``bad_frames``), logged and
skipped; a gap in a sensor's sequence numbers is counted in ``dropped``, as far as the
recorded time allows, a restarted count in ``seq_resets`` and a number out of line in
``implausible_seq`` (:func:`pipeline.nodes.counters.judge_seq`, on the log times). The wire
format carries no ramp counters, so the frames' ``counters`` are empty. A file cut short
yields the frames of its complete chunks and sets ``truncated``. Every chunk's CRC is
checked (:class:`replay.mcapio.McapFile`): a damaged chunk's frames are never yielded;
it is logged, and its messages are counted in ``lost`` (``damaged``: the chunks).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

from pipeline.nodes.counters import SeqTrack, judge_seq
from pipeline.wire import WireError, decode_raw
from radar_driver.source import RawFrame, StoppableSource

from mcap.records import Channel, Message

from .errors import ReplayError
from .mcapio import McapFile, qradar_channels
from .mcapread import check_mcap

log = logging.getLogger("qradar.replay")


def recorded_messages(f: McapFile, rate: float | None, stop: threading.Event, start_s: float | None = None,
                      end_s: float | None = None, topic: Callable[[str], bool] | None = None
                      ) -> Iterator[tuple[Channel, Message]]:
    """The qradar messages of ``f`` in file order, each released at its recorded time
    (log time) divided by ``rate`` (None: at once), from ``start_s`` to ``end_s`` (s
    from the file's first qradar message; None: the start, the end), those whose topic
    ``topic`` accepts. Ends early once ``stop`` is set."""
    first_log = t0 = None
    for ch, msg in f.messages():
        if stop.is_set():
            return
        if ch.id not in qradar_channels({ch.id: ch}):
            continue
        if first_log is None:
            first_log = msg.log_time
        rel_s = (msg.log_time - first_log) / 1e9
        if start_s is not None and rel_s < start_s:
            continue
        if end_s is not None and rel_s > end_s:
            return
        if topic is not None and not topic(ch.topic):
            continue
        if rate is not None:
            if t0 is None:
                t0 = time.monotonic()
            delay = t0 + (rel_s - (start_s or 0.0)) / rate - time.monotonic()
            if delay > 0 and stop.wait(delay):
                return
        yield ch, msg


@dataclass
class _RecordedSensorStats:
    frames: int = 0
    dropped: int = 0
    bad_frames: int = 0
    seq_resets: int = 0
    implausible_seq: int = 0
    track: SeqTrack | None = None


class RecordingSource(StoppableSource):
    """``with RecordingSource(path) as src: for frame in src.frames(): ...``

    sensors: the sensor ids to read (None = all). rate: None = as fast as read, else
    the recorded pace (log times) times ``rate``."""

    def __init__(self, path: str | Path, sensors: list[str] | None = None, rate: float | None = None):
        super().__init__()
        if rate is not None and not rate > 0:
            raise ReplayError(f"rate={rate!r} must be > 0 (or None: as fast as read)")
        self.path = Path(path)
        self.sensors_wanted = None if sensors is None else set(sensors)
        self.rate = rate
        self.file = McapFile(self.path)
        self.truncated = False
        self.lost = 0  # messages of damaged chunks (never yielded), once the file was read
        self.damaged: list[str] = []  # one line per damaged chunk or problem
        self._stats: dict[str, _RecordedSensorStats] = {}

    def __enter__(self) -> "RecordingSource":
        check_mcap(self.path)  # missing, a folder, empty, not MCAP: one line saying which
        return self

    def stats(self) -> dict[str, dict[str, int]]:
        return {sid: {"frames": st.frames, "dropped": st.dropped, "bad_frames": st.bad_frames,
                      "seq_resets": st.seq_resets, "implausible_seq": st.implausible_seq}
                for sid, st in self._stats.items()}

    @property
    def sensors(self) -> list[str]:
        """Sensor ids met so far (all of them once the file was read), sorted."""
        return sorted(self._stats)

    @property
    def metadata(self) -> dict[str, dict[str, str]]:
        """The file's metadata records met so far (all of them once the file was read)."""
        return self.file.metadata_dict()

    def frames(self, limit: int | None = None) -> Iterator[RawFrame]:
        n = 0
        for ch, msg in recorded_messages(self.file, self.rate, self._stop, topic=lambda t: t.endswith("/raw")):
            if limit is not None and n >= limit:
                break
            try:
                m = decode_raw(msg.data, f"{self.path}: {ch.topic} #{msg.sequence}")
            except WireError as exc:
                sid = ch.topic.rsplit("/", 2)[-2] if ch.topic.count("/") >= 2 else "_unknown"
                self._stats.setdefault(sid, _RecordedSensorStats()).bad_frames += 1
                log.warning("skipping a bad raw frame (counted in bad_frames): %s", exc)
                continue
            if self.sensors_wanted is not None and m.sensor_id not in self.sensors_wanted:
                continue
            st = self._stats.setdefault(m.sensor_id, _RecordedSensorStats())
            st.track, verdict = judge_seq(st.track, m.seq, msg.log_time / 1e9)
            st.dropped += verdict.missing
            st.seq_resets += verdict.resets
            st.implausible_seq += verdict.implausible
            st.frames += 1
            n += 1
            yield RawFrame(m.sensor_id, m.seq, m.timestamp_ns, m.data, (), m.config_id)
        self.truncated = self.file.truncated
        if self.truncated:
            log.warning("%s is cut short (%s); read up to its last complete chunk", self.path,
                        self.file.truncation_reason)
        if self.file.complete:
            self.lost, self.damaged = self.file.lost, self.file.damage_lines()
            self.file.warn(log, "its frames are not read")
