"""Cramer-Rao bounds on the targets' positions from unquantized and from dithered b-bit
frames in white Gaussian noise.

Signal model (:mod:`radar_driver.model`, eq. 2): measurement m on antenna p of target k is
``A_k exp(-i 4 pi f_m R_k / c) G_p(theta_k)`` with ``G_1 = 1``,
``G_2 = exp(i kappa sin(theta))``, ``kappa = 2 pi f0 d / c`` (positive angle: antenna 2
leads). The parameters of target k are ``(R_k [m], theta_k [rad], Re A_k, Im A_k)``, P = 4K
of them in that order per target. A frame of M measurements, 2 antennas and I/Q gives
L = 4M real samples ``s_l``, laid out as the quantizer lays out its codes: (M, antenna, I/Q)
in C order.

Noise ``n_l ~ N(0, sigma^2)`` on every real sample (std sigma on I and on Q, frame units).
Per real sample the Fisher information is ``w_l (ds_l/dtheta)(ds_l/dtheta)^T`` with

* unquantized: ``w = 1 / sigma^2``;
* 1 bit, code ``[s + d + n >= 0]`` with the known dither d:
  ``w = phi(z)^2 / (sigma^2 Phi(z) (1 - Phi(z)))``, ``z = (s + d) / sigma``
  (:func:`weights_1bit`, computed in logs);
* b bits of step delta (levels of :mod:`pipeline.dsp.quantize`, thresholds ``j delta``):
  ``w = sum_q (phi(a_q) - phi(b_q))^2 / (sigma^2 P_q)`` over the code intervals
  ``[a_q, b_q)`` (standardized) of probability P_q (:func:`weights_bits`).

The expected information over the dither ``d = alpha delta u``, ``u ~ U[-1/2, 1/2)`` (what
the quantizer draws), is the mean of w over it: exact for 1 bit from a table of the
integral of ``phi^2 / (Phi (1 - Phi))`` (:func:`weights_1bit_expected`), by the midpoint
rule for b bits. The inverse of the Fisher matrix bounds the covariance of any unbiased
estimator; :func:`position_covariance` maps its (R, theta) blocks to x, y
(``x = R cos theta``, ``y = R sin theta``, :func:`radar_driver.model.polar_to_xy`).

Shapes: batch axis first; scenes (B, K); samples (B, L); Jacobians (B, L, P);
Fisher matrices (B, P, P).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from radar_driver.model import RadarConfig, antenna_phase_rad

from pipeline.errors import ParameterError
from pipeline.dsp.quantize import check_bits


def ndtr(x):
    """The standard normal CDF, ``scipy.special.ndtr``; scipy.special imported on first use
    (~0.12 s: a process that never asks for an uncertainty does not pay it)."""
    from scipy.special import ndtr as phi

    return phi(x)


def log_ndtr(x):
    """``log`` of the standard normal CDF, ``scipy.special.log_ndtr`` (imported on first use)."""
    from scipy.special import log_ndtr as log_phi

    return log_phi(x)

#: parameters per target: range (m), angle (rad), Re A, Im A
PARAMS_PER_TARGET = 4
_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)
#: the 1-bit table: standardized margins z in [-Z_MAX, Z_MAX] in steps of Z_STEP
Z_MAX = 40.0
Z_STEP = 1e-3


def _check_sigma(sigma) -> np.ndarray:
    s = np.asarray(sigma, dtype=float)
    if not (np.all(np.isfinite(s)) and np.all(s > 0)):
        raise ParameterError(f"noise sigma must be finite and > 0, got {np.ravel(s)[:4].tolist()}")
    return s


def _per_batch(v, ndim: int) -> np.ndarray:
    """A scalar or (B,) value shaped to broadcast against a (B, ...) array of ``ndim`` dims."""
    v = np.asarray(v, dtype=float)
    return v.reshape(v.shape + (1,) * (ndim - v.ndim)) if v.ndim else v


# -- the signal and its derivatives ----------------------------------------------------
def signal_jacobian(range_m: np.ndarray, angle_rad: np.ndarray, amplitude: np.ndarray, config: RadarConfig,
                    ramps: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Noiseless real samples and their derivatives for a batch of scenes of whole ramps.

    range_m, angle_rad, amplitude : (B, K) ranges (m), angles (rad, positive = antenna 2
        leads) and complex amplitudes.
    ramps : whole ramps per frame (default ``config.ramps_per_frame``); M = ramps * N.

    Returns ``s`` (B, L) and ``ds`` (B, L, 4K), L = 4M, float64: sample l of
    (measurement, antenna, I/Q) in C order; parameter columns (R_k, theta_k, Re A_k, Im A_k)
    for k = 0 .. K-1.
    """
    r = np.atleast_2d(np.asarray(range_m, dtype=float))
    th = np.atleast_2d(np.asarray(angle_rad, dtype=float))
    a = np.atleast_2d(np.asarray(amplitude, dtype=complex))
    if not (r.shape == th.shape == a.shape) or r.ndim != 2:
        raise ParameterError(f"range_m {r.shape}, angle_rad {th.shape}, amplitude {a.shape} must share one (B, K)")
    reps = config.ramps_per_frame if ramps is None else ramps
    if isinstance(reps, bool) or not isinstance(reps, (int, np.integer)) or reps < 1:
        raise ParameterError(f"ramps={ramps!r} must be an integer >= 1")
    b, k = r.shape
    f = config.frequencies_hz(np.arange(config.samples_per_ramp))  # (N,)
    kr = 4.0 * np.pi / config.c_m_s
    steer = np.exp(-1j * kr * f[None, :, None] * r[:, None, :])  # (B, N, K)
    kappa_cos = antenna_phase_rad(np.full(1, np.pi / 2), config)[0] * np.cos(th)  # d/dtheta of the phase
    g2 = np.exp(1j * antenna_phase_rad(th, config))  # (B, K)
    gains = np.stack([np.ones_like(g2), g2], axis=-1)  # (B, K, 2)
    unit = steer[..., None] * gains[:, None]  # (B, N, K, 2): one target of amplitude 1
    per = unit * a[:, None, :, None]  # (B, N, K, 2)
    d = np.empty((b, config.samples_per_ramp, 2, k, PARAMS_PER_TARGET), dtype=complex)
    dt = np.moveaxis(per, 2, 3)  # (B, N, 2, K)
    d[..., 0] = dt * (-1j * kr * f)[None, :, None, None]
    d[..., 1] = 0.0
    d[:, :, 1, :, 1] = dt[:, :, 1, :] * (1j * kappa_cos)[:, None, :]
    d[..., 2] = np.moveaxis(unit, 2, 3)
    d[..., 3] = 1j * d[..., 2]
    s = per.sum(axis=2)  # (B, N, 2)
    s_real = np.stack([s.real, s.imag], axis=-1)  # (B, N, 2, 2)
    d_real = np.stack([d.real, d.imag], axis=3).reshape(b, config.samples_per_ramp, 2, 2, k * PARAMS_PER_TARGET)
    s_real = np.tile(s_real, (1, reps, 1, 1)).reshape(b, -1)
    d_real = np.tile(d_real, (1, reps, 1, 1, 1)).reshape(b, s_real.shape[1], k * PARAMS_PER_TARGET)
    return s_real, d_real


