"""The nodes of the stream: a source node (any frame source -> raw frames), the
quantize-with-dither node and the localizer node. The node machinery is in
:mod:`pipeline.nodes.runtime` (transport, liveliness, health) and :mod:`pipeline.nodes.intake`
(queues, budgets, batches); how each kind of frame decodes is in
:mod:`pipeline.nodes.frame_codec`; the math they call is in
:mod:`pipeline.dsp.quantize` and :mod:`pipeline.dsp.decode`: a node decodes payloads, groups
them into batches and publishes what the math returns.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field, fields
from typing import Any, Callable

import numpy as np
import zenoh

from radar_driver.model import RadarConfig
from radar_driver.source import FrameSource, RawFrame, frame_batches

from pipeline.bus.session import BusConfig
from pipeline.dsp.calibration import Calibration
from pipeline.dsp.dither import load_kernel as load_dither_kernel
from pipeline.dsp.decode import DEFAULT_ALGO, Algo, Decoder, DecoderConfig, DitherUnavailable
from pipeline.errors import CalibrationError, ParameterError
from pipeline.nodes.front_end import FrontEndCheck
from pipeline.nodes.frame_codec import (CODECS, MAX_SAMPLE, FrameCodec, bad_samples, check_frames, codec_for,
                                        radar_configs)
from pipeline.dsp.gate import RangeGate
from pipeline.nodes.intake import ProcessingNode, QueuedFrame
from pipeline.dsp.localize import DEFAULT_PFA, Detections
from pipeline.dsp.noise import NoiseTracker
from pipeline.dsp.quantize import AUTO_ALPHA, QuantizedFrames, QuantizerConfig, quantize_frames, sensor_dither_seeds
from pipeline.nodes.runtime import Node, run_nodes
from pipeline.dsp.track import TrackerConfig
from pipeline.nodes.tracker import Integration, Tracker, publish_tracks
from pipeline.nodes.transport import Transport
from pipeline.wire import FrameHeaders, encode_targets_batch

log = logging.getLogger("qradar.node")

#: cml's warm start: a full search every this many frames of a sensor (LocalizerConfig); 1 = a
#: full search on every frame, the default: a warm frame's targets depend on how the node
#: batched the sensor's earlier frames (timing), and live runs are compared target for target
DEFAULT_FULL_SEARCH_EVERY = 1

__all__ = ["LocalizeNode", "LocalizerConfig", "QuantizeNode", "SourceNode", "run_nodes"]


class SourceNode(Node):
    """Any :class:`~radar_driver.source.FrameSource` (a K-MD2 over serial, simulated
    sensors in this process, a recording) -> ``<prefix>/<sensor>/raw``, and with a
    ``quantizer`` (edge quantization) -> ``<prefix>/<sensor>/quantized``: the sensor's
    process quantizes with the same per-sensor dither seed rule and options as the
    quantize node, so its 1-bit frames are bit for bit the quantize node's. ``raw_every``:
    publish the raw frames whose seq is a multiple of it too (default: every one without a
    quantizer, none with one; 0 = none). The source is read in its own thread, in the
    groups it makes frames (one vectorized quantization per group); its drop counters go
    into the health of each sensor. ``frames``: stop after that many frames in all (None
    = when the source ends); ``on_frame`` sees every frame after it is published."""

    name = "source"
    role = "sensor"

    def __init__(self, bus: BusConfig, source: FrameSource, session: zenoh.Session | Transport | None = None,
                 frames: int | None = None, on_frame: Callable[[RawFrame], None] | None = None,
                 quantizer: QuantizerConfig | None = None, raw_every: int | None = None,
                 calibration: Calibration | None = None, **kw):
        raw_every = (0 if quantizer is not None else 1) if raw_every is None else raw_every
        if not (isinstance(raw_every, int) and raw_every >= 0) or (quantizer is None and not raw_every):
            raise ParameterError(f"raw_every={raw_every!r} must be an integer >= 0, and >= 1 without edge "
                                 "quantization (else nothing is published)")
        super().__init__(bus, session, **kw)
        self.source = source
        self.frames_limit = frames
        self.on_frame = on_frame
        self.quantizer = quantizer
        self.calibration = calibration
        if calibration is not None and quantizer is None:
            raise ParameterError("a calibration is applied where frames are quantized: give a quantizer too")
        self.raw_every = raw_every
        self.noise = noise_tracker(quantizer, getattr(source, "radar", None))
        self._source_stats: dict[str, dict[str, int]] = {}
        self.done = threading.Event()

    @property
    def topics(self) -> list[str]:
        """The topics it publishes (:meth:`_publish_batch`): raw (``raw_every``), quantized (edge
        quantization)."""
        return [t for t, on in (("raw", self.raw_every), ("quantized", self.quantizer is not None)) if on]

    def _start(self) -> None:
        self._spawn(self._read_loop, "reader", after=self.done.set)  # done once an error is recorded

    def _read_loop(self) -> None:
        with self.source:
            for batch in frame_batches(self.source, self.frames_limit):  # ends at request_stop()
                self._publish_batch(batch)
                if self.on_frame is not None:
                    for frame in batch:
                        self.on_frame(frame)

    def _publish_batch(self, batch: list[RawFrame]) -> None:
        by_m: dict[int, list[RawFrame]] = defaultdict(list)
        for f in batch:
            by_m[f.data.shape[0]].append(f)
        for group in by_m.values():
            headers = FrameHeaders([f.sensor_id for f in group],  # ids checked by the encoders
                                   np.array([f.seq for f in group], dtype=np.uint64),
                                   np.array([f.timestamp_ns for f in group], dtype=np.int64),
                                   np.array([f.config_id for f in group], dtype=np.uint32))
            data = np.stack([f.data for f in group])
            if self.raw_every:
                keep = np.flatnonzero(headers.seq % np.uint64(self.raw_every) == 0)
                if keep.size:
                    raw = headers.take(keep)
                    self.publish_many(raw.sensor_id, "raw", CODECS["raw"].encode(raw, data[keep]), OCTETS)
            if self.quantizer is not None:
                quantize_and_publish(self, self.quantizer, headers, data, "raw", self.calibration, self.noise)

    def _stopping(self) -> None:
        self.source.request_stop()  # the reader ends at the next frame and closes the source itself

    def health_extra(self, sensor_id: str) -> dict:
        extra = {"source": self._source_stats.get(sensor_id, {})}
        if self.quantizer is not None:  # edge quantization: whether its frames are calibrated, as the quantizer's
            extra["calibrated"] = self.calibration.source if self.calibration is not None else False
        if self.noise is not None:
            extra.update(self.noise.health(sensor_id))
        return extra

    def forget(self, sensor_id: str) -> None:
        super().forget(sensor_id)
        if self.noise is not None:
            self.noise.forget(sensor_id)

    def _publish_health(self, part: int | None = None) -> None:
        stats = self._source_stats = self.source.stats()  # once per publication, not per sensor
        with self._lock:
            for sid, st in stats.items():
                self.sensor_stats(sid).drops = st.get("dropped", 0)
        super()._publish_health(part)


OCTETS = "application/octet-stream"


def noise_tracker(config: QuantizerConfig | None, radar: RadarConfig | None) -> NoiseTracker | None:
    """The per-sensor noise estimate a quantizer with ``alpha="auto"`` needs (None for a
    fixed alpha: nothing is estimated)."""
    if config is None or config.alpha != AUTO_ALPHA:
        return None
    return NoiseTracker((radar or RadarConfig()).samples_per_ramp)


def quantize_and_publish(node: Node, config: QuantizerConfig, headers: FrameHeaders, data: np.ndarray,
                         topic: str, calibration: Calibration | None = None,
                         noise: NoiseTracker | None = None) -> None:
    """Quantize frames (B, M, 2) of many sensors in one vectorized call, each with its
    sensor's dither seed, and publish them on ``quantized``. Frames whose samples are not
    finite or beyond MAX_SAMPLE are refused (``invalid_frames``); a failure of the maths
    loses only the frames it fails on (:func:`isolate`). With a ``calibration``, each
    frame's front end is removed first (:mod:`pipeline.dsp.calibration`); a frame of a sensor
    or config id it has no entry for is counted (``invalid_frames``), never quantized as
    it came. With ``alpha="auto"`` the ``noise`` tracker estimates each sensor's noise
    from its frames (after the calibration) and alpha follows it
    (:func:`pipeline.dsp.noise.auto_alpha`); the node publishes both in the sensor's health."""
    bad = bad_samples(data)
    for i in np.flatnonzero(bad).tolist():
        node.count(headers.sensor_id[i], "invalid_frames", f"frame {int(headers.seq[i])} from "
                   f"{node.bus.key(headers.sensor_id[i], topic)}: a sample is not finite or beyond "
                   f"{MAX_SAMPLE:g} full scale")
    keep = np.flatnonzero(~bad)
    if not keep.size:
        return
    frames = (data if keep.size == len(data) else data[keep]).astype(np.complex128)  # one copy when all are kept
    kept = headers.take(keep)
    if calibration is not None:
        frames, ok = calibration.apply(frames, kept.sensor_id, kept.config_id)
        for i in np.flatnonzero(~ok).tolist():
            node.count(kept.sensor_id[i], "invalid_frames", f"frame {int(kept.seq[i])} from "
                       f"{node.bus.key(kept.sensor_id[i], topic)}: no calibration in {calibration.source} for "
                       f"sensor {kept.sensor_id[i]!r}, config id {int(kept.config_id[i]):#010x}, M = {frames.shape[1]}")
        if not ok.all():
            good = np.flatnonzero(ok)
            if not good.size:
                return
            frames, kept = frames[good], kept.take(good)
    seed = sensor_dither_seeds(config.dither_seed, kept.sensor_id)
    if config.alpha == AUTO_ALPHA and noise is None:
        raise ParameterError("alpha 'auto' needs a NoiseTracker (pipeline.nodes.stream.noise_tracker)")

    def compute(idx):
        sigma = None
        if config.alpha == AUTO_ALPHA:  # (inside: a frame the estimate fails on loses only itself)
            ids = [kept.sensor_id[i] for i in idx.tolist()]
            sigma = noise.update(ids, frames[idx])
        q = quantize_frames(frames[idx], config, kept.seq[idx], dither_seed=seed[idx], noise_sigma=sigma)
        if sigma is not None:
            noise.set_alpha(ids, q.alpha)
        return q

    def failed(i, exc):
        node.count(kept.sensor_id[i], "processing_errors", f"frame {int(kept.seq[i])} from "
                   f"{node.bus.key(kept.sensor_id[i], topic)}: {type(exc).__name__}: {exc}")

    for idx, q in isolate(compute, np.arange(keep.size), failed):
        part = kept.take(idx)
        node.publish_many(part.sensor_id, "quantized", CODECS["quantized"].encode(part, q), OCTETS)


