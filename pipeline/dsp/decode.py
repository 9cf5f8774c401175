"""Dither-aware decoders: beyond PBP, using the dither to reach estimates consistent
with the codes (the paper's closing remark).

A quantized frame carries its dither seed, so the decoder regenerates xi and delta and
knows, for every real measurement, the quantizer cell that ``Re/Im (Phi X + xi)`` fell
in. Two stages, both batched and on the FFT path for frames of whole ramps:

1. **QIHT** (quantized iterative hard thresholding, joint support):
   ``X <- P_Theta_K(X + mu Phi^* (Z - Q(Phi X + xi)) / M)``, starting from PBP. Forward
   ``Phi X``: the K atoms of the support on one ramp (an FFT of length N per antenna for
   large K), the same on every ramp; adjoint: fold + inverse FFT. Stopping rule: at most
   ``iters`` iterations; it stops earlier once, for 3 iterations in a row, no frame of
   the batch changed its support or its number of consistent codes.
2. **Maximum likelihood on the support** (1-bit): per antenna, the K complex amplitudes
   maximize a logistic likelihood of the codes, ``P(code | x) = sigmoid(s (a^T x + xi) /
   T)``, by Newton steps while the temperature T falls from delta/8 to delta/(2M). As T
   shrinks the estimate moves into the set of amplitudes consistent with every code, whose
   size shrinks like 1/M, where PBP's error shrinks like 1/sqrt(M). Both antennas at
   once, the sums over the codes folded over the ramps.

Cost (issue 13, ``benchmarks/bench_decoders.py``): about 0.3-0.4 ms a frame in batches
of 16-256 on one core, three times less than the first version, whose results it gives:
the same supports and QIHT amplitudes, the likelihood's amplitudes to rounding.

What was measured and kept is in the README (Monte Carlo of DESIGN.md): QIHT alone
brings the K = 1 median error from 1.2 m to about 0.1 m; the ML stage brings it to 0.08 m
and matters most for the weakest of two targets.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from radar_driver.model import RadarConfig, carrier

from pipeline import defaults
from pipeline.errors import DitherUnavailable, ParameterError
from pipeline.dsp.gate import RangeGate, boundary_skirts, check_gate
from pipeline.dsp.localize import (DEFAULT_PFA, Detections, back_project_ramps, check_pfa, detections_from_support,
                       gated_energy, grid_statistic_db, joint_energy, joint_support, localize)
from pipeline.dsp.significance import target_p_values
from pipeline.dsp.uncertainty import target_uncertainty
from pipeline.dsp.cml import DEFAULT_LIKELIHOOD, ENGINES, LIKELIHOODS, CmlOptions
from pipeline.dsp.cml.engine import resolve as resolve_engine
from pipeline.dsp.quantize import QuantizedFrames, check_bits, frame_peak

if TYPE_CHECKING:
    from pipeline.dsp.cml.decoder import CmlDecoder


class Algo(StrEnum):
    """The decoders: ``pbp`` (the paper's eq. 5, any frames), ``qiht`` (dither-aware, on the
    range grid: QIHT then 1-bit likelihood; dithered frames of whole ramps) and ``cml``
    (continuous ranges, maximum likelihood of the codes with their dither and the sensor
    noise, :mod:`pipeline.dsp.cml`; quantized or unquantized frames of whole ramps)."""

    PBP = "pbp"
    QIHT = "qiht"
    CML = "cml"


ALGOS = tuple(a.value for a in Algo)

#: the decoder of every command that localizes (:mod:`pipeline.defaults`, the one definition)
DEFAULT_ALGO = Algo(defaults.DEFAULT_ALGO)
#: the dither scale of every command that quantizes: the default decoder's best (:mod:`pipeline.defaults`)
DEFAULT_ALPHA = defaults.DEFAULT_ALPHA
if set(defaults.BEST_ALPHA) != set(ALGOS):
    raise ImportError(f"pipeline.defaults.BEST_ALPHA names {sorted(defaults.BEST_ALPHA)}, not the decoders {ALGOS}")


def default_alpha(algo: str) -> float:
    """The dither scale alpha in [0, 1] to quantize with for decoder ``algo``: its best
    (:data:`pipeline.defaults.BEST_ALPHA`); for :data:`DEFAULT_ALGO`, :data:`DEFAULT_ALPHA`."""
    return defaults.BEST_ALPHA[Algo(algo).value]


def ml_temperatures(m: int, steps: int = 8) -> np.ndarray:
    """Temperature schedule of the likelihood stage, in units of delta: ``steps`` values
    falling geometrically from 1/8 to 1/(2M) (the size of a consistent cell), then the
    last one twice more."""
    t = np.geomspace(1 / 8, 1 / (2 * m), max(steps, 1))
    return np.concatenate([t, t[-1:], t[-1:]])


@dataclass(frozen=True)
class DecoderConfig:
    """algo: an :class:`Algo` (or its name). iters / mu: QIHT iterations and step. ml:
    run the likelihood stage (1-bit only). fallback_pbp: decode frames a decoder cannot
    (qiht: without a usable dither or unquantized; qiht and cml: a frequency subset) with
    PBP instead of raising DitherUnavailable. noise_sigma: cml's sensor noise, std of I
    and of Q in frame units (None: estimated from each frame). auto_k: decide each
    frame's count (``K auto``; the K passed to :func:`decode` is then the most), by a
    CFAR test of false-alarm probability ``pfa`` per frame and test (pbp and cml).
    gate: the :class:`~pipeline.dsp.gate.RangeGate` every decoder searches inside (None: the
    whole range axis, the paper's protocol; the live localizer's default is
    :meth:`RangeGate.default <pipeline.dsp.gate.RangeGate.default>`). engine, likelihood:
    cml's (:func:`pipeline.dsp.cml.cml`; None: its defaults). motion: cml's model, a phase
    step between ramps (the default) or, False, the static one
    (:class:`~pipeline.dsp.cml.CmlOptions`). uncertainty: each cml target's uncertainty
    (``sigma_range_m``, ``sigma_angle_deg``, ``cov_range_angle``) and ``p_value``; False:
    neither (positions only, as PBP's: a Monte Carlo that scores positions, a node short of
    CPU), the targets unchanged. p_values: with the uncertainty, each target's ``p_value``
    too (False: its uncertainty alone, which is what an ellipse's coverage reads)."""

    algo: Algo = DEFAULT_ALGO
    iters: int = 10
    mu: float = 1.0
    ml: bool = True
    fallback_pbp: bool = False
    noise_sigma: float | None = None
    auto_k: bool = False
    pfa: float = DEFAULT_PFA
    gate: RangeGate | None = None
    engine: str | None = None
    likelihood: str | None = None
    motion: bool = True
    uncertainty: bool = True
    p_values: bool = True

    def __post_init__(self) -> None:
        check_gate(self.gate)
        if self.engine not in (None, *ENGINES):
            raise ParameterError(f"engine={self.engine!r} is not known; available: {', '.join(ENGINES)}")
        if self.likelihood not in (None, *LIKELIHOODS):
            raise ParameterError(f"likelihood={self.likelihood!r} is not known; available: {', '.join(LIKELIHOODS)}")
        for name in ("motion", "uncertainty", "p_values"):
            if not isinstance(getattr(self, name), bool):
                raise ParameterError(f"{name}={getattr(self, name)!r} must be True or False")
        if self.algo not in ALGOS:
            raise ParameterError(f"algo={self.algo!r} is not known; available: {', '.join(ALGOS)}")
        object.__setattr__(self, "algo", Algo(self.algo))
        check_pfa(self.pfa)
        if self.auto_k and self.algo == Algo.QIHT:
            raise ParameterError("K auto needs a decoder that tests each detection: pbp or cml (qiht projects "
                                 "on exactly K bins)")
        if self.noise_sigma is not None and not (np.isfinite(self.noise_sigma) and self.noise_sigma >= 0):
            raise ParameterError(f"noise_sigma={self.noise_sigma!r} must be a finite number >= 0 or None")
        if not (isinstance(self.iters, int) and 0 <= self.iters <= 1000):
            raise ParameterError(f"iters={self.iters!r} must be an integer in [0, 1000]")
        if not 0 < self.mu <= 4:
            raise ParameterError(f"mu={self.mu!r} must be in (0, 4]")


def forward_ramps(x: np.ndarray, config: RadarConfig, ramps: int) -> np.ndarray:
    """``Phi X`` for frames of ``ramps`` whole ramps: (B, N, 2) -> (B, ramps N, 2)."""
    g = np.fft.fft(x * _carrier(config)[None, :, None], axis=1)
    return np.tile(g, (1, ramps, 1))


def _requantize(lam: np.ndarray, d: np.ndarray, bits: int) -> np.ndarray:
    """Q_b of the real array ``lam``, ``d`` = delta broadcast against it: real values."""
    half = 1 << (bits - 1)
    return (np.clip(np.floor(lam / d), -half, half - 1) + 0.5) * d


@lru_cache(maxsize=4)
def _dft_table(n: int) -> np.ndarray:
    """exp(-2 pi i k n / N), (N frequencies, N bins); read-only."""
    kk = np.arange(n)
    t = np.exp(-2j * np.pi * np.outer(kk, kk) / n)
    t.flags.writeable = False
    return t


@lru_cache(maxsize=8)
def _carrier(config: RadarConfig) -> np.ndarray:
    """:func:`radar_driver.model.carrier` of ``config``, (N,); read-only."""
    c = carrier(config)
    c.flags.writeable = False
    return c


@lru_cache(maxsize=8)
def _atoms(config: RadarConfig) -> np.ndarray:
    """The columns of Phi on one ramp: row n is ``carrier_n exp(-2 pi i k n / N)`` over the
    frequencies k, (N bins, N frequencies) complex; read-only."""
    t = _dft_table(config.samples_per_ramp) * _carrier(config)[:, None]  # the table is symmetric
    t.flags.writeable = False
    return t


def _check(z, xi, delta, bits, config):
    z = np.asarray(z)
    if z.ndim != 3 or z.shape[-1] != 2:
        raise ParameterError(f"Z must have shape (B, M, 2), got {z.shape}")
    if xi is None:
        raise DitherUnavailable("the dither is needed (non-dithered frame or unknown seed)")
    xi = np.asarray(xi)
    if xi.shape != z.shape:
        raise ParameterError(f"dither shape {xi.shape} does not match Z {z.shape}")
    delta = np.asarray(delta, dtype=float).reshape(-1)
    if delta.shape != (z.shape[0],) or np.any(~np.isfinite(delta)) or np.any(delta <= 0):
        raise ParameterError(f"delta must be ({z.shape[0]},) finite values > 0, got shape {delta.shape}")
    check_bits(bits)
    n = config.samples_per_ramp
    if z.shape[1] % n:
        raise ParameterError(f"M={z.shape[1]} is not a whole number of ramps of {n}: the dither-aware "
                             "decoder runs on the FFT path only")
    return z, xi, delta


#: up to this K, QIHT computes ``Phi X`` from K atoms and picks the support by K arg-maxima;
#: beyond, an FFT and a partition
SMALL_K = 8


def _antenna_major(a: np.ndarray, n: int) -> np.ndarray:
    """Frames (B, R N, 2) complex as real (B, R, 2 antennas, N, 2 re/im), contiguous."""
    b, m, _ = a.shape
    t = np.ascontiguousarray(np.asarray(a, dtype=complex).reshape(b, m // n, n, 2).transpose(0, 1, 3, 2))
    return t.view(float).reshape(b, m // n, 2, n, 2)


def _strongest(u: np.ndarray, k: int, outside: np.ndarray | None = None,
               ends_bins: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """:func:`pipeline.dsp.localize.joint_support` of U held antenna-major, (B, 2, N) -> (B, K):
    the K bins of largest ``|U1|^2 + |U2|^2``, strongest first; never a bin where
    ``outside`` (N,) bool is True (a range gate, its ends ``ends_bins``), nor on the skirt of
    a return outside it (:func:`pipeline.dsp.gate.boundary_skirts`)."""
    if k > SMALL_K:
        ut = u.transpose(0, 2, 1)
        if outside is None:
            return joint_support(ut, k)
        energy = joint_energy(ut)
        energy[boundary_skirts(energy, ~outside, ends_bins)] = -1.0
        energy[:, outside] = -1.0
        return joint_support(ut, k, energy)
    p = np.square(np.ascontiguousarray(u, dtype=complex).view(float)).reshape(u.shape + (2,))  # (B, 2, N, re/im)
    energy = (p[:, 0, :, 0] + p[:, 0, :, 1]) + (p[:, 1, :, 0] + p[:, 1, :, 1])  # joint_energy's sums, in its order
    if outside is not None:
        energy[boundary_skirts(energy, ~outside, ends_bins)] = -np.inf
        energy[:, outside] = -np.inf
    b = energy.shape[0]
    rows = np.arange(b)
    top = np.empty((b, k), dtype=np.int64)
    for j in range(k):  # K small: K arg-maxima beat a partition
        top[:, j] = best = np.argmax(energy, axis=1)
        energy[rows, best] = -np.inf
    return top


def consistency(x: np.ndarray, z: np.ndarray, xi: np.ndarray, delta, bits: int, config: RadarConfig) -> np.ndarray:
    """Fraction of the real codes of each frame that ``Q(Phi X + xi)`` reproduces: (B,).

    x: (B, N, 2) estimate; z: the quantized values (B, M, 2); xi: the dither."""
    z, xi, delta = _check(z, xi, delta, bits, config)
    ramps = z.shape[1] // config.samples_per_ramp
    lam = forward_ramps(x, config, ramps) + xi
    d = delta[:, None, None]
    same = sum((np.abs(_requantize(part(lam), d, bits) - part(z)) < 1e-9 * d).sum(axis=(1, 2))
               for part in (np.real, np.imag))
    return same / (2 * z.shape[1] * 2)


def qiht(z: np.ndarray, xi: np.ndarray, delta, bits: int, config: RadarConfig, k: int, iters: int = 10,
         mu: float = 1.0, gate: RangeGate | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """QIHT from PBP. z: quantized values Z (B, M, 2); xi: the dither (B, M, 2); delta (B,);
    gate: the support only among the range bins inside it (None: all N).

    Returns (X (B, N, 2), support (B, K) strongest first, iterations run). Z is
    ``Q(Gamma + xi)``: the dither is added before quantization and not removed."""
    z, xi, delta = _check(z, xi, delta, bits, config)
    n = config.samples_per_ramp
    mask = None if check_gate(gate) is None else gate.check(config).bin_mask(config)
    amp, support, done = _qiht(_antenna_major(z, n), _antenna_major(xi, n), back_project_ramps(z, config), delta,
                               bits, config, k, iters, mu, mask, None if gate is None else gate.bins(config))
    return _scatter(amp, support, n), support, done


def _scatter(amp: np.ndarray, support: np.ndarray, n: int) -> np.ndarray:
    """X (B, N, 2): the amplitudes (B, 2, K) on the support (B, K), zero elsewhere."""
    x = np.zeros((support.shape[0], n, 2), dtype=complex)
    np.put_along_axis(x, support[:, :, None], amp.transpose(0, 2, 1), axis=1)
    return x


def _qiht(zr: np.ndarray, xr: np.ndarray, u0: np.ndarray, delta: np.ndarray, bits: int, config: RadarConfig, k: int,
          iters: int, mu: float, mask: np.ndarray | None = None,
          ends_bins: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`qiht` on checked frames: zr, xr (B, R, 2, N, 2) from :func:`_antenna_major`;
    u0 the back projection (B, N, 2); mask: the range bins (N,) a support may hold (a
    range gate whose ends are ``ends_bins``; None: all), never the skirt of a return outside
    it (:func:`pipeline.dsp.gate.boundary_skirts`). Returns (amplitudes (B, 2, K) on the support, support (B, K),
    iterations run).

    X lives as its K amplitudes a frame: ``Phi X`` on a ramp is K atoms (an FFT for large
    K), and ``X + step`` is the step with the amplitudes added on the support."""
    b, ramps, _, n, _ = zr.shape
    car, atoms = _carrier(config), _atoms(config)
    back = np.conj(car)
    scale = mu * (1.0 / ramps)  # mu N / M
    outside = None if mask is None else ~mask
    support = joint_support(u0, k, None if mask is None else gated_energy(joint_energy(u0), mask, k, ends_bins)[0])
    amp = np.ascontiguousarray(np.take_along_axis(u0, support[:, :, None], axis=1).transpose(0, 2, 1))
    offsets = (np.arange(b)[:, None, None] * 2 + np.arange(2)[None, :, None]) * n  # of U[b, p, 0] in U (B, 2, N)
    prev_sup, prev_bad, stable, done = np.sort(support, axis=1), None, 0, 0
    d = delta[:, None, None, None, None]
    if bits == 1:
        # a code that disagrees leaves a residual of 2 Z = +-delta: delta (code > 0) - delta (lambda >= 0),
        # counted in int8; lambda = Phi X + xi >= 0 exactly when Phi X >= -xi
        z_pos, neg_xr = (zr > 0).view(np.int8), -xr
        lam_pos, signed = np.empty(zr.shape, dtype=bool), np.empty(zr.shape, dtype=np.int8)
    for it in range(iters):
        if k <= SMALL_K:
            g = np.matmul(amp, atoms[support])  # Phi X, one ramp: (B, 2, N)
        else:
            x = np.zeros((b, 2, n), dtype=complex)
            np.put_along_axis(x, support[:, None, :], amp, axis=2)
            g = np.fft.fft(x * car, axis=2)
        gr = g.view(float).reshape(b, 1, 2, n, 2)
        if bits == 1:
            np.greater_equal(gr, neg_xr, out=lam_pos)
            np.subtract(z_pos, lam_pos.view(np.int8), out=signed)  # (Z - Q(lambda)) / delta
            bad = np.abs(signed).reshape(b, -1).sum(axis=1, dtype=np.int32)  # codes that disagree
            folded = signed.sum(axis=1, dtype=np.int16).astype(float)
            folded *= d[:, 0]
        else:
            resid = zr - _requantize(gr + xr, d, bits)
            bad = np.count_nonzero(resid.reshape(b, -1), axis=1)
            folded = resid.sum(axis=1)
        u = np.fft.ifft(folded.view(complex).reshape(b, 2, n), axis=2)  # Phi^* (Z - Q(.)) / N
        u *= back
        u *= scale
        flat = u.reshape(-1)
        flat[offsets + support[:, None, :]] += amp  # X + step
        support = _strongest(u, k, outside, ends_bins)
        amp = flat[offsets + support[:, None, :]]
        sup_sorted = np.sort(support, axis=1)
        same = prev_bad is not None and np.array_equal(sup_sorted, prev_sup) and np.array_equal(bad, prev_bad)
        stable = stable + 1 if same else 0
        prev_sup, prev_bad, done = sup_sorted, bad, it + 1
        if stable >= 3:
            break
    return amp, support, done


def ml_refine(z: np.ndarray, xi: np.ndarray, delta, support: np.ndarray, x0: np.ndarray, config: RadarConfig,
              temperatures=None) -> np.ndarray:
    """1-bit maximum likelihood of the support amplitudes, per antenna.

    z, xi: (B, M, 2); support: (B, K); x0: starting amplitudes (B, K, 2). Returns (B, K, 2)."""
    z, xi, delta = _check(z, xi, delta, 1, config)
    n = config.samples_per_ramp
    amp = _ml_refine(_antenna_major(z, n), _antenna_major(xi, n), delta, support,
                     np.ascontiguousarray(np.asarray(x0, dtype=complex).transpose(0, 2, 1)), config, temperatures)
    return amp.transpose(0, 2, 1)


#: frames the likelihood stage works on at once: its work arrays (about 100 kB a frame) stay in cache
ML_BLOCK_FRAMES = 32


def _ml_refine(zr: np.ndarray, xr: np.ndarray, delta: np.ndarray, support: np.ndarray, amp: np.ndarray,
               config: RadarConfig, temperatures=None) -> np.ndarray:
    """:func:`ml_refine` on checked frames: zr, xr (B, R, 2, N, 2) from
    :func:`_antenna_major`; amp: starting amplitudes (B, 2, K). Returns (B, 2, K).

    Both antennas at once, in blocks of ML_BLOCK_FRAMES frames, and the sums over the 2M
    real codes folded over the ramps (every ramp repeats the same rows ``a`` of Phi): for
    a code of sign s, with ``t = tanh((a.th + xi) / 2T)`` the logistic's
    ``s q = (s - t) / 2`` and ``q (1 - q) = (1 - t^2) / 4`` (tanh is odd), so the
    gradient and the Hessian need only the sums over the ramps of s, t and t^2."""
    b, ramps, _, n, _ = zr.shape
    if temperatures is None:
        temperatures = ml_temperatures(ramps * n)
    out = np.empty(amp.shape, dtype=complex)
    for lo in range(0, b, ML_BLOCK_FRAMES):
        sl = slice(lo, lo + ML_BLOCK_FRAMES)
        out[sl] = _ml_block(zr[sl], xr[sl], delta[sl], support[sl], amp[sl], config, temperatures)
    return out


def _ml_block(zr: np.ndarray, xr: np.ndarray, delta: np.ndarray, support: np.ndarray, amp: np.ndarray,
              config: RadarConfig, temperatures) -> np.ndarray:
    """:func:`_ml_refine` of one block of frames."""
    b, ramps, _, n, _ = zr.shape
    k = support.shape[1]
    cols = _atoms(config)[support]  # (B, K, N): Phi on the support, one ramp
    # a (B, 2K, 2N): rows Re x_j then Im x_j (Re x moves Phi x by phi, Im x by i phi);
    # columns (sample, re/im) as in zr, so th @ a is (Re, Im) of Phi x on a ramp
    a = np.stack([cols, 1j * cols], axis=1).view(float).reshape(b, 2 * k, 2 * n)
    first, second = np.triu_indices(2 * k)
    pairs = np.take(a, first, axis=1) * np.take(a, second, axis=1)  # (B, P, 2N): what the Hessian sums
    full = _symmetric_index(2 * k)  # Hessian entry -> its pair
    s_sum = np.sign(zr).sum(axis=1).reshape(b, 2, 2 * n)
    o = xr.reshape(b, ramps, 2, 2 * n)
    v = np.empty(o.shape)
    th = np.concatenate([amp.real, amp.imag], axis=2)  # (B, 2 antennas, 2K)
    eye = np.eye(2 * k)
    for t in temperatures:
        sig = (t * delta)[:, None, None]  # (B, 1, 1)
        np.add(np.matmul(th, a)[:, None], o, out=v)  # a.th + xi: (B, R, 2, 2N)
        v *= 0.5 / sig[..., None]
        np.tanh(v, out=v)
        grad = np.matmul(s_sum - v.sum(axis=1), a.transpose(0, 2, 1)) * (0.5 / sig)  # sum s q a / T: (B, 2, 2K)
        np.square(v, out=v)
        hess = (np.matmul(ramps - v.sum(axis=1), pairs.transpose(0, 2, 1)) * (0.25 / sig**2))[..., full]
        trace = np.trace(hess, axis1=2, axis2=3)
        hess += eye * (1e-9 * trace[:, :, None, None] + 1e-300)
        step = np.linalg.solve(hess, grad[..., None])[..., 0]
        norm = np.linalg.norm(step, axis=2, keepdims=True)
        th = th + step * np.minimum(1.0, delta[:, None, None] / np.maximum(norm, 1e-300))  # at most delta
    return th[:, :, :k] + 1j * th[:, :, k:]


@lru_cache(maxsize=8)
def _symmetric_index(size: int) -> np.ndarray:
    """(size, size) indices into the upper triangle of a symmetric matrix, listed as by
    ``np.triu_indices(size)``."""
    rows, cols = np.triu_indices(size)
    index = np.empty((size, size), dtype=np.int64)
    index[rows, cols] = index[cols, rows] = np.arange(rows.size)
    index.flags.writeable = False
    return index


class Decoder:
    """The decoder a :class:`DecoderConfig` describes, with what it keeps between batches:
    cml's decoder (:class:`~pipeline.dsp.cml.CmlDecoder`: its tables and work buffers) of each
    radar configuration. Hold one where batches follow one another (a localizer node, a
    re-processing run, a benchmark); :func:`decode` and :func:`decode_batch` make one a call.
    Its calls may come from several threads."""

    #: radar configurations whose cml decoder it keeps (a node sees one per number of ramps)
    KEPT = 32

    def __init__(self, config: DecoderConfig = DecoderConfig()):
        self.config = config
        #: how it regenerates a frame's dither (:data:`pipeline.dsp.dither.DITHER_ENGINES`): as
        #: cml's engine (numba when it imports: the same bits, one compiled pass)
        self.dither_engine = resolve_engine(config.engine)
        self._options = CmlOptions(engine=config.engine, likelihood=config.likelihood or DEFAULT_LIKELIHOOD,
                                   motion=config.motion)
        self._cml: dict[RadarConfig, CmlDecoder] = {}

    def cml(self, radar: RadarConfig) -> CmlDecoder:
        """cml's decoder for frames of ``radar``, kept."""
        decoder = self._cml.get(radar)
        if decoder is None:
            if len(self._cml) >= self.KEPT:
                self._cml.clear()
            from pipeline.dsp.cml.decoder import CmlDecoder  # the compiled kernels: loaded on first use

            decoder = self._cml[radar] = CmlDecoder(radar, self._options)
        return decoder

    def decode(self, z: np.ndarray, xi: np.ndarray | None, delta, bits: int | None, radar: RadarConfig, k: int,
               indices: np.ndarray | None = None, noise_sigma=None,
               init_range_m: np.ndarray | None = None, alpha=None) -> Detections:
        """:func:`decode` with this decoder."""
        z = np.asarray(z)
        cfg = self.config
        pfa = cfg.pfa if cfg.auto_k else None
        if cfg.algo == Algo.CML and indices is None:  # cml checks the gate (once per gate and radar)
            res = self.cml(radar).decode(z, xi if bits is not None else None, delta if bits is not None else None,
                                         bits, k, noise_sigma=cfg.noise_sigma if noise_sigma is None else noise_sigma,
                                         pfa=pfa, gate=cfg.gate, init_range_m=init_range_m)
            if not cfg.uncertainty:
                return res.detections(radar)
            unc = target_uncertainty(res.range_m, res.amplitudes, res.present, radar, res.sigma_eff, xi, delta, bits,
                                     estimated=noise_sigma is None and cfg.noise_sigma is None,
                                     phase_step_rad=res.phase_step_rad)
            p = None if not cfg.p_values else target_p_values(
                res.range_m, res.amplitudes, res.phase_step_rad, res.present, res.sigma_eff, z,
                xi if bits is not None else None, delta, bits, radar, cfg.gate)
            return res.detections(radar).with_uncertainty(unc.sigma_range_m, unc.sigma_angle_deg, unc.cov_range_angle,
                                                          p_value=p)
        gate = None if cfg.gate is None else cfg.gate.check(radar)
        unfit = xi is None or bits is None or indices is not None  # not for cml or qiht: PBP as fallback, or an error
        if cfg.algo == Algo.PBP or (unfit and cfg.fallback_pbp):
            # unquantized frames: the count test's model holds the targets' tones, not a quantizer's
            reach = None if pfa is None else level_reach(z, delta, bits)  # (what the count test's floor reads)
            return localize(z, radar, k, indices, pfa, gate, dither_alpha(alpha, xi, delta, bits),
                            bits is not None, bits or 1, reach)
        if unfit:
            what = ("frames are a frequency subset" if indices is not None else "frames are not quantized"
                    if bits is None else "frame is not dithered")
            needs = ("frames of whole ramps" if cfg.algo == Algo.CML else
                     "the dither of every frame (a dithered frame of whole ramps with a known seed)")
            raise DitherUnavailable(f"{cfg.algo} needs {needs}; this {what}. Use PBP, or ask for the PBP fallback")
        return _qiht_ml(z, xi, delta, bits, radar, k, cfg, gate)

    def decode_batch(self, frames: QuantizedFrames | np.ndarray, radar: RadarConfig, k: int,
                     init_range_m: np.ndarray | None = None) -> Detections:
        """:func:`decode_batch` with this decoder."""
        algo = self.config.algo
        if isinstance(frames, QuantizedFrames):
            n = radar.samples_per_ramp
            if algo == Algo.PBP and frames.codes.shape[1] % n == 0:
                # PBP back-projects the ramps' sum: fold the codes first (no dither needed)
                return self.decode(frames.ramp_mean(n), None, frames.delta, frames.bits, radar, k, alpha=frames.alpha)
            xi = None if algo == Algo.PBP else frames.dither(self.dither_engine)  # PBP does not use it
            z = frames.codes if algo == Algo.CML else frames.values()  # cml takes the codes as they are
            return self.decode(z, xi, frames.delta, frames.bits, radar, k, init_range_m=init_range_m)
        return self.decode(np.asarray(frames, dtype=np.complex128), None, None, None, radar, k,
                           init_range_m=init_range_m)


def level_reach(z: np.ndarray, delta, bits: int | None):
    """How many steps from the middle the levels of ``bits``-bit frames' values ``z`` (B, M, 2)
    reach (B,): their largest real or imaginary part over ``delta`` (the top level's value is
    its index and a half steps); None for 1-bit or unquantized frames, or no ``delta``."""
    if bits is None or bits == 1 or delta is None:
        return None
    return frame_peak(z) / np.asarray(delta, dtype=float)


def dither_alpha(alpha, xi: np.ndarray | None, delta, bits: int | None):
    """The dither scale of quantized frames for PBP's count test (:func:`pipeline.dsp.residual.product_floor_db`):
    ``alpha`` (scalar or (B,)) when given, else read off their dither ``xi`` (B, M, 2) (uniform
    over ``alpha delta``: twice its largest real part over ``delta``); None for unquantized
    frames, or frames whose dither is not known."""
    if bits is None:
        return None
    if alpha is not None:
        return alpha
    if xi is None or delta is None:
        return None
    return 2.0 * frame_peak(xi) / np.asarray(delta, dtype=float)


def _qiht_ml(z: np.ndarray, xi: np.ndarray, delta, bits: int, config: RadarConfig, k: int, decoder: DecoderConfig,
             gate: RangeGate | None) -> Detections:
    """QIHT then (1 bit, ``decoder.ml``) the likelihood on the support, inside ``gate``."""
    z, xi, delta = _check(z, xi, delta, bits, config)
    n = config.samples_per_ramp
    zr, xr, u0 = _antenna_major(z, n), _antenna_major(xi, n), back_project_ramps(z, config)
    mask = None if gate is None else gate.bin_mask(config)
    ends = None if gate is None else gate.bins(config)
    amp, support, _ = _qiht(zr, xr, u0, delta, bits, config, k, decoder.iters, decoder.mu, mask, ends)
    if decoder.ml and bits == 1:
        amp = _ml_refine(zr, xr, delta, support, amp, config)
    if mask is None:
        stat = grid_statistic_db(u0, support)
    else:
        _, energy, cells = gated_energy(joint_energy(u0), mask, k, ends)
        stat = grid_statistic_db(u0, support, energy, cells)
    return detections_from_support(_scatter(amp, support, n), support, config, stat)


def decode(z: np.ndarray, xi: np.ndarray | None, delta, bits: int | None, config: RadarConfig, k: int,
           decoder: DecoderConfig = DecoderConfig(), indices: np.ndarray | None = None,
           noise_sigma=None, init_range_m: np.ndarray | None = None, alpha=None) -> Detections:
    """Targets of a batch of frames with the configured decoder: the one place where a
    decoder is chosen.

    z: (B, M, 2) quantized values Z (``bits`` >= 1, step ``delta`` (B,), dither ``xi``
    (B, M, 2) or None; cml also takes their codes (B, M, 2, 2), see
    :func:`pipeline.dsp.cml.cml`) or full-resolution frames (``bits=None``); ``indices``: the
    frequency subset of the dense path (None = whole ramps). PBP decodes anything. A
    dither-aware decoder needs quantized frames of whole ramps with their dither; other
    frames go to PBP if ``decoder.fallback_pbp``, else raise DitherUnavailable. ``cml``
    decodes quantized frames (with or without dither) and unquantized ones (least
    squares), of whole ramps. Every decoder searches only inside ``decoder.gate``
    (checked against ``config``; None: the whole range axis). ``noise_sigma``: cml's
    sensor noise, scalar or (B,), in place of ``decoder.noise_sigma`` (None: that).
    ``init_range_m`` (B, J), NaN for none: cml's warm start (see :func:`pipeline.dsp.cml.cml`);
    the others ignore it. ``alpha``: the dither scale of 1-bit frames (scalar or (B,); None:
    read off ``xi``, not known without it), for PBP's count test (:func:`dither_alpha`). One
    call, one :class:`Decoder` (where calls follow one another, hold one: it keeps cml's tables)."""
    return Decoder(decoder).decode(z, xi, delta, bits, config, k, indices, noise_sigma, init_range_m, alpha)


def decode_batch(frames: QuantizedFrames | np.ndarray, config: RadarConfig, k: int,
                 decoder: DecoderConfig = DecoderConfig(), init_range_m: np.ndarray | None = None) -> Detections:
    """Targets of a batch: quantized frames (their dither regenerated from their seeds)
    or full-resolution frames (B, M, 2) complex. What the localizer node and offline
    re-processing call (through a :class:`Decoder` they hold); see :func:`decode` for the
    rules (and ``init_range_m``)."""
    return Decoder(decoder).decode_batch(frames, config, k, init_range_m)
