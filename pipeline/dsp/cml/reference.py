"""cml's numpy reference (``engine="numpy"``): the same decode as the compiled engine, vectorized
over a block of frames in numpy, with the exact logistic (numpy's ``exp`` and ``log1p``) and the
Gauss--Newton system from explicit Jacobians. It is the oracle the compiled kernels are tested
against (tests/test_cml_kernels.py and the others): the two take the same steps, in another
floating-point order.

Shapes: a block of B frames of R ramps of N samples; the real parts of a sample as
(antenna, re/im); per-target arrays (B, K), amplitudes (B, K, 2); ranges in bins."""

from __future__ import annotations

import numpy as np

from radar_driver.model import RadarConfig, range_phase

from pipeline.dsp.cml.checks import Frames
from pipeline.dsp.cml.count import COUNT_GUARD_BINS, information_floor, precision_floor
from pipeline.dsp.cml.grid import MIN_SEPARATION_BINS, SearchGrid
from pipeline.dsp.cml.options import LOGISTIC_PER_SIGMA, MAX_RANGE_STEP_BINS, WRONG_RMS_PER_SIGMA, CmlOptions
from pipeline.dsp.cml.result import CmlResult
from pipeline.dsp.cml.schedule import WARM_STEPS, anneal_levels, residual_rms, start, warm_levels, wrong_codes_rms
from pipeline.dsp.localize import to_db

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)


