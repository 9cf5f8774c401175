"""cml's numpy reference (``engine="numpy"``): the same decode as the compiled engine, vectorized
over a block of frames in numpy, with the exact logistic (numpy's ``exp`` and ``log1p``, the
codes' likelihood in :mod:`pipeline.dsp.cml.reference_codes`) and the Gauss--Newton system from
explicit Jacobians. It is the oracle the compiled kernels are tested
against (tests/test_cml_kernels.py and the others): the two take the same steps, in another
floating-point order.

Shapes: a block of B frames of R ramps of N samples; Rm the model's ramps (R with a phase step
between ramps, 1 for the static model); the real parts of a sample as (antenna, re/im);
per-target arrays (B, K), amplitudes (B, K, 2); ranges in bins, phase steps in rad."""

from __future__ import annotations

import numpy as np

from radar_driver.model import RadarConfig, range_phase

from pipeline.dsp.cml.checks import Frames
from pipeline.dsp.cml.count import COUNT_GUARD_BINS, information_floor, precision_floor
from pipeline.dsp.cml.grid import COARSE_PER_BIN, MIN_SEPARATION_BINS, SearchGrid
from pipeline.dsp.cml.options import MAX_PHASE_STEP_RAD, MAX_RANGE_STEP_BINS, WRONG_RMS_PER_SIGMA, CmlOptions
from pipeline.dsp.cml.reference_codes import Codes
from pipeline.dsp.cml.result import CmlResult
from pipeline.dsp.cml.schedule import WARM_STEPS, anneal_levels, start, warm_levels
from pipeline.dsp.localize import to_db