def fisher(ds: np.ndarray, weights) -> np.ndarray:
    """Fisher matrices ``sum_l w_l ds_l ds_l^T``: ds (B, L, P), weights scalar, (B,) or
    (B, L). Returns (B, P, P)."""
    ds = np.asarray(ds, dtype=float)
    w = np.asarray(weights, dtype=float)
    dst = np.swapaxes(ds, 1, 2)  # (B, P, L): batched matrix products (BLAS), not einsum's loops
    if w.ndim < 2:
        return _per_batch(w, 3) * (dst @ ds)
    return (dst * w[:, None, :]) @ ds


# -- per-sample information weights ---------------------------------------------------------
def weights_unquantized(sigma) -> np.ndarray:
    """``1 / sigma^2`` (sigma: scalar or (B,), std per real sample, frame units)."""
    return 1.0 / _check_sigma(sigma) ** 2


def _h(z: np.ndarray) -> np.ndarray:
    """``phi(z)^2 / (Phi(z) (1 - Phi(z)))``, in logs (no underflow to 0/0)."""
    return np.exp(-z * z - 2.0 * _LOG_SQRT_2PI - log_ndtr(z) - log_ndtr(-z))


def weights_1bit(s: np.ndarray, dither: np.ndarray | None, sigma) -> np.ndarray:
    """Information weight of each 1-bit code ``[s + d + n >= 0]``, (B, L).

    s, dither : (B, L) real samples and their known dither (None: no dither), frame units.
    sigma : scalar or (B,), noise std per real sample.
    """
    sg = _per_batch(_check_sigma(sigma), 2)
    w = np.asarray(s, dtype=float) if dither is None else np.asarray(s, dtype=float) + dither
    return _h(w / sg) / sg**2


