"""Compiled (numba) kernels of :mod:`pipeline.dsp.cml`: the likelihood of the codes and the
Levenberg--Marquardt refinement, one frame at a time (so a frame costs the same in a batch
of 1 or of 64). The pure-numpy code in :mod:`pipeline.dsp.cml` is the reference these kernels
are tested against (tests/test_cml_kernels.py).

Layouts (one block of B frames, R ramps of N samples, K targets; the 4 real parts of a
sample are ``2 p + c``, antenna p, c = 0 real, 1 imaginary):

* ``a``, ``b``: (B, R, N, 4) the codes' arrays: least squares ``y`` (and ``b`` unused);
  1 bit ``s`` (the code's sign) and ``s xi``; b bits the cell ``[lo, hi)`` of lambda;
* ``mu``, ``g``, ``h``: (B, N, 4) the model on one ramp, and the first and second
  derivatives of the negative log-likelihood (NLL) in each real part, summed over ramps;
* ``nu`` (B, K) ranges in bins, ``amp`` (B, K, 2) complex amplitudes referred to
  mid-sweep, ``live`` (B, K) bool, ``lm`` (B,) damping.

Kinds: ``LSQ`` least squares, ``ONE_BIT``, ``MULTI_BIT``; likelihoods: ``LOGISTIC`` (the
scaled logistic of the module docstring of :mod:`pipeline.dsp.cml`) or ``GAUSSIAN`` (the
exact ``Phi((hi - lambda) / s) - Phi((lo - lambda) / s)``).

The logistic likelihood, the common case, runs as flat float32 loops without branches or
calls that LLVM vectorizes (AVX2: 8 codes an instruction; ``error_model="numpy"`` keeps
divisions free of Python's zero checks, which would stop it), with ``exp`` and ``log1p``
as polynomials (:func:`_softplus`; 1e-7 of the NLL, 1e-6 of its derivatives against the
numpy reference's exact functions). The Gaussian likelihood is scalar float64.

Compiled on first use and cached on disk (``cache=True``: ``__pycache__`` beside this
file, or ``NUMBA_CACHE_DIR``), so a later process loads them instead of compiling.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

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


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy", inline="always")
def _exp_neg(a):
    """``exp(-a)`` for float32 ``a`` in [0, SOFTPLUS_REACH], branch-free (vectorizes without
    SVML): ``exp(-a / 128)`` by its degree-6 Taylor polynomial, squared 7 times (relative
    error ~1e-5 from float32 rounding, which the squarings double each time)."""
    x = a * _F32(-1.0 / 128.0)
    e = _F32(1.0) + x * (_F32(1.0) + x * (_F32(0.5) + x * (_F32(1.0 / 6.0) + x * (
        _F32(1.0 / 24.0) + x * (_F32(1.0 / 120.0) + x * _F32(1.0 / 720.0))))))
    e = e * e
    e = e * e
    e = e * e
    e = e * e
    e = e * e
    e = e * e
    return e * e


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy", inline="always")
def _log1p_small(e):
    """``log(1 + e)`` for float32 e in [0, 1]: ``2 atanh(t)``, ``t = e / (2 + e)`` <= 1/3, by
    its series to t^13 (relative error < 1e-7)."""
    t = e / (_F32(2.0) + e)
    t2 = t * t
    return _F32(2.0) * t * (_F32(1.0) + t2 * (_F32(1.0 / 3.0) + t2 * (_F32(0.2) + t2 * (_F32(1.0 / 7.0) + t2 * (
        _F32(1.0 / 9.0) + t2 * (_F32(1.0 / 11.0) + t2 * _F32(1.0 / 13.0)))))))


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy", inline="always")
def _softplus(u):
    """The logistic F's ``-log F(u)``, ``F(-u)`` and ``F(u) F(-u)`` of a float32 margin u
    (any value, infinite too), branch-free: ``-log F(u) = max(-u, 0) + log(1 + exp(-|u|))``."""
    e = _exp_neg(min(abs(u), _F32(SOFTPLUS_REACH)))
    q = e / (_F32(1.0) + e)  # F(-|u|)
    fneg = q if u > _F32(0.0) else _F32(1.0) - q
    return max(-u, _F32(0.0)) + _log1p_small(e), fneg, q * (_F32(1.0) - q)


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy", inline="always")
def _softplus_nll(u):
    """The first value of :func:`_softplus` alone (the same arithmetic)."""
    return max(-u, _F32(0.0)) + _log1p_small(_exp_neg(min(abs(u), _F32(SOFTPLUS_REACH))))


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy")
def _one_bit_logistic(s, so, mu32, inv, g, h) -> float:
    """The 1-bit logistic NLL of the codes' signs ``s`` and ``s xi`` (R, 4N) float32 at the
    model ``mu32`` (4N,) float32 and inverse logistic scale ``inv``; adds its derivatives
    in lambda (times 1/inv and 1/inv^2) to ``g``, ``h`` (4N,) float64. One flat loop the
    compiler vectorizes (8 codes an instruction)."""
    ramps, m4 = s.shape
    inv32 = _F32(inv)
    ga, ha = np.zeros(m4, dtype=np.float32), np.zeros(m4, dtype=np.float32)
    total = 0.0
    for r in range(ramps):
        sr = s[r]
        sor = so[r]
        part = _F32(0.0)  # float32 sums (a float64 one stops the vectorizer), one a ramp
        for i in range(m4):
            v, fneg, ff = _softplus((sr[i] * mu32[i] + sor[i]) * inv32)  # the margin: > 0 for a right code
            part += v
            ga[i] -= sr[i] * fneg
            ha[i] += ff
        total += part
    _add(g, h, ga, ha)
    return total


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy")
def _one_bit_logistic_nll(s, so, mu32, inv) -> float:
    """:func:`_one_bit_logistic`'s NLL alone."""
    ramps, m4 = s.shape
    inv32 = _F32(inv)
    total = 0.0
    for r in range(ramps):
        sr = s[r]
        sor = so[r]
        part = _F32(0.0)
        for i in range(m4):
            part += _softplus_nll((sr[i] * mu32[i] + sor[i]) * inv32)
        total += part
    return total


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy")
def _multi_bit_logistic(lo, hi, mu32, inv, g, h) -> float:
    """The b-bit logistic NLL ``-log F((mu - lo) / T) - log F((hi - mu) / T)`` (+ const) of
    the cells ``[lo, hi)`` (R, 4N) float32 (open ends infinite) at ``mu32``, ``inv = 1 / T``;
    adds its derivatives (times T and T^2) to ``g``, ``h``, as :func:`_one_bit_logistic`."""
    ramps, m4 = lo.shape
    inv32 = _F32(inv)
    ga, ha = np.zeros(m4, dtype=np.float32), np.zeros(m4, dtype=np.float32)
    total = 0.0
    for r in range(ramps):
        lr = lo[r]
        hr = hi[r]
        part = _F32(0.0)
        for i in range(m4):
            v1, f1, h1 = _softplus((mu32[i] - lr[i]) * inv32)
            v2, f2, h2 = _softplus((hr[i] - mu32[i]) * inv32)
            part += v1 + v2
            ga[i] += f2 - f1
            ha[i] += h1 + h2
        total += part
    _add(g, h, ga, ha)
    return total


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy")
def _add(g, h, ga, ha):
    for i in range(g.shape[0]):
        g[i] += ga[i]
        h[i] += ha[i]


