"""The tracker of many sensors: each sensor's tracks (:mod:`pipeline.dsp.track`) stepped
frame by frame, bounded and forgotten with the sensor, static tracks refined on their
last frames' codes decoded together (:mod:`pipeline.dsp.integrate`), and the tracks JSON
(:class:`pipeline.wire.TracksMsg`) published after each frame."""

from __future__ import annotations

import queue
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from radar_driver.model import RadarConfig

from pipeline.dsp.gate import RangeGate
from pipeline.dsp.integrate import concat_frames, integrate
from pipeline.dsp.quantize import QuantizedFrames
from pipeline.dsp.track import (SensorTracks, TrackerConfig, assignment_solver, assign, innovations, late,
                    measurement_sigmas, measurements, report, step_tracks)
from pipeline.wire import TracksMsg


@dataclass(frozen=True)
class Integration:
    """How static tracks are refined (:mod:`pipeline.dsp.integrate`): the localizer's count
    ``k`` (with ``pfa``: the most, counted with that false-alarm probability; None:
    exactly k) and range ``gate``; a refinement at most every ``every_s`` seconds a sensor
    (the decode of T frames costs about T frames' decodes), the position held between."""

    k: int = 2
    gate: RangeGate | None = None
    pfa: float | None = None
    every_s: float = 1.0

    @classmethod
    def of_localizer(cls, config, every_s: float = 1.0) -> "Integration":
        """The integration of a :class:`pipeline.nodes.stream.LocalizerConfig`'s decoder."""
        return cls(config.k, config.gate, config.pfa if config.auto_k else None, every_s)


@dataclass
class _Window:
    """A sensor's last frames for integration: (timestamp_ns, one-frame QuantizedFrames,
    radar) in time order, and when it was last decoded."""

    frames: deque = field(default_factory=deque)
    last_refine_ns: int | None = None


#: frames a sensor's integration window holds at most (60 s at 20 Hz)
MAX_WINDOW_FRAMES = 1200
#: frames a refinement needs at least: on fewer, the filter's average of the track's past
#: targets is the better position (chamber, README: 5 frames integrated 0.061 m, the filter
#: 0.051 m; 10 frames 0.043 m)
MIN_INTEGRATED_FRAMES = 10


