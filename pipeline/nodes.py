"""The zenoh nodes of the stream: a source node (any frame source -> raw frames), the
quantize-with-dither node and the localizer node. The node machinery (queues, health,
liveliness) is in :mod:`pipeline.node`; the math they call is in
:mod:`pipeline.quantize` and :mod:`pipeline.decode`: a node decodes payloads, groups
them into batches and publishes what the math returns.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np
import zenoh

from radar_driver.model import RadarConfig
from radar_driver.source import FrameSource, RawFrame

from .bus import BusConfig
from .decode import Algo, DecoderConfig, DitherUnavailable, decode_batch
from .errors import ParameterError, PipelineError
from .localize import DEFAULT_PFA
from .node import Node, ProcessingNode, run_nodes
from .quantize import MAX_BITS, QuantizerConfig, packed_size, quantize_frames, sensor_dither_seed
from .wire import (
    HEADER_LEN,
    QUANT_HEADER_LEN,
    QuantizedFrameMsg,
    RawFrameMsg,
    TargetsMsg,
    WireError,
    check_sensor_id,
    decode_quantized,
    decode_raw,
    encode_quantized,
    encode_raw,
    quantized_batch,
)

log = logging.getLogger("qradar.node")

__all__ = ["LocalizeNode", "LocalizerConfig", "QuantizeNode", "SourceNode", "run_nodes"]


class SourceNode(Node):
    """Any :class:`~radar_driver.source.FrameSource` (a K-MD2 over serial, simulated
    sensors in this process, a recording) -> ``<prefix>/<sensor>/raw``. The source is
    read in its own thread; its drop counters go into the health of each sensor.
    ``frames``: stop after that many frames in all (None = when the source ends);
    ``on_frame`` sees every frame after it is published."""

    name = "source"

    def __init__(self, bus: BusConfig, source: FrameSource, session: zenoh.Session | None = None,
                 frames: int | None = None, on_frame: Callable[[RawFrame], None] | None = None, **kw):
        super().__init__(bus, session, **kw)
        self.source = source
        self.frames_limit = frames
        self.on_frame = on_frame
        self.done = threading.Event()

    def _start(self) -> None:
        self._spawn(self._read_loop, "reader", after=self.done.set)  # done once an error is recorded

    def _read_loop(self) -> None:
        with self.source:
            for frame in self.source.frames(self.frames_limit):  # ends at request_stop()
                check_sensor_id(frame.sensor_id)
                msg = RawFrameMsg(frame.sensor_id, frame.seq, frame.timestamp_ns, frame.config_id, frame.data)
                self.publish(frame.sensor_id, "raw", encode_raw(msg), "application/octet-stream")
                if self.on_frame is not None:
                    self.on_frame(frame)

    def _stopping(self) -> None:
        self.source.request_stop()  # the reader ends at the next frame and closes the source itself

    def health_extra(self, sensor_id: str) -> dict:
        return {"source": self.source.stats().get(sensor_id, {})}

    def _publish_health(self) -> None:
        stats = self.source.stats()
        with self._lock:
            for sid, st in stats.items():
                self.sensor_stats(sid).drops = st.get("dropped", 0)
        super()._publish_health()


#: the largest |Re| or |Im| of a raw sample a node accepts, full-scale units (the ADC's
#: full scale is 1; beyond this a frame is refused as invalid, not quantized)
MAX_SAMPLE = 1e4


def radar_configs(radar: RadarConfig, max_ramps: int) -> dict[int, RadarConfig]:
    """The announced configurations: ``radar`` with 1..max_ramps ramps per frame, by config id."""
    if not (isinstance(max_ramps, int) and max_ramps >= 1):
        raise ParameterError(f"max_ramps={max_ramps!r} must be an integer >= 1")
    return {c.config_id(): c for c in (replace(radar, ramps_per_frame=r) for r in range(1, max_ramps + 1))}


def frame_lengths(configs: dict[int, RadarConfig], topic: str) -> frozenset[int]:
    """Every payload length a raw or quantized frame of these configurations can have, bytes."""
    ms = {c.n_measurements for c in configs.values()}
    if topic == "raw":
        return frozenset(HEADER_LEN + 16 * m for m in ms)
    return frozenset(QUANT_HEADER_LEN + packed_size(4 * m, b) for m in ms for b in range(1, MAX_BITS + 1))


def bad_samples(frames: np.ndarray) -> np.ndarray:
    """(B,) True where a frame (B, M, 2) has a sample that is not finite or beyond MAX_SAMPLE."""
    parts = frames.view(np.float32 if frames.dtype == np.complex64 else np.float64)
    return ~(np.abs(parts) <= MAX_SAMPLE).reshape(frames.shape[0], -1).all(axis=1)  # NaN fails <=


class FrameNode(ProcessingNode):
    """A processing node of radar frames: it refuses, before copying, payloads whose
    length no announced configuration (``radar`` with 1..max_ramps ramps) has, and
    checks each decoded frame's sensor id, config id and M."""

    def __init__(self, bus: BusConfig, radar: RadarConfig, max_ramps: int, session: zenoh.Session | None, **kw):
        super().__init__(bus, session, **kw)
        self._configs = radar_configs(radar, max_ramps)
        self._lengths = frame_lengths(self._configs, self.in_topic)

    def admit(self, key: str, n_bytes: int) -> str | None:
        if n_bytes in self._lengths:
            return None
        return (f"{n_bytes} bytes, a length no announced radar configuration has "
                f"({len(self._configs)} configs, {min(self._lengths)}-{max(self._lengths)} bytes)")

    def decode(self, sensor: str, key: str, payload: bytes) -> QuantizedFrameMsg | RawFrameMsg | None:
        """The frame, or None when it is counted as a decode error or an invalid frame."""
        try:
            msg = decode_quantized(payload, key) if self.in_topic == "quantized" else decode_raw(payload, key)
            if msg.sensor_id != sensor:
                raise WireError(f"frame from {key}: sensor id {msg.sensor_id!r} does not match the key")
        except WireError as exc:
            self.count(sensor, "decode_errors", exc)
            return None
        radar = self._configs.get(msg.config_id)
        m = msg.codes.shape[0] if isinstance(msg, QuantizedFrameMsg) else msg.data.shape[0]
        if radar is None:
            self.count(sensor, "invalid_frames", f"frame {msg.seq} from {key}: unknown radar config id "
                       f"{msg.config_id:#010x}")
        elif m != radar.n_measurements:
            self.count(sensor, "invalid_frames", f"frame {msg.seq} from {key}: M={m} but its radar config "
                       f"has M={radar.n_measurements}")
        else:
            return msg
        return None

    def valid_raw(self, msgs: list[RawFrameMsg]) -> tuple[list[RawFrameMsg], np.ndarray | None]:
        """The frames whose samples are finite and within MAX_SAMPLE, stacked (B, M, 2)
        complex128; the others are counted as invalid."""
        frames = np.stack([m.data for m in msgs])
        bad = bad_samples(frames)
        if bad.any():
            for i in np.flatnonzero(bad):
                m = msgs[i]
                self.count(m.sensor_id, "invalid_frames", f"frame {m.seq} from "
                           f"{self.bus.key(m.sensor_id, self.in_topic)}: a sample is not finite or beyond "
                           f"{MAX_SAMPLE:g} full scale")
            keep = np.flatnonzero(~bad)
            msgs, frames = [msgs[i] for i in keep], frames[keep]
        return msgs, (frames.astype(np.complex128) if msgs else None)

    def publish_each(self, items) -> None:
        """Publish (sensor, topic, payload-maker, encoding) one by one; a failure loses that
        message only (processing_errors)."""
        for sensor, topic, make, encoding in items:
            try:
                self.publish(sensor, topic, make(), encoding)
            except (PipelineError, zenoh.ZError) as exc:
                self.count(sensor, "processing_errors", f"{self.bus.key(sensor, topic)}: {exc}")


