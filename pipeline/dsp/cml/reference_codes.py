"""The codes of cml's numpy reference (:mod:`pipeline.dsp.cml.reference`): a block's
measurements as real arrays and the negative log-likelihood of a model of each ramp, with the
exact logistic (numpy's ``exp`` and ``log1p``) and the exact Gaussian (scipy's ``log_ndtr``),
in float32 work arrays (quantized) as the kernels' (:mod:`pipeline.dsp.cml.kernels.likelihood`).

Shapes: a block of B frames of R ramps of N samples; Rm the model's ramps (R with a phase step
between ramps, 1 for the static model); the real parts of a sample as (antenna, re/im)."""

from __future__ import annotations

import numpy as np

from pipeline.dsp.cml.checks import Frames
from pipeline.dsp.cml.options import LOGISTIC_PER_SIGMA
from pipeline.dsp.cml.schedule import residual_rms, wrong_codes_rms

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)


class Codes:
    """A block's measurements as real arrays (B, R, N, 2 antennas, 2 re/im) and the negative
    log-likelihood (NLL) of a model ``mu`` (B, Rm, N, 2, 2) of each ramp (Rm = 1: repeated on
    every ramp), in float32 work arrays (quantized) as the kernels'."""

    def __init__(self, frames: Frames, n: int, likelihood: str, motion: bool):
        z, bits, delta = frames.z, frames.bits, frames.delta
        b, m = z.shape[:2]
        self.bits, self.ramps, self.n, self.likelihood = bits, m // n, n, likelihood
        self.rm = self.ramps if motion else 1
        shape = (b, self.ramps, n, 2, 2)
        q = None
        if z.ndim == 4:  # codes: the levels q in [-2^(b-1), 2^(b-1)), Z = delta (q + 1/2)
            q = z.reshape(shape).astype(np.float64) - (1 << (bits - 1))
            z = (delta[:, None, None, None, None] * (q + 0.5)).view(complex).reshape(b, m, 2)
        zr = np.ascontiguousarray(z, dtype=complex).view(float).reshape(shape)
        data = (z if bits is None else z - frames.xi).reshape(b, self.ramps, n, 2)  # what detection back-projects
        self.data = data if self.rm > 1 else data.sum(axis=1, keepdims=True)  # (B, Rm, N, 2); static: summed
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
            self.s, self.so, self.half_s = s.astype(np.float32), (s * xr).astype(np.float32), self._ramps_sum(0.5 * s)
            self.ka, self.kb = self.s, self.so
            return
        self.lo = (np.where(q <= -half, -np.inf, q * d) - xr).astype(np.float32)  # lambda's cell: [lo, hi)
        self.hi = (np.where(q >= half - 1, np.inf, (q + 1) * d) - xr).astype(np.float32)
        self.ka, self.kb = self.lo, self.hi

    def _ramps_sum(self, x: np.ndarray, dtype=None) -> np.ndarray:
        """``x`` (B, R, ...) per model ramp: summed over the ramps (Rm = 1, keeping the axis)
        or as it is."""
        return x.sum(axis=1, keepdims=True, dtype=dtype) if self.rm == 1 else x.astype(dtype or x.dtype)

    def evaluate(self, mu: np.ndarray, sigma: np.ndarray):
        """NLL (B,) and its first and second derivatives in each real measurement of each model
        ramp (B, Rm, N, 2, 2) (Rm = 1: summed over the ramps). mu : (B, Rm, N, 2, 2); sigma :
        (B,) the noise std of the likelihood (the logistic's scale is ``sigma / LOGISTIC_PER_SIGMA``)."""
        if self.bits is None:
            r = mu - self.y
            return (0.5 * np.einsum("brnpc,brnpc->b", r, r), self._ramps_sum(r),
                    np.full(mu.shape, float(self.ramps // self.rm)))
        if self.likelihood == "gaussian":
            return self._gaussian(mu, sigma)
        scale = sigma / LOGISTIC_PER_SIGMA
        mu = mu.astype(np.float32)
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
        inv = inv.astype(float)
        return nll, g * inv, h * (inv * inv)

    def _gaussian(self, mu: np.ndarray, sigma: np.ndarray):
        """:meth:`evaluate` with the exact Gaussian likelihood (float64, scipy's log_ndtr)."""
        from scipy.special import log_ndtr  # here: importing scipy costs the others' start-up

        b = mu.shape[0]
        inv = (1.0 / sigma)[:, None, None, None, None]
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            if self.bits == 1:
                s = self.s.astype(float)
                v = (s * mu + self.so) * inv  # the margin in units of sigma
                lp = log_ndtr(v)
                r = np.exp(-0.5 * v * v - _LOG_SQRT_2PI - lp)  # phi(v) / Phi(v)
                nll, dv, d2v = -lp, -r * s, r * (v + r)
            else:
                nll, dv, d2v = _gauss_cells((self.lo - mu) * inv, (self.hi - mu) * inv, log_ndtr)
        return nll.reshape(b, -1).sum(axis=1), self._ramps_sum(dv) * inv, self._ramps_sum(d2v) * (inv * inv)

    def _softplus(self, u, sign):
        """Sum per frame of ``-log F(u)`` (B,), and its first and second derivatives in
        lambda times T and T^2 of each model ramp (B, Rm, N, 2, 2), where
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
        h = self._ramps_sum(t, dtype=float)
        np.subtract(0.5, e, out=e)
        np.copysign(e, u, out=e)  # F(-u) = 1/2 - copysign(1/2 - q, u)
        if np.isscalar(sign):  # d(-log F(u)) / d lambda = -sign F(-u) / T
            g = sign * (self._ramps_sum(e, dtype=float) - 0.5 * (self.ramps // self.rm))
        else:
            e *= sign
            g = self._ramps_sum(e, dtype=float) - self.half_s
        return nll, g, h

    def noise_rms(self, mu: np.ndarray) -> np.ndarray:
        """RMS distance (B,) of the codes that ``mu`` (B, Rm, N, 2, 2) gets wrong to their
        cells (0 when none is wrong); unquantized frames: RMS of the residual."""
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
