"""A node's counters: per sensor (:class:`SensorStats`), summed (``totals``), failures
counted by kind and logged at most once a second, with a summary of who sent them.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from pipeline.nodes.budget import MAX_TOPIC_BUCKETS, IntakeBudget, KeyBudget
from pipeline.errors import ParameterError
from pipeline.nodes.histogram import LogHistogram

log = logging.getLogger("qradar.node")

#: counters of failures, by kind: unparsable payloads; frames that parse but contradict
#: the announced configuration (length, M, config id, bits, samples not finite);
#: failures of the math or of publishing one message
ERROR_KINDS = ("decode_errors", "invalid_frames", "processing_errors")
#: the counters summed by :meth:`Node.totals`
COUNTERS = ("frames_in", "frames_out", "drops", *ERROR_KINDS, "frames_missing", "seq_resets",
            "over_budget", "refused", "bytes_in", "bytes_out")
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
#: a node publishes health in this many slices of its sensors spread over the health
#: period, so that a thousand sensors never cost one long stall (each still once a period)
HEALTH_SLICES = 10
#: the largest sequence gap counted as frames missing (50 s at 20 frames/s); a larger jump
#: ahead counts as a reset of the sequence (seq_resets)
MAX_SEQ_GAP = 1000


def sensor_label(sensor_id: str) -> str:
    """A sensor id as a log line names it (the unknown senders' aggregate has none)."""
    return sensor_id if sensor_id != NO_SENSOR else "unknown senders"


#: the binning of every sensor's latency histogram (ms): :meth:`Counters.record_latencies`
#: finds a batch's bins with it
LATENCY_BINNING = LogHistogram()


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
    #: frames dropped on arrival over their key's budget (pipeline.nodes.budget)
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


class Counters:
    """The statistics of a node: ``stats`` per sensor (under ``_lock``), the counters of
    expired sensors, failures counted by kind and their once-a-minute summary."""

    name = "node"

    def __init__(self) -> None:
        self.stats: dict[str, SensorStats] = {}
        self._retired = SensorStats()  # counters of expired sensors
        self._next_slot = 0
        self.sensors_expired = 0
        self.worker_restarts = 0
        self._lock = threading.Lock()
        self._last_log: dict[str, float] = {}
        self._tally: dict[str, dict[str, int]] = {}  # kind -> sender -> count since the last summary
        self.last_reason: dict[str, str] = {}  # kind -> the reason of the last failure counted
        self._last_summary = time.monotonic()

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
            self.last_reason[kind] = str(reason)
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
        """One latency (ms) per sensor id, under one lock (a batch of frames): the
        histogram bins of the batch found in one vectorized pass (every sensor's latency
        histogram has the default binning, :data:`LATENCY_BINNING`), one at a time below 4."""
        values = np.asarray(latency_ms, dtype=float).ravel()
        if values.size < 4:  # a few frames: numpy's fixed cost is more than it saves
            with self._lock:
                for sensor, value in zip(sensor_ids, values.tolist()):
                    self.sensor_stats(sensor).latency.add(value)
            return
        bins = LATENCY_BINNING.bins(values).tolist()
        with self._lock:
            for sensor, value, i in zip(sensor_ids, values.tolist(), bins):
                self.sensor_stats(sensor).latency.add_binned(value, i)

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
