"""Compiled (numba) detection and count test of cml, one frame at a time inside the kernel (a
frame costs the same in a batch of 1 or of 64): the peak over mean of the joint energy of a
residual's back projection (the count test), the peak's range (detection) and a new target's
phase step between ramps and least-squares amplitudes. With a phase step (Rm > 1 model
ramps) the energy at a range is the peak over the phase step and its mean the total over the
ramps (:func:`pipeline.dsp.cml.kernels.doppler.doppler`). On a coarse inverse FFT the fine
grid's peak and mean come from :mod:`pipeline.dsp.cml.kernels.search`; else from the fine FFT directly (layouts:
:mod:`pipeline.dsp.cml.kernels.layout`)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from pipeline.dsp.cml.kernels.layout import JIT, Scratch
from pipeline.dsp.cml.kernels.doppler import doppler, doppler_phase
from pipeline.dsp.cml.kernels.search import coarse_energies, coarse_peak, guard, open_sum, parabola, peak_range, steer


@njit(**JIT, inline="always")
def _energy(u, nu, live, oversample, guard_bins, energy, near, totals, vals):
    """Peak energy (:func:`~pipeline.dsp.cml.kernels.doppler.doppler`) of ``u`` (Rm, 2, L) into
    ``energy`` (L,) and the total into ``totals`` (L,), both zero within ``guard_bins`` of the
    live targets ``nu`` (T,) (``near`` (L,): that mask), as the numpy reference's (the same
    order of the sums; ``vals`` (Rm, 2): work)."""
    size = energy.shape[0]
    rm = u.shape[0]
    for i in range(size):
        for r in range(rm):
            vals[r, 0] = u[r, 0, i]
            vals[r, 1] = u[r, 1, i]
        totals[i], energy[i] = doppler(vals, rm)
        near[i] = False
    reach = int(math.ceil(guard_bins * oversample)) - 1
    for j in range(nu.shape[0]):
        c = int(np.rint(nu[j] * oversample))
        for d in range(-reach, reach + 1):
            near[(c + d) % size] = live[j]  # later targets overwrite, as put_along_axis
    for i in range(size):
        if near[i]:
            energy[i] = 0.0
            totals[i] = 0.0


@njit(**JIT, inline="always")
def peak_ratio(u, nu, live, oversample, guard_bins, gate, s, floor) -> float:
    """Peak over mean of the joint energy of ``u`` (Rm, 2, L) beyond ``guard_bins`` of the
    targets and inside the gate (0 when the energy is 0 there): the peak energy's largest over
    the totals' mean, the mean not below ``floor``; ``s``: a
    :data:`~pipeline.dsp.cml.kernels.layout.Scratch` (its ``energy``, ``near``, ``totals``,
    ``vals``)."""
    energy, near, totals, use, outside = s.energy, s.near, s.totals, gate.use, gate.outside
    _energy(u, nu, live, oversample, guard_bins, energy, near, totals, s.vals)
    size = energy.shape[0]
    total = 0.0
    peak = 0.0
    cells = 0
    for i in range(size):
        if use and outside[i]:
            energy[i] = 0.0
            totals[i] = 0.0
            near[i] = True
        total += totals[i]
        peak = max(peak, energy[i])
        if not near[i]:
            cells += 1
    mean = max(total / max(cells, 1), floor)
    return peak / mean if mean > 0.0 else 0.0


@njit(**JIT, inline="always")
def peak(u, nu, live, oversample, guard_bins, gate, s) -> float:
    """Range (bins) of the peak of the joint energy of ``u`` (Rm, 2, L) beyond ``guard_bins``
    of the targets, refined by a parabola, inside the gate (``gate.use``)."""
    energy, use, outside = s.energy, gate.use, gate.outside
    _energy(u, nu, live, oversample, guard_bins, energy, s.near, s.totals, s.vals)
    size = energy.shape[0]
    best = 0
    top = -math.inf
    for i in range(size):
        v = -1.0 if use and outside[i] else energy[i]  # -1: below any energy
        if v > top:
            top = v
            best = i
    left = energy[(best - 1) % size]
    centre = energy[best]
    right = energy[(best + 1) % size]
    return parabola(best, left, centre, right, oversample, gate)


@njit(**JIT, inline="always")
def coarse_ratio(uc, x, n, nu, live, grid, gate, s, threshold, floor):
    """:func:`peak_ratio` (its mean not below ``floor``) from the coarse inverse FFT ``uc``
    (Rm, 2, Lc) of ``x`` (Rm, 2, >= N): the
    mean by :func:`~pipeline.dsp.cml.kernels.search.open_sum`, the peak by
    :func:`~pipeline.dsp.cml.kernels.search.coarse_peak`, sought only as far as it decides
    ``ratio >= threshold`` (< 0: the ratio itself; else a ratio that reaches ``threshold``
    exactly when the ratio does). Returns the ratio and the peak's point; ``s.energy``,
    ``s.known``, ``s.near`` then hold the fine energies found and the guard."""
    total = coarse_energies(uc, grid.table.shape[0], s)
    reach = guard(nu, live, grid.oversample, grid.count_guard, gate, s)
    kept, cells = open_sum(total, nu, reach, grid, gate, s)
    mean = max(kept / max(cells, 1), floor)
    bar = threshold * mean if threshold >= 0.0 and mean > 0.0 else -math.inf
    best, top = coarse_peak(steer(uc, x, n, gate, s), n, grid, gate, s, bar, threshold >= 0.0)
    if threshold >= 0.0 and mean > 0.0 and top >= bar:  # decided: at the threshold even where top / mean rounds below
        return max(top / mean, threshold), best
    return (max(top, 0.0) / mean if mean > 0.0 else 0.0), best


@njit(**JIT, inline="always")
def coarse_range(uc, x, n, nu, live, grid, gate, s, prepared) -> float:
    """:func:`peak` from the coarse inverse FFT ``uc`` (Rm, 2, Lc) of ``x`` (Rm, 2, >= N)
    (:func:`~pipeline.dsp.cml.kernels.search.coarse_peak`), detection's guard; ``prepared``:
    ``s.coarse``, ``s.peaks``, ``s.energy`` and ``s.known`` hold ``uc``'s already (:func:`coarse_ratio`)."""
    if not prepared:
        coarse_energies(uc, grid.table.shape[0], s)
    guard(nu, live, grid.oversample, grid.sep_guard, gate, s)
    xs = steer(uc, x, n, gate, s)
    best, _ = coarse_peak(xs, n, grid, gate, s, -math.inf, False)
    return peak_range(xs, n, best, grid, gate, s)


