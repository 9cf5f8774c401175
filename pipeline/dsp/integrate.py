"""Integration in time: T quantized frames of a static scene decoded as one (issue 25).

Each frame of whole ramps carries its own dither, so T frames of R ramps of the same
static scene are one frame of T R ramps (:mod:`pipeline.dsp.cml`'s model: every ramp sees
the same N frequencies, the dither is known per measurement): the codes of the T frames
and their dithers are stacked along the measurement axis and decoded together by
:func:`pipeline.dsp.cml.cml`, whose error falls with the number of codes (off the grid, like
1/M without noise).

One-bit frames whose step ``delta`` differs from frame to frame (``delta = "auto"``) stack
exactly: a 1-bit code is the sign of ``Re/Im (Gamma + xi)``, which does not depend on
delta, and each frame keeps its own dither ``xi``; the stacked frame is given one common
step (the median) for cml's schedule. Frames of more bits must share one delta.
"""

from __future__ import annotations

import numpy as np

from radar_driver.model import RadarConfig

from pipeline.dsp.cml import CmlOptions, cml
from pipeline.errors import ParameterError
from pipeline.dsp.gate import RangeGate
from pipeline.dsp.localize import Detections
from pipeline.dsp.quantize import QuantizedFrames


def stack_frames(frames: QuantizedFrames) -> tuple[np.ndarray, np.ndarray, float]:
    """T dithered frames (B = T) -> one frame: Z (1, T M, 2), its dither xi (1, T M, 2)
    and its step delta (frame units), for :func:`pipeline.dsp.cml.cml`."""
    z, xi, delta = stack_windows(frames, frames.codes.shape[0])
    return z, xi, float(delta[0])


