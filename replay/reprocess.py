"""Offline re-processing of a recording: its raw frames (read through
:class:`~replay.source.RecordingSource`) quantized and localized again with other
parameters, without zenoh; the dither-scale sweep of the paper's Sec. 6 (Fig. 5a: mean
position error against alpha, one curve per decoder; Fig. 5b: reconstructions over
consecutive frames, alpha = 0 against the best alpha). :func:`run` does the whole job
of ``qradar reprocess`` from a :class:`ReprocessConfig`."""

from __future__ import annotations

import json
import logging
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from pipeline.dsp.calibration import Calibration
from pipeline.dsp.calibration import load as load_calibration
from pipeline.dsp.decode import DEFAULT_ALGO, Algo, DecoderConfig, decode_batch
from pipeline.errors import ParameterError
from pipeline.dsp.gate import RangeGate, check_range_m, gate_warning
from pipeline.dsp.localize import DEFAULT_PFA, Detections, leakage_return, match_detections, nearest_estimates
from pipeline.nodes.front_end import front_end_warning, leakage_shown
from pipeline.dsp.score import FrameScores, score_frames, score_text
from pipeline.dsp.score import summarize as summarize_scores
from replay.progress import Progress
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames, sensor_dither_seed
from pipeline.dsp.track import TrackerConfig
from pipeline.nodes.tracker import Integration, Tracker, track_batch
from pipeline.wire import FrameHeaders, TargetsMsg, decode_tracks, encode_targets_batch
from radar_driver.model import RadarConfig
from radar_driver.options import nonneg_int, option
from radar_driver.scene import SimScene, load_truth, scene_from_dict

from .errors import NoQradarChannelsError, ReplayError
from .outputs import check_new_file, output_folder
from .reprocess_figures import plot_alpha_sweep, plot_reconstructions
from .mcapinfo import named_clock_ns, split_note, truth_clocks
from .mcapio import McapSink, pointcloud_json
from .source import RecordingSource

log = logging.getLogger("qradar.reprocess")


#: the alpha sweep of ``qradar reprocess`` unless told: start:stop:step
DEFAULT_SWEEP = "0:1:0.05"


def parse_alphas(text: str) -> np.ndarray:
    """``0:1:0.05`` (start:stop:step, stop included), ``0,0.5,1`` or ``0.55``; each
    mistake gets its own one-line ReplayError."""
    if ":" in text:
        parts = text.split(":")
        if len(parts) != 3:
            raise ReplayError(f"--alpha {text!r}: a sweep is START:STOP:STEP, three numbers (e.g. 0:1:0.1)")
        try:
            start, stop, step = (float(x) for x in parts)
        except ValueError:
            raise ReplayError(f"--alpha {text!r}: START:STOP:STEP must be three numbers (e.g. 0:1:0.1)") from None
        if not step > 0:
            raise ReplayError(f"--alpha {text!r}: step {step:g} must be > 0 (e.g. 0:1:0.1)")
        if start > stop:
            raise ReplayError(f"--alpha {text!r}: start {start:g} is above stop {stop:g}; write START:STOP:STEP "
                              f"with START <= STOP (e.g. {stop:g}:{start:g}:{step:g})")
        vals = np.arange(start, stop + step / 2, step)
    else:
        try:
            vals = np.array([float(x) for x in text.split(",")])
        except ValueError:
            raise ReplayError(f"--alpha {text!r}: expected START:STOP:STEP, a list a,b,c or one value") from None
    vals = np.round(vals, 10)
    bad = vals[~((vals >= 0) & (vals <= 1))]
    if bad.size:
        raise ReplayError(f"--alpha {text!r}: every alpha must lie in [0, 1], not {bad[0]:g}")
    return vals


@dataclass
class RawRecording:
    sensor_id: str
    frames: np.ndarray  # (F, M, 2) complex128
    seq: np.ndarray  # (F,)
    timestamp_ns: np.ndarray  # (F,)
    config_id: int
    metadata: dict[str, dict[str, str]]
    sensors: list[str]
    truncated: bool
    lost: int = 0  # messages of damaged chunks (never re-processed)
    damaged: list[str] = field(default_factory=list)  # one line per damaged chunk or problem


