"""The base of every zenoh node: session, liveliness, health, publishers, statistics,
and the subscribe -> bounded fair queue -> batch -> process loop of processing nodes.

A processing node subscribes with a wildcard (``<prefix>/*/raw``, ...) and so serves
many sensors at once. zenoh's callback thread hands over each message (the default); with
``input_mode="pull"`` zenoh queues the messages in a FIFO of its own (Rust, no Python
thread woken per message) and the worker drains it between batches, which saves the GIL
changing hands once a message (at thousands a second a sixth of a core) but, when that
FIFO is full, makes zenoh wait (back-pressure through the transport to the senders, and
to other subscribers of the same session): for a node with its process to itself. Each
message's key and length are checked before anything is copied (a frame whose length no announced configuration has is refused
there), notes the frame's sequence number (a gap is counted in ``frames_missing``) and
puts the payload into a :class:`~pipeline.fairqueue.FairQueue`: one FIFO per sensor,
bounded per sensor, in frames and in bytes, served round-robin, so a flooding sensor
loses its own frames (counted in its ``drops``), not the others'. A worker thread takes
batches and hands them to :meth:`ProcessingNode.process`, which calls the vectorized
math. Data publishers use ``CongestionControl.BLOCK``: when the network is slower than
the data, a publisher waits instead of dropping, so back-pressure reaches the node's
bounded queue, where every drop is counted. Health goes out with ``DROP``: it is
periodic and a lost one is replaced a second later.

No input stops a node: each failure is counted by kind (:data:`ERROR_KINDS`), logged at
most once a second with the key and the reason, and the node goes on; a worker that
dies anyway is restarted and counted (``worker_restarts``). A sensor silent for
``sensor_expiry_s`` is forgotten (its counters stay in the node's totals), and sensor
ids that are not valid key chunks (``*``, ``$*``, ...) never get state, health or a key.

Every node declares a liveliness token and publishes ``<prefix>/<sensor>/health``
once a second for every sensor it has seen.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import zenoh

from radar_driver.errors import RadarError

from . import audit
from .budget import MAX_TOPIC_BUCKETS, IntakeBudget, KeyBudget, TokenBucket
from .bus import BusConfig, Shard, check_sensor_pattern, pattern_chunk, zenoh_reason
from .errors import ParameterError, PipelineError, WireError
from .fairqueue import FairQueue
from .histogram import LogHistogram
from .memory import release_memory
from .wire import HEADER_LEN, MAGIC, TOPICS, HealthMsg, check_sensor_id, forget_sensor_id

log = logging.getLogger("qradar.node")

#: counters of failures, by kind: unparsable payloads; frames that parse but contradict
#: the announced configuration (length, M, config id, bits, samples not finite);
#: failures of the math or of publishing one message
ERROR_KINDS = ("decode_errors", "invalid_frames", "processing_errors")
#: the counters summed by :meth:`Node.totals`
COUNTERS = ("frames_in", "frames_out", "drops", *ERROR_KINDS, "frames_missing", "seq_resets",
            "over_budget", "refused", "bytes_in", "bytes_out")
#: a key gets a declared publisher once its sensor has sent this many frames (Node._put)
PUBLISHER_AFTER = 20
#: the most publishers a node declares (the other keys are put with session.put)
MAX_PUBLISHERS = 2048
#: the stats bucket of messages with no valid sensor id, or of an id not admitted (its
#: health goes out as the sensor UNKNOWN_SENSOR)
NO_SENSOR = ""
#: the sensor id of the health of the unknown senders' aggregate (a real sensor of that
#: id would share it)
UNKNOWN_SENSOR = "_unknown"
#: a node logs a summary of the failures it counted (by kind and sender) this often (s)
SUMMARY_PERIOD_S = 60.0
#: the most senders a summary names per kind (the rest are summed)
SUMMARY_SENDERS = 5
#: the most senders counted apart between two summaries, per kind
TALLY_MAX = 64
#: the unknown senders' aggregate gets this many times a key's budget, per topic
UNKNOWN_BUDGET_SCALE = 100
SEQ = struct.Struct("<Q")
SEQ_OFFSET = 8  # of the uint64 sequence number in the common frame header
DEFAULT_SENSOR_EXPIRY_S = 60.0
#: sensors forgotten (~12 KB of state each, freed into the C heap) before an expiry sweep
#: hands the heap's free memory back to the system (pipeline.memory.release_memory)
TRIM_AFTER_SENSORS = 64
DEFAULT_SENSOR_QUEUE = 128
DEFAULT_QUEUE_BYTES = 64 << 20
#: a node publishes health in this many slices of its sensors spread over the health
#: period, so that a thousand sensors never cost one long stall (each still once a period)
HEALTH_SLICES = 10
#: the most keys whose classification (sensor id, served or not) a node remembers
KEY_CACHE_SIZE = 8192
#: how a processing node's worker gets its input: is handed each message by zenoh's callback
#: thread (the default), or drains zenoh's FIFO itself
INPUT_MODES = ("callback", "pull")
#: the most messages zenoh's FIFO holds for a pulling node (before their length is checked;
#: when it is full zenoh waits, holding the transport: back-pressure to the senders)
PULL_FIFO = 1024
#: a pulling worker with nothing to do looks at its input this often (s) while frames came
#: in the last second, else every IDLE_POLL_S: ~1 % of a core while idle
POLL_S = 0.0005
IDLE_POLL_S = 0.002
#: on_idle() is called when no message came for this long (s)
IDLE_S = 0.1


#: the largest sequence gap counted as frames missing (50 s at 20 frames/s); a larger jump
#: ahead counts as a reset of the sequence (seq_resets)
MAX_SEQ_GAP = 1000


def sensor_label(sensor_id: str) -> str:
    """A sensor id as a log line names it (the unknown senders' aggregate has none)."""
    return sensor_id if sensor_id != NO_SENSOR else "unknown senders"


@dataclass
class SensorStats:
    """Counters of one sensor at one node; ``latency`` in ms (a fixed-size histogram)."""

    frames_in: int = 0
    frames_out: int = 0
    drops: int = 0
    decode_errors: int = 0
    invalid_frames: int = 0
    processing_errors: int = 0
    frames_missing: int = 0
    seq_resets: int = 0
    #: frames dropped on arrival over their key's budget (pipeline.budget)
    over_budget: int = 0
    #: frames of sensor ids not admitted (new ids over the node's admission rate)
    refused: int = 0
    bytes_in: int = 0
    bytes_out: int = 0
    latency: LogHistogram = field(default_factory=LogHistogram)
    last_seen: float = field(default_factory=time.monotonic)
    #: which of the HEALTH_SLICES publishes this sensor's health
    slot: int = 0
    # the last sequence number seen per input topic
    last_seq: dict = field(default_factory=dict)
    # topic -> KeyBudget (at most MAX_TOPIC_BUCKETS; then the topic "" holds the rest)
    budgets: dict = field(default_factory=dict)
    # topic -> frames dropped over budget since the last sequence number noted (not missing)
    skipped: dict = field(default_factory=dict)
    # for rates between two health messages
    _last_bytes: tuple[int, int, float] = (0, 0, 0.0)

    def add_counters(self, other: "SensorStats") -> None:
        for k in COUNTERS:
            setattr(self, k, getattr(self, k) + getattr(other, k))

    def note_seq(self, topic: str, seq: int) -> None:
        """Count a gap (frames_missing) or a restart of the sequence (seq_resets). A jump
        ahead by more than MAX_SEQ_GAP frames is no loss a transport makes (a sender
        restarted with another count, or a forged sequence number): a reset, so that one
        frame cannot make the count of missing frames implausible."""
        last = self.last_seq.get(topic)
        self.last_seq[topic] = seq
        skipped = self.skipped.pop(topic, 0) if self.skipped else 0  # dropped here, counted in over_budget
        if last is None or seq == last + 1:
            return
        if last + 1 < seq <= last + 1 + MAX_SEQ_GAP + skipped:
            self.frames_missing += max(seq - last - 1 - skipped, 0)
        else:  # the sender restarted its count (or repeated a frame), or an implausible jump
            self.seq_resets += 1

    def within_budget(self, topic: str, n_bytes: int, now: float, budget: IntakeBudget, scale: int = 1) -> str | None:
        """None when a message of ``n_bytes`` on ``topic`` fits this sensor's budget for it,
        else which budget it exceeds."""
        kb = self.budgets.get(topic)
        if kb is None:
            if len(self.budgets) >= MAX_TOPIC_BUCKETS:
                topic = ""
                kb = self.budgets.get(topic)
            if kb is None:
                b = budget if scale == 1 else IntakeBudget(budget.rate_hz * scale, budget.bytes_per_s * scale,
                                                           budget.burst_s)
                kb = self.budgets[topic] = KeyBudget(b, now)
        return kb.admit(now, n_bytes)


class Node:
    """Base of every node: zenoh session, liveliness, health, publishers, statistics.

    ``session=None`` opens a session from ``bus`` (closed on stop); a given session is
    shared and left open. ``sensor_expiry_s``: a sensor silent that long is forgotten
    (None: never)."""

    name = "node"

    def __init__(self, bus: BusConfig, session: zenoh.Session | None = None, health_period_s: float = 1.0,
                 sensor_expiry_s: float | None = DEFAULT_SENSOR_EXPIRY_S):
        if sensor_expiry_s is not None and not sensor_expiry_s > 0:
            raise ParameterError(f"sensor expiry {sensor_expiry_s!r} s must be > 0 (or None: never)")
        self.bus = bus
        self._own_session = session is None
        self.session = session if session is not None else bus.open()
        self.health_period_s = health_period_s
        self.sensor_expiry_s = sensor_expiry_s
        self.stats: dict[str, SensorStats] = {}
        self._retired = SensorStats()  # counters of expired sensors
        self._next_slot = 0
        self.sensors_expired = 0
        self.worker_restarts = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._publishers: dict[str, dict[str, zenoh.Publisher]] = {}  # sensor -> topic -> publisher
        self._n_publishers = 0
        self._encodings: dict[str, zenoh.Encoding] = {}
        self._retiring: list[zenoh.Publisher] = []
        self._released = 0  # sensors forgotten since the C heap was last trimmed
        self._token = None
        self._last_log: dict[str, float] = {}
        self._tally: dict[str, dict[str, int]] = {}  # kind -> sender -> count since the last summary
        self._last_summary = time.monotonic()
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
        self._publish_health()  # last counters
        self.log_summary()
        for pub in [p for pubs in self._publishers.values() for p in pubs.values()] + self._retiring:
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

    # -- statistics ---------------------------------------------------------------------------
    def sensor_stats(self, sensor_id: str) -> SensorStats:
        """The stats of a sensor, created on first use; call with ``_lock`` held."""
        st = self.stats.get(sensor_id)
        if st is None:
            st = self.stats[sensor_id] = SensorStats(slot=self._next_slot)
            self._next_slot = (self._next_slot + 1) % HEALTH_SLICES
        return st

    def log_limited(self, what: str, fmt: str, *args) -> None:
        """A warning, at most one a second for each ``what``."""
        now = time.monotonic()
        if now - self._last_log.get(what, -1e9) >= 1.0:
            self._last_log[what] = now
            log.warning(fmt, *args)

    def count(self, sensor_id: str, kind: str, reason: object, n: int = 1) -> None:
        """Count ``n`` failures of ``kind`` (one of :data:`ERROR_KINDS`) against a sensor
        and log the reason (which names the key) at most once a second per kind; every
        SUMMARY_PERIOD_S a summary line says how many of each kind came from whom."""
        if kind not in ERROR_KINDS:
            raise ParameterError(f"error kind {kind!r} is not one of {ERROR_KINDS}")
        with self._lock:
            st = self.sensor_stats(sensor_id)
            setattr(st, kind, getattr(st, kind) + n)
            self._note(kind, sensor_id, n)
        self.log_limited(kind, "%s: %s (counted in %s; node keeps running)", self.name, reason, kind)

    def _note(self, kind: str, sensor_id: str, n: int = 1) -> None:
        """Tally ``n`` events of ``kind`` from a sender for the next summary (``_lock`` held);
        at most TALLY_MAX senders apart, the others summed under "others"."""
        tally = self._tally.setdefault(kind, {})
        sender = sensor_id if sensor_id in tally or len(tally) < TALLY_MAX else "others"
        tally[sender] = tally.get(sender, 0) + n

    def log_summary(self, force: bool = True) -> None:
        """Log, per kind counted since the last summary, one line: how many and from which
        senders (the largest SUMMARY_SENDERS by name). Without ``force``, only once
        SUMMARY_PERIOD_S has passed since the last one."""
        now = time.monotonic()
        with self._lock:
            if not force and now - self._last_summary < SUMMARY_PERIOD_S:
                return
            tally, self._tally = self._tally, {}
            span, self._last_summary = now - self._last_summary, now
        for kind, senders in sorted(tally.items()):
            top = sorted(senders.items(), key=lambda kv: -kv[1])
            named = ", ".join(f"{n} from {sensor_label(s)}" for s, n in top[:SUMMARY_SENDERS])
            rest = sum(n for _, n in top[SUMMARY_SENDERS:])
            more = f", {rest} from {len(top) - SUMMARY_SENDERS} more" if rest else ""
            log.warning("%s: %d %s in the last %.0f s: %s%s", self.name, sum(senders.values()), kind, span, named,
                        more)

    def count_error(self, sensor_id: str, exc: Exception) -> None:
        """A payload that does not decode (``decode_errors``)."""
        self.count(sensor_id, "decode_errors", exc)

    def record_latencies(self, sensor_ids: list[str], latency_ms) -> None:
        """One latency (ms) per sensor id, under one lock (a batch of frames)."""
        with self._lock:
            for sensor, value in zip(sensor_ids, latency_ms.tolist() if hasattr(latency_ms, "tolist") else latency_ms):
                self.sensor_stats(sensor).latency.add(value)

    # -- publishing -----------------------------------------------------------------------------
    def _publisher(self, sensor_id: str, topic: str, encoding: str) -> zenoh.Publisher:
        """The publisher of ``<prefix>/<sensor_id>/<topic>``, declared on first use (a put
        through it skips the key's parsing and routing that each ``session.put`` does); a
        sensor id that is not a plain key chunk (a wildcard, ...) is a WireError, never a
        key. Data waits when the network is slow (BLOCK), health is dropped (DROP)."""
        pubs = self._publishers.get(sensor_id)
        pub = None if pubs is None else pubs.get(topic)
        if pub is None:
            key = self.bus.key(check_sensor_id(sensor_id), topic)
            pub = self.session.declare_publisher(key, encoding=self._encoding(encoding), congestion_control=(
                zenoh.CongestionControl.DROP if topic == "health" else zenoh.CongestionControl.BLOCK))
            with self._lock:
                self._publishers.setdefault(sensor_id, {})[topic] = pub
                self._n_publishers += 1
        return pub

    def _encoding(self, encoding: str) -> zenoh.Encoding:
        enc = self._encodings.get(encoding)
        if enc is None:
            enc = self._encodings[encoding] = zenoh.Encoding(encoding)
        return enc

    def _put(self, sensor_id: str, topic: str, payload: bytes, encoding: str) -> None:
        """Put ``payload`` on ``<prefix>/<sensor_id>/<topic>``: through the key's declared
        publisher once its sensor has sent PUBLISHER_AFTER frames (while the node holds
        fewer than MAX_PUBLISHERS), else with ``session.put``. zenoh's declaration of a
        publisher costs more the more a session holds (0.16 ms each at 1 000, 3.5 ms at
        5 000, on 127.0.0.1 through a router): a crowd of new ids with one frame each would
        stall the node for seconds; their puts cost ~9 us instead."""
        pubs = self._publishers.get(sensor_id)
        pub = None if pubs is None else pubs.get(topic)
        if pub is None:
            st = self.stats.get(sensor_id)
            if (st is not None and st.frames_in + st.frames_out >= PUBLISHER_AFTER
                    and self._n_publishers < MAX_PUBLISHERS):
                pub = self._publisher(sensor_id, topic, encoding)
        if pub is not None:
            pub.put(payload)
            return
        self.session.put(self.bus.key(check_sensor_id(sensor_id), topic), payload,
                         encoding=self._encoding(encoding), congestion_control=(
                             zenoh.CongestionControl.DROP if topic == "health" else zenoh.CongestionControl.BLOCK))

    def publish(self, sensor_id: str, topic: str, payload: bytes, encoding: str) -> None:
        """Put ``payload`` on ``<prefix>/<sensor_id>/<topic>``."""
        self._put(sensor_id, topic, payload, encoding)
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
                self._put(sensor, topic, payload, encoding)
                sent.append((sensor, len(payload)))
            except (PipelineError, zenoh.ZError) as exc:
                why = zenoh_reason(exc) if isinstance(exc, zenoh.ZError) else exc
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
            except zenoh.ZError:
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
                forget_sensor_id(sensor)
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
                    over_budget=st.over_budget, refused=st.refused,
                )
                st._last_bytes = (st.bytes_in, st.bytes_out, now_ns)
                snapshot.append(msg)
        for msg in snapshot:
            try:
                msg.extra = audit.health(self.health_extra(msg.sensor_id))  # + "audit" counts under --secure
                self._put(msg.sensor_id, "health", msg.to_json(), "application/json")
            except (zenoh.ZError, WireError) as exc:
                log.debug("health publish failed: %s", exc)

    def totals(self) -> dict[str, int]:
        """Every counter summed over the sensors (expired ones included), plus
        ``worker_restarts`` and ``sensors_expired``."""
        with self._lock:
            out = {k: getattr(self._retired, k) for k in COUNTERS}
            for st in self.stats.values():
                for k in COUNTERS:
                    out[k] += getattr(st, k)
            out["worker_restarts"] = self.worker_restarts
            out["sensors_expired"] = self.sensors_expired
            return out


