"""The likelihood of the codes and the Levenberg--Marquardt fit of :func:`pipeline.dsp.cml.cml`
(numpy reference; :mod:`pipeline.dsp.cml_kernels` holds the compiled equivalents).

Shapes: a block of B frames of R ramps of N samples; the real parts of a sample as
(antenna, re/im); per-target arrays (B, K), amplitudes (B, K, 2)."""

from __future__ import annotations

import importlib.util
from functools import lru_cache

import numpy as np

from radar_driver.model import RadarConfig

from pipeline.dsp.gate import RangeGate

#: numba is installed: the compiled kernels (:mod:`pipeline.dsp.cml_kernels`, imported on first
#: use so that importing this module stays cheap) can run; the numpy code below is their reference
HAVE_NUMBA = importlib.util.find_spec("numba") is not None
_kernels_module = None


def _kernels():
    global _kernels_module
    if _kernels_module is None:
        from pipeline.dsp import cml_kernels
        _kernels_module = cml_kernels
    return _kernels_module


#: the implementations of the per-frame work: "numba" (compiled, one frame at a time) or
#: "numpy" (vectorized over a block; the reference)
ENGINES = ("numba", "numpy")
DEFAULT_ENGINE = "numba" if HAVE_NUMBA else "numpy"
#: likelihoods of a code: "logistic" (scaled logistic in place of the Gaussian CDF) or
#: "gaussian" (the exact Gaussian CDF of the noise: ``Phi((hi - l) / s) - Phi((lo - l) / s)``)
LIKELIHOODS = ("logistic", "gaussian")
DEFAULT_LIKELIHOOD = "logistic"
_LIK = {"logistic": 0, "gaussian": 1}  # the kernels' codes

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)
#: logistic scale of a Gaussian of unit std (Phi(x) ~ F(1.702 x))
LOGISTIC_PER_SIGMA = 1.702
#: largest range change of one refinement step, range bins
MAX_RANGE_STEP_BINS = 0.5
#: RMS distance of the wrong codes to their cells, in units of the noise std (:mod:`pipeline.dsp.cml`)
WRONG_RMS_PER_SIGMA = np.sqrt(2.0 / 3.0)


_codes_arrays = None  # pipeline.dsp.cml_detect_kernels.codes_arrays, imported on first use


@lru_cache(maxsize=8)
def centred_indices(n: int) -> np.ndarray:
    """The sample indices of a ramp from its middle, ``kc = n - (N - 1) / 2`` (N,), once per N:
    shared by every :class:`_Fit` and only read (writeable: the compiled kernels' signatures)."""
    return np.arange(n) - (n - 1) / 2.0