#: how long a frame node's worker waits at most, once a frame is queued, for a full batch
#: while frames keep coming (a 1-ms lull ends the wait), s. Measured (bench_stream, 60 s):
#: 5 ms with a 3-ms lull carried fewer sensors within p99 <= 20 ms than 2 ms with 1 ms
#: (PBP edge 131 against 150; qiht 10, not 17): the wait itself is latency.
BATCH_LINGER_S = 0.002

class FrameNode(ProcessingNode):
    """A processing node of radar frames: it refuses, before copying, payloads whose
    length no announced configuration (``radar`` with 1..max_ramps ramps) has, and
    checks each decoded frame's sensor id, config id and M. Its worker waits up to
    BATCH_LINGER_S after a frame for others while they keep coming, so sensors sending at
    their own times share a vectorized call (whose fixed cost, ~1 ms, would otherwise be
    paid per frame)."""

    batch_linger_s = BATCH_LINGER_S

    def __init__(self, bus: BusConfig, radar: RadarConfig, max_ramps: int, session: zenoh.Session | Transport | None,
                 **kw):
        super().__init__(bus, session, **kw)
        self.codec: FrameCodec = codec_for(self.in_topic)
        self._configs = radar_configs(radar, max_ramps)
        self._lengths = self.codec.lengths({c.n_measurements for c in self._configs.values()})

    def admit(self, key: str, n_bytes: int) -> str | None:
        if n_bytes in self._lengths:
            return None
        return (f"{n_bytes} bytes, a length no announced radar configuration has "
                f"({len(self._configs)} configs, {min(self._lengths)}-{max(self._lengths)} bytes)")

    def decode(self, batch: list[QueuedFrame]) -> tuple[list, list[str]]:
        """Decode a batch of queued frames with the input's codec, in one vectorized call per
        length: the groups of frames whose sensor id matches the key, whose config id is
        announced and whose M is that configuration's (:func:`check_frames`), each with the
        keys of its frames (in order). The others are counted (decode_errors, invalid_frames)."""
        keys = [item.key for item in batch]
        out, refused = check_frames(self.codec, self._configs, [item.payload for item in batch], keys,
                                    [item.sensor for item in batch])
        for i, kind, why in refused:
            self.count(batch[i].sensor, kind, why)
        return out, keys


