"""Continuous maximum likelihood (CML): off-grid ranges from quantized or full frames.

Model (DESIGN.md, eq. 2), for frames of whole ramps (``M = R N``,
``f_m = f0 + B (m mod N) / N``)::

    Gamma_{m,p} = sum_t a_{t,p} exp(-i 4 pi f_m r_t / c),   r_t in [0, N dR)

with one continuous range ``r_t`` and one complex amplitude per antenna ``a_{t,1}``,
``a_{t,2}`` per target (angle = :func:`radar_driver.model.angle_from_antennas_rad`).

Decoding is greedy, as in NOMP (Mamandipoor et al., arXiv 1509.01942):

1. **Detect**: back-project a residual (folded over the ramps, zero-padded inverse FFT
   of ``oversample * N`` points) and take the peak of the joint energy
   ``|U1|^2 + |U2|^2`` at least a range bin away from the targets already found. The
   residual is ``Z - xi`` for the first target (full frames: ``Z``), then the score of
   the likelihood in each measurement: for quantized codes it sits on the few codes the
   current model gets wrong, which is far less noisy than ``Z - xi - model``.
2. **Refine**: Levenberg--Marquardt steps (Gauss--Newton, a step kept only when the
   likelihood improves) on the negative log-likelihood of the codes given the known
   dither, over all the parameters of all the targets found so far at once (5 reals a
   target: range and two complex amplitudes). This joint step does what NOMP's cyclic
   re-refinement does -- a strong off-grid target's sidelobes no longer hide a weak
   one -- with one likelihood evaluation a step for all the targets.

Likelihood of each real measurement ``lambda = Re/Im (Gamma_model + xi)``, with the
logistic ``F(x) = 1 / (1 + exp(-x))`` of scale ``T = sigma_eff / 1.702`` (the logistic
closest to a Gaussian of std ``sigma_eff``):

* b bits (b >= 1): ``P(code) = F((hi - lambda) / T) - F((lo - lambda) / T)`` for the
  code's cell ``[lo, hi)``, the two saturated end cells open (1 bit: ``F(s lambda / T)``
  for the sign ``s``);
* unquantized (``bits=None``): least squares.

``likelihood="gaussian"`` uses the exact ``Phi((hi - lambda) / s) - Phi((lo - lambda) / s)``
instead (a stable log in both tails); measured, it is no more accurate than the logistic
under noise (README) and costs more, so the logistic is the default.

The per-frame work (the likelihood, its derivatives and the Levenberg--Marquardt steps) runs
in compiled kernels, one frame at a time (:mod:`pipeline.dsp.cml_kernels`, ``engine="numba"``);
``engine="numpy"`` is the vectorized reference they are tested against.

``sigma_eff`` (frame units) starts at ``max(delta / 4, noise_sigma)`` for the greedy
stage, then falls geometrically over ``anneal`` levels (one step each) to its floor
``max(delta / M, noise_sigma)`` (``delta / M``: the size of the cell of amplitudes
consistent with M codes). When ``noise_sigma`` is not given, no level is sharper than the
noise estimated from the codes the current model gets wrong: under Gaussian noise of std
sigma (and a dither or signal spread wider than sigma) their RMS distance to their cell is
``sigma sqrt(2/3)``. A noisy frame is thus decoded with its noise's likelihood, not a
sharper one. (Without dither the 1-bit codes do not fix the scale of the amplitudes and the
noise together: the estimate runs high and the likelihood is softer than it could be.)
Unquantized frames get ``anneal`` more least-squares steps instead.

With a range gate (:mod:`pipeline.dsp.gate`) detection looks only at the points of the
oversampled grid inside it, the count test's peak and mean are taken there, and every
refinement step is clamped to it: a target never leaves the gate (ranges then in
``[min_range_m, max_range_m]``, not wrapped).

Internally ranges are in bins (``nu = r / dR``) and amplitudes are referred to the middle
of the sweep (``b = a exp(-i 2 pi nu (f0 / B + (N - 1) / (2 N)))``), which decorrelates
range from phase; the results are given in the model's terms.

Shapes: frames (B, M, 2) complex (measurement, antenna); per-target arrays (B, K),
strongest first; amplitudes (B, K, 2).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import lru_cache

import numpy as np

from radar_driver.limits import MAX_BITS
from radar_driver.model import RadarConfig, range_phase

from pipeline.dsp.cml_detect import _amplitude_at, _count_statistic, _detect, _kernels as detect_kernels, _residual, \
    _NOT_FINITE, _NOT_FINITE_DITHER, _NOT_LEVELS, add_target_compiled, check_frames_compiled, detect_compiled, \
    finish_compiled, residual_compiled, warm_compiled
from pipeline.dsp.cml_fit import (DEFAULT_ENGINE, DEFAULT_LIKELIHOOD, ENGINES, HAVE_NUMBA, LIKELIHOODS,  # noqa: F401
                      _Codes, _Fit, _Gate, centred_indices)
from pipeline.errors import ParameterError
from pipeline.dsp import cml_warmup
from pipeline.dsp.cml_warmup import kernels_ready  # noqa: F401 (cml's API)
from pipeline.dsp.gate import RangeGate, check_gate
from pipeline.dsp.localize import STATISTIC_CAP_DB, Detections, cfar_threshold, to_db

def warm_up_kernels(wait: bool | str = False) -> None:
    """Load (or compile) :func:`cml`'s kernels in a daemon thread started once, 1-bit codes
    first; ``wait``: True until every kind is loaded, ``"common"`` until 1-bit codes' are
    (:func:`pipeline.dsp.cml_warmup.warm_up_kernels`)."""
    cml_warmup.warm_up_kernels(cml, wait)


#: refinement steps after each detection: one is enough, the annealing refines all the targets
#: together after the last detection (measured, 2 000 off-grid scenes a case, K 1-3, K auto,
#: alpha 1 and 0.45, sigma 0-0.1, unquantized: errors the same or smaller than with 3 steps;
#: with none the weaker of two targets is found worse at alpha 0.45)
DEFAULT_ITERS = 1
#: ... but quantized frames without a dither, whose codes do not fix the amplitudes' scale,
#: need three (K = 2 with one: median error 0.69 -> 0.76 m on the grid, 0.46 -> 0.51 m off it)
UNDITHERED_ITERS = 3
#: first sigma_eff, in units of delta
SIGMA_START = 0.25
#: frames decoded at once: the likelihood's work arrays (B x 4M float32 each) stay in cache
BLOCK_FRAMES = 64
#: independent cells a bin of the count test's search is worth (its peak is sought on the
#: oversampled grid, between the bins too); measured on target-free residuals (README)
SEARCH_CELLS_PER_BIN = 3.0


@dataclass(frozen=True)
class CmlResult:
    """Targets found by :func:`cml`; per-target arrays strongest first.

    range_m : (B, K) ranges in [0, N dR), m (with a range gate: inside it).
    amplitudes : (B, K, 2) complex amplitudes ``a_{t,p}`` of the model, frame units.
    statistic_db : (B, K) detection statistic, dB: the target's joint power
        ``|a1|^2 + |a2|^2`` over the mean joint power per range bin of the back
        projection of the final residual (``Z - xi - model``).
    sigma_eff : (B,) the last ``sigma_eff`` of the likelihood (std of each real part,
        frame units); for unquantized frames the RMS of the residual.
    present : (B, K) bool; with a count test (``pfa``) the targets past a frame's count
        are False (their other entries are meaningless), else all True.
    """

    range_m: np.ndarray
    amplitudes: np.ndarray
    statistic_db: np.ndarray
    sigma_eff: np.ndarray
    present: np.ndarray

    def detections(self, config: RadarConfig) -> Detections:
        """The same targets as :class:`pipeline.dsp.localize.Detections`."""
        return cml_detections(self, config)


def cml_detections(result: CmlResult, config: RadarConfig) -> Detections:
    """Range, angle (from the phase between the antennas), position, amplitude
    ``sqrt((|a1|^2 + |a2|^2) / 2)`` and nearest range bin of each target of ``result``: the
    operations of :func:`radar_driver.model.angle_from_antennas_rad` and
    :func:`~radar_driver.model.polar_to_xy` in their order (the same bits), fewer numpy calls."""
    a = result.amplitudes
    c, per_phase, dr, n = _detection_constants(config)
    x = a[..., 1] * np.conj(a[..., 0])
    s = c * np.arctan2(x.imag, x.real) / per_phase  # np.angle, then the arcsin's argument
    angle = np.arcsin(np.minimum(np.maximum(s, -1.0), 1.0))  # np.clip's result, NaN kept
    r = result.range_m
    p = r * np.exp(1j * angle)
    power = np.abs(a)
    np.square(power, out=power)
    amp = np.sqrt((power[..., 0] + power[..., 1]) / 2.0)  # the sum over the 2 antennas
    bins = np.rint(np.where(np.isnan(r), 0.0, r) / dr).astype(np.int64) % n
    values = (r, np.rad2deg(angle), p.real, p.imag, amp)
    present = result.present
    if present.all():
        return Detections(*values, bins, result.statistic_db)
    present = present.astype(bool)  # a copy; then Detections.masked(present)'s, without the unmasked Detections
    return Detections(*(np.where(present, v, np.nan) for v in values), np.where(present, bins, -1),
                      np.where(present, result.statistic_db, np.nan), present)


@lru_cache(maxsize=16)
def _detection_constants(config: RadarConfig) -> tuple[float, float, float, int]:
    """c (m/s), the phase (rad) per unit of the arcsin's argument, dR (m) and N, computed as the model does."""
    return (config.c_m_s, 2.0 * np.pi * config.f0_hz * config.d_m, config.range_resolution_m,
            config.samples_per_ramp)


