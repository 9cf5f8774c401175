"""How sure each target is: the covariance of its range and angle from the Fisher
information of the frame's codes at the estimate (the maths of :mod:`pipeline.dsp.crb`).

The model is the one :mod:`pipeline.dsp.cml` fits: ``Gamma_{m,p} = sum_t a_{t,p}
exp(-i 4 pi f_m r_t / c)`` (:func:`pipeline.dsp.cml.result.model_frames`), five real
parameters a target (``r_t`` m, ``Re a_{t,1}``, ``Im a_{t,1}``, ``Re a_{t,2}``,
``Im a_{t,2}``), all present targets of a frame jointly; with a phase step between ramps
(the radial velocity, cml's default model) ramp r's amplitudes are ``a_t exp(i (r - (R - 1)
/ 2) phi_t)`` and ``phi_t`` is a sixth parameter (a nuisance of the range and angle: the
codes of each ramp are weighed at that ramp's signal). Per real sample the information
weight is the one of its code (:func:`~pipeline.dsp.crb.weights_1bit` with the frame's own
dither, :func:`~pipeline.dsp.crb.weights_bits`, or ``1 / sigma^2`` unquantized) at the
estimated signal and noise ``sigma`` (for 1-bit codes, the sandwich of the logistic
likelihood the decoder maximizes, and the noise the decoder estimated less the part of it
its own fit explains: :func:`fitted_noise`). The angle ``theta = arcsin(c arg(a_2 conj a_1) /
(2 pi f0 d))`` and its variance follow by the delta method.

Shapes: batch axis first; targets (B, K); the returned arrays (B, K), NaN where a target
is absent or its information is singular.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radar_driver.model import RadarConfig, range_phase

from pipeline.dsp.crb import fisher, log_ndtr, ndtr, weights_bits

#: real parameters a target: r, Re a1, Im a1, Re a2, Im a2 (with a phase step between ramps,
#: phi after them: :data:`MOVING_PARAMS`)
PARAMS = 5
MOVING_PARAMS = 6
#: a 1-bit code whose margin ``|s + d|`` exceeds this many noise stds carries no information
#: (its weight below 1e-5 of the largest, the probit's below 1e-13); the weights are computed on the
#: others only
NEAR_Z = 8.0
#: the logistic closest to a Gaussian of std sigma has the scale sigma / LOGISTIC_SCALE
LOGISTIC_SCALE = 1.702
_LOG_2PI = np.log(2.0 * np.pi)


@dataclass(frozen=True)
class Uncertainty:
    """Per target (B, K): ``sigma_range_m`` (m), ``sigma_angle_deg`` (deg) and
    ``cov_range_angle`` (m deg), the covariance's off-diagonal; NaN where unknown."""

    sigma_range_m: np.ndarray
    sigma_angle_deg: np.ndarray
    cov_range_angle: np.ndarray


def model_jacobian(range_m: np.ndarray, amplitudes: np.ndarray, config: RadarConfig) -> tuple[np.ndarray, np.ndarray]:
    """The model's real samples ``s`` (B, 4N) on one ramp and their derivatives ``ds``
    (B, 4N, 5K) for targets ``range_m`` (B, K) m of amplitudes (B, K, 2) complex;
    (sample, antenna, I/Q) in C order as the quantizer lays out its codes (every ramp of a
    frame the same; with a phase step between ramps: :func:`moving_jacobian`)."""
    steer, _ = _steering(range_m, config)
    ds = jacobian(range_m, amplitudes, np.zeros(range_m.shape), config, 1, False)
    return _static_samples(steer, amplitudes), np.swapaxes(ds, 1, 2)


