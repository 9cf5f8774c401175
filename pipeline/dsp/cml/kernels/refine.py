"""Compiled (numba) Levenberg--Marquardt refinement of cml's targets, one frame at a time
(so a frame costs the same in a batch of 1 or of 64): Gauss--Newton steps on the negative
log-likelihood (NLL) of the codes in all the parameters of all the targets of a frame at
once, a step kept only when the NLL does not grow (layouts: :mod:`pipeline.dsp.cml.kernels.layout`).
The numpy reference (:mod:`pipeline.dsp.cml.reference`) takes the same steps."""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit

from pipeline.dsp.cml.kernels.layout import JIT
from pipeline.dsp.cml.kernels.likelihood import LOGISTIC, ONE_BIT, evaluate_frame, nll_frame, wrong_rms
from pipeline.dsp.cml.kernels.linalg import solve
from pipeline.dsp.cml.kernels.model import PARAMS, centred, model, normal_equations, ramp_offsets, sums

#: the work arrays of a call (the current state and the candidate swap places, index ``cur``):
#: atoms ``w`` (2, K, 2, N), models ``mus`` and derivatives ``gs``, ``hs`` (2, Rm, N, 4), the
#: derivative's factors ``cw`` (N,) and ``cw32``, :func:`~pipeline.dsp.cml.kernels.model.sums`'
#: ``ht``, ``bw``, ``gram``, ``proj``, the system ``hess``, ``grad``, ``lw``, ``step``, the
#: candidate ``nu2``, ``phi2``, ``amp2``, the likelihood's ``work`` (3, Rm, 4N) float32, the
#: model ramps' offsets ``cr`` (Rm,) and the system's ``turn`` (K, 2), ``coef`` (Rm, 4, 4K, 2),
#: ``rows`` (4, 4K, 4) int
Work = namedtuple("Work", ["w", "mus", "gs", "hs", "cw", "cw32", "ht", "bw", "gram", "proj", "hess", "grad", "lw",
                           "step", "nu2", "phi2", "amp2", "work", "cr", "turn", "coef", "rows"])


@njit(**JIT)
def refine(codes, fit, steps):
    """Levenberg--Marquardt steps of every frame of ``fit`` on ``codes``: step j at noise std
    ``steps.levels[f, j]`` (``steps.adapt``: not below the wrong codes' RMS distance over
    ``steps.wrong_per_sigma``), re-evaluating the likelihood when the level changes (a
    candidate whose derivatives the next step does not use gets its NLL alone); a step is
    kept only when the NLL does not grow; ranges are not bounded (a range gate bounds detection and
    what is reported, not the refinement). Updates
    ``fit``'s ``nu``, ``amp``, ``lm``, ``mu``, ``g``, ``h``, ``nll`` in place and writes each
    frame's last level to ``fit.sigma``. ``fit.nll`` on entry: the NLL at ``fit.sigma`` (the
    current level; NaN: none)."""
    k = fit.nu.shape[1]
    if k == 0:
        return
    rm, n = fit.mu.shape[1], fit.mu.shape[2]
    npar = PARAMS * k
    kc = centred(n)
    cw = 2.0 * math.pi * kc / n
    work = Work(np.empty((2, k, 2, n)), np.empty((2, rm, n, 4)), np.empty((2, rm, n, 4)), np.empty((2, rm, n, 4)),
                cw, cw.astype(np.float32), np.empty((4, n), dtype=np.float32), np.empty((2 * k, n), dtype=np.float32),
                np.empty((3, 4, 2 * k, 2 * k)), np.empty((rm, 2, 4, 2 * k)), np.empty((npar, npar)),
                np.empty(npar), np.empty((npar, npar)), np.empty(npar), np.empty(k), np.empty(k),
                np.empty((k, 2), dtype=np.complex128), np.empty((3, rm, 4 * n), dtype=np.float32), ramp_offsets(rm),
                np.empty((k, 2)), np.empty((rm, 4, 4 * k, 2)), np.empty((4, 4 * k, 4), dtype=np.int64))
    for f in range(fit.nu.shape[0]):
        _refine_frame(codes, fit, steps, kc, work, f)


