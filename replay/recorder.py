"""The recorder node: everything under ``<prefix>/**`` (or ``topics``) into MCAP.

Each message is checked before any byte of it is written (:mod:`replay.admission`: its
key, size, shape and times, with the nodes' own checks); a message refused is counted
by kind and sensor (``refused_time``, ``refused_size``, ``refused_shape``,
``refused_topic``) and touches nothing else. Each message is written with its log time
(arrival at the recorder, ns), its publish time (the message's own timestamp: sensor
time for frames and targets, the node's for health) and its sequence number (the
frame's). Targets are also written as ``foxglove.PointCloud``. A chunk is flushed at
least every second, so a recorder killed with SIGKILL loses at most the last second;
``qradar recover`` turns such a file into a complete, indexed one. Each flush reads back
what it wrote: ``written`` counts the messages read back from the file (chunk CRCs
checked), and a message written but not read back is an error (``verify_errors``,
``error``, lost by topic), as is a summary whose statistics disagree at the file's end.
Counters go to the recorder's health topic and, at the end, into the file's metadata.

Memory is bounded: per-sensor state lives as long as the sensor (its counters are
folded into the totals when it expires), and mcap's Writer, which keeps every channel of
its file (~0.5 KB each) and every chunk's index until the file ends, starts a new file
(``name_0001.mcap``, ...) once ``max_dead_channels`` of its channels belong to sensors
no longer live, or the file nears MCAP's 65 535 channels.

A write error (a full disk, EFBIG, EIO, a removed folder) never stops the node: the
file is cut back to its last flushed chunk and closed (:meth:`McapSink.abort`), the
error is logged once (then at most once a second) and shown in health, and by the
``on_write_error`` policy the recorder either pauses — counting every message it cannot
write, by topic — and every ``retry_s`` probes for space (at least ``resume_free_bytes``
free), resuming into the next file (``name_0001.mcap``, ...), or stops recording for
good. Only the first file is different: a recording that cannot even begin is an error
at start (ReplayError), before anything runs.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import threading
import time
from enum import Enum
from pathlib import Path

import zenoh

from pipeline.bus.session import BusConfig, zenoh_reason
from pipeline.nodes.counters import NO_SENSOR, UNKNOWN_SENSOR
from pipeline.nodes.intake import ProcessingNode, QueueConfig, QueuedFrame
from pipeline.nodes.transport import Transport
from radar_driver.model import RadarConfig

from .admission import Admission, RefusalCounts
from .errors import RecordingExists, ReplayError, UnwritableMessage
from pipeline.wire.shared import DecodedOnce

from .derived import DerivedConfig, Derivations
from .mcapio import DERIVED, MAX_FILE_CHANNELS, FlushCheck, McapSink, describe_os_error, topic_of
from .outputs import check_file_kind

log = logging.getLogger("qradar.record")


def default_recording_path(folder: Path = Path("recordings"), now_ns: int | None = None) -> Path:
    """``<folder>/run-YYYYmmdd-HHMMSS-mmm.mcap`` (local time, to the millisecond); a
    recorder given it with ``new_name_if_taken`` goes on to ``-1``, ``-2``, ... if that
    name is taken (two runs in the same millisecond)."""
    now_ns = time.time_ns() if now_ns is None else now_ns
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now_ns // 1_000_000_000))
    return Path(folder) / f"run-{stamp}-{now_ns // 1_000_000 % 1000:03d}.mcap"

FLUSH_PERIOD_S = 1.0

#: at most one log line per this many seconds while recording is paused
PAUSED_LOG_PERIOD_S = 1.0
#: the sensors whose first raw frame later files of a split set name (``first_raw_ns``), at most
MAX_CLOCKS = 4096
#: file names listed in health and summaries (the newest); ``files_written`` counts them all
LISTED_FILES = 8
#: senders named in the summary's ``refused_by_sensor`` (the most refused; the rest summed)
LISTED_SENDERS = 16
#: channels of sensors no longer live that a file may hold before the next file starts
#: (mcap's Writer keeps ~0.5 KB of each channel until its file ends)
DEAD_CHANNELS_MAX = 4096
#: the health messages of one slice of sensors share one summary of the recorder (it sums
#: every sensor's counters), at most this old, s
HEALTH_SUMMARY_S = 0.05
#: a new file starts before this many channels (MCAP's channel ids are uint16); a batch
#: adds at most three channels a message (a targets message, its pointcloud and its scene)
FILE_CHANNELS_MAX = MAX_FILE_CHANNELS - 3 * 512


class OnWriteError(str, Enum):
    """What the recorder does after a write error: pause and resume into a new file
    when space returns, or stop recording (the node, and the pipeline, keep running)."""

    RESUME = "resume"
    STOP = "stop"


class RecordingState(str, Enum):
    WRITING = "writing"
    PAUSED = "paused"    # after a write error, probing for space every retry_s
    STOPPED = "stopped"  # after a write error with on_write_error=stop


def versions() -> dict[str, str]:
    """Python's and the packages' versions, for a recording's metadata."""
    from importlib import metadata as importlib_metadata  # here: its import costs every process's start

    out = {"python": platform.python_version()}
    for pkg in ("qradar", "numpy", "eclipse-zenoh", "mcap", "pyserial"):
        try:
            out[pkg] = importlib_metadata.version(pkg)
        except importlib_metadata.PackageNotFoundError:
            out[pkg] = "unknown"
    return out


