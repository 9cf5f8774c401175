"""A node's counters: per sensor (:class:`SensorStats`), summed (``totals``), failures
counted by kind and logged at most once a second, with a summary of who sent them; and
:func:`judge_seq`, the one judge of a sequence number (missing frames, a reset, or a
number out of line), which every reader of sequence numbers calls.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from pipeline.nodes.budget import DEFAULT_RATE_HZ, MAX_TOPIC_BUCKETS, IntakeBudget, KeyBudget
from pipeline.errors import ParameterError
from pipeline.nodes.histogram import LogHistogram

log = logging.getLogger("qradar.node")

#: counters of failures, by kind: unparsable payloads; frames that parse but contradict
#: the announced configuration (length, M, config id, bits, samples not finite);
#: failures of the math or of publishing one message
ERROR_KINDS = ("decode_errors", "invalid_frames", "processing_errors")
#: the counters summed by :meth:`Node.totals`
COUNTERS = ("frames_in", "frames_out", "drops", *ERROR_KINDS, "frames_missing", "seq_resets", "implausible_seq",
            "over_budget", "refused", "denied_puts", "bytes_in", "bytes_out")
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
#: the sequence numbers of a key may advance at most this much faster than its sender's
#: rate (a clock a little fast, a queue emptying after a stall) ...
SEQ_RATE_SLACK = 1.25
#: ... plus this many seconds of frames at that rate, at any moment (frames of a gap that
#: arrive bunched: a node's queue dropped some of a burst)
SEQ_AHEAD_S = 2.0
#: the rate (frames/s) a reader bounds a sequence by when it knows none: the intake
#: budget's default per key (5 x a K-MD2's 20 frames/s)
DEFAULT_SEQ_RATE_HZ = DEFAULT_RATE_HZ


@dataclass(slots=True)
class SeqTrack:
    """The sequence of one key at one reader: ``last``, the last number in line and
    ``last_s``, when it came (monotonic s); ``first_s``, when the key was first seen;
    ``advanced``, the frames the line has moved on by since (received, missing or
    skipped); ``pending``, a number out of line waiting for the next one to say whether
    the sender restarted its count (it follows on from it) or not (a forgery)."""

    last: int
    last_s: float
    first_s: float
    advanced: int = 1
    pending: int | None = None


@dataclass(frozen=True, slots=True)
class SeqVerdict:
    """What one sequence number adds to the counters: ``missing`` frames (a gap the
    elapsed time allows), ``resets`` (the sender restarted its count: a number out of line
    followed on by the next), ``implausible`` (a number out of line that nothing followed
    on: a jump ahead beyond what the elapsed time allows, one back, or a repeat)."""

    missing: int = 0
    resets: int = 0
    implausible: int = 0


_NOTHING = SeqVerdict()


def seq_allowance(track: SeqTrack, now_s: float, rate_hz: float) -> int:
    """The most frames the line of ``track`` may move on by at ``now_s`` (a gap counted as
    missing is at most this): what the time since its last number allows at ``rate_hz``
    (times SEQ_RATE_SLACK, plus SEQ_AHEAD_S of frames), and no more than the time since the
    key was first seen allows in all, less what the line moved on by already."""
    rate = rate_hz if rate_hz and rate_hz > 0 else DEFAULT_SEQ_RATE_HZ
    ahead = rate * SEQ_AHEAD_S
    since_last = rate * SEQ_RATE_SLACK * max(now_s - track.last_s, 0.0) + ahead
    in_all = rate * SEQ_RATE_SLACK * max(now_s - track.first_s, 0.0) + ahead - track.advanced
    return max(int(min(since_last, in_all)), 0)


def judge_seq(track: SeqTrack | None, seq: int, now_s: float, rate_hz: float = DEFAULT_SEQ_RATE_HZ,
              skipped: int = 0) -> tuple[SeqTrack, SeqVerdict]:
    """The one judge of a sequence number ``seq`` arriving at ``now_s`` (monotonic s) on a
    key whose state is ``track`` (None: its first number): the track to keep and what it
    counts. ``rate_hz``: the most frames a second the sender makes (the bound of what is
    missing); ``skipped``: frames of this key the reader dropped on purpose since its last
    number (in the sequence, not missing).

    A number that follows the last one within :func:`seq_allowance` moves the line on and
    counts the gap as missing (less ``skipped``). Any other (back, a repeat, too far ahead)
    waits as ``pending`` and moves nothing: if the next number follows on from it, the
    sender restarted its count (a reset, the line moves there); if the next follows the
    line, it was out of line (implausible: a forged number, or one replayed), and so is a
    pending one that the next number neither follows on from nor follows the line after.
    So no number, forged or not, counts a frame missing that the elapsed time does not
    allow, and one out of line never moves the line: the honest numbers after it count
    nothing."""
    if track is None:
        return SeqTrack(seq, now_s, now_s), _NOTHING
    gap = seq - track.last - 1
    if gap == 0 and track.pending is None:  # the next one: always in line, whatever the rate
        track.last, track.last_s, track.advanced = seq, now_s, track.advanced + 1
        return track, _NOTHING
    implausible = 0
    if gap == 0 or 0 < gap <= seq_allowance(track, now_s, rate_hz) + skipped:  # in line
        if track.pending is not None:  # the number out of line before was followed by nothing
            track.pending, implausible = None, 1
        track.last, track.last_s, track.advanced = seq, now_s, track.advanced + gap + 1
        if gap == 0 and not implausible:
            return track, _NOTHING
        return track, SeqVerdict(max(gap - skipped, 0), 0, implausible)
    if track.pending is not None:
        restart_gap = seq - track.pending - 1
        if 0 <= restart_gap <= seq_allowance(track, now_s, rate_hz) + skipped:  # it follows on from the pending
            track.last, track.last_s = seq, now_s
            track.advanced += restart_gap + 2
            track.pending = None
            return track, SeqVerdict(max(restart_gap - skipped, 0), 1, 0)
        implausible = 1  # neither followed: the pending was out of line; this one waits now
    track.pending = seq
    return track, SeqVerdict(0, 0, implausible) if implausible else _NOTHING


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
    #: sequence numbers out of line that nothing followed on from (forged, replayed: judge_seq)
    implausible_seq: int = 0
    #: frames dropped on arrival over their key's budget (pipeline.nodes.budget)
    over_budget: int = 0
    #: frames of sensor ids not admitted (new ids over the node's admission rate)
    refused: int = 0
    #: messages not put because the access policy (--secure) denies this node's identity their key
    denied_puts: int = 0
    bytes_in: int = 0
    bytes_out: int = 0
    latency: LogHistogram = field(default_factory=LogHistogram)
    last_seen: float = field(default_factory=time.monotonic)
    #: which of the HEALTH_SLICES publishes this sensor's health
    slot: int = 0
    # topic -> SeqTrack: the sequence of each input topic (judge_seq)
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

    def note_seq(self, topic: str, seq: int, now_s: float | None = None,
                 rate_hz: float = DEFAULT_SEQ_RATE_HZ) -> SeqVerdict:
        """Count what :func:`judge_seq` makes of ``seq`` on ``topic``: a gap in
        ``frames_missing``, a restart of the count in ``seq_resets``, a number out of line
        in ``implausible_seq``. Frames dropped over budget since the last number
        (``skipped``) are not missing. Call with the owner's lock held."""
        skipped = self.skipped.pop(topic, 0) if self.skipped else 0  # dropped here, counted in over_budget
        now_s = time.monotonic() if now_s is None else now_s
        track, verdict = judge_seq(self.last_seq.get(topic), seq, now_s, rate_hz, skipped)
        self.last_seq[topic] = track
        if skipped and track.pending is not None:  # out of line: the skipped frames still lie ahead of the line
            self.skipped[topic] = skipped
        if verdict is not _NOTHING:
            self.frames_missing += verdict.missing
            self.seq_resets += verdict.resets
            self.implausible_seq += verdict.implausible
        return verdict

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
