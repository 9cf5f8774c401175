"""PBP's count test on residuals (``K auto``): each target found is fitted to the folded ramps
as a tone at its continuous range bin, together with the tones the 1-bit quantizer makes of
the targets found so far, and removed before the next target is tested.

Why: a target between two range bins spreads over every bin of the back projection (the
Dirichlet kernel's sidelobes, -13 dB next to it, falling as 1/distance), and a 1-bit
quantizer adds its odd harmonics and intermodulation (``sign`` of I and of Q: tones at
``sum_t c_t nu_t`` with ``sum_t c_t = 1 (mod 4)``, e.g. -3 nu, 5 nu, 2 nu_1 - nu_2). Read
off the back projection, these passed the cell-averaging test beside a strong target
(0.7-1.9 false targets a frame at pfa 1e-3). Tested on the residual, each test sees what
the targets found so far do not explain. With a range gate, strong returns beyond it are
fitted first, unreported (:func:`outside_returns`): their skirts and tones inside the gate
are theirs, not targets.

Shapes: ``y`` the folded ramps (B, N, 2) (the mean of a frame's ramps, per antenna),
bins in units of the range grid (N bins, the inverse FFT's convention: a tone
``exp(-2 pi i k nu / N)`` peaks at bin ``nu``).
"""

from __future__ import annotations

from functools import lru_cache
from itertools import product

import numpy as np

#: the highest order of the quantizer's tones of one target kept in the model (-3, 5, ..., -15)
ORDER_SINGLE = 15
#: the highest order of the intermodulation of several targets kept (2 nu_1 - nu_2, -2 nu_1 - nu_2, ...)
ORDER_MIXED = 3
#: a range bin this close (bins) to a target found is that target (its model's residue), not another
RESOLUTION_BINS = 1
#: two of the model's tones closer than this (bins) are one to the fit (the lower order kept):
#: tones 0.5 bins apart have a normalized inner product of 0.64, still well posed; at 1 bin,
#: the quantizer's -3 nu_1 and 2 nu_1 - nu_2 of targets at 100.3 and 40.2 m (0.8 bins apart)
#: were one, and the one left out read as a target in 27 % of the frames
TONE_SEPARATION_BINS = 0.5
#: an intermodulation tone is at most 1/this of its strongest target's amplitude (a hard
#: limiter makes 1/3 of two equal tones; the bound keeps it from taking a real target)
MIXED_BOUND = 2.0
#: the residual's floor, dB under the strongest target: what the tone model leaves of a
#: target (its unmodelled higher orders, the error of its continuous bin) is not a target;
#: higher where the quantizer's products the model leaves are stronger (:func:`product_floor_db`)
DYNAMIC_RANGE_DB = 45.0
#: the dither scales :func:`product_floor_db` is computed at (a frame's alpha between two of
#: them takes the lower floor of the two: the products rise and fall with alpha)
ALPHA_STEP = 0.05
#: more than the steps of alpha's grid (0 .. 1 / ALPHA_STEP): a grid point's key is step + _STEP_KEYS * twice
_STEP_KEYS = round(1.0 / ALPHA_STEP) + 1
#: frames of this many bits or more are fitted as unquantized ones are (the targets' tones alone,
#: refined together): their staircase's products lie under the floor, and what the fit leaves of
#: two targets refined apart passed the test (4-8 bits beside two targets, noise 0.03, alpha
#: 0.45: 0.04-0.05 false targets a frame with the quantizer's tones; 0.003 and 0 without)
FINE_BITS = 4
#: the ridge of the tone fit, relative to the samples (N): coinciding tones stay solvable
RIDGE = 1e-9