def free_bytes(folder: Path) -> int | None:
    """Free bytes (for an unprivileged writer) in ``folder``, or in its nearest existing
    ancestor (the folder may have been removed); None if unknown."""
    d = Path(folder)
    for _ in range(64):
        try:
            st = os.statvfs(d)
            return st.f_bavail * st.f_frsize
        except FileNotFoundError:
            if d.parent == d:
                return None
            d = d.parent
        except OSError:
            return None
    return None


class RecordingFiles(ProcessingNode):
    """The files of a recording (the recorder node's base): each created exclusively,
    split by size (``split_size_mb``) or age (``split_duration_s``) into ``name_0001.mcap``,
    ...; flushed at least every FLUSH_PERIOD_S and read back (``written``: messages read
    back from the files; ``pending``: since the last flush; ``verify_errors``: read-backs
    that disagreed with what was written); after a write error closed up to its last
    flushed chunk, then paused (probing for space every ``retry_s``, for at least
    :attr:`resume_free_bytes`, resuming into the next file) or stopped, by ``on_write_error``
    (``recording_ended`` is set). ``metadata``: name -> {key: value} records written at
    the start of every file. Messages lost (write errors, read-backs) are counted by topic."""

    #: the free bytes a paused recording waits for before it resumes into the next file
    resume_free_bytes: int = 1_000_000

    def __init__(self, bus: BusConfig, path: str | Path, session: zenoh.Session | Transport | None = None,
                 split_size_mb: float | None = None, split_duration_s: float | None = None,
                 metadata: dict[str, dict] | None = None, on_write_error: OnWriteError | str = OnWriteError.RESUME,
                 retry_s: float = 5.0, new_name_if_taken: bool = False, overwrite: bool = False, **kw):
        super().__init__(bus, session, **kw)
        self.base_path = Path(path)
        if self.base_path.suffix != ".mcap":
            raise ReplayError(f"recording path {self.base_path} must end in .mcap")
        if not new_name_if_taken:
            check_file_kind(self.base_path, "recording")  # a folder or a link, --force or not
        if not (new_name_if_taken or overwrite) and os.path.lexists(self.base_path):
            raise RecordingExists.at(self.base_path)  # at once (and again, exclusively, at the start)
        if split_size_mb is not None and not split_size_mb > 0:
            raise ReplayError(f"split size {split_size_mb!r} MB must be > 0")
        if split_duration_s is not None and not split_duration_s > 0:
            raise ReplayError(f"split duration {split_duration_s!r} s must be > 0")
        try:
            self.on_write_error = OnWriteError(on_write_error)
        except ValueError:
            raise ReplayError(f"on_write_error={on_write_error!r} must be one of "
                              f"{[p.value for p in OnWriteError]}") from None
        if not retry_s > 0:
            raise ReplayError(f"write-error retry period {retry_s!r} s must be > 0")
        self.split_size = None if split_size_mb is None else int(split_size_mb * 1e6)
        self.split_duration_s = split_duration_s
        self.extra_metadata = metadata or {}
        self.retry_s = float(retry_s)
        self.paths: list[Path] = []
        self.new_name_if_taken, self.overwrite = new_name_if_taken, overwrite and not new_name_if_taken
        self._part = 0  # the number of the next split file (names taken by others are skipped)
        self.written = 0  # messages read back from the files (after each flush; not those cut off by a write error)
        self.pending = 0  # messages written since the last flush (not yet read back)
        self.state = RecordingState.WRITING
        self.error: str | None = None  # the last write or read-back error: file and reason
        self.write_errors = 0
        self.verify_errors = 0
        self.lost_by_topic: dict[str, int] = {}  # received, not kept (write errors, read-backs), by topic
        self.recording_ended = threading.Event()
        self._sink: McapSink | None = None
        self._opened_at = 0.0
        self._last_flush = 0.0
        self._paused_at = 0.0
        self._lost_at_pause = 0
        self._next_probe = 0.0
        self._last_state_log = 0.0

    @property
    def lost(self) -> int:
        with self._lock:
            return sum(self.lost_by_topic.values())

    def _file_metadata(self) -> dict[str, dict]:
        """The metadata records every file starts with."""
        return self.extra_metadata

    def _file_opened(self) -> None:
        """Called when a file was opened."""

    def _final_counters(self) -> dict[str, str]:
        """More counters for a file's closing ``qradar.recorder_counters`` metadata."""
        return {}

    def _before_flush(self) -> None:
        """Called by the worker after each batch and when idle, before a flush is due."""

    # -- files ------------------------------------------------------------------------------
    #: names tried for one file before giving up (another program taking them all)
    MAX_NAME_TRIES = 1000

    def _next_path(self) -> Path:
        """The next file's name: the base path (or, for a default name, -1, -2, ... after
        it), then ``<stem>_0001.mcap``, ... for the files after it."""
        if not self.paths:
            if not self.new_name_if_taken or self._part == 0:
                return self.base_path
            return self.base_path.with_name(f"{self.base_path.stem}-{self._part}.mcap")
        return self.base_path.with_name(f"{self.paths[0].stem}_{self._part:04d}.mcap")

    def _open(self) -> str | None:
        """Start the next file; None on success, else why not (nothing is left on disk).
        A file is created exclusively: a name another program took is skipped (files after
        the first, and a default first name), or refused (a first name the user gave)."""
        for _ in range(self.MAX_NAME_TRIES):
            path = self._next_path()
            self._part += 1
            try:
                sink = McapSink(path, overwrite=self.overwrite and not self.paths)  # ReplayError naming the path
                break
            except RecordingExists as exc:
                if not self.paths and not self.new_name_if_taken:
                    return str(exc)
                log.info("%s exists (not ours): the recording goes on in the next free name", path)
            except ReplayError as exc:
                return str(exc)
        else:
            return f"no free file name after {self.base_path} ({self.MAX_NAME_TRIES} tried)"
        try:
            for name, data in self._file_metadata().items():
                sink.metadata(name, {k: v if isinstance(v, str) else json.dumps(v) for k, v in data.items()})
            check = sink.flush()
        except OSError as exc:
            sink.abort()
            try:
                path.unlink()  # ours, with no message in it: nothing worth keeping (its name is free again)
                self._part -= 1
            except OSError:
                pass
            return f"cannot write {path}: {describe_os_error(exc)}"
        self._sink = sink
        self._file_opened()
        self._flushed(sink, check)
        self.paths.append(path)
        if len(self.paths) == 1:
            self._part = 1  # the files after the first are <its stem>_0001, _0002, ...
        self._opened_at = self._last_flush = time.monotonic()
        log.info("recording to %s", path)
        return None

    def _close(self) -> None:
        """Finish the current file; a write error on the way is handled as anywhere else."""
        sink, self._sink = self._sink, None
        if sink is None:
            return
        try:
            self._flushed(sink, sink.flush())
            t = self.totals()
            sink.metadata("qradar.recorder_counters", {
                "received": str(t["frames_in"]), "written": str(self.written), "dropped": str(t["drops"]),
                "lost": str(self.lost), "verify_errors": str(self.verify_errors), **self._final_counters()})
            problems = list(sink.problems)
            sink.close()  # (the metadata record is no message: nothing more to read back)
            for problem in sink.problems[len(problems):]:  # the summary disagrees with what was read back
                self._verify_failed(problem)
        except OSError as exc:
            self._write_failed(sink, exc)

    def _start(self) -> None:
        why = self._open()
        if why is not None:
            raise ReplayError(why)
        super()._start()

    def stop(self, timeout_s: float = 5.0) -> None:
        super().stop(timeout_s)
        self._close()

    # -- write errors ------------------------------------------------------------------------------
    def _lose(self, topic: str, n: int = 1) -> None:
        with self._lock:
            self.lost_by_topic[topic] = self.lost_by_topic.get(topic, 0) + n

    def _write_failed(self, sink: McapSink, exc: BaseException) -> None:
        """Close ``sink`` as cleanly as the disk allows, count what it loses, pause or stop."""
        kept = sink.abort()
        if self._sink is sink:
            self._sink = None
        lost = 0
        for topic, n in kept["lost_by_topic"].items():
            if topic not in DERIVED:  # derived from a message, which is counted
                self._lose(topic, n)
                lost += n
        self.written -= sum(n for topic, n in kept["flushed_lost_by_topic"].items() if topic not in DERIVED)
        self.pending = 0
        if sink.removed:
            detail = f"; its {lost} messages are lost with it"
        else:
            detail = (f"; closed it with {kept['messages']} messages ({kept['bytes']} bytes) up to its last flushed "
                      f"chunk ({'ended with a footer' if kept['footer'] else 'no footer: qradar recover reads it'}), "
                      f"{lost} unflushed messages lost")
        self._pause_or_stop(f"cannot write {sink.path}: {describe_os_error(exc)}", detail)

    def _pause_or_stop(self, error: str, detail: str = "") -> None:
        """After a write error (``error``: file and reason): stop or pause, by the policy; one log line."""
        self.write_errors += 1
        self.error = error
        now = time.monotonic()
        self._last_state_log = now
        if self.on_write_error is OnWriteError.STOP:
            self.state = RecordingState.STOPPED
            self.recording_ended.set()
            log.error("recording stopped: %s%s; the pipeline keeps running (on write error: stop)", error, detail)
        else:
            self.state = RecordingState.PAUSED
            self._paused_at, self._lost_at_pause = now, self.lost
            self._next_probe = now + self.retry_s
            log.error("recording paused: %s%s; messages are counted as lost until %s can be written (probing "
                      "every %g s); the pipeline keeps running", error, detail, self._next_path(), self.retry_s)

    def _probe(self) -> None:
        """While paused: is there room again? Then resume into the next file."""
        now = time.monotonic()
        self._next_probe = now + self.retry_s
        free = free_bytes(self._next_path().parent)
        why = None
        if free is not None and free < self.resume_free_bytes:
            why = f"{free} bytes free, waiting for {self.resume_free_bytes}"
        else:
            why = self._open()
        if why is None:
            self.state = RecordingState.WRITING
            log.warning("recording resumed into %s after %.1f s paused; %d messages lost while paused (lost in "
                        "all, by topic: %s)", self._sink.path, now - self._paused_at,
                        self.lost - self._lost_at_pause, dict(self.lost_by_topic))
        elif now - self._last_state_log >= PAUSED_LOG_PERIOD_S:
            self._last_state_log = now
            log.warning("recording still paused (%s); %d messages lost so far", why, self.lost)

    def on_idle(self) -> None:
        self._maybe_flush()

    def _maybe_flush(self) -> None:
        self._before_flush()
        if self._sink is None:
            if self.state is RecordingState.PAUSED and time.monotonic() >= self._next_probe:
                self._probe()
            return
        now = time.monotonic()
        try:
            if now - self._last_flush >= FLUSH_PERIOD_S:
                self._flushed(self._sink, self._sink.flush())
                self._last_flush = now
        except OSError as exc:
            self._write_failed(self._sink, exc)

    def _split_if_due(self) -> None:
        """Before a message is written: the next file, if this one is at its size or age. A
        file is split only when a message is there to start the next one, so no file of a set
        holds its metadata alone (a run that stops, or sensors that fall silent, just after a
        split point: a file every split period while nothing arrives)."""
        if self._sink is not None and (
                (self.split_size and self._sink.size >= self.split_size)
                or (self.split_duration_s and time.monotonic() - self._opened_at >= self.split_duration_s)):
            self._next_file()

    def _next_file(self) -> None:
        """Close the current file and go on in the next one."""
        self._close()
        if self.state is RecordingState.WRITING:
            why = self._open()
            if why is not None:  # e.g. the folder was removed: pause (or stop) like a write error
                self._pause_or_stop(why)

    def _flushed(self, sink: McapSink, check: FlushCheck) -> None:
        """What a flush read back: readable messages count as written; messages written and
        not read back are lost, and an error (logged, in health and the summary)."""
        self.written += sum(n for topic, n in check.readable.items() if topic not in DERIVED)
        self.pending = 0
        for topic, n in check.unreadable.items():
            if topic not in DERIVED:
                self._lose(topic, n)
        for problem in check.problems:
            self._verify_failed(f"{sink.path}: {problem}")

    def _verify_failed(self, problem: str) -> None:
        self.verify_errors += 1
        self.error = f"read back: {problem}"
        log.error("recorder: what was written does not read back: %s (counted in verify_errors; the messages "
                  "concerned are lost)", problem)