def model_frames(range_m: np.ndarray, amplitudes: np.ndarray, config: RadarConfig, ramps: int) -> np.ndarray:
    """``Gamma_{m,p} = sum_t a_{t,p} exp(-i 4 pi f_m r_t / c)`` for ``ramps`` whole ramps.

    range_m : (B, K), m; amplitudes : (B, K, 2) complex. Returns (B, ramps N, 2) complex.
    """
    f = config.frequencies_hz(np.arange(config.samples_per_ramp))
    steer = range_phase(f[None, :, None], np.asarray(range_m, dtype=float)[:, None, :], config)  # (B, N, K)
    ramp = np.einsum("bnk,bkp->bnp", steer, np.asarray(amplitudes, dtype=complex))
    return np.tile(ramp, (1, ramps, 1))


# -- checks -------------------------------------------------------------------------------
def _is_int(v) -> bool:
    return type(v) is int or (isinstance(v, (int, np.integer)) and not isinstance(v, bool))


@lru_cache(maxsize=32)
def _dtype_kind(dtype: np.dtype) -> tuple[bool, bool]:
    """Whether ``dtype`` is an integer (codes) and a number, once per dtype (issubdtype is slow)."""
    return bool(np.issubdtype(dtype, np.integer)), bool(np.issubdtype(dtype, np.number))


