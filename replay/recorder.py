"""The recorder node: everything under ``<prefix>/**`` (or ``topics``) into MCAP.

Each message is written with its log time (arrival at the recorder, ns), its publish
time (the message's own timestamp: sensor time for frames and targets, the node's for
health) and its sequence number (the frame's). Targets are also written as
``foxglove.PointCloud``. A chunk is flushed at least every second, so a recorder
killed with SIGKILL loses at most the last second; ``qradar recover`` turns such a file
into a complete, indexed one. Counters (received, written, dropped) go to the
recorder's health topic and, at the end, into the file's metadata.

A write error (a full disk, EFBIG, EIO, a removed folder) never stops the node: the
file is cut back to its last flushed chunk and closed (:meth:`McapSink.abort`), the
error is logged once (then at most once a second) and shown in health, and by the
``on_write_error`` policy the recorder either pauses — counting every message it cannot
write, by topic — and every ``retry_s`` probes for space (at least ``resume_free_mb``
free), resuming into the next file (``name_0001.mcap``, ...), or stops recording for
good. Only the first file is different: a recording that cannot even begin is an error
at start (ReplayError), before anything runs.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import struct
import threading
import time
from enum import Enum
from importlib import metadata as importlib_metadata
from pathlib import Path

import zenoh

from pipeline.bus.session import BusConfig, zenoh_reason
from pipeline.nodes.counters import NO_SENSOR
from pipeline.nodes.intake import ProcessingNode, QueuedFrame
from pipeline.nodes.transport import Transport
from pipeline.wire import COMMON, HEADER_LEN, MAGIC, MAX_M, QUANT_HEADER_LEN, WireError, decode_targets, load_json

from .errors import RecordingExists, ReplayError
from .mcapio import McapSink, describe_os_error, pointcloud_json, topic_of

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
#: file names listed in health and summaries (the newest); ``files_written`` counts them all
LISTED_FILES = 8


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
    out = {"python": platform.python_version()}
    for pkg in ("qradar", "numpy", "eclipse-zenoh", "mcap", "pyserial"):
        try:
            out[pkg] = importlib_metadata.version(pkg)
        except importlib_metadata.PackageNotFoundError:
            out[pkg] = "unknown"
    return out


def message_times(topic: str, payload: bytes, log_time_ns: int) -> tuple[int, int]:
    """(publish_time_ns, sequence) read from a message; (log time, 0) if unreadable."""
    try:
        if topic in ("raw", "quantized"):
            magic, _, _, _, _, seq, ts, _, _, _ = COMMON.unpack_from(payload)
            if magic == MAGIC:
                return int(ts), int(seq)
        elif topic in ("targets", "tracks", "health"):
            obj = load_json(payload, topic)  # bounded in size and depth: a WireError (a ValueError)
            return int(obj.get("timestamp_ns", log_time_ns)), int(obj.get("seq", 0))
    except (struct.error, ValueError, TypeError, AttributeError):
        pass
    return log_time_ns, 0


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


class RecorderNode(ProcessingNode):
    """Subscribes ``topics`` (default ``<prefix>/**``) and writes MCAP files.

    ``split_size_mb`` / ``split_duration_s`` start a new file (``name_0001.mcap``, ...)
    when the current one is that large or that old. ``metadata``: name -> {key: value}
    records written at the start of every file (radar config, node configs, scene).
    ``on_write_error``, ``retry_s`` (s between probes while paused) and ``resume_free_mb``
    (free space a probe wants, MB): see the module docstring. ``recording_ended`` is set
    when recording stops for good after a write error."""

    name = "record"
    role = "recorder"
    accepts_any_key = True  # every key under the subscription is recorded
    batch_per_sensor = None  # writing is cheap: whole batches

    def __init__(self, bus: BusConfig, path: str | Path, topics: str | None = None,
                 session: zenoh.Session | Transport | None = None, split_size_mb: float | None = None,
                 split_duration_s: float | None = None, metadata: dict[str, dict] | None = None,
                 queue_size: int = 20000, on_write_error: OnWriteError | str = OnWriteError.RESUME,
                 retry_s: float = 5.0, resume_free_mb: float = 1.0, new_name_if_taken=False, overwrite=False, **kw):
        kw.setdefault("sensor_queue_size", queue_size)  # fair, but one busy sensor may fill the queue
        super().__init__(bus, session, queue_size=queue_size, batch_max=512, **kw)
        self.base_path = Path(path)
        if self.base_path.suffix != ".mcap":
            raise ReplayError(f"recording path {self.base_path} must end in .mcap")
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
        if not resume_free_mb >= 0:
            raise ReplayError(f"resume_free_mb={resume_free_mb!r} must be >= 0")
        self.topics = topics or f"{bus.prefix}/**"
        try:
            zenoh.KeyExpr(self.topics)
        except zenoh.ZError as exc:
            raise ReplayError(f"--topics {self.topics!r} is not a key expression: {zenoh_reason(exc)}") from None
        self.split_size = None if split_size_mb is None else int(split_size_mb * 1e6)
        self.split_duration_s = split_duration_s
        self.extra_metadata = metadata or {}
        self.retry_s = float(retry_s)
        self.resume_free_bytes = int(resume_free_mb * 1e6)
        self.paths: list[Path] = []
        self.new_name_if_taken, self.overwrite = new_name_if_taken, overwrite and not new_name_if_taken
        self._part = 0  # the number of the next split file (names taken by others are skipped)
        self.written = 0  # messages kept in the files (not those cut off by a write error)
        self.unparsed = 0
        self.state = RecordingState.WRITING
        self.error: str | None = None  # the last write error: file and reason
        self.write_errors = 0
        self.lost_by_topic: dict[str, int] = {}  # received, not kept (write errors), by topic
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

    def admit(self, key: str, n_bytes: int) -> str | None:
        """A raw or quantized frame of a length no frame of any M can have is refused
        (counted in invalid_frames, not written): garbage must not grow the file's channels.
        Anything of a possible length is recorded, whatever its configuration."""
        topic = key.rsplit("/", 1)[-1]
        if topic == "raw" and not (n_bytes >= HEADER_LEN + 16 and (n_bytes - HEADER_LEN) % 16 == 0
                                   and n_bytes <= HEADER_LEN + 16 * MAX_M):
            return f"{n_bytes} bytes, not the length of a raw frame (48 + 16 M) (not recorded)"
        if topic == "quantized" and not QUANT_HEADER_LEN < n_bytes <= QUANT_HEADER_LEN + 8 * MAX_M:
            return f"{n_bytes} bytes, not the length of a quantized frame (not recorded)"
        return None

    def subscription(self) -> str:
        return self.topics

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
            sink.metadata("qradar.versions", versions())
            sink.metadata("qradar.recorder", {"topics": self.topics, "prefix": self.bus.prefix,
                                              "part": str(len(self.paths))})
            for name, data in self.extra_metadata.items():
                sink.metadata(name, {k: v if isinstance(v, str) else json.dumps(v) for k, v in data.items()})
            sink.flush()
        except OSError as exc:
            sink.abort()
            try:
                path.unlink()  # ours, with no message in it: nothing worth keeping (its name is free again)
                self._part -= 1
            except OSError:
                pass
            return f"cannot write {path}: {describe_os_error(exc)}"
        self._sink = sink
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
            sink.flush()
            t = self.totals()
            sink.metadata("qradar.recorder_counters", {
                "received": str(t["frames_in"]), "written": str(self.written), "dropped": str(t["drops"]),
                "unparsed": str(self.unparsed), "lost": str(self.lost)})
            sink.close()
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
            if topic != "pointcloud":  # derived from a targets message, which is counted
                self.written -= n
                self._lose(topic, n)
                lost += n
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
                        self.lost - self._lost_at_pause, self.summary()["lost_by_topic"])
        elif now - self._last_state_log >= PAUSED_LOG_PERIOD_S:
            self._last_state_log = now
            log.warning("recording still paused (%s); %d messages lost so far", why, self.lost)

    # -- writing -------------------------------------------------------------------------------
    def process(self, batch: list[QueuedFrame]) -> None:
        for item in batch:
            sensor, key, payload, log_ns = item.sensor, item.key, item.payload, item.received_ns
            topic = topic_of(key)
            sink = self._sink
            if sink is None:  # paused or stopped
                self._lose(topic or "other")
                continue
            publish_ns, seq = message_times(topic or "", payload, log_ns)
            kept = False
            try:
                sink.write(key, payload, log_ns, publish_ns, seq)
                kept = True
                self.written += 1
                if topic == "targets":
                    try:
                        msg = decode_targets(payload, key)
                    except WireError:
                        self.unparsed += 1
                    else:
                        sink.write(key.rsplit("/", 1)[0] + "/pointcloud", pointcloud_json(msg), log_ns,
                                   publish_ns, seq)
            except OSError as exc:
                if not kept:  # else it is among the sink's unflushed messages, counted by _write_failed
                    self._lose(topic or "other")
                self._write_failed(sink, exc)
                continue
            if topic is None:
                self.unparsed += 1
            with self._lock:  # a late message of an expired sensor makes no new state
                (self.stats.get(sensor) or self.sensor_stats(NO_SENSOR)).frames_out += 1
        self._maybe_flush_or_split()

    def on_idle(self) -> None:
        self._maybe_flush_or_split()

    def _maybe_flush_or_split(self) -> None:
        if self._sink is None:
            if self.state is RecordingState.PAUSED and time.monotonic() >= self._next_probe:
                self._probe()
            return
        now = time.monotonic()
        try:
            if now - self._last_flush >= FLUSH_PERIOD_S:
                self._sink.flush()
                self._last_flush = now
        except OSError as exc:
            self._write_failed(self._sink, exc)
            return
        if (self.split_size and self._sink.size >= self.split_size) or \
                (self.split_duration_s and now - self._opened_at >= self.split_duration_s):
            self._close()
            if self.state is RecordingState.WRITING:
                why = self._open()
                if why is not None:  # e.g. the folder was removed: pause (or stop) like a write error
                    self._pause_or_stop(why)

    # -- reporting -----------------------------------------------------------------------------
    def summary(self, all_files: bool = True) -> dict:
        """State, files (all, or the newest LISTED_FILES), counters: for health, ``qradar run``'s
        summary and ``qradar record``."""
        t = self.totals()
        with self._lock:
            lost_by_topic = dict(self.lost_by_topic)
        files = self.paths if all_files else self.paths[-LISTED_FILES:]
        return {"state": self.state.value, "files": [str(p) for p in files],
                "files_written": len(self.paths), "received": t["frames_in"], "written": self.written,
                "dropped": t["drops"], "lost": sum(lost_by_topic.values()), "lost_by_topic": lost_by_topic,
                "write_errors": self.write_errors, "error": self.error}

    def health_extra(self, sensor_id: str) -> dict:
        return {"recorder": self.summary(all_files=False)}