class Codes:
    """A block's measurements as real arrays (B, R, N, 2 antennas, 2 re/im) and the negative
    log-likelihood (NLL) of a model ``mu`` (B, N, 2, 2) repeated on every ramp, in float32 work
    arrays (quantized) as the kernels'."""

    def __init__(self, frames: Frames, n: int, likelihood: str):
        z, bits, delta = frames.z, frames.bits, frames.delta
        b, m = z.shape[:2]
        self.bits, self.ramps, self.n, self.likelihood = bits, m // n, n, likelihood
        shape = (b, self.ramps, n, 2, 2)
        q = None
        if z.ndim == 4:  # codes: the levels q in [-2^(b-1), 2^(b-1)), Z = delta (q + 1/2)
            q = z.reshape(shape).astype(np.float64) - (1 << (bits - 1))
            z = (delta[:, None, None, None, None] * (q + 0.5)).view(complex).reshape(b, m, 2)
        zr = np.ascontiguousarray(z, dtype=complex).view(float).reshape(shape)
        self.data = z if bits is None else z - frames.xi  # what detection and amplitudes back-project
        self.folded = self.data.reshape(b, self.ramps, n, 2).sum(axis=1)  # summed over the ramps, (B, N, 2)
        if bits is None:
            self.y = zr
            return
        xr = np.ascontiguousarray(frames.xi, dtype=complex).view(float).reshape(shape)
        d = delta[:, None, None, None, None]
        half = 1 << (bits - 1)
        if q is None:
            q = np.rint(zr / d - 0.5)  # zr = (q + 1/2) delta
        self.work = [np.empty(shape, dtype=np.float32) for _ in range(3)]
        if bits == 1:
            s = np.where(q >= 0, 1.0, -1.0)  # the sign of lambda + xi
            self.s, self.so, self.half_s = s.astype(np.float32), (s * xr).astype(np.float32), 0.5 * s.sum(axis=1)
            self.ka, self.kb = self.s, self.so
            return
        self.lo = (np.where(q <= -half, -np.inf, q * d) - xr).astype(np.float32)  # lambda's cell: [lo, hi)
        self.hi = (np.where(q >= half - 1, np.inf, (q + 1) * d) - xr).astype(np.float32)
        self.ka, self.kb = self.lo, self.hi

    def evaluate(self, mu: np.ndarray, sigma: np.ndarray):
        """NLL (B,) and its first and second derivatives in each real measurement, summed
        over the ramps (B, N, 2, 2). mu : (B, N, 2, 2); sigma : (B,) the noise std of the
        likelihood (the logistic's scale is ``sigma / LOGISTIC_PER_SIGMA``)."""
        if self.bits is None:
            r = mu[:, None] - self.y
            return 0.5 * np.einsum("brnpc,brnpc->b", r, r), r.sum(axis=1), np.full(mu.shape, float(self.ramps))
        if self.likelihood == "gaussian":
            return self._gaussian(mu, sigma)
        scale = sigma / LOGISTIC_PER_SIGMA
        mu = mu[:, None].astype(np.float32)
        inv = (1.0 / scale).astype(np.float32)[:, None, None, None, None]
        u = self.work[0]
        if self.bits == 1:
            np.multiply(self.s, mu, out=u)
            u += self.so
            u *= inv  # s (mu + xi) / T: the margin, > 0 for a code the model gets right
            nll, g, h = self._softplus(u, self.s)
        else:
            # -log(F(c) - F(a)) = -log F(-a) - log F(c) + const, a = (lo - mu) / T, c = (hi - mu) / T
            np.subtract(mu, self.lo, out=u)
            u *= inv
            nll, g, h = self._softplus(u, 1.0)
            np.subtract(self.hi, mu, out=u)
            u *= inv
            nll_c, g_c, h_c = self._softplus(u, -1.0)
            nll, g, h = nll + nll_c, g + g_c, h + h_c
        inv = inv[:, 0].astype(float)
        return nll, g * inv, h * (inv * inv)

    def _gaussian(self, mu: np.ndarray, sigma: np.ndarray):
        """:meth:`evaluate` with the exact Gaussian likelihood (float64, scipy's log_ndtr)."""
        from scipy.special import log_ndtr  # here: importing scipy costs the others' start-up

        b = mu.shape[0]
        inv = (1.0 / sigma)[:, None, None, None, None]
        mu = mu[:, None]
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            if self.bits == 1:
                s = self.s.astype(float)
                v = (s * mu + self.so) * inv  # the margin in units of sigma
                lp = log_ndtr(v)
                r = np.exp(-0.5 * v * v - _LOG_SQRT_2PI - lp)  # phi(v) / Phi(v)
                nll, dv, d2v = -lp, -r * s, r * (v + r)
            else:
                nll, dv, d2v = _gauss_cells((self.lo - mu) * inv, (self.hi - mu) * inv, log_ndtr)
        inv = inv[:, 0]
        return nll.reshape(b, -1).sum(axis=1), dv.sum(axis=1) * inv, d2v.sum(axis=1) * (inv * inv)

    def _softplus(self, u, sign):
        """Sum per frame of ``-log F(u)`` (B,), and its first and second derivatives in
        lambda times T and T^2, summed over the ramps (B, N, 2, 2), where
        ``u = sign lambda / T + const``; ``sign`` is +-1 or an array. Overwrites work arrays."""
        b = u.shape[0]
        e, t = self.work[1], self.work[2]
        np.abs(u, out=e)
        np.minimum(e, 40.0, out=e)  # exp(-40) ~ 4e-18: no float32 subnormals (slow) downstream
        np.negative(e, out=e)
        np.exp(e, out=e)  # exp(-|u|)
        np.minimum(u, 0.0, out=t)
        nll = -t.reshape(b, -1).sum(axis=1, dtype=float)
        np.log1p(e, out=t)
        nll += t.reshape(b, -1).sum(axis=1, dtype=float)  # -log F(u) = max(-u, 0) + log(1 + exp(-|u|))
        np.add(e, 1.0, out=t)
        np.reciprocal(t, out=t)
        np.multiply(e, t, out=e)  # q = F(-|u|)
        np.multiply(e, t, out=t)  # F(u) F(-u) = q (1 - q)
        h = t.sum(axis=1, dtype=float)
        np.subtract(0.5, e, out=e)
        np.copysign(e, u, out=e)  # F(-u) = 1/2 - copysign(1/2 - q, u)
        if np.isscalar(sign):  # d(-log F(u)) / d lambda = -sign F(-u) / T
            g = sign * (e.sum(axis=1, dtype=float) - 0.5 * self.ramps)
        else:
            e *= sign
            g = e.sum(axis=1, dtype=float) - self.half_s
        return nll, g, h

    def noise_rms(self, mu: np.ndarray) -> np.ndarray:
        """RMS distance (B,) of the codes that ``mu`` gets wrong to their cells (0 when none
        is wrong); unquantized frames: RMS of the residual."""
        if self.bits is None:
            return residual_rms(self.y, mu)
        return wrong_codes_rms(self.ka, self.kb, self.bits, mu)