_MIN, _MAX = np.minimum.reduce, np.maximum.reduce  # ndarray.min and max without their Python wrappers


def _per_frame(name: str, value, b: int, positive: bool) -> np.ndarray:
    """A scalar or (B,) array of finite values > 0 (``positive``) or >= 0, as (B,) floats (the
    common case, (B,) float64, by two reductions: NaN fails both)."""
    if type(value) is np.ndarray and value.dtype == np.float64 and value.shape == (b,) and b and (
            (_MIN(value) > 0.0) if positive else (_MIN(value) >= 0.0)) and _MAX(value) < np.inf:
        return value if value.flags.c_contiguous and value.flags.writeable else value.copy()  # numba's signature
    try:
        v = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ParameterError(f"cml: {name}={value!r} must be a number or ({b},) numbers") from None
    bad = ~np.isfinite(v) | ((v <= 0) if positive else (v < 0))
    if v.ndim > 1 or (v.ndim == 1 and v.shape != (b,)) or np.any(bad):
        raise ParameterError(f"cml: {name} must be a finite value {'> 0' if positive else '>= 0'} or ({b},) of "
                             f"them, got shape {v.shape}" + (f", values {v[bad][:3].tolist()}" if v.ndim <= 1 and
                                                             np.any(bad) else ""))
    return np.broadcast_to(v, (b,)).astype(float)


def _check(z, xi, delta, bits, config, k, noise_sigma, iters, anneal, oversample, gate=None, compiled=False):
    z = np.asarray(z)
    integer, number = _dtype_kind(z.dtype)
    codes = z.ndim == 4 and integer  # the quantizer's codes
    if codes and (z.shape[-2:] != (2, 2) or bits is None):
        raise ParameterError(f"cml: codes must have shape (B, M, 2, 2) and bits given, got {z.shape}, bits={bits!r}")
    if not codes and (z.ndim != 3 or z.shape[-1] != 2):
        raise ParameterError(f"cml: Z must have shape (B, M, 2) (or codes (B, M, 2, 2) integers), got {z.shape}")
    if not number:
        raise ParameterError(f"cml: Z must be numbers, got dtype {z.dtype}")
    b, m = z.shape[:2]
    n = config.samples_per_ramp
    if m == 0 or m % n:
        raise ParameterError(f"cml: M={m} is not a whole number of ramps of N={n} samples")
    in_kernel = compiled and bits is not None  # the finite and level checks in one compiled pass
    if not codes and not in_kernel and not np.all(np.isfinite(z)):
        raise ParameterError(_NOT_FINITE)
    if not _is_int(k) or not 1 <= k <= n // 2:
        raise ParameterError(f"cml: k={k!r} must be an integer in [1, N/2 = {n // 2}]")
    for name, value, lo in (("iters", iters, 0), ("anneal", anneal, 0), ("oversample", oversample, 1)):
        if not _is_int(value) or not lo <= value <= 1000:
            raise ParameterError(f"cml: {name}={value!r} must be an integer in [{lo}, 1000]")
    if noise_sigma is not None:
        noise_sigma = _per_frame("noise_sigma", noise_sigma, b, positive=False)
    if gate is not None and check_gate(gate) is not None:
        _gate(gate, config, oversample)  # checked against the radar once per gate, radar and grid
    z = z if codes else np.asarray(z, dtype=complex)
    if bits is None:
        return z, None, None, noise_sigma
    if not _is_int(bits) or not 1 <= bits <= MAX_BITS:
        raise ParameterError(f"cml: bits={bits!r} must be None (unquantized) or an integer in [1, {MAX_BITS}]")
    xi = np.zeros(z.shape[:3], dtype=complex) if xi is None else np.asarray(xi, dtype=complex)
    if xi.shape != z.shape[:3]:
        raise ParameterError(f"cml: dither shape {xi.shape} does not match Z {z.shape[:3]}")
    if not in_kernel and not np.all(np.isfinite(xi)):
        raise ParameterError(_NOT_FINITE_DITHER)
    d = _per_frame("delta", delta, b, positive=True)
    half = 1 << (bits - 1)
    if in_kernel and b:
        z = check_frames_compiled(z, xi, d, bits, codes)
    if codes and z.size and ((z.dtype.kind != "u" and z.min() < 0) or z.max() >= 1 << bits):  # levels: the range
        raise ParameterError(f"cml: codes must be integers in [0, {(1 << bits) - 1}] for {bits} bits, got "
                             f"[{z.min()}, {z.max()}]")
    if codes or in_kernel:
        return z, xi, d, noise_sigma
    level = np.stack([z.real, z.imag]) / d[None, :, None, None] - 0.5  # an integer in [-2^(b-1), 2^(b-1))
    if level.size and (np.any(np.abs(level - np.rint(level)) > 1e-6) or level.min() < -half - 1e-6
                       or level.max() > half - 1 + 1e-6):
        raise ParameterError(_NOT_LEVELS.format(bits=bits, lo=-half, hi=half - 1))
    return z, xi, d, noise_sigma