@njit(**JIT, inline="always")
def _refine_frame(codes, fit, steps, kc, work, f):
    """:func:`refine` of frame ``f``. (The fields of the namedtuples are read once, before the
    steps: a field read from a namedtuple is a reference counted each time, measured 3-5 % of
    the steps when read in the loop.)"""
    kind, lik, a, b = codes.kind, codes.lik, codes.a[f], codes.b[f]
    nu, phi, amp, live = fit.nu[f], fit.phi[f], fit.amp[f], fit.live[f]
    levels, amp_cap = steps.levels[f], steps.amp_cap[f]
    adapt, wrong_per_sigma, max_step = steps.adapt, steps.wrong_per_sigma, steps.max_range_step
    max_phase = steps.max_phase_step
    w, mus, gs, hs, nu2, phi2, amp2, lw = work.w, work.mus, work.gs, work.hs, work.nu2, work.phi2, work.amp2, work.work
    cw, cw32, ht, bw, gram, proj = work.cw, work.cw32, work.ht, work.bw, work.gram, work.proj
    hess, grad, chol, step, cr, turn = work.hess, work.grad, work.lw, work.step, work.cr, work.turn
    coef, rows = work.coef, work.rows
    nll_only = kind == ONE_BIT and lik == LOGISTIC  # a cheaper NLL alone (nll_frame)
    count = levels.shape[0]
    cur = 0
    model(nu, phi, amp, kc, cr, w[0], mus[0])
    gs[0] = fit.g[f]
    hs[0] = fit.h[f]
    current, nll, lm = fit.sigma[f], fit.nll[f], fit.lm[f]
    fresh = True  # gs[cur], hs[cur] hold the derivatives at mus[cur] and the current level
    for s in range(count):
        level = levels[s]
        if adapt:
            level = max(level, wrong_rms(kind, a, b, mus[cur]) / wrong_per_sigma)
        if level != current or not fresh:
            nll = evaluate_frame(kind, lik, a, b, mus[cur], level, gs[cur], hs[cur], lw)
            current = level
            fresh = True
        sums(w[cur], cw, cw32, gs[cur], hs[cur], ht, bw, gram, proj)
        normal_equations(amp, phi, cr, gram, proj, hess, grad, turn, coef, rows)
        _damp(hess, grad, lm, live)
        solve(hess, grad, chol, step)
        _candidate(nu, phi, amp, live, step, (amp_cap, max_step, max_phase), nu2, phi2, amp2)
        o = 1 - cur
        model(nu2, phi2, amp2, kc, cr, w[o], mus[o])
        # the candidate's derivatives only when the next step is at this level (known
        # unless adapted) or this is the last step; else the NLL alone
        derivs = not nll_only or s == count - 1 or (not adapt and levels[s + 1] == current)
        if derivs:
            cand = evaluate_frame(kind, lik, a, b, mus[o], current, gs[o], hs[o], lw)
        else:
            cand = nll_frame(a, b, mus[o], current, lw)
        if cand <= nll:
            fresh = derivs
            lm = max(lm / 3.0, 1e-9)
            nll = cand
            nu[:] = nu2
            phi[:] = phi2
            amp[:, :] = amp2
            cur = o
        else:
            lm = min(lm * 8.0, 1e9)
    fit.nll[f], fit.lm[f], fit.sigma[f] = nll, lm, current
    fit.mu[f] = mus[cur]
    fit.g[f] = gs[cur]
    fit.h[f] = hs[cur]


@njit(**JIT, inline="always")
def _damp(hess, grad, lm, live):
    """The Gauss--Newton system ``hess`` (P, P), ``grad`` (P,) damped by ``lm`` (Levenberg's
    term, plus 1e-9 of the largest diagonal entry), the gradient negated: the step solves it.
    The targets not ``live`` (K,) take no part (their rows and columns zero): the system is
    the live targets' alone."""
    npar = grad.shape[0]
    for t in range(live.shape[0]):
        if not live[t]:
            for q in range(PARAMS * t, PARAMS * (t + 1)):
                grad[q] = 0.0
                for c in range(npar):
                    hess[q, c] = 0.0
                    hess[c, q] = 0.0
    dmax = 0.0
    for q in range(npar):
        dmax = max(dmax, hess[q, q])
    for q in range(npar):
        hess[q, q] += lm * hess[q, q] + 1e-9 * dmax + 1e-300
        grad[q] = -grad[q]


