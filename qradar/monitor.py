"""The live monitor of ``qradar run``: counts and sizes per topic, latency, the honest score
of the targets against the true positions (:mod:`pipeline.dsp.score`), each sensor's rate,
losses and front-end state (calibrated or not, leakage seen), the live lines and warnings."""

from __future__ import annotations

import sys
import threading
import time
from collections import defaultdict
from dataclasses import dataclass
from typing import TextIO

import numpy as np
import zenoh

from pipeline.bus.session import BusConfig
from pipeline.nodes.counters import DEFAULT_SEQ_RATE_HZ, SeqTrack, judge_seq
from pipeline.nodes.front_end import front_end_warning, leakage_shown
from pipeline.nodes.histogram import LogHistogram
from pipeline.nodes.transport import as_transport
from pipeline.dsp.score import DETECTION_DISTANCE_M, Score, score_frames
from pipeline.wire import TOPICS, WireError
from pipeline.wire.shared import DecodedOnce, decoder
from radar_driver.model import polar_to_xy
from radar_driver.scene import SimScene



#: topics the monitor counts by name (``other`` for the rest)
MONITORED_TOPICS = frozenset(TOPICS)
class Monitor:
    """Watches ``<prefix>/**``: counts and sizes per topic, latency and position error of
    the targets against the true positions (``truth``: a scene whose targets are where
    the reflectors are; None: no error, as for a real sensor without ``--truth``), each
    sensor's rate and losses, and prints live lines (at most one a second per sensor).
    Light work only, so it runs in zenoh's callback. Its memory is fixed however long it
    runs: latency and error go into fixed-size histograms, counts are per known topic
    (the rest under ``other``), per-sensor state is bounded."""

    #: sensors whose last live line is remembered (beyond, the memory is cleared)
    MAX_SENSORS = 1024

    def __init__(self, bus: BusConfig, session: zenoh.Session | None, truth: SimScene | None, t0_ns: int,
                 live: TextIO | None = sys.stdout, clock_per_sensor: bool = False,
                 seq_rate_hz: float = DEFAULT_SEQ_RATE_HZ, calibration: str | None = None,
                 truths: dict[str, SimScene] | None = None, decoded: DecodedOnce | None = None):
        """``t0_ns``: the wall clock at which the truth's time is 0 (a moving target's start);
        with ``clock_per_sensor`` it is each sensor's first frame instead (a simulated K-MD2's
        scene starts moving with its first measured frame, after its driver connected).
        ``seq_rate_hz``: the sensors' frame rate, which bounds what a gap in the targets'
        sequence numbers can count as missing (:func:`~pipeline.nodes.counters.judge_seq`).
        ``calibration``: the calibration file the run's quantizer applies (None: none), until
        a sensor's health says otherwise. ``truths``: per sensor id, the truth as that sensor
        sees it (from its pose, :func:`qradar.liveview.seen_from`): the same targets, in order.
        ``decoded``: the process's JSON messages decoded once (pipeline.wire.shared: the run's
        recorder and views share them; None: decoded here)."""
        self._decode = decoder(decoded)
        self.bus, self.session, self.truth, self.t0_ns = bus, session, truth, t0_ns
        self.truths = dict(truths or {})
        self.clock_per_sensor = clock_per_sensor
        self._t0_by_sensor: dict[str, int] = {}
        self.live = live
        self.count: dict[str, int] = defaultdict(int)
        self.bytes: dict[str, int] = defaultdict(int)
        self.latency_ms = LogHistogram(lo=1e-3, hi=1e6)  # sensor timestamp -> targets published, ms
        self.errors_m = LogHistogram(lo=1e-4, hi=1e4)  # each true target to the nearest estimate, m
        # the honest score (pipeline.dsp.score): per true target, frames in which a target was matched
        # to it and the matched targets' errors; false targets and targets in all; frames scored
        self.distance_m = DETECTION_DISTANCE_M
        n_true = len(truth.targets) if truth is not None else 0
        self.detected = np.zeros(n_true, dtype=np.int64)
        self.detection_errors_m = [LogHistogram(lo=1e-4, hi=1e4) for _ in range(n_true)]
        self.false_targets = 0
        self.targets = 0
        self.frames_scored = 0
        # per sensor: what its health says of its front end ({"calibrated": file or False,
        # "checked": n, "leakage": m}) and the warnings printed (one per sensor)
        self.front_end: dict[str, dict] = {}
        self.calibration = calibration
        self.warnings: dict[str, str] = {}
        self.bad_targets = 0  # targets or tracks that do not decode (counted, never raised)
        self.bad_health = 0  # health that does not decode
        self.failed_messages = 0  # messages whose handling failed otherwise
        # tracks (--track): each static true target to the nearest static track within 1 m, m;
        # the largest track id seen per sensor (ids count up from 1)
        self.static_track_errors_m = LogHistogram(lo=1e-4, hi=1e4)
        self.track_ids: dict[str, int] = {}
        # the targets' sequence numbers judged per sensor (judge_seq): gaps, restarts, numbers out of line
        self.targets_missing = 0
        self.targets_seq_resets = 0
        self.targets_implausible_seq = 0
        self.seq_rate_hz = seq_rate_hz
        self.raw_by_sensor: dict[str, int] = {}  # raw frames received, per sensor (a driver's shutdown waits on it)
        self._last_seq: dict[str, SeqTrack] = {}
        self._sensor: dict[str, SensorState] = {}
        self._lock = threading.Lock()
        self._sub = None

    def start(self) -> "Monitor":
        # its counts are final once stop returns: the messages zenoh still held are handed over first
        self._sub = as_transport(self.session).declare_subscriber(f"{self.bus.prefix}/**", self._on_sample)
        return self

    def stop(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            self.on_message(str(sample.key_expr), sample.payload.to_bytes())
        except Exception:  # nothing a sender puts may raise in zenoh's callback: counted instead
            with self._lock:
                self.failed_messages += 1

    def _state(self, sensor: str) -> "SensorState":
        st = self._sensor.get(sensor)
        if st is None:
            if len(self._sensor) >= self.MAX_SENSORS:  # keys of garbage: bounded
                self._sensor.clear()
            st = self._sensor[sensor] = SensorState()
        return st

    def on_message(self, key: str, payload: bytes) -> None:
        """One message of ``<prefix>/**`` (what the zenoh callback hands over)."""
        topic = key.rsplit("/", 1)[-1]
        if topic not in MONITORED_TOPICS:
            topic = "other"
        self._count(topic, key, len(payload))
        if topic == "health":
            self._on_health(key, payload)
        elif topic == "tracks":
            self._on_tracks(key, payload)
        elif topic == "targets":
            self._on_targets(key, payload)

    def _count(self, topic: str, key: str, size: int) -> None:
        with self._lock:
            self.count[topic] += 1
            self.bytes[topic] += size
            if topic == "raw":
                sensor = key.rsplit("/", 2)[-2]
                if sensor not in self.raw_by_sensor and len(self.raw_by_sensor) >= self.MAX_SENSORS:
                    self.raw_by_sensor.clear()  # keys of garbage: bounded
                self.raw_by_sensor[sensor] = self.raw_by_sensor.get(sensor, 0) + 1

    def truth_at(self, sensor_id: str, timestamp_ns: int) -> list[dict] | None:
        """The true positions a sensor's frame at ``timestamp_ns`` sees (None: no truth):
        the truth's clock starts at ``t0_ns``, or at the sensor's first frame."""
        truth = self.truths.get(sensor_id, self.truth)
        if truth is None:
            return None
        t0_ns = self.t0_ns
        if self.clock_per_sensor:
            with self._lock:
                if len(self._t0_by_sensor) >= self.MAX_SENSORS and sensor_id not in self._t0_by_sensor:
                    self._t0_by_sensor.clear()
                t0_ns = self._t0_by_sensor.setdefault(sensor_id, timestamp_ns)
        return truth.truth(max(0.0, (timestamp_ns - t0_ns) / 1e9))

    def _on_targets(self, key: str, payload: bytes) -> None:
        """A targets message: its sequence number judged, its latency, its score against
        the truth, the sensor's rate; a live line at most once a second per sensor."""
        try:
            msg = self._decode("targets", payload, key)
        except WireError:
            with self._lock:
                self.bad_targets += 1
            return
        truth = self.truth_at(msg.sensor_id, msg.timestamp_ns)
        scored = score_one(truth, msg.targets, self.distance_m) if truth else None
        err = scored.nearest_m[0][np.isfinite(scored.nearest_m[0])] if scored is not None else np.array([])
        now = time.monotonic()
        with self._lock:
            track = self._last_seq.get(msg.sensor_id)
            if track is None and len(self._last_seq) >= self.MAX_SENSORS:  # keys of garbage: bounded
                self._last_seq.clear()
            st = self._state(msg.sensor_id)
            self._last_seq[msg.sensor_id], verdict = judge_seq(track, msg.seq, now, self.seq_rate_hz)
            self.targets_missing += verdict.missing
            self.targets_seq_resets += verdict.resets
            self.targets_implausible_seq += verdict.implausible
            st.missing += verdict.missing
            self.latency_ms.add((msg.published_ns - msg.timestamp_ns) / 1e6)
            self.errors_m.add_many(err)
            if scored is not None:
                self._tally(scored)
            rate_hz, lost = st.frame(msg.timestamp_ns, now)
        if self.live is not None and rate_hz is not False:
            print(live_line(msg, truth, scored, rate_hz, lost) + "   " + self.calibration_tag(msg.sensor_id),
                  file=self.live, flush=True)

    def _on_tracks(self, key: str, payload: bytes) -> None:
        """A tracks message: its largest id, and with a truth the static tracks' errors."""
        try:
            msg = self._decode("tracks", payload, key)
        except WireError:
            with self._lock:
                self.bad_targets += 1
            return
        errors = []
        truth = self.truths.get(msg.sensor_id, self.truth)
        if truth is not None:
            static = [(t["x_m"], t["y_m"]) for t in msg.tracks if t["static"]]
            for tg in truth.targets:
                if tg.velocity_m_s or not static:
                    continue
                x, y = polar_to_xy(tg.range_m, np.radians(tg.angle_deg))
                d = min(float(np.hypot(sx - x, sy - y)) for sx, sy in static)
                if d < 1.0:
                    errors.append(d)
        with self._lock:
            if msg.sensor_id not in self.track_ids and len(self.track_ids) >= self.MAX_SENSORS:
                self.track_ids.clear()  # keys of garbage: bounded
            self.track_ids[msg.sensor_id] = max([self.track_ids.get(msg.sensor_id, 0)]
                                                + [t["track_id"] for t in msg.tracks])
            self.static_track_errors_m.add_many(errors)

    def calibration_tag(self, sensor_id: str) -> str:
        """What a live line says of a sensor's calibration: ``calibrated`` or ``uncalibrated``,
        in capitals with the leakage seen (or ``calibration does not fit``)."""
        front = self.front_end.get(sensor_id) or {"calibrated": self.calibration or False}
        if not leakage_shown(front):
            return "calibrated" if front.get("calibrated") else "uncalibrated"
        return "calibration does not fit (leakage seen)" if front.get("calibrated") else "UNCALIBRATED (leakage seen)"

    def _tally(self, scored) -> None:
        """Add one frame's score (``_lock`` held)."""
        found = np.isfinite(scored.error_m[0])
        self.detected += found
        for i in np.flatnonzero(found).tolist():
            self.detection_errors_m[i].add(float(scored.error_m[0, i]))
        self.false_targets += int(scored.false_targets[0])
        self.targets += int(scored.targets[0])
        self.frames_scored += 1

    def score(self) -> Score | None:
        """The honest score so far (medians from the histograms: within 2 %), None without a truth."""
        if self.truth is None:
            return None
        with self._lock:
            n = self.frames_scored
            rate = self.detected / n if n else np.full(len(self.detected), np.nan)
            med = np.array([np.nan if h.count == 0 else h.percentile(50) for h in self.detection_errors_m])
            near = self.errors_m.percentile(50)
            return Score(self.distance_m, n, rate, med, self.false_targets / n if n else np.nan,
                         self.targets / n if n else np.nan, np.nan if near is None else near)

    def _on_health(self, key: str, payload: bytes) -> None:
        """A node's health: the sensor frames its link lost (the driver's: the DONE counter's
        gaps), whether its frames are calibrated (the quantizer's) and whether the localizer
        sees its front end (``front_end``); a sensor whose front end shows is warned about once."""
        if not (b'"node":"source"' in payload or b'"front_end"' in payload or b'"calibrated"' in payload):
            return
        try:
            msg = self._decode("health", payload, key)
        except WireError:
            with self._lock:
                self.bad_health += 1
            return
        warn = None
        with self._lock:
            if msg.node == "source":
                self._state(msg.sensor_id).link_lost = msg.drops
            front = self.front_end.get(msg.sensor_id)
            if front is None:
                if len(self.front_end) >= self.MAX_SENSORS:  # keys of garbage: bounded
                    self.front_end.clear()
                front = self.front_end[msg.sensor_id] = {"calibrated": self.calibration or False, "checked": 0,
                                                         "leakage": 0}
            if "calibrated" in msg.extra:
                front["calibrated"] = msg.extra["calibrated"] or False
            fe = msg.extra.get("front_end")
            if isinstance(fe, dict):
                front["checked"], front["leakage"] = int(fe.get("checked", 0)), int(fe.get("leakage", 0))
            if (leakage_shown(front) and msg.sensor_id not in self.warnings
                    and len(self.warnings) < self.MAX_SENSORS):
                warn = self.warnings[msg.sensor_id] = front_end_warning(msg.sensor_id, front)
        if warn is not None and self.live is not None:
            print(f"warning: {warn}", file=self.live, flush=True)

    def rates_hz(self) -> dict[str, float]:
        """Each sensor's targets per second, over its first and last targets' timestamps."""
        with self._lock:
            return {sid: round((st.targets - 1) / ((st.last_ns - st.first_ns) / 1e9), 2)
                    for sid, st in sorted(self._sensor.items()) if st.targets > 1 and st.last_ns > st.first_ns}


@dataclass
class SensorState:
    """What the monitor keeps of one sensor: its live line's time (monotonic s) and the
    targets messages since, the gaps in their sequence numbers, the frames its link lost
    (its driver's health), its targets messages in all, their first and last timestamps (ns)."""

    line_s: float = 0.0
    since_line: int = 0
    missing: int = 0
    link_lost: int = 0
    targets: int = 0
    first_ns: int = 0
    last_ns: int = 0

    def frame(self, timestamp_ns: int, now: float) -> tuple[float | None | bool, int]:
        """One targets message at ``timestamp_ns``: (its rate since the last live line, or
        None, or False when no live line is due; the frames lost)."""
        self.since_line += 1
        self.targets += 1
        if self.targets == 1:
            self.first_ns = timestamp_ns
        self.last_ns = timestamp_ns
        if now - self.line_s < 1.0:
            return False, 0
        rate_hz = (self.since_line - 1) / (now - self.line_s) if self.line_s and self.since_line > 1 else None
        self.line_s, self.since_line = now, 1
        return rate_hz, self.missing + self.link_lost


def score_one(truth: list[dict], targets: list[dict], distance_m: float):
    """:func:`~pipeline.dsp.score.score_frames` of one frame's targets against the truth."""
    return score_frames(np.array([[t["range_m"] for t in truth]]), np.array([[t["angle_deg"] for t in truth]]),
                        np.array([[t["range_m"] for t in targets]]).reshape(1, -1),
                        np.array([[t["angle_deg"] for t in targets]]).reshape(1, -1), distance_m)


def live_line(msg, truth: list[dict] | None, scored, rate_hz: float | None, lost: int) -> str:
    """A sensor's live line: its targets, the truth and the errors, its rate and losses."""
    line = f"{msg.sensor_id} #{msg.seq:<5d} targets " + ("  ".join(
        f"({t['range_m']:5.1f} m, {t['angle_deg']:+6.1f}°)" for t in msg.targets) or "none")
    if truth:
        line += "   truth " + "  ".join(f"({t['range_m']:5.1f} m, {t['angle_deg']:+6.1f}°)" for t in truth)
        line += "   error m " + " ".join("miss" if not np.isfinite(e) else f"{e:.2f}" for e in scored.error_m[0])
        if scored.false_targets[0]:
            line += f" +{scored.false_targets[0]} false"
    return line + "   " + (f"{rate_hz:4.1f} frames/s, " if rate_hz is not None else "") + f"{lost} lost"
