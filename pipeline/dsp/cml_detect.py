"""Detection and the count test of :func:`pipeline.dsp.cml.cml`: the back projection of a
residual on the oversampled range grid, its peak, and the peak over mean of its joint
energy (numpy reference; :func:`detect_compiled` runs the per-frame part compiled).

Shapes: a block of B frames of N samples a ramp, 2 antennas; ranges in bins."""

from __future__ import annotations

import threading
import weakref

import numpy as np

from pipeline.dsp.cml_fit import _LIK, MAX_RANGE_STEP_BINS, WRONG_RMS_PER_SIGMA, _atoms, _Codes, _Fit
from pipeline.errors import ParameterError

_kernels_module = None


def _kernels():
    """:mod:`pipeline.dsp.cml_detect_kernels`, imported on first use (it imports numba)."""
    global _kernels_module
    if _kernels_module is None:
        from pipeline.dsp import cml_detect_kernels
        _kernels_module = cml_detect_kernels
    return _kernels_module


#: a detection keeps at least this far from the targets already found, range bins
MIN_SEPARATION_BINS = 1.0
#: detection and the count test take their inverse FFT on a grid of this many points a bin,
#: coarser than ``oversample``, and find the same fine-grid peak by summing the fine energy
#: directly around the coarse points that could hold it
#: (:func:`pipeline.dsp.cml_count_kernels.coarse_peak`); the count test's mean, the fine
#: energy summed over the points not masked, by sums over runs of fine points from the
#: coarse energies (:func:`pipeline.dsp.cml_count_kernels.open_sum`; measured against the
#: full grid: within 5e-15 relative; K auto on 80 040 frames: the same counts as the full grid)
COARSE_PER_BIN = 2
#: ... those whose energy reaches this fraction of the best fine energy found: the fine peak's
#: nearest coarse point (at most 1 / (2 COARSE_PER_BIN) bin away) holds more (a maximum of the
#: energy: over cos^2(pi / 4) = 1/2, Riesz; a tone's: 0.81; a peak against the guard or the gate:
#: its coarse neighbours count too). Measured against the full grid on 288 000 detections of
#: 1-bit and unquantized frames (K = 1..3, alpha 1 and 0.45, noise 0 and 0.1, gated or not,
#: targets 0.3 or 1.5 m apart): the same fine point every time, ranges within 3e-14 bins
COARSE_RHO = 0.5
#: the count test looks for a peak this far from the targets found, range bins (a guard
#: band: a strong target's 1-bit fit leaves residual energy up to ~2 bins away)
COUNT_GUARD_BINS = 2.0


def _energy(y: np.ndarray, fit: _Fit, oversample: int, guard_bins: float) -> tuple[np.ndarray, np.ndarray]:
    """Joint energy ``|U1|^2 + |U2|^2`` (B, L) of the back projection of ``y`` (B, N, 2)
    on a grid of ``oversample`` points a bin (zero-padded inverse FFT), zero within
    ``guard_bins`` of the live targets found, and that mask (B, L) bool."""
    b, n = y.shape[:2]
    size = oversample * n
    u = np.fft.ifft(np.ascontiguousarray(y.transpose(0, 2, 1)), n=size, axis=2).view(float)  # (B, 2, 2L)
    np.square(u, out=u)
    both = u[:, 0] + u[:, 1]
    energy = both[:, 0::2] + both[:, 1::2]  # (B, L): |U1|^2 + |U2|^2
    near = np.zeros(energy.shape, dtype=bool)
    reach = int(np.ceil(guard_bins * oversample)) - 1
    for j in range(fit.nu.shape[1]):
        idx = np.rint(fit.nu[:, j] * oversample).astype(np.int64)[:, None] + np.arange(-reach, reach + 1)
        np.put_along_axis(near, idx % size, fit.live[:, j, None], axis=1)
    energy[near] = 0.0
    return energy, near


def _residual(codes: _Codes, fit: _Fit) -> np.ndarray:
    """``Z - xi - model`` (full frames: ``Z - model``) summed over the ramps, (B, N, 2)."""
    if codes.folded is None:  # Z - xi does not change during a decode: summed once
        codes.folded = codes.data.reshape(fit.nu.shape[0], codes.ramps, codes.n, 2).sum(axis=1)
    return codes.folded - codes.ramps * fit.model()