def load_raw(path, sensor: str | None = None) -> RawRecording:
    """The raw frames of one sensor of a recording (the first sensor by name if None)."""
    src = RecordingSource(path)
    with src:
        frames = list(src.frames())
    by_sensor: dict[str, list] = {}
    for fr in frames:
        by_sensor.setdefault(fr.sensor_id, []).append(fr)
    if not by_sensor:
        topics = sorted({c.topic for c in src.file.channels.values()})
        raise NoQradarChannelsError(f"{path} holds no raw frames (<prefix>/<sensor>/raw) to re-process; "
                                    f"its topics: {topics or 'none'}")
    sensors = sorted(by_sensor)
    if sensor is None:
        sensor = sensors[0]
    elif sensor not in by_sensor:
        raise ReplayError(f"{path} has no raw frames of sensor {sensor!r}; it has {sensors}")
    got = sorted(by_sensor[sensor], key=lambda f: f.seq)
    if len({f.data.shape[0] for f in got}) != 1 or len({f.config_id for f in got}) != 1:
        raise ReplayError(f"{path}: frames of {sensor} change M or radar config mid-recording; split the file")
    return RawRecording(sensor, np.stack([f.data for f in got]).astype(np.complex128),
                        np.array([f.seq for f in got]), np.array([f.timestamp_ns for f in got]),
                        got[0].config_id, src.metadata, sensors, src.truncated, src.lost, src.damaged)


def calibrated(rec: RawRecording, calibration: Calibration) -> RawRecording:
    """The recording's frames with the front end of ``calibration`` removed; a file without
    an entry for its sensor and config id is refused (one line)."""
    calibration.check_sensor(rec.sensor_id)
    n = rec.frames.shape[0]
    frames, ok = calibration.apply(rec.frames, [rec.sensor_id] * n, np.full(n, rec.config_id))
    if not ok.all():
        raise ReplayError(f"calibration {calibration.source} has no entry for sensor {rec.sensor_id!r} with config id "
                          f"{rec.config_id:#010x} and M = {rec.frames.shape[1]} (made for another radar configuration)")
    return replace(rec, frames=frames)


def truth_scene(rec: RawRecording, truth_file: str | Path | None) -> SimScene:
    """The true positions: ``truth_file`` (``--truth``, as ``run`` reads it: a scene file whose
    targets' amplitudes may be left out, :func:`radar_driver.scene.load_truth`), else the
    recording's own simulated scene."""
    if truth_file is not None:
        return load_truth(truth_file)
    md = rec.metadata.get("qradar.scene")
    if md is None or "scene" not in md:
        raise ReplayError("the recording holds no ground truth (no qradar.scene metadata: not simulated?); "
                          "give --truth SCENE.toml with the reflectors' positions")
    return scene_from_dict(json.loads(md["scene"]), "qradar.scene metadata")


