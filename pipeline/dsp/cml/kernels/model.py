"""Compiled (numba) model of cml's targets on each ramp and its Jacobian: the atoms
``w_t[n] = exp(-i 2 pi kc_n nu_t / N)`` (``kc = n - (N - 1) / 2``, the sample index from the
middle of the ramp), the model ``mu_{r,n,p} = sum_t b_{t,p} exp(i c_r phi_t) w_t[n]`` (``c_r =
r - (Rm - 1) / 2``, the ramp from the middle of the frame) and the Gauss--Newton system
of the negative log-likelihood in the parameters of the targets (layouts:
:mod:`pipeline.dsp.cml.kernels.layout`).

A target's parameters are :data:`PARAMS` reals: ``[nu, Re b1, Im b1, Re b2, Im b2, phi]``,
its range in bins, its two amplitudes referred to mid-sweep and to the middle of the frame,
and its phase step between consecutive ramps (rad: ``-4 pi f_c v dt / c`` for a radial
velocity v, ramps dt apart, f_c the sweep's middle frequency), target t's at ``PARAMS t``.
Ramp r of a frame of Rm model ramps sees the target's amplitudes turned by
``exp(i (r - (Rm - 1) / 2) phi)``; the static model (Rm = 1, every ramp the same) has
phi's column 0 and phi stays 0.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from pipeline.dsp.cml.kernels.layout import FAST, JIT

#: the parameters of a target: range (bins), the real and imaginary parts of its two amplitudes,
#: and its phase step between ramps (rad)
PARAMS = 6


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


@njit(**JIT)
def ramp_offsets(rm):
    """Each model ramp's place from the middle of the frame, ``r - (Rm - 1) / 2`` (Rm,): ramp
    r of a target of phase step phi is its amplitude times ``exp(i (r - (Rm - 1) / 2) phi)``
    (Rm = 1, the static model: 0)."""
    return np.arange(rm) - (rm - 1) / 2.0


@njit(**FAST)
def model(nu, phi, amp, kc, cr, w, mu):
    """Atoms ``w`` (K, 2, N) (real and imaginary parts, :func:`atom`) and the model ``mu``
    (Rm, N, 4) of targets ``nu`` (K,) bins, ``phi`` (K,) phase steps, ``amp`` (K, 2); ``kc``
    (N,) in unit steps, ``cr`` (Rm,) the ramps' offsets (:func:`ramp_offsets`): ramp q's
    amplitudes are ``amp exp(i cr[q] phi)``."""
    k = nu.shape[0]
    n = kc.shape[0]
    rm = cr.shape[0]
    for t in range(k):
        atom(nu[t], kc, w[t, 0], w[t, 1])
    for q in range(rm):
        muf = mu[q].reshape(4 * n)
        for t in range(k):
            wr, wi = w[t, 0], w[t, 1]
            a1, a2 = amp[t, 0], amp[t, 1]
            if rm > 1:
                turn = complex(math.cos(cr[q] * phi[t]), math.sin(cr[q] * phi[t]))
                a1, a2 = a1 * turn, a2 * turn
            a1r, a1i, a2r, a2i = a1.real, a1.imag, a2.real, a2.imag
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
def models(nu, phi, amp, kc, mu):
    """The model ``mu`` (B, Rm, N, 4) of targets ``nu`` (B, K) bins, ``phi`` (B, K),
    ``amp`` (B, K, 2) (as :func:`pipeline.dsp.cml.kernels.refine.refine` builds it)."""
    w = np.empty((nu.shape[1], 2, kc.shape[0]))
    cr = ramp_offsets(mu.shape[1])
    for f in range(nu.shape[0]):
        model(nu[f], phi[f], amp[f], kc, cr, w, mu[f])


@njit(**FAST)
def sums(w, cw, cw32, g, h, ht, bw, gram, proj):
    """The weighted sums of the atoms the Gauss--Newton system is made of, for each real part
    j of the model and power l of ``cw`` (N,) (= 2 pi kc / N, the derivative's factor; ``cw32``
    in float32): ``gram[l, j, m1, m2] = sum_i hbar[i, j] cw^l e_m1 e_m2`` (l < 3; float32
    sums, as the numpy reference's) with ``hbar`` the mean of ``h`` over the model ramps, and
    for each model ramp q ``proj[q, l, j, m] = sum_i g[q, i, j] cw^l e_m`` (l < 2; float64),
    e_m the rows of ``w`` (K, 2, N) (e_2t = Re w_t, e_2t+1 = Im w_t); ``g``, ``h`` (Rm, N, 4).
    Work arrays: ``ht`` (4, N) float32 (hbar transposed), ``bw`` (2K, N) float32.

    The ramps share one curvature (``hbar``): the Gauss--Newton matrix ``sum_q J_q^T
    diag(h_q) J_q`` taken as ``sum_q J_q^T diag(hbar) J_q``; the curvature of a code differs
    from ramp to ramp only by its dither and noise, and the gradient stays exact (measured:
    the same errors as the exact matrix, at the cost of the static model's sums).

    A pair's 12 float32 sums in two vectorized loops (8, then the 4 of cw^2: 12 accumulators
    in one loop spill to the stack); ``proj`` reads g in its (N, 4) layout."""
    k, n = w.shape[0], w.shape[2]
    rm = h.shape[0]
    nm = 2 * k
    if rm == 1:
        hf = h.reshape(4 * n)
        for i in range(n):
            ht[0, i] = hf[4 * i]
            ht[1, i] = hf[4 * i + 1]
            ht[2, i] = hf[4 * i + 2]
            ht[3, i] = hf[4 * i + 3]
    elif rm == 2:
        h0, h1 = h[0].reshape(4 * n), h[1].reshape(4 * n)
        for i in range(n):
            ht[0, i] = (h0[4 * i] + h1[4 * i]) * 0.5
            ht[1, i] = (h0[4 * i + 1] + h1[4 * i + 1]) * 0.5
            ht[2, i] = (h0[4 * i + 2] + h1[4 * i + 2]) * 0.5
            ht[3, i] = (h0[4 * i + 3] + h1[4 * i + 3]) * 0.5
    else:
        inv = 1.0 / rm
        for i in range(n):
            for j in range(4):
                acc = 0.0
                for q in range(rm):
                    acc += h[q, i, j]
                ht[j, i] = acc * inv
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
    for q in range(rm):
        _projections(w, cw, g[q], proj[q])


@njit(**FAST)
def _projections(w, cw, g, proj):
    """``proj[l, j, m] = sum_i g[i, j] cw^l e_m`` (l < 2) of one model ramp: ``g`` (N, 4),
    ``proj`` (2, 4, 2K)."""
    k, n = w.shape[0], w.shape[2]
    gf = g.reshape(4 * n)
    for m1 in range(2 * k):
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
def _column(t, u, p, c, ar, ai, cs, sn, cq):
    """Column u (0: nu_t, 1: Re b_tp, 2: Im b_tp, 3: phi_t) of the Jacobian of part c of
    antenna p's model on a ramp where target t's amplitude is ``ar + i ai`` (``b_tp``
    turned by ``cs + i sn`` = ``exp(i cq phi_t)``, cq the ramp's offset): the parameter's
    index, the power of cw, and two atoms' rows with their coefficients (see
    :func:`normal_equations`)."""
    re, im = 2 * t, 2 * t + 1
    if u == 0:
        if c == 0:
            return PARAMS * t, 1, im, ar, re, ai
        return PARAMS * t, 1, im, ai, re, -ar
    if u == 1:
        if c == 0:
            return PARAMS * t + 1 + 2 * p, 0, re, cs, im, -sn
        return PARAMS * t + 1 + 2 * p, 0, re, sn, im, cs
    if u == 2:
        if c == 0:
            return PARAMS * t + 2 + 2 * p, 0, re, -sn, im, -cs
        return PARAMS * t + 2 + 2 * p, 0, re, cs, im, -sn
    if c == 0:
        return PARAMS * t + 5, 0, im, -cq * ar, re, -cq * ai
    return PARAMS * t + 5, 0, re, cq * ar, im, -cq * ai


@njit(cache=True, nogil=True, error_model="numpy")
def normal_equations(amp, phi, cr, gram, proj, hess, grad, turn, coef, rows):
    """The Gauss--Newton system of one frame: ``hess`` (6K, 6K) and ``grad`` (6K,), the
    parameters of target t being [nu, Re b1, Im b1, Re b2, Im b2, phi] at PARAMS t, from the
    sums of :func:`sums` (``gram`` the ramps' shared one, ``proj`` each model ramp q's, of
    offset ``cr[q]``; phi's column is 0 in the static model, Rm = 1). On ramp q target t's
    amplitude is ``b_q = b exp(i cq phi)``; part j = 2 p + c of the model (antenna p, c = 0
    real, 1 imaginary) moves with the parameters of ``b_tp``, ``nu_t`` and ``phi_t`` alone,
    each along at most two atoms' rows (the same rows on every ramp): Re part: ``d/dRe b =
    Re(e w)``, ``d/dIm b = -Im(e w)`` (e = ``exp(i cq phi)``), ``d/dnu = cw (Re b_q Im w + Im
    b_q Re w)``, ``d/dphi = -cq (Re b_q Im w + Im b_q Re w)``; Im part: ``Im(e w)``, ``Re(e
    w)``, ``cw (Im b_q Im w - Re b_q Re w)``, ``cq (Re b_q Re w - Im b_q Im w)``. Work:
    ``turn`` (K, 2), ``coef`` (Rm, 4, 4K, 2) each column's two coefficients on each ramp,
    ``rows`` (4, 4K, 4) int its parameter, power of cw and two rows. The static model's
    columns skip phi (its row and column of ``hess`` stay 0)."""
    k = amp.shape[0]
    rm = cr.shape[0]
    per = 4 if rm > 1 else 3  # columns a target: the static model has no phi's
    nx = per * k
    hess[:] = 0.0
    grad[:] = 0.0
    for q in range(rm):
        cq = cr[q]
        for t in range(k):
            turn[t, 0], turn[t, 1] = math.cos(cq * phi[t]), math.sin(cq * phi[t])
        for j in range(4):
            p, c = j // 2, j % 2
            for x in range(nx):
                t1 = x // per
                cs1, sn1 = turn[t1, 0], turn[t1, 1]
                b1 = amp[t1, p] * complex(cs1, sn1)
                q1, l1, r1, c1, s1, d1 = _column(t1, x % per, p, c, b1.real, b1.imag, cs1, sn1, cq)
                rows[j, x, 0], rows[j, x, 1], rows[j, x, 2], rows[j, x, 3] = q1, l1, r1, s1
                coef[q, j, x, 0], coef[q, j, x, 1] = c1, d1
                grad[q1] += c1 * proj[q, l1, j, r1] + d1 * proj[q, l1, j, s1]
    for j in range(4):
        for x in range(nx):
            q1, l1, r1, s1 = rows[j, x, 0], rows[j, x, 1], rows[j, x, 2], rows[j, x, 3]
            for y in range(x, nx):
                q2, l2, r2, s2 = rows[j, y, 0], rows[j, y, 1], rows[j, y, 2], rows[j, y, 3]
                lq = l1 + l2
                if rm == 1:
                    c1, d1, c2, d2 = coef[0, j, x, 0], coef[0, j, x, 1], coef[0, j, y, 0], coef[0, j, y, 1]
                    hess[q1, q2] += c1 * (c2 * gram[lq, j, r1, r2] + d2 * gram[lq, j, r1, s2]) + d1 * (
                        c2 * gram[lq, j, s1, r2] + d2 * gram[lq, j, s1, s2])
                    continue
                rr = rs = sr = ss = 0.0
                for q in range(rm):
                    c1, d1, c2, d2 = coef[q, j, x, 0], coef[q, j, x, 1], coef[q, j, y, 0], coef[q, j, y, 1]
                    rr += c1 * c2
                    rs += c1 * d2
                    sr += d1 * c2
                    ss += d1 * d2
                hess[q1, q2] += (rr * gram[lq, j, r1, r2] + rs * gram[lq, j, r1, s2] + sr * gram[lq, j, s1, r2]
                                 + ss * gram[lq, j, s1, s2])
    for q in range(PARAMS * k):
        for r in range(q):
            hess[q, r] = hess[r, q]