@njit(cache=True, nogil=True, fastmath=False)
def log_ndtr(v: float) -> float:
    """``log Phi(v)``, stable for any v (asymptotic series below -20)."""
    if v > 6.0:
        return -0.5 * math.erfc(v * _SQRT1_2)  # log(1 - t) ~ -t, t < 1e-9
    if v > -20.0:
        return math.log(0.5 * math.erfc(-v * _SQRT1_2))
    x2 = 1.0 / (v * v)
    return -0.5 * v * v - math.log(-v) - _LOG_SQRT_2PI + math.log1p(x2 * (-1.0 + x2 * (3.0 - 15.0 * x2)))


@njit(cache=True, nogil=True)
def _gauss_tail(v: float):
    """``-log Phi(v)``, its derivative in v and the second derivative: ``-r`` and
    ``r (v + r)`` with ``r = phi(v) / Phi(v)``."""
    lp = log_ndtr(v)
    r = math.exp(-0.5 * v * v - _LOG_SQRT_2PI - lp)
    return -lp, -r, r * (v + r)


@njit(cache=True, nogil=True)
def _log_diff_ndtr(lo: float, hi: float) -> float:
    """``log(Phi(hi) - Phi(lo))`` for lo < hi (either may be infinite), stable in the tails."""
    if lo + hi > 0.0:  # the upper tail: Phi(hi) - Phi(lo) = Phi(-lo) - Phi(-hi)
        lo, hi = -hi, -lo
    lh = log_ndtr(hi)
    if lo == -math.inf:
        return lh
    return lh + math.log1p(-math.exp(log_ndtr(lo) - lh))


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
def evaluate(kind: int, lik: int, a, b, mu, sigma, g, h):
    """NLL (B,) of the models ``mu`` (B, N, 4) at noise std ``sigma`` (B,) (the
    logistic's scale is ``sigma / 1.702``; least squares ignores it); writes ``g``, ``h``."""
    nb = mu.shape[0]
    nll = np.zeros(nb)
    for f in range(nb):
        nll[f] = _evaluate_frame(kind, lik, a[f], b[f], mu[f], sigma[f], g[f], h[f])
    return nll