def _gauss_cells(a: np.ndarray, c: np.ndarray, log_ndtr):
    """``-log(Phi(c) - Phi(a))`` and its first and second derivatives in lambda times s and
    s^2, with ``a = (lo - lambda) / s``, ``c = (hi - lambda) / s``, stable in both tails."""
    flip = a + c > 0.0  # the upper tail: Phi(c) - Phi(a) = Phi(-a) - Phi(-c)
    a2, c2 = np.where(flip, -c, a), np.where(flip, -a, c)
    lh = log_ndtr(c2)
    ld = lh + np.log1p(-np.exp(log_ndtr(a2) - lh))  # log(Phi(c) - Phi(a))
    pa = np.where(np.isfinite(a), np.exp(-0.5 * a * a - _LOG_SQRT_2PI - ld), 0.0)  # phi(a) / P
    pc = np.where(np.isfinite(c), np.exp(-0.5 * c * c - _LOG_SQRT_2PI - ld), 0.0)
    dv = pc - pa
    d2v = dv * dv + np.where(np.isfinite(c), c * pc, 0.0) - np.where(np.isfinite(a), a * pa, 0.0)
    return -ld, dv, d2v


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


def coefficients(amp: np.ndarray) -> np.ndarray:
    """Z (B, 4, 4K, 5K): the derivative of part c (0 real, 1 imaginary) of the model on
    antenna p in the parameters is ``R^T Z[2p + c]`` (see :meth:`Fit.step`)."""
    b, k, _ = amp.shape
    z = np.zeros((b, 4, 4 * k, 5 * k))
    t = np.arange(k)
    for p in range(2):
        re, im = 2 * p, 2 * p + 1
        # a parameter moves mu_p along A v: Re b_tp: v = e_t; Im b_tp: v = i e_t; nu_t:
        # v = b_tp e_{K+t}. Re(A v) = Re A Re v - Im A Im v, Im(A v) = Re A Im v + Im A Re v;
        # rows [0, 2K) of R are Re A, rows [2K, 4K) Im A.
        z[:, re, t, 5 * t + 1 + 2 * p] = 1.0
        z[:, im, 2 * k + t, 5 * t + 1 + 2 * p] = 1.0
        z[:, re, 2 * k + t, 5 * t + 2 + 2 * p] = -1.0
        z[:, im, t, 5 * t + 2 + 2 * p] = 1.0
        a = amp[:, :, p]
        z[:, re, k + t, 5 * t] = a.real
        z[:, re, 3 * k + t, 5 * t] = -a.imag
        z[:, im, k + t, 5 * t] = a.imag
        z[:, im, 3 * k + t, 5 * t] = a.real
    return z


