"""Compiled (numba) search of the oversampled range grid from a coarser inverse FFT, for
detection and the count test (:mod:`pipeline.dsp.cml.kernels.detect`): the peak of the joint
energy (detection, and the count test's numerator) and the mean of that energy over the
points not masked (the count test's denominator), without the fine grid's FFT: the mean
exactly the fine grid's (to rounding), the peak the fine grid's by a bound (Riesz) at a
maximum and every cell by a masked point summed, measured against the full grid
(tests/test_cml_count.py).

Grids: the fine one of L = ``oversample`` N points (``grid.table`` (L,) its twiddles
``exp(2 pi i k / L)``), the coarse one of Lc = L / ``ratio`` points, ``uc`` (Rm, 2, Lc) the
zero-padded inverse FFT per model ramp and antenna of ``x`` (Rm, 2, >= N) (its first N
points). Energies in the fine FFT's scale (``|ifft(x, L)|^2`` summed over the antennas).

With a phase step between ramps (Rm > 1 model ramps, back projections ``U_r`` per ramp r
and antenna) a point has a **total** ``sum_r |U_r|^2`` (the mean's: the energy's mean over
the phase step) and the energy at a phase step phi, ``E_phi = sum_p |sum_r exp(-i c_r phi)
U_rp|^2`` (:func:`doppler`: its peak over phi). The search over range then runs on one
**channel**: the residual steered to the phase step phi* of the best coarse point (the
largest peak over phi among the coarse points not masked, :func:`steer`), so that the fine
grid's peak is that of ``E_phi*`` (the energy of a residual of N points: Riesz's bound
below holds) at the cost of the static search. One ramp (the static model): the channel is
the residual itself. The work arrays of a search are a
:data:`~pipeline.dsp.cml.kernels.layout.Scratch` ``s``: ``s.near`` (L,) bool within the
guard of the targets found, ``s.energy`` (L,) the channel's fine energies found
(``s.known``), ``s.coarse`` (Lc,) the coarse totals, ``s.peaks`` (Lc,) the coarse peaks over
phi, ``s.chan`` (Lc,) the channel's coarse energies, ``s.steered`` (1, 2, N) the steered
residual and ``s.phis`` (1,) its phase step (NaN: none yet), ``s.cross`` (2, Lc) two ramps'
cross term (:func:`two_ramps`, the channel's energies from it); ``gate.outside`` (L,) bool:
beyond the range gate."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from pipeline.dsp.cml.kernels.doppler import STEER_GAIN, doppler, doppler_phase, static_energy, two_ramps
from pipeline.dsp.cml.kernels.layout import FAST, JIT


@njit(**JIT, inline="always")
def parabola(best, left, centre, right, oversample, gate) -> float:
    """Range (bins) of grid point ``best`` refined by a parabola through its energy and its
    neighbours', in the gate (``gate.use``)."""
    curv = left - 2.0 * centre + right
    off = 0.5 * (left - right) / curv if curv < 0.0 else 0.0
    nu0 = (best + min(max(off, -0.5), 0.5)) / oversample
    if gate.use:
        nu0 = min(max(nu0, gate.lo), gate.hi)
    return nu0