def moving_jacobian(range_m: np.ndarray, amplitudes: np.ndarray, phase_step_rad: np.ndarray,
                    config: RadarConfig) -> tuple[np.ndarray, np.ndarray]:
    """:func:`model_jacobian` with a phase step between ramps: each of the frame's R ramps'
    real samples ``s`` (B, R, 4N) and their derivatives ``ds`` (B, R, 4N, 6K) in the
    parameters ``[r, Re a1, Im a1, Re a2, Im a2, phi]`` of each target, amplitudes (B, K, 2)
    at the middle of the frame, ramp r's ``a exp(i c_r phi)``, ``c_r = r - (R - 1) / 2``,
    ``phase_step_rad`` (B, K) (NaN counts as 0)."""
    b, ramps = range_m.shape[0], config.ramps_per_frame
    steer, _ = _steering(range_m, config)
    _, _, a = _turns(amplitudes, phase_step_rad, ramps)
    ds = jacobian(range_m, amplitudes, np.nan_to_num(phase_step_rad), config, ramps, True)
    return _moving_samples(steer, a), np.swapaxes(ds, 1, 2).reshape(b, ramps, -1, ds.shape[1])


def jacobian(range_m: np.ndarray, amplitudes: np.ndarray, phase_step_rad: np.ndarray, config: RadarConfig, ramps: int,
             moving: bool) -> np.ndarray:
    """The derivatives (B, P K, S) of a frame's S = R 4N real samples ((ramp, sample, antenna,
    I/Q) in C order) in each target's parameters ``[r, Re a1, Im a1, Re a2, Im a2]`` and,
    ``moving``, ``phi`` (P = 6; else P = 5; the static model's ramps all the same), each
    parameter's row written as complex samples (:func:`model_jacobian`'s and
    :func:`moving_jacobian`'s ``ds`` are its transpose). Targets ``range_m`` (B, K) m,
    ``amplitudes`` (B, K, 2) at the middle of the frame, ``phase_step_rad`` (B, K) (ignored
    unless ``moving``)."""
    b, k = range_m.shape
    n = config.samples_per_ramp
    per = MOVING_PARAMS if moving else PARAMS
    steer, kr = _steering(range_m, config)
    steer = np.swapaxes(steer, 1, 2)  # (B, K, N)
    if moving:
        c, turn, _ = _turns(amplitudes, phase_step_rad, ramps)  # turn (B, R, K): exp(i c_r phi)
        at = steer[:, :, None, :] * np.swapaxes(turn, 1, 2)[..., None]  # (B, K, R, N)
    else:
        at = np.broadcast_to(steer[:, :, None, :], (b, k, ramps, n))
    d = np.zeros((b, k, per, ramps, n, 2), dtype=complex)  # (target, parameter) x (ramp, sample, antenna)
    for p in range(2):
        ap = amplitudes[:, :, p, None, None]  # (B, K, 1, 1)
        d[:, :, 0, :, :, p] = at * ap * (-1j * kr)
        d[:, :, 1 + 2 * p, :, :, p] = at
        d[:, :, 2 + 2 * p, :, :, p] = 1j * at
        if moving:
            d[:, :, 5, :, :, p] = at * ap * (1j * c[:, None])
    return d.view(float).reshape(b, k * per, ramps * 4 * n)


def _steering(range_m: np.ndarray, config: RadarConfig) -> tuple[np.ndarray, np.ndarray]:
    """Each target's range term at each sample of a ramp, ``steer`` (B, N, K), and ``kr``
    (N,): ``d steer / dr = -i kr steer``."""
    f = config.frequencies_hz(np.arange(config.samples_per_ramp))
    steer = range_phase(f[None, :, None], range_m[:, None, :], config)  # (B, N, K)
    return steer, (4.0 * np.pi / config.c_m_s) * f


