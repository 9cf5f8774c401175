"""The base of every node (:class:`Node`): its transport (:mod:`pipeline.nodes.transport`; a
zenoh session, opened from the bus configuration unless one is given), liveliness,
publishers, health, supervised threads and statistics (:mod:`pipeline.nodes.counters`); and
:func:`run_nodes`, which runs anything :class:`Runnable` (nodes, driver processes).

Data publishers wait when the network is slower than the data (zenoh's
``CongestionControl.BLOCK``), so back-pressure reaches the node's bounded queue, where
every drop is counted. Health goes out with ``DROP``: it is periodic and a lost one is
replaced a second later. A worker that dies is restarted and counted
(``worker_restarts``). A sensor silent for ``sensor_expiry_s`` is forgotten (its
counters stay in the node's totals).

Every node declares a liveliness token and publishes ``<prefix>/<sensor>/health``
once a second for every sensor it has seen. The nodes that process input are
:class:`pipeline.nodes.intake.ProcessingNode`.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable, ClassVar, Protocol, Sequence, runtime_checkable

import zenoh

from radar_driver.errors import RadarError

from pipeline.bus import audit, router_check
from pipeline.bus.session import BusConfig, zenoh_reason
from pipeline.nodes.counters import HEALTH_SLICES, NO_SENSOR, UNKNOWN_SENSOR, Counters
from pipeline.errors import ParameterError, PipelineError, WireError
from pipeline.nodes.memory import release_memory
from pipeline.nodes.transport import Declared, Publisher, Transport, TransportError, ZenohTransport, as_transport
from pipeline.keys import TOPICS
from pipeline.wire import HealthMsg, check_sensor_id

log = logging.getLogger("qradar.node")

#: a key gets a declared publisher once its sensor has sent this many frames (Node._put)
PUBLISHER_AFTER = 20
#: the most publishers a node declares (the other keys are put with Transport.put)
MAX_PUBLISHERS = 2048
DEFAULT_SENSOR_EXPIRY_S = 60.0
#: sensors forgotten (~12 KB of state each, freed into the C heap) before an expiry sweep
#: hands the heap's free memory back to the system (pipeline.nodes.memory.release_memory)
TRIM_AFTER_SENSORS = 64



class KeyMemory:
    """A node's keys ``<prefix>/<sensor>/<topic>``: each sensor id checked the first time
    it is put on (a WireError, never a key, for an id that is not a plain key chunk), not
    at every put; at most ``limit`` keys, a sensor's forgotten with it."""

    def __init__(self, bus: BusConfig, limit: int):
        self.bus, self.limit = bus, limit
        self._keys: dict[tuple[str, str], str] = {}
        self._held = 0  # the most keys held since the dict was last made anew

    def key(self, sensor_id: str, topic: str) -> str:
        key = self._keys.get((sensor_id, topic))
        if key is None:
            if len(self._keys) >= self.limit:  # keys of many sensors: bounded
                self._keys.clear()
            key = self._keys[(sensor_id, topic)] = self.bus.key(check_sensor_id(sensor_id), topic)
            self._held = max(self._held, len(self._keys))
        return key

    def forget(self, sensor_id: str) -> None:
        for topic in TOPICS:
            self._keys.pop((sensor_id, topic), None)
        if len(self._keys) * 4 < self._held:  # a dict never shrinks as it empties: made anew
            self._keys, self._held = dict(self._keys), len(self._keys)

def _undeclare_all(publishers: list) -> None:
    """Undeclare each of ``publishers``; one already gone with its session is no error."""
    for pub in publishers:
        try:
            pub.undeclare()
        except TransportError:
            pass