def take_detections(det: Detections, index) -> Detections:
    """The detections of frames ``index`` of a batch."""
    return Detections(*(getattr(det, f.name)[index] for f in fields(Detections)))


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
    role = "quantizer"
    in_topic = "raw"

    def __init__(self, bus: BusConfig, config: QuantizerConfig, session: zenoh.Session | Transport | None = None,
                 radar: RadarConfig | None = None, max_ramps: int = 16, calibration: Calibration | None = None,
                 calibration_required: bool = False, **kw):
        """``calibration_required``: a sensor whose first frame the ``calibration`` has no
        entry for (its id, config id, M) is a wrong set-up: a CalibrationError in
        :attr:`errors`, which ends a run (``qradar run``); else such frames are counted
        (``invalid_frames``) and dropped, and the node goes on."""
        super().__init__(bus, radar or RadarConfig(), max_ramps, session, **kw)
        self.config = config
        self.calibration = calibration
        self.calibration_required = calibration_required and calibration is not None
        self._checked: set[str] = set()  # sensors whose first frame was checked against the calibration
        self.noise = noise_tracker(config, radar)

    def process(self, batch: list[QueuedFrame]) -> None:
        groups, _ = self.decode(batch)
        for g in groups:  # frames of one M, of any sensors: one vectorized quantization
            if self.calibration_required:
                self._check_calibration(g.headers, g.data.shape[1])
            quantize_and_publish(self, self.config, g.headers, g.data, "raw", self.calibration, self.noise)

    def _check_calibration(self, headers: FrameHeaders, m: int) -> None:
        """At each sensor's first frame: the calibration has an entry for it, or the node fails."""
        for i, sid in enumerate(headers.sensor_id):
            if sid in self._checked:
                continue
            self._checked.add(sid)
            why = self.calibration.mismatch(sid, int(headers.config_id[i]), m)
            if why is not None and not self.errors:
                self.errors.append(CalibrationError(why))

    def health_extra(self, sensor_id: str) -> dict:
        """Whether the sensor's frames are calibrated (``calibrated``: the file, or false);
        with alpha auto: the sensor's noise estimate and the alpha of its last frame."""
        extra = {"calibrated": self.calibration.source if self.calibration is not None else False}
        return extra if self.noise is None else {**extra, **self.noise.health(sensor_id)}

    def forget(self, sensor_id: str) -> None:
        super().forget(sensor_id)
        self._checked.discard(sensor_id)
        if self.noise is not None:
            self.noise.forget(sensor_id)


