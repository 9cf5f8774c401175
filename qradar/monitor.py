"""The live monitor of ``qradar run``: counts and sizes per topic, latency and position
error of the targets against the true positions, each sensor's rate and losses, the live lines."""

from __future__ import annotations

import sys
import threading
import time
from collections import defaultdict
from typing import TextIO

import numpy as np
import zenoh

from pipeline.bus.session import BusConfig
from pipeline.nodes.counters import DEFAULT_SEQ_RATE_HZ, SeqTrack, judge_seq
from pipeline.nodes.histogram import LogHistogram
from pipeline.dsp.localize import position_error_m
from pipeline.wire import TOPICS, WireError, decode_health, decode_targets, decode_tracks
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
                 seq_rate_hz: float = DEFAULT_SEQ_RATE_HZ):
        """``t0_ns``: the wall clock at which the truth's time is 0 (a moving target's start);
        with ``clock_per_sensor`` it is each sensor's first frame instead (a simulated K-MD2's
        scene starts moving with its first measured frame, after its driver connected).
        ``seq_rate_hz``: the sensors' frame rate, which bounds what a gap in the targets'
        sequence numbers can count as missing (:func:`~pipeline.nodes.counters.judge_seq`)."""
        self.bus, self.session, self.truth, self.t0_ns = bus, session, truth, t0_ns
        self.clock_per_sensor = clock_per_sensor
        self._t0_by_sensor: dict[str, int] = {}
        self.live = live
        self.count: dict[str, int] = defaultdict(int)
        self.bytes: dict[str, int] = defaultdict(int)
        self.latency_ms = LogHistogram(lo=1e-3, hi=1e6)  # sensor timestamp -> targets published, ms
        self.errors_m = LogHistogram(lo=1e-4, hi=1e4)  # each true target to the nearest estimate, m
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
        # per sensor: [monotonic s of the last live line, targets since, sequence gaps, frames the
        # sensor's link lost (its driver's health), targets in all, first and last timestamp_ns]
        self._sensor: dict[str, list] = {}
        self._lock = threading.Lock()
        self._sub = None

    def start(self) -> "Monitor":
        self._sub = self.session.declare_subscriber(f"{self.bus.prefix}/**", self._on_sample)
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

    def _state(self, sensor: str) -> list:
        st = self._sensor.get(sensor)
        if st is None:
            if len(self._sensor) >= self.MAX_SENSORS:  # keys of garbage: bounded
                self._sensor.clear()
            st = self._sensor[sensor] = [0.0, 0, 0, 0, 0, 0, 0]
        return st

    def on_message(self, key: str, payload: bytes) -> None:
        """One message of ``<prefix>/**`` (what the zenoh callback hands over)."""
        topic = key.rsplit("/", 1)[-1]
        if topic not in MONITORED_TOPICS:
            topic = "other"
        with self._lock:
            self.count[topic] += 1
            self.bytes[topic] += len(payload)
            if topic == "raw":
                sensor = key.rsplit("/", 2)[-2]
                if sensor not in self.raw_by_sensor and len(self.raw_by_sensor) >= self.MAX_SENSORS:
                    self.raw_by_sensor.clear()  # keys of garbage: bounded
                self.raw_by_sensor[sensor] = self.raw_by_sensor.get(sensor, 0) + 1
        if topic == "health":
            self._on_health(key, payload)
            return
        if topic == "tracks":
            self._on_tracks(key, payload)
            return
        if topic != "targets":
            return
        try:
            msg = decode_targets(payload, key)
        except WireError:
            with self._lock:
                self.bad_targets += 1
            return
        t0_ns = self.t0_ns
        if self.clock_per_sensor:
            with self._lock:
                if len(self._t0_by_sensor) >= self.MAX_SENSORS and msg.sensor_id not in self._t0_by_sensor:
                    self._t0_by_sensor.clear()
                t0_ns = self._t0_by_sensor.setdefault(msg.sensor_id, msg.timestamp_ns)
        t_s = max(0.0, (msg.timestamp_ns - t0_ns) / 1e9)
        truth = self.truth.truth(t_s) if self.truth is not None else None
        est_r = np.array([[t["range_m"] for t in msg.targets]])
        est_a = np.array([[t["angle_deg"] for t in msg.targets]])
        err = position_error_m(np.array([[t["range_m"] for t in truth]]), np.array([[t["angle_deg"] for t in truth]]),
                               est_r, est_a)[0] if truth and msg.targets else np.array([])
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
            st[2] += verdict.missing
            self.latency_ms.add((msg.published_ns - msg.timestamp_ns) / 1e6)
            self.errors_m.add_many(err)
            st[1] += 1
            st[4] += 1
            if st[4] == 1:
                st[5] = msg.timestamp_ns
            st[6] = msg.timestamp_ns
            due = now - st[0] >= 1.0
            if due:
                rate_hz = (st[1] - 1) / (now - st[0]) if st[0] and st[1] > 1 else None
                lost = st[2] + st[3]
                st[0], st[1] = now, 1
        if self.live is not None and due:
            line = f"{msg.sensor_id} #{msg.seq:<5d} targets " + "  ".join(
                f"({t['range_m']:5.1f} m, {t['angle_deg']:+6.1f}°)" for t in msg.targets)
            if truth is not None:
                line += "   truth " + "  ".join(f"({t['range_m']:5.1f} m, {t['angle_deg']:+6.1f}°)" for t in truth)
                line += "   error m " + " ".join(f"{e:.2f}" for e in err)
            line += "   " + (f"{rate_hz:4.1f} frames/s, " if rate_hz is not None else "") + f"{lost} lost"
            print(line, file=self.live, flush=True)

    def _on_tracks(self, key: str, payload: bytes) -> None:
        """A tracks message: its largest id, and with a truth the static tracks' errors."""
        try:
            msg = decode_tracks(payload, key)
        except WireError:
            with self._lock:
                self.bad_targets += 1
            return
        errors = []
        if self.truth is not None:
            static = [(t["x_m"], t["y_m"]) for t in msg.tracks if t["static"]]
            for tg in self.truth.targets:
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

    def _on_health(self, key: str, payload: bytes) -> None:
        """A driver's health: the sensor frames its link lost so far (the DONE counter's gaps)."""
        if b'"node":"source"' not in payload:
            return
        try:
            msg = decode_health(payload, key)
        except WireError:
            with self._lock:
                self.bad_health += 1
            return
        with self._lock:
            self._state(msg.sensor_id)[3] = msg.drops

    def rates_hz(self) -> dict[str, float]:
        """Each sensor's targets per second, over its first and last targets' timestamps."""
        with self._lock:
            return {sid: round((st[4] - 1) / ((st[6] - st[5]) / 1e9), 2)
                    for sid, st in sorted(self._sensor.items()) if st[4] > 1 and st[6] > st[5]}