class Node(Counters):
    """Base of every node: transport, liveliness, health, publishers, statistics.

    ``session``: a zenoh session or another :class:`~pipeline.nodes.transport.Transport`
    (shared and left open); None opens a zenoh session from ``bus`` (closed on stop).
    ``sensor_expiry_s``: a sensor silent that long is forgotten (None: never). ``role``:
    the access-control role (:mod:`pipeline.bus.security`) whose identity runs this node, if
    any; ``name`` names its liveliness token."""

    name = "node"
    role: ClassVar[str | None] = None

    def __init__(self, bus: BusConfig, session: zenoh.Session | Transport | None = None,
                 health_period_s: float = 1.0, sensor_expiry_s: float | None = DEFAULT_SENSOR_EXPIRY_S):
        if sensor_expiry_s is not None and not sensor_expiry_s > 0:
            raise ParameterError(f"sensor expiry {sensor_expiry_s!r} s must be > 0 (or None: never)")
        super().__init__()
        self.bus = bus
        self._own_session = session is None
        self.transport: Transport = ZenohTransport(bus.open()) if session is None else as_transport(session)
        #: the zenoh session under the transport (None for another transport)
        self.session: zenoh.Session | None = getattr(self.transport, "session", None)
        self.health_period_s = health_period_s
        self.sensor_expiry_s = sensor_expiry_s
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._publishers: dict[str, dict[str, Publisher]] = {}  # sensor -> topic -> publisher
        self._n_publishers = 0
        self._retiring: list[Publisher] = []
        self._released = 0  # sensors forgotten since the C heap was last trimmed
        self._token: Declared | None = None
        self.errors: list[BaseException] = []
        if self.session is not None and bus.secure is not None:  # a link to an impostor ends the node
            router_check.watch(self.session, self.errors.append)
        # under --secure: this node's identity, whose rights say which keys the router lets it put on
        self._identity = None if bus.secure is None else bus.secure.policy.get(bus.secure.identity)
        self._may_put: dict[tuple[str, str], bool] = {}  # (sensor, topic) -> the policy lets the identity put there
        self._keys = KeyMemory(bus, 4 * MAX_PUBLISHERS)  # the keys it puts on, each sensor id checked once
        self._told_denied = False

    # -- life cycle -----------------------------------------------------------------------
    def start(self) -> "Node":
        self._token = self.transport.declare_token(self.bus.liveliness_key(self.name))
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

    def _spawn_supervised(self, target: Callable[[], None], what: str, backoff_s: float = 0.1) -> None:
        """Run ``target`` in a thread and run it again (counted in ``worker_restarts``)
        whenever it dies of an Exception before stop: a worker never stays dead."""
        def supervise():
            while not self._stop.is_set():
                try:
                    target()
                    return
                except Exception as exc:
                    with self._lock:
                        self.worker_restarts += 1
                    log.debug("%s %s thread died", self.name, what, exc_info=True)
                    self.log_limited("restart", "%s: %s thread died (%s: %s); restarted (counted in "
                                     "worker_restarts)", self.name, what, type(exc).__name__, exc)
                    self._stop.wait(backoff_s)
        self._spawn(supervise, what)

    def stop(self, timeout_s: float = 5.0) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        self._stopping()
        for t in self._threads:
            t.join(timeout_s)
        busy = [t.name for t in self._threads if t.is_alive()]
        self._workers_ended()
        self._publish_health()  # last counters
        self.log_summary()
        if busy:  # undeclaring a publisher under a worker's put fails in zenoh ("Already borrowed")
            log.warning("%s: %s still busy %.1f s after stop; its publishers are left to the session's close",
                        self.name, ", ".join(busy), timeout_s)
        else:
            _undeclare_all([p for pubs in self._publishers.values() for p in pubs.values()] + self._retiring)
        if self._token is not None:
            self._token.undeclare()
        if self._own_session:
            self.transport.close()

    def _stopping(self) -> None:
        """Subclass hook, called once stop is requested."""

    def _workers_ended(self) -> None:
        """Subclass hook, called after stop has waited for the node's threads to end."""

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def wait(self, timeout_s: float | None = None) -> bool:
        return self._stop.wait(timeout_s)

    # -- publishing -----------------------------------------------------------------------------
    def _publisher(self, sensor_id: str, topic: str, encoding: str) -> Publisher:
        """The publisher of ``<prefix>/<sensor_id>/<topic>``, declared on first use (a put
        through it skips the key's parsing and routing that each ``session.put`` does); a
        sensor id that is not a plain key chunk (a wildcard, ...) is a WireError, never a
        key. Data waits when the network is slow (BLOCK), health is dropped (DROP)."""
        pubs = self._publishers.get(sensor_id)
        pub = None if pubs is None else pubs.get(topic)
        if pub is None:
            pub = self.transport.declare_publisher(self._keys.key(sensor_id, topic), encoding, drop=topic == "health")
            with self._lock:
                self._publishers.setdefault(sensor_id, {})[topic] = pub
                self._n_publishers += 1
        return pub

    def _denied(self, sensor_id: str, topic: str) -> bool:
        """Under --secure, whether the access policy denies this node's identity putting on the key
        (the router would drop it unseen): then it is not sent, counted in the sensor's ``denied_puts``."""
        ident = self._identity
        if ident is None:
            return False
        allowed = self._may_put.get((sensor_id, topic))
        if allowed is None:
            self._keys.key(sensor_id, topic)  # the id checked (a WireError) before it has a count
            if len(self._may_put) >= 4 * MAX_PUBLISHERS:  # keys of many sensors: bounded
                self._may_put.clear()
            allowed = self._may_put[(sensor_id, topic)] = ident.may_publish(self.bus.prefix, sensor_id, topic)
        if allowed:
            return False
        with self._lock:
            self.sensor_stats(sensor_id).denied_puts += 1
            told, self._told_denied = self._told_denied, True
        if not told:
            log.error("%s: the access policy of %s denies identity %r putting on %s (it may put on %s): the router "
                      "drops such messages, so they are not sent and are counted in denied_puts; give the node "
                      "--identity of a sensor it publishes, or issue one (`qradar security add`)", self.name,
                      self.bus.secure.directory, ident.name, self.bus.key(sensor_id, topic),
                      ", ".join(ident.publishes(self.bus.prefix)))
        return True

    def _put(self, sensor_id: str, topic: str, payload: bytes, encoding: str) -> bool:
        """Put ``payload`` on ``<prefix>/<sensor_id>/<topic>`` (False: not put, the access
        policy denies this node's identity the key, :meth:`_denied`): through the key's declared
        publisher once its sensor has sent PUBLISHER_AFTER frames (while the node holds
        fewer than MAX_PUBLISHERS), else with ``session.put``. zenoh's declaration of a
        publisher costs more the more a session holds (0.16 ms each at 1 000, 3.5 ms at
        5 000, on 127.0.0.1 through a router): a crowd of new ids with one frame each would
        stall the node for seconds; their puts cost ~9 us instead."""
        if self._identity is not None and self._denied(sensor_id, topic):
            return False
        pubs = self._publishers.get(sensor_id)
        pub = None if pubs is None else pubs.get(topic)
        if pub is None:
            st = self.stats.get(sensor_id)
            if (st is not None and st.frames_in + st.frames_out >= PUBLISHER_AFTER
                    and self._n_publishers < MAX_PUBLISHERS):
                pub = self._publisher(sensor_id, topic, encoding)
        if pub is not None:
            pub.put(payload)
            return True
        self.transport.put(self._keys.key(sensor_id, topic), payload, encoding, drop=topic == "health")
        return True

    def publish(self, sensor_id: str, topic: str, payload: bytes, encoding: str) -> None:
        """Put ``payload`` on ``<prefix>/<sensor_id>/<topic>``."""
        if not self._put(sensor_id, topic, payload, encoding):
            return
        with self._lock:
            st = self.sensor_stats(sensor_id)
            st.frames_out += 1
            st.bytes_out += len(payload)
            st.last_seen = time.monotonic()

    def publish_many(self, sensor_ids: list[str], topic: str, payloads: list[bytes], encoding: str,
                     frames_out: bool = True) -> None:
        """Put each payload on its sensor's ``topic`` key, the counters under one lock; a
        message that fails is counted in its sensor's ``processing_errors`` (the others go on).
        ``frames_out=False``: a second message about frames already counted (the tracks after
        the targets): its bytes count, not its frames."""
        sent = []
        for sensor, payload in zip(sensor_ids, payloads):
            try:
                if self._put(sensor, topic, payload, encoding):
                    sent.append((sensor, len(payload)))
            except (PipelineError, TransportError) as exc:
                why = zenoh_reason(exc) if isinstance(exc, TransportError) else exc
                self.count(sensor, "processing_errors", f"{self.bus.key(sensor, topic)}: {why}")
        now = time.monotonic()
        with self._lock:
            for sensor, n in sent:
                st = self.sensor_stats(sensor)
                st.frames_out += frames_out
                st.bytes_out += n
                st.last_seen = now

    # -- health ------------------------------------------------------------------------------------
    def _health_loop(self) -> None:
        tick = 0
        while not self._stop.wait(self.health_period_s / HEALTH_SLICES):
            tick += 1
            try:
                self.log_summary(force=False)
                self._publish_health(tick % HEALTH_SLICES)
                if tick % HEALTH_SLICES == 0:
                    self._expire()
            except Exception as exc:  # health must not die either
                self.log_limited("health", "%s: health failed (%s: %s)", self.name, type(exc).__name__, exc)

    def _expire(self) -> None:
        """Forget sensors silent for sensor_expiry_s; their publishers are undeclared one
        period later (a worker may still hold one), and once TRIM_AFTER_SENSORS sensors are
        gone that way the C heap's free memory goes back to the system (:func:`release_memory`)."""
        retiring, self._retiring = self._retiring, []
        for pub in retiring:
            try:
                pub.undeclare()
            except TransportError:
                pass
        retiring.clear()  # their memory is free once nothing holds them
        if self._released >= TRIM_AFTER_SENSORS:
            self._released = 0
            release_memory()
        if self.sensor_expiry_s is None:
            return
        horizon = time.monotonic() - self.sensor_expiry_s
        with self._lock:
            expired = [s for s, st in self.stats.items() if st.last_seen < horizon and s != NO_SENSOR]
            for sensor in expired:
                self._retired.add_counters(self.stats.pop(sensor))
                gone = self._publishers.pop(sensor, {})
                self._n_publishers -= len(gone)
                self._retiring.extend(gone.values())
                self.sensors_expired += 1
                self._keys.forget(sensor)
                self.forget(sensor)
            self._released += len(expired)
            if expired and len(expired) >= len(self.stats):  # a dict never shrinks as it empties
                self.stats = dict(self.stats)
                self._publishers = dict(self._publishers)

    def forget(self, sensor_id: str) -> None:
        """Subclass hook (called with ``_lock`` held): drop per-sensor state of an expired sensor."""

    def health_extra(self, sensor_id: str) -> dict:
        return {}

    def _publish_health(self, part: int | None = None) -> None:
        """Publish the health of the sensors of slice ``part`` (0..HEALTH_SLICES-1; None: of
        every sensor); subclasses that add once-a-period work do it for part 0 or None."""
        now_ns = time.time_ns()
        with self._lock:
            snapshot = []
            restarts = self.worker_restarts
            for sensor, st in self.stats.items():
                if part is not None and st.slot != part:
                    continue
                if sensor == NO_SENSOR:  # the unknown senders' aggregate
                    sensor = UNKNOWN_SENSOR
                b_in, b_out, t_prev = st._last_bytes
                dt = (now_ns - t_prev) / 1e9 if t_prev else self.health_period_s
                msg = HealthMsg(
                    node=self.name, sensor_id=sensor, timestamp_ns=now_ns, frames_in=st.frames_in,
                    frames_out=st.frames_out, drops=st.drops, decode_errors=st.decode_errors,
                    latency_ms=st.latency.summary(),
                    bytes_in_per_s=(st.bytes_in - b_in) / max(dt, 1e-9),
                    bytes_out_per_s=(st.bytes_out - b_out) / max(dt, 1e-9),
                    invalid_frames=st.invalid_frames, processing_errors=st.processing_errors,
                    frames_missing=st.frames_missing, seq_resets=st.seq_resets, worker_restarts=restarts,
                    over_budget=st.over_budget, refused=st.refused, implausible_seq=st.implausible_seq,
                    denied_puts=st.denied_puts,
                )
                st._last_bytes = (st.bytes_in, st.bytes_out, now_ns)
                snapshot.append(msg)
        for msg in snapshot:
            try:
                msg.extra = audit.health(self.health_extra(msg.sensor_id))  # + "audit" counts under --secure
                self._put(msg.sensor_id, "health", msg.to_json(), "application/json")
            except (TransportError, WireError) as exc:
                log.debug("health publish failed: %s", exc)



@runtime_checkable
class Runnable(Protocol):
    """What :func:`run_nodes` runs (a :class:`Node`, ``qradar.run.DriverProcess``): started,
    stopped once, named in errors; ``errors`` holds what its threads died of."""

    name: str
    errors: list[BaseException]

    def start(self) -> object: ...

    def stop(self) -> None: ...


def _raise_node_error(nodes: Sequence[Runnable]) -> None:
    """Raise the first error of a failed node: its own when it is a RadarError or a
    PipelineError (its message says what and where), else a PipelineError naming the node."""
    for nd in nodes:
        if nd.errors:
            exc = nd.errors[0]
            if isinstance(exc, (RadarError, PipelineError)):
                raise exc
            raise PipelineError(f"node {nd.name} failed: {exc!r}") from exc


def run_nodes(nodes: Sequence[Runnable], duration_s: float | None, stop: threading.Event | None = None) -> None:
    """Start nodes in order, run until ``duration_s`` or ``stop``, stop them in reverse order."""
    started: list[Runnable] = []
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
