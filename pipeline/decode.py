"""Dither-aware decoders: beyond PBP, using the dither to reach estimates consistent
with the codes (the paper's closing remark).

A quantized frame carries its dither seed, so the decoder regenerates xi and delta and
knows, for every real measurement, the quantizer cell that ``Re/Im (Phi X + xi)`` fell
in. Two stages, both batched and on the FFT path for frames of whole ramps:

1. **QIHT** (quantized iterative hard thresholding, joint support):
   ``X <- P_Theta_K(X + mu Phi^* (Z - Q(Phi X + xi)) / M)``, starting from PBP. Forward
   ``Phi X``: one FFT of length N per antenna (times the carrier term), tiled over the
   ramps; adjoint: fold + inverse FFT. Stopping rule: at most ``iters`` iterations; it
   stops earlier once, for 3 iterations in a row, no frame of the batch changed its
   support or its number of consistent codes.
2. **Maximum likelihood on the support** (1-bit): per antenna, the K complex amplitudes
   maximize a logistic likelihood of the codes, ``P(code | x) = sigmoid(s (a^T x + xi) /
   T)``, by Newton steps while the temperature T falls from delta/8 to delta/(2M). As T
   shrinks the estimate moves into the set of amplitudes consistent with every code, whose
   size shrinks like 1/M, where PBP's error shrinks like 1/sqrt(M).

What was measured and kept is in the README (Monte Carlo of DESIGN.md): QIHT alone
brings the K = 1 median error from 1.2 m to about 0.1 m; the ML stage brings it to 0.08 m
and matters most for the weakest of two targets.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from functools import lru_cache

import numpy as np

from radar_driver.model import RadarConfig, carrier

from .errors import DitherUnavailable, ParameterError
from .localize import (DEFAULT_PFA, Detections, back_project, back_project_ramps, check_pfa, detections_from_support,
                       grid_statistic_db, localize, project_theta_k)
from .cml import cml
from .quantize import QuantizedFrames


class Algo(StrEnum):
    """The decoders: ``pbp`` (the paper's eq. 5, any frames), ``qiht`` (dither-aware, on the
    range grid: QIHT then 1-bit likelihood; dithered frames of whole ramps) and ``cml``
    (continuous ranges, maximum likelihood of the codes with their dither and the sensor
    noise, :mod:`pipeline.cml`; quantized or unquantized frames of whole ramps)."""

    PBP = "pbp"
    QIHT = "qiht"
    CML = "cml"


ALGOS = tuple(a.value for a in Algo)

#: dither scale used when none is given: PBP at the paper's best alpha for its noisy
#: chamber (Fig. 5a); qiht wants the full dither; cml at its best on the off-grid noisy
#: chamber recording (0.45-0.6 within 5 % of the best, README)
DEFAULT_ALPHA = {Algo.PBP: 0.55, Algo.QIHT: 1.0, Algo.CML: 0.5}


def default_alpha(algo: str) -> float:
    """The dither scale alpha in [0, 1] to quantize with for decoder ``algo``."""
    return DEFAULT_ALPHA[Algo(algo)]


def ml_temperatures(m: int, steps: int = 8) -> np.ndarray:
    """Temperature schedule of the likelihood stage, in units of delta: ``steps`` values
    falling geometrically from 1/8 to 1/(2M) (the size of a consistent cell), then the
    last one twice more."""
    t = np.geomspace(1 / 8, 1 / (2 * m), max(steps, 1))
    return np.concatenate([t, t[-1:], t[-1:]])


@dataclass(frozen=True)
class DecoderConfig:
    """algo: an :class:`Algo` (or its name). iters / mu: QIHT iterations and step. ml:
    run the likelihood stage (1-bit only). fallback_pbp: decode frames a decoder cannot
    (qiht: without a usable dither or unquantized; qiht and cml: a frequency subset) with
    PBP instead of raising DitherUnavailable. noise_sigma: cml's sensor noise, std of I
    and of Q in frame units (None: estimated from each frame). auto_k: decide each
    frame's count (``K auto``; the K passed to :func:`decode` is then the most), by a
    CFAR test of false-alarm probability ``pfa`` per frame and test (pbp and cml)."""

    algo: Algo = Algo.QIHT
    iters: int = 10
    mu: float = 1.0
    ml: bool = True
    fallback_pbp: bool = False
    noise_sigma: float | None = None
    auto_k: bool = False
    pfa: float = DEFAULT_PFA

    def __post_init__(self) -> None:
        if self.algo not in ALGOS:
            raise ParameterError(f"algo={self.algo!r} is not known; available: {', '.join(ALGOS)}")
        object.__setattr__(self, "algo", Algo(self.algo))
        check_pfa(self.pfa)
        if self.auto_k and self.algo == Algo.QIHT:
            raise ParameterError("K auto needs a decoder that tests each detection: pbp or cml (qiht projects "
                                 "on exactly K bins)")
        if self.noise_sigma is not None and not (np.isfinite(self.noise_sigma) and self.noise_sigma >= 0):
            raise ParameterError(f"noise_sigma={self.noise_sigma!r} must be a finite number >= 0 or None")
        if not (isinstance(self.iters, int) and 0 <= self.iters <= 1000):
            raise ParameterError(f"iters={self.iters!r} must be an integer in [0, 1000]")
        if not 0 < self.mu <= 4:
            raise ParameterError(f"mu={self.mu!r} must be in (0, 4]")


def forward_ramps(x: np.ndarray, config: RadarConfig, ramps: int) -> np.ndarray:
    """``Phi X`` for frames of ``ramps`` whole ramps: (B, N, 2) -> (B, ramps N, 2)."""
    g = np.fft.fft(x * carrier(config)[None, :, None], axis=1)
    return np.tile(g, (1, ramps, 1))


def _requantize(lam: np.ndarray, d: np.ndarray, bits: int) -> np.ndarray:
    """Q_b of the real array ``lam``, ``d`` = delta broadcast against it: real values."""
    half = 1 << (bits - 1)
    return (np.clip(np.floor(lam / d), -half, half - 1) + 0.5) * d


@lru_cache(maxsize=4)
def _dft_table(n: int) -> np.ndarray:
    """exp(-2 pi i k n / N), (N frequencies, N bins); read-only."""
    kk = np.arange(n)
    t = np.exp(-2j * np.pi * np.outer(kk, kk) / n)
    t.flags.writeable = False
    return t


def _check(z, xi, delta, bits, config):
    z = np.asarray(z)
    if z.ndim != 3 or z.shape[-1] != 2:
        raise ParameterError(f"Z must have shape (B, M, 2), got {z.shape}")
    if xi is None:
        raise DitherUnavailable("the dither is needed (non-dithered frame or unknown seed)")
    xi = np.asarray(xi)
    if xi.shape != z.shape:
        raise ParameterError(f"dither shape {xi.shape} does not match Z {z.shape}")
    delta = np.asarray(delta, dtype=float).reshape(-1)
    if delta.shape != (z.shape[0],) or np.any(~np.isfinite(delta)) or np.any(delta <= 0):
        raise ParameterError(f"delta must be ({z.shape[0]},) finite values > 0, got shape {delta.shape}")
    if not (isinstance(bits, (int, np.integer)) and 1 <= bits <= 16):
        raise ParameterError(f"bits={bits!r} must be an integer in [1, 16]")
    n = config.samples_per_ramp
    if z.shape[1] % n:
        raise ParameterError(f"M={z.shape[1]} is not a whole number of ramps of {n}: the dither-aware "
                             "decoder runs on the FFT path only")
    return z, xi, delta


def consistency(x: np.ndarray, z: np.ndarray, xi: np.ndarray, delta, bits: int, config: RadarConfig) -> np.ndarray:
    """Fraction of the real codes of each frame that ``Q(Phi X + xi)`` reproduces: (B,).

    x: (B, N, 2) estimate; z: the quantized values (B, M, 2); xi: the dither."""
    z, xi, delta = _check(z, xi, delta, bits, config)
    ramps = z.shape[1] // config.samples_per_ramp
    lam = forward_ramps(x, config, ramps) + xi
    d = delta[:, None, None]
    same = sum((np.abs(_requantize(part(lam), d, bits) - part(z)) < 1e-9 * d).sum(axis=(1, 2))
               for part in (np.real, np.imag))
    return same / (2 * z.shape[1] * 2)


def qiht(z: np.ndarray, xi: np.ndarray, delta, bits: int, config: RadarConfig, k: int, iters: int = 10,
         mu: float = 1.0) -> tuple[np.ndarray, np.ndarray, int]:
    """QIHT from PBP. z: quantized values Z (B, M, 2); xi: the dither (B, M, 2); delta (B,).

    Returns (X (B, N, 2), support (B, K) strongest first, iterations run). Z is
    ``Q(Gamma + xi)``: the dither is added before quantization and not removed."""
    z, xi, delta = _check(z, xi, delta, bits, config)
    n = config.samples_per_ramp
    b, m, _ = z.shape
    ramps = m // n
    car = carrier(config)[None, :, None]
    # real views (B, R, N, 2 antennas, 2 re/im) of Z and xi, ramp by ramp
    zr = np.ascontiguousarray(z).view(float).reshape(b, ramps, n, 2, 2)
    xr = np.ascontiguousarray(xi).view(float).reshape(b, ramps, n, 2, 2)
    d = delta[:, None, None, None, None]
    scale = mu * (n / m)
    x, support = project_theta_k(back_project_ramps(z, config), k)
    prev_sup, prev_bad, stable, done = np.sort(support, axis=1), None, 0, 0
    z_pos, z_twice = zr > 0, 2 * zr  # 1 bit: a code that disagrees leaves a residual of 2 Z
    for it in range(iters):
        g = np.fft.fft(x * car, axis=1).view(float).reshape(b, 1, n, 2, 2)  # Phi X, one ramp
        lam = g + xr
        if bits == 1:
            wrong = (lam >= 0) != z_pos
            resid = np.where(wrong, z_twice, 0.0)
            bad = np.count_nonzero(wrong.reshape(b, -1), axis=1)
        else:
            resid = zr - _requantize(lam, d, bits)
            bad = np.count_nonzero(resid.reshape(b, -1), axis=1)
        folded = resid.sum(axis=1).reshape(b, n, 4).view(complex)  # (B, N, 2)
        step = np.fft.ifft(folded, axis=1) * np.conj(car) * scale
        x, support = project_theta_k(x + step, k)
        sup_sorted = np.sort(support, axis=1)
        same = prev_bad is not None and np.array_equal(sup_sorted, prev_sup) and np.array_equal(bad, prev_bad)
        stable = stable + 1 if same else 0
        prev_sup, prev_bad, done = sup_sorted, bad, it + 1
        if stable >= 3:
            break
    return x, support, done


def ml_refine(z: np.ndarray, xi: np.ndarray, delta, support: np.ndarray, x0: np.ndarray, config: RadarConfig,
              temperatures=None) -> np.ndarray:
    """1-bit maximum likelihood of the support amplitudes, per antenna.

    z, xi: (B, M, 2); support: (B, K); x0: starting amplitudes (B, K, 2). Returns (B, K, 2)."""
    z, xi, delta = _check(z, xi, delta, 1, config)
    b, m, _ = z.shape
    n = config.samples_per_ramp
    k = support.shape[1]
    if temperatures is None:
        temperatures = ml_temperatures(m)
    # Phi restricted to the support, from a DFT table: Phi_mn = carrier_n exp(-2 pi i (m mod N) n / N)
    phi = _dft_table(n)[:, support] * carrier(config)[support][None]  # (N, B, K)
    phi = np.transpose(phi, (1, 0, 2))  # (B, N, K): one ramp; the others repeat it
    ramps = m // n
    a_re = np.concatenate([phi.real, -phi.imag], axis=2)  # Re(Phi x) = a_re . [Re x, Im x]
    a_im = np.concatenate([phi.imag, phi.real], axis=2)
    a = np.tile(np.concatenate([a_re, a_im], axis=1), (1, ramps, 1))  # (B, 2M, 2K), rows: ramp-major
    out = np.empty((b, k, 2), dtype=complex)
    for p in range(2):
        zp = z[:, :, p].reshape(b, ramps, n)
        xp = xi[:, :, p].reshape(b, ramps, n)
        s = np.sign(np.concatenate([zp.real, zp.imag], axis=2)).reshape(b, -1)  # (B, 2M), ramp-major like a
        o = np.concatenate([xp.real, xp.imag], axis=2).reshape(b, -1)
        th = np.concatenate([x0[:, :, p].real, x0[:, :, p].imag], axis=1)  # (B, 2K)
        for t in temperatures:
            sig = (t * delta)[:, None]
            u = s * (np.einsum("bmj,bj->bm", a, th) + o) / sig
            q = 0.5 * (1.0 - np.tanh(0.5 * u))  # 1 - sigmoid(u), stable
            grad = np.einsum("bmj,bm->bj", a, s * q / sig)
            w = q * (1.0 - q) / sig**2
            hess = np.matmul(np.transpose(a * w[:, :, None], (0, 2, 1)), a)
            hess += np.eye(2 * k)[None] * (1e-9 * np.trace(hess, axis1=1, axis2=2)[:, None, None] + 1e-300)
            step = np.linalg.solve(hess, grad[..., None])[..., 0]
            norm = np.linalg.norm(step, axis=1, keepdims=True)
            th = th + step * np.minimum(1.0, delta[:, None] / np.maximum(norm, 1e-300))  # at most delta
        out[:, :, p] = th[:, :k] + 1j * th[:, k:]
    return out


def decode(z: np.ndarray, xi: np.ndarray | None, delta, bits: int | None, config: RadarConfig, k: int,
           decoder: DecoderConfig = DecoderConfig(), indices: np.ndarray | None = None) -> Detections:
    """Targets of a batch of frames with the configured decoder: the one place where a
    decoder is chosen.

    z: (B, M, 2) quantized values Z (``bits`` >= 1, step ``delta`` (B,), dither ``xi``
    (B, M, 2) or None) or full-resolution frames (``bits=None``); ``indices``: the
    frequency subset of the dense path (None = whole ramps). PBP decodes anything. A
    dither-aware decoder needs quantized frames of whole ramps with their dither; other
    frames go to PBP if ``decoder.fallback_pbp``, else raise DitherUnavailable. ``cml``
    decodes quantized frames (with or without dither) and unquantized ones (least
    squares), of whole ramps."""
    z = np.asarray(z)
    pfa = decoder.pfa if decoder.auto_k else None
    if decoder.algo == Algo.PBP:
        return localize(z, config, k, indices, pfa)
    if decoder.algo == Algo.CML and indices is None:
        return cml(z, xi if bits is not None else None, delta if bits is not None else None, bits, config, k,
                   noise_sigma=decoder.noise_sigma, pfa=pfa).detections(config)
    if xi is None or bits is None or indices is not None:
        if decoder.fallback_pbp:
            return localize(z, config, k, indices, pfa)
        what = ("frames are a frequency subset" if indices is not None else "frames are not quantized"
                if bits is None else "frame is not dithered")
        needs = ("frames of whole ramps" if decoder.algo == Algo.CML else
                 "the dither of every frame (a dithered frame of whole ramps with a known seed)")
        raise DitherUnavailable(f"{decoder.algo} needs {needs}; this {what}. Use PBP, or ask for the PBP fallback")
    x, support, _ = qiht(z, xi, delta, bits, config, k, decoder.iters, decoder.mu)
    if decoder.ml and bits == 1:
        x0 = np.take_along_axis(x, support[:, :, None], axis=1)
        amp = ml_refine(z, xi, delta, support, x0, config)
        x = np.zeros_like(x)
        np.put_along_axis(x, support[:, :, None], amp, axis=1)
    return detections_from_support(x, support, config, grid_statistic_db(back_project(z, config), support))


def decode_batch(frames: QuantizedFrames | np.ndarray, config: RadarConfig, k: int,
                 decoder: DecoderConfig = DecoderConfig()) -> Detections:
    """Targets of a batch: quantized frames (their dither regenerated from their seeds)
    or full-resolution frames (B, M, 2) complex. What the localizer node and offline
    re-processing call; see :func:`decode` for the rules."""
    if isinstance(frames, QuantizedFrames):
        xi = None if decoder.algo == Algo.PBP else frames.dither()  # PBP does not use it: skip regenerating it
        return decode(frames.values(), xi, frames.delta, frames.bits, config, k, decoder)
    return decode(np.asarray(frames).astype(np.complex128), None, None, None, config, k, decoder)