# -- the likelihood ---------------------------------------------------------------------
class _Codes:
    """The measurements of a batch as real arrays (B, R, N, 2 antennas, 2 re/im) and the
    negative log-likelihood (NLL) of a model ``mu`` (B, N, 2, 2) repeated on every ramp.

    Quantized frames are held in float32 work arrays: float32 resolves 1e-7 of delta, far
    below the finest sigma_eff (delta / M), and halves the cost of the likelihood, which is
    evaluated about 20 times."""

    def __init__(self, z: np.ndarray, xi: np.ndarray | None, delta: np.ndarray | None, bits: int | None,
                 n: int, compiled: bool = False):
        """z: (B, M, 2) complex values, or (B, M, 2, 2) integer codes of ``bits`` bits
        (:class:`pipeline.dsp.quantize.QuantizedFrames`' codes: their levels are taken as they
        are, not recovered from the values). ``compiled``: only what the compiled engine reads
        (``ka``, ``kb``, ``folded``), built by one kernel."""
        b, m = z.shape[:2]
        self.bits, self.ramps, self.n = bits, m // n, n
        self.folded = None  # Z - xi (or Z) summed over the ramps, (B, N, 2) complex: set on first use
        shape = (b, self.ramps, n, 2, 2)
        if compiled and bits is not None:
            self._compiled(z, xi, delta, bits, (b, self.ramps, n, 4))
            return
        q = None
        if z.ndim == 4:  # codes: the levels q in [-2^(b-1), 2^(b-1)), Z = delta (q + 1/2)
            q = z.reshape(shape).astype(np.float64) - (1 << (bits - 1))
            z = (delta[:, None, None, None, None] * (q + 0.5)).view(complex).reshape(b, m, 2)
        zr = np.ascontiguousarray(z, dtype=complex).view(float).reshape(shape)
        if bits is None:
            self.data = z  # what detection and amplitudes back-project
            self.y = zr
            self.kind = 0  # the kernels' LSQ
            self.ka = self.kb = zr.reshape(b, self.ramps, n, 4)  # the kernels' arrays
            return
        self.data = z - xi
        xr = np.ascontiguousarray(xi, dtype=complex).view(float).reshape(shape)
        d = delta[:, None, None, None, None]
        half = 1 << (bits - 1)
        if q is None:
            q = np.rint(zr / d - 0.5)  # zr = (q + 1/2) delta
        self.work = [np.empty(shape, dtype=np.float32) for _ in range(3)]
        if bits == 1:
            s = np.where(q >= 0, 1.0, -1.0)  # the sign of lambda + xi
            self.s = s.astype(np.float32)
            self.so = (s * xr).astype(np.float32)
            self.half_s = 0.5 * s.sum(axis=1)
            self.kind = 1  # ONE_BIT
            self.ka, self.kb = self.s.reshape(b, self.ramps, n, 4), self.so.reshape(b, self.ramps, n, 4)
            return
        self.lo = (np.where(q <= -half, -np.inf, q * d) - xr).astype(np.float32)  # lambda's cell: [lo, hi)
        self.hi = (np.where(q >= half - 1, np.inf, (q + 1) * d) - xr).astype(np.float32)
        self.kind = 2  # MULTI_BIT
        self.ka, self.kb = self.lo.reshape(b, self.ramps, n, 4), self.hi.reshape(b, self.ramps, n, 4)

    def _compiled(self, z, xi, delta, bits, shape) -> None:
        global _codes_arrays
        if _codes_arrays is None:  # imported on first use (it imports numba)
            from pipeline.dsp.cml_detect_kernels import codes_arrays as _codes_arrays

        from_codes = z.ndim == 4
        if from_codes:
            zk = (z if z.dtype == np.uint8 else z.astype(np.int64)).reshape(shape)
        else:
            zk = np.ascontiguousarray(z, dtype=complex).view(float).reshape(shape)
        ka = self.ka = np.empty(shape, dtype=np.float32)
        kb = self.kb = np.empty(shape, dtype=np.float32)
        folded = self.folded = np.empty((shape[0], shape[2], 2), dtype=complex)
        _codes_arrays(zk, from_codes, np.ascontiguousarray(xi, dtype=complex).view(float).reshape(shape),
                      np.ascontiguousarray(delta, dtype=float), bits, ka, kb,
                      folded.view(float).reshape(shape[0], shape[2], 4))
        self.kind = 1 if bits == 1 else 2  # the kernels' ONE_BIT, MULTI_BIT

    def evaluate(self, mu: np.ndarray, sigma: np.ndarray, likelihood: str = DEFAULT_LIKELIHOOD):
        """NLL (B,) and its first and second derivatives in each real measurement, summed
        over the ramps (B, N, 2, 2). mu : (B, N, 2, 2); sigma : (B,) the noise std of the
        likelihood (the logistic's scale is ``sigma / LOGISTIC_PER_SIGMA``)."""
        if self.bits is None:
            r = mu[:, None] - self.y
            return 0.5 * np.einsum("brnpc,brnpc->b", r, r), r.sum(axis=1), np.full(mu.shape, float(self.ramps))
        if likelihood == "gaussian":
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
                a = (self.lo - mu) * inv
                c = (self.hi - mu) * inv
                flip = a + c > 0.0  # the upper tail: Phi(c) - Phi(a) = Phi(-a) - Phi(-c)
                a2, c2 = np.where(flip, -c, a), np.where(flip, -a, c)
                lh = log_ndtr(c2)
                ld = lh + np.log1p(-np.exp(log_ndtr(a2) - lh))  # log(Phi(c) - Phi(a))
                pa = np.where(np.isfinite(a), np.exp(-0.5 * a * a - _LOG_SQRT_2PI - ld), 0.0)  # phi(a) / P
                pc = np.where(np.isfinite(c), np.exp(-0.5 * c * c - _LOG_SQRT_2PI - ld), 0.0)
                dv = pc - pa
                d2v = dv * dv + np.where(np.isfinite(c), c * pc, 0.0) - np.where(np.isfinite(a), a * pa, 0.0)
                nll = -ld
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

    def wrong_rms(self, mu: np.ndarray) -> np.ndarray:
        """RMS distance (B,) of the codes that ``mu`` gets wrong to their cells, frame
        units (0 when none is wrong); unquantized frames: RMS of the residual."""
        b = mu.shape[0]
        if self.bits is None:
            return np.sqrt(np.mean((mu[:, None] - self.y).reshape(b, -1) ** 2, axis=1))
        mu = mu[:, None].astype(np.float32)
        shape = (b, self.ramps, self.n, 2, 2)
        ka, kb = self.ka.reshape(shape), self.kb.reshape(shape)  # s and s xi, or lo and hi
        v, t = self.work[:2] if hasattr(self, "work") else (np.empty(shape, dtype=np.float32) for _ in range(2))
        if self.bits == 1:
            np.multiply(ka, mu, out=v)
            v += kb
            np.minimum(v, 0.0, out=v)
        else:
            np.subtract(ka, mu, out=v)
            np.maximum(v, 0.0, out=v)
            np.subtract(mu, kb, out=t)
            np.maximum(t, 0.0, out=t)
            v += t
        miss = v.reshape(b, -1)
        wrong = np.count_nonzero(miss, axis=1)
        return np.sqrt(np.einsum("bj,bj->b", miss, miss, dtype=float) / np.maximum(wrong, 1))