def isolate(compute: Callable[[list], Any], items: list, on_error: Callable[[Any, Exception], None]) -> list:
    """[(items, result)]: ``compute(items)`` on the whole group, or, if that raises, on each
    item alone, so one bad frame loses only itself (``on_error(item, exc)``)."""
    try:
        return [(items, compute(items))]
    except Exception as exc:
        if len(items) == 1:
            on_error(items[0], exc)
            return []
    out = []
    for it in items:
        try:
            out.append(([it], compute([it])))
        except Exception as exc:
            on_error(it, exc)
    return out


class QuantizeNode(FrameNode):
    """``<prefix>/*/raw`` -> dithered b-bit quantization -> ``<prefix>/<sensor>/quantized``.

    radar, max_ramps: the announced configurations; other frames are refused."""

    name = "quantize"
    in_topic = "raw"

    def __init__(self, bus: BusConfig, config: QuantizerConfig, session: zenoh.Session | None = None,
                 radar: RadarConfig | None = None, max_ramps: int = 16, **kw):
        super().__init__(bus, radar or RadarConfig(), max_ramps, session, **kw)
        self.config = config

    def process(self, batch) -> None:
        by_m: dict[int, list[RawFrameMsg]] = defaultdict(list)
        for sensor, key, payload, _ in batch:
            msg = self.decode(sensor, key, payload)
            if msg is not None:
                by_m[msg.data.shape[0]].append(msg)
        for msgs in by_m.values():
            msgs, frames = self.valid_raw(msgs)
            if not msgs:
                continue
            # one dither seed per sensor: quantize per sensor group, vectorized inside
            by_sensor: dict[str, list[int]] = defaultdict(list)
            for i, m in enumerate(msgs):
                by_sensor[m.sensor_id].append(i)
            for sensor, idx in by_sensor.items():
                group = [(msgs[i], frames[i]) for i in idx]
                seed = sensor_dither_seed(self.config.dither_seed, sensor)

                def compute(g, seed=seed):
                    return quantize_frames(np.stack([f for _, f in g]), self.config, [m.seq for m, _ in g],
                                           dither_seed=seed)

                for part, q in isolate(compute, group, self._failed):
                    self.publish_each(
                        (sensor, "quantized", functools.partial(encode_quantized, QuantizedFrameMsg(
                            sensor, m.seq, m.timestamp_ns, m.config_id, q.bits, q.alpha, float(q.delta[j]),
                            int(q.dither_seed), q.codes[j])), "application/octet-stream")
                        for j, (m, _) in enumerate(part))

    def _failed(self, item, exc: Exception) -> None:
        m = item[0]
        self.count(m.sensor_id, "processing_errors", f"frame {m.seq} from "
                   f"{self.bus.key(m.sensor_id, 'raw')}: {type(exc).__name__}: {exc}")


