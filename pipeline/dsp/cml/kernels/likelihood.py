"""Compiled (numba) likelihood of the codes: the negative log-likelihood (NLL) of one frame's
codes at a model and its first and second derivatives in each real measurement of each model
ramp (the static model's one ramp: summed over the ramps; layouts and kinds:
:mod:`pipeline.dsp.cml.kernels.layout`).

The logistic likelihood, the common case, runs as flat float32 loops without branches or
calls that LLVM vectorizes (AVX2: 8 codes an instruction; ``error_model="numpy"`` keeps
divisions free of Python's zero checks, which would stop it), with ``exp`` and ``log1p``
as polynomials without divisions (:func:`softplus`; 3e-7 of the NLL, 1e-6 of its
derivatives against the numpy reference's exact functions, :mod:`pipeline.dsp.cml.reference`).
The Gaussian likelihood is scalar float64.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from pipeline.dsp.cml.kernels.layout import JIT

LSQ, ONE_BIT, MULTI_BIT = 0, 1, 2
LOGISTIC, GAUSSIAN = 0, 1
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
_SQRT1_2 = math.sqrt(0.5)


#: fastmath flags of the vectorized likelihood loops: reassociation (SIMD sums), contraction
#: (FMA), reciprocal and approximate functions; not nnan/ninf (a multi-bit cell's open end is
#: an infinite bound, which must stay exact)
_SIMD = {"reassoc", "contract", "arcp", "nsz", "afn"}
#: the margin |u| beyond which the logistic's terms are taken at their limits (exp(-40) ~ 4e-18)
SOFTPLUS_REACH = 40.0
_F32 = np.float32


#: ``exp(-x)`` on [0, SOFTPLUS_REACH / 32] = [0, 1.25]: a near-minimax polynomial of degree 7
#: (float32 coefficients, relative error 8e-8), low degree first
_EXP_C = tuple(_F32(c) for c in (1.0, -0.999999702, 0.499994695, -0.166632831, 0.0415616520, -0.00815444347,
                                 0.00121561589, -0.000105531581))
#: ``log(1 + e) / e`` on [0, 1]: a near-minimax polynomial of degree 9 (relative error 1.6e-8)
_LOG1P_C = tuple(_F32(c) for c in (1.0, -0.499999225, 0.333302051, -0.249553785, 0.196789086, -0.153080612,
                                   0.106008776, -0.0568829514, 0.0197911020, -0.00322727091))


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy", inline="always")
def exp_neg(a):
    """``exp(-a)`` for float32 ``a`` in [0, SOFTPLUS_REACH], branch-free (vectorizes without
    SVML): ``exp(-a / 32)`` by :data:`_EXP_C` (Horner's rule: fewest operations), squared 5
    times (relative error < 1.1e-5 over the range, float32 rounding doubled by each squaring;
    2e-5 with the Taylor polynomial of ``exp(-a / 128)`` squared 7 times)."""
    c0, c1, c2, c3, c4, c5, c6, c7 = _EXP_C
    x = a * _F32(1.0 / 32.0)
    e = c0 + x * (c1 + x * (c2 + x * (c3 + x * (c4 + x * (c5 + x * (c6 + x * c7))))))
    e = e * e
    e = e * e
    e = e * e
    e = e * e
    return e * e


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy", inline="always")
def log1p_small(e):
    """``log(1 + e)`` for float32 e in [0, 1]: ``e`` times :data:`_LOG1P_C` by Horner's rule,
    no division (relative error < 1.2e-7). Horner's, not Estrin's: no power of e below
    float32's normal range (exp(-40)^4 would be, and subnormals are slow)."""
    d0, d1, d2, d3, d4, d5, d6, d7, d8, d9 = _LOG1P_C
    return e * (d0 + e * (d1 + e * (d2 + e * (d3 + e * (d4 + e * (d5 + e * (d6 + e * (d7 + e * (
        d8 + e * d9)))))))))


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy", inline="always")
def softplus(u):
    """The logistic F's ``-log F(u)``, ``F(-u)`` and ``F(u) F(-u)`` of a float32 margin u
    (any value, infinite too), branch-free: ``-log F(u) = max(-u, 0) + log(1 + exp(-|u|))``."""
    e = exp_neg(min(abs(u), _F32(SOFTPLUS_REACH)))
    q = e / (_F32(1.0) + e)  # F(-|u|)
    fneg = q if u > _F32(0.0) else _F32(1.0) - q
    return max(-u, _F32(0.0)) + log1p_small(e), fneg, q * (_F32(1.0) - q)


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy", inline="always")
def softplus_nll(u):
    """The first value of :func:`softplus` alone (the same arithmetic)."""
    return max(-u, _F32(0.0)) + log1p_small(exp_neg(min(abs(u), _F32(SOFTPLUS_REACH))))


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy")
def _one_bit_logistic(s, so, mu32, inv, g, h, ga, ha) -> float:
    """The 1-bit logistic NLL of the codes' signs ``s`` and ``s xi`` (R, 4N) float32 at the
    model ``mu32`` (Rm, 4N) float32 (Rm = 1: every ramp's) and inverse logistic scale
    ``inv``; writes its derivatives in lambda to ``g``, ``h`` (Rm 4N,) float64 (``ga``, ``ha``
    (Rm, 4N) float32: work). One flat loop a ramp the compiler vectorizes (8 codes an
    instruction)."""
    ramps, m4 = s.shape
    rm = mu32.shape[0]
    inv32 = _F32(inv)
    ga[:] = 0.0
    ha[:] = 0.0
    total = 0.0
    for r in range(ramps):
        sr = s[r]
        sor = so[r]
        q = r if rm > 1 else 0
        mr = mu32[q]
        gr = ga[q]
        hr = ha[q]
        part = _F32(0.0)  # float32 sums (a float64 one stops the vectorizer), one a ramp
        for i in range(m4):
            v, fneg, ff = softplus((sr[i] * mr[i] + sor[i]) * inv32)  # the margin: > 0 for a right code
            part += v
            gr[i] -= sr[i] * fneg
            hr[i] += ff
        total += part
    _store(g, h, ga.reshape(g.shape[0]), ha.reshape(h.shape[0]), inv)
    return total


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy")
def _one_bit_logistic_nll(s, so, mu32, inv) -> float:
    """:func:`_one_bit_logistic`'s NLL alone."""
    ramps, m4 = s.shape
    rm = mu32.shape[0]
    inv32 = _F32(inv)
    total = 0.0
    for r in range(ramps):
        sr = s[r]
        sor = so[r]
        mr = mu32[r if rm > 1 else 0]
        part = _F32(0.0)
        for i in range(m4):
            part += softplus_nll((sr[i] * mr[i] + sor[i]) * inv32)
        total += part
    return total


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy")
def _multi_bit_logistic(lo, hi, mu32, inv, g, h, ga, ha) -> float:
    """The b-bit logistic NLL ``-log F((mu - lo) / T) - log F((hi - mu) / T)`` (+ const) of
    the cells ``[lo, hi)`` (R, 4N) float32 (open ends infinite) at ``mu32`` (Rm, 4N),
    ``inv = 1 / T``; writes its derivatives to ``g``, ``h``, as :func:`_one_bit_logistic`."""
    ramps, m4 = lo.shape
    rm = mu32.shape[0]
    inv32 = _F32(inv)
    ga[:] = 0.0
    ha[:] = 0.0
    total = 0.0
    for r in range(ramps):
        lr = lo[r]
        hr = hi[r]
        q = r if rm > 1 else 0
        mr = mu32[q]
        gr = ga[q]
        har = ha[q]
        part = _F32(0.0)
        for i in range(m4):
            v1, f1, h1 = softplus((mr[i] - lr[i]) * inv32)
            v2, f2, h2 = softplus((hr[i] - mr[i]) * inv32)
            part += v1 + v2
            gr[i] += f2 - f1
            har[i] += h1 + h2
        total += part
    _store(g, h, ga.reshape(g.shape[0]), ha.reshape(h.shape[0]), inv)
    return total


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy")
def _store(g, h, ga, ha, inv):
    """The derivatives in u summed in float32, ``ga``, ``ha``, as derivatives in lambda."""
    inv2 = inv * inv
    for i in range(g.shape[0]):
        g[i] = ga[i] * inv
        h[i] = ha[i] * inv2


@njit(cache=True, nogil=True, fastmath=False)
def log_ndtr(v: float) -> float:
    """``log Phi(v)``, stable for any v (asymptotic series below -20)."""
    if v > 6.0:
        return -0.5 * math.erfc(v * _SQRT1_2)  # log(1 - t) ~ -t, t < 1e-9
    if v > -20.0:
        return math.log(0.5 * math.erfc(-v * _SQRT1_2))
    x2 = 1.0 / (v * v)
    return -0.5 * v * v - math.log(-v) - _LOG_SQRT_2PI + math.log1p(x2 * (-1.0 + x2 * (3.0 - 15.0 * x2)))


@njit(**JIT)
def _gauss_tail(v: float):
    """``-log Phi(v)``, its derivative in v and the second derivative: ``-r`` and
    ``r (v + r)`` with ``r = phi(v) / Phi(v)``."""
    lp = log_ndtr(v)
    r = math.exp(-0.5 * v * v - _LOG_SQRT_2PI - lp)
    return -lp, -r, r * (v + r)


@njit(**JIT)
def _log_diff_ndtr(lo: float, hi: float) -> float:
    """``log(Phi(hi) - Phi(lo))`` for lo < hi (either may be infinite), stable in the tails."""
    if lo + hi > 0.0:  # the upper tail: Phi(hi) - Phi(lo) = Phi(-lo) - Phi(-hi)
        lo, hi = -hi, -lo
    lh = log_ndtr(hi)
    if lo == -math.inf:
        return lh
    return lh + math.log1p(-math.exp(log_ndtr(lo) - lh))


@njit(**JIT)
def _gauss_cell(a: float, c: float):
    """``-log(Phi(c) - Phi(a))`` with ``a = (lo - lambda) / s``, ``c = (hi - lambda) / s``,
    and its first and second derivatives in ``lambda`` times s and s^2."""
    ld = _log_diff_ndtr(a, c)
    pa = 0.0 if a == -math.inf else math.exp(-0.5 * a * a - _LOG_SQRT_2PI - ld)  # phi(a) / P
    pc = 0.0 if c == math.inf else math.exp(-0.5 * c * c - _LOG_SQRT_2PI - ld)
    g = pc - pa
    apa = 0.0 if a == -math.inf else a * pa
    cpc = 0.0 if c == math.inf else c * pc
    return -ld, g, g * g + cpc - apa


@njit(**JIT)
def evaluate(codes, mu, sigma, g, h):
    """NLL (B,) of the models ``mu`` (B, Rm, N, 4) at noise std ``sigma`` (B,) of ``codes`` (a
    :data:`~pipeline.dsp.cml.kernels.layout.Codes`; the logistic's scale is ``sigma / 1.702``,
    least squares ignores it); writes ``g``, ``h`` (B, Rm, N, 4)."""
    nb = mu.shape[0]
    nll = np.zeros(nb)
    work = np.empty((3, mu.shape[1], 4 * mu.shape[2]), dtype=np.float32)
    for f in range(nb):
        nll[f] = evaluate_frame(codes.kind, codes.lik, codes.a[f], codes.b[f], mu[f], sigma[f], g[f], h[f], work)
    return nll


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _to_float32(mu, out):
    """``out`` (Rm, 4N) float32 = ``mu`` (Rm, N, 4) float64 (rounded to nearest)."""
    muf = mu.reshape(out.size)
    outf = out.reshape(out.size)
    for i in range(out.size):
        outf[i] = muf[i]
    return out


@njit(**JIT)
def evaluate_frame(kind, lik, a, b, mu, sigma, g, h, work) -> float:
    """The NLL of one frame's codes ``a``, ``b`` (R, N, 4) at the model ``mu`` (Rm, N, 4)
    (Rm = 1: every ramp's) and noise std ``sigma``; writes its derivatives to ``g``, ``h``
    (Rm, N, 4). ``work`` (3, Rm, 4N) float32: the logistic's work arrays (the model in
    float32, its float32 sums)."""
    ramps, n = a.shape[0], a.shape[1]
    rm = mu.shape[0]
    if lik == LOGISTIC and kind != LSQ:  # vectorized, float32 (as the numpy reference)
        m4 = n * 4
        mu32 = _to_float32(mu, work[0])
        gf, hf = g.reshape(rm * m4), h.reshape(rm * m4)
        if kind == ONE_BIT:
            return _one_bit_logistic(a.reshape(ramps, m4), b.reshape(ramps, m4), mu32, 1.702 / sigma, gf, hf,
                                     work[1], work[2])
        return _multi_bit_logistic(a.reshape(ramps, m4), b.reshape(ramps, m4), mu32, 1.702 / sigma, gf, hf,
                                   work[1], work[2])
    g[:] = 0.0
    h[:] = 0.0
    total = 0.0
    if kind == LSQ:
        for r in range(ramps):
            q = r if rm > 1 else 0
            for i in range(n):
                for j in range(4):
                    d = mu[q, i, j] - a[r, i, j]
                    total += 0.5 * d * d
                    g[q, i, j] += d
                    h[q, i, j] += 1.0
        return total
    inv = 1.0 / sigma
    inv2 = inv * inv
    for r in range(ramps):
        q = r if rm > 1 else 0
        for i in range(n):
            for j in range(4):
                m = mu[q, i, j]
                if kind == ONE_BIT:
                    s = float(a[r, i, j])
                    u = (s * m + float(b[r, i, j])) * inv  # the margin: > 0 for a code the model gets right
                    if u > 38.0:
                        continue
                    v, dv, d2v = _gauss_tail(u)
                    total += v
                    g[q, i, j] += s * dv * inv
                    h[q, i, j] += d2v * inv2
                else:
                    v, dv, d2v = _gauss_cell((float(a[r, i, j]) - m) * inv, (float(b[r, i, j]) - m) * inv)
                    total += v
                    g[q, i, j] += dv * inv
                    h[q, i, j] += d2v * inv2
    return total


@njit(**JIT)
def nll_frame(a, b, mu, sigma, work) -> float:
    """The NLL of :func:`evaluate_frame` (the same arithmetic) without its derivatives,
    for 1-bit codes and the logistic likelihood (``work`` as there)."""
    ramps, m4 = a.shape[0], a.shape[1] * 4
    return _one_bit_logistic_nll(a.reshape(ramps, m4), b.reshape(ramps, m4), _to_float32(mu, work[0]),
                                 1.702 / sigma)


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy")
def wrong_rms(kind, a, b, mu) -> float:
    """RMS distance of the codes ``mu`` (Rm, N, 4) gets wrong to their cells (0 when none is)."""
    ramps, m4 = a.shape[0], a.shape[1] * 4
    rm = mu.shape[0]
    af = a.reshape(ramps, m4)
    bf = b.reshape(ramps, m4)
    mf = mu.reshape(rm, m4)
    acc = 0.0
    wrong = 0
    for r in range(ramps):
        ar = af[r]
        br = bf[r]
        muf = mf[r if rm > 1 else 0]
        if kind == ONE_BIT:
            for i in range(m4):
                v = min(float(ar[i]) * muf[i] + float(br[i]), 0.0)
                acc += v * v
                wrong += v != 0.0
        else:
            for i in range(m4):
                v = max(float(ar[i]) - muf[i], 0.0) + max(muf[i] - float(br[i]), 0.0)
                acc += v * v
                wrong += v != 0.0
    return math.sqrt(acc / max(wrong, 1))