@njit(cache=True, nogil=True)
def _evaluate_frame(kind, lik, a, b, mu, sigma, g, h) -> float:
    ramps, n = a.shape[0], a.shape[1]
    g[:] = 0.0
    h[:] = 0.0
    total = 0.0
    if kind == LSQ:
        for r in range(ramps):
            for i in range(n):
                for j in range(4):
                    d = mu[i, j] - a[r, i, j]
                    total += 0.5 * d * d
                    g[i, j] += d
                    h[i, j] += 1.0
        return total
    if lik == LOGISTIC:  # vectorized, float32 (as the numpy reference), derivatives scaled at the end
        inv = 1.702 / sigma
        m4 = n * 4
        mu32 = _as_float32(mu.reshape(m4))
        gf, hf = g.reshape(m4), h.reshape(m4)
        if kind == ONE_BIT:
            total = _one_bit_logistic(a.reshape(ramps, m4), b.reshape(ramps, m4), mu32, inv, gf, hf)
        else:
            total = _multi_bit_logistic(a.reshape(ramps, m4), b.reshape(ramps, m4), mu32, inv, gf, hf)
        _scale(gf, hf, inv)
        return total
    inv = 1.0 / sigma
    inv2 = inv * inv
    for r in range(ramps):
        for i in range(n):
            for j in range(4):
                m = mu[i, j]
                if kind == ONE_BIT:
                    s = float(a[r, i, j])
                    u = (s * m + float(b[r, i, j])) * inv  # the margin: > 0 for a code the model gets right
                    if u > 38.0:
                        continue
                    v, dv, d2v = _gauss_tail(u)
                    total += v
                    g[i, j] += s * dv * inv
                    h[i, j] += d2v * inv2
                else:
                    v, dv, d2v = _gauss_cell((float(a[r, i, j]) - m) * inv, (float(b[r, i, j]) - m) * inv)
                    total += v
                    g[i, j] += dv * inv
                    h[i, j] += d2v * inv2
    return total


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy")
def _as_float32(x):
    out = np.empty(x.shape[0], dtype=np.float32)
    for i in range(x.shape[0]):
        out[i] = x[i]
    return out


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy")
def _scale(g, h, inv):
    inv2 = inv * inv
    for i in range(g.shape[0]):
        g[i] *= inv
        h[i] *= inv2


@njit(cache=True, nogil=True)
def _nll_frame(a, b, mu, sigma) -> float:
    """The NLL of :func:`_evaluate_frame` (the same arithmetic) without its derivatives,
    for 1-bit codes and the logistic likelihood."""
    ramps, m4 = a.shape[0], a.shape[1] * 4
    return _one_bit_logistic_nll(a.reshape(ramps, m4), b.reshape(ramps, m4), _as_float32(mu.reshape(m4)),
                                 1.702 / sigma)