class Tracker:
    """Tracks of many sensors: :meth:`step` one frame of a sensor, :meth:`forget` a sensor.
    Thread-safe (one lock); ``max_sensors`` bounds the sensors held (the oldest is dropped).
    With ``integration`` and ``config.integrate_s`` > 0, frames given to :meth:`step` are
    kept for ``integrate_s`` seconds and static tracks are refined on them."""

    def __init__(self, config: TrackerConfig = TrackerConfig(), integration: Integration | None = None,
                 max_sensors: int = 4096, background: bool = False):
        """``background``: refinements run in a thread of their own (the live localizer: a
        refinement decodes T frames at once, which its worker must not wait for; the kernels
        release the GIL), a sensor's result applied to its static tracks when it is ready;
        else in :meth:`step`, so a re-processing's tracks do not depend on timing."""
        self.config = config
        self.integration = integration if config.integrate_s > 0 else None
        self.max_sensors = max_sensors
        assignment_solver()  # now, not in the first frame's time
        self._sensors: dict[str, SensorTracks] = {}
        self._windows: dict[str, _Window] = {}
        self._lock = threading.Lock()
        self.background = background
        #: the background refinements waiting (at most one a sensor: ``_pending``), and their thread
        self._jobs: queue.Queue = queue.Queue()
        self._pending: set[str] = set()
        self._thread: threading.Thread | None = None
        self.refinements_skipped = 0  # due while the sensor's previous one still ran
        self.refinement_errors = 0
        #: integration decodes run and the seconds they took (for the health and benchmarks)
        self.refinements = 0
        self.refine_s = 0.0

    def state(self, sensor_id: str) -> SensorTracks:
        """The sensor's tracks (created empty)."""
        st = self._sensors.get(sensor_id)
        if st is None:
            if len(self._sensors) >= self.max_sensors:
                gone = next(iter(self._sensors))
                self._sensors.pop(gone)
                self._windows.pop(gone, None)
            st = self._sensors[sensor_id] = SensorTracks()
        return st

    def step(self, sensor_id: str, timestamp_ns: int, range_m, angle_deg, frame: QuantizedFrames | None = None,
             radar: RadarConfig | None = None, statistic_db=None, radial_velocity_mps=None) -> list[dict]:
        """One frame's targets (K,) of ``sensor_id`` at ``timestamp_ns`` (``statistic_db``:
        their detection statistics, dB, or None; ``radial_velocity_mps``: their Doppler,
        modulo the ``radar``'s ambiguity interval, or None): its confirmed tracks
        (:func:`report`). ``frame``: the frame itself (a batch of one) and its ``radar``, for
        the integration of static tracks."""
        now = int(timestamp_ns)
        with self._lock:
            st = self.state(sensor_id)
            if late(st, self.config, now):
                return report(st, st.last_ns)
            restart = st.last_ns is not None and not 0 <= now - st.last_ns <= self.config.max_gap_s * 1e9
            step_tracks(st, self.config, now, np.atleast_1d(range_m), np.atleast_1d(angle_deg),
                        None if statistic_db is None else np.atleast_1d(statistic_db),
                        None if radial_velocity_mps is None or radar is None else np.atleast_1d(radial_velocity_mps),
                        None if radar is None else radar.velocity_ambiguity_mps)
            if self.integration is not None:
                self._integrate(sensor_id, st, now, frame, radar, restart)
            return report(st, now)

    def _integrate(self, sensor_id: str, st: SensorTracks, now: int, frame, radar, restart: bool) -> None:
        win = self._windows.get(sensor_id)
        if win is None:
            win = self._windows[sensor_id] = _Window()
        if restart:
            win.frames.clear()
        if frame is not None and radar is not None and frame.dithered:
            win.frames.append((now, frame, radar))
        horizon = now - int(self.config.integrate_s * 1e9)
        while win.frames and (win.frames[0][0] < horizon or len(win.frames) > MAX_WINDOW_FRAMES):
            win.frames.popleft()
        static = np.flatnonzero(st.static)
        if not static.size or not win.frames:
            return
        if win.last_refine_ns is not None and 0 <= now - win.last_refine_ns < self.integration.every_s * 1e9:
            return
        win.last_refine_ns = now
        _, last, radar = win.frames[-1]
        shape = last.codes.shape[1:]
        # the frames like the last one (same radar, M, bits), since each static track became static
        starts = np.maximum(st.static_since_ns[static], horizon)
        jobs = []
        for start in np.unique(starts).tolist():
            parts = [f for t, f, r in win.frames if t >= start and r == radar and f.codes.shape[1:] == shape
                     and f.bits == last.bits]
            if len(parts) >= MIN_INTEGRATED_FRAMES:
                jobs.append((start, parts))
        if not jobs:
            return
        if not self.background:
            for start, parts in jobs:
                self._apply(st, horizon, start, self._refine(parts, radar))
            return
        if sensor_id in self._pending:  # its previous refinement still runs: this one waits for the next due
            self.refinements_skipped += 1
            return
        self._pending.add(sensor_id)
        if self._thread is None:
            self._thread = threading.Thread(target=self._work, name="qradar-integrate", daemon=True)
            self._thread.start()
        self._jobs.put((sensor_id, horizon, radar, jobs))

    def _refine(self, parts: list, radar: RadarConfig):
        """One integration decode (:func:`pipeline.dsp.integrate.integrate`) of ``parts``."""
        t0 = time.perf_counter()
        det = integrate(concat_frames(parts), radar, self.integration.k, self.integration.gate, self.integration.pfa)
        self.refine_s += time.perf_counter() - t0
        self.refinements += 1
        return det

    def _apply(self, st: SensorTracks, horizon: int, start: int, det) -> None:
        """The refined positions of ``det`` (one integrated frame) to the static tracks of
        ``st`` integrated since ``start`` (with the sensor's lock held)."""
        ok = det.present[0] & np.isfinite(det.range_m[0]) & np.isfinite(det.angle_deg[0])
        static = np.flatnonzero(st.static)
        mine = static[np.maximum(st.static_since_ns[static], horizon) == start]
        if not ok.any() or not mine.size:
            return
        sr, sa = measurement_sigmas(det.statistic_db[0][ok], det.angle_deg[0][ok], self.config)
        z, r = measurements(det.range_m[0][ok], det.angle_deg[0][ok], sr, sa)
        d2, logdet = innovations(st.x[mine], st.p[mine], z, r)
        rows, cols = assign(d2, logdet, self.config.gate_chi2)
        st.refined[mine] = np.nan
        st.refined[mine[rows]] = z[cols]

    def _work(self) -> None:
        """The background refinements, one at a time; a sensor forgotten meanwhile gets none."""
        while True:
            job = self._jobs.get()
            if job is None:
                return
            sensor_id, horizon, radar, jobs = job
            try:
                results = [(start, self._refine(parts, radar)) for start, parts in jobs]
            except Exception:  # a refinement that fails leaves the filter's positions: counted, not fatal
                self.refinement_errors += 1
                results = []
            with self._lock:
                self._pending.discard(sensor_id)
                st = self._sensors.get(sensor_id)
                if st is not None:
                    for start, det in results:
                        self._apply(st, horizon, start, det)

    def close(self) -> None:
        """End the background refinements' thread (after the one running)."""
        if self._thread is not None:
            self._jobs.put(None)
            self._thread.join(timeout=10)
            self._thread = None

    def forget(self, sensor_id: str) -> None:
        """Drop a sensor's tracks and frames (an expired sensor)."""
        with self._lock:
            self._sensors.pop(sensor_id, None)
            self._windows.pop(sensor_id, None)

    @property
    def sensors(self) -> list[str]:
        with self._lock:
            return list(self._sensors)