# -- the decoder ----------------------------------------------------------------------------
def cml(z: np.ndarray, xi: np.ndarray | None, delta, bits: int | None, config: RadarConfig, k: int, *,
        noise_sigma=None, iters: int | None = None, anneal: int = 6, oversample: int = 8,
        pfa: float | None = None, gate: RangeGate | None = None, engine: str | None = None,
        likelihood: str | None = None, init_range_m: np.ndarray | None = None) -> CmlResult:
    """Greedy continuous-range maximum likelihood decoder (see the module docstring).

    Parameters
    ----------
    z : (B, M, 2) complex, M = R N (whole ramps): quantized values ``Q_b(Gamma + xi)``
        (``bits`` >= 1) or full-resolution frames (``bits=None``: least squares); or the
        quantizer's integer codes (B, M, 2, 2) (:class:`pipeline.dsp.quantize.QuantizedFrames`,
        ``Z = delta (code - 2^(b-1) + 1/2)``), taken as they are: cheaper than values,
        which are checked to lie on the quantizer's grid and turned back into codes.
    xi : (B, M, 2) complex, the dither added before quantization (None: no dither);
        ignored when ``bits`` is None.
    delta : quantizer step, scalar or (B,), frame units; ignored when ``bits`` is None.
    bits : bits per real value, or None for unquantized frames.
    config : the radar configuration (N, frequencies, c).
    k : targets per frame, 1 <= k <= N/2; with ``pfa``, the most a frame can have.
    noise_sigma : std of the sensor noise on each real part, frame units, scalar or (B,);
        None: estimated from the frame. The likelihood is never sharper than the noise.
    iters : refinement steps after each detection; None: ``DEFAULT_ITERS``, or
        ``UNDITHERED_ITERS`` for quantized frames without a dither (``xi`` None).
    anneal : final levels of ``sigma_eff``, falling geometrically to its floor (one
        refinement step each); unquantized frames: more least-squares steps.
    oversample : detection grid of ``oversample * N`` ranges.
    pfa : None (exactly ``k`` targets), or decide each frame's count: before each
        detection, the peak over the mean of the joint energy of the residual's back
        projection (away from the targets found) must reach the threshold whose
        false-alarm probability on a target-free residual is ``pfa`` per frame and test
        (:func:`pipeline.dsp.localize.cfar_threshold` over ``SEARCH_CELLS_PER_BIN * N``
        cells, N the bins of the gate), on the linear residual and on the likelihood's
        score both (:func:`_count_statistic`); the first miss ends the frame's targets.
    gate : a :class:`~pipeline.dsp.gate.RangeGate`: targets are sought, tested and refined
        only inside it, and their ranges stay in it (None: the whole, circular, range axis).

    engine : "numba" (compiled kernels, :mod:`pipeline.dsp.cml_kernels`; the default when numba
        imports) or "numpy" (the vectorized reference); None: ``DEFAULT_ENGINE``.
    likelihood : "logistic" or "gaussian" (the exact Gaussian likelihood of a code given the
        dither and the noise); None: ``DEFAULT_LIKELIHOOD``.
    init_range_m : (B, J) ranges (m) to start from, NaN for none (e.g. the previous
        frame's targets: warm start), J <= k. A frame with at least one gives no greedy
        search: its amplitudes are estimated at those ranges (a target's phase turns by
        ``4 pi dr / lambda``, 5 rad for 5 mm at 24 GHz: the previous amplitudes say
        little), then ``WARM_STEPS`` refinement steps and ``WARM_ANNEAL`` levels of the
        annealing. Frames without
        one, or whose warm fit the model no longer explains (the count test, at ``pfa`` or
        else ``WARM_PFA``, finds a peak in the residual: a target appeared or moved beyond
        the steps' reach; with ``pfa`` also a target's statistic below the test's
        threshold: it vanished), are decoded from scratch.

    Returns
    -------
    CmlResult, targets strongest first (with ``pfa``: the present ones first).

    The batch is decoded in blocks of ``BLOCK_FRAMES`` frames (vectorized within a
    block): with a fixed ``k`` a frame's result does not depend on the others. With
    ``pfa``, a frame whose count is decided keeps taking refinement steps while others
    of its block look for more targets, so its estimates can move slightly with the
    batch (about 1e-5 m in range and 1 % in amplitude in a 4-bit case). About 14 evaluations of the
    likelihood and 8 Gauss--Newton systems for K = 2 (M = 512).
    """
    if iters is None:
        iters = UNDITHERED_ITERS if bits is not None and xi is None else DEFAULT_ITERS
    engine = DEFAULT_ENGINE if engine is None else engine
    likelihood = DEFAULT_LIKELIHOOD if likelihood is None else likelihood
    if engine not in ENGINES or (engine == "numba" and not HAVE_NUMBA):
        raise ParameterError(f"cml: engine={engine!r} is not available; available: "
                             f"{', '.join(e for e in ENGINES if e != 'numba' or HAVE_NUMBA)}")
    if likelihood not in LIKELIHOODS:
        raise ParameterError(f"cml: likelihood={likelihood!r} is not known; available: {', '.join(LIKELIHOODS)}")
    z, xi, delta, noise_sigma = _check(z, xi, delta, bits, config, k, noise_sigma, iters, anneal, oversample, gate,
                                       engine == "numba")
    cgate = None if gate is None else _gate(gate, config, oversample)
    threshold = None if pfa is None else _threshold(pfa, config, cgate)
    if z.shape[0] == 0:
        return CmlResult(np.zeros((0, k)), np.zeros((0, k, 2), dtype=complex), np.zeros((0, k)), np.zeros(0),
                         np.zeros((0, k), dtype=bool))
    if init_range_m is not None:
        return _warm_or_cold(z, xi, delta, bits, config, k, noise_sigma, iters, anneal, oversample, threshold, cgate,
                             engine, likelihood, _check_init(init_range_m, z.shape[0], k, config, gate))
    if z.shape[0] <= BLOCK_FRAMES:  # one block: the arrays as they are
        return _decode(z, xi, delta, bits, config, k, noise_sigma, iters, anneal, oversample, threshold, cgate, engine,
                       likelihood)
    parts = []
    for lo in range(0, z.shape[0], BLOCK_FRAMES):  # blocks small enough for the work arrays to stay in cache
        sl = slice(lo, lo + BLOCK_FRAMES)
        parts.append(_decode(z[sl], None if xi is None else xi[sl], None if delta is None else delta[sl], bits,
                             config, k, None if noise_sigma is None else noise_sigma[sl], iters, anneal, oversample,
                             threshold, cgate, engine, likelihood))
    if len(parts) == 1:
        return parts[0]
    return CmlResult(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(CmlResult)))


