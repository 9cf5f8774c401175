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

The likelihood's kernels are in :mod:`pipeline.dsp.cml_likelihood_kernels` (re-exported here).

Compiled on first use and cached on disk (``cache=True``: ``__pycache__`` beside this
file, or ``NUMBA_CACHE_DIR``), so a later process loads them instead of compiling.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from pipeline.dsp.cml_likelihood_kernels import (GAUSSIAN, LOGISTIC, LSQ, MULTI_BIT, ONE_BIT,  # noqa: F401
                                               _evaluate_frame, _nll_frame, _softplus, _wrong_rms, evaluate,
                                               log_ndtr)
from pipeline.dsp.kernel_cache import drop_stale


#: an atom's block (samples): the first block by a recurrence, each later one that block
#: times ``exp(i ph b)`` at its start (:func:`_atom`)
_BLOCK = 32
#: the vectorized kernels' options: no zero-division checks (they stop LLVM's vectorizer),
#: reassociated float sums
_FAST = dict(cache=True, nogil=True, error_model="numpy", fastmath=True)


@njit(**_FAST)
def _atom(nu_t, kc, wr, wi):
    """The atom of a target at ``nu_t`` bins: ``wr + i wi`` (N,) ``= exp(i ph kc)``,
    ``ph = -2 pi nu_t / N``, ``kc`` (N,) in unit steps: three cos/sin pairs, the rest
    products (relative error ~1e-14): the first block of 32 samples by a recurrence, each
    later one that block times ``exp(i ph b)`` at its start. (Its conjugate is the matched
    filter of a target's least-squares amplitude.)"""
    n = kc.shape[0]
    ph = -2.0 * math.pi * nu_t / n
    cr, ci = math.cos(ph), math.sin(ph)
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


@njit(**_FAST)
def _model(nu, amp, kc, w, mu):
    """Atoms ``w`` (K, 2, N) (real and imaginary parts, :func:`_atom`) and the model ``mu``
    (N, 4) of targets ``nu`` (K,) bins, ``amp`` (K, 2); ``kc`` (N,) in unit steps."""
    k = nu.shape[0]
    n = kc.shape[0]
    muf = mu.reshape(4 * n)
    for t in range(k):
        wr, wi = w[t, 0], w[t, 1]
        _atom(nu[t], kc, wr, wi)
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
def _sums(w, cw, cw32, g, h, ht, bw, gram, proj):
    """The weighted sums of the atoms the Gauss--Newton system is made of, for each real part
    j of the model and power l of ``cw`` (N,) (= 2 pi kc / N, the derivative's factor;
    ``cw32`` in float32):
    ``gram[l, j, m1, m2] = sum_i h[i, j] cw^l e_m1 e_m2`` (l < 3; float32 sums, as the numpy
    reference's) and ``proj[l, j, m] = sum_i g[i, j] cw^l e_m`` (l < 2; float64), e_m the
    rows of ``w`` (K, 2, N) (e_2t = Re w_t, e_2t+1 = Im w_t); ``g``, ``h`` (N, 4). Work
    arrays: ``ht`` (4, N) float32 (h transposed), ``bw`` (2K, N) float32.

    A pair's 12 float32 sums in two vectorized loops (8, then the 4 of cw^2: 12 accumulators
    in one loop spill to the stack); ``proj`` reads g in its (N, 4) layout."""
    k, n = w.shape[0], w.shape[2]
    nm = 2 * k
    hf = h.reshape(4 * n)
    gf = g.reshape(4 * n)
    for i in range(n):
        ht[0, i] = hf[4 * i]
        ht[1, i] = hf[4 * i + 1]
        ht[2, i] = hf[4 * i + 2]
        ht[3, i] = hf[4 * i + 3]
    for t in range(k):
        for s in range(2):
            for i in range(n):
                bw[2 * t + s, i] = w[t, s, i]
    for m1 in range(nm):
        for m2 in range(m1, nm):
            a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = np.float32(0.0)
            for i in range(n):
                v = bw[m1, i] * bw[m2, i]
                vc = v * cw32[i]
                a0 += ht[0, i] * v
                a1 += ht[1, i] * v
                a2 += ht[2, i] * v
                a3 += ht[3, i] * v
                a4 += ht[0, i] * vc
                a5 += ht[1, i] * vc
                a6 += ht[2, i] * vc
                a7 += ht[3, i] * vc
            a8 = a9 = a10 = a11 = np.float32(0.0)
            for i in range(n):
                vcc = bw[m1, i] * bw[m2, i] * cw32[i] * cw32[i]
                a8 += ht[0, i] * vcc
                a9 += ht[1, i] * vcc
                a10 += ht[2, i] * vcc
                a11 += ht[3, i] * vcc
            acc = (a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10, a11)
            for q in range(12):
                gram[q // 4, q % 4, m1, m2] = acc[q]
                gram[q // 4, q % 4, m2, m1] = acc[q]
        t, s = m1 // 2, m1 % 2
        p0 = p1 = p2 = p3 = p4 = p5 = p6 = p7 = 0.0
        for i in range(n):
            v = w[t, s, i]
            vc = v * cw[i]
            g0 = gf[4 * i]
            g1 = gf[4 * i + 1]
            g2 = gf[4 * i + 2]
            g3 = gf[4 * i + 3]
            p0 += g0 * v
            p1 += g1 * v
            p2 += g2 * v
            p3 += g3 * v
            p4 += g0 * vc
            p5 += g1 * vc
            p6 += g2 * vc
            p7 += g3 * vc
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
                lq = l1 + l2
                hess[q1, q2] += c1 * (c2 * gram[lq, j, r1, r2] + d2 * gram[lq, j, r1, s2]) + d1 * (
                    c2 * gram[lq, j, s1, r2] + d2 * gram[lq, j, s1, s2])
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
    bw = np.empty((2 * k, n), dtype=np.float32)
    gram = np.empty((3, 4, 2 * k, 2 * k))
    proj = np.empty((2, 4, 2 * k))
    hess = np.empty((npar, npar))
    grad = np.empty(npar)
    lw = np.empty((npar, npar))
    step = np.empty(npar)
    nu2 = np.empty(k)
    amp2 = np.empty((k, 2), dtype=np.complex128)
    work = np.empty((3, 4 * n), dtype=np.float32)
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
                nll[f] = _evaluate_frame(kind, lik, a[f], b[f], mus[cur], level, gs[cur], hs[cur], work)
                current = level
                fresh = True
            _sums(w[cur], cw, cw32, gs[cur], hs[cur], ht, bw, gram, proj)
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
                cand = _evaluate_frame(kind, lik, a[f], b[f], mus[o], current, gs[o], hs[o], work)
            else:
                cand = _nll_frame(a[f], b[f], mus[o], current, work)
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


# numba keys a cached kernel on this file alone: refine is dropped from the cache when the
# likelihood's kernels (which it calls) change
drop_stale(__file__, (refine,), ("cml_likelihood_kernels.py",))
