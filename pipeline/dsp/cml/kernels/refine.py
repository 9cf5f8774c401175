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
from pipeline.dsp.cml.kernels.model import PARAMS, centred, model, normal_equations, sums

#: the work arrays of a call (the current state and the candidate swap places, index ``cur``):
#: atoms ``w`` (2, K, 2, N), models ``mus`` and derivatives ``gs``, ``hs`` (2, N, 4), the
#: derivative's factors ``cw`` (N,) and ``cw32``, :func:`~pipeline.dsp.cml.kernels.model.sums`'
#: ``ht``, ``bw``, ``gram``, ``proj``, the system ``hess``, ``grad``, ``lw``, ``step``, the
#: candidate ``nu2``, ``amp2``, and the likelihood's ``work`` (3, 4N) float32
Work = namedtuple("Work", ["w", "mus", "gs", "hs", "cw", "cw32", "ht", "bw", "gram", "proj", "hess", "grad", "lw",
                           "step", "nu2", "amp2", "work"])


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
    n = fit.mu.shape[1]
    npar = PARAMS * k
    kc = centred(n)
    cw = 2.0 * math.pi * kc / n
    work = Work(np.empty((2, k, 2, n)), np.empty((2, n, 4)), np.empty((2, n, 4)), np.empty((2, n, 4)), cw,
                cw.astype(np.float32), np.empty((4, n), dtype=np.float32), np.empty((2 * k, n), dtype=np.float32),
                np.empty((3, 4, 2 * k, 2 * k)), np.empty((2, 4, 2 * k)), np.empty((npar, npar)), np.empty(npar),
                np.empty((npar, npar)), np.empty(npar), np.empty(k), np.empty((k, 2), dtype=np.complex128),
                np.empty((3, 4 * n), dtype=np.float32))
    for f in range(fit.nu.shape[0]):
        _refine_frame(codes, fit, steps, gate, kc, work, f)


@njit(**JIT)
def _refine_frame(codes, fit, steps, gate, kc, work, f):
    """:func:`refine` of frame ``f``."""
    a, b = codes.a[f], codes.b[f]
    nll_only = codes.kind == ONE_BIT and codes.lik == LOGISTIC  # a cheaper NLL alone (nll_frame)
    count = steps.levels.shape[1]
    cur = 0
    model(fit.nu[f], fit.amp[f], kc, work.w[0], work.mus[0])
    work.gs[0] = fit.g[f]
    work.hs[0] = fit.h[f]
    current = fit.sigma[f]
    fresh = True  # gs[cur], hs[cur] hold the derivatives at mus[cur] and the current level
    for s in range(count):
        level = steps.levels[f, s]
        if steps.adapt:
            level = max(level, wrong_rms(codes.kind, a, b, work.mus[cur]) / steps.wrong_per_sigma)
        if level != current or not fresh:
            fit.nll[f] = evaluate_frame(codes.kind, codes.lik, a, b, work.mus[cur], level, work.gs[cur], work.hs[cur],
                                        work.work)
            current = level
            fresh = True
        _gauss_newton(fit, f, work, cur)
        _candidate(fit, steps, gate, work, f)
        o = 1 - cur
        model(work.nu2, work.amp2, kc, work.w[o], work.mus[o])
        # the candidate's derivatives only when the next step is at this level (known
        # unless adapted) or this is the last step; else the NLL alone
        derivs = not nll_only or s == count - 1 or (not steps.adapt and steps.levels[f, s + 1] == current)
        if derivs:
            cand = evaluate_frame(codes.kind, codes.lik, a, b, work.mus[o], current, work.gs[o], work.hs[o], work.work)
        else:
            cand = nll_frame(a, b, work.mus[o], current, work.work)
        if cand <= fit.nll[f]:
            fresh = derivs
            fit.lm[f] = max(fit.lm[f] / 3.0, 1e-9)
            fit.nll[f] = cand
            fit.nu[f, :] = work.nu2
            fit.amp[f, :, :] = work.amp2
            cur = o
        else:
            fit.lm[f] = min(fit.lm[f] * 8.0, 1e9)
    fit.mu[f, :, :] = work.mus[cur]
    fit.g[f, :, :] = work.gs[cur]
    fit.h[f, :, :] = work.hs[cur]
    fit.sigma[f] = current


@njit(**JIT)
def _gauss_newton(fit, f, work, cur):
    """The damped Gauss--Newton step ``work.step`` of frame ``f`` from the current state ``cur``."""
    sums(work.w[cur], work.cw, work.cw32, work.gs[cur], work.hs[cur], work.ht, work.bw, work.gram, work.proj)
    normal_equations(fit.amp[f], work.gram, work.proj, work.hess, work.grad)
    hess, grad = work.hess, work.grad
    npar = grad.shape[0]
    dmax = 0.0
    for q in range(npar):
        dmax = max(dmax, hess[q, q])
    for q in range(npar):
        hess[q, q] += fit.lm[f] * hess[q, q] + 1e-9 * dmax + 1e-300
        grad[q] = -grad[q]
    solve(hess, grad, work.lw, work.step)


@njit(**JIT)
def _candidate(fit, steps, gate, work, f):
    """The candidate targets ``work.nu2``, ``work.amp2`` of frame ``f``: its targets moved by
    ``work.step`` (not the targets that are not live), the range step clipped to
    ``steps.max_range_step``, the amplitudes' to ``steps.amp_cap[f]``, ranges kept in the gate."""
    step = work.step
    for t in range(fit.nu.shape[1]):
        base = PARAMS * t
        if not fit.live[f, t]:
            for q in range(PARAMS):
                step[base + q] = 0.0
        dnu = min(max(step[base], -steps.max_range_step), steps.max_range_step)
        norm = 0.0
        for q in range(1, PARAMS):
            norm += step[base + q] ** 2
        norm = math.sqrt(norm)
        cut = min(1.0, steps.amp_cap[f] / max(norm, 1e-300))
        v = fit.nu[f, t] + dnu
        if gate.use:
            v = min(max(v, gate.lo), gate.hi)
        work.nu2[t] = v
        for p in range(2):
            work.amp2[t, p] = fit.amp[f, t, p] + complex(step[base + 1 + 2 * p] * cut, step[base + 2 + 2 * p] * cut)
