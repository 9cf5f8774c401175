"""Sources of raw frames: one interface, whatever makes the frames.

A :class:`FrameSource` is used with ``with`` and iterated: it yields :class:`RawFrame`
objects (sensor id, sequence number, timestamp, the frame Gamma and the sensor's ramp
counters) until it ends or is asked to stop. Three implementations:

- :class:`~radar_driver.session.SensorSession`: a K-MD2, real or simulated, on any
  pyserial URL;
- :class:`SimulatedSource` (here): simulated sensors in this process, no serial link;
  the same scene, front end, noise and 12-bit ADC as the simulated K-MD2, so that with
  the same seed both give the same frames;
- ``replay.source.RecordingSource``: the raw frames of an MCAP recording.

One source node (``pipeline.nodes.stream.SourceNode``) publishes any of them, and one contract
test suite (``tests/test_sources.py``) runs over all three.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Iterator, Protocol, runtime_checkable

import numpy as np

from .errors import ConfigError
from .options import nonneg_int, option, pos_int
from .limits import check_sensor_id
from .profile import DEFAULT_PROFILE
from .scene import SIM_RATE_HZ, SimScene, check_sim_rate, frame_ramp_times_s


@dataclass(frozen=True, eq=False)
class RawFrame:
    """One frame of one sensor: ``data`` (M, 2) complex64 in full-scale units
    (measurement m = ramp r x 256 + sample k, antenna), the source's sequence number
    ``seq`` (per sensor, from 0), ``timestamp_ns`` (host clock when the frame's first
    ramp arrived), the sensor's ramp counters (empty when unknown, e.g. from a
    recording) and the id of the radar configuration that made it."""

    sensor_id: str
    seq: int
    timestamp_ns: int
    data: np.ndarray
    counters: tuple[int, ...] = ()
    config_id: int = 0


@runtime_checkable
class FrameSource(Protocol):
    """What every source of raw frames offers.

    ``with source: for frame in source.frames(limit): ...``. :meth:`frames` ends when
    ``limit`` frames were yielded, when the source has no more (a recording's end, a
    simulated source's frame budget) or after :meth:`request_stop` (safe from another
    thread). :meth:`close` is idempotent. :meth:`stats` counts per sensor: at least
    ``frames`` (yielded) and ``dropped`` (frames the source knows it lost)."""

    def __enter__(self) -> "FrameSource": ...

    def __exit__(self, *exc) -> None: ...

    def frames(self, limit: int | None = None) -> Iterator[RawFrame]: ...

    def request_stop(self) -> None: ...

    def close(self) -> None: ...

    def stats(self) -> dict[str, dict[str, int]]: ...


class StoppableSource:
    """The life cycle shared by sources without a port to close: a context manager whose
    :meth:`request_stop` (safe from another thread) and :meth:`close` set ``_stop``,
    which :meth:`frames` watches."""

    def __init__(self) -> None:
        self._stop = threading.Event()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def request_stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        self._stop.set()

    def frames(self, limit: int | None = None) -> Iterator[RawFrame]:
        raise NotImplementedError

    def __iter__(self) -> Iterator[RawFrame]:
        return self.frames()


def frame_batches(source: FrameSource, limit: int | None = None) -> Iterator[list[RawFrame]]:
    """The frames of any source in the groups it makes them (one tick of many simulated
    sensors at once: a batch for vectorized work downstream), or one by one."""
    batches = getattr(source, "frame_batches", None)
    if batches is not None:
        return batches(limit)
    return ([f] for f in source.frames(limit))


#: how simulated sensors send: all in one burst per frame period, or spread evenly over it
SEND_MODES = ("burst", "spread")
#: with ``send="spread"``, the sensors are sent in groups this far apart (at most), s
SPREAD_SLOT_S = 2e-3


def send_groups(sensors: int, rate_hz: float, send: str) -> list[range]:
    """The groups of sensor indices sent together in a frame period: all at once
    (``burst``, or ``rate_hz`` 0), or ``spread`` over the period in groups SPREAD_SLOT_S
    apart (group j due j / len(groups) of a period after the first)."""
    slots = 1 if send == "burst" or not rate_hz else max(1, min(sensors, int(round(1.0 / (rate_hz * SPREAD_SLOT_S)))))
    return [range(j * sensors // slots, (j + 1) * sensors // slots) for j in range(slots)]


@dataclass(frozen=True)
class SimSourceConfig:
    """In-process simulated sensors.

    scene: what they see (targets, noise, radar configuration). sensors: how many;
    their ids are ``<id_prefix>0``, ``<id_prefix>1``, ... rate_hz: frames per second
    per sensor (0 = as fast as they are read; moving targets then move on the
    simulated K-MD2's nominal time base). seed: sensor i draws its noise as a simulated
    K-MD2 with seed ``seed + i`` does. frames: frames per sensor, then the source ends
    (None = never). send: "burst" (every sensor's frame of a period at its start, as
    sensors on one clock) or "spread" (the sensors' send times spread evenly over the
    period, in groups SPREAD_SLOT_S apart, as independent sensors send)."""

    scene: SimScene
    sensors: int = option(1, "simulated sensors at once", parse=pos_int)
    id_prefix: str = option("sim", "sensor ids are <prefix>0, <prefix>1, ...")
    rate_hz: float = SIM_RATE_HZ
    seed: int = option(0, "noise seed (sensor i draws as a K-MD2 of seed + i)", parse=nonneg_int)
    frames: int | None = option(None, "frames per sensor, then stop (with --recording: frames in all)", parse=pos_int)
    send: str = option("burst", "burst: every sensor's frame at the start of each period (sensors on one clock); "
                       "spread: the sensors' send times spread evenly over the period, in groups 2 ms apart "
                       "(independent sensors)", choices=SEND_MODES)

    def __post_init__(self) -> None:
        if self.send not in SEND_MODES:
            raise ConfigError(f"send={self.send!r} must be one of {list(SEND_MODES)}")
        if not (isinstance(self.sensors, int) and 1 <= self.sensors <= 4096):
            raise ConfigError(f"sensors={self.sensors!r} must be an integer in [1, 4096]")
        check_sim_rate(self.rate_hz, zero="0 = as fast as read")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ConfigError(f"seed={self.seed!r} must be an integer >= 0")
        if self.frames is not None and not (isinstance(self.frames, int) and self.frames >= 1):
            raise ConfigError(f"frames={self.frames!r} must be an integer >= 1 or None")
        check_sensor_id(f"{self.id_prefix}{self.sensors - 1}")  # the longest id (radar_driver.limits)

    @property
    def sensor_ids(self) -> list[str]:
        return [f"{self.id_prefix}{i}" for i in range(self.sensors)]


@dataclass
class _SimSensorStats:
    frames: int = 0
    dropped: int = 0


class SimulatedSource(StoppableSource):
    """Simulated sensors in this process (see :class:`SimSourceConfig`): every frame
    period, one frame per sensor of the scene's ramps through the paper's model and the
    scene's front end, with sensor noise and the 12-bit ADC of the simulated K-MD2, made for a group of sensors at
    once (:meth:`frame_batches`). Paced on the monotonic clock; a period whose first group
    comes more than a frame period late is counted in ``late_ticks``. A frame's timestamp
    is the time its group was due (or made, when late)."""

    def __init__(self, config: SimSourceConfig):
        super().__init__()
        self.config = config
        self.radar = config.scene.radar
        self.late_ticks = 0
        self.elapsed_s = 0.0
        self._ids = config.sensor_ids
        self._config_id = self.radar.config_id()
        self._stats = {sid: _SimSensorStats() for sid in self._ids}
        self._rngs = [np.random.default_rng(np.random.SeedSequence(config.seed + i, spawn_key=(0,)))
                      for i in range(config.sensors)]
        self._tick = 0  # the frame period being made
        self._slot = 0  # its next group of sensors
        self._pending: list[RawFrame] = []  # made, not yet handed out (a read stopped at a limit)
        self._clean: tuple[int, np.ndarray] | None = None  # the tick's noiseless ramps
        self._slots = send_groups(config.sensors, config.rate_hz, config.send)

    def stats(self) -> dict[str, dict[str, int]]:
        return {sid: {"frames": st.frames, "dropped": st.dropped} for sid, st in self._stats.items()}

    def _make(self, k: int, sensors: range, ts: int) -> list[RawFrame]:
        """Frame ``k`` of ``sensors``: the tick's clean ramps (targets through the front end)
        plus each sensor's noise (drawn from its own generator as :meth:`SimScene.noise`
        draws it), through the ADC, the group at once and in place on its real and
        imaginary parts."""
        cfg, scene = self.config, self.config.scene
        rpf, n = self.radar.ramps_per_frame, self.radar.samples_per_ramp
        ramp_index = k * rpf + np.arange(rpf)
        if self._clean is None or self._clean[0] != k:
            t_s = frame_ramp_times_s(k, np.arange(rpf), cfg.rate_hz, self.radar.ramp_interval_s)
            self._clean = (k, scene.clean_ramps(t_s))  # (R, N, 2)
        clean = self._clean[1]
        parts = np.empty((len(sensors), rpf, 2, n, 2))  # (S, R, re/im, N, antenna)
        if scene.noise_std:
            for j, i in enumerate(sensors):
                self._rngs[i].standard_normal(out=parts[j])  # scene.noise's draw: ramp by ramp, re then im
            parts *= scene.noise_std
        else:
            parts[:] = 0.0
        parts[:, :, 0] += clean.real
        parts[:, :, 1] += clean.imag
        DEFAULT_PROFILE.radc.round_trip_parts(parts)
        data = np.empty((len(sensors), rpf, n, 2), dtype=np.complex64)
        data.real, data.imag = parts[:, :, 0], parts[:, :, 1]
        data = data.reshape(len(sensors), rpf * n, 2)
        counters = tuple(int(c) for c in ramp_index)
        ids, config_id = self._ids, self._config_id
        return [RawFrame(ids[i], k, ts, data[j], counters, config_id) for j, i in enumerate(sensors)]

    def _groups(self) -> Iterator[list[RawFrame]]:
        """Groups of frames as they fall due, until the frame budget or a stop."""
        cfg = self.config
        period = 1.0 / cfg.rate_hz if cfg.rate_hz else 0.0
        t0 = time.monotonic() - self._tick * period
        t0_ns = time.time_ns() - int((time.monotonic() - t0) * 1e9)  # the wall clock of t0
        try:
            while not self._stop.is_set():
                if self._slot >= len(self._slots):
                    self._tick, self._slot = self._tick + 1, 0
                k, j = self._tick, self._slot
                if cfg.frames is not None and k >= cfg.frames:
                    return
                due = t0 + (k + j / len(self._slots)) * period
                delay = due - time.monotonic()
                if period and delay > 0:
                    if self._stop.wait(delay):
                        return
                    ts = t0_ns + int((due - t0) * 1e9)
                else:
                    if period and j == 0 and delay < -period:
                        self.late_ticks += 1
                    ts = time.time_ns()
                self._slot = j + 1
                yield self._make(k, self._slots[j], ts)
        finally:
            self.elapsed_s = time.monotonic() - t0

    def frame_batches(self, limit: int | None = None) -> Iterator[list[RawFrame]]:
        """The frames in the groups they are made (see :class:`SimSourceConfig` ``send``),
        at most ``limit`` frames in all (a cut group's rest is handed out by the next read)."""
        yielded = 0
        groups = self._groups()
        try:
            while limit is None or yielded < limit:
                if self._pending:
                    batch, self._pending = self._pending, []
                else:
                    batch = next(groups, None)
                    if batch is None:
                        return
                if limit is not None and yielded + len(batch) > limit:
                    batch, self._pending = batch[:limit - yielded], batch[limit - yielded:]
                for f in batch:
                    self._stats[f.sensor_id].frames += 1
                yielded += len(batch)
                yield batch
        finally:
            groups.close()  # sets elapsed_s

    def frames(self, limit: int | None = None) -> Iterator[RawFrame]:
        for batch in self.frame_batches(limit):
            yield from batch
