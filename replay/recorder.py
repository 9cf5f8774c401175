"""The recorder node: everything under ``<prefix>/**`` (or ``topics``) into MCAP.

Each message is written with its log time (arrival at the recorder, ns), its publish
time (the message's own timestamp: sensor time for frames and targets, the node's for
health) and its sequence number (the frame's). Targets are also written as
``foxglove.PointCloud``. A chunk is flushed at least every second, so a recorder
killed with SIGKILL loses at most the last second; ``qradar recover`` turns such a file
into a complete, indexed one. Counters (received, written, dropped) go to the
recorder's health topic and, at the end, into the file's metadata.
"""

from __future__ import annotations

import json
import logging
import platform
import struct
import time
from importlib import metadata as importlib_metadata
from pathlib import Path

import zenoh

from pipeline.bus import BusConfig
from pipeline.node import NO_SENSOR, ProcessingNode
from pipeline.wire import COMMON, MAGIC, WireError, decode_targets

from .errors import ReplayError
from .mcapio import McapSink, pointcloud_json, topic_of

log = logging.getLogger("qradar.record")

FLUSH_PERIOD_S = 1.0


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
        elif topic in ("targets", "health"):
            obj = json.loads(payload)
            return int(obj.get("timestamp_ns", log_time_ns)), int(obj.get("seq", 0))
    except (struct.error, ValueError, TypeError, AttributeError):
        pass
    return log_time_ns, 0


class RecorderNode(ProcessingNode):
    """Subscribes ``topics`` (default ``<prefix>/**``) and writes MCAP files.

    ``split_size_mb`` / ``split_duration_s`` start a new file (``name_0001.mcap``, ...)
    when the current one is that large or that old. ``metadata``: name -> {key: value}
    records written at the start of every file (radar config, node configs, scene)."""

    name = "record"
    accepts_any_key = True  # every key under the subscription is recorded

    def __init__(self, bus: BusConfig, path: str | Path, topics: str | None = None,
                 session: zenoh.Session | None = None, split_size_mb: float | None = None,
                 split_duration_s: float | None = None, metadata: dict[str, dict] | None = None,
                 queue_size: int = 20000, **kw):
        kw.setdefault("sensor_queue_size", queue_size)  # fair, but one busy sensor may fill the queue
        super().__init__(bus, session, queue_size=queue_size, batch_max=512, **kw)
        self.base_path = Path(path)
        if self.base_path.suffix != ".mcap":
            raise ReplayError(f"recording path {self.base_path} must end in .mcap")
        if split_size_mb is not None and not split_size_mb > 0:
            raise ReplayError(f"split size {split_size_mb!r} MB must be > 0")
        if split_duration_s is not None and not split_duration_s > 0:
            raise ReplayError(f"split duration {split_duration_s!r} s must be > 0")
        self.topics = topics or f"{bus.prefix}/**"
        try:
            zenoh.KeyExpr(self.topics)
        except zenoh.ZError as exc:
            raise ReplayError(f"--topics {self.topics!r} is not a key expression: {exc}") from None
        self.split_size = None if split_size_mb is None else int(split_size_mb * 1e6)
        self.split_duration_s = split_duration_s
        self.extra_metadata = metadata or {}
        self.paths: list[Path] = []
        self.written = 0
        self.unparsed = 0
        self._sink: McapSink | None = None
        self._opened_at = 0.0
        self._last_flush = 0.0

    def subscription(self) -> str:
        return self.topics

    # -- files ------------------------------------------------------------------------------
    def _next_path(self) -> Path:
        if not self.paths:
            return self.base_path
        return self.base_path.with_name(f"{self.base_path.stem}_{len(self.paths):04d}.mcap")

    def _open(self) -> None:
        path = self._next_path()
        self._sink = McapSink(path)  # creates the folder; ReplayError naming the path if it cannot
        self.paths.append(path)
        self._opened_at = self._last_flush = time.monotonic()
        self._sink.metadata("qradar.versions", versions())
        self._sink.metadata("qradar.recorder", {"topics": self.topics, "prefix": self.bus.prefix,
                                                "part": str(len(self.paths) - 1)})
        for name, data in self.extra_metadata.items():
            self._sink.metadata(name, {k: v if isinstance(v, str) else json.dumps(v) for k, v in data.items()})
        self._sink.flush()
        log.info("recording to %s", path)

    def _close(self) -> None:
        if self._sink is None:
            return
        t = self.totals()
        self._sink.metadata("qradar.recorder_counters", {
            "received": str(t["frames_in"]), "written": str(self.written), "dropped": str(t["drops"]),
            "unparsed": str(self.unparsed)})
        self._sink.close()
        self._sink = None

    def _start(self) -> None:
        self._open()
        super()._start()

    def stop(self, timeout_s: float = 5.0) -> None:
        super().stop(timeout_s)
        self._close()

    # -- writing -------------------------------------------------------------------------------
    def process(self, batch) -> None:
        sink = self._sink
        for sensor, key, payload, log_ns in batch:
            topic = topic_of(key)
            publish_ns, seq = message_times(topic or "", payload, log_ns)
            if topic is None:
                self.unparsed += 1
            sink.write(key, payload, log_ns, publish_ns, seq)
            self.written += 1
            with self._lock:  # a late message of an expired sensor makes no new state
                (self.stats.get(sensor) or self.sensor_stats(NO_SENSOR)).frames_out += 1
            if topic == "targets":
                try:
                    msg = decode_targets(payload, key)
                    sink.write(key.rsplit("/", 1)[0] + "/pointcloud", pointcloud_json(msg), log_ns, publish_ns, seq)
                except WireError:
                    self.unparsed += 1
        self._maybe_flush_or_split()

    def on_idle(self) -> None:
        if self._sink is not None:
            self._maybe_flush_or_split()

    def _maybe_flush_or_split(self) -> None:
        now = time.monotonic()
        if now - self._last_flush >= FLUSH_PERIOD_S:
            self._sink.flush()
            self._last_flush = now
        size = self._sink.path.stat().st_size if self.split_size else 0
        if (self.split_size and size >= self.split_size) or \
                (self.split_duration_s and now - self._opened_at >= self.split_duration_s):
            self._close()
            self._open()

    def health_extra(self, sensor_id: str) -> dict:
        t = self.totals()
        return {"recorder": {"received": t["frames_in"], "written": self.written, "dropped": t["drops"],
                             "files": [str(p) for p in self.paths]}}
