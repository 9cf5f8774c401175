"""Compiled (numba) detection and count test of :mod:`pipeline.dsp.cml_detect`, one frame at a
time inside the kernel (a frame costs the same in a batch of 1 or of 64). The numpy
functions of :mod:`pipeline.dsp.cml_detect` are the reference (tests/test_cml_kernels.py).

Layouts (one block of B frames, N samples a ramp, L = oversample N grid points, T targets
found so far): ``u`` (B, S, 2, L) complex (or on the coarse grid, L / ratio points: the fine
grid's peak and mean from it, :mod:`pipeline.dsp.cml_count_kernels`), the zero-padded
inverse FFTs of S residuals
(0: the linear residual ``Z - xi - model`` summed over the ramps, 1: the likelihood's
score) per antenna; ``y`` (B, N, 2) complex the linear residual; ``nu`` (B, T) ranges in
bins, ``live`` (B, T) bool; ``outside`` (L,) bool the grid points beyond the range gate.

Compiled on first use and cached on disk (``cache=True``), as :mod:`pipeline.dsp.cml_kernels`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from pipeline.dsp.cml_count_kernels import _parabola, coarse_energies, coarse_peak, gate_edge, gate_weights, guard, \
    open_sum, peak_range
from pipeline.dsp.cml_kernels import evaluate, models, refine
from pipeline.dsp.kernel_cache import drop_stale


@njit(cache=True, nogil=True)
def _energy(u, nu, live, oversample, guard_bins, energy, near):
    """Joint energy ``|U1|^2 + |U2|^2`` of ``u`` (2, L) into ``energy`` (L,), zero within
    ``guard_bins`` of the live targets ``nu`` (T,) (``near`` (L,): that mask), as
    :func:`pipeline.dsp.cml_detect._energy` (the same order of the sums)."""
    size = energy.shape[0]
    for i in range(size):
        a = u[0, i]
        b = u[1, i]
        energy[i] = (a.real * a.real + b.real * b.real) + (a.imag * a.imag + b.imag * b.imag)
        near[i] = False
    reach = int(math.ceil(guard_bins * oversample)) - 1
    for j in range(nu.shape[0]):
        c = int(np.rint(nu[j] * oversample))
        for d in range(-reach, reach + 1):
            near[(c + d) % size] = live[j]  # later targets overwrite, as put_along_axis
    for i in range(size):
        if near[i]:
            energy[i] = 0.0


@njit(cache=True, nogil=True)
def _peak_ratio(u, nu, live, oversample, guard_bins, outside, use_gate, energy, near) -> float:
    """Peak over mean of the joint energy beyond ``guard_bins`` of the targets and inside
    the gate (0 when the energy is 0 there)."""
    _energy(u, nu, live, oversample, guard_bins, energy, near)
    size = energy.shape[0]
    total = 0.0
    peak = 0.0
    cells = 0
    for i in range(size):
        if use_gate and outside[i]:
            energy[i] = 0.0
            near[i] = True
        total += energy[i]
        peak = max(peak, energy[i])
        if not near[i]:
            cells += 1
    mean = total / max(cells, 1)
    return peak / mean if mean > 0.0 else 0.0


@njit(cache=True, nogil=True)
def _peak(u, nu, live, oversample, guard_bins, outside, use_gate, gate_lo, gate_hi, energy, near) -> float:
    """Range (bins) of the peak of the joint energy (:func:`_parabola`), inside the gate (``use_gate``)."""
    _energy(u, nu, live, oversample, guard_bins, energy, near)
    size = energy.shape[0]
    best = 0
    top = -math.inf
    for i in range(size):
        v = -1.0 if use_gate and outside[i] else energy[i]  # -1: below any energy
        if v > top:
            top = v
            best = i
    left = energy[(best - 1) % size]
    centre = energy[best]
    right = energy[(best + 1) % size]
    return _parabola(best, left, centre, right, oversample, use_gate, gate_lo, gate_hi)


@njit(cache=True, nogil=True)
def _coarse_ratio(uc, x, n, nu, live, oversample, guard_bins, outside, use_gate, gate_edges, gate_w, inside, rho,
                  table, tables, coarse, energy, known, near, edge, seen, offsets, turned, cell, span, threshold):
    """:func:`_peak_ratio` from the coarse inverse FFT ``uc`` (2, Lc) of ``x`` (2, >= N):
    the mean by :func:`pipeline.dsp.cml_count_kernels.open_sum`, the peak by
    :func:`pipeline.dsp.cml_count_kernels.coarse_peak`, sought only as far as it decides
    ``ratio >= threshold`` (< 0: the ratio itself; else a ratio that reaches ``threshold``
    exactly when the ratio does). Returns the ratio and the peak's point; ``energy``,
    ``known``, ``near`` then hold the fine energies found and the guard."""
    total = coarse_energies(uc, table.shape[0], coarse, energy, known)
    reach = guard(nu, live, oversample, guard_bins, use_gate, gate_edges, near, edge)
    kept, cells = open_sum(coarse, total, tables, nu, oversample, reach, near, outside, use_gate, gate_w, inside, seen)
    mean = kept / max(cells, 1)
    bar = threshold * mean if threshold >= 0.0 and mean > 0.0 else -math.inf
    best, top = coarse_peak(x, n, coarse, energy, known, near, edge, outside, use_gate, rho, table, offsets, turned,
                            cell, span, bar, threshold >= 0.0)
    if threshold >= 0.0 and mean > 0.0 and top >= bar:  # decided: at the threshold even where top / mean rounds below
        return max(top / mean, threshold), best
    return (max(top, 0.0) / mean if mean > 0.0 else 0.0), best


@njit(cache=True, nogil=True)
def _coarse_range(uc, x, n, nu, live, oversample, guard_bins, outside, use_gate, gate_lo, gate_hi, gate_edges, rho,
                  table, coarse, energy, known, near, edge, offsets, turned, cell, span, prepared) -> float:
    """:func:`_peak` from the coarse inverse FFT ``uc`` (2, Lc) of ``x`` (2, >= N)
    (:func:`pipeline.dsp.cml_count_kernels.coarse_peak`); ``prepared``: ``coarse``,
    ``energy`` and ``known`` hold ``uc``'s already (:func:`_coarse_ratio`)."""
    if not prepared:
        coarse_energies(uc, table.shape[0], coarse, energy, known)
    guard(nu, live, oversample, guard_bins, use_gate, gate_edges, near, edge)
    best, _ = coarse_peak(x, n, coarse, energy, known, near, edge, outside, use_gate, rho, table, offsets, turned, cell,
                          span, -math.inf, False)
    return peak_range(x, n, best, oversample, table, near, energy, known, use_gate, gate_lo, gate_hi)