@lru_cache(maxsize=1)
def _h_table() -> tuple[np.ndarray, np.ndarray]:
    """z grid and the running integral H(z) = int_{-Z_MAX}^{z} h (trapezoids), read-only."""
    z = np.linspace(-Z_MAX, Z_MAX, int(round(2 * Z_MAX / Z_STEP)) + 1)
    h = _h(z)
    big_h = np.concatenate([[0.0], np.cumsum(0.5 * (h[1:] + h[:-1]) * np.diff(z))])
    z.flags.writeable = False
    big_h.flags.writeable = False
    return z, big_h


def h_integral() -> float:
    """``int phi(z)^2 / (Phi(z) (1 - Phi(z))) dz`` over the real line (1.806): a dithered
    1-bit sample whose dither spreads ``s + d`` uniformly over a width ``a >> sigma`` around
    0 carries this times ``1 / (a sigma)``."""
    return float(_h_table()[1][-1])


def weights_1bit_expected(s: np.ndarray, dither_width, sigma) -> np.ndarray:
    """Mean information weight of 1-bit codes over a uniform dither of width ``a``
    (``d ~ U[-a/2, a/2)``; the quantizer's ``a = alpha delta``), (B, L).

    s : (B, L) real samples; dither_width, sigma : scalars or (B,), frame units. Exact up
    to the table's trapezoids: ``(H((s + a/2)/sigma) - H((s - a/2)/sigma)) / (a sigma)``;
    the point value where ``a < 0.05 sigma``.
    """
    sg = _per_batch(_check_sigma(sigma), 2)
    a = np.asarray(dither_width, dtype=float)
    if not (np.all(np.isfinite(a)) and np.all(a >= 0)):
        raise ParameterError(f"dither_width must be finite and >= 0, got {np.ravel(a)[:4].tolist()}")
    a = _per_batch(a, 2)
    s = np.asarray(s, dtype=float)
    half = 0.5 * a / sg
    zs = s / sg
    wide = np.broadcast_to(half > 0.025, s.shape)
    if wide.all():
        avg = (_big_h(zs + half) - _big_h(zs - half)) / (2.0 * half)
    else:
        avg = _h(zs)
        with np.errstate(invalid="ignore", divide="ignore"):
            avg[wide] = ((_big_h(zs + half) - _big_h(zs - half)) / (2.0 * half))[wide]
    return avg / sg**2


def _big_h(x: np.ndarray) -> np.ndarray:
    """H(x) by linear interpolation in the uniform table (constant beyond its ends)."""
    _, table = _h_table()
    pos = np.clip((x + Z_MAX) / Z_STEP, 0.0, table.size - 1.0)
    i = np.minimum(pos.astype(np.int64), table.size - 2)
    frac = pos - i
    return table[i] + frac * (table[i + 1] - table[i])


def weights_bits(s: np.ndarray, dither: np.ndarray | None, sigma, delta, bits: int) -> np.ndarray:
    """Information weight of each b-bit code of :func:`pipeline.dsp.quantize.quantize`, (B, L).

    Code q covers ``[delta (q - 2**(b-1)), delta (q - 2**(b-1) + 1))`` of ``s + d + n``,
    the end codes open to +-infinity. s, dither : (B, L); sigma, delta : scalars or (B,).
    One pass per level (levels are few; samples vectorized).
    """
    bits = check_bits(bits)
    sg = _per_batch(_check_sigma(sigma), 2)
    dl = _per_batch(delta, 2)
    w = np.asarray(s, dtype=float) if dither is None else np.asarray(s, dtype=float) + dither
    if bits == 1:
        return _h(w / sg) / sg**2
    half = 1 << (bits - 1)
    out = np.zeros(np.broadcast_shapes(w.shape, np.shape(sg), np.shape(dl)))
    for j in range(-half, half):
        lo = -np.inf if j == -half else (j * dl - w) / sg
        hi = np.inf if j == half - 1 else ((j + 1) * dl - w) / sg
        lo, hi = np.broadcast_to(lo, out.shape), np.broadcast_to(hi, out.shape)
        upper = lo + hi > 0  # the interval lies mostly above 0: difference of upper tails
        p = np.where(upper, ndtr(-lo) - ndtr(-hi), ndtr(hi) - ndtr(lo))
        dp = _phi(lo) - _phi(hi)
        np.add(out, np.divide(dp * dp, p, out=np.zeros_like(p), where=p > 0), out=out)
    return out / sg**2