def radar_for(rec: RawRecording, base: RadarConfig) -> RadarConfig:
    n = base.samples_per_ramp
    m = rec.frames.shape[1]
    if m % n:
        raise ReplayError(f"frames of M={m} are not whole ramps of {n}")
    radar = replace(base, ramps_per_frame=m // n)
    if radar.config_id() != rec.config_id:
        log.warning("frames carry radar config id %#010x, the scene's config has %#010x", rec.config_id,
                    radar.config_id())
    return radar


@dataclass
class AlphaResult:
    alpha: float
    errors_m: np.ndarray  # (F, T): error of each true target per frame
    nearest_xy: np.ndarray  # (F, T, 2): the estimate nearest each true target (x_m, y_m)
    detections: Detections
    scores: FrameScores | None = None  # the honest score of each frame (pipeline.dsp.score)


def clock_start_ns(rec: RawRecording) -> tuple[int, bool]:
    """When the truth's clock of ``rec``'s sensor began (ns) and whether that is known, as the
    live run's monitor took it: a real sensor's run names its start (``qradar.scene``'s
    ``truth_t0_ns``); else the sensor's first raw frame, which a later file of a split set
    names (``qradar.recorder``'s ``first_raw_ns``; a sensor it does not name began in this
    file); else this file's first frame (False: a later file that names none). A value that
    is no time at or before this file's first frame is not taken."""
    first = int(rec.timestamp_ns[0])
    named = named_clock_ns(truth_clocks(rec.metadata), rec.sensor_id, first)
    return (first, False) if named is None else (named, True)


def truth_positions(rec: RawRecording, scene: SimScene) -> tuple[np.ndarray, np.ndarray]:
    """Where each of the ``scene``'s targets is in each frame of ``rec``: (F, T) ranges (m)
    and angles (deg), a moving target's at the frame's time since the sensor's first frame
    (:func:`clock_start_ns`: the live run's clock for a simulated sensor)."""
    r, a, _ = scene.arrays(np.maximum(rec.timestamp_ns - clock_start_ns(rec)[0], 0) / 1e9)
    return r, a


def run_alpha(rec: RawRecording, radar: RadarConfig, positions: tuple[np.ndarray, np.ndarray], alpha: float,
              bits: int, k: int, seed: int, algo: Algo = DEFAULT_ALGO, auto_k: bool = False,
              pfa: float = DEFAULT_PFA, gate: RangeGate | None = None) -> AlphaResult:
    """One alpha: quantize every frame, decode (``auto_k``: at most ``k`` targets, counted
    with false-alarm probability ``pfa``; only inside ``gate``, None: the whole range
    axis) and measure each true target's error, the targets at ``positions`` ((F, T) ranges
    (m) and angles (deg), :func:`truth_positions`)."""
    q = quantize_frames(rec.frames, QuantizerConfig(bits=bits, alpha=float(alpha)), rec.seq,
                        dither_seed=sensor_dither_seed(seed, rec.sensor_id))
    # alpha = 0 has no dither to use: qiht falls back to PBP there (cml decodes it without dither)
    det = decode_batch(q, radar, k, DecoderConfig(algo=algo, fallback_pbp=True, auto_k=auto_k, pfa=pfa, gate=gate))
    tr, ta = positions
    err, pos = nearest_estimates(tr, ta, det.range_m, det.angle_deg)
    return AlphaResult(float(alpha), err, np.stack([pos.real, pos.imag], axis=-1), det,
                       score_frames(tr, ta, det.range_m, det.angle_deg))


@dataclass
class SweepResult:
    alphas: np.ndarray
    results: list[AlphaResult]
    truth: list[dict]
    rec: RawRecording
    positions: tuple[np.ndarray, np.ndarray]  # (F, T) true ranges (m), angles (deg): truth_positions
    params: dict = field(default_factory=dict)

    def moving(self, i: int) -> bool:
        """Whether true target ``i`` moves over the frames."""
        return bool(np.ptp(self.positions[0][:, i]) > 0)

    @property
    def mean_error_m(self) -> np.ndarray:
        """(A, T) mean error of each true target for each alpha (frames without any
        target, possible with K auto, left out; NaN if every frame is)."""
        e = np.array([r.errors_m for r in self.results])  # (A, F, T)
        ok = np.isfinite(e)
        n = ok.sum(axis=1)
        return np.where(n > 0, np.where(ok, e, 0.0).sum(axis=1) / np.maximum(n, 1), np.nan)

    @property
    def best_index(self) -> int:
        me = self.mean_error_m.mean(axis=1)
        return int(np.nanargmin(me)) if np.isfinite(me).any() else 0

    @property
    def frames_without_targets(self) -> np.ndarray:
        """(A,) frames in which the decoder reported no target at all (K auto)."""
        return np.array([int(np.all(~np.isfinite(r.errors_m), axis=1).sum()) for r in self.results])

    def summary(self) -> dict:
        """The sweep's figures as JSON-ready values (null where no frame had a target)."""
        me = self.mean_error_m
        labels = [f"target {i + 1} ({t['range_m']:.2f} m, {t['angle_deg']:+.1f} deg)"
                  for i, t in enumerate(self.truth)]
        best = self.best_index
        zero = int(np.argmin(np.abs(self.alphas))) if np.any(self.alphas == 0) else None

        def m(v) -> float | None:
            return round(float(v), 4) if np.isfinite(v) else None

        detection = {}
        if self.params.get("K_auto"):  # found: a detection within one range bin (0.6 m) of the true range
            found, false = zip(*(match_detections(self.positions[0], r.detections.range_m, 0.6) for r in self.results))
            detection = {"detected": {lab: [round(float(f[:, i].mean()), 4) for f in found]
                                      for i, lab in enumerate(labels)},
                         "false_targets_per_frame": [round(float(x.mean()), 4) for x in false]}
        return {
            "sensor_id": self.rec.sensor_id, "frames": int(self.rec.frames.shape[0]),
            "alphas": [float(a) for a in self.alphas],
            "mean_error_m": {lab: [m(v) for v in me[:, i]] for i, lab in enumerate(labels)},
            "mean_error_all_m": [m(v) for v in me.mean(axis=1)],
            "frames_without_targets": self.frames_without_targets.tolist(),
            "best_alpha": float(self.alphas[best]),
            "error_at_best_m": m(me[best].mean()),
            "error_at_alpha0_m": None if zero is None else m(me[zero].mean()),
            # per alpha, the honest score: each true target's detection rate (a target within
            # distance_m) and the median error of its detections, false targets and targets a frame
            "score": [summarize_scores(r.scores).to_dict(self.truth) for r in self.results if r.scores is not None],
            "truth": self.truth, **detection, **self.params,
        }


def sweep(rec: RawRecording, radar: RadarConfig, scene: SimScene, alphas: np.ndarray, bits: int = 1,
          k: int | None = None, seed: int = 0, algo: Algo = DEFAULT_ALGO, auto_k: bool = False,
          pfa: float = DEFAULT_PFA, bar: Progress | bool = True, gate: RangeGate | None = None) -> SweepResult:
    """Every alpha of ``alphas`` with one decoder, searching inside ``gate`` (None: the
    whole range axis), each frame scored against where the ``scene``'s targets are at its
    time (:func:`truth_positions`; the result's ``truth``: at the file's first frame). ``bar``: a
    progress bar of the caller's to advance, or whether to show one of its own."""
    positions = truth_positions(rec, scene)
    truth = scene.truth(float(rec.timestamp_ns[0] - clock_start_ns(rec)[0]) / 1e9)  # at this file's first frame
    k = k or len(truth)
    out = []
    own = Progress(len(alphas) * rec.frames.shape[0], "reprocess", unit="frames", enabled=bar is True)
    with own if isinstance(bar, bool) else nullcontext(bar) as bar:
        for a in alphas:
            out.append(run_alpha(rec, radar, positions, float(a), bits, k, seed, algo, auto_k, pfa, gate))
            bar.update(rec.frames.shape[0])
    return SweepResult(np.asarray(alphas, float), out, truth, rec, positions,
                       {"bits": bits, "K": k, "K_auto": auto_k, "algo": str(algo), "seed": seed,
                        **({} if gate is None else gate.to_dict())})


def write_targets_mcap(result: SweepResult, index: int, radar: RadarConfig, path: Path,
                       tracks: list[bytes] | None = None) -> int:
    """The re-processed targets of one alpha as an MCAP (targets + foxglove.PointCloud),
    and ``tracks`` (the tracks JSON of each frame, :func:`track_recording`) when given."""
    r = result.results[index]
    rec = result.rec
    sink = McapSink(path, overwrite=True)  # an output in reprocess's own --out folder
    try:
        sink.metadata("qradar.reprocess", {"alpha": str(r.alpha), **{k: str(v) for k, v in result.params.items()}})
        n = rec.frames.shape[0]
        headers = FrameHeaders([rec.sensor_id] * n, rec.seq, rec.timestamp_ns, [radar.config_id()] * n)
        payloads = encode_targets_batch(headers, r.detections, result.params["algo"], result.params["K"], "quantized",
                                        0, result.params["K_auto"])
        for i in range(n):
            msg = TargetsMsg(rec.sensor_id, int(rec.seq[i]), int(rec.timestamp_ns[i]), radar.config_id(),
                             result.params["algo"], result.params["K"], "quantized", r.detections.frame(i), 0,
                             auto_k=result.params["K_auto"])
            key = f"reprocess/{rec.sensor_id}/targets"
            ts = int(rec.timestamp_ns[i])
            sink.write(key, payloads[i], ts, ts, int(rec.seq[i]))
            sink.write(f"reprocess/{rec.sensor_id}/pointcloud", pointcloud_json(msg), ts, ts, int(rec.seq[i]))
            if tracks is not None:
                sink.write(f"reprocess/{rec.sensor_id}/tracks", tracks[i], ts, ts, int(rec.seq[i]))
        return rec.frames.shape[0]
    finally:
        sink.close()


def track_recording(result: SweepResult, index: int, radar: RadarConfig, tracking: TrackerConfig,
                    gate: RangeGate | None, pfa: float | None = None) -> tuple[list[bytes], dict]:
    """Tracks (pipeline.dsp.track) of the re-processed targets of one alpha, frame by frame, the
    static ones integrated on the frames quantized again as that alpha's were: the tracks
    JSON of each frame and a summary (``pfa``: the decoder's count test, None: K targets) (ids, and against the truth's static targets the median
    position error of the static tracks after the integration time and of the targets)."""
    r, rec, params = result.results[index], result.rec, result.params
    q = quantize_frames(rec.frames, QuantizerConfig(bits=params["bits"], alpha=float(r.alpha)), rec.seq,
                        dither_seed=sensor_dither_seed(params["seed"], rec.sensor_id))
    tracker = Tracker(tracking, Integration(params["K"], gate, pfa))
    f = rec.frames.shape[0]
    headers = FrameHeaders([rec.sensor_id] * f, rec.seq.astype(np.uint64), rec.timestamp_ns.astype(np.int64),
                           np.full(f, radar.config_id(), dtype=np.uint32))
    payloads = track_batch(tracker, headers, r.detections, q if q.dithered else None, radar)
    msgs = [decode_tracks(p) for p in payloads]
    ids = sorted({t["track_id"] for m in msgs for t in m.tracks})
    static_truth = [t for i, t in enumerate(result.truth) if not result.moving(i)]
    settled = (rec.timestamp_ns - rec.timestamp_ns[0]) >= (tracking.integrate_s + 0.5) * 1e9
    errors, target_errors = [], []
    for i in np.flatnonzero(settled).tolist():
        for j, t in enumerate(static_truth):
            d = [np.hypot(k["x_m"] - t["x_m"], k["y_m"] - t["y_m"]) for k in msgs[i].tracks if k["static"]]
            if d and min(d) < 1.0:
                errors.append(min(d))
        target_errors.extend(e for e in r.errors_m[i] if np.isfinite(e))
    summary = {"integrate_s": tracking.integrate_s, "track_ids": ids, "refinements": tracker.refinements,
               "static_track_error_median_m": round(float(np.median(errors)), 4) if errors else None,
               "target_error_median_m": round(float(np.median(target_errors)), 4) if target_errors else None,
               "frames_settled": int(settled.sum())}
    return payloads, summary


def metres(v: float | None) -> str:
    """A figure in metres to its digits, or n/a."""
    return "n/a" if v is None else f"{v:.3g} m"


# -- the whole job -------------------------------------------------------------------------------
@dataclass(frozen=True)
class ReprocessConfig:
    """What ``qradar reprocess`` does. file: the recording. alphas: dither scales to sweep
    (see :func:`parse_alphas`). k: targets (None = the truth's count; with ``auto_k`` the
    most a frame has, counted with false-alarm probability ``pfa``). algos: the
    decoders, one sweep each (the first is the reference of the summary's top level).
    sensor: sensor id (None = the first). truth: a scene TOML with the true positions
    (None = the recording's ``qradar.scene`` metadata). out: folder for results.json and
    the plots. mcap: also write the targets of the best (decoder, alpha) there.
    min_range_m / max_range_m: the range gate the decoders search inside (None: the end
    of :meth:`RangeGate.default <pipeline.dsp.gate.RangeGate.default>` for the recording's
    radar, as the live localizer); checked here (min < max) and against the radar once
    the recording is read.
    calibration: a ``qradar calibrate`` file whose front end is removed from the raw
    frames before they are quantized."""

    file: Path = option(help="a qradar MCAP recording with raw frames", positional=True, required=True)
    alphas: tuple[float, ...] = tuple(parse_alphas(DEFAULT_SWEEP))
    bits: int = 1
    k: int | None = None
    algos: tuple[Algo, ...] = option((DEFAULT_ALGO,), f"decoders, one alpha sweep and one curve each (default "
                                     f"{DEFAULT_ALGO}); qiht decodes alpha = 0 with PBP (there is no dither to use)",
                                     aliases=("--algo",), many="+", choices=tuple(a.value for a in Algo))
    seed: int = option(0, "random seed (runs are reproducible for a seed)", parse=nonneg_int)
    sensor: str | None = option(None, "sensor id (default: the first)")
    truth: Path | None = option(None, "scene TOML with the true positions (real recordings)")
    out: Path = option(Path("out/reprocess"), "folder for results.json and the plots")
    mcap: Path | None = option(None, "also write the best alpha's targets to this MCAP")
    progress: bool = option(True, "no progress bar", flag="--quiet", negate=True)
    auto_k: bool = False
    pfa: float = DEFAULT_PFA
    calibration: Path | None = None
    min_range_m: float | None = None
    max_range_m: float | None = None
    tracking: TrackerConfig | None = None  # tracks of the best (decoder, alpha)'s targets (pipeline.dsp.track)
    # replace the outputs (results.json, the plots, mcap) when they exist
    force: bool = option(False, "replace results.json, the plots and the --mcap file if it exists (without it: "
                         "refused, nothing written)")

    def __post_init__(self) -> None:
        if not self.alphas or any(not 0.0 <= a <= 1.0 for a in self.alphas):
            raise ReplayError(f"alphas {self.alphas!r} must be at least one value in [0, 1]")
        try:  # before the file is read: numbers >= 0, min < max (against the radar: in run)
            for name in ("min_range_m", "max_range_m"):
                if getattr(self, name) is not None:
                    check_range_m(name, getattr(self, name))
            if self.min_range_m is not None and self.max_range_m is not None:
                RangeGate(self.min_range_m, self.max_range_m)
        except ParameterError as exc:
            raise ReplayError(str(exc)) from None
        if isinstance(self.algos, str):
            object.__setattr__(self, "algos", (self.algos,))
        algos = tuple(DecoderConfig(algo=a, auto_k=self.auto_k, pfa=self.pfa).algo for a in self.algos)
        if not algos or len(set(algos)) != len(algos):
            raise ReplayError(f"algos {self.algos!r} must be distinct and at least one")
        object.__setattr__(self, "algos", algos)


@dataclass
class ReprocessResult:
    summary: dict
    written: list[Path]
    notes: list[str]
    lines: list[str]


#: what results.json keeps of each decoder's sweep under ``by_algo``
PER_ALGO = ("mean_error_m", "mean_error_all_m", "best_alpha", "error_at_best_m", "error_at_alpha0_m", "score")
#: the files reprocess writes into its --out folder
OUTPUT_FILES = ("results.json", "alpha_sweep.png", "reconstructions.png")


def run(cfg: ReprocessConfig) -> ReprocessResult:
    """Load, sweep alpha with each decoder, write results.json, the two figures and
    (optionally) an MCAP of the best (decoder, alpha)'s targets. Returns the summary,
    the files written, notes for the user (warnings) and the report lines. Existing outputs
    are refused before any work unless ``cfg.force`` (:mod:`replay.outputs`)."""
    inputs = (cfg.file, cfg.calibration, cfg.truth)
    with output_folder(cfg.out, OUTPUT_FILES, cfg.force, inputs):  # made, and removed again if the work fails
        return _run(cfg, inputs)


def _notes(cfg: ReprocessConfig, rec: RawRecording, front: dict, scene: SimScene, radar: RadarConfig,
           gate: RangeGate) -> list[str]:
    """What a re-processing says besides its figures: a calibration the live run had and this
    one has not, a front end no calibration removed (``front``: the frames checked and
    flagged), targets outside the range ``gate``, one file of a split set, moving targets."""
    notes = []
    live = rec.metadata.get("qradar.calibration", {}).get("file")
    # raw frames keep the front end; the live run removed it where it quantized
    if front["calibrated"] is None and live:
        notes.append(f"warning: {cfg.file} was recorded by a run calibrated with {live}, and its raw frames keep the "
                     f"front end: give --calibration {live} to decode them as that run did")
    elif leakage_shown(front):
        notes.append(f"warning: {front_end_warning(rec.sensor_id, front, radar)}")
    outside = gate_warning(scene, gate)
    if outside is not None:
        notes.append(f"warning: {outside}")
    split = split_note(cfg.file, "reprocess")
    if split is not None:
        notes.append(split)
    if any(t.velocity_m_s for t in scene.targets):
        known = clock_start_ns(rec)[1] or split is None or split.startswith(f"note: {cfg.file} is file 1 ")
        since = ("the run's start (a real sensor's run: the live run's clock)"
                 if "truth_t0_ns" in rec.metadata.get("qradar.scene", {}) else "the sensor's first frame")
        notes.append(f"note: moving targets: each frame is scored where they are at its time since {since}"
                     + ("" if known else " (taken as this file's first: a file of a split set whose "
                                          "recorder did not name the sensor's first frame, so its moving targets' "
                                          "truth is early by the files before it)"))
    return notes


def _run(cfg: ReprocessConfig, inputs: tuple) -> ReprocessResult:
    """:func:`run` once its output folder is there."""
    if cfg.mcap is not None:
        check_new_file(cfg.mcap, cfg.force, "--mcap", inputs)
    rec = load_raw(cfg.file, cfg.sensor)
    calibration = None
    if cfg.calibration is not None:
        calibration = load_calibration(cfg.calibration)
        rec = calibrated(rec, calibration)
    scene = truth_scene(rec, cfg.truth)
    radar = radar_for(rec, scene.radar)
    try:
        gate = RangeGate.resolve(cfg.min_range_m, cfg.max_range_m, radar)
    except ParameterError as exc:
        raise ReplayError(f"{cfg.file}: {exc}") from None
    # as a run's localizer: frames with a return in the first range bins within 10 dB of their strongest show
    # the front end, which no calibration removed or another sensor's did (a calibration that does not fit: said, as run says it)
    front = {"checked": int(rec.frames.shape[0]), "leakage": int(leakage_return(rec.frames, radar).sum()),
             "calibrated": None if calibration is None else calibration.source}
    notes = _notes(cfg, rec, front, scene, radar, gate)
    results: dict[str, SweepResult] = {}
    with Progress(len(cfg.alphas) * rec.frames.shape[0] * len(cfg.algos), "reprocess", unit="frames",
                  enabled=cfg.progress) as bar:
        for algo in cfg.algos:
            results[str(algo)] = sweep(rec, radar, scene, np.asarray(cfg.alphas), bits=cfg.bits, k=cfg.k,
                                       seed=cfg.seed, algo=algo, auto_k=cfg.auto_k, pfa=cfg.pfa, bar=bar, gate=gate)
    first = next(iter(results.values()))
    summaries = {a: r.summary() for a, r in results.items()}
    summary = summaries[str(cfg.algos[0])] | {"file": str(cfg.file), "first_timestamp_ns": int(rec.timestamp_ns[0]),
                                              "truncated": rec.truncated, "lost_messages": rec.lost,
                                              "damage": rec.damaged}
    if rec.damaged:
        notes.append(f"warning: {cfg.file} is damaged: {rec.lost} messages lost, not re-processed "
                     f"({len(rec.damaged)} damaged chunk(s) or problem(s), in results.json's \"damage\")")
    if calibration is not None:
        summary["calibration"] = calibration.summary()
    summary["front_end"] = front
    if len(results) > 1:
        summary["by_algo"] = {a: {key: s[key] for key in PER_ALGO} for a, s in summaries.items()}
    best_algo = min(summaries, key=lambda a: np.inf if summaries[a]["error_at_best_m"] is None
                    else summaries[a]["error_at_best_m"])
    try:
        (cfg.out / "results.json").write_text(json.dumps(summary, indent=2) + "\n")
        written = [cfg.out / "results.json", plot_alpha_sweep(results, cfg.out / "alpha_sweep.png"),
                   plot_reconstructions(results[best_algo], cfg.out / "reconstructions.png")]
        tracks = None
        if cfg.tracking is not None:
            tracks, summary["tracks"] = track_recording(results[best_algo], results[best_algo].best_index, radar,
                                                        cfg.tracking, gate, cfg.pfa if cfg.auto_k else None)
            (cfg.out / "results.json").write_text(json.dumps(summary, indent=2) + "\n")
        if cfg.mcap is not None:
            write_targets_mcap(results[best_algo], results[best_algo].best_index, radar, cfg.mcap, tracks)
            written.append(cfg.mcap)
    except OSError as exc:
        raise ReplayError(f"cannot write the re-processing results ({exc.filename or cfg.out}): "
                          f"{exc.strerror or exc}") from None
    lines = [f"{rec.sensor_id}: {first.rec.frames.shape[0]} frames"]
    m = metres
    lines += [f"  {a:<5} best alpha {s['best_alpha']:.2f} (mean error {m(s['error_at_best_m'])}; at alpha 0: "
              f"{m(s['error_at_alpha0_m'])})" + (f"; frames without any target: {max(s['frames_without_targets'])} at "
                                               "worst" if any(s["frames_without_targets"]) else "")
              + "\n        at it: " + score_text(s["score"][results[a].best_index]) for a, s in summaries.items()]
    if "tracks" in summary:
        t = summary["tracks"]
        lines.append(f"  tracks: ids {t['track_ids']}; static tracks' median error {m(t['static_track_error_median_m'])} "
                     f"after {t['integrate_s']:g} s of integration (targets: {m(t['target_error_median_m'])})")
    lines.append(f"wrote {written[0]}, " + ", ".join(str(f) for f in written[1:]))
    return ReprocessResult(summary, written, notes, lines)