#: the most targets a frame a live cml localizer is set to find (K, or --max-targets with K
#: auto): its cost grows faster than K^2 (1-bit, one core, 2026-11-30: 2.1 ms a frame at K = 2,
#: 13.6 at 8, 49 at 16, 2 700 at 32), and at 16 one sensor at 20 frames/s takes a whole core
CML_LIVE_MAX_K = 16


@dataclass(frozen=True)
class LocalizerConfig:
    """k: targets per frame. algo: the decoder (:class:`~pipeline.dsp.decode.Algo`; default
    :data:`pipeline.defaults.DEFAULT_ALGO`). source: "quantized" or "raw"
    (full-resolution baseline). radar: the base configuration; frames of any whole number
    of ramps are accepted (their config ids are derived from it). min_range_m /
    max_range_m: the range gate the decoder searches inside (:mod:`pipeline.dsp.gate`); None:
    the end of :meth:`RangeGate.default <pipeline.dsp.gate.RangeGate.default>` for ``radar``
    (2 range bins kept out at each end of the axis: 1.2 m to 152.4 m for the K-MD2),
    filled in on construction. full_search_every: cml starts a sensor's frame from that
    sensor's last targets (warm start) and searches from scratch on its first frame, every
    ``full_search_every`` frames and whenever the fit no longer explains the codes
    (:func:`pipeline.dsp.cml.cml`'s ``init_range_m``); 1: always from scratch. uncertainty:
    cml's targets carry their uncertainty and p-value (:class:`~pipeline.dsp.decode.DecoderConfig`);
    False: positions only, for a node short of CPU."""

    k: int = 2
    algo: Algo = DEFAULT_ALGO
    source: str = "quantized"
    radar: RadarConfig = field(default_factory=RadarConfig)
    max_ramps: int = 16
    fallback_pbp: bool = False
    auto_k: bool = False
    pfa: float = DEFAULT_PFA
    min_range_m: float | None = None
    max_range_m: float | None = None
    full_search_every: int = DEFAULT_FULL_SEARCH_EVERY
    uncertainty: bool = True

    def __post_init__(self) -> None:
        if not (isinstance(self.full_search_every, int) and self.full_search_every >= 1):
            raise ParameterError(f"full_search_every={self.full_search_every!r} must be an integer >= 1")
        most = f"--max-targets={self.k!r}" if self.auto_k else f"K={self.k!r}"  # K auto: the most a frame has
        if not (isinstance(self.k, int) and 1 <= self.k <= self.radar.samples_per_ramp):
            raise ParameterError(f"{most} must be an integer in [1, N = {self.radar.samples_per_ramp}]: a "
                                 f"frame has N range bins a ramp and a target takes one")
        gate = RangeGate.resolve(self.min_range_m, self.max_range_m, self.radar)
        object.__setattr__(self, "min_range_m", gate.min_range_m)
        object.__setattr__(self, "max_range_m", gate.max_range_m)
        mask = gate.bin_mask(self.radar)
        cells = self.radar.samples_per_ramp if mask is None else int(mask.sum())
        if self.k > cells:
            raise ParameterError(f"{most} targets do not fit in the range gate [{gate.min_range_m:g}, "
                                 f"{gate.max_range_m:g}] m: it holds {cells} range bins")
        object.__setattr__(self, "algo", self.decoder().algo)  # validates the name, K auto and pfa
        if self.algo == Algo.CML and self.k > self.radar.samples_per_ramp // 2:
            raise ParameterError(f"{most} must be at most N/2 = "
                                 f"{self.radar.samples_per_ramp // 2} for cml: its fit of K tones to N samples a "
                                 f"ramp needs at least two samples a tone")
        if self.algo == Algo.CML and self.k > CML_LIVE_MAX_K:
            raise ParameterError(f"{most} is more than cml decodes live: at most "
                                 f"{CML_LIVE_MAX_K} (a 1-bit frame took 2 ms at K = 2, 49 ms at 16, 2.7 s at 32 on one "
                                 "core); pbp decodes more, or decode offline with the API")
        if self.source not in ("quantized", "raw"):
            raise ParameterError(f"source={self.source!r} must be quantized or raw")
        if self.source == "raw" and self.algo == Algo.QIHT:
            raise ParameterError(f"algo={self.algo!r} decodes quantized frames; the raw baseline uses pbp or cml")

    @property
    def gate(self) -> RangeGate:
        return RangeGate(self.min_range_m, self.max_range_m)

    def decoder(self) -> DecoderConfig:
        return DecoderConfig(algo=self.algo, fallback_pbp=self.fallback_pbp, auto_k=self.auto_k, pfa=self.pfa,
                             gate=self.gate, uncertainty=self.uncertainty)

    def known_configs(self) -> dict[int, RadarConfig]:
        return radar_configs(self.radar, self.max_ramps)


