"""How likely noise alone makes each of cml's targets: its p-value.

Target j's statistic is a score test of the frame given the other targets: the residual of
the model without j (unquantized frames: ``y - model``; codes: the score of the logistic
likelihood the decoder maximizes, at its last scale, :func:`code_score`) back-projected at
j's range and phase step (its joint energy over the antennas), over that residual's mean
joint energy per range bin inside the gate, away from the targets
(:func:`leave_one_out_statistic`), less what refitting the other targets would explain
(the efficient score: their ranges, phase steps and amplitudes are nuisance parameters).
The residual without j is what the frame would hold if j
were noise, so the p-value is the chance that noise alone makes the largest statistic over
the search reach it (:func:`p_value`): the search spans the gate's range bins and, with a
phase step between ramps, the phase step too (a two-dimensional field, whose largest
value is likelier than a one-dimensional one's: the Euler-characteristic density of a
chi-square field, :func:`moving_p_value`). The search's effective size per bin is measured
on noise-only frames (:data:`STATIC_CELLS_PER_BIN`, :data:`MOVING_AREA_PER_BIN`; the
figures: docs/science.md). The score, not the linear residual, is read for codes: the
linear residual of a 1-bit frame holds the quantizer's harmonics of the other targets,
which the likelihood explains.

Shapes: frames (B, M, 2) complex or codes (B, M, 2, 2) (batch, measurement, antenna,
I/Q), M = R N whole ramps; per target (B, K)."""

from __future__ import annotations

import numpy as np

from radar_driver.model import RadarConfig

from pipeline.dsp.cml.count import COUNT_GUARD_BINS as GUARD_BINS, SEARCH_CELLS_PER_BIN, precision_floor
from pipeline.dsp.cml.options import LOGISTIC_PER_SIGMA
from pipeline.dsp.gate import RangeGate
from pipeline.dsp.localize import cfar_p_value, to_db
from pipeline.dsp.uncertainty import MOVING_PARAMS, PARAMS, jacobian

#: independent cells a range bin of the static model's search is worth: the count test's
#: (measured on noise-only frames for both)
STATIC_CELLS_PER_BIN = SEARCH_CELLS_PER_BIN
#: the area (the second Lipschitz-Killing curvature, in :func:`moving_p_value`) a range bin
#: of the search over range and phase step is worth, measured on noise-only frames
#: (docs/science.md)
MOVING_AREA_PER_BIN = 2.4
#: values in the largest array of a block of the computation, (B, J, per K, S) (8 MB: faster than 32)
BLOCK_VALUES = 1 << 20


def moving_p_value(x: np.ndarray, bins: float) -> np.ndarray:
    """The chance that the largest of a chi-square field of 4 degrees of freedom (two
    antennas' complex back projection, normalized: ``x`` = energy over its mean) over
    ``bins`` range bins and the phase step's circle reaches ``x`` (any shape): ``1 - exp(-A
    rho2(u))``, u = 4 x, ``rho2(u) = u (u - 3) e^(-u/2) / (4 pi)`` the field's EC density in
    two dimensions (Worsley 1994), A = :data:`MOVING_AREA_PER_BIN` ``bins``; below the
    density's peak (u = 6) it is ~1 (the approximation holds in the tail)."""
    with np.errstate(over="ignore", invalid="ignore"):
        u = np.maximum(4.0 * np.asarray(x, dtype=float), 6.0)
        rho2 = u * (u - 3.0) * np.exp(-u / 2.0) / (4.0 * np.pi)
        p = -np.expm1(-MOVING_AREA_PER_BIN * max(bins, 1.0) * rho2)
    return np.where(np.isnan(x), np.nan, p)


def p_value(x: np.ndarray, bins: float, moving: bool) -> np.ndarray:
    """The p-value of statistics ``x`` (linear, any shape) of a search over ``bins`` range
    bins, with (``moving``) or without the phase step between ramps."""
    if moving:
        return moving_p_value(x, bins)
    return np.where(np.isnan(x), np.nan, cfar_p_value(to_db(x), STATIC_CELLS_PER_BIN * bins))