@njit(**JIT)
def scratch(n, size, lc, table, rm):
    """The work arrays of a search of L = ``size`` fine points (:data:`~pipeline.dsp.cml.kernels.layout.Scratch`),
    on a coarse grid of ``lc`` points (0: none) with the fine grid's twiddles ``table`` (L,),
    of ``rm`` model ramps."""
    known = np.empty(size if lc else 0, dtype=np.bool_)
    seen = np.zeros(size if lc else 0, dtype=np.bool_)
    half = (size // lc) // 2 if lc else 0
    offsets = np.empty((2, 2 * half, n))  # the fine offsets' twiddles (_cell_energies)
    for j in range(2 * half):
        d, k = (j - half + (j >= half)) % size, 0  # exp(2 pi i i d / L) = table[i d mod L]
        for i in range(n):
            offsets[0, j, i], offsets[1, j, i] = table[k].real, table[k].imag
            k = k + d - size if k + d >= size else k + d
    return Scratch(np.empty(size), known, np.empty(size, dtype=np.bool_), seen, np.empty(lc), np.empty(lc),
                   np.empty(lc), np.empty(lc, dtype=np.bool_), offsets, np.empty((4, n)), np.empty(2 * half),
                   np.empty((rm, 2), dtype=np.complex128), np.empty(0 if lc else size), np.empty(lc),
                   np.empty((1, 2, n), dtype=np.complex128), np.full(1, np.nan), np.empty(rm, dtype=np.complex128),
                   np.empty((2, lc if rm == 2 else 0)))


@njit(**JIT)
def detect(sources, grid, gate, seed_gate, nu, live, decision) -> bool:
    """Per frame: the count test's statistic into ``decision.stat`` (B,) (the smaller peak
    ratio of the first ``sources.count_sources`` residuals; 0 sources: left alone), with
    ``decision.threshold`` >= 0 the count's decision (``decision.active`` (B,) bool, updated
    in place: a frame stays active when its statistic reaches the threshold; the statistic is
    then only that decision: at or beyond it exactly when the exact one is, 0 in frames
    inactive already), the detected range into ``decision.nu0`` (B,) (residual
    ``sources.detect_source``; -1: ``nu0`` given), and the phase step and least-squares
    amplitudes (B, 2) of one target at ``nu0`` in ``sources.y`` into ``decision.phi0``,
    ``decision.amp0``; ``nu`` (B, T) bins and ``live`` (B, T): the targets found; the count
    test looks inside ``gate``, detection inside ``seed_gate`` (the whole axis: a range gate
    bounds what is reported, not what is modelled, :class:`pipeline.dsp.cml.grid.SearchGrid`).
    Returns whether a frame is active (no threshold:
    True); with none, the ranges and amplitudes are left alone. ``sources.u`` coarser than
    ``grid.oversample`` N points: the fine grid's peak and mean from it
    (:mod:`pipeline.dsp.cml.kernels.search`)."""
    nb, rm, n = sources.y.shape[0], sources.y.shape[1], sources.y.shape[2]
    size = grid.oversample * n
    on_coarse = sources.u.shape[4] < size and (sources.detect_source >= 0 or sources.count_sources > 0)
    s = scratch(n, size, sources.u.shape[4] if on_coarse else 0, grid.table, rm)
    pending = np.zeros(nb, dtype=np.bool_)
    any_active = decision.threshold < 0.0
    for f in range(nb):
        prepared, best = _count(sources, grid, gate, nu[f], live[f], decision, s, on_coarse, f)
        if decision.threshold >= 0.0:
            decision.active[f] = decision.active[f] and decision.stat[f] >= decision.threshold
            any_active = any_active or decision.active[f]
            if not decision.active[f] and sources.detect_source >= 0:  # detected only if another frame goes on
                pending[f] = True
                continue
        _detect_frame(sources, grid, gate, seed_gate, nu[f], live[f], decision, s, on_coarse, f, prepared, best)
    if not any_active:
        return False
    for f in range(nb):
        if pending[f]:
            _detect_frame(sources, grid, gate, seed_gate, nu[f], live[f], decision, s, on_coarse, f, False, 0)
    return True


@njit(**JIT, inline="always")
def _count(sources, grid, gate, nu, live, decision, s, on_coarse, f):
    """The count test's statistic of frame ``f`` into ``decision.stat[f]``, the detection's
    source last; returns whether ``s`` then holds the detection source's fine energies and
    its peak's point."""
    prepared = False  # the fine energies of the detection's source found by the count test
    best = 0
    count, det = sources.count_sources, sources.detect_source
    n = sources.y.shape[2]
    decide = decision.threshold >= 0.0
    for step in range(count):
        if decide and (not decision.active[f] or (step > 0 and decision.stat[f] < decision.threshold)):
            break  # decided: inactive already, or a source's peak falls short
        src = step if det < 0 or det >= count else (step + det + 1) % count
        if on_coarse:
            r, best = coarse_ratio(sources.u[f, src], sources.src[f, src], n, nu, live, grid, gate, s,
                                   decision.threshold, decision.floor[f, src])
            prepared = src == det
        else:
            r = peak_ratio(sources.u[f, src], nu, live, grid.oversample, grid.count_guard, gate, s, decision.floor[f, src])
        decision.stat[f] = r if step == 0 else min(decision.stat[f], r)
    return prepared, best


@njit(**JIT)
def _detect_frame(sources, grid, gate, seed_gate, nu, live, decision, s, on_coarse, f, prepared, best):
    """Frame ``f``'s detected range (inside ``seed_gate``) into ``decision.nu0[f]`` (unless
    given), its phase step and amplitudes into ``decision.phi0[f]``, ``decision.amp0[f]``;
    ``prepared``, ``best``: as :func:`_count` returns (``gate``: the count test's)."""
    det = sources.detect_source
    n = sources.y.shape[2]
    if prepared and decision.threshold < 0.0 and not live.any() and not gate.use:  # no guard, one search
        x = s.steered if sources.src.shape[2] > 1 else sources.src[f, det]  # the channel searched
        decision.nu0[f] = peak_range(x, n, best, grid, seed_gate, s)
    elif on_coarse and det >= 0:
        decision.nu0[f] = coarse_range(sources.u[f, det], sources.src[f, det], n, nu, live, grid, seed_gate, s,
                                       prepared)
    elif det >= 0:
        decision.nu0[f] = peak(sources.u[f, det], nu, live, grid.oversample, grid.sep_guard, seed_gate, s)
    decision.phi0[f] = amplitude(sources.y[f], decision.nu0[f], sources.ramps, decision.amp0[f], s.vals)


@njit(**JIT, inline="always")
def amplitude(y, nu0, ramps, amp0, vals) -> float:
    """The phase step (rad, returned) and least-squares amplitudes ``amp0`` (2,) of one target
    at ``nu0`` bins in ``y`` (Rm, N, 2), the residual of each model ramp (Rm = 1: summed over
    ``ramps`` ramps): each ramp's matched filter into ``vals`` (Rm, 2) (work), the phase step
    at its peak (:func:`~pipeline.dsp.cml.kernels.doppler.doppler_phase`), then the ramps
    turned back by it and averaged (amplitudes at the frame's middle)."""
    rm, n = y.shape[0], y.shape[1]
    ph = 2.0 * math.pi * nu0 / n
    kc0 = 0.0 - (n - 1) / 2.0  # the first sample from the middle of the ramp
    for r in range(rm):
        a1 = a2 = 0.0 + 0.0j
        w = complex(math.cos(ph * kc0), math.sin(ph * kc0))  # conj(exp(-i 2 pi kc nu / N)); kc in unit steps
        turn = complex(math.cos(ph), math.sin(ph))  # by a recurrence (relative error ~1e-14)
        for i in range(n):
            a1 += w * y[r, i, 0]
            a2 += w * y[r, i, 1]
            w *= turn
        vals[r, 0] = a1
        vals[r, 1] = a2
    if rm == 1:
        scale = 1.0 / (ramps * n)
        amp0[0] = vals[0, 0] * scale
        amp0[1] = vals[0, 1] * scale
        return 0.0
    phi = doppler_phase(vals, rm)
    a1 = a2 = 0.0 + 0.0j
    for r in range(rm):
        c = r - (rm - 1) / 2.0
        back = complex(math.cos(c * phi), -math.sin(c * phi))
        a1 += back * vals[r, 0]
        a2 += back * vals[r, 1]
    scale = 1.0 / (rm * n)
    amp0[0] = a1 * scale
    amp0[1] = a2 * scale
    return phi