@njit(**JIT, inline="always")
def fine_energy(x, n, p, table, vals):
    """Joint energy at point ``p`` of the inverse FFT of ``x`` (Rm, 2, >= N) zero-padded to L
    = ``table.shape[0]`` points (its first ``n`` points; ``table`` (L,) ``exp(2 pi i k / L)``):
    ``U_r = (1 / L) sum_i x[r, :, i] exp(2 pi i i p / L)`` summed directly; one ramp (a
    channel) ``|U1|^2 + |U2|^2``, more the peak over the phase step (:func:`doppler`;
    ``vals`` (Rm, 2): work)."""
    size = table.shape[0]
    rm = x.shape[0]
    inv = 1.0 / size  # as the FFT's, before squaring
    for r in range(rm):
        ar = ai = br = bi = 0.0
        k = 0
        for i in range(n):
            w = table[k]
            a = x[r, 0, i]
            b = x[r, 1, i]
            ar += a.real * w.real - a.imag * w.imag
            ai += a.real * w.imag + a.imag * w.real
            br += b.real * w.real - b.imag * w.imag
            bi += b.real * w.imag + b.imag * w.real
            k += p
            if k >= size:
                k -= size
        ar, ai, br, bi = ar * inv, ai * inv, br * inv, bi * inv
        if rm == 1:
            return (ar * ar + br * br) + (ai * ai + bi * bi)
        vals[r, 0] = complex(ar, ai)
        vals[r, 1] = complex(br, bi)
    return doppler(vals, rm)[1]


@njit(**JIT, inline="always")
def _fine_value(x, n, p, table, near, energy, known, vals) -> float:
    """The masked fine peak energy at ``p`` (0 within the guard ``near``), computed once
    (:func:`fine_energy`) and kept in ``energy`` (``known``). (The kernels' hot loops take
    arrays, not the namedtuples holding them: a field read from a namedtuple is a reference
    counted each time, measured 10-15 % of the search.)"""
    if near[p]:
        return 0.0
    if not known[p]:
        energy[p] = fine_energy(x, n, p, table, vals)
        known[p] = True
    return energy[p]


@njit(**FAST)
def _cell_energies(x, n, s, table, offsets, v, out):
    """:func:`fine_energy` of a channel ``x`` (1, 2, >= N) at the fine points ``s + d`` for
    the offsets ``d`` of ``offsets`` (2, D, N) (real and imaginary parts of ``exp(2 pi i i d
    / L)``) into ``out`` (D,), in one pass: ``x`` turned by the twiddles of point ``s`` into
    ``v`` (4, N) (work), then one vectorized sum a point."""
    size = table.shape[0]
    k = 0
    for i in range(n):
        w = table[k]
        a = x[0, 0, i]
        b = x[0, 1, i]
        v[0, i], v[1, i] = a.real * w.real - a.imag * w.imag, a.real * w.imag + a.imag * w.real
        v[2, i], v[3, i] = b.real * w.real - b.imag * w.imag, b.real * w.imag + b.imag * w.real
        k += s
        if k >= size:
            k -= size
    inv = 1.0 / size
    for j in range(offsets.shape[1]):
        dr, di = offsets[0, j], offsets[1, j]
        ar = ai = br = bi = 0.0
        for i in range(n):
            ar += v[0, i] * dr[i] - v[1, i] * di[i]
            ai += v[0, i] * di[i] + v[1, i] * dr[i]
            br += v[2, i] * dr[i] - v[3, i] * di[i]
            bi += v[2, i] * di[i] + v[3, i] * dr[i]
        ar, ai, br, bi = ar * inv, ai * inv, br * inv, bi * inv
        out[j] = (ar * ar + br * br) + (ai * ai + bi * bi)


@njit(**JIT, inline="always")
def _open_cell(c, ratio, half, size, use, outside) -> bool:
    """Whether the fine points within ``half`` of coarse point ``c`` hold one inside the gate
    (``use``: a gate, ``outside`` (L,) the points beyond it)."""
    for d in range(-half, half + 1):
        if not use or not outside[(c * ratio + d) % size]:
            return True
    return False


