"""Compiled (numba) stages of cml, each one kernel call a block: the checks of quantized
frames and their codes' arrays, the residuals detection back-projects, a greedy stage
(count test, detection, amplitudes, refinement), the annealing with the result, and the warm
start with the result (layouts: :mod:`pipeline.dsp.cml.kernels.layout`)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from pipeline.dsp.cml.kernels.detect import amplitude, detect
from pipeline.dsp.cml.kernels.layout import JIT
from pipeline.dsp.cml.kernels.likelihood import evaluate
from pipeline.dsp.cml.kernels.model import centred, models
from pipeline.dsp.cml.kernels.refine import refine


# -- the codes' arrays and the residuals ------------------------------------------------------
@njit(**JIT, error_model="numpy")
def frame_faults(z, xi, delta, half) -> int:
    """What is wrong with quantized frames, in one pass: 1 ``z`` (B, J) float (the real parts
    of the values; J = 0 for codes) holds values that are not finite, else 2 the dither's
    ``xi`` (B, J') float does, else 3 a value is not ``delta[f] (q + 1/2)`` with q an integer
    in [-half, half) (to 1e-6 of delta); 0 none."""
    bad_z = bad_xi = off = False
    for f in range(z.shape[0]):
        d = delta[f]
        for i in range(z.shape[1]):
            v = z[f, i]
            if not math.isfinite(v):
                bad_z = True
            level = v / d - 0.5
            if not (abs(level - np.rint(level)) <= 1e-6 and level >= -half - 1e-6 and level <= half - 1 + 1e-6):
                off = True
    for f in range(xi.shape[0]):
        for i in range(xi.shape[1]):
            if not math.isfinite(xi[f, i]):
                bad_xi = True
    return 1 if bad_z else 2 if bad_xi else 3 if off else 0


@njit(**JIT, error_model="numpy")
def codes_arrays(z, from_codes, xi, delta, bits, ka, kb, data):
    """The codes' kernel arrays of quantized frames in one pass.

    z : (B, R, N, 4) the quantizer's integer codes (``from_codes``) or the real parts of the
    values ``Z``; xi : (B, R, N, 4) float the dither's; delta : (B,). Writes ``ka``, ``kb``
    (B, R, N, 4) float32 (1 bit: the sign s and ``s xi``; b bits: the cell ``[lo, hi)`` of
    lambda) and ``data`` (B, Rm, N, 4) float, ``Z - xi`` of each ramp (Rm = 1: summed over
    the ramps)."""
    nb, ramps, n = z.shape[0], z.shape[1], z.shape[2]
    rm = data.shape[1]
    half = 1 << (bits - 1)
    for f in range(nb):
        d = delta[f]
        for q in range(rm):
            for i in range(n):
                for j in range(4):
                    data[f, q, i, j] = 0.0
        for r in range(ramps):
            rq = r if rm > 1 else 0
            for i in range(n):
                for j in range(4):
                    x = xi[f, r, i, j]
                    if from_codes:
                        q = float(z[f, r, i, j]) - half
                        v = d * (q + 0.5)
                    else:
                        v = float(z[f, r, i, j])
                        q = np.rint(v / d - 0.5)  # v = (q + 1/2) delta
                    data[f, rq, i, j] += v - x
                    if bits == 1:
                        s = 1.0 if q >= 0.0 else -1.0
                        ka[f, r, i, j] = s
                        kb[f, r, i, j] = s * x
                    else:
                        lo = -math.inf if q <= -half else q * d
                        hi = math.inf if q >= half - 1 else (q + 1.0) * d
                        ka[f, r, i, j] = lo - x
                        kb[f, r, i, j] = hi - x


@njit(**JIT, error_model="numpy")
def sources(data, mu, g, ramps, residual, score, y, buf):
    """The residuals detection back-projects: ``y`` (B, Rm, N, 4) the linear residual of each
    model ramp ``data - (ramps / Rm) mu`` (data, mu (B, Rm, N, 4); Rm = 1: summed over the
    ``ramps`` ramps), and into ``buf`` (B, S, Rm, 2, L) complex, per model ramp and antenna,
    its first N points: source 0 that residual (``residual``), then the likelihood's score
    ``-g`` (``score``; g (B, Rm, N, 4)). The points beyond N are left as they are (zeros:
    the FFT's padding)."""
    nb, rm, n = mu.shape[0], mu.shape[1], mu.shape[2]
    scale = ramps / rm
    for f in range(nb):
        for q in range(rm):
            for i in range(n):
                for j in range(4):
                    y[f, q, i, j] = data[f, q, i, j] - scale * mu[f, q, i, j]
        s = 0
        if residual:
            for q in range(rm):
                for p in range(2):
                    for i in range(n):
                        buf[f, s, q, p, i] = complex(y[f, q, i, 2 * p], y[f, q, i, 2 * p + 1])
            s += 1
        if score:
            for q in range(rm):
                for p in range(2):
                    for i in range(n):
                        buf[f, s, q, p, i] = complex(-g[f, q, i, 2 * p], -g[f, q, i, 2 * p + 1])


# -- the greedy stage, the annealing, the warm start -------------------------------------------
@njit(**JIT, inline="always")
def add_target(sources, grid, gate, seed_gate, fit, codes, steps, sigma, decision, new) -> bool:
    """One greedy stage in one call: :func:`~pipeline.dsp.cml.kernels.detect.detect` (the count
    test when ``decision.threshold`` >= 0: ``decision.active`` (B,) bool updated in place),
    then into ``new`` (a :data:`~pipeline.dsp.cml.kernels.layout.Fit` of T + 1 targets, its
    ``lm`` 1e-3, ``nll`` 0 and ``sigma`` NaN: refine's first step evaluates) ``fit``'s targets
    and the new one (amplitude 0 in inactive frames), their model, then the refinement steps
    ``steps`` (levels: ``sigma`` (B,) repeated, :func:`~pipeline.dsp.cml.kernels.refine.refine`;
    none: the likelihood evaluated at ``sigma``). Returns whether a frame is active; with none,
    ``new`` is not to be used."""
    nb, t = fit.nu.shape
    any_active = detect(sources, grid, gate, seed_gate, fit.nu, fit.live, decision)
    active = decision.active
    if decision.threshold < 0.0:
        any_active = False
        for f in range(nb):
            any_active = any_active or active[f]
    if not any_active:
        return False
    _append(fit.nu, fit.phi, fit.amp, fit.live, active, decision.nu0, decision.phi0, decision.amp0, new.nu,
            new.phi, new.amp, new.live)
    models(new.nu, new.phi, new.amp, centred(new.mu.shape[2]), new.mu)
    if steps.levels.shape[1] == 0:
        new.nll[:] = evaluate(codes, new.mu, sigma, new.g, new.h)
        new.sigma[:] = sigma
    else:
        refine(codes, new, steps)
    return True


@njit(**JIT, inline="always")
def _append(nu, phi, amp, live, active, nu0, phi0, amp0, nu2, phi2, amp2, live2):
    """``nu2`` (B, T + 1), ``phi2``, ``amp2``, ``live2``: the targets ``nu`` (B, T), ``phi``,
    ``amp``, ``live`` and a new one at ``nu0`` (B,) of phase step ``phi0`` and amplitudes
    ``amp0`` (B, 2) in the ``active`` (B,) frames (else 0)."""
    nb, t = nu.shape
    for f in range(nb):
        for j in range(t):
            nu2[f, j] = nu[f, j]
            phi2[f, j] = phi[f, j]
            amp2[f, j, 0] = amp[f, j, 0]
            amp2[f, j, 1] = amp[f, j, 1]
            live2[f, j] = live[f, j]
        nu2[f, t] = nu0[f]
        phi2[f, t] = phi0[f] if active[f] else 0.0
        amp2[f, t, 0] = amp0[f, 0] if active[f] else 0.0
        amp2[f, t, 1] = amp0[f, 1] if active[f] else 0.0
        live2[f, t] = active[f]


@njit(**JIT, inline="always")
def finish(codes, fit, steps, report, out):
    """The end of a decode in one call: the annealing's refinement steps ``steps``
    (:func:`~pipeline.dsp.cml.kernels.refine.refine`), the residual ``data - (ramps / Rm) mu``
    and :func:`result` into ``out``."""
    if steps.levels.shape[1]:
        refine(codes, fit, steps)
    y = np.empty((fit.mu.shape[0], fit.mu.shape[1], fit.mu.shape[2], 2), dtype=np.complex128)
    _residual_into(codes.data, fit.mu, codes.a.shape[1], y)
    result(fit, y, codes.a.shape[1], report, out)


@njit(**JIT, inline="always")
def warm(codes, start, first, anneal, sigma, report, out, fit):
    """The warm start in one call: into ``fit`` (a :data:`~pipeline.dsp.cml.kernels.layout.Fit`
    of the T given targets, its ``lm`` 1e-3, ``nll`` 0, ``sigma`` NaN), the phase steps and
    amplitudes of the targets ``start`` = (``nu_all`` (B, K) bins, ``live_all`` (B, K) the ones
    given, first) one at a time in the residual of the model so far (as
    :func:`~pipeline.dsp.cml.kernels.detect.amplitude`), the refinement steps ``first`` (at
    ``sigma`` (B,); none: the likelihood evaluated there), those of the annealing ``anneal``,
    then :func:`result` into ``out``."""
    nu_all, live_all = start
    nu, phi, amp, live, mu, data = fit.nu, fit.phi, fit.amp, fit.live, fit.mu, codes.data
    nb, rm, n = mu.shape[0], mu.shape[1], mu.shape[2]
    ramps = codes.a.shape[1]
    kc = centred(n)
    mu[:] = 0.0
    y = np.empty((nb, rm, n, 2), dtype=np.complex128)
    amp0 = np.empty((nb, 2), dtype=np.complex128)
    vals = np.empty((rm, 2), dtype=np.complex128)
    for t in range(nu.shape[1]):
        _residual_into(data, mu, ramps, y)
        for f in range(nb):
            phi0 = amplitude(y[f], nu_all[f, t], ramps, amp0[f], vals)
            nu[f, t] = nu_all[f, t]
            live[f, t] = live_all[f, t]
            phi[f, t] = phi0 if live_all[f, t] else 0.0
            amp[f, t, 0] = amp0[f, 0] if live_all[f, t] else 0.0
            amp[f, t, 1] = amp0[f, 1] if live_all[f, t] else 0.0
        models(np.ascontiguousarray(nu[:, :t + 1]), np.ascontiguousarray(phi[:, :t + 1]),
               np.ascontiguousarray(amp[:, :t + 1]), kc, mu)
    if first.levels.shape[1] == 0:  # level NaN: refine's first step evaluates
        fit.nll[:] = evaluate(codes, mu, sigma, fit.g, fit.h)
        fit.sigma[:] = sigma
    else:
        refine(codes, fit, first)
    if anneal.levels.shape[1]:
        refine(codes, fit, anneal)
    _residual_into(data, mu, ramps, y)
    result(fit, y, ramps, report, out)


@njit(**JIT, inline="always")
def _residual_into(data, mu, ramps, y):
    """``y`` (B, Rm, N, 2) complex = ``data - (ramps / Rm) mu`` (both (B, Rm, N, 4) float)."""
    rm = mu.shape[1]
    scale = ramps / rm
    for f in range(mu.shape[0]):
        for q in range(rm):
            for i in range(mu.shape[2]):
                for p in range(2):
                    y[f, q, i, p] = complex(data[f, q, i, 2 * p] - scale * mu[f, q, i, 2 * p],
                                            data[f, q, i, 2 * p + 1] - scale * mu[f, q, i, 2 * p + 1])


# -- the result ----------------------------------------------------------------------------
@njit(**JIT, error_model="numpy")
def result(fit, y, ramps, report, out):
    """The result per frame: the targets of ``fit`` (``nu`` (B, T) bins, ``phi`` (B, T), ``amp``
    (B, T, 2) mid-sweep and mid-frame, ``live``), ``y`` (B, Rm, N, 2) the residual of each
    model ramp (Rm = 1: summed over the ``ramps`` ramps). Writes ``out``
    (:data:`~pipeline.dsp.cml.kernels.layout.Targets`): ranges (B, K) m (modulo N bins),
    amplitudes (B, K, 2) of the model, the statistic (B, K) dB (capped at ``report.cap``),
    ``present`` (live and inside the gate, ``report``), and the phase steps in (-pi, pi] (the
    amplitudes turned to match: with an even Rm a turn of 2 pi of phi turns them by pi; NaN
    with Rm = 1, the static model), present targets first, strongest first (T > K: the first
    K of them)."""
    nu, phi, amp, live = fit.nu, fit.phi, fit.amp, fit.live
    range_m, amp_out, stat, present, phi_out = out
    (nb, t), k = nu.shape, range_m.shape[1]
    rm, n = y.shape[1], y.shape[2]
    slots = max(k, t)
    power = np.empty(slots)
    order = np.empty(slots, dtype=np.int64)
    shown = np.empty(t, dtype=np.bool_)
    for f in range(nb):
        noise = 0.0
        for q in range(rm):
            for i in range(n):
                for p in range(2):
                    v = y[f, q, i, p]
                    noise += v.real * v.real + v.imag * v.imag
        noise /= float(n * ramps) ** 2
        for j in range(t):
            v = nu[f, j] % n
            shown[j] = live[f, j] and (not report.use or (v >= report.lo and v <= report.hi))
        _order(amp[f], shown, power, order)
        for pos in range(k):
            j = order[pos]
            if j >= t:
                range_m[f, pos] = np.nan
                amp_out[f, pos, 0] = 0.0
                amp_out[f, pos, 1] = 0.0
                stat[f, pos] = np.nan
                present[f, pos] = False
                phi_out[f, pos] = np.nan
                continue
            r, e, db = _target(nu[f, j], n, power[j] / noise, report)
            turns = np.rint(phi[f, j] / (2.0 * math.pi)) if rm > 1 else 0.0
            if rm % 2 == 0 and turns % 2.0 != 0.0:  # exp(i c_r 2 pi) = -1 for every ramp
                e = -e
            range_m[f, pos] = r
            amp_out[f, pos, 0] = amp[f, j, 0] * e
            amp_out[f, pos, 1] = amp[f, j, 1] * e
            stat[f, pos] = db
            present[f, pos] = shown[j]
            phi_out[f, pos] = phi[f, j] - 2.0 * math.pi * turns if rm > 1 else np.nan


@njit(**JIT, inline="always")
def _order(amp, live, power, order):
    """``order`` (S,), S >= T: the targets present (``live`` (T,)) first, then strongest first
    (a stable insertion, as numpy's lexsort) by their joint power into ``power`` (S,) (0 past
    the T targets)."""
    t = amp.shape[0]
    for j in range(order.shape[0]):
        power[j] = 0.0
        if j < t:
            a1, a2 = amp[j, 0], amp[j, 1]
            power[j] = (a1.real * a1.real + a1.imag * a1.imag) + (a2.real * a2.real + a2.imag * a2.imag)
        alive = j < t and live[j]
        pos = j
        while pos > 0:
            o = order[pos - 1]
            o_alive = o < t and live[o]
            if o_alive > alive or (o_alive == alive and power[o] >= power[j]):
                break
            order[pos] = o
            pos -= 1
        order[pos] = j


@njit(**JIT, error_model="numpy", inline="always")
def _target(nu, n, ratio, report):
    """A target at ``nu`` bins (N = ``n``) of joint power ``ratio`` times the residual's mean
    per bin: its range (m), the factor from its mid-sweep amplitudes to the model's and its
    statistic (dB)."""
    kc0 = 0.0 - (n - 1) / 2.0  # the first sample from the middle of the ramp
    r = (nu % n) * report.range_res
    # a = mu at k = 0 over the carrier term there, exp(-i 4 pi f0 r / c)
    e = np.exp(complex(0.0, ((-2.0 * math.pi / n) * nu) * kc0)) / np.exp(complex(0.0, -(report.carrier * r)))
    if ratio != ratio or ratio <= 0.0:
        db = -report.cap
    elif ratio == math.inf:
        db = report.cap
    else:
        db = min(max(10.0 * math.log10(ratio), -report.cap), report.cap)
    return r, e, db
