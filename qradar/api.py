"""qradar from Python: recordings as arrays, quantize and decode a batch, Monte Carlo runs.

What a notebook in the lab needs, on the same functions the commands use (docs/api.md)::

    import qradar

    rec = qradar.open_recording("recordings/chamber.mcap")
    raw = rec.raw()                    # Frames: data (F, M, 2) complex64, seq, timestamp_ns
    q = qradar.quantize(raw, alpha=0.3)  # QuantizedFrames, the dither drawn as the stream does
    det = qradar.decode(q, rec.radar, k=2, algo="cml")  # Detections: (F, K) arrays
    targets = rec.targets()            # Targets: what the localizer published, (F, K) arrays

Shapes are batch first; units are in the names (m, deg, ns). Errors are the package's own
(:class:`replay.errors.ReplayError`, :class:`pipeline.errors.ParameterError`), one line each.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from pipeline.dsp.decode import DecoderConfig, decode_batch
from pipeline.dsp.localize import Detections, position_error_m
from pipeline.dsp.score import DETECTION_DISTANCE_M, FrameScores, Score, score, score_frames
from replay.montecarlo import MonteCarloConfig, MonteCarloResult, run_montecarlo
from pipeline.dsp.quantize import DITHER_COUNTER, QuantizedFrames, QuantizerConfig, quantize_frames, sensor_dither_seeds
from pipeline.nodes.counters import DEFAULT_SEQ_RATE_HZ, judge_seq
from pipeline.wire import (COMMON, MAGIC, TARGET_FIELDS, HealthMsg, WireError, decode_health, decode_quantized_batch,
                           decode_raw_batch, decode_targets, load_json, quantized_batch)
from radar_driver.model import RadarConfig
from radar_driver.scene import SimScene, load_scene, scene_from_dict
from replay.errors import ReplayError
from replay.mcapio import McapFile, topic_of
from replay.reprocess import ReprocessConfig, ReprocessResult
from replay.reprocess import run as run_reprocess

log = logging.getLogger("qradar.api")

__all__ = ["Frames", "Quantized", "Targets", "Recording", "open_recording", "quantize", "decode", "montecarlo",
           "alpha_sweep", "MonteCarloConfig", "MonteCarloResult", "ReprocessConfig", "ReprocessResult",
           "QuantizerConfig", "DecoderConfig", "RadarConfig", "Detections", "SimScene", "load_scene",
           "position_error_m", "score", "score_frames", "Score", "FrameScores",
           "DETECTION_DISTANCE_M"]  # qradar._API lists the same


@dataclass(frozen=True)
class _Stream:
    """Messages of one sensor in sequence order: ``seq`` (F,) uint64, ``timestamp_ns`` (F,)
    int64 (the sensor's clock), ``config_id`` of the radar configuration."""

    sensor_id: str
    seq: np.ndarray
    timestamp_ns: np.ndarray
    config_id: int

    def __len__(self) -> int:
        return len(self.seq)


@dataclass(frozen=True)
class Frames(_Stream):
    """Full-resolution frames of one sensor: ``data`` (F, M, 2) complex64 (measurement,
    antenna; full-scale units)."""

    data: np.ndarray


@dataclass(frozen=True)
class Quantized(_Stream):
    """Quantized frames of one sensor as the stream carried them: ``frames``, the codes
    (F, M, 2, 2) and each frame's delta, alpha and dither seed
    (:class:`pipeline.dsp.quantize.QuantizedFrames`)."""

    frames: QuantizedFrames


@dataclass(frozen=True)
class Targets:
    """Targets of one sensor per frame, padded with NaN to the most targets of a frame:
    ``range_m``, ``angle_deg``, ``x_m``, ``y_m``, ``amplitude`` (F, K) float; ``count`` (F,)
    targets in each frame; ``seq`` (F,) uint64, ``timestamp_ns`` (F,) int64,
    ``published_ns`` (F,) int64 (the localizer's clock: latency = published - timestamp);
    ``algo`` the decoder that found them."""

    sensor_id: str
    seq: np.ndarray
    timestamp_ns: np.ndarray
    published_ns: np.ndarray
    count: np.ndarray
    range_m: np.ndarray
    angle_deg: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    amplitude: np.ndarray
    algo: str = ""

    def __len__(self) -> int:
        return len(self.seq)


def _ordered(seq: list[int]) -> np.ndarray:
    """Indices putting the frames in sequence order (a recording keeps arrival order)."""
    return np.argsort(np.asarray(seq, dtype=np.uint64), kind="stable")


@dataclass
class Recording:
    """A qradar recording (MCAP), read once into memory by topic. ``sensors``: the sensor
    ids with frames or targets in it; ``metadata``: the file's metadata records
    (name -> dict); ``radar``: its radar configuration (``qradar.radar`` metadata, else the
    default K-MD2's); ``truncated``: the file was cut short (its complete chunks are read).
    Messages that do not parse are counted in ``unparsed`` (topic -> count), not raised.
    Every chunk's CRC is checked: the messages of a damaged chunk are never returned, they
    are counted in ``lost`` (topic -> count) and each damaged chunk is named in ``damaged``
    (offset, log time range, topics; also logged as a warning)."""

    path: Path
    metadata: dict[str, dict[str, str]]
    sensors: list[str]
    truncated: bool
    unparsed: dict[str, int] = field(default_factory=dict)
    lost: dict[str, int] = field(default_factory=dict)
    damaged: list[str] = field(default_factory=list)
    _payloads: dict[tuple[str, str], list[bytes]] = field(default_factory=dict, repr=False)
    _log_ns: dict[tuple[str, str], list[int]] = field(default_factory=dict, repr=False)  # each message's log time

    @property
    def radar(self) -> RadarConfig:
        md = self.metadata.get("qradar.radar")
        if not md:
            return RadarConfig()
        values = {k: json.loads(v) for k, v in md.items() if k != "config_id"}
        return RadarConfig.from_dict(values)

    def scene(self) -> SimScene:
        """The simulated scene it was recorded from (``qradar.scene`` metadata): its targets'
        truth with ``.truth(t_s)`` or ``.arrays(t_s)``. A recording of a real sensor has none
        (ReplayError): give the reflectors' positions as a scene file (:func:`load_scene`)."""
        md = self.metadata.get("qradar.scene")
        if md is None or "scene" not in md:
            raise ReplayError(f"{self.path} holds no ground truth (no qradar.scene metadata: a real sensor's?); "
                              "load the reflectors' positions with qradar.load_scene(TOML)")
        return scene_from_dict(json.loads(md["scene"]), f"{self.path}: qradar.scene metadata")

    def _messages(self, topic: str, sensor: str | None, decode_fn) -> tuple[str, list]:
        if sensor is None:
            have = sorted(s for s, t in self._payloads if t == topic)
            if not have:
                raise ReplayError(f"{self.path} holds no {topic} messages (its sensors: {self.sensors or 'none'})")
            sensor = have[0]
        payloads = self._payloads.get((sensor, topic))
        if not payloads:
            raise ReplayError(f"{self.path} has no {topic} messages of sensor {sensor!r}; "
                              f"sensors with {topic}: {sorted(s for s, t in self._payloads if t == topic)}")
        source = f"{self.path}:{sensor}/{topic}"
        out = []
        if decode_fn in (decode_raw_batch, decode_quantized_batch):  # the binary frames: all in one call
            groups, errors = decode_fn(payloads, [source] * len(payloads))
            out = [m for g in groups for m in g.messages()]
            if errors:
                self.unparsed[topic] = self.unparsed.get(topic, 0) + len(errors)
        else:
            for p in payloads:
                try:
                    out.append(decode_fn(p, source))
                except WireError:
                    self.unparsed[topic] = self.unparsed.get(topic, 0) + 1
        if not out:
            raise ReplayError(f"{self.path}: none of the {len(payloads)} {topic} messages of {sensor!r} parse")
        return sensor, out

    def raw(self, sensor: str | None = None) -> Frames:
        """The raw frames of ``sensor`` (the first sensor by name if None), in sequence order."""
        sensor, msgs = self._messages("raw", sensor, decode_raw_batch)
        order = _ordered([m.seq for m in msgs])
        msgs = [msgs[i] for i in order]
        if len({m.data.shape for m in msgs}) != 1:
            raise ReplayError(f"{self.path}: the raw frames of {sensor} change M mid-recording; split the file")
        return Frames(sensor, np.array([m.seq for m in msgs], np.uint64),
                      np.array([m.timestamp_ns for m in msgs], np.int64), msgs[0].config_id,
                      np.stack([m.data for m in msgs]).astype(np.complex64))

    def quantized(self, sensor: str | None = None) -> Quantized:
        """The quantized frames of ``sensor`` as the stream carried them, in sequence order."""
        sensor, msgs = self._messages("quantized", sensor, decode_quantized_batch)
        msgs = [msgs[i] for i in _ordered([m.seq for m in msgs])]
        return Quantized(sensor, np.array([m.seq for m in msgs], np.uint64),
                         np.array([m.timestamp_ns for m in msgs], np.int64), msgs[0].config_id, quantized_batch(msgs))

    def targets(self, sensor: str | None = None) -> Targets:
        """The targets the localizer published for ``sensor``, in sequence order."""
        sensor, msgs = self._messages("targets", sensor, decode_targets)
        msgs = [msgs[i] for i in _ordered([m.seq for m in msgs])]
        f, k = len(msgs), max(1, max(len(m.targets) for m in msgs))
        cols = {name: np.full((f, k), np.nan) for name in TARGET_FIELDS}
        for i, m in enumerate(msgs):
            for j, t in enumerate(m.targets):
                for name in cols:
                    cols[name][i, j] = t[name]
        return Targets(sensor, np.array([m.seq for m in msgs], np.uint64),
                       np.array([m.timestamp_ns for m in msgs], np.int64),
                       np.array([m.published_ns for m in msgs], np.int64),
                       np.array([len(m.targets) for m in msgs]), cols["range_m"], cols["angle_deg"],
                       cols["x_m"], cols["y_m"], cols["amplitude"], msgs[0].algo)

    def losses(self, topic: str = "raw", sensor: str | None = None, rate_hz: float | None = None) -> dict[str, int]:
        """What the sequence numbers of ``sensor``'s (the first by name if None) ``topic``
        messages (raw, quantized, targets or tracks) say was lost, judged in file order on
        their log times as the nodes judge them live
        (:func:`pipeline.nodes.counters.judge_seq`): ``messages`` (with a sequence number),
        ``frames_missing`` (gaps the elapsed time allows at ``rate_hz``), ``seq_resets``
        (restarts of the count), ``implausible_seq`` (numbers out of line: forged or
        replayed). ``rate_hz``: the sensor's frame rate (default: the simulated scene's,
        else the nodes' bound, DEFAULT_SEQ_RATE_HZ)."""
        if topic not in ("raw", "quantized", "targets", "tracks"):
            raise ReplayError(f"topic {topic!r} carries no sequence numbers: raw, quantized, targets or tracks")
        if sensor is None:
            have = sorted(s for s, t in self._payloads if t == topic)
            if not have:
                raise ReplayError(f"{self.path} holds no {topic} messages (its sensors: {self.sensors or 'none'})")
            sensor = have[0]
        if rate_hz is None:
            rate_hz = float(self.metadata.get("qradar.scene", {}).get("rate_hz") or DEFAULT_SEQ_RATE_HZ)
        out = {"messages": 0, "frames_missing": 0, "seq_resets": 0, "implausible_seq": 0}
        track = None
        for payload, log_ns in zip(self._payloads.get((sensor, topic), []), self._log_ns.get((sensor, topic), [])):
            seq = _seq_of(topic, payload)
            if seq is None:
                continue
            track, verdict = judge_seq(track, seq, log_ns / 1e9, rate_hz)
            out["messages"] += 1
            out["frames_missing"] += verdict.missing
            out["seq_resets"] += verdict.resets
            out["implausible_seq"] += verdict.implausible
        return out

    def health(self) -> list[HealthMsg]:
        """Every health message of the recording (all nodes and sensors), in file order."""
        out = []
        for (sensor, topic), payloads in self._payloads.items():
            if topic == "health":
                for p in payloads:
                    try:
                        out.append(decode_health(p, f"{self.path}:{sensor}/health"))
                    except (WireError, ValueError):
                        self.unparsed["health"] = self.unparsed.get("health", 0) + 1
        return sorted(out, key=lambda h: h.timestamp_ns)


def _seq_of(topic: str, payload: bytes) -> int | None:
    """The sequence number of a message (None when it has none that reads)."""
    if topic in ("raw", "quantized"):
        if len(payload) < COMMON.size or payload[:4] != MAGIC:
            return None
        return int(COMMON.unpack_from(payload)[5])
    try:
        seq = load_json(payload, topic).get("seq")
    except (WireError, AttributeError):
        return None
    return seq if type(seq) is int and 0 <= seq < 2**64 else None


def open_recording(path: str | Path) -> Recording:
    """Read a qradar MCAP recording (every message, in memory: a recording of an hour of
    one sensor is ~1 GB; split long ones with ``--split-size``)."""
    f = McapFile(path)
    payloads: dict[tuple[str, str], list[bytes]] = {}
    log_ns: dict[tuple[str, str], list[int]] = {}
    for ch, msg in f.messages():
        topic = topic_of(ch.topic)
        if topic is None:
            continue
        sensor = ch.topic.rsplit("/", 2)[-2]
        payloads.setdefault((sensor, topic), []).append(bytes(msg.data))
        log_ns.setdefault((sensor, topic), []).append(msg.log_time)
    sensors = sorted({s for s, t in payloads if t != "health"})
    f.warn(log, "its messages are not returned")
    return Recording(Path(path), f.metadata_dict(), sensors, f.truncated, lost=f.lost_by_topic,
                     damaged=f.damage_lines(), _payloads=payloads, _log_ns=log_ns)


def quantize(frames: Frames | np.ndarray, alpha: float | None = None, bits: int = 1, dither_seed: int = 0,
             seq: np.ndarray | None = None, sensor_id: str | None = None,
             config: QuantizerConfig | None = None, generator: str = DITHER_COUNTER) -> QuantizedFrames:
    """Dither and quantize frames (F, M, 2) as the quantize node does: ``alpha`` the dither
    scale in [0, 1] (default the default decoder's best), ``bits`` per real value, delta
    from each frame (``config`` for the rest of :class:`QuantizerConfig`). The dither of a
    frame is drawn from (``dither_seed``, its sensor id, its ``seq``), so a
    :class:`Frames` of a recording gets the dither the stream would have given it
    (``generator``: the dither generator, ``"seedseq"`` for recordings made before the
    counter-based one; a recording's quantized frames say which in ``frames.generator``)."""
    if config is None:
        config = QuantizerConfig(bits=bits, dither_seed=dither_seed,
                                 **({} if alpha is None else {"alpha": float(alpha)}))
    if isinstance(frames, Frames):
        data, seq, sensor_id = frames.data, frames.seq if seq is None else seq, sensor_id or frames.sensor_id
    else:
        data = np.asarray(frames)
        seq = np.arange(data.shape[0], dtype=np.uint64) if seq is None else seq
    seeds = None if sensor_id is None else sensor_dither_seeds(config.dither_seed, [sensor_id] * data.shape[0])
    return quantize_frames(np.asarray(data, np.complex128), config, np.asarray(seq, np.uint64), dither_seed=seeds,
                           generator=generator)


def decode(frames: Quantized | QuantizedFrames | Frames | np.ndarray, radar: RadarConfig, k: int = 2,
           algo: str | None = None, auto_k: bool = False, decoder: DecoderConfig | None = None) -> Detections:
    """Targets of a batch with a decoder (``algo``: "pbp", "qiht" or "cml", default the
    stream's): quantized frames (their dither regenerated from their seeds) or
    full-resolution ones. ``k``: the targets to find (with ``auto_k`` the most). Returns
    :class:`Detections`, (F, K) arrays strongest first."""
    if decoder is None:
        decoder = DecoderConfig(auto_k=auto_k, **({} if algo is None else {"algo": algo}))
    if isinstance(frames, Quantized):
        frames = frames.frames
    elif isinstance(frames, Frames):
        frames = frames.data
    if not isinstance(frames, QuantizedFrames):
        frames = np.asarray(frames)
    m = frames.codes.shape[1] if isinstance(frames, QuantizedFrames) else frames.shape[1]
    if m != radar.samples_per_ramp * radar.ramps_per_frame:
        if m % radar.samples_per_ramp:
            raise ReplayError(f"frames of M = {m} are not whole ramps of {radar.samples_per_ramp} samples")
        radar = replace(radar, ramps_per_frame=m // radar.samples_per_ramp)
    return decode_batch(frames, radar, k, decoder)


def montecarlo(config: MonteCarloConfig | None = None, progress: bool = False, **kwargs) -> MonteCarloResult:
    """The Monte Carlo of the paper (``qradar montecarlo``): a :class:`MonteCarloConfig` or
    its fields as keywords (``ks=(1,), runs=2000, algos=("cml",), off_grid=True``). The
    result's ``summary`` is the dict the command writes as ``summary.json``; write it all with
    :func:`replay.montecarlo_report.write_outputs`."""
    if config is None:
        config = MonteCarloConfig(**kwargs)
    elif kwargs:
        raise TypeError("give a MonteCarloConfig or its fields, not both")
    return run_montecarlo(config, progress=progress)


def alpha_sweep(path: str | Path, out: str | Path, alphas=(0.25, 0.5, 0.75, 1.0), algos=("cml",),
                progress: bool = False, **kwargs) -> ReprocessResult:
    """Re-process a recording's raw frames for each dither scale and decoder (``qradar
    reprocess``): writes results.json, alpha_sweep.png and reconstructions.png into ``out``
    and returns the summary (``result.summary["by_algo"]``, ``best_alpha``, ...). More
    :class:`ReprocessConfig` fields as keywords (``k``, ``bits``, ``calibration``, ``truth``)."""
    cfg = ReprocessConfig(file=Path(path), alphas=tuple(float(a) for a in alphas), algos=tuple(algos),
                          out=Path(out), progress=progress, **kwargs)
    return run_reprocess(cfg)