def product_floor_db(alpha, bits: int = 1, reach=None) -> tuple[np.ndarray, np.ndarray]:
    """The residual's floor (dB under the strongest return) of ``bits``-bit frames dithered at
    ``alpha`` (scalar or (B,), in [0, 1]; NaN: not known): the strongest product of the
    quantizer that the tone model leaves out, (with one target in the model, with two or more)
    each (B,), at most DYNAMIC_RANGE_DB (NaN alpha: DYNAMIC_RANGE_DB). More bits: the
    staircase of the levels the frame reaches, ``reach`` (scalar or (B,)) steps from the middle
    at its peak (None: the step of :func:`pipeline.dsp.quantize.auto_delta`, 2^(bits-1) - 1/2;
    a margin or a fixed step reaches fewer), smoothed by the dither (:func:`mean_code`).

    The quantizer's mean output at a sample is a line of slope 1 / alpha clipped at +-1 (the
    uniform dither of width alpha delta, the step delta twice the frame's peak): without dither
    a hard limiter, whose harmonics fall only as 1 / order (the 17th, the first the model leaves,
    24.6 dB under its target) and whose intermodulation of two equal targets as much (the 5th
    order, 3 nu_1 - 2 nu_2, 14 dB); at alpha 0.45 these are 42.8 and 30.3 dB under, at alpha 1
    (no clipping) none. A residual holding them holds no noise to hide them in (alpha 0, little
    noise): 3 false targets a frame beside one strong target at pfa 1e-3 with the 45 dB floor."""
    a = np.atleast_1d(np.asarray(alpha, dtype=float))
    single, mixed = np.full(a.shape, DYNAMIC_RANGE_DB), np.full(a.shape, DYNAMIC_RANGE_DB)
    known = np.isfinite(a)
    if not known.any():
        return single, mixed
    x = np.clip(a[known], 0.0, 1.0) / ALPHA_STEP
    lo, hi = np.floor(x + 1e-9).astype(np.int64), np.ceil(x - 1e-9).astype(np.int64)
    if bits == 1 or reach is None:  # (twice the reach in steps: the cache's key, an odd integer at delta auto)
        twice = np.full(lo.shape, (1 << bits) - 1)
        shifts = (0,)
    else:  # the values' top level reaches r steps; the peak under it, between r - 1/2 and r: the lower floor of both
        twice = np.maximum(np.rint(2.0 * np.broadcast_to(np.asarray(reach, dtype=float), a.shape)[known]), 2)
        shifts = (0, -1)
    steps = np.concatenate([s for s in (lo, hi) for _ in shifts]).astype(np.int64)  # alpha's grid, 0..1/ALPHA_STEP
    twices = np.concatenate([twice + d for _ in (lo, hi) for d in shifts]).astype(np.int64)
    # the grid points these frames need, as one integer each (a 1-D unique: ~10x faster than rows')
    keys, where = np.unique(steps + _STEP_KEYS * twices, return_inverse=True)
    levels = np.array([_product_levels_db(int(k % _STEP_KEYS), bits, int(k // _STEP_KEYS))
                       for k in keys])  # each ~3 ms, once
    floor = levels[where.ravel()].reshape(-1, lo.size, 2).min(axis=0)
    single[known] = np.minimum(DYNAMIC_RANGE_DB, floor[:, 0])
    mixed[known] = np.minimum(DYNAMIC_RANGE_DB, floor[:, 1])
    return single, mixed


def mean_code(x: np.ndarray, alpha: float, bits: int = 1, reach: float | None = None) -> np.ndarray:
    """The quantizer's mean output at values ``x`` in [-1, 1] of the frame's peak, dithered
    uniformly over ``alpha`` steps: one bit, the line of slope 1 / alpha clipped at +-1 (a hard
    limiter at alpha 0; in half steps); more, in steps from the middle, the staircase whose
    levels reach ``reach`` steps at the peak (None: delta auto's 2^(bits-1) - 1/2), its risers
    ``alpha`` steps wide."""
    if bits == 1:
        return np.sign(x) if alpha == 0.0 else np.clip(x / alpha, -1.0, 1.0)
    y = np.asarray(x) * (((1 << bits) - 1) / 2.0 if reach is None else reach)  # in steps
    if alpha == 0.0:
        return np.floor(y) + 0.5

    def integral(t):  # of floor(s) ds from 0 to t
        f = np.floor(t)
        return f * t - f * (f + 1.0) / 2.0

    return (integral(y + alpha / 2.0) - integral(y - alpha / 2.0)) / alpha + 0.5


@lru_cache(maxsize=1024)
def _product_levels_db(step: int, bits: int, twice_reach: int, points: int = 256) -> tuple[float, float]:
    """(:func:`product_floor_db` of one target, of two equal ones) at alpha = step ALPHA_STEP:
    the strongest harmonic above ORDER_SINGLE of a tone through the quantizer's mean output
    (:func:`mean_code`), the strongest product above ORDER_MIXED of two equal tones, each in
    dB under a tone's fundamental."""
    alpha = step * ALPHA_STEP
    t = 2.0 * np.pi * np.arange(points) / points

    def code(x):
        return mean_code(x, alpha, bits, twice_reach / 2.0)

    one = np.abs(np.fft.fft(code(np.cos(t))))
    m = np.arange(points)
    order = np.minimum(m, points - m)
    high = one[(order > ORDER_SINGLE) & (order < points // 4)].max()
    two = np.abs(np.fft.fft2(code(0.5 * (np.cos(t)[:, None] + np.cos(t)[None, :]))))
    o1, o2 = order[:, None], order[None, :]
    mixed = two[(o1 > 0) & (o2 > 0) & (o1 + o2 > ORDER_MIXED) & (o1 + o2 < points // 4)].max()
    with np.errstate(divide="ignore"):
        return (float(-20.0 * np.log10(high / one[1])) if high > 0 else np.inf,
                float(-20.0 * np.log10(mixed / two[1, 0])) if mixed > 0 else np.inf)


@lru_cache(maxsize=32)
def tone_combinations(k: int, one_bit: bool = True) -> np.ndarray:
    """The integer combinations ``c`` (P, k) of ``k`` tones whose frequency ``c @ nu`` a
    1-bit quantizer of I and Q makes of them and the model keeps: ``sum |c|`` odd,
    ``sum c = 1 (mod 4)``; up to ORDER_SINGLE for one tone alone, ORDER_MIXED when several
    mix. The fundamentals first (the k unit vectors); ``one_bit`` False (unquantized frames: no
    quantizer's products), the fundamentals alone."""
    out = [tuple(int(i == t) for i in range(k)) for t in range(k)]
    if not one_bit:
        combos = np.array(out, dtype=float).reshape(-1, k)
        combos.flags.writeable = False
        return combos
    span = range(-ORDER_SINGLE, ORDER_SINGLE + 1)
    for t, h in product(range(k), span):
        if h != 1 and abs(h) % 2 == 1 and h % 4 == 1:
            out.append(tuple(h if i == t else 0 for i in range(k)))
    if k > 1:
        for c in product(range(-ORDER_MIXED, ORDER_MIXED + 1), repeat=k):
            order = sum(abs(x) for x in c)
            if sum(x != 0 for x in c) > 1 and order <= ORDER_MIXED and order % 2 == 1 and sum(c) % 4 == 1:
                out.append(c)
    out.sort(key=lambda c: sum(abs(x) for x in c))  # by order (stable: the fundamentals first)
    combos = np.array(out, dtype=float).reshape(-1, k)
    combos.flags.writeable = False
    return combos


def tones(nu: np.ndarray, n: int) -> np.ndarray:
    """Tones at continuous bins ``nu`` (B, P): ``exp(-2 pi i k nu / n)``, (B, n, P) complex."""
    k = np.arange(n, dtype=float)
    return np.exp(-2j * np.pi * k[None, :, None] * (np.asarray(nu, dtype=float)[:, None, :] / n))


def combination_tones(nu: np.ndarray, combos: np.ndarray, n: int) -> np.ndarray:
    """:func:`tones` at the bins ``nu @ combos.T`` ((B, J) bins, (P, J) integers), made of
    the J tones' integer powers (products, not an exponential a sample and tone): (B, n, P)."""
    base = tones(nu, n)  # (B, n, J)
    powers = [{1: base[:, :, t]} for t in range(base.shape[2])]  # tone t -> {|h|: base_t ** |h|}

    def power(t: int, h: int) -> np.ndarray:
        have = powers[t]
        if abs(h) not in have:
            low = max(m for m in have if m < abs(h))
            have[abs(h)] = have[low] * power(t, abs(h) - low)
        return np.conj(have[abs(h)]) if h < 0 else have[abs(h)]

    out = np.empty(base.shape[:2] + (combos.shape[0],), dtype=complex)
    for p, c in enumerate(combos.astype(int)):  # over the few tones of the model
        factors = [power(t, h) for t, h in enumerate(c) if h]
        out[:, :, p] = factors[0] if len(factors) == 1 else np.prod(factors, axis=0)
    return out


def refine_bins(y: np.ndarray, bins: np.ndarray, newton: int = 3) -> np.ndarray:
    """The continuous bin (B,) near integer ``bins`` (B,) where the joint power of ``y``
    (B, N, 2) peaks: the parabola through the magnitude at the bin and its neighbours, then
    ``newton`` Newton steps on the power's derivatives (each at most half a bin)."""
    n = y.shape[1]
    p = np.asarray(bins, dtype=float)
    lo, mid, hi = np.sqrt(_joint_power(y, p[:, None] + np.array([-1.0, 0.0, 1.0])[None, :], n).T)
    curv = lo - 2.0 * mid + hi
    with np.errstate(divide="ignore", invalid="ignore"):
        nu = p + np.clip(np.where(curv < 0, 0.5 * (lo - hi) / curv, 0.0), -0.5, 0.5)
    w = 2j * np.pi * np.arange(n) / n  # d/dnu of the phase of exp(+2 pi i k nu / n)
    for _ in range(newton):
        e = np.exp(w[None, :] * nu[:, None])[:, :, None] * y  # (B, N, 2)
        s0, s1, s2 = e.sum(axis=1), (w[None, :, None] * e).sum(axis=1), (w[None, :, None] ** 2 * e).sum(axis=1)
        d1 = 2 * np.real(np.conj(s0) * s1).sum(axis=-1)
        d2 = 2 * np.real(np.square(np.abs(s1)) + np.conj(s0) * s2).sum(axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            nu = nu - np.where(d2 < 0, np.clip(d1 / d2, -0.5, 0.5), 0.0)
    return nu


#: Gauss-Newton steps of the targets' joint refinement (:func:`refine_jointly`)
JOINT_STEPS = 3


def refine_jointly(y: np.ndarray, nu: np.ndarray, active: np.ndarray, steps: int = JOINT_STEPS) -> np.ndarray:
    """The bins ``nu`` (B, J) of the targets a frame has (``active`` (B, J)) refined together
    on the folded ramps ``y`` (B, N, 2): each a tone with a complex amplitude an antenna, the
    amplitudes solved by least squares, then a Gauss-Newton step of all bins on the squared
    residual (each at most half a bin), ``steps`` times. Each bin refined alone on the
    residual of the ones before it (:func:`refine_bins`) is pulled by the skirts of those found
    after it: two strong targets of unquantized frames left -25 to -35 dB of their tones in
    the residual, which the count test read as a third (27-35 times its false-alarm rate)."""
    b, n, _ = y.shape
    j = nu.shape[1]
    if j == 0 or not active.any():
        return nu
    on = active.astype(float)
    dphase = -2j * np.pi * np.arange(n, dtype=float) / n  # d/dnu of the phase of exp(-2 pi i k nu / n)
    eye = np.eye(j)
    nu = np.array(nu, dtype=float)
    for _ in range(steps):
        e = tones(nu, n) * on[:, None, :]  # (B, N, J): a target a frame lacks is no tone
        eh = np.ascontiguousarray(np.conj(e).transpose(0, 2, 1))
        gram = eh @ e + (RIDGE * n + n * (1.0 - on))[:, :, None] * eye  # (B, J, J)
        amp = np.linalg.solve(gram, eh @ y)  # (B, J, 2)
        r = y - e @ amp  # (B, N, 2)
        jac = (e * dphase[None, :, None])[:, :, :, None] * amp[:, None, :, :]  # (B, N, J, 2): d model / d nu_j
        # projected off the tones' span (Kaufman's variable projection: the amplitudes follow the bins)
        flat = jac.reshape(b, n, 2 * j)
        flat = flat - e @ np.linalg.solve(gram, eh @ flat)
        jt = np.ascontiguousarray(flat.reshape(b, n, j, 2).transpose(0, 2, 1, 3)).reshape(b, j, 2 * n)
        normal = np.real(np.conj(jt) @ jt.transpose(0, 2, 1))
        # relative (frames in any unit); a target of no amplitude takes no step
        ridge = 1e-9 * normal.diagonal(axis1=1, axis2=2).max(axis=1) + np.finfo(float).tiny
        normal += (ridge[:, None] + (1.0 - on))[:, :, None] * eye
        grad = np.real(np.conj(jt) @ r.reshape(b, 2 * n, 1))[..., 0]  # (B, J)
        step = np.linalg.solve(normal, grad[..., None])[..., 0]
        nu = nu + np.clip(np.nan_to_num(step), -0.5, 0.5) * on
    return nu


def _joint_power(y: np.ndarray, nu: np.ndarray, n: int) -> np.ndarray:
    """``sum_antenna |sum_k y_k exp(+2 pi i k nu / n)|^2`` at bins ``nu`` (B, G): (B, G)."""
    proj = np.ascontiguousarray(np.conj(tones(nu, n)).transpose(0, 2, 1)) @ y  # (B, G, 2)
    return np.square(np.abs(proj)).sum(axis=-1)


def fit_residual(y: np.ndarray, nu: np.ndarray, active: np.ndarray | None = None, one_bit: bool = True) -> np.ndarray:
    """``y`` (B, N, 2) less its fit by the tones of the targets at bins ``nu`` (B, J)
    (:func:`tone_combinations`, one complex amplitude a tone and antenna): (B, N, 2).
    ``active`` (B, J) bool: the targets a frame has (None: all); a tone made of one a frame
    lacks is left out of its fit. The
    quantizer's tones are bounded as a hard limiter bounds them (a harmonic of order ``h`` at
    most ``1/h`` of its target's joint amplitude, an intermodulation tone 1/MIXED_BOUND of its
    strongest target's), so that a high order aliased onto another target does not take it;
    of tones within TONE_SEPARATION_BINS of each other the fit keeps the lowest order (:func:`separated`)."""
    n, j = y.shape[1], nu.shape[1]
    combos = tone_combinations(j, one_bit)
    freq, keep = kept_tones(nu, active, n, one_bit)
    order = np.abs(combos).sum(axis=1)  # (P,)
    involved = np.abs(combos) > 0  # (P, J)
    a = combination_tones(nu, combos, n) * keep[:, None, :]  # (B, N, P)
    gram = dirichlet(freq[:, :, None] - freq[:, None, :], n) * (keep[:, :, None] & keep[:, None, :])
    gram += RIDGE * n * np.eye(gram.shape[-1])
    amp = np.linalg.solve(gram, np.ascontiguousarray(np.conj(a).transpose(0, 2, 1)) @ y)  # (B, P, 2)
    size = np.sqrt(np.square(np.abs(amp)).sum(axis=-1))  # (B, P)
    mixed = involved.sum(axis=1) > 1
    bound = np.where(involved[None], size[:, None, :j], 0.0).max(axis=2) / np.where(mixed, MIXED_BOUND, order)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(order[None] > 1, np.minimum(1.0, bound / size), 1.0)
    amp *= np.nan_to_num(scale, nan=0.0)[:, :, None]
    return y - a @ amp


def kept_tones(nu: np.ndarray, active: np.ndarray | None, n: int, one_bit: bool = True
               ) -> tuple[np.ndarray, np.ndarray]:
    """The bins (B, P) of the model's tones of the targets at bins ``nu`` (B, J)
    (:func:`tone_combinations`) and which of them :func:`fit_residual` fits (B, P) bool:
    those :func:`separated` from a lower order, made only of targets ``active`` (B, J) (None: all)."""
    combos = tone_combinations(nu.shape[1], one_bit)
    freq = nu @ combos.T
    keep = separated(freq, n)
    if active is not None:
        keep &= made_of(combos, active)
    return freq, keep


def made_of(combos: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Which tones ``combos`` (P, J) are made of a frame's ``active`` (B, J) targets alone: (B, P)."""
    return ~((np.abs(combos) > 0)[None] & ~active[:, None, :]).any(axis=2)


def fitted_inside(nu: np.ndarray, active: np.ndarray | None, n: int, inside: np.ndarray,
                  one_bit: bool = True) -> np.ndarray:
    """How many of the residual's degrees of freedom (B,) inside the gate ``inside`` (N,) bool
    the tone fit of :func:`fit_residual` took: its tones whose bin is inside. A least-squares
    fit of P tones takes P of the N bins' worth of noise (the projection's trace is its rank,
    and the bins are an orthogonal basis), each mostly at its own bin, so the residual's mean
    energy over the gate's bins is ``(cells - fitted) / cells`` of the noise's: the count
    test's mean divides by ``cells - fitted``, not ``cells``. Without it the test's threshold
    sank with every tone the model holds (PBP beside two strong targets: 5.6-5.8 times the
    false-alarm rate promised, 1.7-2.7 with it on two seeds; more tones in the model made it worse)."""
    if nu.shape[1] == 0:
        return np.zeros(nu.shape[0], dtype=np.int64)
    freq, keep = kept_tones(nu, active, n, one_bit)
    return (keep & inside[np.rint(freq).astype(np.int64) % n]).sum(axis=1)


def dirichlet(delta: np.ndarray, n: int) -> np.ndarray:
    """``sum_k exp(2 pi i k delta / n)`` over k < n, for bin differences ``delta`` (any shape):
    the inner product of two tones (:func:`tones`) ``delta`` bins apart, in closed form."""
    theta = 2 * np.pi * np.asarray(delta, dtype=float) / n
    den = np.expm1(1j * theta)
    small = np.abs(den) < 1e-9  # the same tone (modulo n)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.expm1(1j * theta * n) / np.where(small, 1.0, den)
    return np.where(small, complex(n), out)


def separated(freq: np.ndarray, n: int) -> np.ndarray:
    """Which tones at bins ``freq`` (B, P) (lowest order first) the fit keeps: (B, P) bool,
    each farther than TONE_SEPARATION_BINS from every tone before it (two tones closer are
    one to the fit: its amplitudes would be ill-posed)."""
    gap = np.abs((freq[:, :, None] - freq[:, None, :] + n / 2) % n - n / 2)  # (B, P, P) bins
    before = np.tri(freq.shape[1], k=-1, dtype=bool)  # [p, q]: q comes before p
    return ~((gap <= TONE_SEPARATION_BINS) & before[None]).any(axis=2)


#: frames decoded together by :func:`residual_support` (its tone tables are (frames, N, tones))
CHUNK_FRAMES = 128


def residual_support(y: np.ndarray, energy: np.ndarray, pick: np.ndarray, inside: np.ndarray, k: int,
                     threshold: float, alpha=None, quantized: bool = True,
                     bits: int = 1, reach=None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`residual_support_of` CHUNK_FRAMES frames at a time (memory bounded whatever the
    batch, the tables small enough to stay in cache); ``alpha``: the ``bits``-bit frames' dither
    scale (scalar or (B,); None or NaN: not known) and ``reach`` their levels' (in steps), the
    floor under the strongest return the quantizer's products the model leaves (:func:`product_floor_db`). ``quantized``
    False: unquantized frames, whose model holds the targets' tones alone, refined together (so are
    frames of FINE_BITS bits or more)."""
    b = y.shape[0]
    floors = np.stack(product_floor_db(np.broadcast_to(np.nan if alpha is None else alpha, (b,)), bits, reach),
                      axis=1)
    joint = not quantized or bits >= FINE_BITS  # the targets' tones alone, their bins refined together
    if b <= CHUNK_FRAMES:
        return residual_support_of(y, energy, pick, inside, k, threshold, floors, joint)
    parts = [residual_support_of(*(a[i:i + CHUNK_FRAMES] for a in (y, energy, pick)), inside, k, threshold,
                                 floors[i:i + CHUNK_FRAMES], joint) for i in range(0, b, CHUNK_FRAMES)]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def residual_support_of(y: np.ndarray, energy: np.ndarray, pick: np.ndarray, inside: np.ndarray, k: int,
                        threshold: float, floors: np.ndarray | None = None,
                        joint: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``k`` targets of the folded ramps ``y`` (B, N, 2), each the strongest bin of the
    residual of the ones before it: (support (B, k) int, statistic_db (B, k)). ``energy``
    (B, N): the joint energy of ``y``'s bins (the back projection's, known to the caller);
    ``pick`` (B, N):
    the back projection's joint energy with -1 where no target may be (outside the range gate,
    the skirt of a return beyond it); ``inside`` (N,) bool: the gate's bins, over which the
    statistic's mean is taken (the first target's statistic is PBP's cell-averaging one).
    A frame's testing stops at its first statistic under ``threshold`` (linear): its later
    slots repeat that pick and statistic (the caller masks them); the fits are made for the
    frames still being tested only. ``floors`` (B, 2): the floor (dB under the strongest
    return) with one return in the model and with two or more (:func:`product_floor_db`; None:
    DYNAMIC_RANGE_DB). ``joint``: unquantized frames: the model holds the targets' tones alone
    (no quantizer's products: fitted to noise, they took a target's neighbour bins), their bins
    refined together after each one found (:func:`refine_jointly`)."""
    b, n, _ = y.shape
    floors = np.full((b, 2), DYNAMIC_RANGE_DB) if floors is None else floors
    cells = max(int(inside.sum()), 2)
    support = np.zeros((b, k), dtype=np.int64)
    stat = np.zeros((b, k))
    idx, blocked = np.arange(b), pick < 0
    one_bit = not joint  # the quantizer's tones in the model: quantized frames under FINE_BITS bits
    energy, nu, active, strongest = outside_returns(y, energy, inside, threshold, one_bit)
    fitted = fitted_inside(nu, active, n, inside, one_bit)
    residual = y
    for t in range(k):
        choice = np.where(blocked, -1.0, energy)
        p = choice.argmax(axis=1)
        e = np.where(choice[np.arange(idx.size), p] < 0, 0.0, energy[np.arange(idx.size), p])  # none left: 0
        # the mean of the other bins, over the degrees of freedom the tones fitted so far left them
        rest = (np.where(inside[None, :], energy, 0.0).sum(axis=1) - e) / np.maximum(cells - 1 - fitted, 1)
        # what the tone model leaves of the strongest return is not a target (the first test,
        # PBP's statistic as it is, has no floor but that of a strong return beyond the gate)
        floor_db = np.where(active.sum(axis=1) >= 2, floors[:, 1], floors[:, 0])
        rest = np.maximum(rest, strongest * 10 ** (-floor_db / 10))
        if t == 0:
            strongest = np.maximum(strongest, e)
        with np.errstate(divide="ignore", invalid="ignore"):
            s_db = np.clip(np.nan_to_num(10 * np.log10(e / rest), nan=-300.0), -300.0, 300.0)
        stat[idx, t:], support[idx, t:] = s_db[:, None], p[:, None]
        go = (e >= threshold * rest) & (e > 0)
        if t == k - 1 or not go.any():
            break
        near = np.abs((np.arange(n)[None, :] - p[:, None] + n // 2) % n - n // 2) <= RESOLUTION_BINS
        blocked, strongest, idx, floors = (blocked | near)[go], strongest[go], idx[go], floors[go]
        nu = np.concatenate([nu[go], refine_bins(residual[go], p[go])[:, None]], axis=1)
        active = np.concatenate([active[go], np.ones((idx.size, 1), dtype=bool)], axis=1)
        if joint:
            nu = refine_jointly(y[idx], nu, active)
        residual = fit_residual(y[idx], nu, active, one_bit)
        energy = _bin_energy(residual)
        fitted = fitted_inside(nu, active, n, inside, one_bit)
        blocked = blocked | merged_near(nu, active, n, one_bit)
    return support, stat


def merged_near(nu: np.ndarray, active: np.ndarray, n: int, one_bit: bool = True) -> np.ndarray:
    """The bins (B, N) bool within RESOLUTION_BINS of a tone of the model that the fit merged
    into a lower order one (:func:`separated`): what is left of it there is the model's residue."""
    combos = tone_combinations(nu.shape[1], one_bit)
    freq = nu @ combos.T  # (B, P)
    made = made_of(combos, active)
    frame, tone = np.nonzero(made & ~separated(np.where(made, freq, np.nan), n))  # the merged tones
    at = freq[frame, tone]
    out = np.zeros((nu.shape[0], n), dtype=bool)
    for step in range(2 * RESOLUTION_BINS + 1):  # the integer bins within RESOLUTION_BINS of each
        cand = np.ceil(at - RESOLUTION_BINS) + step
        ok = np.abs(cand - at) <= RESOLUTION_BINS
        out[frame[ok], cand[ok].astype(np.int64) % n] = True
    return out


#: strong returns beyond the range gate fitted (unreported) before the gate's first test, at most
OUTSIDE_RETURNS = 2


def outside_returns(y: np.ndarray, energy: np.ndarray, inside: np.ndarray, threshold: float, one_bit: bool = True
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The returns beyond the range gate strong enough to be targets (their bin's energy over
    the gate's mean reaches ``threshold``), fitted as tones, unreported, before the gate is
    tested: a strong reflector just beyond the gate puts its Dirichlet skirt and its 1-bit
    quantizer's tones (-3 nu, 5 nu, ...) inside the gate, where they would read as targets
    (1.06 false targets a frame for a target at 100.3 m and a gate ending at 100 m). Returns
    the energy (B, N) the gate is tested on (``energy`` itself in frames with no such
    return), their bins ``nu`` (B, J) and which frames have each (``active`` (B, J)), and the
    strongest one's energy (B,) (0 without), under which DYNAMIC_RANGE_DB is not a target."""
    b, n, _ = y.shape
    nu, active, strongest = np.zeros((b, 0)), np.zeros((b, 0), dtype=bool), np.zeros(b)
    if inside.all() or not inside.any():
        return energy, nu, active, strongest
    cells = max(int(inside.sum()), 2)
    rows, current, residual = np.arange(b), energy, y
    for _ in range(OUTSIDE_RETURNS):
        beyond = np.where(inside[None, :], -1.0, current)
        taken = np.abs((np.arange(n)[None, None, :] - nu[:, :, None] + n / 2) % n - n / 2) <= RESOLUTION_BINS
        beyond = np.where((taken & active[:, :, None]).any(axis=1), -1.0, beyond)
        q = beyond.argmax(axis=1)
        # over the gate's degrees of freedom the returns fitted so far left it (:func:`fitted_inside`)
        dof = np.maximum(cells - fitted_inside(nu, active, n, inside, one_bit), 1)
        mean = np.where(inside[None, :], current, 0.0).sum(axis=1) / dof
        strong = current[rows, q] >= threshold * mean
        if not strong.any():
            break
        strongest = np.maximum(strongest, np.where(strong, current[rows, q], 0.0))
        nu = np.concatenate([nu, refine_bins(residual, q)[:, None]], axis=1)
        active = np.concatenate([active, strong[:, None]], axis=1)
        residual = fit_residual(y, nu, active, one_bit)  # the next return is refined on it
        current = np.where(active.any(axis=1)[:, None], _bin_energy(residual), energy)
    return current, nu, active, strongest


def _bin_energy(y: np.ndarray) -> np.ndarray:
    """The joint energy of each range bin of ``y`` (B, N, 2): its inverse FFT's
    ``|U_1|^2 + |U_2|^2`` (the back projection's, up to the carrier's phase): (B, N)."""
    u = np.fft.ifft(y, axis=1)
    return np.square(np.abs(u)).sum(axis=-1)