def stack_windows(frames: QuantizedFrames, t: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """W windows of T dithered frames each (B = W T frames, window after window) -> W
    frames: Z (W, T M, 2), their dither xi (W, T M, 2) and step delta (W,) (1 bit: the
    median of the window's; more bits: the window's one delta)."""
    b = frames.codes.shape[0]
    if b == 0 or t < 1 or b % t:
        raise ParameterError(f"integrate: {b} frames are not windows of {t} frames (at least one)")
    xi = frames.dither()
    if xi is None:
        raise ParameterError("integrate: the frames must all be dithered (alpha > 0): the codes of a static "
                             "scene without dither repeat, and stacking them adds nothing")
    w, m = b // t, frames.codes.shape[1]
    delta = np.asarray(frames.delta, dtype=float).reshape(w, t)
    z = frames.values()
    if frames.bits == 1:
        common = np.median(delta, axis=1)
        z = (np.sign(z.real) + 1j * np.sign(z.imag)) * (0.5 * np.repeat(common, t))[:, None, None]  # signs, one step
    else:
        common = delta[:, 0]
        if not np.allclose(delta, common[:, None], rtol=1e-6, atol=0):
            raise ParameterError(f"integrate: {frames.bits}-bit frames must share one step delta to be stacked, "
                                 f"got {delta.min():g} to {delta.max():g}")
    return z.reshape(w, t * m, 2), xi.reshape(w, t * m, 2), common


def integrate(frames: QuantizedFrames, radar: RadarConfig, k: int, gate: RangeGate | None = None,
              pfa: float | None = None, window: int | None = None) -> Detections:
    """Targets (W, k) of W windows of T dithered frames (B = W T, window after window,
    each frame of whole ramps of ``radar``; ``window`` = T, None: one window of all) of a
    static scene each, each window decoded as one frame by cml, the windows in one batch
    (``pfa``: its count test, None: exactly k; ``gate``: the range gate it searches inside)."""
    n = radar.samples_per_ramp
    if frames.codes.shape[1] % n:
        raise ParameterError(f"integrate: M={frames.codes.shape[1]} is not a whole number of ramps of {n}")
    z, xi, delta = stack_windows(frames, frames.codes.shape[0] if window is None else window)
    g = None if gate is None else gate.check(radar)
    # the static model: the scene is static, and the stacked ramps are of frames far apart in
    # time, not a frame's evenly spaced ramps (a phase step between them means nothing); the
    # phase step's search over T R ramps made a refinement of 20 frames 206 ms, 2.5 ms without
    options = CmlOptions(iters=INTEGRATE_ITERS, anneal=anneal_levels(z.shape[1]), motion=False)
    return cml(z, xi, delta, frames.bits, radar, k, pfa=pfa, gate=g, options=options).detections(radar)


#: cml's refinement steps after each detection on stacked frames: the annealing that follows
#: does the work there (measured: 1, 2 or 3 give the same positions to the last digit on the
#: chamber's 20-frame windows and the Monte Carlo in time, and 1 costs 0.73 of 3)
INTEGRATE_ITERS = 1


def anneal_levels(m: int) -> int:
    """cml's annealing levels for a frame of M measurements: each level at most halves its
    sigma_eff on the way from delta / 4 to delta / M (at least cml's default, 6). Measured
    (one target off the grid, no noise, alpha 0.45, T = 1..32 frames): 6 levels whatever T
    give an error slope of -0.60 against T, these -0.88 (README, Tracks)."""
    return max(6, int(np.ceil(np.log2(max(m, 4) / 4.0))))


def concat_frames(parts: list[QuantizedFrames]) -> QuantizedFrames:
    """Frames of several batches (same M and bits) as one batch, each field per frame."""
    if not parts:
        raise ParameterError("integrate: no frames")
    b = [p.codes.shape[0] for p in parts]

    def per_frame(name, dtype=None):
        return np.concatenate([np.broadcast_to(np.asarray(getattr(p, name), dtype=dtype), (n,))
                               for p, n in zip(parts, b)])

    first = parts[0]
    return QuantizedFrames(np.concatenate([p.codes for p in parts]), per_frame("delta", float), first.bits,
                           per_frame("alpha", float), per_frame("dither_seed", np.uint64), per_frame("seq", np.uint64),
                           per_frame("generator"))


def time_monte_carlo(runs: int, frames_t: tuple[int, ...], noise_sigma: float = 0.0, alpha: float | None = None,
                     seed: int = 0, radar: RadarConfig | None = None) -> dict:
    """The Monte Carlo in time: ``runs`` static scenes of one target (amplitude 1, random
    phase, continuous range uniform in [3, 150] m, angle uniform in [-60, 60] deg), each
    seen in max(frames_t) 1-bit frames with a fresh dither (and fresh complex noise of
    std ``noise_sigma`` per I and Q); for each T of ``frames_t`` the first T frames of
    every run decoded together (:func:`integrate`, the runs in one batch). Returns the
    median and 90th percentile of the position error (m) against T and the slope of a
    least-squares line through log(median) against log(T)."""
    from radar_driver.model import polar_to_xy, simulate_frames

    from pipeline.dsp.quantize import QuantizerConfig, quantize_frames

    radar = radar or RadarConfig()
    if not (isinstance(runs, int) and runs >= 1) or not frames_t or min(frames_t) < 1:
        raise ParameterError(f"time Monte Carlo: runs={runs!r} and frames {frames_t!r} must be >= 1")
    if not (np.isfinite(noise_sigma) and noise_sigma >= 0):
        raise ParameterError(f"time Monte Carlo: noise_sigma={noise_sigma!r} must be a finite number >= 0")
    frames_t = tuple(sorted(set(frames_t)))  # a curve against T: in order, once each (4 1 2 2 drew a zigzag)
    rng = np.random.default_rng(seed)
    tmax = max(frames_t)
    r = rng.uniform(3.0, 150.0, runs)
    a = rng.uniform(-60.0, 60.0, runs)
    amp = np.exp(2j * np.pi * rng.random(runs))
    one = simulate_frames(r[:, None], a[:, None], amp[:, None], radar)  # (runs, M, 2): static, one frame each
    frames = np.repeat(one, tmax, axis=0)
    if noise_sigma:
        frames = frames + noise_sigma * (rng.standard_normal(frames.shape) + 1j * rng.standard_normal(frames.shape))
    cfg = QuantizerConfig() if alpha is None else QuantizerConfig(alpha=alpha)
    q = quantize_frames(frames, cfg, np.arange(runs * tmax, dtype=np.uint64), dither_seed=seed)
    x, y = polar_to_xy(r, np.deg2rad(a))
    gate = RangeGate.default(radar)
    med, p90 = [], []
    for t in frames_t:
        idx = (np.arange(runs)[:, None] * tmax + np.arange(t)).ravel()  # the first T frames of each run
        det = integrate(q.take(idx), radar, 1, gate, window=t)
        err = np.hypot(det.x_m[:, 0] - x, det.y_m[:, 0] - y)
        med.append(float(np.median(err)))
        p90.append(float(np.percentile(err, 90)))
    slope = float(np.polyfit(np.log(frames_t), np.log(med), 1)[0]) if len(frames_t) > 1 else None
    return {"noise_sigma": noise_sigma, "T": list(frames_t), "median_m": med, "p90_m": p90, "slope": slope,
            "runs": runs, "alpha": cfg.alpha, "seed": seed}