@njit(**JIT, inline="always")
def _candidate(nu, phi, amp, live, step, caps, nu2, phi2, amp2):
    """The candidate targets ``nu2`` (K,), ``phi2``, ``amp2`` (K, 2): the targets ``nu`` bins,
    ``phi`` rad, ``amp`` moved by ``step`` (not those not ``live``), with ``caps`` = (amp_cap,
    max_step, max_phase): the range step clipped to ``max_step``, the phase step's to
    ``max_phase``, the amplitudes' to ``amp_cap`` (a range gate does not bound them: a target
    may leave it, :class:`pipeline.dsp.cml.grid.SearchGrid`)."""
    amp_cap, max_step, max_phase = caps
    for t in range(nu.shape[0]):
        base = PARAMS * t
        if not live[t]:
            for q in range(PARAMS):
                step[base + q] = 0.0
        dnu = min(max(step[base], -max_step), max_step)
        norm = 0.0
        for q in range(1, 5):
            norm += step[base + q] ** 2
        norm = math.sqrt(norm)
        cut = min(1.0, amp_cap / max(norm, 1e-300))
        nu2[t] = nu[t] + dnu
        phi2[t] = phi[t] + min(max(step[base + 5], -max_phase), max_phase)
        for p in range(2):
            amp2[t, p] = amp[t, p] + complex(step[base + 1 + 2 * p] * cut, step[base + 2 + 2 * p] * cut)


@njit(**JIT)
def settled_score(fit, ge):
    """The efficient score's ``g`` of every frame of ``fit`` into ``ge`` (B, Rm, N, 4): on each
    model ramp q ``g_q + h_q (J_q d)``, ``d`` the undamped Gauss--Newton step of the live
    targets (all their parameters, the phase step too) at ``fit``'s ``g``, ``h`` and ``J_q``
    the model's Jacobian on ramp q (``sum_q J_q^T ge_q = 0`` up to the ramps' shared
    curvature of the system, :func:`~pipeline.dsp.cml.kernels.model.sums`: what no target found
    could take up by moving; :meth:`pipeline.dsp.cml.reference.Fit.settled_score`, the same
    sums and system as :func:`refine`'s step). With a phase step phi_t, ramp q sees target t
    move by ``exp(i c_q phi_t) ((db_t + i c_q dphi_t b_t) w_t + b_t dnu_t dw_t / dnu)``."""
    nb, k = fit.nu.shape
    rm, n = fit.mu.shape[1], fit.mu.shape[2]
    if k == 0:
        ge[:] = fit.g
        return
    npar = PARAMS * k
    kc = centred(n)
    cw = 2.0 * math.pi * kc / n
    cw32 = cw.astype(np.float32)
    cr = ramp_offsets(rm)
    w = np.empty((k, 2, n))
    mu = np.empty((rm, n, 4))
    ht, bw = np.empty((4, n), dtype=np.float32), np.empty((2 * k, n), dtype=np.float32)
    gram, proj = np.empty((3, 4, 2 * k, 2 * k)), np.empty((rm, 2, 4, 2 * k))
    hess, grad, chol, step = np.empty((npar, npar)), np.empty(npar), np.empty((npar, npar)), np.empty(npar)
    turn, coef, rows = np.empty((k, 2)), np.empty((rm, 4, 4 * k, 2)), np.empty((4, 4 * k, 4), dtype=np.int64)
    for f in range(nb):
        nu, phi, amp, live, g, h = fit.nu[f], fit.phi[f], fit.amp[f], fit.live[f], fit.g[f], fit.h[f]
        model(nu, phi, amp, kc, cr, w, mu)
        sums(w, cw, cw32, g, h, ht, bw, gram, proj)
        normal_equations(amp, phi, cr, gram, proj, hess, grad, turn, coef, rows)
        _damp(hess, grad, 0.0, live)
        solve(hess, grad, chol, step)
        for q in range(rm):
            for i in range(n):
                for j in range(4):
                    ge[f, q, i, j] = g[q, i, j]
        for t in range(k):
            if not live[t]:
                continue
            base = PARAMS * t
            dnu = step[base]
            dphi = step[base + 5] if rm > 1 else 0.0
            for q in range(rm):
                e = complex(math.cos(cr[q] * phi[t]), math.sin(cr[q] * phi[t])) if rm > 1 else 1.0 + 0.0j
                for p in range(2):
                    b = amp[t, p]
                    # the atom's coefficient and its derivative's: d mu = ca w + cb (d w / d nu),
                    # d w / d nu = -i cw w
                    ca = e * (complex(step[base + 1 + 2 * p], step[base + 2 + 2 * p]) + 1j * cr[q] * dphi * b)
                    cb = e * b * dnu
                    for i in range(n):
                        c = ca - 1j * cw[i] * cb
                        d = c * complex(w[t, 0, i], w[t, 1, i])
                        ge[f, q, i, 2 * p] += h[q, i, 2 * p] * d.real
                        ge[f, q, i, 2 * p + 1] += h[q, i, 2 * p + 1] * d.imag