@njit(cache=True, nogil=True, fastmath=_SIMD, error_model="numpy")
def _wrong_rms(kind, a, b, mu) -> float:
    """RMS distance of the codes ``mu`` gets wrong to their cells (0 when none is)."""
    ramps, m4 = a.shape[0], a.shape[1] * 4
    af = a.reshape(ramps, m4)
    bf = b.reshape(ramps, m4)
    muf = mu.reshape(m4)
    acc = 0.0
    wrong = 0
    for r in range(ramps):
        ar = af[r]
        br = bf[r]
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


#: the model's block (samples): the first block by a recurrence, each later one that block
#: times ``exp(i ph b)`` at its start
_BLOCK = 32
#: the vectorized kernels' options: no zero-division checks (they stop LLVM's vectorizer),
#: reassociated float sums
_FAST = dict(cache=True, nogil=True, error_model="numpy", fastmath=True)


@njit(**_FAST)
def _model(nu, amp, kc, w, mu):
    """Atoms ``w`` (K, 2, N) (real and imaginary parts) and the model ``mu`` (N, 4) of
    targets ``nu`` (K,) bins, ``amp`` (K, 2); ``kc`` (N,) in unit steps. ``w_t[i] =
    exp(i ph kc[i])``, ``ph = -2 pi nu_t / N``: three cos/sin pairs a target, the rest
    products (relative error ~1e-14)."""
    k = nu.shape[0]
    n = kc.shape[0]
    muf = mu.reshape(4 * n)
    for t in range(k):
        ph = -2.0 * math.pi * nu[t] / n
        cr, ci = math.cos(ph), math.sin(ph)
        wr, wi = w[t, 0], w[t, 1]
        m = min(_BLOCK, n)
        wr[0], wi[0] = math.cos(ph * kc[0]), math.sin(ph * kc[0])
        for i in range(1, m):
            wr[i] = wr[i - 1] * cr - wi[i - 1] * ci
            wi[i] = wr[i - 1] * ci + wi[i - 1] * cr
        sr, si = math.cos(ph * _BLOCK), math.sin(ph * _BLOCK)
        br, bi = sr, si  # exp(i ph i0)
        for i0 in range(_BLOCK, n, _BLOCK):
            for i in range(min(_BLOCK, n - i0)):
                wr[i0 + i] = br * wr[i] - bi * wi[i]
                wi[i0 + i] = br * wi[i] + bi * wr[i]
            br, bi = br * sr - bi * si, br * si + bi * sr
        a1r, a1i, a2r, a2i = amp[t, 0].real, amp[t, 0].imag, amp[t, 1].real, amp[t, 1].imag
        if t == 0:
            for i in range(n):
                muf[4 * i] = a1r * wr[i] - a1i * wi[i]
                muf[4 * i + 1] = a1r * wi[i] + a1i * wr[i]
                muf[4 * i + 2] = a2r * wr[i] - a2i * wi[i]
                muf[4 * i + 3] = a2r * wi[i] + a2i * wr[i]
        else:
            for i in range(n):
                muf[4 * i] += a1r * wr[i] - a1i * wi[i]
                muf[4 * i + 1] += a1r * wi[i] + a1i * wr[i]
                muf[4 * i + 2] += a2r * wr[i] - a2i * wi[i]
                muf[4 * i + 3] += a2r * wi[i] + a2i * wr[i]
    if k == 0:
        mu[:] = 0.0


@njit(cache=True, nogil=True)
def models(nu, amp, kc, mu):
    """The model ``mu`` (B, N, 4) of targets ``nu`` (B, K) bins, ``amp`` (B, K, 2) (as
    :func:`refine` builds it)."""
    w = np.empty((nu.shape[1], 2, kc.shape[0]))
    for f in range(nu.shape[0]):
        _model(nu[f], amp[f], kc, w, mu[f])


