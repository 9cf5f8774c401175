"""The zenoh nodes of the stream: a source node (any frame source -> raw frames), the
quantize-with-dither node and the localizer node. The node machinery (queues, health,
liveliness) is in :mod:`pipeline.node`; the math they call is in
:mod:`pipeline.quantize` and :mod:`pipeline.decode`: a node decodes payloads, groups
them into batches and publishes what the math returns.
"""

from __future__ import annotations

import logging
import threading
from collections import defaultdict
from dataclasses import dataclass, field, replace
import time
from typing import Callable

import numpy as np
import zenoh

from radar_driver.model import RadarConfig
from radar_driver.source import FrameSource, RawFrame

from .bus import BusConfig
from .decode import Algo, DecoderConfig, DitherUnavailable, decode_batch
from .errors import ParameterError
from .localize import DEFAULT_PFA
from .node import Node, ProcessingNode, run_nodes
from .quantize import QuantizerConfig, quantize_frames, sensor_dither_seed
from .wire import (
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
                self.stats[sid].drops = st.get("dropped", 0)
        super()._publish_health()


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
                seed = int(q.dither_seed)
                for j, i in enumerate(idx):
                    m = msgs[i]
                    out = QuantizedFrameMsg(sensor, m.seq, m.timestamp_ns, m.config_id, q.bits, q.alpha,
                                            float(q.delta[j]), seed, q.codes[j])
                    self.publish(sensor, "quantized", encode_quantized(out), "application/octet-stream")


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

    def _decode(self, sensor: str, key: str, payload: bytes) -> QuantizedFrameMsg | RawFrameMsg:
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
            if isinstance(msg, QuantizedFrameMsg):
                groups[(msg.config_id, msg.bits, msg.dithered)].append(msg)
            else:
                groups[(msg.config_id, 0, False)].append(msg)
        for (config_id, bits, _), msgs in groups.items():
            frames = quantized_batch(msgs) if bits else np.stack([m.data for m in msgs])
            try:
                det = decode_batch(frames, self._configs[config_id], self.config.k, self.config.decoder())
            except DitherUnavailable as exc:
                for m in msgs:
                    self.count_error(m.sensor_id, DitherUnavailable(
                        f"frame {m.seq} from {self.bus.key(m.sensor_id, self.in_topic)}: {exc}; run the localizer "
                        "with --fallback-pbp to decode such frames with PBP"))
                continue
            for i, m in enumerate(msgs):
                now = time.time_ns()
                out = TargetsMsg(m.sensor_id, m.seq, m.timestamp_ns, config_id, str(self.config.algo), self.config.k,
                                 self.config.source, det.frame(i), published_ns=now, auto_k=self.config.auto_k)
                self.publish(m.sensor_id, "targets", out.to_json(), "application/json")
                with self._lock:
                    self.stats[m.sensor_id].latency_ms.append((now - m.timestamp_ns) / 1e6)