class Fit:
    """The targets found so far, the model and the likelihood at them, and
    Levenberg--Marquardt steps on all of them at once. A target's parameters are [nu, Re b1,
    Im b1, Re b2, Im b2]: range in bins and the amplitudes referred to mid-sweep; on one ramp
    the model is ``mu_{n,p} = sum_t b_{t,p} w_t[n]`` with ``w_t[n] = exp(-i 2 pi kc_n nu_t / N)``."""

    def __init__(self, codes: Codes, grid: SearchGrid):
        n = codes.n
        self.codes, self.grid, self.kc = codes, grid, np.arange(n) - (n - 1) / 2.0
        b = codes.folded.shape[0]
        self.set(np.zeros((b, 0)), np.zeros((b, 0, 2), dtype=complex), np.zeros((b, 0), dtype=bool))

    def set(self, nu: np.ndarray, amp: np.ndarray, live: np.ndarray) -> None:
        """Targets (B, K) in bins, amplitudes (B, K, 2); ``live`` (B, K): the targets
        that move (the others stay where they are: zero amplitude, past a frame's count)."""
        self.nu, self.amp, self.live = nu, amp, live
        self.ge = None  # the efficient score's g (:meth:`settled_score`), while the fit does not move
        self.w = atoms(nu, self.kc)
        self.mu = self._mu(self.w, amp)
        self.lm = np.full(nu.shape[0], 1e-3)  # damping, per frame

    @staticmethod
    def _mu(w: np.ndarray, amp: np.ndarray) -> np.ndarray:
        mu = np.matmul(w.transpose(0, 2, 1), amp)  # (B, N, 2) complex
        return mu.view(float).reshape(mu.shape + (2,))

    def model(self) -> np.ndarray:
        """One ramp of the model, (B, N, 2) complex."""
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
        norm = np.linalg.norm(step[..., 1:], axis=2)
        step[..., 1:] *= np.minimum(1.0, amp_cap[:, None] / np.maximum(norm, 1e-300))[..., None]
        nu = self.nu + step[..., 0]
        amp = self.amp + (step[..., 1::2] + 1j * step[..., 2::2])
        w = atoms(nu, self.kc)
        mu = self._mu(w, amp)
        nll, g, h = self.codes.evaluate(mu, self.sigma)
        ok = nll <= self.nll
        self.lm = np.clip(np.where(ok, self.lm / 3.0, self.lm * 8.0), 1e-9, 1e9)
        bad = np.flatnonzero(~ok)  # frames that keep their parameters (few)
        for new, old in ((nu, self.nu), (amp, self.amp), (w, self.w), (mu, self.mu), (g, self.g), (h, self.h),
                         (nll, self.nll)):
            new[bad] = old[bad]
        self.nu, self.amp, self.w, self.mu, self.g, self.h, self.nll = nu, amp, w, mu, g, h, nll
        self.ge = None

    def settled_score(self) -> None:
        """Into ``ge`` (B, N, 2, 2) the efficient score's ``g``: the NLL's derivatives at the
        model less what the targets' own parameters explain, ``g + h (J d)`` with ``d`` the
        undamped Gauss--Newton step of the live targets (:meth:`_solve`) and ``J`` the model's
        Jacobian: ``J^T ge = 0``, the score no target found could take up by moving (Rao's
        test with the found targets' parameters as nuisances). A fit not yet at its optimum
        (steps left in a direction the codes barely fix, as the amplitudes of 1-bit codes
        without a dither) otherwise leaves a score along ``h J d``, which the weights ``h``
        (periodic with the targets where the codes are) carry to the targets' harmonics."""
        b, k = self.nu.shape
        if k == 0:
            self.ge = self.g
            return
        lm, self.lm = self.lm, np.zeros(b)
        step = self._solve()
        self.lm = lm
        step[~self.live] = 0.0
        n = self.kc.size
        db = step[..., 1::2] + 1j * step[..., 2::2]  # (B, K, 2)
        dw = self.w * ((-2j * np.pi / n) * self.kc)  # d w / d nu
        dmu = np.einsum("bkn,bkp->bnp", self.w, db) + np.einsum("bkn,bkp->bnp", dw, self.amp * step[..., :1])
        self.ge = self.g + self.h * dmu.view(float).reshape(self.g.shape)

    def _solve(self) -> np.ndarray:
        """The damped Gauss--Newton step (B, K, 5): the Jacobian of part c of mu_p is
        ``R^T Z[2p + c]``, R (4K, N) the real and imaginary parts of the atoms w_t and of
        dw_t / dnu, Z how each parameter mixes them (:func:`coefficients`). The system is the
        live targets' alone: a target that is not live (zero amplitude) takes no part in it
        (its rows and columns zero), so it does not bend the live ones' step."""
        b, k = self.nu.shape
        n = self.kc.size
        dw = self.w * ((-2j * np.pi / n) * self.kc)
        r = np.concatenate([self.w.real, dw.real, self.w.imag, dw.imag], axis=1)  # (B, 4K, N)
        r32 = r.astype(np.float32)
        hw = np.ascontiguousarray(self.h.reshape(b, n, 4).transpose(0, 2, 1), dtype=np.float32)
        gram = np.matmul(r32[:, None] * hw[:, :, None], np.ascontiguousarray(r32.transpose(0, 2, 1))[:, None])
        zc = coefficients(self.amp)
        hess = np.matmul(zc.transpose(0, 1, 3, 2), np.matmul(gram.astype(float), zc)).sum(axis=1)
        proj = np.matmul(r, self.g.reshape(b, n, 4)).transpose(0, 2, 1)[..., None]  # (B, 4, 4K, 1)
        grad = np.matmul(zc.transpose(0, 1, 3, 2), proj).sum(axis=1)[..., 0]
        dead = np.repeat(~self.live, 5, axis=1)  # (B, 5K): the system of the live targets' parameters alone
        if dead.any():
            hess = np.where(dead[:, :, None] | dead[:, None, :], 0.0, hess)
            grad = np.where(dead, 0.0, grad)
        diag = np.diagonal(hess, axis1=1, axis2=2)
        damp = self.lm[:, None] * diag + 1e-9 * diag.max(axis=1, keepdims=True) + 1e-300
        step = -np.linalg.solve(hess + damp[:, :, None] * np.eye(5 * k), grad[..., None])[..., 0]
        return step.reshape(b, k, 5)


