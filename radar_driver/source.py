"""Sources of raw frames: one interface, whatever makes the frames.

A :class:`FrameSource` is used with ``with`` and iterated: it yields :class:`RawFrame`
objects (sensor id, sequence number, timestamp, the frame Gamma and the sensor's ramp
counters) until it ends or is asked to stop. Three implementations:

- :class:`~radar_driver.session.SensorSession`: a K-MD2, real or simulated, on any
  pyserial URL;
- :class:`SimulatedSource` (here): simulated sensors in this process, no serial link;
  the same scene, noise and 12-bit ADC as the simulated K-MD2, so that with the same
  seed both give the same frames;
- ``replay.source.RecordingSource``: the raw frames of an MCAP recording.

One source node (``pipeline.nodes.SourceNode``) publishes any of them, and one contract
test suite (``tests/test_sources.py``) runs over all three.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Iterator, Protocol, runtime_checkable

import numpy as np

from .errors import ConfigError
from .profile import DEFAULT_PROFILE
from .scene import SimScene, ramp_time_s


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


@dataclass(frozen=True)
class SimSourceConfig:
    """In-process simulated sensors.

    scene: what they see (targets, noise, radar configuration). sensors: how many;
    their ids are ``<id_prefix>0``, ``<id_prefix>1``, ... rate_hz: frames per second
    per sensor (0 = as fast as they are read; moving targets then move on the
    simulated K-MD2's nominal time base). seed: sensor i draws its noise as a simulated
    K-MD2 with seed ``seed + i`` does. frames: frames per sensor, then the source ends
    (None = never)."""

    scene: SimScene
    sensors: int = 1
    id_prefix: str = "sim"
    rate_hz: float = 20.0
    seed: int = 0
    frames: int | None = None

    def __post_init__(self) -> None:
        if not (isinstance(self.sensors, int) and 1 <= self.sensors <= 4096):
            raise ConfigError(f"sensors={self.sensors!r} must be an integer in [1, 4096]")
        if not (np.isfinite(self.rate_hz) and self.rate_hz >= 0):
            raise ConfigError(f"rate_hz={self.rate_hz!r} must be >= 0 (0 = as fast as read)")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ConfigError(f"seed={self.seed!r} must be an integer >= 0")
        if self.frames is not None and not (isinstance(self.frames, int) and self.frames >= 1):
            raise ConfigError(f"frames={self.frames!r} must be an integer >= 1 or None")

    @property
    def sensor_ids(self) -> list[str]:
        return [f"{self.id_prefix}{i}" for i in range(self.sensors)]


@dataclass
class _SimSensorStats:
    frames: int = 0
    dropped: int = 0


class SimulatedSource(StoppableSource):
    """Simulated sensors in this process (see :class:`SimSourceConfig`): every tick,
    one frame per sensor of the scene's ramps through the paper's model, with sensor
    noise and the 12-bit ADC of the simulated K-MD2. Paced on the monotonic clock; a
    tick that comes more than a frame period late is counted in ``late_ticks``."""

    def __init__(self, config: SimSourceConfig):
        super().__init__()
        self.config = config
        self.radar = config.scene.radar
        self.late_ticks = 0
        self.elapsed_s = 0.0
        self._stats = {sid: _SimSensorStats() for sid in config.sensor_ids}
        self._rngs = [np.random.default_rng(np.random.SeedSequence(config.seed + i, spawn_key=(0,)))
                      for i in range(config.sensors)]
        self._tick = 0  # frames made per sensor
        self._next_sensor = 0  # where a read that stopped mid-tick resumes
        self._tick_data: tuple | None = None

    def stats(self) -> dict[str, dict[str, int]]:
        return {sid: {"frames": st.frames, "dropped": st.dropped} for sid, st in self._stats.items()}

    def frames(self, limit: int | None = None) -> Iterator[RawFrame]:
        cfg, scene = self.config, self.config.scene
        rpf, n = self.radar.ramps_per_frame, self.radar.samples_per_ramp
        ramp_rate_hz = cfg.rate_hz * rpf
        config_id = self.radar.config_id()
        ids = cfg.sensor_ids
        t0 = time.monotonic() - (self._tick / cfg.rate_hz if cfg.rate_hz else 0.0)
        yielded = 0
        try:
            while not self._stop.is_set():
                if self._next_sensor >= len(ids):  # the tick is done for every sensor
                    self._tick, self._next_sensor, self._tick_data = self._tick + 1, 0, None
                k = self._tick
                if cfg.frames is not None and k >= cfg.frames:
                    return
                if self._tick_data is None:  # a new tick: wait for its time, then the scene's ramps
                    if cfg.rate_hz:
                        delay = t0 + k / cfg.rate_hz - time.monotonic()
                        if delay > 0:
                            if self._stop.wait(delay):
                                return
                        elif delay < -1.0 / cfg.rate_hz:
                            self.late_ticks += 1
                    ramp_index = k * rpf + np.arange(rpf)
                    clean = scene.clean_ramps(ramp_time_s(ramp_index, ramp_rate_hz))  # (R, N, 2)
                    self._tick_data = (tuple(int(c) for c in ramp_index), clean, time.time_ns())
                counters, clean, ts = self._tick_data
                i = self._next_sensor
                data = DEFAULT_PROFILE.radc.round_trip(clean + scene.noise(rpf, self._rngs[i])).reshape(rpf * n, 2)
                self._stats[ids[i]].frames += 1
                self._next_sensor = i + 1
                yield RawFrame(ids[i], k, ts, data.astype(np.complex64), counters, config_id)
                yielded += 1
                if limit is not None and yielded >= limit:
                    return
        finally:
            self.elapsed_s = time.monotonic() - t0