@njit(cache=True, nogil=True)
def detect(u, src, table, rho, tables, gate_w, inside, y, kc, ramps, nu, live, oversample, count_guard, sep_guard,
           outside, use_gate, gate_lo, gate_hi, count_sources, detect_source, threshold, active, stat, nu0,
           amp0) -> bool:
    """Per frame: the count test's statistic into ``stat`` (B,) (the smaller peak ratio of
    the first ``count_sources`` residuals of ``u``; 0 sources: left alone), with
    ``threshold`` >= 0 the count's decision (``active`` (B,) bool, updated in place: a frame
    stays active when its statistic reaches ``threshold``; the statistic is then only that
    decision: at or beyond ``threshold`` exactly when the exact one is, 0 in frames
    inactive already), the
    detected range into ``nu0`` (B,) (residual ``detect_source`` of ``u``; -1: ``nu0``
    given), and the least-squares amplitudes (B, 2) of one target at ``nu0`` in ``y`` into
    ``amp0``. Returns whether a frame is active (``threshold`` < 0: True); with none, the
    ranges and amplitudes are left alone. ``u`` coarser than ``oversample`` N points: the
    fine grid's peak and mean from it (:mod:`pipeline.dsp.cml_count_kernels`) with ``src``
    (B, S, 2, >= N) (the sources before their FFT), ``table`` (``oversample`` N,), ``rho``,
    ``tables`` (:func:`pipeline.dsp.cml_detect._run_tables`) and the gate's ``gate_w``,
    ``inside`` (:func:`pipeline.dsp.cml_count_kernels.gate_weights`); else those unused."""
    nb = u.shape[0]
    n = y.shape[1]
    size = oversample * n
    energy = np.empty(size)
    near = np.empty(size, dtype=np.bool_)
    on_coarse = u.shape[3] < size and (detect_source >= 0 or count_sources > 0)
    lc = u.shape[3] if on_coarse else 0
    known = np.empty(size if on_coarse else 0, dtype=np.bool_)
    seen = np.zeros(size if on_coarse else 0, dtype=np.bool_)
    coarse = np.empty(lc)
    span = np.empty(lc)
    edge = np.empty(lc, dtype=np.bool_)
    gate_edges = np.zeros(lc, dtype=np.bool_)
    if on_coarse and use_gate:
        gate_edge(outside, lc, gate_edges)
    half = (size // lc) // 2 if on_coarse else 0
    offsets = np.empty((2, 2 * half, n))  # the fine offsets' twiddles (_cell_energies)
    if on_coarse:
        for j in range(2 * half):
            d, k = (j - half + (j >= half)) % size, 0  # exp(2 pi i i d / L) = table[i d mod L]
            for i in range(n):
                offsets[0, j, i], offsets[1, j, i] = table[k].real, table[k].imag
                k = k + d - size if k + d >= size else k + d
    turned = np.empty((4, n))
    cell = np.empty(2 * half)
    pending = np.zeros(nb, dtype=np.bool_)
    any_active = threshold < 0.0
    decide = threshold >= 0.0
    for f in range(nb):
        prepared = False  # the fine energies of the detection's source found by the count test
        best = 0
        for step in range(count_sources):  # the detection's source last
            if decide and (not active[f] or (step > 0 and stat[f] < threshold)):
                break  # decided: inactive already, or a source's peak falls short
            s = step if detect_source < 0 or detect_source >= count_sources else \
                (step + detect_source + 1) % count_sources
            if on_coarse:
                r, best = _coarse_ratio(u[f, s], src[f, s], n, nu[f], live[f], oversample, count_guard, outside,
                                        use_gate, gate_edges, gate_w, inside, rho, table, tables, coarse, energy,
                                        known, near, edge, seen, offsets, turned, cell, span, threshold)
                prepared = s == detect_source
            else:
                r = _peak_ratio(u[f, s], nu[f], live[f], oversample, count_guard, outside, use_gate, energy, near)
            stat[f] = r if step == 0 else min(stat[f], r)
        if decide:
            active[f] = active[f] and stat[f] >= threshold
            any_active = any_active or active[f]
            if not active[f] and detect_source >= 0:  # its detection matters only if another frame goes on
                pending[f] = True
                continue
        if prepared and not decide and not live[f].any():  # no guard: the count test's peak is the detection's
            nu0[f] = peak_range(src[f, detect_source], n, best, oversample, table, near, energy, known, use_gate,
                                gate_lo, gate_hi)
        elif on_coarse and detect_source >= 0:
            nu0[f] = _coarse_range(u[f, detect_source], src[f, detect_source], n, nu[f], live[f], oversample,
                                   sep_guard, outside, use_gate, gate_lo, gate_hi, gate_edges, rho, table, coarse,
                                   energy, known, near, edge, offsets, turned, cell, span, prepared)
        elif detect_source >= 0:
            nu0[f] = _peak(u[f, detect_source], nu[f], live[f], oversample, sep_guard, outside, use_gate, gate_lo,
                           gate_hi, energy, near)
        _amplitude(y[f], nu0[f], kc, ramps, amp0[f])
    if not any_active:
        return False
    for f in range(nb):
        if pending[f]:
            if on_coarse:
                nu0[f] = _coarse_range(u[f, detect_source], src[f, detect_source], n, nu[f], live[f], oversample,
                                       sep_guard, outside, use_gate, gate_lo, gate_hi, gate_edges, rho, table, coarse,
                                       energy, known, near, edge, offsets, turned, cell, span, False)
            else:
                nu0[f] = _peak(u[f, detect_source], nu[f], live[f], oversample, sep_guard, outside, use_gate,
                               gate_lo, gate_hi, energy, near)
            _amplitude(y[f], nu0[f], kc, ramps, amp0[f])
    return True


@njit(cache=True, nogil=True, inline="always")
def _amplitude(y, nu0, kc, ramps, amp0):
    """Least-squares amplitudes ``amp0`` (2,) of one target at ``nu0`` bins in ``y`` (N, 2)."""
    n = y.shape[0]
    ph = 2.0 * math.pi * nu0 / n
    a1 = a2 = 0.0 + 0.0j
    w = complex(math.cos(ph * kc[0]), math.sin(ph * kc[0]))  # conj(exp(-i 2 pi kc nu / N)); kc in unit steps
    turn = complex(math.cos(ph), math.sin(ph))  # by a recurrence (relative error ~1e-14)
    for i in range(n):
        a1 += w * y[i, 0]
        a2 += w * y[i, 1]
        w *= turn
    scale = 1.0 / (ramps * n)
    amp0[0] = a1 * scale
    amp0[1] = a2 * scale

@njit(cache=True, nogil=True, error_model="numpy")
def result(nu, amp, live, y, kc0, ramps, range_res, carrier, wrap, cap, range_m, amp_out, stat, present):
    """:func:`pipeline.dsp.cml._result` per frame: the targets ``nu`` (B, T) bins, ``amp``
    (B, T, 2) (mid-sweep) and ``live`` (B, T) of the fit, ``y`` (B, N, 2) the residual summed
    over the ramps, ``carrier`` = 4 pi f0 / c (rad/m), ``wrap``: ranges modulo N (no gate),
    ``cap``: the statistic's cap, dB. Writes ``range_m`` (B, K) m, ``amp_out`` (B, K, 2),
    ``stat`` (B, K) dB and ``present`` (B, K), present targets first, strongest first."""
    nb, t = nu.shape
    k = range_m.shape[1]
    n = y.shape[1]
    power = np.empty(k)
    order = np.empty(k, dtype=np.int64)
    for f in range(nb):
        noise = 0.0
        for i in range(n):
            for p in range(2):
                v = y[f, i, p]
                noise += v.real * v.real + v.imag * v.imag
        noise /= float(n * ramps) ** 2
        for j in range(k):
            power[j] = 0.0
            if j < t:
                a1, a2 = amp[f, j, 0], amp[f, j, 1]
                power[j] = (a1.real * a1.real + a1.imag * a1.imag) + (a2.real * a2.real + a2.imag * a2.imag)
            # stable insertion: present first, then strongest first (as numpy's lexsort)
            alive = j < t and live[f, j]
            pos = j
            while pos > 0:
                o = order[pos - 1]
                o_alive = o < t and live[f, o]
                if o_alive > alive or (o_alive == alive and power[o] >= power[j]):
                    break
                order[pos] = o
                pos -= 1
            order[pos] = j
        for pos in range(k):
            j = order[pos]
            if j >= t:
                range_m[f, pos] = np.nan
                amp_out[f, pos, 0] = 0.0
                amp_out[f, pos, 1] = 0.0
                stat[f, pos] = np.nan
                present[f, pos] = False
                continue
            v = nu[f, j] % n if wrap else nu[f, j]
            r = v * range_res
            # a = mu at k = 0 over the carrier term there, exp(-i 4 pi f0 r / c)
            e = np.exp(complex(0.0, ((-2.0 * math.pi / n) * nu[f, j]) * kc0)) / np.exp(complex(0.0, -(carrier * r)))
            range_m[f, pos] = r
            amp_out[f, pos, 0] = amp[f, j, 0] * e
            amp_out[f, pos, 1] = amp[f, j, 1] * e
            ratio = power[j] / noise
            if ratio != ratio or ratio <= 0.0:
                db = -cap
            elif ratio == math.inf:
                db = cap
            else:
                db = min(max(10.0 * math.log10(ratio), -cap), cap)
            stat[f, pos] = db
            present[f, pos] = live[f, j]


# -- the codes' arrays and the residuals ------------------------------------------------------
@njit(cache=True, nogil=True, error_model="numpy")
def frame_faults(z, xi, delta, half) -> int:
    """What is wrong with quantized frames, as :func:`pipeline.dsp.cml._check` asks, in one
    pass: 1 ``z`` (B, J) float (the real parts of the values; J = 0 for codes) holds values
    that are not finite, else 2 the dither's ``xi`` (B, J') float does, else 3 a value is not
    ``delta[f] (q + 1/2)`` with q an integer in [-half, half) (to 1e-6 of delta); 0 none."""
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


@njit(cache=True, nogil=True, error_model="numpy")
def codes_arrays(z, from_codes, xi, delta, bits, ka, kb, folded):
    """:class:`pipeline.dsp.cml_fit._Codes`' kernel arrays of quantized frames in one pass.

    z : (B, R, N, 4) the quantizer's integer codes (``from_codes``) or the real parts of the
    values ``Z``; xi : (B, R, N, 4) float the dither's; delta : (B,). Writes ``ka``, ``kb``
    (B, R, N, 4) float32 (1 bit: the sign s and ``s xi``; b bits: the cell ``[lo, hi)`` of
    lambda) and ``folded`` (B, N, 4) float, ``Z - xi`` summed over the ramps."""
    nb, ramps, n = z.shape[0], z.shape[1], z.shape[2]
    half = 1 << (bits - 1)
    for f in range(nb):
        d = delta[f]
        for i in range(n):
            for j in range(4):
                folded[f, i, j] = 0.0
        for r in range(ramps):
            for i in range(n):
                for j in range(4):
                    x = xi[f, r, i, j]
                    if from_codes:
                        q = float(z[f, r, i, j]) - half
                        v = d * (q + 0.5)
                    else:
                        v = float(z[f, r, i, j])
                        q = np.rint(v / d - 0.5)  # v = (q + 1/2) delta
                    folded[f, i, j] += v - x
                    if bits == 1:
                        s = 1.0 if q >= 0.0 else -1.0
                        ka[f, r, i, j] = s
                        kb[f, r, i, j] = s * x
                    else:
                        lo = -math.inf if q <= -half else q * d
                        hi = math.inf if q >= half - 1 else (q + 1.0) * d
                        ka[f, r, i, j] = lo - x
                        kb[f, r, i, j] = hi - x


@njit(cache=True, nogil=True, error_model="numpy")
def sources(folded, mu, g, ramps, residual, score, y, buf):
    """The residuals detection back-projects: ``y`` (B, N, 4) the linear residual
    ``folded - ramps mu`` (folded, mu (B, N, 4)), and into ``buf`` (B, S, 2, L) complex,
    per antenna, its first N points: source 0 that residual (``residual``), then the
    likelihood's score ``-g`` (``score``; g (B, N, 4)). The points beyond N are left as
    they are (zeros: the FFT's padding)."""
    nb, n = mu.shape[0], mu.shape[1]
    for f in range(nb):
        for i in range(n):
            for j in range(4):
                y[f, i, j] = folded[f, i, j] - ramps * mu[f, i, j]
        s = 0
        if residual:
            for p in range(2):
                for i in range(n):
                    buf[f, s, p, i] = complex(y[f, i, 2 * p], y[f, i, 2 * p + 1])
            s += 1
        if score:
            for p in range(2):
                for i in range(n):
                    buf[f, s, p, i] = complex(-g[f, i, 2 * p], -g[f, i, 2 * p + 1])


@njit(cache=True, nogil=True)
def add_target(u, src, table, rho, tables, gate_w, inside, y, kc, ramps, nu, amp, live, oversample, count_guard,
               sep_guard, outside, use_gate, gate_lo, gate_hi, count_sources, detect_source, threshold, active, kind,
               lik, a, b, sigma, iters, amp_cap, max_range_step, mu, g, h):
    """One greedy stage of :func:`pipeline.dsp.cml._decode` in one call: :func:`detect` (the
    count test when ``threshold`` >= 0: ``active`` (B,) bool updated in place), the new
    target (amplitude 0 in inactive frames) appended to ``nu`` (B, T), ``amp``, ``live``, the
    model into ``mu`` (B, N, 4), then ``iters`` refinement steps at ``sigma`` (B,)
    (:func:`pipeline.dsp.cml_kernels.refine`, its first step evaluating the likelihood).
    Returns whether a frame is active, and the fit's ``nu``, ``amp``, ``live`` (B, T + 1),
    damping ``lm``, ``nll`` and level (B,); with no active frame the fit is unchanged."""
    nb, t = nu.shape
    stat = np.zeros(nb)
    nu0 = np.empty(nb)
    amp0 = np.empty((nb, 2), dtype=np.complex128)
    any_active = detect(u, src, table, rho, tables, gate_w, inside, y, kc, ramps, nu, live, oversample, count_guard,
                        sep_guard, outside, use_gate, gate_lo, gate_hi, count_sources, detect_source, threshold, active,
                        stat, nu0, amp0)
    if threshold < 0.0:
        any_active = False
        for f in range(nb):
            any_active = any_active or active[f]
    nu2 = np.empty((nb, t + 1))
    amp2 = np.empty((nb, t + 1, 2), dtype=np.complex128)
    live2 = np.empty((nb, t + 1), dtype=np.bool_)
    lm = np.full(nb, 1e-3)
    nll = np.zeros(nb)
    level = np.full(nb, np.nan)  # no level evaluated yet: refine's first step evaluates
    if not any_active:
        return False, nu2, amp2, live2, lm, nll, level
    for f in range(nb):
        for j in range(t):
            nu2[f, j] = nu[f, j]
            amp2[f, j, 0] = amp[f, j, 0]
            amp2[f, j, 1] = amp[f, j, 1]
            live2[f, j] = live[f, j]
        nu2[f, t] = nu0[f]
        amp2[f, t, 0] = amp0[f, 0] if active[f] else 0.0
        amp2[f, t, 1] = amp0[f, 1] if active[f] else 0.0
        live2[f, t] = active[f]
    models(nu2, amp2, kc, mu)
    if iters == 0:
        nll[:] = evaluate(kind, lik, a, b, mu, sigma, g, h)
        level[:] = sigma
        return True, nu2, amp2, live2, lm, nll, level
    levels = np.empty((nb, iters))
    for f in range(nb):
        levels[f, :] = sigma[f]
    refine(kind, lik, a, b, kc, nu2, amp2, live2, lm, levels, False, 1.0, amp_cap, gate_lo, gate_hi, use_gate,
           max_range_step, mu, g, h, nll, level)
    return True, nu2, amp2, live2, lm, nll, level


@njit(cache=True, nogil=True)
def finish(kind, lik, a, b, kc, nu, amp, live, lm, levels, adapt, wrong_per_sigma, amp_cap, gate_lo, gate_hi,
           use_gate, max_range_step, mu, g, h, nll, level, folded, ramps, range_res, carrier, wrap, cap, range_m,
           amp_out, stat, present):
    """The end of :func:`pipeline.dsp.cml._decode` in one call: the annealing's refinement
    steps at ``levels`` (B, S) (:func:`pipeline.dsp.cml_kernels.refine`, its arguments up to
    ``level``), the residual ``folded - ramps mu`` and :func:`result` (its arguments from
    ``range_res``)."""
    if levels.shape[1]:
        refine(kind, lik, a, b, kc, nu, amp, live, lm, levels, adapt, wrong_per_sigma, amp_cap, gate_lo, gate_hi,
               use_gate, max_range_step, mu, g, h, nll, level)
    nb, n = mu.shape[0], mu.shape[1]
    y = np.empty((nb, n, 2), dtype=np.complex128)
    for f in range(nb):
        for i in range(n):
            for p in range(2):
                y[f, i, p] = complex(folded[f, i, 2 * p] - ramps * mu[f, i, 2 * p],
                                     folded[f, i, 2 * p + 1] - ramps * mu[f, i, 2 * p + 1])
    result(nu, amp, live, y, kc[0], ramps, range_res, carrier, wrap, cap, range_m, amp_out, stat, present)


@njit(cache=True, nogil=True)
def warm(nu_all, live_all, targets, kc, ramps, folded, kind, lik, a, b, sigma, steps, levels, adapt, wrong_per_sigma,
         amp_cap, gate_lo, gate_hi, use_gate, max_range_step, range_res, carrier, wrap, cap, mu, g, h, range_m,
         amp_out, stat, present):
    """The warm start of :func:`pipeline.dsp.cml._refine_warm` in one call: the amplitudes of
    the first ``targets`` of ``nu_all`` (B, K) bins (``live_all``: given) one at a time in
    the residual of the model so far (as :func:`detect` with ``nu0`` given), ``steps``
    refinement steps at ``sigma`` (B,), the annealing's at ``levels`` (B, S) (``adapt``),
    then :func:`result`. Arguments as :func:`finish`'s; returns the fit's ``nu``, ``amp``,
    ``live`` (B, targets), ``lm``, ``nll`` and level (B,)."""
    nb, n = mu.shape[0], mu.shape[1]
    y = np.empty((nb, n, 2), dtype=np.complex128)
    none = np.empty((nb, 0, 2, 1), dtype=np.complex128)
    no_gate = np.zeros(1, dtype=np.bool_)
    no_table = np.empty(0, dtype=np.complex128)
    no_tables = np.empty((0, 0))
    no_weights = np.empty(0)
    no_active = np.ones(nb, dtype=np.bool_)
    stat0 = np.zeros(nb)
    amp0 = np.empty((nb, 2), dtype=np.complex128)
    amp = np.empty((nb, 0, 2), dtype=np.complex128)
    mu[:] = 0.0
    for t in range(targets):
        _residual_into(folded, mu, ramps, y)
        nu0 = nu_all[:, t].copy()
        detect(none, none, no_table, 0.0, no_tables, no_weights, 0, y, kc, ramps, np.ascontiguousarray(nu_all[:, :t]),
               np.ascontiguousarray(live_all[:, :t]), 1, 0.0, 0.0, no_gate, False, 0.0, 0.0, 0, -1, -1.0, no_active,
               stat0, nu0, amp0)
        amp2 = np.empty((nb, t + 1, 2), dtype=np.complex128)
        for f in range(nb):
            for j in range(t):
                amp2[f, j, 0] = amp[f, j, 0]
                amp2[f, j, 1] = amp[f, j, 1]
            amp2[f, t, 0] = amp0[f, 0] if live_all[f, t] else 0.0
            amp2[f, t, 1] = amp0[f, 1] if live_all[f, t] else 0.0
        amp = amp2
        models(np.ascontiguousarray(nu_all[:, :t + 1]), amp, kc, mu)
    nu = np.ascontiguousarray(nu_all[:, :targets])
    live = np.ascontiguousarray(live_all[:, :targets])
    lm = np.full(nb, 1e-3)
    nll = np.zeros(nb)
    level = np.full(nb, np.nan)  # no level evaluated yet: refine's first step evaluates
    if steps == 0:
        nll[:] = evaluate(kind, lik, a, b, mu, sigma, g, h)
        level[:] = sigma
    else:
        first = np.empty((nb, steps))
        for f in range(nb):
            first[f, :] = sigma[f]
        refine(kind, lik, a, b, kc, nu, amp, live, lm, first, False, wrong_per_sigma, amp_cap, gate_lo, gate_hi,
               use_gate, max_range_step, mu, g, h, nll, level)
    if levels.shape[1]:
        refine(kind, lik, a, b, kc, nu, amp, live, lm, levels, adapt, wrong_per_sigma, amp_cap, gate_lo, gate_hi,
               use_gate, max_range_step, mu, g, h, nll, level)
    _residual_into(folded, mu, ramps, y)
    result(nu, amp, live, y, kc[0], ramps, range_res, carrier, wrap, cap, range_m, amp_out, stat, present)
    return nu, amp, live, lm, nll, level


@njit(cache=True, nogil=True, inline="always")
def _residual_into(folded, mu, ramps, y):
    """``y`` (B, N, 2) complex = ``folded - ramps mu`` (both (B, N, 4) float)."""
    for f in range(mu.shape[0]):
        for i in range(mu.shape[1]):
            for p in range(2):
                y[f, i, p] = complex(folded[f, i, 2 * p] - ramps * mu[f, i, 2 * p],
                                     folded[f, i, 2 * p + 1] - ramps * mu[f, i, 2 * p + 1])


# numba keys a cached kernel on this file alone: the kernels that call cml_kernels' refine
# (and the likelihood it calls) or cml_count_kernels' search are dropped from the cache when
# those files change
drop_stale(__file__, (add_target, finish, warm, detect, _peak, _coarse_ratio, _coarse_range),
           ("cml_kernels.py", "cml_likelihood_kernels.py", "cml_count_kernels.py"))