@lru_cache(maxsize=64)
def _gate(gate: RangeGate | None, config: RadarConfig, oversample: int) -> _Gate | None:
    """The range gate in cml's terms (None: none), checked (:meth:`RangeGate.check`) and built once
    per gate, radar and grid (a live node decodes every frame with the same)."""
    if gate is None:
        return None
    cgate = _Gate(gate.check(config), config, oversample)
    cgate.outside.flags.writeable = False
    return cgate


@lru_cache(maxsize=64)
def _threshold(pfa: float, config: RadarConfig, cgate: _Gate | None) -> float:
    """The count test's threshold (linear) at false-alarm probability ``pfa`` over the
    bins the search spans (:func:`pipeline.dsp.localize.cfar_threshold`)."""
    search_bins = config.samples_per_ramp if cgate is None else cgate.width_bins
    return cfar_threshold(pfa, SEARCH_CELLS_PER_BIN * search_bins)


def _check_init(init, b: int, k: int, config: RadarConfig, gate: RangeGate | None) -> np.ndarray:
    """``init_range_m`` as (B, k) floats in the range axis (inside the gate), NaN padded."""
    try:
        r = np.asarray(init, dtype=float)
    except (TypeError, ValueError):
        raise ParameterError(f"cml: init_range_m must be ({b}, J) numbers, got {init!r}") from None
    if r.ndim != 2 or r.shape[0] != b or r.shape[1] > k:
        raise ParameterError(f"cml: init_range_m must have shape ({b}, J) with J <= k={k}, got {r.shape}")
    top = config.samples_per_ramp * config.range_resolution_m
    if np.any(np.isinf(r)) or np.any((r < 0) | (r > top)):
        raise ParameterError(f"cml: init_range_m must be NaN or in [0, {top:g}] m")
    if gate is not None:
        r = np.where(np.isnan(r), np.nan, np.clip(r, gate.min_range_m, gate.max_range_m))
    return np.concatenate([r, np.full((b, k - r.shape[1]), np.nan)], axis=1)


