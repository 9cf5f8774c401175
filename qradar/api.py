"""qradar from Python: recordings as arrays and tables, quantize and decode a batch, Monte Carlo runs.

What a notebook in the lab needs, on the same functions the commands use (docs/api.md)::

    import qradar

    rec = qradar.open_recording("recordings/chamber.mcap", start=1.0, end=3.0)  # seconds from its start
    raw = rec.raw()                    # Frames: data (F, M, 2) complex64, seq, timestamp_ns, t_s
    q = qradar.quantize(raw, alpha=0.3)  # QuantizedFrames, the dither drawn as the stream does
    det = qradar.decode(q, rec.radar, k=2, algo="cml")  # Detections: (F, K) arrays
    targets = rec.targets()            # Targets: what the localizer published, (F, K) arrays
    table = rec.to_pandas("targets")   # one row per target (pandas: pip install -e '.[pandas]')

Shapes are batch first; units are in the names (m, deg, ns, s). Errors are the package's own
(:class:`replay.errors.ReplayError`, :class:`pipeline.errors.ParameterError`), one line each.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from pipeline.dsp.decode import DecoderConfig, decode_batch
from pipeline.dsp.localize import Detections, position_error_m
from pipeline.dsp.quantize import DITHER_COUNTER, QuantizedFrames, QuantizerConfig, quantize_frames, sensor_dither_seeds
from pipeline.dsp.score import DETECTION_DISTANCE_M, FrameScores, Score, score, score_frames
from experiments.montecarlo import MonteCarloConfig, MonteCarloResult, run_montecarlo
from radar_driver.model import RadarConfig
from radar_driver.scene import SimScene, load_scene
from replay.errors import ReplayError
from replay.reprocess import ReprocessConfig, ReprocessResult
from replay.reprocess import run as run_reprocess

from .recording import Recording, open_recording
from .streams import Frames, Quantized, Targets, Tracks

__all__ = ["Frames", "Quantized", "Targets", "Tracks", "Recording", "open_recording", "quantize", "decode",
           "montecarlo", "alpha_sweep", "MonteCarloConfig", "MonteCarloResult", "ReprocessConfig", "ReprocessResult",
           "QuantizerConfig", "DecoderConfig", "RadarConfig", "Detections", "SimScene", "load_scene",
           "position_error_m", "score", "score_frames", "Score", "FrameScores",
           "DETECTION_DISTANCE_M", "ReplayError"]  # qradar._API lists the same


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
    if not isinstance(radar, RadarConfig):
        raise ReplayError(f"radar must be a RadarConfig (a recording's rec.radar, or RadarConfig() for the default "
                          f"K-MD2), not {type(radar).__name__}")
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
    :func:`experiments.report.write_outputs`."""
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
