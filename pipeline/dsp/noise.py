"""Sensor noise estimated from full-resolution frames, and the dither scale it calls for
(issue 24: ``--alpha auto``).

:func:`estimate_noise_sigma` measures the std of each of I and Q of a frame's white noise,
robust to targets and to the front end: the difference of consecutive ramps (a static
scene, the DC offset, the leakage and the I/Q ghosts cancel in it; a frame of one ramp
uses the ramp itself) through a 4-term Blackman--Harris window (sidelobes 92 dB down, so
a target leaks into a few range bins only) and an FFT. A first guess of the noise power
is the lower quartile of the bins' power (a complex Gaussian bin's power is exponential:
its quartile is ``-ln(3/4)`` times its mean; a target in up to three quarters of the bins
only biases it up a little); the bins of a peak above :data:`PEAK_FACTOR` times it, and
the window's main lobe around, are left out, and the mean power of the others is the
noise's. :func:`auto_alpha` maps the noise relative to the quantizer's step to the dither
scale the Monte Carlo found best (its table in the docstring). :class:`NoiseTracker`
smooths the estimate per sensor for a node.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from pipeline.errors import ParameterError

#: the quantile of the bins' power the estimate reads (robust to targets in 3/4 of them)
NOISE_QUANTILE = 0.25
#: a bin above this many times the first guess of the noise power holds a target (noise
#: alone passes it with probability e^-12)
PEAK_FACTOR = 12.0
#: bins of the window's main lobe on either side of a target's peak (Blackman--Harris: 4)
MAIN_LOBE_BINS = 5
#: the 4-term Blackman--Harris window's coefficients (Harris 1978, -92 dB sidelobes)
_BH4 = (0.35875, 0.48829, 0.14128, 0.01168)


@lru_cache(maxsize=8)
def _window(n: int) -> np.ndarray:
    """The periodic 4-term Blackman--Harris window of n points (read-only)."""
    k = 2.0 * np.pi * np.arange(n) / n  # periodic: the FFT's
    a0, a1, a2, a3 = _BH4
    w = a0 - a1 * np.cos(k) + a2 * np.cos(2 * k) - a3 * np.cos(3 * k)
    w.flags.writeable = False
    return w


def estimate_noise_sigma(frames: np.ndarray, samples_per_ramp: int) -> np.ndarray:
    """Std of each of I and Q of the white noise of each frame, frame units: (B,).

    ``frames``: (B, M, 2) complex of whole ramps (M = R N, ``N = samples_per_ramp``).
    With R >= 2 the R - 1 differences of consecutive ramps are used (what does not change
    from ramp to ramp cancels; their noise is sqrt(2) times the frame's), with R = 1 the
    ramp. Each is windowed and transformed; the mean of ``|X|^2`` over the bins away
    from the peaks (module docstring), the ramps and the antennas is
    ``2 sigma^2 sum(w^2)`` (times 2 for differences). Vectorized over the batch."""
    f = np.asarray(frames)
    if f.ndim != 3 or f.shape[-1] != 2:
        raise ParameterError(f"frames must have shape (B, M, 2), got {f.shape}")
    n = int(samples_per_ramp)
    if n < 8 or f.shape[1] % n:
        raise ParameterError(f"frames of M={f.shape[1]} are not whole ramps of N={n} (N >= 8)")
    r = f.shape[1] // n
    ramps = f.reshape(f.shape[0], r, n, 2)
    scale = 1.0
    if r >= 2:
        ramps = np.diff(ramps, axis=1)
        scale = 2.0
    w = _window(n)
    # (B, R', 2, N): the FFT along the last, contiguous axis
    spec = np.fft.fft(np.ascontiguousarray(ramps.transpose(0, 1, 3, 2)) * w, axis=-1)
    power = spec.real ** 2 + spec.imag ** 2
    per_bin = 2.0 * scale * float(np.sum(w * w))  # E|X|^2 of a noise bin over sigma^2
    b = f.shape[0]
    flat = power.reshape(b, -1)
    kq = int(NOISE_QUANTILE * (flat.shape[1] - 1))
    first = np.partition(flat, kq, axis=1)[:, kq] / -math.log1p(-NOISE_QUANTILE)
    # the bins of targets: above PEAK_FACTOR times the first guess in any ramp or antenna,
    # widened by the window's main lobe; the mean of the others is the noise's
    peak = (power > PEAK_FACTOR * first[:, None, None, None]).any(axis=(1, 2))  # (B, N)
    h = MAIN_LOBE_BINS  # near: a peak within h bins, circularly (a running sum of the padded peaks)
    run = np.concatenate([peak[:, n - h:], peak, peak[:, :h]], axis=1).cumsum(axis=1, dtype=np.int32)
    near = (run[:, 2 * h:] - np.concatenate([np.zeros((b, 1), np.int32), run[:, :n - 1]], axis=1)) > 0
    keep = ~near[:, None, None, :]
    count = keep.sum(axis=(1, 2, 3)) * power.shape[1] * 2
    total = np.where(keep, power, 0.0).sum(axis=(1, 2, 3))
    mean = np.where(count > 0, total / np.maximum(count, 1), first)
    return np.sqrt(mean / per_bin)


#: the Monte Carlo's best alpha against rho = noise_sigma / delta (see :func:`auto_alpha`)
AUTO_ALPHA_RHO = (0.0, 0.004, 0.012, 0.033)
AUTO_ALPHA_BEST = (1.0, 1.0, 0.6, 0.45)


def auto_alpha(noise_sigma, delta) -> np.ndarray:
    """The dither scale for sensor noise ``noise_sigma`` (std of I and of Q) under a
    quantizer step ``delta`` (same units; scalars or (B,)): alpha in [0, 1], (B,) or ().

    Piecewise linear in ``rho = noise_sigma / delta`` through :data:`AUTO_ALPHA_RHO` ->
    :data:`AUTO_ALPHA_BEST`, constant beyond the ends: the full dither without noise, less
    as the noise itself dithers the quantizer. From the Monte Carlo sweep
    (``benchmarks/sweep_alpha.py --runs 2000 --workers 2``: cml, 1-bit M = 512, continuous
    scenes over 3-150 m, |theta| <= 60 deg, weaker amplitude in [0.1, 1], seed 0, 2000 runs
    a point; rho: the median over the runs of K = 1 and 2; errors in m, K = 1 median and
    K = 2 median / weakest mean)::

        sigma  rho     alpha: 0        0.3          0.45         0.6          1          rule
        0      0       0.085 .29/4.5   0.075 .21/1.3 0.111 .16/.83 0.101 .17/.97 0.055 .17/.47  1
        0.01   0.004   0.110 .25/4.2   0.127 .23/1.4 0.127 .21/.94 0.129 .21/1.2 0.109 .23/.65  1
        0.03   0.012   0.168 .32/4.0   0.172 .30/1.5 0.176 .29/1.2 0.170 .30/1.4 0.181 .34/.91  0.6
        0.1    0.033   0.303 .51/3.2   0.294 .48/1.9 0.289 .48/1.8 0.308 .51/1.9 0.369 .63/1.8  0.45
        0.3    0.072   0.513 .85/3.4   0.548 .90/3.0 0.554 .90/3.0 0.590 .97/3.4 0.799 1.2/4.9  0.45

    From rho ~ 0.03 on the curves are flat between alpha 0.25 and 0.6 within the sweep's
    noise (a few %; at sigma = 0.3 the 4000-run rows put 0.25 4 % behind 0.45), and the
    committed chamber recording (rho ~ 0.07, README) puts its best at 0.45 over ten dither
    seeds (0.228 m, against 0.263 m at 0.25): the rule stays at 0.45 there, the default's
    value. The full dither wins clearly without noise (K = 1 and the weaker of two targets)
    and loses clearly with much (sigma = 0.3: 0.80 m against 0.55 m)."""
    s = np.asarray(noise_sigma, dtype=float)
    d = np.asarray(delta, dtype=float)
    if not (np.all(np.isfinite(s)) and np.all(s >= 0)):
        raise ParameterError(f"noise_sigma must be finite and >= 0, got {np.ravel(s)[:4].tolist()}")
    if not (np.all(np.isfinite(d)) and np.all(d > 0)):
        raise ParameterError(f"delta must be finite and > 0, got {np.ravel(d)[:4].tolist()}")
    return np.interp(s / d, AUTO_ALPHA_RHO, AUTO_ALPHA_BEST)


#: frames over which :class:`NoiseTracker` averages a sensor's noise (an exponential
#: average of this time constant once that many frames came; 1 s at 20 frames/s)
NOISE_SMOOTHING_FRAMES = 20


@dataclass
class _SensorNoise:
    variance: float
    frames: int
    alpha: float = float("nan")


class NoiseTracker:
    """Each sensor's noise, estimated from its full-resolution frames and smoothed, and
    the dither scale :func:`auto_alpha` picks from it. One entry per sensor (a node forgets
    a sensor with :meth:`forget` when it expires, so the state stays bounded by the sensors
    alive). The variance is averaged: a plain mean over the first
    :data:`NOISE_SMOOTHING_FRAMES` frames, then an exponential average of that time
    constant. ``samples_per_ramp``: N of the frames (a frame that is not whole ramps of N
    is taken as one ramp)."""

    def __init__(self, samples_per_ramp: int, smoothing_frames: int = NOISE_SMOOTHING_FRAMES):
        if isinstance(smoothing_frames, bool) or not isinstance(smoothing_frames, int) or smoothing_frames < 1:
            raise ParameterError(f"smoothing_frames={smoothing_frames!r} must be an integer >= 1")
        self.samples_per_ramp = int(samples_per_ramp)
        self.smoothing_frames = smoothing_frames
        self._sensors: dict[str, _SensorNoise] = {}

    def update(self, sensor_ids: list[str], frames: np.ndarray) -> np.ndarray:
        """Estimate the noise of ``frames`` (B, M, 2) (frame b from sensor_ids[b]), fold it
        into each sensor's average (frames in batch order) and return the smoothed sigma
        of each frame's sensor after its frame, (B,)."""
        f = np.asarray(frames)
        n = self.samples_per_ramp if f.shape[1] % self.samples_per_ramp == 0 else f.shape[1]
        var = estimate_noise_sigma(f, n) ** 2
        out = np.empty(var.shape)
        for i, (sid, v) in enumerate(zip(sensor_ids, var.tolist())):  # one dict update a frame
            st = self._sensors.get(sid)
            if st is None:
                st = self._sensors[sid] = _SensorNoise(v, 1)
            else:
                st.frames += 1
                st.variance += (v - st.variance) / min(st.frames, self.smoothing_frames)
            out[i] = st.variance
        return np.sqrt(out)

    def set_alpha(self, sensor_ids: list[str], alpha: np.ndarray) -> None:
        """Remember the dither scale each sensor's last frame was quantized with."""
        for sid, a in zip(sensor_ids, np.broadcast_to(alpha, (len(sensor_ids),)).tolist()):
            if sid in self._sensors:
                self._sensors[sid].alpha = a

    def health(self, sensor_id: str) -> dict:
        """``{"noise_sigma": ..., "alpha": ..., "noise_frames": ...}`` of a sensor (empty
        before its first frame)."""
        st = self._sensors.get(sensor_id)
        if st is None:
            return {}
        out = {"noise_sigma": float(np.sqrt(st.variance)), "noise_frames": st.frames}
        if np.isfinite(st.alpha):
            out["alpha"] = st.alpha
        return out

    def snapshot(self) -> dict[str, dict]:
        """:meth:`health` of every sensor tracked, by sensor id."""
        return {sid: self.health(sid) for sid in list(self._sensors)}

    def forget(self, sensor_id: str) -> None:
        self._sensors.pop(sensor_id, None)

    def __len__(self) -> int:
        return len(self._sensors)