def _warm_or_cold(z, xi, delta, bits, config, k, noise_sigma, iters, anneal, oversample, threshold, cgate, engine,
                  likelihood, init) -> CmlResult:
    """:func:`cml` with starting ranges ``init`` (B, k) (NaN: none): warm frames refined
    from them, the others and the warm ones the model no longer explains from scratch."""
    b = z.shape[0]
    warm_threshold = _threshold(WARM_PFA, config, cgate)
    warm = ~np.isnan(init).all(axis=1)
    out = [None] * b
    cold = np.flatnonzero(~warm)

    def sub(idx):
        return (z[idx], None if xi is None else xi[idx], None if delta is None else delta[idx],
                None if noise_sigma is None else noise_sigma[idx])

    widx = np.flatnonzero(warm)
    if widx.size:
        whole = widx.size == b <= BLOCK_FRAMES  # one block of warm frames (a live node's call): no copies
        for lo in range(0, widx.size, BLOCK_FRAMES):
            idx = widx[lo:lo + BLOCK_FRAMES]
            zz, xx, dd, nn = (z, xi, delta, noise_sigma) if whole else sub(idx)
            res, misfit = _refine_warm(zz, xx, dd, bits, config, k, nn, anneal, threshold, cgate, engine, likelihood,
                                       init if whole else init[idx], oversample, warm_threshold)
            if whole and not misfit.any():
                return res
            for j, i in enumerate(idx.tolist()):
                out[i] = None if misfit[j] else _row(res, j)
        cold = np.flatnonzero([o is None for o in out])
    whole = cold.size == b <= BLOCK_FRAMES  # one block, every frame from scratch: no copies
    for lo in range(0, cold.size, BLOCK_FRAMES):
        idx = cold[lo:lo + BLOCK_FRAMES]
        zz, xx, dd, nn = (z, xi, delta, noise_sigma) if whole else sub(idx)
        res = _decode(zz, xx, dd, bits, config, k, nn, iters, anneal, oversample, threshold, cgate, engine, likelihood)
        if whole:
            return res
        for j, i in enumerate(idx.tolist()):
            out[i] = _row(res, j)
    return CmlResult(*(np.stack([getattr(o, f.name) for o in out]) for f in fields(CmlResult)))


def _row(res: CmlResult, j: int) -> CmlResult:
    return CmlResult(*(getattr(res, f.name)[j] for f in fields(CmlResult)))


#: without a count test (k given), a warm frame goes back to a full search when its residual
#: has a peak the count test would take for a target at this false-alarm probability
WARM_PFA = 1e-3
#: refinement steps of a warm start at the greedy stage's scale, before the annealing
WARM_STEPS = 1
#: levels of the warm start's annealing (at most ``anneal``): from the greedy stage's scale
#: to the floor in fewer, larger steps, the ranges being close already
WARM_ANNEAL = 4


def _start(z, xi, delta, bits, config, noise_sigma, gate, engine, likelihood):
    """What a block's decode starts from: its codes, an empty fit, the first likelihood
    scale sigma_eff (B,), its floor (B,; None unquantized) and the largest amplitude change
    of a step (the quantizer's half range)."""
    b, m = z.shape[:2]
    n = config.samples_per_ramp
    codes = _Codes(z, xi, delta, bits, n, compiled=engine != "numpy")
    fit = _Fit(codes, centred_indices(n), b, gate, engine, likelihood)
    if bits is None:  # least squares: the scale plays no part
        return codes, fit, np.ones(b), None, np.full(b, np.inf)
    if noise_sigma is None:  # delta > 0: the maxima with a noise of 0, without computing them
        return codes, fit, SIGMA_START * delta, delta / m, delta * (1 << (bits - 1))
    return (codes, fit, np.maximum(SIGMA_START * delta, noise_sigma), np.maximum(delta / m, noise_sigma),
            delta * (1 << (bits - 1)))