def _peak_ratio(y: np.ndarray, fit: _Fit, oversample: int) -> np.ndarray:
    """Peak over mean (B,) of the joint energy of the back projection of ``y`` (B, N, 2)
    beyond COUNT_GUARD_BINS of the targets found and inside the range gate (0 where
    ``y`` is exactly 0)."""
    energy, near = _energy(y, fit, oversample, COUNT_GUARD_BINS)
    if fit.gate is not None:
        energy[:, fit.gate.outside] = 0.0
        near |= fit.gate.outside
    mean = energy.sum(axis=1) / np.maximum(energy.shape[1] - near.sum(axis=1), 1)
    peak = energy.max(axis=1)
    return np.divide(peak, mean, out=np.zeros_like(peak), where=mean > 0)


def _count_statistic(fit: _Fit, codes: _Codes, oversample: int) -> np.ndarray:
    """The count test's statistic (B,), peak over mean of two residuals, the smaller:

    * the linear residual ``Z - xi - model``: white when the quantizer is linear on
      average over the dither (alpha = 1: ``E Q(x + xi) = x``), but with alpha < 1 it
      carries the quantizer's harmonics of strong targets;
    * the score of the likelihood (``Z - E[Z | model, xi]`` per code, the generalized
      residual): free of those harmonics, but not white while the likelihood is
      sharper or softer than the noise (noiseless frames at the greedy stage).

    A frame passes only if both show a peak, so the false-alarm rate holds wherever
    either residual is white. Unquantized frames: the linear residual."""
    ratio = _peak_ratio(_residual(codes, fit), fit, oversample)
    if codes.bits is None:
        return ratio
    b = fit.nu.shape[0]
    score = np.ascontiguousarray(-fit.g).reshape(b, codes.n, 4).view(complex)
    return np.minimum(ratio, _peak_ratio(score, fit, oversample))


def _detect(fit: _Fit, codes: _Codes, oversample: int) -> np.ndarray:
    """Range (bins, (B,)) of the peak of the joint energy of the residual's back
    projection on a grid of ``oversample`` points a bin, refined by a parabola."""
    n = codes.n
    b, t = fit.nu.shape
    if t == 0 or codes.bits is None:
        y = _residual(codes, fit)
    else:
        y = np.ascontiguousarray(-fit.g).reshape(b, n, 4).view(complex)  # the score, (B, N, 2)
    size = oversample * n
    energy, _ = _energy(y, fit, oversample, MIN_SEPARATION_BINS)  # not within a bin of a target found
    if fit.gate is None:
        peak = np.argmax(energy, axis=1)
    else:  # the peak inside the gate (-1: below any energy, so also a residual of zeros peaks inside)
        peak = np.argmax(np.where(fit.gate.outside, -1.0, energy), axis=1)
    left, centre, right = (np.take_along_axis(energy, ((peak + d) % size)[:, None], axis=1)[:, 0] for d in (-1, 0, 1))
    curv = left - 2 * centre + right
    off = np.where(curv < 0, 0.5 * (left - right) / np.where(curv < 0, curv, -1.0), 0.0)
    nu = (peak + np.clip(off, -0.5, 0.5)) / oversample
    return nu if fit.gate is None else np.clip(nu, fit.gate.lo, fit.gate.hi)


def _amplitude_at(codes: _Codes, fit: _Fit, nu0: np.ndarray) -> np.ndarray:
    """Least-squares amplitudes (B, 2) of one target at ``nu0`` (bins) in ``Z - xi - model``."""
    n, ramps = codes.n, codes.ramps
    y = _residual(codes, fit)
    w = _atoms(nu0[:, None], fit.kc)[:, 0]
    return np.einsum("bn,bnp->bp", np.conj(w), y) / (ramps * n)


def _ifft(x: np.ndarray, size: int | None = None, axis: int = -1) -> np.ndarray:
    """Inverse FFT (zero-padded to ``size`` points) along ``axis``: scipy's when it
    imports (the same pocketfft as numpy's, with less overhead a call: most of a frame's
    FFT cost at B = 1), else numpy's."""
    global _fft_module
    if _fft_module is None:
        try:
            import scipy.fft as _fft_module
        except ImportError:
            _fft_module = np.fft
    return _fft_module.ifft(x, n=size, axis=axis)