class ProcessingNode(Node):
    """Subscribes ``<prefix>/<sensors>/<in_topic>``; callback -> fair queue -> batches ->
    :meth:`process`.

    queue_size: frames waiting in all; sensor_queue_size: of one sensor (default
    min(queue_size, 128)); queue_bytes: payload bytes waiting in all. ``sensors``: the
    sensors served, a key chunk with ``*`` wildcards (zenoh filters the others before they
    reach this process); ``shard``: serve only the sensors of this :class:`~pipeline.bus.Shard`
    (the others' frames are counted in ``foreign_frames`` and dropped on arrival, before
    any copy). ``input_mode``: "callback" (zenoh's callback thread queues each message) or
    "pull" (zenoh's FIFO of at most PULL_FIFO messages, drained by the worker; when it is
    full zenoh holds the next messages back in the transport)."""

    in_topic = "raw"
    #: True: messages on keys without a valid sensor chunk are processed too (the recorder)
    accepts_any_key = False
    #: the most frames of one sensor in a batch (None: no limit): a flooding sensor's batch
    #: ends early, so the others' next frames do not wait behind a whole batch of its
    batch_per_sensor: int | None = 16
    #: once a frame waits, the worker waits this long (s) for a full batch: frames of many
    #: sensors sending at their own times then share one vectorized call, whose fixed cost
    #: dominates a batch of one
    batch_linger_s: float = 0.0
    #: a lull this long without a new frame ends the wait for a full batch (s)
    batch_lull_s: float = 0.001

    def __init__(self, bus: BusConfig, session: zenoh.Session | None = None, queue_size: int = 8192,
                 batch_max: int = 64, health_period_s: float = 1.0, sensor_queue_size: int | None = None,
                 queue_bytes: int = DEFAULT_QUEUE_BYTES, sensor_expiry_s: float | None = DEFAULT_SENSOR_EXPIRY_S,
                 sensors: str = "*", shard: Shard | None = None, batch_linger_s: float | None = None,
                 input_mode: str = "callback", intake: IntakeBudget | None = None):
        super().__init__(bus, session, health_period_s, sensor_expiry_s)
        self.intake = IntakeBudget() if intake is None else intake
        self._new_ids = (TokenBucket(self.intake.new_sensors_per_s, self.intake.new_sensors_burst, time.monotonic())
                         if self.intake.new_sensors_per_s else None)
        if input_mode not in INPUT_MODES:
            raise ParameterError(f"input mode {input_mode!r} must be one of {INPUT_MODES}")
        self.input_mode = input_mode
        self._input = None  # pull: the subscriber's FIFO, drained by the worker
        if batch_linger_s is not None:
            if not 0 <= batch_linger_s <= 1.0:
                raise ParameterError(f"batch linger {batch_linger_s!r} s must be in [0, 1]")
            self.batch_linger_s = batch_linger_s
        self.sensors = check_sensor_pattern(sensors)
        self.shard = shard
        self.foreign_frames = 0
        self._key_info: dict[str, tuple[str, bool]] = {}  # key -> (sensor or NO_SENSOR, served)
        if queue_size < 1 or batch_max < 1:
            raise ParameterError(f"queue_size={queue_size} and batch_max={batch_max} must be >= 1")
        per_sensor = min(queue_size, DEFAULT_SENSOR_QUEUE) if sensor_queue_size is None else sensor_queue_size
        self._queue = FairQueue(queue_size, per_sensor, queue_bytes)
        self.batch_max = batch_max
        self._subscriber = None

    def totals(self) -> dict[str, int]:
        """:meth:`Node.totals`, plus ``foreign_frames`` (other shards' frames) with a shard."""
        out = super().totals()
        if self.shard is not None:
            with self._lock:
                out["foreign_frames"] = self.foreign_frames
        return out

    def forget(self, sensor_id: str) -> None:
        """An expired sensor's keys leave the key cache (subclasses that override call this)."""
        for topic in TOPICS:
            self._key_info.pop(self.bus.key(sensor_id, topic), None)

    def subscription(self) -> str:
        """The key expression this node listens to."""
        return self.bus.key(pattern_chunk(self.sensors), self.in_topic)

    def _start(self) -> None:
        if self.input_mode == "pull":
            self._subscriber = self.session.declare_subscriber(
                self.subscription(), zenoh.handlers.FifoChannel(min(self._queue.max_frames, PULL_FIFO)))
            self._input = self._subscriber.handler  # still yields what it holds after undeclare
            self._spawn_supervised(self._pull_loop, "worker")
        else:
            self._subscriber = self.session.declare_subscriber(self.subscription(), self._on_sample)
            self._spawn_supervised(self._work_loop, "worker")

    def _stopping(self) -> None:
        if self._subscriber is not None:  # a pulling worker then drains what zenoh holds, and ends
            self._subscriber.undeclare()
            self._subscriber = None

    def _drain(self) -> int:
        """Pull input: move the messages zenoh holds into the fair queue (at most its FIFO's
        capacity); how many frames the fair queue gained. Once the subscriber is undeclared
        and its FIFO empty, the input is closed (``_input`` None)."""
        h, before = self._input, len(self._queue)
        if h is None:
            return 0
        for _ in range(PULL_FIFO):
            try:
                sample = h.try_recv()
            except zenoh.ZError:  # undeclared and empty: nothing more will come
                self._input = None
                break
            if sample is None:
                break
            self._on_sample(sample)
        return max(len(self._queue) - before, 0)

    def _pull_loop(self) -> None:
        """The worker with pulled input: drain, linger for a fuller batch, process; poll
        every POLL_S when there is nothing to do; after stop, drain to the end and finish
        what was queued."""
        last_input = last_idle = time.monotonic()
        while True:
            got = self._drain()
            now = time.monotonic()
            if got:
                last_input = now
            if self._queue.empty():
                if self._input is None:  # closed and drained (after stop)
                    return
                if now - max(last_input, last_idle) >= IDLE_S:
                    last_idle = now
                    self.on_idle()
                time.sleep(POLL_S if now - last_input < 1.0 else IDLE_POLL_S)
                continue
            if self.batch_linger_s > 0:
                until = now + self.batch_linger_s
                while len(self._queue) < self.batch_max and (left := until - time.monotonic()) > 0:
                    time.sleep(min(left, self.batch_lull_s))
                    if not self._drain():  # a lull: no one else is sending now
                        break
            self._process_batch(self._queue.get_batch(self.batch_max, 0.0, self.batch_per_sensor))

    def admit(self, key: str, n_bytes: int) -> str | None:
        """Why a payload of ``n_bytes`` on ``key`` is refused before it is copied (None:
        admitted). Subclasses check the lengths their announced configurations allow."""
        return None

    def sensor_of(self, key: str) -> str:
        """The key's sensor id, or :data:`NO_SENSOR` when it has none that is valid."""
        sensor = self.bus.sensor_of(key)
        if sensor is None:
            return NO_SENSOR
        try:
            return check_sensor_id(sensor)
        except WireError:
            return NO_SENSOR

    def _on_sample(self, sample: zenoh.Sample) -> None:
        """The worker's drain (pull) or zenoh's callback thread: check the key and the length,
        note the sequence number, enqueue."""
        try:
            self._admit_sample(sample)
        except Exception as exc:  # nothing a sender does may kill zenoh's callback thread
            self.count(NO_SENSOR, "processing_errors", f"{sample.key_expr}: {type(exc).__name__}: {exc}")

    def _classify(self, key: str) -> tuple[str, bool]:
        """(sensor id or NO_SENSOR, whether this node serves it), remembered per key."""
        info = self._key_info.get(key)
        if info is None:
            sensor = self.sensor_of(key)
            info = (sensor, sensor == NO_SENSOR or self.shard is None or self.shard.serves(sensor))
            if len(self._key_info) >= KEY_CACHE_SIZE:  # a flood of junk keys: start again
                self._key_info.clear()
            self._key_info[key] = info
        return info

    def _admit_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        sensor, served = self._classify(key)
        if not served:  # another shard's sensor: not ours to count or queue
            with self._lock:
                self.foreign_frames += 1
            return
        n = len(sample.payload)
        reason = None
        if sensor == NO_SENSOR and not self.accepts_any_key:
            reason = "not a key of a valid sensor id (1-16 characters of [A-Za-z0-9_-])"
        else:
            reason = self.admit(key, n)
        if reason is not None:  # refused before the copy; an unknown sensor gets no state
            with self._lock:
                bucket = sensor if sensor in self.stats else NO_SENSOR
                st = self.sensor_stats(bucket)
                st.frames_in += 1
                st.bytes_in += n
            self.count(bucket, "invalid_frames", f"{key}: {reason}")
            return
        topic = key.rsplit("/", 1)[-1]
        health = topic == "health"
        now = time.monotonic()
        with self._lock:  # the intake budgets (pipeline.budget), before the copy
            if sensor not in self.stats and sensor != NO_SENSOR and (
                    health or (self._new_ids is not None and not self._new_ids.take(now))):
                sensor = NO_SENSOR  # health makes no sensor state; nor does an id not admitted
                refused = not health
            else:
                refused = False
            st = self.sensor_stats(sensor)
            st.frames_in += 1
            st.bytes_in += n
            if refused:
                st.refused += 1
                self._note("refused", sensor)
            else:
                over = st.within_budget(topic, n, now, self.intake,
                                        UNKNOWN_BUDGET_SCALE if sensor == NO_SENSOR else 1)
                if over is not None:
                    st.over_budget += 1
                    if sensor != NO_SENSOR:
                        st.skipped[topic] = st.skipped.get(topic, 0) + 1
                    self._note("over_budget", sensor)
        if refused:
            self.log_limited("refused", "%s: %s: a new sensor id over the admission budget (%g a second); "
                             "dropped, counted in refused", self.name, key, self.intake.new_sensors_per_s)
            return
        if over is not None:
            self.log_limited("over_budget", "%s: %s: over its %s budget; dropped, counted in over_budget",
                             self.name, key, over)
            return
        payload = sample.payload.to_bytes()
        with self._lock:
            st = self.sensor_stats(sensor)  # the same, unless it expired meanwhile
            if not health:  # nor keeps one alive: else a sensor seen once by a recorder never expires
                st.last_seen = now
            if sensor != NO_SENSOR and len(payload) >= HEADER_LEN and payload[:4] == MAGIC:
                st.note_seq(topic, SEQ.unpack_from(payload, SEQ_OFFSET)[0])
        for victim in self._queue.put(sensor, (sensor, key, payload, time.time_ns()), n):
            with self._lock:
                self.sensor_stats(victim).drops += 1
            self.log_limited("drops", "%s: queue full, dropped a frame of %s (counted in its drops)",
                             self.name, victim or key)

    def _work_loop(self) -> None:
        # after stop, drain what was queued before the subscriber went away
        while not (self._stop.is_set() and self._queue.empty()):
            batch = self._queue.get_batch(self.batch_max, 0.1, self.batch_per_sensor, self.batch_linger_s,
                                         self.batch_lull_s)
            if not batch:
                self.on_idle()
                continue
            self._process_batch(batch)

    def _process_batch(self, batch: list[tuple[str, str, bytes, int]]) -> None:
        try:
            self.process(batch)
        except Exception as exc:  # a failure process() did not isolate: the batch is lost, counted
            log.debug("%s: batch failed", self.name, exc_info=True)
            for sensor, key, _, _ in batch:
                self.count(sensor, "processing_errors", f"{key}: {type(exc).__name__}: {exc}")

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