def _refine_warm(z, xi, delta, bits, config, k, noise_sigma, anneal, threshold, gate, engine, likelihood, init,
                 oversample, warm_threshold):
    """Refine the targets at ``init`` (B, k) ranges (NaN: absent) of one block; returns
    the result and the frames (B,) bool the model no longer explains (:func:`cml`)."""
    b = z.shape[0]
    codes, fit, sigma, floor, amp_cap = _start(z, xi, delta, bits, config, noise_sigma, gate, engine, likelihood)
    live_all = ~np.isnan(init)
    order = np.argsort(~live_all, axis=1, kind="stable")  # the given ranges first
    init = np.take_along_axis(init, order, axis=1)
    live_all = np.take_along_axis(live_all, order, axis=1)
    nu_all = np.nan_to_num(init) / config.range_resolution_m
    targets = int(live_all.sum(axis=1).max())
    if engine != "numpy" and bits is not None and targets:  # the start, the steps and the result in one call
        levels = _warm_levels(sigma, floor, anneal) if anneal else np.empty((b, 0))
        res = CmlResult(*warm_compiled(codes, fit, config, nu_all, live_all, targets, sigma, WARM_STEPS, levels,
                                       noise_sigma is None, amp_cap, k, STATISTIC_CAP_DB))
    else:
        res = _warm_steps(codes, fit, config, k, nu_all, live_all, targets, sigma, floor, amp_cap, anneal, bits,
                          noise_sigma, oversample, engine)
    count = fit.live.sum(axis=1)
    # the residual (and the likelihood's score, at the last level) holds a peak the targets do
    # not explain: a target appeared, or one moved beyond the refinement's reach
    at = warm_threshold if threshold is None else threshold  # compiled: the statistic only decides stat >= at
    unexplained = (_count_statistic(fit, codes, oversample) if engine == "numpy" else
                   detect_compiled(codes, fit, oversample, True, np.zeros(b), at)[0]) >= at
    if threshold is None:  # k targets a frame, whatever their strength
        misfit = (count < k) | unexplained
    else:
        weakest = np.where(res.present, res.statistic_db, np.inf).min(axis=1)
        misfit = ((count < k) & unexplained) | (weakest < to_db(np.asarray(threshold, dtype=float)))  # or vanished
    return res, misfit


def _warm_steps(codes, fit, config, k, nu_all, live_all, targets, sigma, floor, amp_cap, anneal, bits, noise_sigma,
                oversample, engine) -> CmlResult:
    """:func:`_refine_warm`'s amplitudes, steps and result (the numpy engine, or unquantized)."""
    b = fit.nu.shape[0]
    for t in range(targets):  # amplitudes one at a time in the residual
        amp_t = (_amplitude_at(codes, fit, nu_all[:, t]) if engine == "numpy" else
                 detect_compiled(codes, fit, oversample, False, nu_all[:, t])[2])
        amp0 = np.where(live_all[:, t, None], amp_t, 0.0)
        fit.set(nu_all[:, :t + 1], np.concatenate([fit.amp, amp0[:, None]], axis=1), live_all[:, :t + 1])
    fit.evaluate_and_run(sigma, np.repeat(sigma[:, None], WARM_STEPS, axis=1), amp_cap)
    if bits is not None and anneal:
        fit.run(_warm_levels(sigma, floor, anneal), amp_cap, adapt=noise_sigma is None)
        sigma = fit.sigma
    if bits is None:
        fit.run(np.ones((b, anneal)), amp_cap)
        sigma = codes.wrong_rms(fit.mu)
    return _result(fit, codes, config, sigma, k)


def _warm_levels(sigma: np.ndarray, floor: np.ndarray, anneal: int) -> np.ndarray:
    """The warm start's annealing levels (B, min(anneal, WARM_ANNEAL)), from ``sigma`` to ``floor``."""
    levels_n = min(anneal, WARM_ANNEAL)
    return sigma[:, None] * ((floor / sigma) ** (1.0 / levels_n))[:, None] ** np.arange(1, levels_n + 1)