_fft_module = None


_NOT_FINITE = "cml: Z holds values that are not finite"
_NOT_FINITE_DITHER = "cml: the dither holds values that are not finite"
_NOT_LEVELS = ("cml: Z is not a {bits}-bit quantized frame of step delta: its real and imaginary parts must be "
               "delta (q + 1/2) with q an integer in [{lo}, {hi}]")


def check_frames_compiled(z: np.ndarray, xi: np.ndarray, delta: np.ndarray, bits: int, codes: bool) -> np.ndarray:
    """:func:`pipeline.dsp.cml._check`'s finite and level checks of B quantized frames ``z``
    (values (B, M, 2) complex, or ``codes``) and their dither ``xi`` (B, M, 2) complex in one
    compiled pass (:func:`pipeline.dsp.cml_detect_kernels.frame_faults`); returns ``z``
    (values: C-contiguous) or raises ParameterError."""
    b, half = z.shape[0], 1 << (bits - 1)
    z = z if codes else np.ascontiguousarray(z)
    zr = np.empty((b, 0)) if codes else z.view(float).reshape(b, -1)
    fault = _kernels().frame_faults(zr, np.ascontiguousarray(xi).view(float).reshape(b, -1), delta, half)
    if fault:
        raise ParameterError({1: _NOT_FINITE, 2: _NOT_FINITE_DITHER}.get(fault) or
                             _NOT_LEVELS.format(bits=bits, lo=-half, hi=half - 1))
    return z


_buffers = threading.local()


def _padded(shape: tuple[int, int, int, int], n: int) -> np.ndarray:
    """A (B, S, 2, L) complex buffer of this thread whose points beyond N stay zero (the
    inverse FFT's padding: only the first ``n`` points of each row are ever written): the
    first B frames of one buffer per (S, L, n), as large as the largest block seen (at most
    :data:`pipeline.dsp.cml.BLOCK_FRAMES`: 8 MB for S = 2, L = 2048)."""
    cache = getattr(_buffers, "cache", None)
    if cache is None:
        cache = _buffers.cache = {}
    b, key = shape[0], shape[1:] + (n,)
    buf = cache.get(key)
    if buf is None or buf.shape[0] < b:
        if buf is None and len(cache) >= 4:  # a few grids live at once: keep the memory bounded
            cache.clear()
        buf = cache[key] = np.zeros(shape, dtype=complex)
    return buf[:b]