class LocalizeNode(FrameNode):
    """``<prefix>/*/quantized`` (or raw) -> the decoder (inside the range gate) ->
    ``<prefix>/<sensor>/targets`` (JSON).

    Latency (health and ``published_ns``) runs from the frame's sensor timestamp to the
    publication of its targets."""

    name = "localize"
    role = "localizer"

    def __init__(self, bus: BusConfig, config: LocalizerConfig, session: zenoh.Session | Transport | None = None,
                 tracking: TrackerConfig | None = None, bits: int | None | str = "any", **kw):
        """``bits``: the bits of the codes this node will be sent (None: unquantized frames), when
        the caller knows them (``qradar run``: its own quantizer's): cml then loads those frames'
        kernels alone (the others cost 0.26 s of CPU at start, from numba's cache); "any": a
        standalone node, which loads the common kind's kernels before it subscribes and the
        others in a thread."""
        self.in_topic = config.source
        self._bits = bits
        super().__init__(bus, config.radar, config.max_ramps, session, **kw)
        self.config = config
        # tracks (pipeline.dsp.track): ``<prefix>/<sensor>/tracks`` after each frame's targets
        # (static tracks refined in a thread of their own: a refinement decodes a second of frames at once)
        self.tracker = None if tracking is None else Tracker(tracking, Integration.of_localizer(config),
                                                             background=True)
        #: cml's warm start: sensor -> (frames since its last full search, its last ranges (k,), NaN
        #: for none); a sensor has an entry only while it has stats (forgotten when it expires)
        self._last: dict[str, tuple[int, np.ndarray]] = {}
        self._warm = config.algo == Algo.CML and config.full_search_every > 1
        #: the decoder (checked once, not per batch) and the tables and buffers it keeps between batches
        self._decoder = Decoder(config.decoder())
        self._loading: threading.Thread | None = None  # cml's other kinds of kernels, loaded after start
        self.front_end = FrontEndCheck()  # a front end's return in the first range bins, per sensor
        #: the targets of the last frame published: (sensor id, seq, targets as dicts), for a status line
        self.last_targets: tuple[str, int, list[dict]] | None = None
        #: sensors told that PBP's count test cannot read their 1-bit frames without dither (once each)
        self._told_undithered: set[str] = set()

    def start(self) -> "LocalizeNode":
        if self.config.algo == Algo.CML and self._decoder.cml(self.config.radar).engine == "numba":
            # cml's kernels of 1-bit codes from numba's cache (~1 s; `make` compiles them at install)
            # before subscribing (the session already listens), the other kinds' after in a thread
            from pipeline.dsp.cml.loading import kind_of, load_kernels  # numba: only a cml localizer loads it

            # the decodes this node makes: a count test with --K auto (its tracker's too), a warm start
            paths = {"count": self.config.auto_k, "warm": self._warm}
            if self._bits == "any":
                load_kernels(common=True, **paths)
                self._loading = threading.Thread(target=load_kernels, name="cml-kernels", kwargs=paths, daemon=True)
                self._loading.start()
            else:
                load_kernels(kinds=(kind_of(self._bits),), **paths)
        if self.config.algo != Algo.PBP and self._decoder.dither_engine == "numba":
            load_dither_kernel()  # the compiled dither (pipeline.dsp.dither_kernels), from the same cache
        return super().start()

    def stop(self, timeout_s: float = 5.0) -> None:
        super().stop(timeout_s)
        if self.tracker is not None:
            self.tracker.close()

    def forget(self, sensor_id: str) -> None:
        super().forget(sensor_id)
        self._last.pop(sensor_id, None)
        self._told_undithered.discard(sensor_id)
        self.front_end.forget(sensor_id)
        if self.tracker is not None:
            self.tracker.forget(sensor_id)

    def health_extra(self, sensor_id: str) -> dict:
        """``front_end``: frames checked for a front end's return in the first range bins and
        those that showed one (:mod:`pipeline.nodes.front_end`)."""
        return self.front_end.health(sensor_id)

    def _init_ranges(self, sensors: list[str]) -> np.ndarray | None:
        """The warm start's ranges (B, k) of frames from ``sensors`` (NaN: a full search)."""
        if not self._warm:
            return None
        every = self.config.full_search_every
        init = np.full((len(sensors), self.config.k), np.nan)
        seen: dict[str, int] = {}  # a sensor's frames earlier in this batch
        with self._lock:
            for i, sid in enumerate(sensors):
                last = self._last.get(sid)
                j = seen[sid] = seen.get(sid, 0) + 1
                if last is not None and last[0] + j < every:
                    init[i] = last[1]
        return init

    def _remember(self, sensors: list[str], init: np.ndarray, ranges: np.ndarray) -> None:
        full = np.isnan(init).all(axis=1).tolist()  # the frames searched from scratch
        ranges = np.asarray(ranges, dtype=float)
        with self._lock:
            for i, sid in enumerate(sensors):
                if sid not in self.stats:  # expired meanwhile (or never counted): keep nothing
                    continue
                last = self._last.get(sid)
                since = 0 if full[i] or last is None else last[0] + 1
                self._last[sid] = (since, ranges[i].copy())  # a copy: not a view keeping the batch's array

    def process(self, batch: list[QueuedFrame]) -> None:
        groups, keys = self.decode(batch)
        for g in groups:
            h = g.headers
            frames, dithered, bad = self.codec.frames(g)
            if (self.config.algo == Algo.PBP and self.config.auto_k and isinstance(frames, QuantizedFrames)
                    and frames.bits == 1 and not dithered.all()):
                self._tell_undithered(s for s, d in zip(h.sensor_id, dithered.tolist()) if not d)
            if bad is not None:  # raw frames: finite samples only
                for j in np.flatnonzero(bad).tolist():
                    self.count(h.sensor_id[j], "invalid_frames", f"frame {int(h.seq[j])} from {keys[g.index[j]]}: "
                               f"a sample is not finite or beyond {MAX_SAMPLE:g} full scale")
            # one decoder call per configuration (and dither), whatever the sensors
            cids = h.config_id
            if bad is None and (cids == cids[0]).all() and (dithered == dithered[0]).all():
                # the usual batch: one configuration, every frame, nothing to copy
                self._localize(self._configs[int(cids[0])], h, frames, [keys[i] for i in g.index.tolist()])
                continue
            for cid, dith in {(c, d) for c, d in zip(h.config_id.tolist(), dithered.tolist())}:
                sel = (h.config_id == cid) & (dithered == dith)
                if bad is not None:
                    sel &= ~bad
                idx = np.flatnonzero(sel)
                if idx.size == len(h):  # one configuration, nothing to copy
                    self._localize(self._configs[cid], h, frames, [keys[i] for i in g.index.tolist()])
                elif idx.size:
                    self._localize(self._configs[cid], h.take(idx), self.codec.select(frames, idx),
                                   [keys[i] for i in g.index[idx].tolist()])

    def _tell_undithered(self, sensors) -> None:
        """Once a sensor: PBP's count test cannot tell weak targets from the quantizer's
        harmonics in 1-bit frames without dither (its floor: pipeline.dsp.residual.product_floor_db,
        docs/science.md); the frames are still decoded."""
        for sid in sorted({str(s) for s in sensors} - self._told_undithered):
            self._told_undithered.add(sid)
            log.warning("%s: %s's frames are 1-bit without dither (alpha 0): PBP's --K auto cannot tell a target "
                        "weaker than the strongest by 25 dB (14 dB beside two) from the quantizer's harmonics, and "
                        "reports none there (docs/science.md); decode them with --algo cml, or quantize with "
                        "--alpha > 0", self.name, sid)

    def _localize(self, radar: RadarConfig, headers: FrameHeaders, frames, keys: list[str]) -> None:
        cfg = self.config
        decoder = self._decoder
        n = len(headers)
        sensors = [str(s) for s in headers.sensor_id]
        init = self._init_ranges(sensors)

        def compute(idx):
            if len(idx) == n:
                return decoder.decode_batch(frames, radar, cfg.k, init_range_m=init)
            return decoder.decode_batch(frames.take(idx) if isinstance(frames, QuantizedFrames) else frames[idx],
                                        radar, cfg.k, init_range_m=None if init is None else init[idx])

        def failed(i, exc):
            self._failed(headers.sensor_id[i], int(headers.seq[i]), keys[i], exc)

        try:
            self.front_end.check(radar, sensors, frames, lambda sid: sid in self.stats)
        except Exception as exc:  # a check, never a frame's loss
            self.log_limited("front_end", "%s: front-end check failed (%s: %s)", self.name, type(exc).__name__, exc)
        for idx, det in isolate(compute, np.arange(n), failed):
            idx = np.atleast_1d(np.asarray(idx))
            now = time.time_ns()
            if init is not None:
                self._remember([sensors[i] for i in idx.tolist()], init[idx], det.range_m)

            def part_of(j):  # the headers of positions j in idx (all of them: no copy)
                return headers if len(j) == n else headers.take(idx[j])

            def encode(j):  # j: positions in idx
                return encode_targets_batch(part_of(j), det if len(j) == len(idx) else take_detections(det, j),
                                            str(cfg.algo), cfg.k, cfg.source, now, cfg.auto_k)

            for j, payloads in isolate(encode, np.arange(idx.size), lambda j, exc: failed(idx[j], exc)):
                part = part_of(j)  # a non-finite target loses its own frame only
                self.publish_many(part.sensor_id, "targets", payloads, "application/json")
                self.record_latencies(part.sensor_id, (now - part.timestamp_ns) / 1e6)
                last = int(idx[j[-1]])
                self.last_targets = (sensors[last], int(headers.seq[last]), det.frame(int(j[-1])))
            if self.tracker is not None:
                publish_tracks(self, self.tracker, part_of(np.arange(idx.size)), det, frames if len(idx) == n
                               else frames.take(idx) if isinstance(frames, QuantizedFrames) else None, radar)

    def _failed(self, sensor: str, seq: int, key: str, exc: Exception) -> None:
        if isinstance(exc, DitherUnavailable):
            self.count(sensor, "invalid_frames", f"frame {seq} from {key}: {exc}; run the localizer "
                       "with --fallback-pbp to decode such frames with PBP")
        else:
            self.count(sensor, "processing_errors", f"frame {seq} from {key}: {type(exc).__name__}: {exc}")