def _decode(z, xi, delta, bits, config, k, noise_sigma, iters, anneal, oversample, threshold,
            gate: _Gate | None = None, engine: str = DEFAULT_ENGINE,
            likelihood: str = DEFAULT_LIKELIHOOD) -> CmlResult:
    """:func:`cml` on one block of checked frames; ``threshold``: the count test's
    (linear), or None; ``gate``: the range gate, or None."""
    b = z.shape[0]
    codes, fit, sigma, floor, amp_cap = _start(z, xi, delta, bits, config, noise_sigma, gate, engine, likelihood)
    active = np.ones(b, dtype=bool)  # frames whose residual may still hold a target
    if threshold is not None:
        fit.evaluate(sigma)  # the score of the empty model, for the first count test
    for t in range(k):
        if engine == "numpy":
            if threshold is not None:
                active &= _count_statistic(fit, codes, oversample) >= threshold
            nu0 = None if not active.any() else _detect(fit, codes, oversample)
            amp_t = None if nu0 is None else _amplitude_at(codes, fit, nu0)
        elif add_target_compiled(codes, fit, oversample, threshold, active, sigma, iters, amp_cap):
            continue  # the statistic, the detection, the amplitudes and the refinement in one kernel call
        else:
            break
        if not active.any():
            break
        amp0 = np.where(active[:, None], amp_t, 0.0)
        fit.set(np.concatenate([fit.nu, nu0[:, None]], axis=1), np.concatenate([fit.amp, amp0[:, None]], axis=1),
                np.concatenate([fit.live, active[:, None]], axis=1))
        fit.evaluate_and_run(sigma, np.repeat(sigma[:, None], iters, axis=1), amp_cap)
    if bits is not None and anneal:
        ratio = (floor / sigma) ** (1.0 / anneal)
        levels = np.empty((b, anneal))
        levels[:] = ratio[:, None]
        levels[:, 0] *= sigma
        np.multiply.accumulate(levels, axis=1, out=levels)  # sigma ratio^j, as repeated products
        if engine != "numpy" and fit.nu.shape[1]:  # the annealing and the result in one kernel call
            return CmlResult(*finish_compiled(fit, codes, config, levels, noise_sigma is None, amp_cap, k,
                                              STATISTIC_CAP_DB))
        fit.run(levels, amp_cap, adapt=noise_sigma is None)  # adapt: not sharper than the noise the model leaves
        sigma = fit.sigma
    if bits is None:
        fit.run(np.ones((b, anneal)), amp_cap)  # least squares: polish
        sigma = codes.wrong_rms(fit.mu)
    return _result(fit, codes, config, sigma, k)


def _result(fit: _Fit, codes: _Codes, config: RadarConfig, sigma: np.ndarray, k: int) -> CmlResult:
    """The fit in the model's terms, its statistic, padded to ``k`` targets (absent ones
    last), present ones strongest first."""
    n, ramps = codes.n, codes.ramps
    b, t = fit.nu.shape
    if fit.engine != "numpy":  # the same, compiled (pipeline.dsp.cml_detect_kernels.result)
        out = (np.empty((b, k)), np.empty((b, k, 2), dtype=complex), np.empty((b, k)), np.empty((b, k), dtype=bool))
        detect_kernels().result(np.ascontiguousarray(fit.nu, dtype=float), np.ascontiguousarray(fit.amp, dtype=complex),
                                np.ascontiguousarray(fit.live), residual_compiled(codes, fit)[0],
                                float(fit.kc[0]), ramps, config.range_resolution_m,
                                4.0 * np.pi / config.c_m_s * config.f0_hz, fit.gate is None, STATISTIC_CAP_DB, *out)
        return CmlResult(out[0], out[1], out[2], sigma, out[3])
    # the axis is circular; inside a gate (within [0, N] bins) a range is not wrapped
    range_m = (fit.nu if fit.gate is not None else fit.nu % n) * config.range_resolution_m
    # a = mu at k = 0 over the carrier term there, exp(-i 4 pi f0 r / c)
    amp = fit.amp * (np.exp((-2j * np.pi / n) * fit.nu * fit.kc[0]) / range_phase(config.f0_hz, range_m, config))[
        ..., None]
    # the mean joint power a bin of the residual's back projection, |ifft(y) / R|^2 summed over the
    # antennas and averaged over the N bins: by Parseval sum |y|^2 / (N R)^2, without the FFT
    y = _residual(codes, fit).view(float)
    noise = np.einsum("bj,bj->b", y.reshape(b, -1), y.reshape(b, -1)) / float(n * ramps) ** 2
    power = (np.abs(fit.amp) ** 2).sum(axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        stat = to_db(power / noise[:, None])
    pad = k - t
    if pad:
        range_m = np.concatenate([range_m, np.full((b, pad), np.nan)], axis=1)
        amp = np.concatenate([amp, np.zeros((b, pad, 2), dtype=complex)], axis=1)
        stat = np.concatenate([stat, np.full((b, pad), np.nan)], axis=1)
        power = np.concatenate([power, np.zeros((b, pad))], axis=1)
    present = np.concatenate([fit.live, np.zeros((b, pad), dtype=bool)], axis=1)
    order = np.lexsort((-power, ~present), axis=1)  # present first, then strongest first
    take = lambda a: np.take_along_axis(a, order, axis=1)  # noqa: E731
    return CmlResult(take(range_m), np.take_along_axis(amp, order[..., None], axis=1), take(stat), sigma,
                     take(present))