# -- detection and the count test ------------------------------------------------------------
def energy(y: np.ndarray, fit: Fit, oversample: int, guard_bins: float) -> tuple[np.ndarray, np.ndarray]:
    """Joint energy ``|U1|^2 + |U2|^2`` (B, L) of the back projection of ``y`` (B, N, 2)
    on a grid of ``oversample`` points a bin (zero-padded inverse FFT), zero within
    ``guard_bins`` of the live targets found, and that mask (B, L) bool."""
    b, n = y.shape[:2]
    size = oversample * n
    u = np.fft.ifft(np.ascontiguousarray(y.transpose(0, 2, 1)), n=size, axis=2).view(float)  # (B, 2, 2L)
    np.square(u, out=u)
    both = u[:, 0] + u[:, 1]
    e = both[:, 0::2] + both[:, 1::2]  # (B, L): |U1|^2 + |U2|^2
    near = np.zeros(e.shape, dtype=bool)
    reach = int(np.ceil(guard_bins * oversample)) - 1
    for j in range(fit.nu.shape[1]):
        idx = np.rint(fit.nu[:, j] * oversample).astype(np.int64)[:, None] + np.arange(-reach, reach + 1)
        np.put_along_axis(near, idx % size, fit.live[:, j, None], axis=1)
    e[near] = 0.0
    return e, near


def residual(codes: Codes, fit: Fit) -> np.ndarray:
    """``Z - xi - model`` (full frames: ``Z - model``) summed over the ramps, (B, N, 2)."""
    return codes.folded - codes.ramps * fit.model()


def score(codes: Codes, fit: Fit) -> np.ndarray:
    """The likelihood's score ``-g`` at the model (the efficient score once the fit settled,
    :meth:`Fit.settled_score`), (B, N, 2) complex."""
    g = fit.g if fit.ge is None else fit.ge
    return np.ascontiguousarray(-g).reshape(fit.nu.shape[0], codes.n, 4).view(complex)