def track_batch(tracker: Tracker, headers, det, frames=None, radar: RadarConfig | None = None,
                published_ns: int = 0) -> list[bytes]:
    """The tracks JSON (:class:`pipeline.wire.TracksMsg`) after each frame of a decoded
    batch, in order: ``headers`` (:class:`pipeline.wire.FrameHeaders`, B frames), ``det``
    their :class:`pipeline.dsp.localize.Detections` (B, K); ``frames`` the batch's
    QuantizedFrames (for integration; raw frames or None: none)."""
    quantized = isinstance(frames, QuantizedFrames)
    present = np.asarray(det.present, dtype=bool)
    stat = np.asarray(det.statistic_db, dtype=float)
    doppler = np.asarray(det.radial_velocity_mps, dtype=float)
    out = []
    seqs, stamps = headers.seq.tolist(), headers.timestamp_ns.tolist()
    for i, sid in enumerate(headers.sensor_id):
        keep = present[i]
        tracks = tracker.step(sid, stamps[i], det.range_m[i][keep], det.angle_deg[i][keep],
                              frames.take(np.array([i])) if quantized else None, radar, stat[i][keep],
                              doppler[i][keep])
        out.append(TracksMsg(sid, seqs[i], stamps[i], tracks, published_ns).to_json())
    return out


def publish_tracks(node, tracker: Tracker, headers, det, frames, radar: RadarConfig) -> None:
    """The localizer node's hook: :func:`track_batch` of a decoded batch, published on
    ``<prefix>/<sensor>/tracks``; a failure is counted (``processing_errors``) and loses
    the tracks of that batch only."""
    try:
        payloads = track_batch(tracker, headers, det, frames, radar, time.time_ns())
    except Exception as exc:  # the targets are out already; the tracks of this batch are lost
        for sid, seq in zip(headers.sensor_id, headers.seq.tolist()):
            node.count(sid, "processing_errors", f"tracks of frame {seq} from {sid}: {type(exc).__name__}: {exc}")
        return
    node.publish_many(headers.sensor_id, "tracks", payloads, "application/json", frames_out=False)