class RecorderNode(RecordingFiles):
    """Subscribes ``topics`` (default ``<prefix>/**``) and writes MCAP files
    (:class:`RecordingFiles`: ``split_size_mb``, ``split_duration_s``, ``metadata``,
    ``on_write_error``, ``retry_s``, ``new_name_if_taken``). ``radar``
    and ``max_ramps``: the announced configurations frames must have (the nodes'
    defaults); ``max_dead_channels``: see the module docstring; ``derived``: the channels
    written beside a sensor's messages (:mod:`replay.derived`: point clouds, scenes, range
    profiles); ``decoded``: the process's JSON messages decoded once (pipeline.wire.shared)."""

    name = "record"
    role = "recorder"
    accepts_any_key = True  # every key under the subscription comes to admit(), which refuses what is not qradar's
    batch_per_sensor = None  # writing is cheap: whole batches

    def __init__(self, bus: BusConfig, path: str | Path, topics: str | None = None,
                 session: zenoh.Session | Transport | None = None, queue_size: int = 20000,
                 radar: RadarConfig | None = None, max_ramps: int = 16, max_dead_channels: int = DEAD_CHANNELS_MAX,
                 derived: DerivedConfig = DerivedConfig(), decoded: DecodedOnce | None = None, **kw):
        # fair, but one busy sensor may fill the queue
        super().__init__(bus, path, session, queue=QueueConfig(queue_size=queue_size, sensor_queue_size=queue_size),
                         batch_max=512, **kw)
        if not (isinstance(max_dead_channels, int) and max_dead_channels >= 1):
            raise ReplayError(f"max_dead_channels={max_dead_channels!r} must be an integer >= 1")
        self.admission = Admission(radar, max_ramps, decoded)
        self.derivations = Derivations(self.admission.configs, derived)  # the channels written beside (replay.derived)
        self.max_dead_channels = max_dead_channels
        self._dead_check_at = max_dead_channels  # the file's channel count at which dead ones are counted next
        self._recheck_channels = False  # sensors expired: count the file's dead channels again
        self.refusals = RefusalCounts()  # by live sensor (or NO_SENSOR) and kind, under _lock
        self._health_summary: tuple[float, dict] | None = None  # (when, summary) for health_extra
        self.first_raw_ns: dict[str, int] = {}  # each sensor's first raw frame (its timestamp): the truth's clock
        self.topics = topics or f"{bus.prefix}/**"
        try:
            zenoh.KeyExpr(self.topics)
        except zenoh.ZError as exc:
            raise ReplayError(f"--topics {self.topics!r} is not a key expression: {zenoh_reason(exc)}") from None

    def admit(self, key: str, n_bytes: int) -> str | None:
        """Before the copy: a key that is not qradar's, a frame of a length no announced
        configuration gives, a JSON message over MAX_JSON_BYTES (counted by kind, and in
        invalid_frames; not written: garbage must not grow the file's channels)."""
        sensor = self._classify(key)[0]
        why = self.admission.before_copy(key.rsplit("/", 1)[-1], sensor, n_bytes)
        if why is None:
            return None
        self._refuse(sensor, why[0])
        return why[1]

    def _refuse(self, sensor: str, kind: str, n: int = 1) -> None:
        """Count ``n`` messages refused of ``kind`` against ``sensor`` if it is live, else
        against the unknown senders (a refused message makes no state)."""
        with self._lock:
            self.refusals.add(sensor if sensor in self.stats else NO_SENSOR, kind, n)

    def forget(self, sensor_id: str) -> None:
        """An expired sensor's refusal counts go into the totals, and its channels count as
        dead at the worker's next look (called with _lock held)."""
        super().forget(sensor_id)
        self.refusals.retire(sensor_id)
        self.derivations.forget(sensor_id)
        self._recheck_channels = True

    def refused(self) -> dict[str, int]:
        """Messages refused, by kind (REFUSED_KINDS), expired sensors included."""
        with self._lock:
            return self.refusals.totals()

    def subscription(self) -> str:
        return self.topics

    def _file_metadata(self) -> dict[str, dict]:
        recorder = {"topics": self.topics, "prefix": self.bus.prefix, "part": str(len(self.paths))}
        if self.first_raw_ns:  # a later file of a split set: where each sensor's clock began (replay.reprocess)
            recorder["first_raw_ns"] = json.dumps(self.first_raw_ns)
        return {"qradar.versions": versions(), "qradar.recorder": recorder, **self.extra_metadata}

    def _final_counters(self) -> dict[str, str]:
        return {kind: str(n) for kind, n in self.refused().items()}

    # -- writing -------------------------------------------------------------------------------
    def process(self, batch: list[QueuedFrame]) -> None:
        sensors = [self._classify(item.key)[0] for item in batch]
        admitted, refused = self.admission.check(batch, sensors)
        for r in refused:
            self._refuse(sensors[r.index], r.kind)
            self.count(batch[r.index].sensor, r.counter, f"{r.reason} (not recorded: {r.kind})")
        for a in admitted:
            item = batch[a.index]
            topic = topic_of(item.key) or "other"
            if topic == "raw" and len(self.first_raw_ns) < MAX_CLOCKS:
                self.first_raw_ns.setdefault(sensors[a.index], a.publish_ns)
            self._split_if_due()
            if self._sink is not None and self._sink.n_channels >= min(self._dead_check_at, FILE_CHANNELS_MAX):
                self._check_channels()
            sink = self._sink
            if sink is None:  # paused or stopped
                self._lose(topic)
                continue
            written = False
            try:
                sink.write(item.key, item.payload, item.received_ns, a.publish_ns, a.sequence)
                written = True
                for key, payload in self.derivations.of(item.key, a):
                    sink.write(key, payload, item.received_ns, a.publish_ns, a.sequence)
            except OSError as exc:
                if not written:  # else it is among the sink's unflushed messages, counted by _write_failed
                    self._lose(topic)
                else:
                    self.pending += 1
                self._write_failed(sink, exc)
                continue
            except UnwritableMessage as exc:  # checked before: a check that missed is a bug, said so
                if written:  # a derived message only: the message is in
                    self.pending += 1
                    log.error("recorder: a channel derived from %s: %s", item.key, exc)
                else:
                    self._refuse(sensors[a.index], f"refused_{exc.kind}" if exc.kind in ("time", "shape")
                                 else "refused_size")
                    self.count(item.sensor, "invalid_frames", f"{item.key}: {exc} (not recorded)")
                continue
            self.pending += 1
            with self._lock:  # a late message of an expired sensor makes no new state
                (self.stats.get(item.sensor) or self.sensor_stats(NO_SENSOR)).frames_out += 1
        self._maybe_flush()

    def _check_channels(self) -> None:
        """The file holds many channels: count those of sensors no longer live; past
        ``max_dead_channels`` of them (or near MCAP's channel limit) the next file starts,
        so mcap's Writer lets go of them."""
        sink = self._sink
        n = sink.n_channels
        with self._lock:
            live = set(self.stats)
        dead = sum(1 for key in sink.keys() if self.bus.sensor_of(key) not in live)  # (no id check: it caches ids)
        if dead < self.max_dead_channels and n < FILE_CHANNELS_MAX:
            self._dead_check_at = n - dead + self.max_dead_channels
            return
        log.info("recorder: %s holds %d channels, %d of sensors no longer live: the recording goes on in a new file "
                 "(mcap's Writer keeps every channel of a file until it ends)", sink.path, n, dead)
        self._next_file()

    def _file_opened(self) -> None:
        self._dead_check_at = self.max_dead_channels

    def _before_flush(self) -> None:
        if self._recheck_channels and self._sink is not None:
            self._recheck_channels = False
            self._check_channels()

    # -- reporting -----------------------------------------------------------------------------
    def summary(self, all_files: bool = True) -> dict:
        """State, files (all, or the newest LISTED_FILES), counters: for health, ``qradar run``'s
        summary and ``qradar record``. ``written``: messages read back from the files;
        ``pending``: written since the last flush; ``refused_*``: refused by kind (before
        any byte was written) and ``refused_by_sensor`` (the LISTED_SENDERS senders with
        the most, live ones; the others and expired ones summed); ``verify_errors``:
        read-backs that disagreed."""
        t = self.totals()
        with self._lock:
            lost_by_topic = dict(self.lost_by_topic)
            refused = self.refusals.totals()
            by_sensor = self.refusals.listed(LISTED_SENDERS, UNKNOWN_SENSOR)
        files = self.paths if all_files else self.paths[-LISTED_FILES:]
        return {"state": self.state.value, "files": [str(p) for p in files],
                "files_written": len(self.paths), "received": t["frames_in"], "written": self.written,
                "pending": self.pending, "dropped": t["drops"], "lost": sum(lost_by_topic.values()),
                "lost_by_topic": lost_by_topic, **refused, "refused_by_sensor": by_sensor,
                "verify_errors": self.verify_errors, "write_errors": self.write_errors, "error": self.error,
                "channels": 0 if self._sink is None else self._sink.n_channels}

    def health_extra(self, sensor_id: str) -> dict:
        """The recorder's state and counters (summed over every sensor: computed once for
        the health messages of one slice, HEALTH_SUMMARY_S), and what it refused of this sensor."""
        now = time.monotonic()
        if self._health_summary is None or now - self._health_summary[0] >= HEALTH_SUMMARY_S:
            summary = self.summary(all_files=False)
            del summary["refused_by_sensor"]
            self._health_summary = (now, summary)
        out = dict(self._health_summary[1])
        with self._lock:
            out["sensor_refused"] = self.refusals.of(NO_SENSOR if sensor_id == UNKNOWN_SENSOR else sensor_id)
        return {"recorder": out}