def peak_ratio(y: np.ndarray, fit: Fit, oversample: int, floor: np.ndarray | None = None) -> np.ndarray:
    """Peak over mean (B,) of the joint energy of the back projection of ``y`` (B, N, 2)
    beyond COUNT_GUARD_BINS of the targets found and inside the range gate (0 where ``y`` is
    exactly 0); the mean not below ``floor`` (B,) (:func:`pipeline.dsp.cml.count.precision_floor`)."""
    e, near = energy(y, fit, oversample, COUNT_GUARD_BINS)
    if fit.grid.use:
        e[:, fit.grid.outside] = 0.0
        near |= fit.grid.outside
    mean = e.sum(axis=1) / np.maximum(e.shape[1] - near.sum(axis=1), 1)
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
    floor = information_floor(fit.h, oversample) if fit.nu.shape[1] else None
    return np.minimum(ratio, peak_ratio(score(codes, fit), fit, oversample, floor))


def detect(fit: Fit, codes: Codes, oversample: int) -> np.ndarray:
    """Range (bins, (B,)) of the peak of the joint energy of the residual's back projection
    (the score after the first target) on a grid of ``oversample`` points a bin, refined by a
    parabola, on the whole axis (a range gate bounds what is reported, not what is modelled)."""
    first = fit.nu.shape[1] == 0 or codes.bits is None
    e, _ = energy(residual(codes, fit) if first else score(codes, fit), fit, oversample, MIN_SEPARATION_BINS)
    size = e.shape[1]
    peak = np.argmax(e, axis=1)
    left, centre, right = (np.take_along_axis(e, ((peak + d) % size)[:, None], axis=1)[:, 0] for d in (-1, 0, 1))
    curv = left - 2 * centre + right
    off = np.where(curv < 0, 0.5 * (left - right) / np.where(curv < 0, curv, -1.0), 0.0)
    return (peak + np.clip(off, -0.5, 0.5)) / oversample


def amplitude_at(codes: Codes, fit: Fit, nu0: np.ndarray) -> np.ndarray:
    """Least-squares amplitudes (B, 2) of one target at ``nu0`` (bins) in ``Z - xi - model``."""
    w = atoms(nu0[:, None], fit.kc)[:, 0]
    return np.einsum("bn,bnp->bp", np.conj(w), residual(codes, fit)) / (codes.ramps * codes.n)


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
        codes = Codes(frames, self.config.samples_per_ramp, self.options.likelihood)
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
            amp0 = np.where(active[:, None], amplitude_at(codes, fit, nu0), 0.0)
            fit.set(np.concatenate([fit.nu, nu0[:, None]], axis=1), np.concatenate([fit.amp, amp0[:, None]], axis=1),
                    np.concatenate([fit.live, active[:, None]], axis=1))
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
        codes = Codes(frames, self.config.samples_per_ramp, self.options.likelihood)
        fit = Fit(codes, grid)
        sigma, floor, amp_cap = start(frames)
        live_all = ~np.isnan(init)
        order = np.argsort(~live_all, axis=1, kind="stable")  # the given ranges first
        nu_all = np.nan_to_num(np.take_along_axis(init, order, axis=1)) / self.config.range_resolution_m
        live_all = np.take_along_axis(live_all, order, axis=1)
        for t in range(int(live_all.sum(axis=1).max())):  # amplitudes one at a time in the residual
            amp0 = np.where(live_all[:, t, None], amplitude_at(codes, fit, nu_all[:, t]), 0.0)
            fit.set(nu_all[:, :t + 1], np.concatenate([fit.amp, amp0[:, None]], axis=1), live_all[:, :t + 1])
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
        power = np.concatenate([power, np.zeros((b, pad))], axis=1)
        present = np.concatenate([fit.live & fit.grid.inside(fit.nu), np.zeros((b, pad), dtype=bool)], axis=1)
        order = np.lexsort((-power, ~present), axis=1)[:, :k]  # present first, then strongest first
        return CmlResult(np.take_along_axis(range_m, order, axis=1), np.take_along_axis(amp, order[..., None], axis=1),
                         np.take_along_axis(stat, order, axis=1), sigma, np.take_along_axis(present, order, axis=1))