def _turns(amplitudes: np.ndarray, phase_step_rad: np.ndarray, ramps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ramps' offsets from the middle of the frame ``c`` (R,), each target's turn
    ``exp(i c_r phi)`` (B, R, K) (NaN counts as 0) and each ramp's amplitudes (B, R, K, 2)."""
    c = np.arange(ramps) - (ramps - 1) / 2.0
    turn = np.exp(1j * c[None, :, None] * np.nan_to_num(phase_step_rad)[:, None, :])  # (B, R, K)
    return c, turn, amplitudes[:, None, :, :] * turn[..., None]


def _static_samples(steer: np.ndarray, amplitudes: np.ndarray) -> np.ndarray:
    """The model's real samples (B, 4N) of one ramp (:func:`model_jacobian`'s ``s``)."""
    s = steer @ amplitudes  # (B, N, 2) (a batched product: einsum's loops take 15 x longer)
    return np.ascontiguousarray(s).view(float).reshape(steer.shape[0], -1)


def _moving_samples(steer: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Each ramp's real samples (B, R, 4N) (:func:`moving_jacobian`'s ``s``); ``a`` (B, R, K,
    2) the ramps' amplitudes."""
    s = steer[:, None] @ a  # (B, R, N, 2) (a batched product: einsum's loops take 15 x longer)
    return np.ascontiguousarray(s).view(float).reshape(steer.shape[0], a.shape[1], -1)


def _near_rows(near: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, ...]]:
    """The samples ``near`` (B, L) bool (those near the threshold): as the padded rows
    ``(rows, real)`` (B, J) (flat indices, padded to the most a frame has, J, with sample 0;
    ``real``: not padding), and as ``(frame, sample, slot)`` (S,) each (the slot: its column
    of ``rows``)."""
    counts = near.sum(axis=1)
    fb, fl = np.nonzero(near)
    slot = np.arange(fb.size) - (np.cumsum(counts) - counts)[fb]
    rows = np.zeros((near.shape[0], int(counts.max(initial=0))), dtype=np.intp)
    rows[fb, slot] = fl
    return (rows, np.arange(rows.shape[1])[None, :] < counts[:, None]), (fb, fl, slot)


def _jacobian_rows(steer: np.ndarray, kr: np.ndarray, amplitudes: np.ndarray, rows: tuple, near: tuple, c=None,
                   turn=None) -> np.ndarray:
    """:func:`model_jacobian`'s ``ds`` (``turn`` None) or :func:`moving_jacobian`'s (``c``
    (R,), ``turn`` (B, R, K): :func:`_turns`) at the samples of :func:`_near_rows` only
    (``rows``, ``near``: what it returns; flat indices, (ramp, sample, antenna, I/Q) in C
    order): (B, J, PK), the same values (the same operations on the same numbers), zeros
    in the padding. The information of 1-bit codes sits on the few samples near the
    threshold: the Fisher matrices need those rows only."""
    b, n, k = steer.shape
    fb, fl, slot = near
    iq, p, smp = fl & 1, (fl >> 1) & 1, fl >> 2
    ni = smp % n
    st = steer[fb, ni]  # (S, K)
    amp = amplitudes[fb, :, p]  # (S, K): antenna p's
    dkr = (-1j * kr)[ni][:, None]
    real = (iq == 0)[:, None]
    moving = turn is not None
    per = MOVING_PARAMS if moving else PARAMS
    d = np.zeros((fb.size, k, per))
    if moving:
        ri = smp // n
        tr = turn[fb, ri]  # (S, K)
        ap = amp * tr
        dr = ap * st * dkr
        at = st * tr
        d[..., 5] = _part(1j * c[ri][:, None] * ap * st, real)
    else:
        dr = st * (amp * dkr)
        at = st
    d[..., 0] = _part(dr, real)
    re, im = _part(at, real), np.where(real, -at.imag, at.real)  # at and i at
    first = (p == 0)[:, None]
    d[..., 1], d[..., 2] = np.where(first, re, 0.0), np.where(first, im, 0.0)
    d[..., 3], d[..., 4] = np.where(first, 0.0, re), np.where(first, 0.0, im)
    out = np.zeros((b, rows[0].shape[1], k * per))
    out[fb, slot] = d.reshape(fb.size, k * per)  # (no sample near the threshold: none)
    return out


def _part(z: np.ndarray, real: np.ndarray) -> np.ndarray:
    """The real part of ``z`` where ``real``, else its imaginary part."""
    return np.where(real, z.real, z.imag)


def _pick(w: np.ndarray, rows) -> np.ndarray:
    """Per-sample weights ``w`` (B, L) at ``rows`` = (the samples (B, J), which are real (B,
    J)) (:func:`_near_rows`; the padding weighs 0); None: ``w`` as it is."""
    if rows is None:
        return w
    idx, real = rows
    return np.where(real, np.take_along_axis(w, idx, axis=1), 0.0)


