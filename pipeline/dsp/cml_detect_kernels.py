"""Compiled (numba) detection and count test of :mod:`pipeline.dsp.cml_detect`, one frame at a
time inside the kernel (a frame costs the same in a batch of 1 or of 64). The numpy
functions of :mod:`pipeline.dsp.cml_detect` are the reference (tests/test_cml_kernels.py).

Layouts (one block of B frames, N samples a ramp, L = oversample N grid points, T targets
found so far): ``u`` (B, S, 2, L) complex, the zero-padded inverse FFTs of S residuals
(0: the linear residual ``Z - xi - model`` summed over the ramps, 1: the likelihood's
score) per antenna; ``y`` (B, N, 2) complex the linear residual; ``nu`` (B, T) ranges in
bins, ``live`` (B, T) bool; ``outside`` (L,) bool the grid points beyond the range gate.

Compiled on first use and cached on disk (``cache=True``), as :mod:`pipeline.dsp.cml_kernels`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from pipeline.dsp.cml_kernels import _FAST, evaluate, models, refine
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


@njit(cache=True, nogil=True, inline="always")
def _parabola(best, left, centre, right, oversample, use_gate, gate_lo, gate_hi) -> float:
    """Range (bins) of grid point ``best`` refined by a parabola through its energy and its neighbours'."""
    curv = left - 2.0 * centre + right
    off = 0.5 * (left - right) / curv if curv < 0.0 else 0.0
    nu0 = (best + min(max(off, -0.5), 0.5)) / oversample
    if use_gate:
        nu0 = min(max(nu0, gate_lo), gate_hi)
    return nu0


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


@njit(cache=True, nogil=True, inline="always")
def _fine_energy(x, n, p, table):
    """Joint energy at point ``p`` of the inverse FFT of ``x`` (2, >= N) zero-padded to L =
    ``table.shape[0]`` points (its first ``n`` points; ``table`` (L,) ``exp(2 pi i k / L)``):
    ``|U1|^2 + |U2|^2``, ``U = (1 / L) sum_i x[i] exp(2 pi i i p / L)`` summed directly."""
    size = table.shape[0]
    ar = ai = br = bi = 0.0
    k = 0
    for i in range(n):
        w = table[k]
        a = x[0, i]
        b = x[1, i]
        ar += a.real * w.real - a.imag * w.imag
        ai += a.real * w.imag + a.imag * w.real
        br += b.real * w.real - b.imag * w.imag
        bi += b.real * w.imag + b.imag * w.real
        k += p
        if k >= size:
            k -= size
    inv = 1.0 / size  # as the FFT's, before squaring
    ar, ai, br, bi = ar * inv, ai * inv, br * inv, bi * inv
    return (ar * ar + br * br) + (ai * ai + bi * bi)


@njit(cache=True, nogil=True, inline="always")
def _fine_value(x, n, p, table, near, energy, known) -> float:
    """:func:`_energy`'s ``energy[p]`` (0 within the guard ``near``), computed once
    (:func:`_fine_energy`) and kept in ``energy`` (``known``)."""
    if near[p]:
        return 0.0
    if not known[p]:
        energy[p] = _fine_energy(x, n, p, table)
        known[p] = True
    return energy[p]


@njit(**_FAST)
def _cell_energies(x, n, s, table, offsets, v, out):
    """:func:`_fine_energy` at the fine points ``s + d`` for the offsets ``d`` of ``offsets``
    (2, D, N) (real and imaginary parts of ``exp(2 pi i i d / L)``) into ``out`` (D,), in one
    pass: ``x`` turned by the twiddles of point ``s`` into ``v`` (4, N) (work), then one
    vectorized sum a point."""
    size = table.shape[0]
    k = 0
    for i in range(n):
        w = table[k]
        a = x[0, i]
        b = x[1, i]
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


@njit(cache=True, nogil=True, inline="always")
def _open_cell(c, ratio, half, size, outside, use_gate) -> bool:
    """Whether the fine points within ``half`` of coarse point ``c`` hold one inside the gate."""
    for d in range(-half, half + 1):
        if not use_gate or not outside[(c * ratio + d) % size]:
            return True
    return False