def _phi(z: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):
        return np.exp(-0.5 * z * z - _LOG_SQRT_2PI)  # 0 at +-inf


def weights_bits_expected(s: np.ndarray, dither_width, sigma, delta, bits: int, nodes: int = 64) -> np.ndarray:
    """Mean of :func:`weights_bits` over ``d ~ U[-a/2, a/2)`` (a = dither_width, scalar or
    (B,)), midpoint rule on ``nodes`` points, (B, L)."""
    a = _per_batch(dither_width, 2)
    total = 0.0
    for u in (np.arange(nodes) + 0.5) / nodes - 0.5:
        total = total + weights_bits(s, a * u, sigma, delta, bits)
    return total / nodes


# -- bounds --------------------------------------------------------------------------------
def crb(fim: np.ndarray) -> np.ndarray:
    """Inverse Fisher matrices (B, P, P): the bound on the parameters' covariance."""
    return np.linalg.inv(np.asarray(fim, dtype=float))


def position_covariance(cov: np.ndarray, range_m: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """Bound on the (x, y) covariance of each target, m^2: (B, K, 2, 2), from the parameter
    bound ``cov`` (B, 4K, 4K) and the true (B, K) ranges (m) and angles (rad), through the
    Jacobian of ``(R cos theta, R sin theta)``."""
    r = np.atleast_2d(np.asarray(range_m, dtype=float))
    th = np.atleast_2d(np.asarray(angle_rad, dtype=float))
    b, k = r.shape
    idx = PARAMS_PER_TARGET * np.arange(k)[:, None] + np.arange(2)  # (K, 2): R_k, theta_k
    block = cov[:, idx[:, :, None], idx[:, None, :]]  # (B, K, 2, 2)
    c, s = np.cos(th), np.sin(th)
    jac = np.stack([np.stack([c, -r * s], -1), np.stack([s, r * c], -1)], -2)  # (B, K, 2, 2)
    return jac @ block @ np.swapaxes(jac, -1, -2)


def position_rms(cov_xy: np.ndarray) -> np.ndarray:
    """RMS position error bound ``sqrt(trace)`` of (..., 2, 2) covariances, m; nan where the
    inverse lost its sign (a target at +-90 deg has no angle information)."""
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.trace(cov_xy, axis1=-2, axis2=-1))


def position_bound(range_m: np.ndarray, angle_rad: np.ndarray, amplitude: np.ndarray, config: RadarConfig,
                   sigma, alpha=None, delta=None, bits: int | None = None, ramps: int | None = None) -> np.ndarray:
    """(x, y) covariance bound (B, K, 2, 2), m^2, of scenes (B, K) measured in noise sigma
    (scalar or (B,)): unquantized when ``bits`` is None; else b-bit codes of step ``delta``
    ((B,) or scalar) with the information averaged over a dither of scale ``alpha``
    (width ``alpha delta``; 0 = no dither)."""
    s, ds = signal_jacobian(range_m, angle_rad, amplitude, config, ramps)
    if bits is None:
        w = weights_unquantized(sigma)
    else:
        if alpha is None or delta is None:
            raise ParameterError("quantized bounds need alpha and delta")
        width = np.asarray(alpha, dtype=float) * np.asarray(delta, dtype=float)
        if bits == 1:
            w = weights_1bit_expected(s, width, sigma)
        else:
            w = weights_bits_expected(s, width, sigma, delta, bits)
    return position_covariance(crb(fisher(ds, w)), range_m, angle_rad)