# -- the range gate -----------------------------------------------------------------------
class _Gate:
    """A range gate in cml's terms: its ends in bins ``lo``, ``hi`` and ``outside`` (L,)
    bool, the points of the oversampled detection grid (``oversample`` a bin) beyond it."""

    def __init__(self, gate: RangeGate, config: RadarConfig, oversample: int):
        self.lo, self.hi = gate.bins(config)
        grid = np.arange(oversample * config.samples_per_ramp) / oversample
        eps = 1e-9
        self.outside = (grid < self.lo - eps) | (grid > self.hi + eps)
        if self.outside.all():  # a gate narrower than the grid's step: its nearest point
            self.outside[np.argmin(np.abs(grid - 0.5 * (self.lo + self.hi)))] = False
        #: the bins the detection search spans (the count test's cells)
        self.width_bins = min(float(config.samples_per_ramp), max(self.hi - self.lo, 1.0 / oversample))


# -- the model and its derivatives -------------------------------------------------------
def _atoms(nu: np.ndarray, kc: np.ndarray) -> np.ndarray:
    """``exp(-i 2 pi kc nu / N)``: ranges (..., K) in bins -> (..., K, N), from two short
    tables (index n1 j + i) rather than K N complex exponentials a frame."""
    n = kc.size
    n1 = int(np.ceil(np.sqrt(n)))
    n2 = -(-n // n1)
    ph = (-2j * np.pi / n) * nu[..., None]
    outer = np.exp(ph * (n1 * np.arange(n2)))
    inner = np.exp(ph * (np.arange(n1) + kc[0]))
    return (outer[..., :, None] * inner[..., None, :]).reshape(nu.shape + (n1 * n2,))[..., :n]


def _coefficients(amp: np.ndarray) -> np.ndarray:
    """Z (B, 4, 4K, 5K): the derivative of part c (0 real, 1 imaginary) of the model on
    antenna p in the parameters is ``R^T Z[2p + c]`` (see :meth:`_Fit.step`)."""
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


class _Fit:
    """The targets found so far, the model and the likelihood at them, and
    Levenberg--Marquardt steps on all of them at once.

    A target's parameters are [nu, Re b1, Im b1, Re b2, Im b2]: range in bins and the
    amplitudes referred to mid-sweep; on one ramp the model is
    ``mu_{n,p} = sum_t b_{t,p} w_t[n]`` with ``w_t[n] = exp(-i 2 pi kc_n nu_t / N)``."""

    def __init__(self, codes: _Codes, kc: np.ndarray, b: int, gate: _Gate | None = None,
                 engine: str = DEFAULT_ENGINE, likelihood: str = DEFAULT_LIKELIHOOD):
        self.codes, self.kc, self.gate = codes, kc, gate
        self.engine, self.likelihood = engine, likelihood
        self.set(np.zeros((b, 0)), np.zeros((b, 0, 2), dtype=complex), np.zeros((b, 0), dtype=bool))

    def set(self, nu: np.ndarray, amp: np.ndarray, live: np.ndarray) -> None:
        """Targets (B, K) in bins, amplitudes (B, K, 2); ``live`` (B, K): the targets
        that move (the others stay where they are: zero amplitude, past a frame's count)."""
        self.nu, self.amp, self.live = nu, amp, live
        if self.engine == "numpy":
            self.w = _atoms(nu, self.kc)
            self.mu = self._mu(self.w, amp)
        elif nu.shape[1] == 0:  # no target: the model is 0
            self.w, self.mu = None, np.zeros((nu.shape[0], self.kc.size, 2, 2))
        else:  # the compiled model (the atoms are only the numpy step's)
            b, n = nu.shape[0], self.kc.size
            self.w, self.mu = None, np.empty((b, n, 2, 2))
            _kernels().models(np.ascontiguousarray(nu, dtype=float), np.ascontiguousarray(amp, dtype=complex),
                              self.kc, self.mu.reshape(b, n, 4))
        self.lm = np.empty(nu.shape[0])  # damping, per frame
        self.lm.fill(1e-3)

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
        if self.engine == "numpy":
            self.nll, self.g, self.h = self.codes.evaluate(self.mu, self.sigma, self.likelihood)
            return
        b, n = self.mu.shape[:2]
        self.g, self.h = np.empty((b, n, 2, 2)), np.empty((b, n, 2, 2))
        self.nll = _kernels().evaluate(self.codes.kind, _LIK[self.likelihood], self.codes.ka, self.codes.kb,
                                     np.ascontiguousarray(self.mu).reshape(b, n, 4), self.sigma,
                                     self.g.reshape(b, n, 4), self.h.reshape(b, n, 4))

    def evaluate_and_run(self, sigma: np.ndarray, levels: np.ndarray, amp_cap: np.ndarray) -> None:
        """:meth:`evaluate` at ``sigma`` (B,) then :meth:`run` (``levels[:, 0]`` equal to
        ``sigma``); compiled, the evaluation is the refinement kernel's first (the same
        numbers, one call fewer)."""
        if self.engine == "numpy" or self.nu.shape[1] == 0 or levels.shape[1] == 0 or \
                not np.array_equal(levels[:, 0], sigma):
            self.evaluate(sigma)
            self.run(levels, amp_cap)
            return
        b, n = self.mu.shape[:2]
        self.g, self.h = np.empty((b, n, 2, 2)), np.empty((b, n, 2, 2))
        self.nll, self.sigma = np.zeros(b), np.full(b, np.nan)  # NaN: no level evaluated yet
        self.run(levels, amp_cap)

    def run(self, levels: np.ndarray, amp_cap: np.ndarray, adapt: bool = False) -> None:
        """One step a level: at noise std ``levels[:, j]`` (B, S) (``adapt``: not below
        the noise the model leaves, ``wrong_rms / WRONG_RMS_PER_SIGMA``), the likelihood
        evaluated again where the level changed, then :meth:`step`."""
        b = self.nu.shape[0]
        if self.engine == "numpy" or self.nu.shape[1] == 0:
            for j in range(levels.shape[1]):
                sigma = levels[:, j]
                if adapt:
                    sigma = np.maximum(sigma, self.codes.wrong_rms(self.mu) / WRONG_RMS_PER_SIGMA)
                if not np.array_equal(sigma, self.sigma):
                    self.evaluate(sigma)
                self.step(amp_cap)
            return
        n = self.kc.size
        nu, amp = np.ascontiguousarray(self.nu, dtype=float), np.ascontiguousarray(self.amp, dtype=complex)
        mu, g, h = (np.ascontiguousarray(v, dtype=float).reshape(b, n, 4) for v in (self.mu, self.g, self.h))
        nll, sigma, lm = self.nll.astype(float), self.sigma.astype(float), self.lm.astype(float)
        gate = self.gate
        _kernels().refine(self.codes.kind, _LIK[self.likelihood], self.codes.ka, self.codes.kb, self.kc, nu, amp,
                        np.ascontiguousarray(self.live), lm, np.ascontiguousarray(levels, dtype=float), adapt,
                        WRONG_RMS_PER_SIGMA, np.ascontiguousarray(amp_cap, dtype=float),
                        0.0 if gate is None else float(gate.lo), 0.0 if gate is None else float(gate.hi),
                        gate is not None, MAX_RANGE_STEP_BINS, mu, g, h, nll, sigma)
        self.nu, self.amp, self.lm, self.nll, self.sigma = nu, amp, lm, nll, sigma
        self.mu, self.g, self.h = (v.reshape(b, n, 2, 2) for v in (mu, g, h))
        self.w = None  # stale: only the numpy step reads it


    def step(self, amp_cap: np.ndarray) -> None:
        """One Levenberg--Marquardt step of every frame at the current scale; a frame
        keeps its step only if its likelihood improves. amp_cap : (B,) largest amplitude
        change of a target."""
        b, k = self.nu.shape
        if k == 0:  # no target found in the whole block (K auto)
            return
        n = self.kc.size
        # the Jacobian of part c of mu_p is R^T Z[2p + c]: R (4K, N) holds the real and the
        # imaginary parts of the atoms w_t and of dw_t / dnu; Z how each parameter mixes them
        dw = self.w * ((-2j * np.pi / n) * self.kc)
        r = np.concatenate([self.w.real, dw.real, self.w.imag, dw.imag], axis=1)  # (B, 4K, N)
        r32 = r.astype(np.float32)
        hw = np.ascontiguousarray(self.h.reshape(b, n, 4).transpose(0, 2, 1), dtype=np.float32)
        gram = np.matmul(r32[:, None] * hw[:, :, None], np.ascontiguousarray(r32.transpose(0, 2, 1))[:, None])
        zc = _coefficients(self.amp)
        hess = np.matmul(zc.transpose(0, 1, 3, 2), np.matmul(gram.astype(float), zc)).sum(axis=1)
        proj = np.matmul(r, self.g.reshape(b, n, 4)).transpose(0, 2, 1)[..., None]  # (B, 4, 4K, 1)
        grad = np.matmul(zc.transpose(0, 1, 3, 2), proj).sum(axis=1)[..., 0]
        diag = np.diagonal(hess, axis1=1, axis2=2)
        damp = self.lm[:, None] * diag + 1e-9 * diag.max(axis=1, keepdims=True) + 1e-300
        step = -np.linalg.solve(hess + damp[:, :, None] * np.eye(5 * k), grad[..., None])[..., 0]
        step = step.reshape(b, k, 5)
        step[~self.live] = 0.0
        step[..., 0] = np.clip(step[..., 0], -MAX_RANGE_STEP_BINS, MAX_RANGE_STEP_BINS)
        norm = np.linalg.norm(step[..., 1:], axis=2)
        step[..., 1:] *= np.minimum(1.0, amp_cap[:, None] / np.maximum(norm, 1e-300))[..., None]
        nu = self.nu + step[..., 0]
        if self.gate is not None:  # a target may not leave the gate
            nu = np.clip(nu, self.gate.lo, self.gate.hi)
        amp = self.amp + (step[..., 1::2] + 1j * step[..., 2::2])
        w = _atoms(nu, self.kc)
        mu = self._mu(w, amp)
        nll, g, h = self.codes.evaluate(mu, self.sigma, self.likelihood)
        ok = nll <= self.nll
        self.lm = np.clip(np.where(ok, self.lm / 3.0, self.lm * 8.0), 1e-9, 1e9)
        bad = np.flatnonzero(~ok)  # frames that keep their parameters (few)
        for new, old in ((nu, self.nu), (amp, self.amp), (w, self.w), (mu, self.mu), (g, self.g), (h, self.h),
                         (nll, self.nll)):
            new[bad] = old[bad]
        self.nu, self.amp, self.w, self.mu, self.g, self.h, self.nll = nu, amp, w, mu, g, h, nll