@njit(cache=True, nogil=True)
def _eliminate(m, rhs, x):
    """``m x = rhs`` by Gaussian elimination with partial pivoting (m and rhs overwritten)."""
    p = m.shape[0]
    for col in range(p):
        piv = col
        best = abs(m[col, col])
        for r in range(col + 1, p):
            if abs(m[r, col]) > best:
                best = abs(m[r, col])
                piv = r
        if piv != col:
            for c in range(p):
                m[col, c], m[piv, c] = m[piv, c], m[col, c]
            rhs[col], rhs[piv] = rhs[piv], rhs[col]
        d = m[col, col]
        for r in range(col + 1, p):
            fct = m[r, col] / d
            if fct != 0.0:
                for c in range(col, p):
                    m[r, c] -= fct * m[col, c]
                rhs[r] -= fct * rhs[col]
    for r in range(p - 1, -1, -1):
        acc = rhs[r]
        for c in range(r + 1, p):
            acc -= m[r, c] * x[c]
        x[r] = acc / m[r, r]


@njit(cache=True, nogil=True)
def _solve(m, rhs, lw, x):
    """``x`` (P,) with ``m x = rhs``, m (P, P) symmetric: by Cholesky into ``lw`` (P, P) (the
    lower triangle), or, if m is not positive definite, by Gaussian elimination with partial
    pivoting (m and rhs then overwritten)."""
    p = m.shape[0]
    for j in range(p):
        d = m[j, j]
        for c in range(j):
            d -= lw[j, c] * lw[j, c]
        if not d > 0.0:
            _eliminate(m, rhs, x)
            return
        d = math.sqrt(d)
        lw[j, j] = d
        inv = 1.0 / d
        for r in range(j + 1, p):
            acc = m[r, j]
            for c in range(j):
                acc -= lw[r, c] * lw[j, c]
            lw[r, j] = acc * inv
    for r in range(p):  # L y = rhs, then L^T x = y
        acc = rhs[r]
        for c in range(r):
            acc -= lw[r, c] * x[c]
        x[r] = acc / lw[r, r]
    for r in range(p - 1, -1, -1):
        acc = x[r]
        for c in range(r + 1, p):
            acc -= lw[c, r] * x[c]
        x[r] = acc / lw[r, r]


