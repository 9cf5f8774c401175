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
def refine(codes, fit, steps, gate):
    """Levenberg--Marquardt steps of every frame of ``fit`` on ``codes``: step j at noise std
    ``steps.levels[f, j]`` (``steps.adapt``: not below the wrong codes' RMS distance over
    ``steps.wrong_per_sigma``), re-evaluating the likelihood when the level changes (a
    candidate whose derivatives the next step does not use gets its NLL alone); a step is
    kept only when the NLL does not grow; ranges stay in ``gate`` (``gate.use``). Updates
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
        _refine_frame(codes, fit, steps, gate, kc, work, f)


@njit(**JIT, inline="always")
def _refine_frame(codes, fit, steps, gate, kc, work, f):
    """:func:`refine` of frame ``f``. (The fields of the namedtuples are read once, before the
    steps: a field read from a namedtuple is a reference counted each time, measured 3-5 % of
    the steps when read in the loop.)"""
    kind, lik, a, b = codes.kind, codes.lik, codes.a[f], codes.b[f]
    nu, phi, amp, live = fit.nu[f], fit.phi[f], fit.amp[f], fit.live[f]
    levels, amp_cap = steps.levels[f], steps.amp_cap[f]
    adapt, wrong_per_sigma, max_step = steps.adapt, steps.wrong_per_sigma, steps.max_range_step
    max_phase = steps.max_phase_step
    use, lo, hi = gate.use, gate.lo, gate.hi
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
        _damp(hess, grad, lm)
        solve(hess, grad, chol, step)
        _candidate(nu, phi, amp, live, step, (amp_cap, max_step, max_phase), (use, lo, hi), nu2, phi2, amp2)
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
def _damp(hess, grad, lm):
    """The Gauss--Newton system ``hess`` (P, P), ``grad`` (P,) damped by ``lm`` (Levenberg's
    term, plus 1e-9 of the largest diagonal entry), the gradient negated: the step solves it."""
    npar = grad.shape[0]
    dmax = 0.0
    for q in range(npar):
        dmax = max(dmax, hess[q, q])
    for q in range(npar):
        hess[q, q] += lm * hess[q, q] + 1e-9 * dmax + 1e-300
        grad[q] = -grad[q]


@njit(**JIT, inline="always")
def _candidate(nu, phi, amp, live, step, caps, bounds, nu2, phi2, amp2):
    """The candidate targets ``nu2`` (K,), ``phi2``, ``amp2`` (K, 2): the targets ``nu`` bins,
    ``phi`` rad, ``amp`` moved by ``step`` (not those not ``live``), with ``caps`` = (amp_cap,
    max_step, max_phase): the range step clipped to ``max_step``, the phase step's to
    ``max_phase``, the amplitudes' to ``amp_cap``; ranges kept in the gate ``bounds`` =
    (use, lo, hi) [``lo``, ``hi``] (``use``)."""
    amp_cap, max_step, max_phase = caps
    use, lo, hi = bounds
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
        v = nu[t] + dnu
        if use:
            v = min(max(v, lo), hi)
        nu2[t] = v
        phi2[t] = phi[t] + min(max(step[base + 5], -max_phase), max_phase)
        for p in range(2):
            amp2[t, p] = amp[t, p] + complex(step[base + 1 + 2 * p] * cut, step[base + 2 + 2 * p] * cut)