@njit(**JIT, inline="always")
def _mark_edge(lo, hi, ratio, lc, edge):
    """``edge[c]`` = True for the coarse points ``c`` within ``ratio`` fine points of the
    fine points ``lo..hi`` (masked ones), modulo ``lc``."""
    for c in range(-((ratio - lo) // ratio), (hi + ratio) // ratio + 1):  # ceil((lo - ratio) / ratio) ...
        edge[c % lc] = True


@njit(**JIT)
def gate_edge(outside, lc, edge):
    """``edge`` (Lc,) bool: the coarse points within a coarse step of a point beyond the gate
    (``outside`` (L,)), as :func:`guard` marks them."""
    size = outside.shape[0]
    ratio = size // lc
    edge[:] = False
    for i in range(size):
        if outside[i] and not outside[i - 1]:  # a run of points beyond the gate (wrapping)
            e = i
            while e + 1 < i + size and outside[(e + 1) % size]:
                e += 1
            _mark_edge(i, e, ratio, lc, edge)


@njit(**JIT, inline="always")
def coarse_energies(uc, size, s) -> float:
    """The energies of the coarse inverse FFT ``uc`` (Rm, 2, Lc) in the fine FFT's scale (L =
    ``size`` points): the totals into ``s.coarse`` (Lc,) and the peaks over the phase step
    (:func:`doppler`) into ``s.peaks`` (Lc,); with one ramp also the channel's (the same)
    into ``s.chan`` and into ``s.energy`` (L,) at the fine points it samples (``s.known``
    (L,) then True there only; with more, :func:`steer` fills them). Returns the totals' sum
    over the Lc points."""
    coarse, peaks, chan, energy, known, vals = s.coarse, s.peaks, s.chan, s.energy, s.known, s.vals
    rm, lc = uc.shape[0], uc.shape[2]
    ratio = size // lc
    s.phis[0] = np.nan
    sc = lc / size  # the coarse FFT's 1 / Lc to the fine one's 1 / L
    if rm == 1:  # the channel is the residual: its energies, as they are
        known[:] = False
        for c in range(lc):
            a = uc[0, 0, c] * sc
            b = uc[0, 1, c] * sc
            coarse[c] = (a.real * a.real + b.real * b.real) + (a.imag * a.imag + b.imag * b.imag)
        for c in range(lc):
            peaks[c] = chan[c] = energy[c * ratio] = coarse[c]
            known[c * ratio] = True
        return _sum(coarse)
    if rm == 2:
        two_ramps(uc, sc, coarse, peaks, s.cross)
    else:
        for c in range(lc):
            for r in range(rm):
                vals[r, 0] = uc[r, 0, c] * sc
                vals[r, 1] = uc[r, 1, c] * sc
            coarse[c], peaks[c] = doppler(vals, rm)
    return _sum(coarse)


@njit(**JIT, inline="always")
def steer(uc, x, n, gate, s):
    """The channel the search runs on (see the module docstring): ``x`` itself with one ramp;
    with more, the residual ``x`` (Rm, 2, >= N) steered to the phase step phi* of the best
    coarse point not masked (``s.peaks``, the guard ``s.near``, beyond the gate -1; the
    first of equal ones) into ``s.steered`` (1, 2, N), its coarse energies from ``uc`` (Rm,
    2, Lc) (two ramps: from the cross term ``s.cross`` of
    :func:`~pipeline.dsp.cml.kernels.doppler.two_ramps`, no pass over ``uc``) into ``s.chan``
    and ``s.energy`` at the coarse points (``s.known``), phi* into
    ``s.phis[0]``; kept as they are when phi* is the one already steered to. phi* is 0 (the
    static channel) unless the peak over the phase step there beats the static energy by
    more than :data:`~pipeline.dsp.cml.kernels.doppler.STEER_GAIN` times the mean total of
    the coarse points (``s.coarse``)."""
    rm = x.shape[0]
    if rm == 1:
        return x
    peaks, chan, energy, known, near, vals = s.peaks, s.chan, s.energy, s.known, s.near, s.vals
    use, outside = gate.use, gate.outside
    size, lc = energy.shape[0], peaks.shape[0]
    ratio = size // lc
    sc = lc / size
    best, top = 0, -math.inf
    for c in range(lc):
        p = c * ratio
        v = -1.0 if use and outside[p] else (0.0 if near[p] else peaks[c])
        if v > top:
            top, best = v, c
    for r in range(rm):
        vals[r, 0] = uc[r, 0, best] * sc
        vals[r, 1] = uc[r, 1, best] * sc
    phi = doppler_phase(vals, rm)
    if peaks[best] - static_energy(vals, rm) <= STEER_GAIN * _sum(s.coarse) / lc:
        phi = 0.0
    if phi == s.phis[0]:
        return s.steered
    s.phis[0] = phi
    out, turns = s.steered, s.turns
    for r in range(rm):
        c = r - (rm - 1) / 2.0
        turns[r] = complex(math.cos(c * phi), -math.sin(c * phi))
    known[:] = False
    if rm == 2:  # one pass; the energies from the cross term two_ramps kept: E_phi = total + 2 Re(cross e^-i phi)
        t0, t1 = turns[0], turns[1]
        for p in range(2):
            for i in range(n):
                out[0, p, i] = t0 * x[0, p, i] + t1 * x[1, p, i]
        _two_ramp_channel(s.coarse, s.cross, math.cos(phi), math.sin(phi), chan, energy, known)
        return out
    for p in range(2):
        for i in range(n):
            out[0, p, i] = 0.0
    for r in range(rm):
        back = turns[r]
        for p in range(2):
            for i in range(n):
                out[0, p, i] += back * x[r, p, i]
    for c in range(lc):
        e = 0.0
        for p in range(2):
            acc = 0.0j
            for r in range(rm):
                acc += turns[r] * uc[r, p, c]
            acc *= sc
            e += acc.real * acc.real + acc.imag * acc.imag
        chan[c] = e
        energy[c * ratio] = e
        known[c * ratio] = True
    return out


@njit(**FAST)
def _two_ramp_channel(coarse, cross, cs, sn, chan, energy, known):
    """Two ramps' energy at the phase step of ``cos``, ``sin`` = ``cs``, ``sn`` at every coarse
    point into ``chan`` (Lc,): ``coarse + 2 (cross[0] cs + cross[1] sn)`` (:func:`two_ramps`),
    and into ``energy`` (L,) at the fine points the coarse ones sample (``known`` there True)."""
    xr, xi = cross[0], cross[1]
    ratio = energy.shape[0] // chan.shape[0]
    for c in range(chan.shape[0]):
        e = coarse[c] + 2.0 * (xr[c] * cs + xi[c] * sn)
        chan[c] = e
        energy[c * ratio] = e
        known[c * ratio] = True


@njit(**FAST)
def _sum(v) -> float:
    """``sum(v)`` (v (J,) float), vectorized."""
    total = 0.0
    for i in range(v.shape[0]):
        total += v[i]
    return total


@njit(**JIT, inline="always")
def guard(nu, live, oversample, guard_bins, gate, s):
    """``s.near`` (L,) = the fine points within ``guard_bins`` of the live targets ``nu``
    (T,) bins (later targets overwrite earlier ones, as numpy's ``put_along_axis``), and
    ``s.edge`` (Lc,) the coarse points within a coarse step of a live target's guard or
    (``gate.use``) of ``gate.edges`` (Lc,) (:func:`gate_edge`). Returns the guard's reach
    (fine points either side of a target's nearest one)."""
    near, edge = s.near, s.edge
    size, lc = near.shape[0], edge.shape[0]
    ratio = size // lc
    near[:] = False
    if gate.use:
        edge[:] = gate.edges
    else:
        edge[:] = False
    reach = int(math.ceil(guard_bins * oversample)) - 1
    for j in range(nu.shape[0]):
        c = int(np.rint(nu[j] * oversample))
        for d in range(-reach, reach + 1):
            near[(c + d) % size] = live[j]  # later targets overwrite, as put_along_axis
        if live[j]:
            _mark_edge(c - reach, c + reach, ratio, lc, edge)
    return reach


@njit(**JIT, inline="always")
def coarse_peak(x, n, grid, gate, s, bar, stop):
    """The fine grid's peak (the first of equal ones, as argmax) of the joint energy, 0
    within the guard ``s.near``, among the points inside the gate (``gate.use``): its point
    and its energy (-inf when no point is inside). From the coarse energies ``s.coarse``
    (Lc,) (:func:`coarse_energies`, which also fills ``s.energy``, ``s.known`` (L,)): the
    fine energy is summed directly (:func:`_cell_energies`) at the fine points within
    ``ratio // 2`` of every coarse point whose energy reaches ``grid.rho`` times the best one
    found. A maximum of ``|U|^2`` (a trigonometric polynomial of degree N - 1) keeps more than
    ``cos^2(pi (N - 1) / (4 N)) > 1/2`` of itself 1/4 bin away (Riesz; a tone: 0.81); a peak
    against the guard or the gate need not be a maximum, so a coarse point within a coarse
    step of a masked fine point (``s.edge`` (Lc,), :func:`guard`) counts its neighbours'
    energy too, and its points against the mask are summed whatever its energy
    (:func:`_against_mask`). ``s.offsets`` (2, 2 (ratio // 2), N): :func:`_cell_energies`' of
    the offsets ``-ratio // 2 .. -1, 1 .. ratio // 2``.

    ``bar``: only a peak reaching it is sought (the count test's threshold times the mean:
    the cells that cannot reach it are skipped): the peak found is the same when it does,
    else an energy below ``bar`` (-inf: always the peak); ``stop``: the first point found
    reaching ``bar`` instead (whether one does, all the count test asks)."""
    at, floor, first = _first_cell(grid, gate, s)
    if stop and floor >= bar:  # a coarse point reaches it
        return at, floor
    floor = max(floor, bar)
    if first >= 0 and s.chan[first] < grid.rho * floor:
        first = -1
    return _search_cells(x, n, grid, gate, s, first, floor, bar, stop)


@njit(**JIT, inline="always")
def _first_cell(grid, gate, s):
    """The best coarse point as a fine one (its point and value, -1 beyond the gate), the
    cell of the largest coarse energy of the channel (the first of equal ones; -1: none
    inside the gate), and into ``s.span`` (Lc,) what each cell may hold: its coarse energy,
    by a masked point its neighbours' too."""
    coarse, span, edge, near = s.chan, s.span, s.edge, s.near
    use, outside = gate.use, gate.outside
    size = grid.table.shape[0]
    lc = coarse.shape[0]
    ratio = size // lc
    half = ratio // 2
    floor = -math.inf  # the best value of the coarse points as fine ones (-1 beyond the gate)
    at = 0
    first = -1
    for c in range(lc):
        p = c * ratio
        v = -1.0 if use and outside[p] else (0.0 if near[p] else coarse[c])
        if v > floor:
            floor = v
            at = p
        if (first < 0 or coarse[c] > coarse[first]) and (not use or _open_cell(c, ratio, half, size, use, outside)):
            first = c
        span[c] = max(coarse[c], max(coarse[c - 1], coarse[(c + 1) % lc])) if edge[c] else coarse[c]
    return at, floor, first


@njit(**JIT, inline="always")
def _search_cells(x, n, grid, gate, s, first, floor, bar, stop):
    """:func:`coarse_peak`'s search of the cells, ``first`` first: ``(best, top)``."""
    table, rho = grid.table, grid.rho
    use, outside = gate.use, gate.outside
    near, energy, known, span, edge, vals = s.near, s.energy, s.known, s.span, s.edge, s.vals
    size = table.shape[0]
    lc = span.shape[0]
    ratio = size // lc
    half = ratio // 2
    top = -math.inf
    best = 0
    lim = rho * floor
    for step in range(lc + 1):
        c = first if step == 0 else step - 1
        if c < 0 or (step > 0 and c == first) or (span[c] < lim and not edge[c]) or not _open_cell(
                c, ratio, half, size, use, outside):
            continue
        if span[c] < lim:  # by a masked point: only its points against the mask (a peak there need not be a maximum)
            top, best = _against_mask(x, n, c * ratio, half, table, gate, near, energy, known, top, best, vals)
        else:
            _sum_cell(x, n, c * ratio, half, table, energy, known, s.offsets, s.turned, s.cell, vals)
            for d in range(-half, half + 1):
                p = (c * ratio + d) % size
                v = -1.0 if use and outside[p] else _fine_value(x, n, p, table, near, energy, known, vals)
                if v > top or (v == top and p < best):  # the first of equal peaks, as argmax
                    top = v
                    best = p
        lim = rho * max(floor, top)
        if stop and top >= bar:
            break
    return best, top


@njit(**JIT, inline="always")
def _sum_cell(x, n, p0, half, table, energy, known, offsets, turned, cell, vals):
    """The fine energies of the points within ``half`` of ``p0`` not summed yet (by another
    search of the same energies) into ``energy`` (``known``), in one pass
    (:func:`_cell_energies`, its work arrays ``offsets``, ``turned``, ``cell``)."""
    size = table.shape[0]
    fresh = False
    for j in range(2 * half):
        fresh = fresh or not known[(p0 + j - half + (j >= half)) % size]
    if fresh:
        _cell_energies(x, n, p0, table, offsets, turned, cell)
        for j in range(2 * half):
            p = (p0 + j - half + (j >= half)) % size
            if not known[p]:
                energy[p] = cell[j]
                known[p] = True


@njit(**JIT, inline="always")
def _against_mask(x, n, p0, half, table, gate, near, energy, known, top, best, vals):
    """``(top, best)`` updated with the fine points within ``half`` of ``p0`` that are not
    masked but have a masked neighbour (within the guard ``near`` or beyond the gate, ``gate.use``
    and ``gate.outside``): the grid's peak is a maximum of the energy or such a point."""
    size = table.shape[0]
    use, outside = gate.use, gate.outside
    for d in range(-half, half + 1):
        p = (p0 + d) % size
        lo, hi = (p - 1) % size, (p + 1) % size
        if near[p] or (use and outside[p]):
            continue
        if near[lo] or near[hi] or (use and (outside[lo] or outside[hi])):
            v = _fine_value(x, n, p, table, near, energy, known, vals)
            if v > top or (v == top and p < best):  # the first of equal peaks, as argmax
                top = v
                best = p
    return top, best


@njit(**JIT, inline="always")
def peak_range(x, n, best, grid, gate, s) -> float:
    """Range (bins) of fine point ``best`` refined by the parabola through its masked energy
    and its neighbours' (:func:`parabola`), in the gate (``gate.use``)."""
    table, near, energy, known, vals = grid.table, s.near, s.energy, s.known, s.vals
    size = table.shape[0]
    left = _fine_value(x, n, (best - 1) % size, table, near, energy, known, vals)
    centre = _fine_value(x, n, best, table, near, energy, known, vals)
    right = _fine_value(x, n, (best + 1) % size, table, near, energy, known, vals)
    return parabola(best, left, centre, right, grid.oversample, gate)


# -- the mean: sums of the fine energy over runs of fine points, from the coarse energies ------
@njit(**FAST)
def _cumulative(coarse, tables, e, size) -> float:
    """``Psi(e) = sum_k coarse[k] G(e - k ratio)`` (the run tables,
    :func:`pipeline.dsp.cml.grid.run_tables`) for fine point ``e`` (any integer): a dot
    product of length Lc with a contiguous slice of ``tables``."""
    lc = coarse.shape[0]
    ratio = size // lc
    e %= size
    row = tables[e % ratio]
    s = (lc - e // ratio) % lc
    acc = 0.0
    for k in range(lc):
        acc += coarse[k] * row[s + k]
    return acc


@njit(**JIT, inline="always")
def run_sum(coarse, total, tables, a, b, size) -> float:
    """The fine energy summed over the fine points ``a..b`` (an unwrapped run, b >= a) from
    the coarse energies ``coarse`` (Lc,) (sum ``total``):
    ``(b - a + 1) total / Lc + Psi(b + 1) - Psi(a)`` (:func:`_cumulative`)."""
    lc = coarse.shape[0]
    return (b - a + 1) * total / lc + _cumulative(coarse, tables, b + 1, size) - _cumulative(coarse, tables, a, size)


@njit(**JIT, inline="always")
def _add_cumulative(tables, p, sign, ratio, weights):
    """``weights[k] += sign G(p - k ratio)`` for k < Lc (fine point ``p`` in [0, L))."""
    lc = weights.shape[0] - 1
    row = tables[p % ratio]
    s = (lc - p // ratio) % lc
    for k in range(lc):
        weights[k] += sign * row[s + k]


@njit(**JIT)
def gate_weights(outside, tables, lc, weights) -> int:
    """``weights`` (Lc + 1,): the sum of the fine energy over the points inside the gate
    (``outside`` (L,) False) is ``sum_k weights[k] coarse[k] + weights[Lc] total``
    (:func:`open_sum`). Returns how many points are inside."""
    size = outside.shape[0]
    ratio = size // lc
    weights[:] = 0.0
    inside = 0
    for i in range(size):
        if not outside[i] and outside[i - 1]:  # a run of points inside the gate (wrapping)
            e = i
            while e + 1 < i + size and not outside[(e + 1) % size]:
                e += 1
            inside += e - i + 1
            weights[lc] += (e - i + 1) / lc
            _add_cumulative(tables, (e + 1) % size, 1.0, ratio, weights)
            _add_cumulative(tables, i, -1.0, ratio, weights)
    if inside == 0 and not outside[0]:  # no point beyond the gate: all of them
        weights[lc] = size / lc
        inside = size
    return inside


@njit(**JIT, inline="always")
def open_sum(total, nu, reach, grid, gate, s):
    """The sum of the fine total energy over the points inside the gate (``gate.use``:
    ``grid.weights`` (Lc + 1,) and ``grid.inside`` of :func:`gate_weights`) and not within
    the guard (``s.near`` (L,), :func:`guard` of ``reach`` fine points about the targets
    ``nu`` (T,) bins), and how many those points are: the sum inside less the guard's points
    inside, summed by runs (:func:`run_sum`) from the coarse totals ``s.coarse`` (Lc,) (sum
    ``total``). ``s.seen`` (L,) bool: work, all False (left so)."""
    coarse, near, seen, tables, weights = s.coarse, s.near, s.seen, grid.tables, grid.weights
    use, outside, oversample = gate.use, gate.outside, grid.oversample
    size = near.shape[0]
    lc = coarse.shape[0]
    if use:
        kept = weights[lc] * total
        for k in range(lc):
            kept += weights[k] * coarse[k]
        cells = grid.inside
    else:
        kept = (size // lc) * total
        cells = size
    for j in range(nu.shape[0]):  # the guard's points inside the gate, each once, by runs
        c = int(np.rint(nu[j] * oversample))
        start = c - reach
        run = False
        for d in range(-reach, reach + 1):
            p = (c + d) % size
            if near[p] and not (use and outside[p]) and not seen[p]:
                seen[p] = True
                cells -= 1
                if not run:
                    start = c + d
                    run = True
            elif run:
                kept -= run_sum(coarse, total, tables, start, c + d - 1, size)
                run = False
        if run:
            kept -= run_sum(coarse, total, tables, start, c + reach, size)
    for j in range(nu.shape[0]):
        c = int(np.rint(nu[j] * oversample))
        for d in range(-reach, reach + 1):
            seen[(c + d) % size] = False
    return (kept if cells > 0 else 0.0), cells
