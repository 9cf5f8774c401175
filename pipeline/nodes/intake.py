"""The input side of a processing node: subscribe -> admit -> bounded fair queue ->
batch -> :meth:`ProcessingNode.process`.

A processing node subscribes with a wildcard (``<prefix>/*/raw``, ...) and so serves
many sensors at once. The transport's callback thread hands over each message (the
default); with ``input_mode="pull"`` the transport queues the messages in a FIFO of its
own (zenoh's, in Rust: no Python thread woken per message) and the worker drains it
between batches, which saves the GIL changing hands once a message (at thousands a
second a sixth of a core) but, when that FIFO is full, makes zenoh wait (back-pressure
through the transport to the senders, and to other subscribers of the same session): for
a node with its process to itself. Each message's key and length are checked before
anything is copied (a frame whose length no announced configuration has is refused
there), its key's intake budget (:mod:`pipeline.nodes.budget`) is applied, the frame's sequence
number is judged (:func:`pipeline.nodes.counters.judge_seq`: a gap the elapsed time allows in
``frames_missing``, a restarted count in ``seq_resets``, a number out of line in
``implausible_seq``; the key's intake rate bounds what can be missing) and the payload goes into a
:class:`~pipeline.nodes.fairqueue.FairQueue`: one FIFO per sensor, bounded per sensor, in
frames and in bytes, served round-robin, so a flooding sensor loses its own frames
(counted in its ``drops``), not the others'. A worker thread takes batches of
:class:`QueuedFrame` and hands them to :meth:`ProcessingNode.process`, which calls the
vectorized math.

No input stops a node: each failure is counted by kind (:data:`pipeline.nodes.counters.ERROR_KINDS`),
logged at most once a second with the key and the reason, and the node goes on. Sensor
ids that are not valid key chunks (``*``, ``$*``, ...) never get state, health or a key.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import zenoh

from radar_driver.options import nonneg_float, option, pos_float, pos_int

from pipeline.nodes.budget import IntakeBudget, TokenBucket
from pipeline.bus.session import BusConfig, Shard, check_sensor_pattern, pattern_chunk
from pipeline.nodes.counters import NO_SENSOR
from pipeline.errors import ParameterError, WireError
from pipeline.nodes.fairqueue import FairQueue
from pipeline.nodes.runtime import DEFAULT_SENSOR_EXPIRY_S, Node
from pipeline.nodes.transport import DRAIN_S, PullSubscriber, Sample, Transport, TransportError
from pipeline.wire import TOPICS, check_sensor_id, peek_seq

log = logging.getLogger("qradar.node")

#: the unknown senders' aggregate gets this many times a key's budget, per topic
UNKNOWN_BUDGET_SCALE = 100
#: frames waiting in a processing node's queue, in all and of one sensor; payload bytes in all
DEFAULT_QUEUE_SIZE = 8192
DEFAULT_SENSOR_QUEUE = 128
DEFAULT_QUEUE_BYTES = 64_000_000
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


@dataclass(frozen=True)
class QueueConfig:
    """A processing node's input queue and per-sensor state (its ``queue``,
    :meth:`node_kwargs`): frames and bytes waiting, of one
    sensor and in all, how long a silent sensor is remembered, how long a worker waits
    for a full batch, and how its input arrives."""

    queue_size: int = option(DEFAULT_QUEUE_SIZE, "frames waiting, in all (the bytes bound --queue-mb holds too)",
                             flag="--queue", parse=pos_int)
    sensor_queue_size: int = option(DEFAULT_SENSOR_QUEUE, "frames waiting of one sensor (a flooding sensor loses its "
                                    "own frames beyond this)", flag="--sensor-queue", parse=pos_int)
    queue_bytes: int = option(DEFAULT_QUEUE_BYTES, "payload megabytes waiting, in all", flag="--queue-mb",
                              parse=pos_float, scale=1e6, kinds=frozenset({"int", "float"}))
    sensor_expiry_s: float = option(DEFAULT_SENSOR_EXPIRY_S, "forget a sensor silent this many seconds (its counters "
                                    "stay in the totals)", flag="--sensor-expiry", parse=pos_float)
    batch_linger_s: float | None = option(
        None, "once a frame waits, wait up to MS ms for a full batch while frames keep coming (default 2): longer "
        "saves CPU on a busy host (a call costs ~1 ms however few its frames) but adds latency",
        flag="--batch-linger", metavar="MS", parse=nonneg_float, scale=1e-3)
    input_mode: str = option("callback", "callback: zenoh's callback thread hands over each message (default); pull: "
                             "the worker drains zenoh's FIFO of up to 1024 messages itself, saving the GIL changing "
                             "hands per message (at 450 sensors 69 %% of a core against 81 %%), but a full FIFO makes "
                             "zenoh wait: for a node with its process to itself", flag="--input", choices=INPUT_MODES)

    def node_kwargs(self) -> dict:
        """The keyword arguments of a ProcessingNode: this queue (its sensor expiry with it)."""
        return {"queue": self}


#: a ProcessingNode's ``sensor_expiry_s`` when not given: its queue's (:class:`QueueConfig`)
_QUEUES_EXPIRY = object()


@dataclass(frozen=True)
class ServeConfig:
    """Which sensors a processing node serves: a key chunk with ``*`` wildcards, and a
    shard ``I/N`` (the sensors with crc32(id) mod N == I)."""

    sensors: str = option("*", "only the sensors whose id matches this key chunk, e.g. 'b1*' (zenoh filters the "
                          "others before they reach this process; default *)", metavar="PATTERN",
                          parse=check_sensor_pattern)
    shard: str | None = option(None, "only the sensors with crc32(id) mod N == I: N processes with 0/N .. N-1/N "
                               "serve each sensor exactly once (the others' frames still arrive and are dropped "
                               "unread)", metavar="I/N", parse=lambda text: str(Shard.parse(text)))

    def node_kwargs(self) -> dict:
        return {"sensors": self.sensors, "shard": None if self.shard is None else Shard.parse(self.shard)}


@dataclass(slots=True)
class QueuedFrame:
    """A message waiting in a processing node's queue: the ``sensor`` id of its key
    (NO_SENSOR: none valid), the ``key``, the ``payload`` and ``received_ns``, the
    wall-clock time it was queued (ns since the epoch)."""

    sensor: str
    key: str
    payload: bytes
    received_ns: int


class ProcessingNode(Node):
    """Subscribes ``<prefix>/<sensors>/<in_topic>``; callback -> fair queue -> batches ->
    :meth:`process`.

    ``queue``: a :class:`QueueConfig`, its frames waiting in all (``queue_size``), of one
    sensor (``sensor_queue_size``, at most the whole), payload bytes waiting in all
    (``queue_bytes``), the batch's linger (None: the node's), the input mode and how long a
    silent sensor is remembered (``sensor_expiry_s``, unless the node's ``sensor_expiry_s`` is
    given: that one; None: never). ``batch_max``: frames a batch at most. ``sensors``: the
    sensors served, a key chunk with ``*`` wildcards (zenoh filters the others before they
    reach this process); ``shard``: serve only the sensors of this :class:`~pipeline.bus.session.Shard`
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

    def __init__(self, bus: BusConfig, session: zenoh.Session | Transport | None = None,
                 queue: QueueConfig | None = None, batch_max: int = 64, health_period_s: float = 1.0,
                 sensor_expiry_s: float | None = _QUEUES_EXPIRY,  # type: ignore[assignment]
                 sensors: str = "*", shard: Shard | None = None,
                 intake: IntakeBudget | None = None):
        queue = QueueConfig() if queue is None else queue
        if sensor_expiry_s is _QUEUES_EXPIRY:
            sensor_expiry_s = queue.sensor_expiry_s
        super().__init__(bus, session, health_period_s, sensor_expiry_s)
        self.intake = IntakeBudget() if intake is None else intake
        self._new_ids = (TokenBucket(self.intake.new_sensors_per_s, self.intake.new_sensors_burst, time.monotonic())
                         if self.intake.new_sensors_per_s else None)
        if queue.input_mode not in INPUT_MODES:
            raise ParameterError(f"input mode {queue.input_mode!r} must be one of {INPUT_MODES}")
        self.input_mode = queue.input_mode
        self._input: PullSubscriber | None = None  # pull: the subscriber's FIFO, drained by the worker
        if queue.batch_linger_s is not None:
            if not 0 <= queue.batch_linger_s <= 1.0:
                raise ParameterError(f"batch linger {queue.batch_linger_s!r} s must be in [0, 1]")
            self.batch_linger_s = queue.batch_linger_s
        self.sensors = check_sensor_pattern(sensors)
        self.shard = shard
        self.foreign_frames = 0
        self._key_info: dict[str, tuple[str, bool]] = {}  # key -> (sensor or NO_SENSOR, served)
        if queue.queue_size < 1 or queue.sensor_queue_size < 1 or batch_max < 1:
            raise ParameterError(f"queue_size={queue.queue_size}, sensor_queue_size={queue.sensor_queue_size} and "
                                 f"batch_max={batch_max} must be >= 1")
        self._queue = FairQueue(queue.queue_size, min(queue.sensor_queue_size, queue.queue_size),
                                int(queue.queue_bytes))
        self.batch_max = batch_max
        self._subscriber = None
        self._ended = False  # the node stopped and its workers ended (_workers_ended)

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
            self._subscriber = self._input = self.transport.declare_pull_subscriber(
                self.subscription(), min(self._queue.max_frames, PULL_FIFO))  # yields what it holds after undeclare
            self._spawn_supervised(self._pull_loop, "worker")
        else:
            self._subscriber = self.transport.declare_subscriber(self.subscription(), self._on_sample)
            self._spawn_supervised(self._work_loop, "worker")

    def _stopping(self) -> None:
        if self._subscriber is not None:  # a pulling worker then drains what zenoh holds, and ends
            if self._subscriber.undeclare() is False:  # a callback's: what zenoh held is handed over first
                log.warning("%s: zenoh still held messages for it %.0f s after stop; those that come later "
                            "are counted in drops", self.name, DRAIN_S)
            self._subscriber = None

    def _workers_ended(self) -> None:
        """A frame a callback still in flight queued after the worker finished is counted
        in its sensor's drops (received, never processed), not left unaccounted."""
        if any(t.is_alive() for t in self._threads):  # a busy worker still owns it
            return
        with self._lock:
            self._ended = True  # what comes later is counted as it comes (_admit_sample)
        if self._queue.empty():
            return
        late = self._queue.get_batch(len(self._queue) + 1, 0.0)
        for item in late:
            with self._lock:
                self.sensor_stats(item.sensor).drops += 1
        if late:
            self.log_limited("drops", "%s: %d frames arrived as it stopped, not processed (counted in drops)",
                             self.name, len(late))

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
            except TransportError:  # undeclared and empty: nothing more will come
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

    def _on_sample(self, sample: Sample) -> None:
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

    def _admit_sample(self, sample: Sample) -> None:
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
        with self._lock:  # the intake budgets (pipeline.nodes.budget), before the copy
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
            seq = peek_seq(payload) if sensor != NO_SENSOR else None
            if seq is not None:
                st.note_seq(topic, seq, now, self.intake.rate_hz)
            if self._ended:  # zenoh held it past DRAIN_S after stop: no worker will take it
                st.drops += 1
                victims = None
            else:  # queued under the lock: _workers_ended's flag and its last look at the queue are one step
                victims = self._queue.put(sensor, QueuedFrame(sensor, key, payload, time.time_ns()), n)
                for victim in victims:
                    self.sensor_stats(victim).drops += 1
        if victims is None:
            self.log_limited("drops", "%s: a frame of %s came after the node stopped (counted in its drops)",
                             self.name, key)
        for victim in victims or ():
            self.log_limited("drops", "%s: queue full, dropped a frame of %s (counted in its drops)",
                             self.name, victim or key)

    def _work_loop(self) -> None:
        # after stop, drain what was queued before the subscriber went away (its undeclare
        # comes just after stop is set: a sample may still be queued until then)
        while not (self._stop.is_set() and self._subscriber is None and self._queue.empty()):
            batch = self._queue.get_batch(self.batch_max, 0.1, self.batch_per_sensor, self.batch_linger_s,
                                         self.batch_lull_s)
            if not batch:
                self.on_idle()
                continue
            self._process_batch(batch)

    def _process_batch(self, batch: list[QueuedFrame]) -> None:
        try:
            self.process(batch)
        except Exception as exc:  # a failure process() did not isolate: the batch is lost, counted
            log.debug("%s: batch failed", self.name, exc_info=True)
            for item in batch:
                self.count(item.sensor, "processing_errors", f"{item.key}: {type(exc).__name__}: {exc}")

    def on_idle(self) -> None:
        """Called by the worker when no sample came for 0.1 s."""

    def process(self, batch: list[QueuedFrame]) -> None:
        raise NotImplementedError