@njit(cache=True, nogil=True, inline="always")
def _mark_edge(lo, hi, ratio, lc, edge):
    """``edge[c]`` = True for the coarse points ``c`` within ``ratio`` fine points of the
    fine points ``lo..hi`` (masked ones), modulo ``lc``."""
    for c in range(-((ratio - lo) // ratio), (hi + ratio) // ratio + 1):  # ceil((lo - ratio) / ratio) ...
        edge[c % lc] = True


@njit(cache=True, nogil=True)
def _peak_coarse(uc, x, n, nu, live, oversample, guard_bins, outside, use_gate, gate_lo, gate_hi, rho, table,
                 offsets, energy, known, near, coarse, edge, turned, cell) -> float:
    """:func:`_peak` (the same fine-grid peak of L = ``table.shape[0]`` points and parabola)
    from the inverse FFT ``uc`` (2, Lc) on a grid ``ratio = L / Lc`` times coarser, of
    ``x`` (2, >= N) (first ``n`` points): the fine energy is summed directly
    (:func:`_cell_energies`) at the fine points within ``ratio // 2`` of every coarse point
    whose energy reaches ``rho`` times the best one found, and at the parabola's
    neighbours. A maximum of ``|U|^2`` (a trigonometric polynomial of degree N - 1) keeps
    more than ``cos^2(pi (N - 1) / (4 N)) > 1/2`` of itself 1/4 bin away (Riesz; a tone:
    0.81); a peak against the guard or the gate need not be a maximum, so a coarse point
    within a coarse step of a masked fine point (``edge``) counts its neighbours' energy
    too. ``offsets`` (2, 2 (ratio // 2), N): :func:`_cell_energies`' of the offsets
    ``-ratio // 2 .. -1, 1 .. ratio // 2``; ``energy``, ``known``, ``near`` (L,), ``coarse``,
    ``edge`` (Lc,), ``turned`` (4, N), ``cell`` (2 (ratio // 2),): work."""
    size = table.shape[0]
    lc = uc.shape[1]
    ratio = size // lc
    half = ratio // 2
    near[:] = False
    known[:] = False
    edge[:] = False
    reach = int(math.ceil(guard_bins * oversample)) - 1
    for j in range(nu.shape[0]):
        c = int(np.rint(nu[j] * oversample))
        for d in range(-reach, reach + 1):
            near[(c + d) % size] = live[j]  # later targets overwrite, as put_along_axis
        if live[j]:
            _mark_edge(c - reach, c + reach, ratio, lc, edge)
    if use_gate:
        for i in range(size):
            if outside[i] and not outside[i - 1]:  # a run of points beyond the gate (wrapping)
                e = i
                while e + 1 < i + size and outside[(e + 1) % size]:
                    e += 1
                _mark_edge(i, e, ratio, lc, edge)
    sc = lc / size  # the coarse FFT's 1 / Lc to the fine one's 1 / L
    floor = -math.inf  # the best value of the coarse points as fine ones (-1 beyond the gate)
    for c in range(lc):
        a = uc[0, c] * sc
        b = uc[1, c] * sc
        e = (a.real * a.real + b.real * b.real) + (a.imag * a.imag + b.imag * b.imag)
        coarse[c] = e
        p = c * ratio
        energy[p] = 0.0 if near[p] else e
        known[p] = True
        v = -1.0 if use_gate and outside[p] else energy[p]
        floor = max(floor, v)
    first = -1
    for c in range(lc):  # the cell of the largest coarse energy first: the others then mostly fall short
        if coarse[c] >= rho * floor and (first < 0 or coarse[c] > coarse[first]) and \
                _open_cell(c, ratio, half, size, outside, use_gate):
            first = c
    top = -math.inf
    best = 0
    for step in range(lc + 1):
        c = first if step == 0 else step - 1
        if c < 0 or (step > 0 and c == first):
            continue
        reach_c = max(coarse[c], max(coarse[c - 1], coarse[(c + 1) % lc])) if edge[c] else coarse[c]
        if reach_c < rho * max(floor, top) or not _open_cell(c, ratio, half, size, outside, use_gate):
            continue
        _cell_energies(x, n, c * ratio, table, offsets, turned, cell)
        for j in range(2 * half):
            p = (c * ratio + j - half + (j >= half)) % size
            if not known[p]:
                energy[p] = cell[j]
                known[p] = True
        for d in range(-half, half + 1):
            p = (c * ratio + d) % size
            v = -1.0 if use_gate and outside[p] else _fine_value(x, n, p, table, near, energy, known)
            if v > top or (v == top and p < best):  # the first of equal peaks, as argmax
                top = v
                best = p
    left = _fine_value(x, n, (best - 1) % size, table, near, energy, known)
    centre = _fine_value(x, n, best, table, near, energy, known)
    right = _fine_value(x, n, (best + 1) % size, table, near, energy, known)
    return _parabola(best, left, centre, right, oversample, use_gate, gate_lo, gate_hi)


@njit(cache=True, nogil=True)
def detect(u, src, table, rho, y, kc, ramps, nu, live, oversample, count_guard, sep_guard, outside, use_gate,
           gate_lo, gate_hi, count_sources, detect_source, stat, nu0, amp0):
    """Per frame: the count test's statistic into ``stat`` (B,) (the smaller peak ratio of
    the first ``count_sources`` residuals of ``u``; 0 sources: left alone), the detected
    range into ``nu0`` (B,) (residual ``detect_source`` of ``u``; -1: ``nu0`` given), and
    the least-squares amplitudes (B, 2) of one target at ``nu0`` in ``y`` into ``amp0``.
    ``u`` coarser than ``oversample`` N points (no count test): :func:`_peak_coarse` of
    ``src`` (B, S, 2, >= N) (the sources before their FFT), ``table`` (``oversample`` N,) and
    ``rho``; else both unused."""
    nb = u.shape[0]
    n = y.shape[1]
    size = oversample * n
    energy = np.empty(size)
    near = np.empty(size, dtype=np.bool_)
    on_coarse = detect_source >= 0 and u.shape[3] < size
    known = np.empty(size if on_coarse else 0, dtype=np.bool_)
    coarse = np.empty(u.shape[3] if on_coarse else 0)
    edge = np.empty(u.shape[3] if on_coarse else 0, dtype=np.bool_)
    half = (size // u.shape[3]) // 2 if on_coarse else 0
    offsets = np.empty((2, 2 * half, n))  # the fine offsets' twiddles (_cell_energies)
    if on_coarse:
        for j in range(2 * half):
            d, k = (j - half + (j >= half)) % size, 0  # exp(2 pi i i d / L) = table[i d mod L]
            for i in range(n):
                offsets[0, j, i], offsets[1, j, i] = table[k].real, table[k].imag
                k = k + d - size if k + d >= size else k + d
    turned = np.empty((4, n))
    cell = np.empty(2 * half)
    scale = 1.0 / (ramps * n)
    for f in range(nb):
        for s in range(count_sources):
            r = _peak_ratio(u[f, s], nu[f], live[f], oversample, count_guard, outside, use_gate, energy, near)
            stat[f] = r if s == 0 else min(stat[f], r)
        if on_coarse:
            nu0[f] = _peak_coarse(u[f, detect_source], src[f, detect_source], n, nu[f], live[f], oversample,
                                  sep_guard, outside, use_gate, gate_lo, gate_hi, rho, table, offsets, energy, known,
                                  near, coarse, edge, turned, cell)
        elif detect_source >= 0:
            nu0[f] = _peak(u[f, detect_source], nu[f], live[f], oversample, sep_guard, outside, use_gate, gate_lo,
                           gate_hi, energy, near)
        ph = 2.0 * math.pi * nu0[f] / n
        a1 = a2 = 0.0 + 0.0j
        w = complex(math.cos(ph * kc[0]), math.sin(ph * kc[0]))  # conj(exp(-i 2 pi kc nu / N)); kc in unit steps
        turn = complex(math.cos(ph), math.sin(ph))  # by a recurrence (relative error ~1e-14)
        for i in range(n):
            a1 += w * y[f, i, 0]
            a2 += w * y[f, i, 1]
            w *= turn
        amp0[f, 0] = a1 * scale
        amp0[f, 1] = a2 * scale


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
def add_target(u, src, table, rho, y, kc, ramps, nu, amp, live, oversample, count_guard, sep_guard, outside,
               use_gate, gate_lo, gate_hi, count_sources, detect_source, threshold, active, kind, lik, a, b, sigma,
               iters, amp_cap, max_range_step, mu, g, h):
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
    detect(u, src, table, rho, y, kc, ramps, nu, live, oversample, count_guard, sep_guard, outside, use_gate, gate_lo,
           gate_hi, count_sources, detect_source, stat, nu0, amp0)
    any_active = False
    for f in range(nb):
        if threshold >= 0.0:
            active[f] = active[f] and stat[f] >= threshold
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
    stat0 = np.zeros(nb)
    amp0 = np.empty((nb, 2), dtype=np.complex128)
    amp = np.empty((nb, 0, 2), dtype=np.complex128)
    mu[:] = 0.0
    for t in range(targets):
        _residual_into(folded, mu, ramps, y)
        nu0 = nu_all[:, t].copy()
        detect(none, none, no_table, 0.0, y, kc, ramps, np.ascontiguousarray(nu_all[:, :t]),
               np.ascontiguousarray(live_all[:, :t]), 1, 0.0, 0.0, no_gate, False, 0.0, 0.0, 0, -1, stat0, nu0, amp0)
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
# (and the likelihood it calls) are dropped from the cache when those files change
drop_stale(__file__, (add_target, finish, warm), ("cml_kernels.py", "cml_likelihood_kernels.py"))
