"""The base of every zenoh node: session, liveliness, health, publishers, statistics,
and the subscribe -> bounded queue -> batch -> process loop of processing nodes.

A processing node subscribes with a wildcard (``<prefix>/*/raw``, ...) and so serves
many sensors at once. zenoh's callback only copies the payload into a bounded queue
(a full queue drops the newest sample and counts it in ``drops``); a worker thread
takes batches from the queue and hands them to :meth:`ProcessingNode.process`, which
calls the vectorized math. Data publishers use ``CongestionControl.BLOCK``: when the
network is slower than the data, a publisher waits instead of dropping, so
back-pressure reaches the node's bounded queue, where every drop is counted. Health
goes out with ``DROP``: it is periodic and a lost one is replaced a second later.

Every node declares a liveliness token and publishes ``<prefix>/<sensor>/health``
once a second for every sensor it has seen. A malformed payload is counted
(``decode_errors``), logged and skipped; the node keeps running.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import defaultdict, deque
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np
import zenoh

from radar_driver.errors import RadarError

from .bus import BusConfig
from .errors import ParameterError, PipelineError
from .wire import HealthMsg

log = logging.getLogger("qradar.node")

LATENCY_WINDOW = 2000


@dataclass
class SensorStats:
    frames_in: int = 0
    frames_out: int = 0
    drops: int = 0
    decode_errors: int = 0
    bytes_in: int = 0
    bytes_out: int = 0
    latency_ms: deque = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))
    # for rates between two health messages
    _last_bytes: tuple[int, int, float] = (0, 0, 0.0)


def percentile_ms(values: Iterable[float], q: float) -> float | None:
    v = np.fromiter(values, dtype=float)
    return round(float(np.percentile(v, q)), 3) if v.size else None


class Node:
    """Base of every node: zenoh session, liveliness, health, publishers, statistics.

    ``session=None`` opens a session from ``bus`` (closed on stop); a given session is
    shared and left open.
    """

    name = "node"

    def __init__(self, bus: BusConfig, session: zenoh.Session | None = None, health_period_s: float = 1.0):
        self.bus = bus
        self._own_session = session is None
        self.session = session if session is not None else bus.open()
        self.health_period_s = health_period_s
        self.stats: dict[str, SensorStats] = defaultdict(SensorStats)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._token = None
        self._last_error_log = 0.0
        self.errors: list[BaseException] = []

    # -- life cycle -----------------------------------------------------------------------
    def start(self) -> "Node":
        self._token = self.session.liveliness().declare_token(self.bus.liveliness_key(self.name))
        self._spawn(self._health_loop, "health")
        self._start()
        return self

    def _start(self) -> None:
        """Subclass hook: declare subscribers, spawn workers."""

    def _spawn(self, target: Callable[[], None], what: str, after: Callable[[], None] | None = None) -> None:
        """Run ``target`` in a thread; an exception it raises goes to :attr:`errors` (which
        the owner raises: run_nodes, the commands), and then ``after`` runs."""
        def run():
            try:
                target()
            except BaseException as exc:  # a dead worker is reported, never silent
                if not self._stop.is_set():
                    log.debug("%s %s thread failed", self.name, what, exc_info=True)  # the traceback under -v
                    self.errors.append(exc)
            finally:
                if after is not None:
                    after()

        t = threading.Thread(target=run, name=f"{self.name}-{what}", daemon=True)
        t.start()
        self._threads.append(t)

    def stop(self, timeout_s: float = 5.0) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        self._stopping()
        for t in self._threads:
            t.join(timeout_s)
        self._publish_health()  # last counters
        for pub in self._publishers.values():
            try:
                pub.undeclare()
            except zenoh.ZError:
                pass
        if self._token is not None:
            self._token.undeclare()
        if self._own_session:
            self.session.close()

    def _stopping(self) -> None:
        """Subclass hook, called once stop is requested."""

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def wait(self, timeout_s: float | None = None) -> bool:
        return self._stop.wait(timeout_s)

    # -- publishing -----------------------------------------------------------------------------
    def publish(self, sensor_id: str, topic: str, payload: bytes, encoding: str) -> None:
        key = self.bus.key(sensor_id, topic)
        pub = self._publishers.get(key)
        if pub is None:
            pub = self.session.declare_publisher(key, encoding=zenoh.Encoding(encoding),
                                                 congestion_control=zenoh.CongestionControl.BLOCK)
            self._publishers[key] = pub
        pub.put(payload)
        with self._lock:
            st = self.stats[sensor_id]
            st.frames_out += 1
            st.bytes_out += len(payload)

    def count_error(self, sensor_id: str, exc: Exception) -> None:
        with self._lock:
            self.stats[sensor_id].decode_errors += 1
        now = time.monotonic()
        if now - self._last_error_log > 1.0:  # at most one line a second
            self._last_error_log = now
            log.warning("%s: %s (counted in decode_errors; node keeps running)", self.name, exc)

    # -- health ------------------------------------------------------------------------------------
    def _health_loop(self) -> None:
        while not self._stop.wait(self.health_period_s):
            self._publish_health()

    def health_extra(self, sensor_id: str) -> dict:
        return {}

    def _publish_health(self) -> None:
        now_ns = time.time_ns()
        with self._lock:
            snapshot = []
            for sensor, st in self.stats.items():
                b_in, b_out, t_prev = st._last_bytes
                dt = (now_ns - t_prev) / 1e9 if t_prev else self.health_period_s
                msg = HealthMsg(
                    node=self.name, sensor_id=sensor, timestamp_ns=now_ns, frames_in=st.frames_in,
                    frames_out=st.frames_out, drops=st.drops, decode_errors=st.decode_errors,
                    latency_ms={"p50": percentile_ms(st.latency_ms, 50), "p99": percentile_ms(st.latency_ms, 99)},
                    bytes_in_per_s=(st.bytes_in - b_in) / max(dt, 1e-9),
                    bytes_out_per_s=(st.bytes_out - b_out) / max(dt, 1e-9),
                )
                st._last_bytes = (st.bytes_in, st.bytes_out, now_ns)
                snapshot.append(msg)
        for msg in snapshot:
            msg.extra = self.health_extra(msg.sensor_id)
            if msg.sensor_id == "_unknown":
                continue
            try:
                self.session.put(self.bus.key(msg.sensor_id, "health"), msg.to_json(),
                                 encoding=zenoh.Encoding.APPLICATION_JSON,
                                 congestion_control=zenoh.CongestionControl.DROP)
            except zenoh.ZError as exc:
                log.debug("health publish failed: %s", exc)

    def totals(self) -> dict[str, int]:
        with self._lock:
            out = {"frames_in": 0, "frames_out": 0, "drops": 0, "decode_errors": 0, "bytes_in": 0, "bytes_out": 0}
            for st in self.stats.values():
                for k in out:
                    out[k] += getattr(st, k)
            return out


class ProcessingNode(Node):
    """Subscribes ``<prefix>/*/<in_topic>``; callback -> bounded queue -> batches -> :meth:`process`."""

    in_topic = "raw"

    def __init__(self, bus: BusConfig, session: zenoh.Session | None = None, queue_size: int = 512,
                 batch_max: int = 64, health_period_s: float = 1.0):
        super().__init__(bus, session, health_period_s)
        if queue_size < 1 or batch_max < 1:
            raise ParameterError(f"queue_size={queue_size} and batch_max={batch_max} must be >= 1")
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        self.batch_max = batch_max
        self._subscriber = None

    def subscription(self) -> str:
        """The key expression this node listens to."""
        return self.bus.wildcard(self.in_topic)

    def _start(self) -> None:
        self._subscriber = self.session.declare_subscriber(self.subscription(), self._on_sample)
        self._spawn(self._work_loop, "worker")

    def _stopping(self) -> None:
        if self._subscriber is not None:
            self._subscriber.undeclare()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        """zenoh's thread: copy and enqueue, nothing else."""
        key = str(sample.key_expr)
        sensor = self.bus.sensor_of(key) or "_unknown"
        payload = sample.payload.to_bytes()
        try:
            self._queue.put_nowait((sensor, key, payload, time.time_ns()))
        except queue.Full:
            with self._lock:
                self.stats[sensor].drops += 1
            now = time.monotonic()
            if now - self._last_error_log > 1.0:
                self._last_error_log = now
                log.warning("%s: queue full, dropped a sample of %s (counted in drops)", self.name, key)
        with self._lock:
            st = self.stats[sensor]
            st.frames_in += 1
            st.bytes_in += len(payload)

    def _work_loop(self) -> None:
        # after stop, drain what was queued before the subscriber went away
        while not (self._stop.is_set() and self._queue.empty()):
            try:
                first = self._queue.get(timeout=0.1)
            except queue.Empty:
                self.on_idle()
                continue
            batch = [first]
            while len(batch) < self.batch_max:
                try:
                    batch.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            self.process(batch)

    def on_idle(self) -> None:
        """Called by the worker when no sample came for 0.1 s."""

    def process(self, batch: list[tuple[str, str, bytes, int]]) -> None:
        raise NotImplementedError


def _raise_node_error(nodes: list[Node]) -> None:
    """Raise the first error of a failed node: its own when it is a RadarError or a
    PipelineError (its message says what and where), else a PipelineError naming the node."""
    for nd in nodes:
        if nd.errors:
            exc = nd.errors[0]
            if isinstance(exc, (RadarError, PipelineError)):
                raise exc
            raise PipelineError(f"node {nd.name} failed: {exc!r}") from exc


def run_nodes(nodes: list[Node], duration_s: float | None, stop: threading.Event | None = None) -> None:
    """Start nodes in order, run until ``duration_s`` or ``stop``, stop them in reverse order."""
    started: list[Node] = []
    try:
        for nd in nodes:
            nd.start()
            started.append(nd)
        deadline = None if duration_s is None else time.monotonic() + duration_s
        stop = stop or threading.Event()
        while deadline is None or time.monotonic() < deadline:
            if stop.wait(0.1):
                break
            _raise_node_error(started)
    finally:
        for nd in reversed(started):
            nd.stop()
    _raise_node_error(started)  # a node that failed and so ended the run