@dataclass(frozen=True)
class LocalizerConfig:
    """k: targets per frame. algo: the decoder (:class:`~pipeline.decode.Algo`). source:
    "quantized" or "raw" (full-resolution baseline). radar: the base configuration;
    frames of any whole number of ramps are accepted (their config ids are derived
    from it)."""

    k: int = 2
    algo: Algo = Algo.PBP
    source: str = "quantized"
    radar: RadarConfig = field(default_factory=RadarConfig)
    max_ramps: int = 16
    fallback_pbp: bool = False
    auto_k: bool = False
    pfa: float = DEFAULT_PFA

    def __post_init__(self) -> None:
        if not (isinstance(self.k, int) and 1 <= self.k <= self.radar.samples_per_ramp):
            raise ParameterError(f"K={self.k!r} must be an integer in [1, {self.radar.samples_per_ramp}]")
        object.__setattr__(self, "algo", self.decoder().algo)  # validates the name, K auto and pfa
        if self.algo == Algo.CML and self.k > self.radar.samples_per_ramp // 2:
            raise ParameterError(f"K={self.k} (or --max-targets) must be at most N/2 = "
                                 f"{self.radar.samples_per_ramp // 2} for cml")
        if self.source not in ("quantized", "raw"):
            raise ParameterError(f"source={self.source!r} must be quantized or raw")
        if self.source == "raw" and self.algo == Algo.QIHT:
            raise ParameterError(f"algo={self.algo!r} decodes quantized frames; the raw baseline uses pbp or cml")

    def decoder(self) -> DecoderConfig:
        return DecoderConfig(algo=self.algo, fallback_pbp=self.fallback_pbp, auto_k=self.auto_k, pfa=self.pfa)

    def known_configs(self) -> dict[int, RadarConfig]:
        return radar_configs(self.radar, self.max_ramps)


class LocalizeNode(FrameNode):
    """``<prefix>/*/quantized`` (or raw) -> PBP -> ``<prefix>/<sensor>/targets`` (JSON).

    Latency (health and ``published_ns``) runs from the frame's sensor timestamp to the
    publication of its targets."""

    name = "localize"

    def __init__(self, bus: BusConfig, config: LocalizerConfig, session: zenoh.Session | None = None, **kw):
        self.in_topic = config.source
        super().__init__(bus, config.radar, config.max_ramps, session, **kw)
        self.config = config

    def process(self, batch) -> None:
        groups: dict[tuple, list] = defaultdict(list)
        for sensor, key, payload, _ in batch:
            msg = self.decode(sensor, key, payload)
            if isinstance(msg, QuantizedFrameMsg):
                groups[(msg.config_id, msg.bits, msg.dithered)].append((msg, None))
            elif msg is not None:
                groups[(msg.config_id, 0, False)].append((msg, None))
        for (config_id, bits, _), items in groups.items():
            if not bits:  # raw frames: finite samples only
                msgs, frames = self.valid_raw([m for m, _ in items])
                items = list(zip(msgs, frames)) if msgs else []
            if not items:
                continue
            radar = self._configs[config_id]

            def compute(g, radar=radar, bits=bits):
                frames = quantized_batch([m for m, _ in g]) if bits else np.stack([f for _, f in g])
                return decode_batch(frames, radar, self.config.k, self.config.decoder())

            for part, det in isolate(compute, items, self._failed):
                for i, (m, _) in enumerate(part):
                    now = time.time_ns()
                    out = TargetsMsg(m.sensor_id, m.seq, m.timestamp_ns, config_id, str(self.config.algo),
                                     self.config.k, self.config.source, det.frame(i), published_ns=now,
                                     auto_k=self.config.auto_k)
                    self.publish_each([(m.sensor_id, "targets", out.to_json, "application/json")])
                    self.record_latency(m.sensor_id, (now - m.timestamp_ns) / 1e6)

    def _failed(self, item, exc: Exception) -> None:
        m = item[0]
        key = self.bus.key(m.sensor_id, self.in_topic)
        if isinstance(exc, DitherUnavailable):
            self.count(m.sensor_id, "invalid_frames", f"frame {m.seq} from {key}: {exc}; run the localizer "
                       "with --fallback-pbp to decode such frames with PBP")
        else:
            self.count(m.sensor_id, "processing_errors", f"frame {m.seq} from {key}: {type(exc).__name__}: {exc}")