def _near(margin: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The samples (flat indices) of ``margin`` (B, R, L) within NEAR_Z ``sigma`` (B,) of the
    threshold, and their standardized margins."""
    z = margin / sigma[:, None, None]
    idx = np.flatnonzero(np.abs(z) < NEAR_Z)
    return idx, z.reshape(-1)[idx]


def _scatter(idx: np.ndarray, values: np.ndarray, shape: tuple) -> np.ndarray:
    """Zeros of ``shape`` holding ``values`` at flat ``idx``, summed over the ramps: (B, L)."""
    out = np.zeros(int(np.prod(shape)))
    out[idx] = values
    return out.reshape(shape).sum(axis=1)


def _probit(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """At standardized margins ``z``: ``h = phi^2 / (Phi (1 - Phi))`` (:mod:`pipeline.dsp.crb`)
    and ``d log h / dz``, from the logs (no 0/0 in the tails)."""
    lo, hi = log_ndtr(z), log_ndtr(-z)
    log_phi = -0.5 * z * z - 0.5 * _LOG_2PI
    h = np.exp(2.0 * log_phi - lo - hi)
    return h, -2.0 * z - np.exp(log_phi - lo) + np.exp(log_phi - hi)


def fitted_noise(sigma: np.ndarray, margin: np.ndarray, ds: np.ndarray, live: np.ndarray, rows=None) -> np.ndarray:
    """The noise std (B,) of 1-bit codes: ``sigma`` (B,), the likeliest at the fitted signal
    (margins ``margin = s + d`` (B, R, L) of R ramps), less its bias: the fitted parameters
    (``ds`` (B, L, P), ``live`` (B, K) the targets present) explain part of the noise, so the
    score about sigma at the fit is off by ``-1/2 tr(I^-1 dI/dsigma)`` (I the parameters'
    Fisher information, :mod:`pipeline.dsp.crb`), and sigma by that over the information
    about sigma, ``sum h(z) z^2 / sigma^2``, ``z = margin / sigma``. (Gaussian samples:
    ``sigma^2 (n - P) / n``, the least-squares residual's; dithered 1-bit codes, whose
    information about a target falls as ``1 / sigma`` rather than ``1 / sigma^2``: about half
    that.) Measured, 1 bit at alpha 0.45, K = 2, noise 0.03: the likeliest sigma 0.83 of the
    noise's, corrected 0.93. ``rows``: ``ds`` (B, J, P) holds only those samples (:func:`_pick`),
    a superset of the ones near the threshold."""
    idx, z = _near(margin, sigma)
    h, dlog = _probit(z)
    sg = sigma[:, None]
    shape = margin.shape
    about_sigma = _scatter(idx, h * z * z, shape).sum(axis=1) / sigma**2
    info = _masked(_fisher(ds, _pick(_scatter(idx, h, shape), rows) / sg**2), live)
    # d/dsigma of h(m / sigma) / sigma^2 = -(z h'(z) + 2 h) / sigma^3
    moved = _masked(_fisher(ds, _pick(_scatter(idx, -(z * dlog + 2.0) * h, shape), rows) / sg**3), live, eye=0.0)
    with np.errstate(invalid="ignore", over="ignore"):
        trace = np.trace(_inverse(info) @ moved, axis1=1, axis2=2)
    # the bias of sigma^2 relative to the noise's, 2 bias / sigma, as a least-squares
    # residual's (n - P) / n: divided out (first order alike; exact for Gaussian samples)
    fixed = sigma / np.sqrt(np.maximum(1.0 + trace / (about_sigma * sigma), 0.25))
    return np.where(np.isfinite(fixed) & (fixed > sigma), fixed, sigma)


#: the most ``P^2 L`` of one batched product of :func:`_fisher` (P parameters, L samples):
#: OpenBLAS runs a larger product on all its threads, which on a busy host wait for each
#: other far longer than the product takes (measured: K auto with the phase step, 4-10 x the
#: time of the same sums in pieces)
FISHER_PIECE = 1 << 17


def _fisher(ds: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """:func:`pipeline.dsp.crb.fisher` of ``ds`` (B, L, P) and ``weights`` (B, L), summed over
    pieces of the samples of at most :data:`FISHER_PIECE` ``/ P^2`` each."""
    step = max(FISHER_PIECE // max(ds.shape[2] ** 2, 1), 1)
    if ds.shape[1] <= step:
        return fisher(ds, weights)
    return sum(fisher(ds[:, i:i + step], weights[:, i:i + step]) for i in range(0, ds.shape[1], step))


def _masked(fim: np.ndarray, live: np.ndarray, eye: float = 1.0) -> np.ndarray:
    """Fisher matrices (B, P, P) with the parameters of absent targets (``live`` (B, K)
    False) held fixed (their rows and columns ``eye`` times the identity's); P / K
    parameters a target."""
    k = live.shape[1]
    per = fim.shape[1] // k
    cols = np.repeat(live, per, axis=1)
    return np.where(cols[:, :, None] & cols[:, None, :], fim, 0.0) + eye * np.eye(k * per) * ~cols[:, None, :]


def target_uncertainty(range_m: np.ndarray, amplitudes: np.ndarray, present: np.ndarray, config: RadarConfig,
                       sigma: np.ndarray, dither: np.ndarray | None = None, delta=None, bits: int | None = None,
                       estimated: bool = True, phase_step_rad: np.ndarray | None = None) -> Uncertainty:
    """:class:`Uncertainty` of the ``present`` (B, K) targets ``range_m`` (B, K) m,
    ``amplitudes`` (B, K, 2) of frames of whole ramps in noise ``sigma`` (B,) (std of each
    real part, frame units; ``estimated`` from the frames themselves: 1-bit codes correct it
    for their fit, :func:`fitted_noise`): unquantized when ``bits`` is None, else b-bit codes
    of step ``delta`` (scalar or (B,)) after the ``dither`` (B, M, 2) complex (None: none).
    ``phase_step_rad`` (B, K): the targets' phase steps between ramps (cml's model with the
    radial velocity, :func:`moving_jacobian`: a sixth parameter a target, each ramp's codes at
    its own signal); None or all NaN: the static model.

    The frames are taken in groups by how many target slots they use (up to their last
    present one): a count test's frames hold fewer targets than their slots, and each slot
    is a block of the Fisher matrix (K auto at most 4 with 2 targets found: half the work)."""
    b, k = range_m.shape
    nan = np.full((b, k), np.nan)
    out = Uncertainty(nan.copy(), nan.copy(), nan.copy())
    if b == 0 or k == 0:
        return out
    live = np.asarray(present, dtype=bool) & np.isfinite(range_m)
    width = np.where(live, np.arange(1, k + 1), 0).max(axis=1)  # (B,) slots a frame uses
    if (width == k).all():
        return _uncertainty(range_m, amplitudes, live, config, sigma, dither, delta, bits, estimated,
                            phase_step_rad, out)
    sg, dl = np.asarray(sigma, dtype=float).reshape(-1) * np.ones(b), np.asarray(delta, dtype=float) * np.ones(b)
    for w in np.unique(width[width > 0]).tolist():  # a few groups (the counts), not the frames
        idx = np.flatnonzero(width == w)
        part = Uncertainty(*(np.full((idx.size, w), np.nan) for _ in range(3)))
        _uncertainty(range_m[idx, :w], amplitudes[idx, :w], live[idx, :w], config, sg[idx],
                     None if dither is None else dither[idx], None if delta is None else dl[idx], bits, estimated,
                     None if phase_step_rad is None else phase_step_rad[idx, :w], part)
        for name in ("sigma_range_m", "sigma_angle_deg", "cov_range_angle"):
            getattr(out, name)[idx, :w] = getattr(part, name)
    return out


def _uncertainty(range_m: np.ndarray, amplitudes: np.ndarray, live: np.ndarray, config: RadarConfig,
                 sigma: np.ndarray, dither: np.ndarray | None, delta, bits: int | None, estimated: bool,
                 phase_step_rad: np.ndarray | None, out: "Uncertainty") -> "Uncertainty":
    """:func:`target_uncertainty` of frames (B,) whose ``live`` (B, K) targets are known,
    written into ``out`` ((B, K) arrays of NaN)."""
    b, k = range_m.shape
    a = np.where(live[..., None], amplitudes, 0.0)
    ramps = config.ramps_per_frame
    moving = phase_step_rad is not None and ramps > 1 and bool(np.isfinite(phase_step_rad).any())
    r_live = np.where(live, range_m, 0.0)
    steer, kr = _steering(r_live, config)
    phi = np.where(live, phase_step_rad, 0.0) if moving else np.zeros((b, k))
    rows_ramps = ramps if moving else 1  # the dense Jacobian's: each ramp's samples, or one ramp's (all the same)
    if moving:  # each ramp its own samples: one "ramp" of R 4N samples
        c, turn, a_ramps = _turns(a, phi, ramps)
        margin = _moving_samples(steer, a_ramps)
    else:
        s = _static_samples(steer, a)
        margin = np.broadcast_to(s[:, None, :], (b, ramps, s.shape[1]))
    if dither is not None:
        margin = margin + np.ascontiguousarray(dither, dtype=complex).view(float).reshape(b, ramps, -1)
    if moving:
        margin = margin.reshape(b, 1, -1)
    sg = np.maximum(np.asarray(sigma, dtype=float).reshape(-1) * np.ones(b), 1e-12)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        if bits == 1:
            # the Jacobian at the samples that may lie within NEAR_Z noise stds of the threshold
            # only (a few % at low noise): fitted_noise's std is sg, _sandwich's at most 2 sg
            # (fitted_noise divides sg by at least 1/2); the others weigh 0. The frames with
            # more than a quarter of their samples there (high noise) take the whole Jacobian
            limit = NEAR_Z * sg * ((2.0 if estimated else 1.0) * (1.0 + 1e-6))
            near = (np.abs(margin) < limit[:, None, None]).any(axis=1)  # (B, L)
            few = 4 * near.sum(axis=1) <= near.shape[1]
            per = k * (MOVING_PARAMS if moving else PARAMS)
            cov = np.empty((b, per, per))
            for part, compact in ((np.flatnonzero(few), True), (np.flatnonzero(~few), False)):
                if part.size == 0:
                    continue
                if compact:
                    rows, flat = _near_rows(near[part])
                    ds = _jacobian_rows(steer[part], kr, a[part], rows, flat, *((c, turn[part]) if moving else ()))
                else:
                    rows = None
                    ds = np.swapaxes(jacobian(r_live[part], a[part], phi[part], config, rows_ramps, moving), 1, 2)
                noise = fitted_noise(sg[part], margin[part], ds, live[part], rows) if estimated else sg[part]
                cov[part] = _sandwich(ds, margin[part], noise, sg[part], live[part], rows)
        else:
            ds = np.swapaxes(jacobian(r_live, a, phi, config, rows_ramps, moving), 1, 2)
            if bits is None:
                w = np.full((b, ds.shape[1]), (1 if moving else ramps) / sg[:, None] ** 2)
            else:
                dl = np.asarray(delta, dtype=float) * np.ones(b)
                w = weights_bits(margin.reshape(b, -1), None, sg, dl, bits).reshape(margin.shape).sum(axis=1)
            cov = _inverse(_masked(_fisher(ds, w), live))
    _angles(cov, a, live, config, out)
    return out


def _sandwich(ds: np.ndarray, margin: np.ndarray, sigma: np.ndarray, level: np.ndarray,
              live: np.ndarray, rows=None) -> np.ndarray:
    """The covariance ``H^-1 J H^-1`` (B, P, P) of the estimate that maximizes the 1-bit
    logistic likelihood of the decoder (:mod:`pipeline.dsp.cml.likelihood`, scale
    ``T = level / 1.702``, ``level`` (B,) its last ``sigma_eff``) when the codes come from
    Gaussian noise ``sigma`` (B,) (``P(+) = Phi(m / sigma)`` at the margins ``m`` (B, R, L)):
    per sample the curvature ``F (1 - F) / T^2`` (H) and the variance of the score
    ``(P(+) (1 - F)^2 + P(-) F^2) / T^2`` (J), ``F = F(m / T)``; absent targets' (``live``
    (B, K) False) parameters held fixed; ``rows``: as :func:`fitted_noise` takes them."""
    t = level / LOGISTIC_SCALE
    idx, x = _near(margin, np.maximum(t, sigma))
    m = x * np.repeat(np.maximum(t, sigma), margin[0].size)[idx]  # the margins near the threshold
    tt, sg = np.repeat(t, margin[0].size)[idx], np.repeat(sigma, margin[0].size)[idx]
    f = 0.5 * (1.0 + np.tanh(0.5 * m / tt))  # the logistic, without overflow
    p = ndtr(m / sg)
    h, j = (_masked(_fisher(ds, _pick(_scatter(idx, w, margin.shape), rows)), live)
            for w in (f * (1.0 - f) / tt**2, (p * (1.0 - f) ** 2 + (1.0 - p) * f * f) / tt**2))
    hi = _inverse(h)
    return hi @ j @ hi


def _inverse(fim: np.ndarray) -> np.ndarray:
    """Inverse Fisher matrices (B, P, P), NaN where singular."""
    cov = np.full(fim.shape, np.nan)
    ok = np.isfinite(fim).all(axis=(1, 2))
    if ok.any():
        try:  # a batched inverse; the pseudo-inverse (an SVD, ~5 x slower) only where one is singular
            cov[ok] = np.linalg.inv(fim[ok])
        except np.linalg.LinAlgError:
            cov[ok] = np.linalg.pinv(fim[ok], hermitian=True)
    return cov


def _angles(cov: np.ndarray, a: np.ndarray, live: np.ndarray, config: RadarConfig, out: Uncertainty) -> None:
    """Range and angle (co)variances of each target from the parameters' covariance ``cov``
    (B, PK, PK), P = 5 or 6 (the phase step last), by the delta method into ``out``;
    amplitudes ``a`` (B, K, 2); every target at once."""
    k = live.shape[1]
    per = cov.shape[1] // k
    per_phase = 2.0 * np.pi * config.f0_hz * config.d_m / config.c_m_s  # phase per sin(theta)
    idx = (np.arange(k) * per)[:, None] + np.arange(PARAMS)  # (K, 5): each target's block
    block = cov[:, idx[:, :, None], idx[:, None, :]]  # (B, K, 5, 5)
    a1, a2 = a[..., 0], a[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        g1 = np.stack([a1.imag, -a1.real], axis=-1) / np.abs(a1)[..., None] ** 2  # d(-arg a1)/d(Re, Im)
        g2 = np.stack([-a2.imag, a2.real], axis=-1) / np.abs(a2)[..., None] ** 2  # d arg a2 / d(Re, Im)
        sin = np.clip(np.angle(a2 * np.conj(a1)) / per_phase, -1.0, 1.0)
        dtheta = 1.0 / (per_phase * np.sqrt(1.0 - sin * sin))  # d theta / d phi, rad
    jac = np.zeros(live.shape + (2, PARAMS))
    jac[..., 0, 0] = 1.0
    jac[..., 1, 1:3] = g1 * dtheta[..., None]
    jac[..., 1, 3:5] = g2 * dtheta[..., None]
    with np.errstate(invalid="ignore"):  # NaN where the information is singular (not ok below)
        c = jac @ block @ np.swapaxes(jac, -1, -2)  # (B, K, 2, 2): range m, angle rad
    ok = live & np.isfinite(c).all(axis=(2, 3)) & (c[..., 0, 0] > 0) & (c[..., 1, 1] > 0)
    c, deg = c[ok], np.rad2deg(1.0)
    out.sigma_range_m[ok] = np.sqrt(c[:, 0, 0])
    out.sigma_angle_deg[ok] = np.sqrt(c[:, 1, 1]) * deg
    out.cov_range_angle[ok] = c[:, 0, 1] * deg
