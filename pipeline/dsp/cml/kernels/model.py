"""Compiled (numba) model of cml's targets on one ramp and its Jacobian: the atoms
``w_t[n] = exp(-i 2 pi kc_n nu_t / N)`` (``kc = n - (N - 1) / 2``, the sample index from the
middle of the ramp), the model ``mu_{n,p} = sum_t b_{t,p} w_t[n]`` and the Gauss--Newton system
of the negative log-likelihood in the parameters of the targets (layouts:
:mod:`pipeline.dsp.cml.kernels.layout`).

A target's parameters are :data:`PARAMS` reals: ``[nu, Re b1, Im b1, Re b2, Im b2]``, its
range in bins and its two amplitudes referred to mid-sweep, target t's at ``PARAMS t``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from pipeline.dsp.cml.kernels.layout import FAST, JIT

#: the parameters of a target: range (bins) and the real and imaginary parts of its two amplitudes
PARAMS = 5


@njit(**JIT)
def centred(n):
    """The sample indices of a ramp from its middle, ``kc = n - (N - 1) / 2`` (N,)."""
    return np.arange(n) - (n - 1) / 2.0


#: an atom's block (samples): the first block by a recurrence, each later one that block
#: times ``exp(i ph b)`` at its start (:func:`atom`)
_BLOCK = 32


@njit(**FAST)
def atom(nu_t, kc, wr, wi):
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


@njit(**FAST)
def model(nu, amp, kc, w, mu):
    """Atoms ``w`` (K, 2, N) (real and imaginary parts, :func:`atom`) and the model ``mu``
    (N, 4) of targets ``nu`` (K,) bins, ``amp`` (K, 2); ``kc`` (N,) in unit steps."""
    k = nu.shape[0]
    n = kc.shape[0]
    muf = mu.reshape(4 * n)
    for t in range(k):
        wr, wi = w[t, 0], w[t, 1]
        atom(nu[t], kc, wr, wi)
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


@njit(**JIT)
def models(nu, amp, kc, mu):
    """The model ``mu`` (B, N, 4) of targets ``nu`` (B, K) bins, ``amp`` (B, K, 2) (as
    :func:`pipeline.dsp.cml.kernels.refine.refine` builds it)."""
    w = np.empty((nu.shape[1], 2, kc.shape[0]))
    for f in range(nu.shape[0]):
        model(nu[f], amp[f], kc, w, mu[f])


@njit(**FAST)
def sums(w, cw, cw32, g, h, ht, bw, gram, proj):
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
    coefficients (see :func:`normal_equations`)."""
    re, im = 2 * t, 2 * t + 1
    if u == 0:
        if c == 0:
            return PARAMS * t, 1, im, ar, re, ai
        return PARAMS * t, 1, im, ai, re, -ar
    if u == 1:
        return PARAMS * t + 1 + 2 * p, 0, re if c == 0 else im, 1.0, re, 0.0
    return PARAMS * t + 2 + 2 * p, 0, im if c == 0 else re, -1.0 if c == 0 else 1.0, re, 0.0


@njit(cache=True, nogil=True, error_model="numpy")
def normal_equations(amp, gram, proj, hess, grad):
    """The Gauss--Newton system of one frame: ``hess`` (5K, 5K) and ``grad`` (5K,), the
    parameters of target t being [nu, Re b1, Im b1, Re b2, Im b2] at PARAMS t, from the sums of
    :func:`sums`. Part j = 2 p + c of the model (antenna p, c = 0 real, 1 imaginary) moves
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
    for q in range(PARAMS * k):
        for r in range(q):
            hess[q, r] = hess[r, q]


