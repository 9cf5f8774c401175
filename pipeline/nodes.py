"""Zenoh nodes: sources of raw frames (the driver, an in-process simulator), the
quantize-with-dither node and the localizer node.

A processing node subscribes with a wildcard (``<prefix>/*/raw``, ...) and so serves
many sensors at once. zenoh's callback only copies the payload into a bounded queue
(a full queue drops the newest sample and counts it in ``drops``); a worker thread
takes batches from the queue and runs the vectorized math on them. Data publishers
use ``CongestionControl.BLOCK``: when the network is slower than the data, a
publisher waits instead of dropping, so back-pressure reaches the node's bounded
queue, where every drop is counted. Health goes out with ``DROP``: it is periodic and
a lost one is replaced a second later.

Every node declares a liveliness token and publishes ``<prefix>/<sensor>/health``
once a second for every sensor it has seen. A malformed payload is counted
(``decode_errors``), logged and skipped; the node keeps running.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import zlib
from collections import defaultdict, deque
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np
import zenoh

from radar_driver.model import RadarConfig

from .bus import BusConfig
from .errors import ParameterError, PipelineError
from .decode import DecoderConfig, DitherUnavailable, decode
from .localize import localize
from .quantize import QuantizerConfig, dequantize, quantize_frames, unit_dither
from .wire import (
    HealthMsg,
    QuantizedFrameMsg,
    RawFrameMsg,
    TargetsMsg,
    WireError,
    decode_quantized,
    decode_raw,
    encode_quantized,
    encode_raw,
)

log = logging.getLogger("qradar.node")

LATENCY_WINDOW = 2000


@dataclass
class SensorStats:
    frames_in: int = 0
    frames_out: int = 0
    drops: int = 0
    decode_errors: int = 0
    bytes_in: int = 0
    bytes_out: int = 0
    latency_ms: deque = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))
    # for rates between two health messages
    _last_bytes: tuple[int, int, float] = (0, 0, 0.0)


def percentile_ms(values: Iterable[float], q: float) -> float | None:
    v = np.fromiter(values, dtype=float)
    return round(float(np.percentile(v, q)), 3) if v.size else None


class Node:
    """Base of every node: zenoh session, liveliness, health, publishers, statistics.

    ``session=None`` opens a session from ``bus`` (closed on stop); a given session is
    shared and left open.
    """

    name = "node"

    def __init__(self, bus: BusConfig, session: zenoh.Session | None = None, health_period_s: float = 1.0):
        self.bus = bus
        self._own_session = session is None
        self.session = session if session is not None else bus.open()
        self.health_period_s = health_period_s
        self.stats: dict[str, SensorStats] = defaultdict(SensorStats)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._token = None
        self._last_error_log = 0.0
        self.errors: list[BaseException] = []

    # -- life cycle -----------------------------------------------------------------------
    def start(self) -> "Node":
        self._token = self.session.liveliness().declare_token(self.bus.liveliness_key(self.name))
        self._spawn(self._health_loop, "health")
        self._start()
        return self

    def _start(self) -> None:
        """Subclass hook: declare subscribers, spawn workers."""

    def _spawn(self, target: Callable[[], None], what: str) -> None:
        def run():
            try:
                target()
            except BaseException as exc:  # a dead worker is reported, never silent
                if not self._stop.is_set():
                    log.exception("%s %s thread failed", self.name, what)
                    self.errors.append(exc)

        t = threading.Thread(target=run, name=f"{self.name}-{what}", daemon=True)
        t.start()
        self._threads.append(t)

    def stop(self, timeout_s: float = 5.0) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        self._stopping()
        for t in self._threads:
            t.join(timeout_s)
        self._publish_health()  # last counters
        for pub in self._publishers.values():
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

    # -- publishing -----------------------------------------------------------------------------
    def publish(self, sensor_id: str, topic: str, payload: bytes, encoding: str) -> None:
        key = self.bus.key(sensor_id, topic)
        pub = self._publishers.get(key)
        if pub is None:
            pub = self.session.declare_publisher(key, encoding=zenoh.Encoding(encoding),
                                                 congestion_control=zenoh.CongestionControl.BLOCK)
            self._publishers[key] = pub
        pub.put(payload)
        with self._lock:
            st = self.stats[sensor_id]
            st.frames_out += 1
            st.bytes_out += len(payload)

    def count_error(self, sensor_id: str, exc: Exception) -> None:
        with self._lock:
            self.stats[sensor_id].decode_errors += 1
        now = time.monotonic()
        if now - self._last_error_log > 1.0:  # at most one line a second
            self._last_error_log = now
            log.warning("%s: %s (counted in decode_errors; node keeps running)", self.name, exc)

    # -- health ------------------------------------------------------------------------------------
    def _health_loop(self) -> None:
        while not self._stop.wait(self.health_period_s):
            self._publish_health()

    def health_extra(self, sensor_id: str) -> dict:
        return {}

    def _publish_health(self) -> None:
        now_ns = time.time_ns()
        with self._lock:
            snapshot = []
            for sensor, st in self.stats.items():
                b_in, b_out, t_prev = st._last_bytes
                dt = (now_ns - t_prev) / 1e9 if t_prev else self.health_period_s
                msg = HealthMsg(
                    node=self.name, sensor_id=sensor, timestamp_ns=now_ns, frames_in=st.frames_in,
                    frames_out=st.frames_out, drops=st.drops, decode_errors=st.decode_errors,
                    latency_ms={"p50": percentile_ms(st.latency_ms, 50), "p99": percentile_ms(st.latency_ms, 99)},
                    bytes_in_per_s=(st.bytes_in - b_in) / max(dt, 1e-9),
                    bytes_out_per_s=(st.bytes_out - b_out) / max(dt, 1e-9),
                )
                st._last_bytes = (st.bytes_in, st.bytes_out, now_ns)
                snapshot.append(msg)
        for msg in snapshot:
            msg.extra = self.health_extra(msg.sensor_id)
            if msg.sensor_id == "_unknown":
                continue
            try:
                self.session.put(self.bus.key(msg.sensor_id, "health"), msg.to_json(),
                                 encoding=zenoh.Encoding.APPLICATION_JSON,
                                 congestion_control=zenoh.CongestionControl.DROP)
            except zenoh.ZError as exc:
                log.debug("health publish failed: %s", exc)

    def totals(self) -> dict[str, int]:
        with self._lock:
            out = {"frames_in": 0, "frames_out": 0, "drops": 0, "decode_errors": 0, "bytes_in": 0, "bytes_out": 0}
            for st in self.stats.values():
                for k in out:
                    out[k] += getattr(st, k)
            return out


class ProcessingNode(Node):
    """Subscribes ``<prefix>/*/<in_topic>``; callback -> bounded queue -> batches -> :meth:`process`."""

    in_topic = "raw"

    def __init__(self, bus: BusConfig, session: zenoh.Session | None = None, queue_size: int = 512,
                 batch_max: int = 64, health_period_s: float = 1.0):
        super().__init__(bus, session, health_period_s)
        if queue_size < 1 or batch_max < 1:
            raise ParameterError(f"queue_size={queue_size} and batch_max={batch_max} must be >= 1")
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        self.batch_max = batch_max
        self._subscriber = None

    def subscription(self) -> str:
        """The key expression this node listens to."""
        return self.bus.wildcard(self.in_topic)

    def _start(self) -> None:
        self._subscriber = self.session.declare_subscriber(self.subscription(), self._on_sample)
        self._spawn(self._work_loop, "worker")

    def _stopping(self) -> None:
        if self._subscriber is not None:
            self._subscriber.undeclare()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        """zenoh's thread: copy and enqueue, nothing else."""
        key = str(sample.key_expr)
        sensor = self.bus.sensor_of(key) or "_unknown"
        payload = sample.payload.to_bytes()
        try:
            self._queue.put_nowait((sensor, key, payload, time.time_ns()))
        except queue.Full:
            with self._lock:
                self.stats[sensor].drops += 1
            now = time.monotonic()
            if now - self._last_error_log > 1.0:
                self._last_error_log = now
                log.warning("%s: queue full, dropped a sample of %s (counted in drops)", self.name, key)
        with self._lock:
            st = self.stats[sensor]
            st.frames_in += 1
            st.bytes_in += len(payload)

    def _work_loop(self) -> None:
        # after stop, drain what was queued before the subscriber went away
        while not (self._stop.is_set() and self._queue.empty()):
            try:
                first = self._queue.get(timeout=0.1)
            except queue.Empty:
                self.on_idle()
                continue
            batch = [first]
            while len(batch) < self.batch_max:
                try:
                    batch.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            self.process(batch)

    def on_idle(self) -> None:
        """Called by the worker when no sample came for 0.1 s."""

    def process(self, batch: list[tuple[str, str, bytes, int]]) -> None:
        raise NotImplementedError


def sensor_dither_seed(seed: int, sensor_id: str) -> int:
    """Dither seed of one sensor: ``seed * 2**32 + crc32(sensor_id)`` (mod 2**64), so that
    sensors with the same frame numbers get independent dithers."""
    return (int(seed) * 2**32 + zlib.crc32(sensor_id.encode())) % 2**64


class QuantizeNode(ProcessingNode):
    """``<prefix>/*/raw`` -> dithered b-bit quantization -> ``<prefix>/<sensor>/quantized``."""

    name = "quantize"
    in_topic = "raw"

    def __init__(self, bus: BusConfig, config: QuantizerConfig, session: zenoh.Session | None = None, **kw):
        super().__init__(bus, session, **kw)
        self.config = config

    def process(self, batch) -> None:
        decoded: list[RawFrameMsg] = []
        for sensor, key, payload, _ in batch:
            try:
                msg = decode_raw(payload, key)
                if msg.sensor_id != sensor:
                    raise WireError(f"raw frame from {key}: sensor id {msg.sensor_id!r} does not match the key")
                decoded.append(msg)
            except WireError as exc:
                self.count_error(sensor, exc)
        by_m: dict[int, list[RawFrameMsg]] = defaultdict(list)
        for msg in decoded:
            by_m[msg.data.shape[0]].append(msg)
        for msgs in by_m.values():
            frames = np.stack([m.data for m in msgs]).astype(np.complex128)
            # one dither seed per sensor: quantize per sensor group, vectorized inside
            by_sensor: dict[str, list[int]] = defaultdict(list)
            for i, m in enumerate(msgs):
                by_sensor[m.sensor_id].append(i)
            for sensor, idx in by_sensor.items():
                q = quantize_frames(frames[idx], self.config, [msgs[i].seq for i in idx],
                                    dither_seed=sensor_dither_seed(self.config.dither_seed, sensor))
                for j, i in enumerate(idx):
                    m = msgs[i]
                    out = QuantizedFrameMsg(sensor, m.seq, m.timestamp_ns, m.config_id, q.bits, q.alpha,
                                            float(q.delta[j]), q.dither_seed, q.codes[j])
                    self.publish(sensor, "quantized", encode_quantized(out), "application/octet-stream")


@dataclass(frozen=True)
class LocalizerConfig:
    """k: targets per frame. algo: "pbp". source: "quantized" or "raw" (full-resolution
    baseline). radar: the base configuration; frames of any whole number of ramps are
    accepted (their config ids are derived from it)."""

    k: int = 2
    algo: str = "pbp"
    source: str = "quantized"
    radar: RadarConfig = field(default_factory=RadarConfig)
    max_ramps: int = 16
    fallback_pbp: bool = False

    def __post_init__(self) -> None:
        if not (isinstance(self.k, int) and 1 <= self.k <= self.radar.samples_per_ramp):
            raise ParameterError(f"K={self.k!r} must be an integer in [1, {self.radar.samples_per_ramp}]")
        DecoderConfig(algo=self.algo)  # validates the name
        if self.source not in ("quantized", "raw"):
            raise ParameterError(f"source={self.source!r} must be quantized or raw")
        if self.source == "raw" and self.algo != "pbp":
            raise ParameterError(f"algo={self.algo!r} decodes quantized frames; the raw baseline uses pbp")

    def decoder(self) -> DecoderConfig:
        return DecoderConfig(algo=self.algo, fallback_pbp=self.fallback_pbp)

    def known_configs(self) -> dict[int, RadarConfig]:
        from dataclasses import replace

        return {c.config_id(): c for c in (replace(self.radar, ramps_per_frame=r)
                                           for r in range(1, self.max_ramps + 1))}


class LocalizeNode(ProcessingNode):
    """``<prefix>/*/quantized`` (or raw) -> PBP -> ``<prefix>/<sensor>/targets`` (JSON).

    Latency (health and ``published_ns``) runs from the frame's sensor timestamp to the
    publication of its targets."""

    name = "localize"

    def __init__(self, bus: BusConfig, config: LocalizerConfig, session: zenoh.Session | None = None, **kw):
        self.in_topic = config.source
        super().__init__(bus, session, **kw)
        self.config = config
        self._configs = config.known_configs()

    def _decode(self, sensor: str, key: str, payload: bytes):
        msg = decode_quantized(payload, key) if self.config.source == "quantized" else decode_raw(payload, key)
        if msg.sensor_id != sensor:
            raise WireError(f"frame from {key}: sensor id {msg.sensor_id!r} does not match the key")
        radar = self._configs.get(msg.config_id)
        if radar is None:
            raise WireError(f"frame from {key}: unknown radar config id {msg.config_id:#010x}")
        m = msg.codes.shape[0] if isinstance(msg, QuantizedFrameMsg) else msg.data.shape[0]
        if m != radar.n_measurements:
            raise WireError(f"frame from {key}: M={m} but its radar config has M={radar.n_measurements}")
        return msg

    def process(self, batch) -> None:
        groups: dict[tuple, list] = defaultdict(list)
        for sensor, key, payload, _ in batch:
            try:
                msg = self._decode(sensor, key, payload)
            except WireError as exc:
                self.count_error(sensor, exc)
                continue
            bits = msg.bits if isinstance(msg, QuantizedFrameMsg) else 0
            dithered = bits > 0 and msg.dithered
            if bits and self.config.algo != "pbp" and not dithered and not self.config.fallback_pbp:
                self.count_error(sensor, DitherUnavailable(
                    f"frame {msg.seq} from {key} is not dithered (alpha 0): {self.config.algo} needs the dither; "
                    "run the localizer with --fallback-pbp to decode such frames with PBP"))
                continue
            groups[(msg.config_id, bits, dithered)].append(msg)
        for (config_id, bits, dithered), msgs in groups.items():
            radar = self._configs[config_id]
            if bits:
                codes = np.stack([m.codes for m in msgs])
                delta = np.array([m.delta for m in msgs])
                z = dequantize(codes, delta, bits)
                xi = None
                if dithered and self.config.algo != "pbp":
                    # regenerate the dither exactly as the quantizer drew it (pipeline.quantize)
                    xi = np.stack([m.alpha * m.delta * unit_dither(m.dither_seed, m.seq, z.shape[1])[0]
                                   for m in msgs])
                det = decode(z, xi, delta, bits, radar, self.config.k, self.config.decoder())
            else:
                z = np.stack([m.data for m in msgs]).astype(np.complex128)
                det = localize(z, radar, self.config.k)
            for i, m in enumerate(msgs):
                now = time.time_ns()
                out = TargetsMsg(m.sensor_id, m.seq, m.timestamp_ns, config_id, self.config.algo, self.config.k,
                                 self.config.source, det.frame(i), published_ns=now)
                self.publish(m.sensor_id, "targets", out.to_json(), "application/json")
                with self._lock:
                    self.stats[m.sensor_id].latency_ms.append((now - m.timestamp_ns) / 1e6)


class DriverNode(Node):
    """A K-MD2 (real or simulated, through the serial driver) -> ``<prefix>/<sensor>/raw``."""

    name = "drive"

    def __init__(self, bus: BusConfig, sensor_id: str, session_config, session: zenoh.Session | None = None,
                 frames: int | None = None, on_frame: Callable | None = None, **kw):
        from radar_driver.session import SensorSession
        from .wire import check_sensor_id

        super().__init__(bus, session, **kw)
        self.sensor_id = check_sensor_id(sensor_id)
        self.sensor = SensorSession(session_config)
        self.radar = session_config.radar()
        self.frames_limit = frames
        self.on_frame = on_frame
        self.done = threading.Event()

    def _start(self) -> None:
        self._spawn(self._read_loop, "reader")

    def _read_loop(self) -> None:
        try:
            with self.sensor:
                for frame in self.sensor.frames(self.frames_limit):  # ends at request_stop()
                    msg = RawFrameMsg(self.sensor_id, frame.seq, frame.timestamp_ns, self.radar.config_id(), frame.data)
                    self.publish(self.sensor_id, "raw", encode_raw(msg), "application/octet-stream")
                    if self.on_frame is not None:
                        self.on_frame(frame)
        finally:
            self.done.set()

    def _stopping(self) -> None:
        self.sensor.request_stop()  # the reader ends at the next frame and closes (GBYE) itself

    def health_extra(self, sensor_id: str) -> dict:
        return {"driver": self.sensor.counters.as_dict()}

    def _publish_health(self) -> None:
        with self._lock:
            self.stats[self.sensor_id].drops = self.sensor.counters.dropped
        super()._publish_health()


class SimSourceNode(Node):
    """In-process simulated sensors, bypassing the serial link: ``n_sensors`` sensors
    ``<id_prefix>0..`` publish raw frames of ``scene`` at ``rate_hz`` each (for
    benchmarks and many-sensor runs). Frames are ADC-quantized like the simulator's."""

    name = "simsource"

    def __init__(self, bus: BusConfig, scene, n_sensors: int = 1, rate_hz: float = 20.0, id_prefix: str = "sim",
                 session: zenoh.Session | None = None, seed: int = 0, frames: int | None = None, **kw):
        super().__init__(bus, session, **kw)
        if n_sensors < 1 or not rate_hz > 0:
            raise ParameterError(f"n_sensors={n_sensors} must be >= 1 and rate_hz={rate_hz} > 0")
        self.scene, self.n, self.rate_hz = scene, n_sensors, rate_hz
        self.sensor_ids = [f"{id_prefix}{i}" for i in range(n_sensors)]
        self._rng = np.random.default_rng(seed)
        self.frames_limit = frames
        self.done = threading.Event()
        self.late_ticks = 0
        self.elapsed_s = 0.0

    def _start(self) -> None:
        self._spawn(self._loop, "source")

    def _loop(self) -> None:
        from radar_driver.protocol import adc_to_complex, complex_to_adc

        radar = self.scene.radar
        rpf, n = radar.ramps_per_frame, radar.samples_per_ramp
        config_id = radar.config_id()
        t0 = time.monotonic()
        k = 0
        try:
            while not self._stop.is_set() and (self.frames_limit is None or k < self.frames_limit):
                due = t0 + k / self.rate_hz
                delay = due - time.monotonic()
                if delay > 0:
                    if self._stop.wait(delay):
                        break
                elif delay < -1.0 / self.rate_hz:
                    self.late_ticks += 1
                t_s = k / self.rate_hz
                clean = np.concatenate([self.scene.clean_ramp(t_s + r / (self.rate_hz * rpf)) for r in range(rpf)])
                noise = self.scene.noise_std * (self._rng.standard_normal((self.n, rpf * n, 2))
                                                + 1j * self._rng.standard_normal((self.n, rpf * n, 2)))
                frames = clean[None] + noise  # (S, M, 2)
                words = complex_to_adc(frames.reshape(self.n * rpf, n, 2)).reshape(self.n * rpf, 2, 2, n)
                data = adc_to_complex(words).reshape(self.n, rpf * n, 2).astype(np.complex64)
                ts = time.time_ns()
                for s, sid in enumerate(self.sensor_ids):
                    self.publish(sid, "raw", encode_raw(RawFrameMsg(sid, k, ts, config_id, data[s])),
                                 "application/octet-stream")
                k += 1
        finally:
            self.elapsed_s = time.monotonic() - t0
            self.done.set()


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
            for nd in started:
                if nd.errors:
                    raise PipelineError(f"node {nd.name} failed: {nd.errors[0]!r}") from nd.errors[0]
    finally:
        for nd in reversed(started):
            nd.stop()