def code_cells(z: np.ndarray, delta, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """The cell ``[lo, hi)`` (B, M, 2, 2) real, frame units, of ``Gamma + xi`` each code
    holds: ``z`` the codes (B, M, 2, 2) or their values (B, M, 2) complex; ``delta``
    scalar or (B,); the end cells open (+-inf)."""
    half = 1 << (bits - 1)
    d = np.asarray(delta, dtype=float).reshape(-1, 1, 1, 1)
    if np.iscomplexobj(z):
        zr = np.ascontiguousarray(z, dtype=complex).view(float).reshape(z.shape + (2,))
        q = np.rint(zr / d + half - 0.5)
    else:
        q = np.asarray(z, dtype=float)
    lo = np.where(q <= 0, -np.inf, (q - half) * d)
    hi = np.where(q >= 2 * half - 1, np.inf, (q - half + 1) * d)
    return lo, hi


def code_score(lam: np.ndarray, lo: np.ndarray, hi: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The score ``g = d log P / d Gamma`` and the curvature ``h = -d^2 log P / d Gamma^2``
    (both shaped as ``lam``) of each real sample's code (cell ``[lo, hi)``) under the
    logistic likelihood of scale ``T = sigma / 1.702`` (``sigma`` (B,) the decoder's last
    ``sigma_eff``) at ``lam`` = model + dither: with ``a, b`` the cell's ends from ``lam``
    in units of T, ``P = F(b) - F(a)``, ``g = (f(a) - f(b)) / (T P)`` (bounded by ``1 /
    T``: a code far from the model weighs no more than one at its edge) and ``h = g^2 -
    (f'(b) - f'(a)) / (T^2 P)`` (>= 0: the logistic's cells are log-concave)."""
    from scipy.special import expit

    t = (np.asarray(sigma, dtype=float) / LOGISTIC_PER_SIGMA).reshape((-1,) + (1,) * (lam.ndim - 1))
    with np.errstate(invalid="ignore"):
        a = np.clip((lo - lam) / t, -700.0, 700.0)
        b = np.clip((hi - lam) / t, -700.0, 700.0)
    fa, fb, ga, gb = expit(a), expit(b), expit(-a), expit(-b)
    p = np.maximum(np.where(a > 0.0, ga - gb, fb - fa), 1e-300)  # both ends above the model: the upper tail's
    g = (fa * ga - fb * gb) / (t * p)
    slope = fb * gb * (gb - fb) - fa * ga * (ga - fa)  # f'(b) - f'(a), f' = f (1 - 2 F)
    return g, np.maximum(g * g - slope / (t * t * p), 0.0)


def leave_one_out_statistic(score, dst: np.ndarray, amplitudes: np.ndarray, nu: np.ndarray, live: np.ndarray, per: int,
                            n: int, inside: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """Each target's statistic (B, K) linear (NaN where not ``live`` (B, K)): the efficient
    score of its amplitudes given the other targets, over the mean per range bin.

    ``dst`` (B, per K, S): the derivatives of the frames' S = R 4N real samples ((ramp,
    sample, antenna, I/Q) in C order) in each target's ``per`` parameters (:func:`jacobian`),
    its amplitudes' ``Re a1, Im a1, Re a2, Im a2`` at 1..4 (the model is linear in them:
    target t's samples are those rows times its ``amplitudes`` (B, K, 2)); ``nu`` (B, K)
    the targets' ranges (bins); ``score(model)``: the residual ``g`` and its curvature ``h``
    (both (B, J, S)) of the frames given J models a frame (B, J, S), model j that of the
    targets besides j (unquantized: ``y - model`` and 1); ``inside`` (N,) bool the range
    bins inside the gate; ``floor`` (B,) the least mean energy per bin. ``g`` less its
    ``h``-weighted projection on the other targets' parameters (what refitting their range,
    phase step and amplitudes would explain) is back-projected on target j's amplitudes
    (``|sum conj(w) g|^2 / N^2`` over ramps and samples, per antenna, summed), over the
    mean of its spectrum's joint energy (``|FFT_N|^2 / N^2`` each ramp and antenna, summed)
    over the bins inside the gate beyond :data:`GUARD_BINS` of every target."""
    b = dst.shape[0]
    k = live.shape[1]
    theta = np.where(live[..., None], np.ascontiguousarray(amplitudes, dtype=complex), 0.0).view(float)  # (B, K, 4)
    d = np.abs((np.arange(n)[None, None, :] - nu[:, :, None] + n / 2) % n - n / 2)
    away = inside[None, :] & ~((d < GUARD_BINS) & live[:, :, None]).any(axis=1)  # (B, N): the bins of the mean
    amp = dst.reshape(b, k, per, -1)[:, :, 1:5]  # (B, K, 4, S), a view: each target's amplitudes
    own = np.matmul(theta[:, :, None, :], amp)[:, :, 0]  # (B, K, S): each target's samples
    others = live[:, None, :] & ~np.eye(k, dtype=bool)[None]  # (B, J, K): the targets besides target j
    g, h = score(np.matmul(others.astype(float), own))  # (B, J, S) each
    if others.any():  # less what refitting the others would explain: the efficient score
        slots = np.array([[t for t in range(k) if t != j] for j in range(k)])  # (J, K - 1): the others' slots
        rows = (slots[..., None] * per + np.arange(per)).reshape(k, -1)  # (J, Q): their parameters, Q = (K-1) per
        keep = np.repeat(np.take_along_axis(others, slots[None], axis=2), per, axis=2)  # (B, J, Q): of live ones
        # (B, J, Q, S): the nuisance parameters' derivatives (two slots: the other one's, a view)
        nuis = dst.reshape(b, k, per, -1)[:, ::-1] if k == 2 else dst[:, rows]
        ns = np.swapaxes(nuis, 2, 3)  # (B, J, S, Q)
        info = np.matmul(nuis * h[:, :, None, :], ns)
        info = info * (keep[..., :, None] & keep[..., None, :]) + np.eye(rows.shape[1]) * ~keep[..., None, :]
        grad = np.where(keep, np.matmul(nuis, g[..., None])[..., 0], 0.0)
        with np.errstate(invalid="ignore"):
            coef = np.linalg.solve(info, grad[..., None])
        g = g - h * np.matmul(ns, coef)[..., 0]
    u = np.matmul(amp, g[..., None])[..., 0]  # (B, J, 4): Re, Im of each antenna's back projection at target j
    energy = (u * u).sum(axis=2) / n ** 2
    spec = np.fft.fft(g.reshape(b, k, -1, n, 2, 2).view(complex)[..., 0], axis=3)  # (B, J, R, N, 2)
    total = (spec.real ** 2 + spec.imag ** 2).sum(axis=(2, 4)) / n ** 2  # (B, J, N)
    mean = np.maximum(np.where(away[:, None], total, 0.0).sum(axis=2) / np.maximum(away.sum(axis=1), 1)[:, None],
                      floor[:, None])
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(live, energy / mean, np.nan)
    return x


def target_p_values(range_m: np.ndarray, amplitudes: np.ndarray, phase_step_rad: np.ndarray, present: np.ndarray,
                    sigma_eff: np.ndarray, z: np.ndarray, xi: np.ndarray | None, delta, bits: int | None,
                    config: RadarConfig, gate: RangeGate | None) -> np.ndarray:
    """The p-value (B, K) of each ``present`` target of cml (NaN elsewhere): ranges
    ``range_m`` (B, K) m, ``amplitudes`` (B, K, 2) (at the middle of the frame),
    ``phase_step_rad`` (B, K) (NaN: the static model), the decoder's last ``sigma_eff``
    (B,) (std of each real part, frame units), of frames ``z`` (``bits`` None: (B, M, 2)
    complex) or b-bit codes or their values after the dither ``xi`` (B, M, 2) complex
    (None: none) of step ``delta`` (scalar or (B,)), searched inside ``gate`` (None: every
    bin)."""
    b, k = range_m.shape
    n = config.samples_per_ramp
    out = np.full((b, k), np.nan)
    live = np.asarray(present, dtype=bool) & np.isfinite(range_m)
    if b == 0 or not live.any():
        return out
    ramps = z.shape[1] // n
    moving = ramps > 1 and bool(np.isfinite(phase_step_rad).any())
    if gate is None:
        inside, width = np.ones(n, dtype=bool), float(n)
    else:
        lo, hi = gate.check(config).bins(config)
        inside, width = (np.arange(n) >= lo) & (np.arange(n) <= hi), min(float(n), max(hi - lo, 1.0))
    sigma = np.asarray(sigma_eff, dtype=float) * np.ones(b)
    dl = None if bits is None else np.asarray(delta, dtype=float) * np.ones(b)
    per = MOVING_PARAMS if moving else PARAMS
    block = max(1, BLOCK_VALUES // (k * k * per * ramps * 4 * n))  # the largest array: (B, J, per K, S)
    for s in range(0, b, block):
        part = slice(s, min(s + block, b))
        w = int(np.where(live[part], np.arange(1, k + 1), 0).max())  # the slots the block's frames use
        if w == 0:
            continue
        on = live[part, :w]
        r_m = np.where(on, range_m[part, :w], 0.0)
        amp = np.where(on[..., None], amplitudes[part, :w], 0.0)
        phi = np.where(on, phase_step_rad[part, :w], 0.0) if moving else np.zeros(r_m.shape)
        dst = jacobian(r_m, amp, phi, config, ramps, moving)
        score, floor = _residual(z[part], None if xi is None else xi[part], None if dl is None else dl[part], bits,
                                 sigma[part], ramps, n)
        x = leave_one_out_statistic(score, dst, amp, r_m / config.range_resolution_m, on, per, n, inside, floor)
        out[part, :w] = p_value(x, width, moving)
    return out


def _residual(z: np.ndarray, xi: np.ndarray | None, delta: np.ndarray | None, bits: int | None, sigma: np.ndarray,
              ramps: int, n: int):
    """The residual of a block of frames given models, as :func:`leave_one_out_statistic`
    takes it (``score(model) -> (g, h)``, all (B, J, S) real: J models a frame), and the
    least mean energy per bin (B,): unquantized ``y - model`` and 1, the mean no less than a
    white residual's at the frames' rounding (:func:`pipeline.dsp.cml.count.precision_floor`);
    codes :func:`code_score` (no floor)."""
    b = z.shape[0]
    if bits is None:
        y = np.ascontiguousarray(z, dtype=complex).view(float).reshape(b, 1, -1)
        return (lambda model: (y - model, np.ones_like(model))), precision_floor(y.reshape(b, ramps, n, 2, 2), 1)
    dither = 0.0 if xi is None else np.ascontiguousarray(xi, dtype=complex).view(float).reshape(b, 1, -1)
    lo, hi = code_cells(z, delta, bits)
    lo, hi = lo.reshape(b, 1, -1), hi.reshape(b, 1, -1)
    if bits == 1:  # one threshold at 0: g = s F(-s lam / T) / T, h = F (1 - F) / T^2 (code_score's, one logistic)
        from scipy.special import expit

        sign = np.where(np.isinf(lo), -1.0, 1.0)
        t = (sigma / LOGISTIC_PER_SIGMA)[:, None, None]

        def one_bit(model):
            e = expit(-sign * (model + dither) / t)
            return sign * e / t, e * (1.0 - e) / (t * t)
        return one_bit, np.zeros(b)
    return (lambda model: code_score(model + dither, lo, hi, sigma)), np.zeros(b)