@njit(**_FAST)
def _sums(w, cw, cw32, g, h, ht, gt, bw, gram, proj):
    """The weighted sums of the atoms the Gauss--Newton system is made of, for each real part
    j of the model and power l of ``cw`` (N,) (= 2 pi kc / N, the derivative's factor;
    ``cw32`` in float32):
    ``gram[l, j, m1, m2] = sum_i h[i, j] cw^l e_m1 e_m2`` (l < 3; float32 sums, as the numpy
    reference's) and ``proj[l, j, m] = sum_i g[i, j] cw^l e_m`` (l < 2; float64), e_m the
    rows of ``w`` (K, 2, N) (e_2t = Re w_t, e_2t+1 = Im w_t). Work arrays: ``ht`` (4, N)
    float32, ``gt`` (4, N), ``bw`` (2K, N) float32."""
    k, n = w.shape[0], w.shape[2]
    nm = 2 * k
    for j in range(4):
        for i in range(n):
            ht[j, i] = h[i, j]
            gt[j, i] = g[i, j]
    for t in range(k):
        for s in range(2):
            for i in range(n):
                bw[2 * t + s, i] = w[t, s, i]
    h0, h1, h2, h3 = ht[0], ht[1], ht[2], ht[3]
    g0, g1, g2, g3 = gt[0], gt[1], gt[2], gt[3]
    for m1 in range(nm):
        x = bw[m1]
        for m2 in range(m1, nm):
            y = bw[m2]
            a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = a8 = a9 = a10 = a11 = np.float32(0.0)
            for i in range(n):
                v = x[i] * y[i]
                vc = v * cw32[i]
                vcc = vc * cw32[i]
                a0 += h0[i] * v
                a1 += h1[i] * v
                a2 += h2[i] * v
                a3 += h3[i] * v
                a4 += h0[i] * vc
                a5 += h1[i] * vc
                a6 += h2[i] * vc
                a7 += h3[i] * vc
                a8 += h0[i] * vcc
                a9 += h1[i] * vcc
                a10 += h2[i] * vcc
                a11 += h3[i] * vcc
            acc = (a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10, a11)
            for q in range(12):
                gram[q // 4, q % 4, m1, m2] = acc[q]
                gram[q // 4, q % 4, m2, m1] = acc[q]
        xs = w[m1 // 2, m1 % 2]
        p0 = p1 = p2 = p3 = p4 = p5 = p6 = p7 = 0.0
        for i in range(n):
            v = xs[i]
            vc = v * cw[i]
            p0 += g0[i] * v
            p1 += g1[i] * v
            p2 += g2[i] * v
            p3 += g3[i] * v
            p4 += g0[i] * vc
            p5 += g1[i] * vc
            p6 += g2[i] * vc
            p7 += g3[i] * vc
        pr = (p0, p1, p2, p3, p4, p5, p6, p7)
        for q in range(8):
            proj[q // 4, q % 4, m1] = pr[q]


@njit(cache=True, nogil=True, inline="always")
def _column(t, u, p, c, ar, ai):
    """Column u (0: nu_t, 1: Re b_tp, 2: Im b_tp) of the Jacobian of part c of antenna p's
    model: the parameter's index, the power of cw, and two atoms' rows with their
    coefficients (see :func:`_normal_equations`)."""
    re, im = 2 * t, 2 * t + 1
    if u == 0:
        if c == 0:
            return 5 * t, 1, im, ar, re, ai
        return 5 * t, 1, im, ai, re, -ar
    if u == 1:
        return 5 * t + 1 + 2 * p, 0, re if c == 0 else im, 1.0, re, 0.0
    return 5 * t + 2 + 2 * p, 0, im if c == 0 else re, -1.0 if c == 0 else 1.0, re, 0.0


@njit(cache=True, nogil=True, error_model="numpy")
def _normal_equations(amp, gram, proj, hess, grad):
    """The Gauss--Newton system of one frame: ``hess`` (5K, 5K) and ``grad`` (5K,), the
    parameters of target t being [nu, Re b1, Im b1, Re b2, Im b2] at 5 t, from the sums of
    :func:`_sums`. Part j = 2 p + c of the model (antenna p, c = 0 real, 1 imaginary) moves
    with the parameters of ``b_tp`` and ``nu_t`` alone, each along at most two atoms' rows:
    Re part: ``d/dRe b = Re w``, ``d/dIm b = -Im w``, ``d/dnu = cw (Re b Im w + Im b Re w)``;
    Im part: ``Im w``, ``Re w``, ``cw (Im b Im w - Re b Re w)``."""
    k = amp.shape[0]
    hess[:] = 0.0
    grad[:] = 0.0
    for j in range(4):
        p, c = j // 2, j % 2
        for x in range(3 * k):
            t1 = x // 3
            q1, l1, r1, c1, s1, d1 = _column(t1, x % 3, p, c, amp[t1, p].real, amp[t1, p].imag)
            grad[q1] += c1 * proj[l1, j, r1] + d1 * proj[l1, j, s1]
            for y in range(x, 3 * k):
                t2 = y // 3
                q2, l2, r2, c2, s2, d2 = _column(t2, y % 3, p, c, amp[t2, p].real, amp[t2, p].imag)
                sg = gram[l1 + l2, j]
                hess[q1, q2] += c1 * (c2 * sg[r1, r2] + d2 * sg[r1, s2]) + d1 * (c2 * sg[s1, r2] + d2 * sg[s1, s2])
    for q in range(5 * k):
        for r in range(q):
            hess[q, r] = hess[r, q]
@njit(cache=True, nogil=True)
def refine(kind, lik, a, b, kc, nu, amp, live, lm, levels, adapt, wrong_per_sigma, amp_cap, gate_lo, gate_hi,
           use_gate, max_range_step, mu, g, h, nll, sigma_out):
    """Levenberg--Marquardt steps of every frame, as :meth:`pipeline.dsp.cml._Fit.step`:
    step j at noise std ``levels[f, j]`` (``adapt``: not below the wrong codes' RMS
    distance over ``wrong_per_sigma``), re-evaluating the likelihood when the level changes
    (a candidate whose derivatives the next step does not use gets its NLL alone);
    a step is kept only when the NLL does not grow. Updates ``nu``, ``amp``, ``lm``, ``mu``,
    ``g``, ``h``, ``nll`` in place and writes each frame's last level to ``sigma_out``.
    ``nll`` on entry: the NLL at ``sigma_out`` (the current level; -1: none)."""
    nb, k = nu.shape
    n = kc.shape[0]
    steps = levels.shape[1]
    if k == 0:
        return
    npar = 5 * k
    # the work arrays, once a call: the current state and the candidate swap places (cur)
    w = np.empty((2, k, 2, n))
    mus = np.empty((2, n, 4))
    gs = np.empty((2, n, 4))
    hs = np.empty((2, n, 4))
    cw = 2.0 * math.pi * kc / n
    cw32 = cw.astype(np.float32)
    ht = np.empty((4, n), dtype=np.float32)
    gt = np.empty((4, n))
    bw = np.empty((2 * k, n), dtype=np.float32)
    gram = np.empty((3, 4, 2 * k, 2 * k))
    proj = np.empty((2, 4, 2 * k))
    hess = np.empty((npar, npar))
    grad = np.empty(npar)
    lw = np.empty((npar, npar))
    step = np.empty(npar)
    nu2 = np.empty(k)
    amp2 = np.empty((k, 2), dtype=np.complex128)
    nll_only = kind == ONE_BIT and lik == LOGISTIC  # a cheaper NLL alone (_nll_frame)
    for f in range(nb):
        cur = 0
        _model(nu[f], amp[f], kc, w[0], mus[0])
        gs[0] = g[f]
        hs[0] = h[f]
        current = sigma_out[f]
        fresh = True  # gs[cur], hs[cur] hold the derivatives at mus[cur] and the current level
        for s in range(steps):
            level = levels[f, s]
            if adapt:
                level = max(level, _wrong_rms(kind, a[f], b[f], mus[cur]) / wrong_per_sigma)
            if level != current or not fresh:
                nll[f] = _evaluate_frame(kind, lik, a[f], b[f], mus[cur], level, gs[cur], hs[cur])
                current = level
                fresh = True
            _sums(w[cur], cw, cw32, gs[cur], hs[cur], ht, gt, bw, gram, proj)
            _normal_equations(amp[f], gram, proj, hess, grad)
            dmax = 0.0
            for q in range(npar):
                dmax = max(dmax, hess[q, q])
            for q in range(npar):
                hess[q, q] += lm[f] * hess[q, q] + 1e-9 * dmax + 1e-300
                grad[q] = -grad[q]
            _solve(hess, grad, lw, step)
            for t in range(k):
                if not live[f, t]:
                    for q in range(5):
                        step[5 * t + q] = 0.0
                dnu = min(max(step[5 * t], -max_range_step), max_range_step)
                norm = 0.0
                for q in range(1, 5):
                    norm += step[5 * t + q] ** 2
                norm = math.sqrt(norm)
                cut = min(1.0, amp_cap[f] / max(norm, 1e-300))
                v = nu[f, t] + dnu
                if use_gate:
                    v = min(max(v, gate_lo), gate_hi)
                nu2[t] = v
                for p in range(2):
                    amp2[t, p] = amp[f, t, p] + complex(step[5 * t + 1 + 2 * p] * cut, step[5 * t + 2 + 2 * p] * cut)
            o = 1 - cur
            _model(nu2, amp2, kc, w[o], mus[o])
            # the candidate's derivatives only when the next step is at this level (known
            # unless adapted) or this is the last step; else the NLL alone
            derivs = not nll_only or s == steps - 1 or (not adapt and levels[f, s + 1] == current)
            if derivs:
                cand = _evaluate_frame(kind, lik, a[f], b[f], mus[o], current, gs[o], hs[o])
            else:
                cand = _nll_frame(a[f], b[f], mus[o], current)
            if cand <= nll[f]:
                fresh = derivs
                lm[f] = max(lm[f] / 3.0, 1e-9)
                nll[f] = cand
                nu[f, :] = nu2
                amp[f, :, :] = amp2
                cur = o
            else:
                lm[f] = min(lm[f] * 8.0, 1e9)
        mu[f, :, :] = mus[cur]
        g[f, :, :] = gs[cur]
        h[f, :, :] = hs[cur]
        sigma_out[f] = current