def atoms(nu: np.ndarray, kc: np.ndarray) -> np.ndarray:
    """``exp(-i 2 pi kc nu / N)``: ranges (..., K) in bins -> (..., K, N), from two short
    tables (index n1 j + i) rather than K N complex exponentials a frame."""
    n = kc.size
    n1 = int(np.ceil(np.sqrt(n)))
    n2 = -(-n // n1)
    ph = (-2j * np.pi / n) * nu[..., None]
    outer = np.exp(ph * (n1 * np.arange(n2)))
    inner = np.exp(ph * (np.arange(n1) + kc[0]))
    return (outer[..., :, None] * inner[..., None, :]).reshape(nu.shape + (n1 * n2,))[..., :n]


def coefficients(amp: np.ndarray, phi: np.ndarray, cq: float) -> np.ndarray:
    """Z (B, 4, 4K, 6K): on a ramp of offset ``cq`` from the middle of the frame (target t's
    amplitude there ``b_tq = b_t exp(i cq phi_t)``) the derivative of part c (0 real, 1
    imaginary) of the model on antenna p in the parameters is ``R^T Z[2p + c]`` (see
    :meth:`Fit.step`)."""
    b, k, _ = amp.shape
    z = np.zeros((b, 4, 4 * k, 6 * k))
    t = np.arange(k)
    cs, sn = np.cos(cq * phi), np.sin(cq * phi)  # (B, K)
    for p in range(2):
        re, im = 2 * p, 2 * p + 1
        # a parameter moves mu_p along A v: Re b_tp: v = e^{i theta} e_t; Im b_tp: v = i e^{i theta} e_t;
        # nu_t: v = b_tpq e_{K+t}; phi_t: v = i cq b_tpq e_t. Re(A v) = Re A Re v - Im A Im v,
        # Im(A v) = Re A Im v + Im A Re v; rows [0, 2K) of R are Re A, rows [2K, 4K) Im A.
        z[:, re, t, 6 * t + 1 + 2 * p] = cs
        z[:, re, 2 * k + t, 6 * t + 1 + 2 * p] = -sn
        z[:, im, t, 6 * t + 1 + 2 * p] = sn
        z[:, im, 2 * k + t, 6 * t + 1 + 2 * p] = cs
        z[:, re, t, 6 * t + 2 + 2 * p] = -sn
        z[:, re, 2 * k + t, 6 * t + 2 + 2 * p] = -cs
        z[:, im, t, 6 * t + 2 + 2 * p] = cs
        z[:, im, 2 * k + t, 6 * t + 2 + 2 * p] = -sn
        a = amp[:, :, p] * (cs + 1j * sn)
        z[:, re, k + t, 6 * t] = a.real
        z[:, re, 3 * k + t, 6 * t] = -a.imag
        z[:, im, k + t, 6 * t] = a.imag
        z[:, im, 3 * k + t, 6 * t] = a.real
        z[:, re, t, 6 * t + 5] = -cq * a.imag
        z[:, re, 2 * k + t, 6 * t + 5] = -cq * a.real
        z[:, im, t, 6 * t + 5] = cq * a.real
        z[:, im, 2 * k + t, 6 * t + 5] = -cq * a.imag
    return z


def ramp_offsets(rm: int) -> np.ndarray:
    """Each model ramp's offset from the middle of the frame, ``r - (Rm - 1) / 2`` (Rm,)."""
    return np.arange(rm) - (rm - 1) / 2.0


class Fit:
    """The targets found so far, the model and the likelihood at them, and
    Levenberg--Marquardt steps on all of them at once. A target's parameters are [nu, Re b1,
    Im b1, Re b2, Im b2, phi]: range in bins, the amplitudes referred to mid-sweep and to the
    middle of the frame, and the phase step between ramps; on ramp q the model is
    ``mu_{q,n,p} = sum_t b_{t,p} exp(i c_q phi_t) w_t[n]`` with ``w_t[n] = exp(-i 2 pi kc_n
    nu_t / N)`` and ``c_q = q - (Rm - 1) / 2`` (the static model: Rm = 1, phi stays 0)."""

    def __init__(self, codes: Codes, grid: SearchGrid):
        n = codes.n
        self.codes, self.grid, self.kc = codes, grid, np.arange(n) - (n - 1) / 2.0
        self.cr = ramp_offsets(codes.rm)
        b = codes.data.shape[0]
        self.set(np.zeros((b, 0)), np.zeros((b, 0)), np.zeros((b, 0, 2), dtype=complex), np.zeros((b, 0), dtype=bool))

    def set(self, nu: np.ndarray, phi: np.ndarray, amp: np.ndarray, live: np.ndarray) -> None:
        """Targets (B, K) in bins, phase steps (B, K), amplitudes (B, K, 2); ``live`` (B, K):
        the targets that move (the others stay where they are: zero amplitude, past a frame's
        count)."""
        self.nu, self.phi, self.amp, self.live = nu, phi, amp, live
        self.ge = None  # the efficient score's g (:meth:`settled_score`), while the fit does not move
        self.w = atoms(nu, self.kc)
        self.mu = self._mu(self.w, phi, amp)
        self.lm = np.full(nu.shape[0], 1e-3)  # damping, per frame

    def _mu(self, w: np.ndarray, phi: np.ndarray, amp: np.ndarray) -> np.ndarray:
        """The model (B, Rm, N, 2, 2) of atoms ``w`` (B, K, N), phase steps and amplitudes."""
        turned = amp[:, None] * np.exp(1j * self.cr[None, :, None, None] * phi[:, None, :, None])  # (B, Rm, K, 2)
        mu = np.matmul(w.transpose(0, 2, 1)[:, None], turned)  # (B, Rm, N, 2) complex
        return mu.view(float).reshape(mu.shape + (2,))

    def model(self) -> np.ndarray:
        """Each model ramp, (B, Rm, N, 2) complex."""
        return self.mu.view(complex)[..., 0]

    def evaluate(self, sigma: np.ndarray) -> None:
        """The likelihood at noise std ``sigma`` (B,) and its derivatives at the model."""
        self.sigma = np.asarray(sigma, dtype=float)
        self.nll, self.g, self.h = self.codes.evaluate(self.mu, self.sigma)
        self.ge = None

    def run(self, levels: np.ndarray, amp_cap: np.ndarray, adapt: bool = False) -> None:
        """One step a level: at noise std ``levels[:, j]`` (B, S) (``adapt``: not below
        the noise the model leaves, ``noise_rms / WRONG_RMS_PER_SIGMA``), the likelihood
        evaluated again where the level changed, then :meth:`step`."""
        for j in range(levels.shape[1]):
            sigma = levels[:, j]
            if adapt:
                sigma = np.maximum(sigma, self.codes.noise_rms(self.mu) / WRONG_RMS_PER_SIGMA)
            if not np.array_equal(sigma, self.sigma):
                self.evaluate(sigma)
            self.step(amp_cap)

    def step(self, amp_cap: np.ndarray) -> None:
        """One Levenberg--Marquardt step of every frame at the current scale; a frame keeps
        its step only if its likelihood improves. amp_cap : (B,) largest amplitude change."""
        b, k = self.nu.shape
        if k == 0:  # no target found in the whole block (K auto)
            return
        step = self._solve()
        step[~self.live] = 0.0
        step[..., 0] = np.clip(step[..., 0], -MAX_RANGE_STEP_BINS, MAX_RANGE_STEP_BINS)
        step[..., 5] = np.clip(step[..., 5], -MAX_PHASE_STEP_RAD, MAX_PHASE_STEP_RAD)
        norm = np.linalg.norm(step[..., 1:5], axis=2)
        step[..., 1:5] *= np.minimum(1.0, amp_cap[:, None] / np.maximum(norm, 1e-300))[..., None]
        nu = self.nu + step[..., 0]
        phi = self.phi + step[..., 5]
        amp = self.amp + (step[..., 1:5:2] + 1j * step[..., 2:5:2])
        w = atoms(nu, self.kc)
        mu = self._mu(w, phi, amp)
        nll, g, h = self.codes.evaluate(mu, self.sigma)
        ok = nll <= self.nll
        self.lm = np.clip(np.where(ok, self.lm / 3.0, self.lm * 8.0), 1e-9, 1e9)
        bad = np.flatnonzero(~ok)  # frames that keep their parameters (few)
        for new, old in ((nu, self.nu), (phi, self.phi), (amp, self.amp), (w, self.w), (mu, self.mu), (g, self.g),
                         (h, self.h), (nll, self.nll)):
            new[bad] = old[bad]
        self.nu, self.phi, self.amp, self.w, self.mu, self.g, self.h, self.nll = nu, phi, amp, w, mu, g, h, nll
        self.ge = None

    def settled_score(self) -> None:
        """Into ``ge`` (B, Rm, N, 2, 2) the efficient score's ``g``: the NLL's derivatives at
        the model less what the targets' own parameters explain, on each model ramp q ``g_q +
        h_q (J_q d)`` with ``d`` the undamped Gauss--Newton step of the live targets (all their
        parameters, the phase step too, :meth:`_solve`) and ``J_q`` the model's Jacobian on
        ramp q: ``sum_q J_q^T ge_q = 0`` (up to the ramps' shared curvature of the system), the
        score no target found could take up by moving (Rao's test with the found targets'
        parameters as nuisances). A fit not yet at its optimum (steps left in a direction the
        codes barely fix, as the amplitudes of 1-bit codes without a dither) otherwise leaves a
        score along ``h J d``, which the weights ``h`` (periodic with the targets where the
        codes are) carry to the targets' harmonics."""
        b, k = self.nu.shape
        if k == 0:
            self.ge = self.g
            return
        lm, self.lm = self.lm, np.zeros(b)
        step = self._solve()
        self.lm = lm
        step[~self.live] = 0.0
        n = self.kc.size
        cr = self.cr[None, :, None, None]  # (1, Rm, 1, 1)
        turn = np.exp(1j * cr[..., 0] * self.phi[:, None, :])[..., None]  # (B, Rm, K, 1)
        db = (step[..., 1:5:2] + 1j * step[..., 2:5:2])[:, None]  # (B, 1, K, 2)
        dphi = step[..., 5][:, None, :, None] if self.codes.rm > 1 else 0.0
        ca = turn * (db + 1j * cr * dphi * self.amp[:, None])  # (B, Rm, K, 2): along w
        cb = turn * (self.amp * step[..., :1])[:, None]  # along d w / d nu
        dw = self.w * ((-2j * np.pi / n) * self.kc)  # d w / d nu
        dmu = np.einsum("bkn,brkp->brnp", self.w, ca) + np.einsum("bkn,brkp->brnp", dw, cb)  # (B, Rm, N, 2)
        self.ge = self.g + self.h * np.ascontiguousarray(dmu).view(float).reshape(self.g.shape)

    def _solve(self) -> np.ndarray:
        """The damped Gauss--Newton step (B, K, 6): on model ramp q the Jacobian of part c of
        mu_p is ``R^T Z_q[2p + c]``, R (4K, N) the real and imaginary parts of the atoms w_t and
        of dw_t / dnu, Z_q how each parameter mixes them there (:func:`coefficients`); the
        matrix ``sum_q J_q^T diag(hbar) J_q`` with hbar the mean curvature over the ramps (as
        :func:`pipeline.dsp.cml.kernels.model.sums`), the gradient exact. The system is the
        live targets' alone: a target that is not live (zero amplitude) takes no part in it
        (its rows and columns zero), so it does not bend the live ones' step."""
        b, k = self.nu.shape
        n = self.kc.size
        dw = self.w * ((-2j * np.pi / n) * self.kc)
        r = np.concatenate([self.w.real, dw.real, self.w.imag, dw.imag], axis=1)  # (B, 4K, N)
        r32 = r.astype(np.float32)
        # the ramps share one curvature, the mean of h over them (as the kernels' sums)
        hbar = self.h[:, 0] if self.codes.rm == 1 else self.h.mean(axis=1)
        hw = np.ascontiguousarray(hbar.reshape(b, n, 4).transpose(0, 2, 1), dtype=np.float32)
        gram = np.matmul(r32[:, None] * hw[:, :, None], np.ascontiguousarray(r32.transpose(0, 2, 1))[:, None])
        gram = gram.astype(float)
        hess = np.zeros((b, 6 * k, 6 * k))
        grad = np.zeros((b, 6 * k))
        for q, cq in enumerate(self.cr):
            zc = coefficients(self.amp, self.phi, cq)
            hess += np.matmul(zc.transpose(0, 1, 3, 2), np.matmul(gram, zc)).sum(axis=1)
            proj = np.matmul(r, self.g[:, q].reshape(b, n, 4)).transpose(0, 2, 1)[..., None]  # (B, 4, 4K, 1)
            grad += np.matmul(zc.transpose(0, 1, 3, 2), proj).sum(axis=1)[..., 0]
        dead = np.repeat(~self.live, 6, axis=1)  # (B, 6K): the system of the live targets' parameters alone
        if dead.any():
            hess = np.where(dead[:, :, None] | dead[:, None, :], 0.0, hess)
            grad = np.where(dead, 0.0, grad)
        diag = np.diagonal(hess, axis1=1, axis2=2)
        damp = self.lm[:, None] * diag + 1e-9 * diag.max(axis=1, keepdims=True) + 1e-300
        step = -np.linalg.solve(hess + damp[:, :, None] * np.eye(6 * k), grad[..., None])[..., 0]
        return step.reshape(b, k, 6)


# -- detection and the count test ------------------------------------------------------------
#: the phase steps of a search of R >= 3 model ramps, a ramp (as the kernels':
#: :data:`pipeline.dsp.cml.kernels.doppler.DOPPLER_PER_RAMP`)
DOPPLER_PER_RAMP = 4
#: the static channel unless the phase step gains this many mean totals (as the kernels':
#: :data:`pipeline.dsp.cml.kernels.doppler.STEER_GAIN`)
STEER_GAIN = 8.0


def _steered(u: np.ndarray, cr: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """``sum_p |sum_r exp(-i c_r phi) u[..., r, p, :]|^2`` for each phase step ``phi`` (D,):
    u (B, Rm, 2, L) -> (B, D, L)."""
    steer = np.exp(-1j * cr[None, :] * phi[:, None])  # (D, Rm)
    v = np.einsum("dr,brpl->bdpl", steer, u)
    return (np.abs(v) ** 2).sum(axis=2)


def doppler(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The total ``sum_r |U_r|^2`` and the peak over the phase step of the back projections
    ``u`` (B, Rm, 2, L), each (B, L) (as :func:`pipeline.dsp.cml.kernels.doppler.doppler`)."""
    rm = u.shape[1]
    if rm == 1:
        w = np.ascontiguousarray(u[:, 0]).view(float)  # (B, 2, 2L)
        w = w * w
        both = w[:, 0] + w[:, 1]
        e = both[:, 0::2] + both[:, 1::2]  # (B, L): |U1|^2 + |U2|^2, the kernels' order
        return e, e.copy()
    total = (np.abs(u) ** 2).sum(axis=(1, 2))
    if rm == 2:
        x = (np.conj(u[:, 0]) * u[:, 1]).sum(axis=1)
        return total, total + 2.0 * np.abs(x)
    d = DOPPLER_PER_RAMP * rm
    return total, _steered(u, ramp_offsets(rm), 2.0 * np.pi * np.arange(d) / d).max(axis=1)


def doppler_phase(vals: np.ndarray) -> np.ndarray:
    """The phase step (B,) rad in (-pi, pi] at the peak of :func:`doppler` of one point's back
    projections ``vals`` (B, Rm, 2) (as :func:`pipeline.dsp.cml.kernels.doppler.doppler_phase`)."""
    b, rm = vals.shape[:2]
    if rm == 1:
        return np.zeros(b)
    if rm == 2:
        x = (np.conj(vals[:, 0]) * vals[:, 1]).sum(axis=1)
        return np.arctan2(x.imag, x.real)
    d = DOPPLER_PER_RAMP * rm
    step = 2.0 * np.pi / d
    e = _steered(vals[..., None], ramp_offsets(rm), step * np.arange(d))[..., 0]  # (B, D)
    best = np.argmax(e, axis=1)
    top, left, right = (np.take_along_axis(e, ((best + j) % d)[:, None], axis=1)[:, 0] for j in (0, -1, 1))
    curv = left - 2.0 * top + right
    off = np.where(curv < 0, np.clip(0.5 * (left - right) / np.where(curv < 0, curv, -1.0), -0.5, 0.5), 0.0)
    phi = step * (best + off)
    return np.where(phi > np.pi, phi - 2.0 * np.pi, phi)


def energy(y: np.ndarray, fit: Fit, oversample: int, guard_bins: float,
           gated: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The joint energy searched and the total (B, L) of the back projections of ``y`` (B,
    Rm, N, 2) (one a model ramp, :func:`doppler`) on a grid of ``oversample`` points a bin
    (zero-padded inverse FFT), zero within ``guard_bins`` of the live targets found, and that
    mask (B, L) bool. The energy searched: one ramp, ``|U1|^2 + |U2|^2``; more, on a grid
    with a coarse one (:attr:`SearchGrid.coarse`) the energy at the phase step of the best
    coarse point not masked (largest peak over the phase step; beyond the range gate -1 when
    ``gated``, the count test's search: detection's is the whole axis; within the guard 0; 0
    unless it gains :data:`STEER_GAIN` mean totals), as
    :func:`pipeline.dsp.cml.kernels.search.steer`; without one, each point's
    peak over the phase step."""
    b, rm, n = y.shape[:3]
    size = oversample * n
    u = np.fft.ifft(np.ascontiguousarray(y.transpose(0, 1, 3, 2)), n=size, axis=3)  # (B, Rm, 2, L)
    total, e = doppler(u)
    near = np.zeros(e.shape, dtype=bool)
    reach = int(np.ceil(guard_bins * oversample)) - 1
    for j in range(fit.nu.shape[1]):
        idx = np.rint(fit.nu[:, j] * oversample).astype(np.int64)[:, None] + np.arange(-reach, reach + 1)
        np.put_along_axis(near, idx % size, fit.live[:, j, None], axis=1)
    if rm > 1 and fit.grid.coarse:
        points = np.arange(0, size, oversample // COARSE_PER_BIN)
        v = np.where(near[:, points], 0.0, e[:, points])
        if gated and fit.grid.use:
            v = np.where(fit.grid.outside[points], -1.0, v)
        best = points[np.argmax(v, axis=1)]
        at = u[np.arange(b), :, :, best]  # (B, Rm, 2)
        gain = e[np.arange(b), best] - (np.abs(at.sum(axis=1)) ** 2).sum(axis=1)
        phi = np.where(gain > STEER_GAIN * total[:, points].mean(axis=1), doppler_phase(at), 0.0)
        steer = np.exp(-1j * fit.cr[None, :] * phi[:, None])  # (B, Rm)
        e = (np.abs(np.einsum("br,brpl->bpl", steer, u)) ** 2).sum(axis=1)
    e[near] = 0.0
    total[near] = 0.0
    return e, total, near


def residual(codes: Codes, fit: Fit) -> np.ndarray:
    """``Z - xi - model`` (full frames: ``Z - model``) of each model ramp (static: summed over
    the ramps), (B, Rm, N, 2)."""
    return codes.data - (codes.ramps // codes.rm) * fit.model()


def score(codes: Codes, fit: Fit) -> np.ndarray:
    """The likelihood's score ``-g`` at the model (the efficient score once the fit settled,
    :meth:`Fit.settled_score`), (B, Rm, N, 2) complex."""
    g = fit.g if fit.ge is None else fit.ge
    return np.ascontiguousarray(-g).reshape(fit.nu.shape[0], codes.rm, codes.n, 4).view(complex)


def peak_ratio(y: np.ndarray, fit: Fit, oversample: int, floor: np.ndarray | None = None) -> np.ndarray:
    """Peak over mean (B,) of the joint energy of the back projections of ``y`` (B, Rm, N, 2)
    beyond COUNT_GUARD_BINS of the targets found and inside the range gate (0 where ``y`` is
    exactly 0): the peak energy's largest over the totals' mean, the mean not below ``floor``
    (B,) (:func:`pipeline.dsp.cml.count.precision_floor`, :func:`~pipeline.dsp.cml.count.information_floor`)."""
    e, total, near = energy(y, fit, oversample, COUNT_GUARD_BINS, gated=True)
    if fit.grid.use:
        e[:, fit.grid.outside] = 0.0
        total[:, fit.grid.outside] = 0.0
        near |= fit.grid.outside
    mean = total.sum(axis=1) / np.maximum(e.shape[1] - near.sum(axis=1), 1)
    if floor is not None:
        mean = np.maximum(mean, floor)
    peak = e.max(axis=1)
    return np.divide(peak, mean, out=np.zeros_like(peak), where=mean > 0)


def count_statistic(fit: Fit, codes: Codes, oversample: int) -> np.ndarray:
    """The count test's statistic (B,): peak over mean of the linear residual and of the
    likelihood's score (:mod:`pipeline.dsp.cml.count`), the smaller; unquantized frames: the
    linear residual, its mean not below the frames' precision."""
    if codes.bits is None:
        return peak_ratio(residual(codes, fit), fit, oversample, precision_floor(codes.y, oversample))
    ratio = peak_ratio(residual(codes, fit), fit, oversample)
    floor = information_floor(fit.h, codes.n, oversample) if fit.nu.shape[1] else None
    return np.minimum(ratio, peak_ratio(score(codes, fit), fit, oversample, floor))


def detect(fit: Fit, codes: Codes, oversample: int) -> np.ndarray:
    """Range (bins, (B,)) of the peak of the joint energy of the residual's back projection
    (the score after the first target) on a grid of ``oversample`` points a bin, refined by a
    parabola, on the whole axis (a range gate bounds what is reported, not what is modelled)."""
    first = fit.nu.shape[1] == 0 or codes.bits is None
    e, _, _ = energy(residual(codes, fit) if first else score(codes, fit), fit, oversample, MIN_SEPARATION_BINS)
    size = e.shape[1]
    peak = np.argmax(e, axis=1)
    left, centre, right = (np.take_along_axis(e, ((peak + d) % size)[:, None], axis=1)[:, 0] for d in (-1, 0, 1))
    curv = left - 2 * centre + right
    off = np.where(curv < 0, 0.5 * (left - right) / np.where(curv < 0, curv, -1.0), 0.0)
    return (peak + np.clip(off, -0.5, 0.5)) / oversample


def amplitude_at(codes: Codes, fit: Fit, nu0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares amplitudes (B, 2) and phase step (B,) of one target at ``nu0`` (bins) in
    ``Z - xi - model``: each model ramp's matched filter, the phase step where they add up
    best (:func:`doppler_phase`), the ramps turned back by it and averaged."""
    w = atoms(nu0[:, None], fit.kc)[:, 0]
    vals = np.einsum("bn,brnp->brp", np.conj(w), residual(codes, fit))  # (B, Rm, 2)
    if codes.rm == 1:
        return vals[:, 0] / (codes.ramps * codes.n), np.zeros(nu0.shape[0])
    phi = doppler_phase(vals)
    back = np.exp(-1j * fit.cr[None, :] * phi[:, None])  # (B, Rm)
    return np.einsum("br,brp->bp", back, vals) / (codes.rm * codes.n), phi


class ReferenceBlocks:
    """The numpy engine of a :class:`pipeline.dsp.cml.decoder.CmlDecoder` (radar ``config``,
    ``options``): decodes blocks of checked frames, as :class:`pipeline.dsp.cml.compiled.CompiledBlocks`."""

    #: the frames' finite and level checks: numpy's (:func:`pipeline.dsp.cml.checks.check_frames`)
    in_kernel = None

    def __init__(self, config: RadarConfig, options: CmlOptions):
        self.config, self.options = config, options

    def decode(self, frames: Frames, k: int, iters: int, grid: SearchGrid, threshold: float | None,
               nuisance: bool = False) -> CmlResult:
        """One block from scratch: greedy stages (count test at ``threshold``), then the
        annealing; with a count test or ``nuisance``, the fit settled before each stage and,
        with a range gate, up to ``grid.stages`` more stages while a frame holds fewer than ``k``
        targets inside it (as :meth:`pipeline.dsp.cml.compiled.CompiledBlocks.decode`)."""
        b = frames.z.shape[0]
        oversample, anneal = self.options.oversample, self.options.anneal
        codes = Codes(frames, self.config.samples_per_ramp, self.options.likelihood, self.options.motion)
        fit = Fit(codes, grid)
        sigma, floor, amp_cap = start(frames)
        active = np.ones(b, dtype=bool)  # frames whose residual may still hold a target
        settled = False  # the fit annealed since its last target (the count test's)
        if threshold is not None:
            fit.evaluate(sigma)  # the score of the empty model, for the first count test
        settling = threshold is not None or nuisance
        for _ in range(k + (grid.stages if settling else 0)):
            if settling and fit.nu.shape[1]:  # the residuals of the settled fit
                self._settle(codes, fit, sigma, floor, amp_cap, frames.noise_sigma is None)
                settled = True
                if threshold is not None and codes.bits is not None:
                    fit.settled_score()
            if settling and grid.use:  # a frame with k targets inside the gate is done
                active &= (fit.live & grid.inside(fit.nu)).sum(axis=1) < k
            if threshold is not None:
                active &= count_statistic(fit, codes, oversample) >= threshold
            if not active.any():
                break
            settled = False
            nu0 = detect(fit, codes, oversample)
            amp0, phi0 = amplitude_at(codes, fit, nu0)
            amp0 = np.where(active[:, None], amp0, 0.0)
            phi0 = np.where(active, phi0, 0.0)
            fit.set(np.concatenate([fit.nu, nu0[:, None]], axis=1), np.concatenate([fit.phi, phi0[:, None]], axis=1),
                    np.concatenate([fit.amp, amp0[:, None]], axis=1), np.concatenate([fit.live, active[:, None]], axis=1))
            fit.evaluate(sigma)
            fit.run(np.repeat(sigma[:, None], iters, axis=1), amp_cap)
        if settled:
            return self._result(fit, codes, codes.noise_rms(fit.mu) if codes.bits is None else fit.sigma, k)
        return self._anneal(codes, fit, sigma, floor, amp_cap, frames.noise_sigma is None, k)

    def _settle(self, codes: Codes, fit: Fit, sigma, floor, amp_cap, adapt: bool) -> None:
        """The fit annealed to its floor (unquantized: polished), as at the end of a decode:
        what the count test reads (at the greedy stage's scale the likelihood's score carries
        the quantizer's harmonics of the targets found, docs/science.md)."""
        anneal = self.options.anneal
        if codes.bits is not None and anneal:
            fit.run(anneal_levels(sigma, floor, anneal), amp_cap, adapt=adapt)
        elif codes.bits is None:
            fit.run(np.ones((fit.nu.shape[0], anneal)), amp_cap)

    def _anneal(self, codes: Codes, fit: Fit, sigma, floor, amp_cap, adapt: bool, k: int,
                levels: np.ndarray | None = None) -> CmlResult:
        """The annealing (``levels``; None: :func:`~pipeline.dsp.cml.schedule.anneal_levels`;
        ``adapt``: not sharper than the noise the model leaves), then the result."""
        anneal = self.options.anneal
        if codes.bits is not None and anneal:
            fit.run(anneal_levels(sigma, floor, anneal) if levels is None else levels, amp_cap, adapt=adapt)
            sigma = fit.sigma
        if codes.bits is None:
            fit.run(np.ones((fit.nu.shape[0], anneal)), amp_cap)  # least squares: polish
            sigma = codes.noise_rms(fit.mu)
        return self._result(fit, codes, sigma, k)

    def warm(self, frames: Frames, k: int, init: np.ndarray, grid: SearchGrid,
             at: float) -> tuple[CmlResult, np.ndarray, np.ndarray]:
        """One block refined from the ranges ``init`` (B, k) m (NaN: absent); returns the
        result, the targets a frame and the count test's statistic of the final residual."""
        codes = Codes(frames, self.config.samples_per_ramp, self.options.likelihood, self.options.motion)
        fit = Fit(codes, grid)
        sigma, floor, amp_cap = start(frames)
        live_all = ~np.isnan(init)
        order = np.argsort(~live_all, axis=1, kind="stable")  # the given ranges first
        nu_all = np.nan_to_num(np.take_along_axis(init, order, axis=1)) / self.config.range_resolution_m
        live_all = np.take_along_axis(live_all, order, axis=1)
        for t in range(int(live_all.sum(axis=1).max())):  # amplitudes one at a time in the residual
            amp0, phi0 = amplitude_at(codes, fit, nu_all[:, t])
            amp0 = np.where(live_all[:, t, None], amp0, 0.0)
            phi0 = np.where(live_all[:, t], phi0, 0.0)
            fit.set(nu_all[:, :t + 1], np.concatenate([fit.phi, phi0[:, None]], axis=1),
                    np.concatenate([fit.amp, amp0[:, None]], axis=1), live_all[:, :t + 1])
        fit.evaluate(sigma)
        fit.run(np.repeat(sigma[:, None], WARM_STEPS, axis=1), amp_cap)
        levels = warm_levels(sigma, floor, self.options.anneal) if codes.bits is not None and self.options.anneal \
            else None
        res = self._anneal(codes, fit, sigma, floor, amp_cap, frames.noise_sigma is None, k, levels)
        if codes.bits is not None:
            fit.settled_score()
        return res, (fit.live & grid.inside(fit.nu)).sum(axis=1), count_statistic(fit, codes, self.options.oversample)

    def _result(self, fit: Fit, codes: Codes, sigma: np.ndarray, k: int) -> CmlResult:
        """The fit in the model's terms, its statistic, padded to ``k`` targets (absent ones
        last) or cut to them, present ones (live, inside the gate) strongest first."""
        n, ramps, config = codes.n, codes.ramps, self.config
        b, t = fit.nu.shape
        range_m = (fit.nu % n) * config.range_resolution_m  # the axis is circular
        # a = mu at k = 0 over the carrier term there, exp(-i 4 pi f0 r / c)
        amp = fit.amp * (np.exp((-2j * np.pi / n) * fit.nu * fit.kc[0]) / range_phase(config.f0_hz, range_m, config))[
            ..., None]
        # the phase step in (-pi, pi]; a turn of 2 pi turns the amplitudes by pi with an even Rm
        turns = np.rint(fit.phi / (2.0 * np.pi))
        phi = fit.phi - 2.0 * np.pi * turns if codes.rm > 1 else np.full(fit.phi.shape, np.nan)
        if codes.rm > 1 and codes.rm % 2 == 0:
            amp = amp * np.where(turns % 2 != 0, -1.0, 1.0)[..., None]
        # the mean joint power a bin of the residual's back projection, |ifft(y) / R|^2 summed over the
        # antennas and averaged over the N bins: by Parseval sum |y|^2 / (N R)^2, without the FFT
        y = residual(codes, fit).view(float)
        noise = np.einsum("bj,bj->b", y.reshape(b, -1), y.reshape(b, -1)) / float(n * ramps) ** 2
        power = (np.abs(fit.amp) ** 2).sum(axis=2)
        with np.errstate(divide="ignore", invalid="ignore"):
            stat = to_db(power / noise[:, None])
        pad = max(k - t, 0)
        range_m = np.concatenate([range_m, np.full((b, pad), np.nan)], axis=1)
        amp = np.concatenate([amp, np.zeros((b, pad, 2), dtype=complex)], axis=1)
        stat = np.concatenate([stat, np.full((b, pad), np.nan)], axis=1)
        phi = np.concatenate([phi, np.full((b, pad), np.nan)], axis=1)
        power = np.concatenate([power, np.zeros((b, pad))], axis=1)
        present = np.concatenate([fit.live & fit.grid.inside(fit.nu), np.zeros((b, pad), dtype=bool)], axis=1)
        order = np.lexsort((-power, ~present), axis=1)[:, :k]  # present first, then strongest first
        return CmlResult(np.take_along_axis(range_m, order, axis=1), np.take_along_axis(amp, order[..., None], axis=1),
                         np.take_along_axis(stat, order, axis=1), sigma, np.take_along_axis(present, order, axis=1),
                         np.take_along_axis(phi, order, axis=1))