def residual_compiled(codes: _Codes, fit: _Fit, score: bool = False, residual: bool = False,
                      oversample: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_residual` (B, N, 2) compiled, and a (B, S, 2, ``oversample`` N) buffer whose
    first N points per antenna hold the residual (``residual``) then the score ``-g``
    (``score``), the rest zeros (:func:`pipeline.dsp.cml_detect_kernels.sources`)."""
    if codes.folded is None:
        _residual(codes, fit)
    b, n = fit.mu.shape[:2]
    y = np.empty((b, n, 2), dtype=complex)
    buf = _padded((b, int(residual) + int(score), 2, oversample * n), n)
    g = fit.g if score else fit.mu
    _kernels().sources(codes.folded.view(float).reshape(b, n, 4), fit.mu.reshape(b, n, 4), g.reshape(b, n, 4),
                       float(codes.ramps), residual, score, y.view(float).reshape(b, n, 4), buf)
    return y, buf


def _back_projections(codes: _Codes, fit: _Fit, oversample: int, count: bool, given: bool, decide: bool):
    """What the detect kernel reads: the linear residual (B, N, 2), the inverse FFTs (B, S, 2,
    L) of the sources it needs, how many the count test reads and which detection reads, the
    sources before their FFT (B, S, 2, L) and the fine grid's twiddles, the run tables and
    the gate's weights and count of points (:func:`_coarse_grid`): L = COARSE_PER_BIN N
    (:mod:`pipeline.dsp.cml_count_kernels`) when ``oversample`` is a multiple of it beyond
    it, else ``oversample`` N, and so for the count test alone (``given``) unless it only
    ``decide``s (the exact statistic of a residual without a target is cheaper on the full
    grid: the coarse search then sums many cells)."""
    on_score = codes.bits is not None and not given and fit.nu.shape[1] > 0  # detection on the likelihood's score
    with_residual = count or (not given and not on_score)
    with_score = codes.bits is not None and (count or on_score)
    coarse = (not given or decide) and oversample % COARSE_PER_BIN == 0 and oversample > COARSE_PER_BIN
    y, buf = residual_compiled(codes, fit, with_score, with_residual, COARSE_PER_BIN if coarse else oversample)
    sources = buf.shape[1]
    u = _ifft(buf) if sources else buf
    grid = _coarse_grid(codes.n, oversample, fit.gate) if coarse else _NO_GRID
    return y, u, (sources if count else 0), (-1 if given else sources - 1 if on_score else 0), buf, grid


def _coarse_grid(n: int, oversample: int, gate) -> tuple:
    """The coarse grid's constants of the detect kernel: the fine grid's twiddles
    (:func:`_twiddles`), COARSE_RHO, the run tables (:func:`_run_tables`), and the gate's
    weights (Lc + 1,) and count of points inside
    (:func:`pipeline.dsp.cml_count_kernels.gate_weights`; no gate: one unused 0, and 0), kept per grid
    and gate."""
    size, lc = oversample * n, COARSE_PER_BIN * n
    tables = _run_tables(n, size, lc)
    if gate is None:
        return _twiddles(size), COARSE_RHO, tables, _NO_WEIGHTS, 0
    key = (id(gate.outside), lc)
    kept = _gate_weights.get(key)
    if kept is None or kept[0]() is not gate.outside:
        if len(_gate_weights) >= 8:
            _gate_weights.clear()
        weights = np.empty(lc + 1)
        inside = _kernels().gate_weights(gate.outside, tables, lc, weights)
        weights.flags.writeable = False
        kept = _gate_weights[key] = (weakref.ref(gate.outside), weights, int(inside))
    return _twiddles(size), COARSE_RHO, tables, kept[1], kept[2]


_gate_weights: dict = {}
_NO_WEIGHTS = np.zeros(1)
_NO_WEIGHTS.flags.writeable = False


def _run_tables(n: int, size: int, lc: int) -> np.ndarray:
    """(ratio, 2 Lc) float, ratio = ``size`` / ``lc``: ``tables[phi, j] = G(phi + ((-j) mod Lc)
    ratio)``, where ``G(x) = F(x) - x / Lc``, ``F(x) = sum_{j < x} f(j)`` and ``f(j) = (1 / Lc)
    sin((2N - 1) pi j / L) / sin(pi j / L)`` interpolates the fine energy (L = ``size``
    points) from the coarse one: ``E_fine[l] = sum_k E_coarse[k] f(l - k ratio)``; G is
    L-periodic (f sums to L / Lc over a period). The prefix sums in extended precision
    (``np.longdouble``; where it is a double, G to ~1e-14). Kept per grid (read-only)."""
    key = (n, size, lc)
    table = _run_table_cache.get(key)
    if table is None:
        if len(_run_table_cache) >= 8:
            _run_table_cache.clear()
        j = np.arange(size)
        pi = np.longdouble("3.14159265358979323846264338327950288")
        num = np.sin(pi * ((2 * n - 1) * j % (2 * size)) / size)  # arguments reduced exactly, then scaled
        den = np.sin(pi * j / size)
        f = np.divide(num, den, out=np.full(size, np.longdouble(2 * n - 1)), where=j > 0) / lc
        g = (np.concatenate([np.zeros(1, dtype=np.longdouble), np.cumsum(f)[:-1]]) - j / np.longdouble(lc))
        ratio, k = size // lc, np.arange(2 * lc)
        table = np.ascontiguousarray(g[(np.arange(ratio)[:, None] + ((-k) % lc)[None, :] * ratio) % size], dtype=float)
        table.flags.writeable = False
        _run_table_cache[key] = table
    return table


_run_table_cache: dict[tuple[int, int, int], np.ndarray] = {}


def _twiddles(size: int) -> np.ndarray:
    """``exp(2 pi i k / size)`` (size,) complex, kept per size (read-only)."""
    table = _twiddle_tables.get(size)
    if table is None:
        if len(_twiddle_tables) >= 8:
            _twiddle_tables.clear()
        table = np.exp(2j * np.pi * np.arange(size) / size)
        table.flags.writeable = False
        _twiddle_tables[size] = table
    return table


_twiddle_tables: dict[int, np.ndarray] = {}
_NO_TABLE = np.zeros(0, dtype=complex)
_NO_TABLE.flags.writeable = False
_NO_TABLES = np.zeros((0, 0))
_NO_TABLES.flags.writeable = False
_NO_GRID = (_NO_TABLE, COARSE_RHO, _NO_TABLES, _NO_WEIGHTS, 0)


def _gate_args(gate):
    return (_NO_GATE if gate is None else gate.outside, gate is not None, 0.0 if gate is None else float(gate.lo),
            0.0 if gate is None else float(gate.hi))


_NO_GATE = np.zeros(1, dtype=bool)
_NO_GATE.flags.writeable = False  # as a gate's (pipeline.dsp.cml._gate): one compiled signature


def detect_compiled(codes: _Codes, fit: _Fit, oversample: int, count: bool, nu0: np.ndarray | None = None,
                    threshold: float | None = None) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
    """:func:`_count_statistic` (``count``; else None), :func:`_detect` (unless ``nu0`` (B,)
    bins is given) and :func:`_amplitude_at` there, with the per-frame work compiled
    (:func:`pipeline.dsp.cml_detect_kernels.detect`): the residuals written by one kernel,
    one inverse FFT of the block, then one kernel call. Returns the statistic (B,), the
    ranges (B,) in bins and the amplitudes (B, 2). ``threshold`` (linear): the statistic
    only decides ``statistic >= threshold`` (reaches it exactly when the exact one does;
    cheaper), else it is exact."""
    given = nu0 is not None
    decide = count and threshold is not None
    y, u, count_sources, detect_source, src, grid = _back_projections(codes, fit, oversample, count, given, decide)
    b = y.shape[0]
    stat = np.zeros(b)
    nu_out = np.array(nu0, dtype=float) if given else np.empty(b)
    amp = np.empty((b, 2), dtype=complex)
    _kernels().detect(u, src, *grid, y, fit.kc, codes.ramps, np.ascontiguousarray(fit.nu, dtype=float),
                      np.ascontiguousarray(fit.live), oversample, COUNT_GUARD_BINS, MIN_SEPARATION_BINS,
                      *_gate_args(fit.gate), count_sources, detect_source, float(threshold) if decide else -1.0,
                      np.ones(b, dtype=bool), stat, nu_out, amp)
    return (stat if count else None), nu_out, amp


def add_target_compiled(codes: _Codes, fit: _Fit, oversample: int, threshold: float | None, active: np.ndarray,
                        sigma: np.ndarray, iters: int, amp_cap: np.ndarray) -> bool:
    """One greedy stage, compiled: the count test (``threshold``, linear; None: none) updating
    ``active`` (B,) bool in place, the detection of a new target, its amplitudes and
    ``iters`` refinement steps at ``sigma`` (B,) of all the targets
    (:func:`pipeline.dsp.cml_detect_kernels.add_target`). Returns False (``fit`` unchanged)
    when no frame holds a new target."""
    y, u, count_sources, detect_source, src, grid = _back_projections(codes, fit, oversample, threshold is not None,
                                                                      False, True)
    b, n = fit.mu.shape[:2]
    mu, g, h = np.empty((b, n, 2, 2)), np.empty((b, n, 2, 2)), np.empty((b, n, 2, 2))
    found, nu, amp, live, lm, nll, level = _kernels().add_target(
        u, src, *grid, y, fit.kc, codes.ramps, np.ascontiguousarray(fit.nu, dtype=float),
        np.ascontiguousarray(fit.amp, dtype=complex), np.ascontiguousarray(fit.live), oversample, COUNT_GUARD_BINS,
        MIN_SEPARATION_BINS, *_gate_args(fit.gate), count_sources, detect_source,
        -1.0 if threshold is None else float(threshold), active, codes.kind, _LIK[fit.likelihood], codes.ka, codes.kb,
        sigma, iters, amp_cap, MAX_RANGE_STEP_BINS, mu.reshape(b, n, 4), g.reshape(b, n, 4), h.reshape(b, n, 4))
    if found:
        fit.nu, fit.amp, fit.live, fit.lm, fit.nll, fit.sigma = nu, amp, live, lm, nll, level
        fit.mu, fit.g, fit.h, fit.w = mu, g, h, None
    return found


def finish_compiled(fit: _Fit, codes: _Codes, config, levels: np.ndarray, adapt: bool, amp_cap: np.ndarray, k: int,
                    cap_db: float) -> tuple:
    """``fit.run(levels, amp_cap, adapt)`` then :func:`pipeline.dsp.cml._result` (statistic
    capped at ``cap_db``), in one kernel call (:func:`pipeline.dsp.cml_detect_kernels.finish`).
    Returns the fields of a :class:`pipeline.dsp.cml.CmlResult`."""
    b, n = fit.mu.shape[:2]
    nu, amp = np.ascontiguousarray(fit.nu, dtype=float), np.ascontiguousarray(fit.amp, dtype=complex)
    mu, g, h = (np.ascontiguousarray(v, dtype=float).reshape(b, n, 4) for v in (fit.mu, fit.g, fit.h))
    sigma, gate = fit.sigma.astype(float), fit.gate
    out = (np.empty((b, k)), np.empty((b, k, 2), dtype=complex), np.empty((b, k)), np.empty((b, k), dtype=bool))
    _kernels().finish(codes.kind, _LIK[fit.likelihood], codes.ka, codes.kb, fit.kc, nu, amp,
                      np.ascontiguousarray(fit.live), fit.lm.astype(float), levels, adapt, WRONG_RMS_PER_SIGMA,
                      np.ascontiguousarray(amp_cap, dtype=float), 0.0 if gate is None else float(gate.lo),
                      0.0 if gate is None else float(gate.hi), gate is not None, MAX_RANGE_STEP_BINS, mu, g, h,
                      fit.nll.astype(float), sigma, codes.folded.view(float).reshape(b, n, 4), float(codes.ramps),
                      config.range_resolution_m, 4.0 * np.pi / config.c_m_s * config.f0_hz, gate is None, cap_db, *out)
    return out[0], out[1], out[2], sigma, out[3]


def warm_compiled(codes: _Codes, fit: _Fit, config, nu_all: np.ndarray, live_all: np.ndarray, targets: int,
                  sigma: np.ndarray, steps: int, levels: np.ndarray, adapt: bool, amp_cap: np.ndarray, k: int,
                  cap_db: float) -> tuple:
    """The warm start of :func:`pipeline.dsp.cml._refine_warm` from the ranges ``nu_all`` (B, K)
    bins (``live_all``: given, first), then its result, in one kernel call
    (:func:`pipeline.dsp.cml_detect_kernels.warm`); ``fit`` (empty) takes the refined
    targets. Returns the fields of a :class:`pipeline.dsp.cml.CmlResult`."""
    b, n = fit.mu.shape[:2]
    mu, g, h = np.empty((b, n, 2, 2)), np.empty((b, n, 2, 2)), np.empty((b, n, 2, 2))
    gate = fit.gate
    out = (np.empty((b, k)), np.empty((b, k, 2), dtype=complex), np.empty((b, k)), np.empty((b, k), dtype=bool))
    fit.nu, fit.amp, fit.live, fit.lm, fit.nll, fit.sigma = _kernels().warm(
        np.ascontiguousarray(nu_all, dtype=float), np.ascontiguousarray(live_all), targets, fit.kc, float(codes.ramps),
        codes.folded.view(float).reshape(b, n, 4), codes.kind, _LIK[fit.likelihood], codes.ka, codes.kb,
        np.ascontiguousarray(sigma, dtype=float), steps, np.ascontiguousarray(levels, dtype=float), adapt,
        WRONG_RMS_PER_SIGMA, np.ascontiguousarray(amp_cap, dtype=float), 0.0 if gate is None else float(gate.lo),
        0.0 if gate is None else float(gate.hi), gate is not None, MAX_RANGE_STEP_BINS, config.range_resolution_m,
        4.0 * np.pi / config.c_m_s * config.f0_hz, gate is None, cap_db, mu.reshape(b, n, 4), g.reshape(b, n, 4),
        h.reshape(b, n, 4), *out)
    fit.mu, fit.g, fit.h, fit.w = mu, g, h, None
    return out[0], out[1], out[2], fit.sigma, out[3]
