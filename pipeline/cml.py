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
in compiled kernels, one frame at a time (:mod:`pipeline.cml_kernels`, ``engine="numba"``);
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

With a range gate (:mod:`pipeline.gate`) detection looks only at the points of the
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

import importlib.util
import threading
from dataclasses import dataclass, fields

import numpy as np

from radar_driver.limits import MAX_BITS
from radar_driver.model import RadarConfig, angle_from_antennas_rad, polar_to_xy, range_phase

from .errors import ParameterError
from .gate import RangeGate, check_gate
from .localize import Detections, cfar_threshold, to_db

#: numba is installed: the compiled kernels (:mod:`pipeline.cml_kernels`, imported on first
#: use so that importing this module stays cheap) can run; the numpy code below is their reference
HAVE_NUMBA = importlib.util.find_spec("numba") is not None
_kernels_module = None


def _kernels():
    global _kernels_module
    if _kernels_module is None:
        from . import cml_kernels
        _kernels_module = cml_kernels
    return _kernels_module


#: the implementations of the per-frame work: "numba" (compiled, one frame at a time) or
#: "numpy" (vectorized over a block; the reference)
ENGINES = ("numba", "numpy")
DEFAULT_ENGINE = "numba" if HAVE_NUMBA else "numpy"
#: likelihoods of a code: "logistic" (scaled logistic in place of the Gaussian CDF) or
#: "gaussian" (the exact Gaussian CDF of the noise: ``Phi((hi - l) / s) - Phi((lo - l) / s)``)
LIKELIHOODS = ("logistic", "gaussian")
DEFAULT_LIKELIHOOD = "logistic"
_LIK = {"logistic": 0, "gaussian": 1}  # the kernels' codes
_ready = threading.Event()
_warming_lock = threading.Lock()
_warming: list[threading.Thread] = []


def kernels_ready() -> bool:
    """Whether :func:`warm_up_kernels` has compiled (or loaded from numba's cache) the kernels."""
    return HAVE_NUMBA and _ready.is_set()


def warm_up_kernels(wait: bool = False) -> None:
    """Compile the kernels for every kind of frame (or load them from numba's on-disk cache:
    about 0.5 s; a first compile takes tens of seconds), in a daemon thread started once;
    ``wait``: until done. A live localizer decodes with the numpy engine meanwhile."""
    if not HAVE_NUMBA:
        return
    with _warming_lock:
        if not _warming:
            _warming.append(threading.Thread(target=_compile_all, name="cml-jit", daemon=True))
            _warming[0].start()
    if wait:
        _warming[0].join()


def _compile_all() -> None:
    cfg = RadarConfig()
    n = cfg.samples_per_ramp
    rng = np.random.default_rng(0)
    g = 0.3 * np.exp(2j * np.pi * rng.random((1, 2 * n, 2)))
    xi = 0.25 * (rng.random(g.shape) - 0.5 + 1j * (rng.random(g.shape) - 0.5))
    gate = RangeGate(5.0, 100.0)
    for bits in (1, 3, None):
        delta = 1.0 if bits is None else 1.0 / (1 << (bits - 1))
        half = 0 if bits is None else 1 << (bits - 1)
        z = g if bits is None else delta * (np.clip(np.floor((g + xi).real / delta), -half, half - 1) + 0.5 + 1j * (
            np.clip(np.floor((g + xi).imag / delta), -half, half - 1) + 0.5))
        for lik in LIKELIHOODS:
            cml(z, xi, delta, bits, cfg, 2, engine="numba", likelihood=lik)
            cml(z, xi, delta, bits, cfg, 2, engine="numba", likelihood=lik, pfa=1e-3, gate=gate,
                init_range_m=np.array([[30.0, np.nan]]))
    _ready.set()

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)
#: logistic scale of a Gaussian of unit std (Phi(x) ~ F(1.702 x))
LOGISTIC_PER_SIGMA = 1.702
#: first sigma_eff, in units of delta
SIGMA_START = 0.25
#: a detection keeps at least this far from the targets already found, range bins
MIN_SEPARATION_BINS = 1.0
#: largest range change of one refinement step, range bins
MAX_RANGE_STEP_BINS = 0.5
#: frames decoded at once: the likelihood's work arrays (B x 4M float32 each) stay in cache
BLOCK_FRAMES = 64
#: RMS distance of the wrong codes to their cells, in units of the noise std (see above)
WRONG_RMS_PER_SIGMA = np.sqrt(2.0 / 3.0)
#: independent cells a bin of the count test's search is worth (its peak is sought on the
#: oversampled grid, between the bins too); measured on target-free residuals (README)
SEARCH_CELLS_PER_BIN = 3.0
#: the count test looks for a peak this far from the targets found, range bins (a guard
#: band: a strong target's 1-bit fit leaves residual energy up to ~2 bins away)
COUNT_GUARD_BINS = 2.0


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
        """The same targets as :class:`pipeline.localize.Detections`."""
        return cml_detections(self, config)


def cml_detections(result: CmlResult, config: RadarConfig) -> Detections:
    """Range, angle (from the phase between the antennas), position, amplitude
    ``sqrt((|a1|^2 + |a2|^2) / 2)`` and nearest range bin of each target of ``result``."""
    a = result.amplitudes
    angle = angle_from_antennas_rad(a[..., 0], a[..., 1], config)
    x, y = polar_to_xy(result.range_m, angle)
    amp = np.sqrt((np.abs(a) ** 2).sum(axis=-1) / 2.0)
    bins = np.rint(np.nan_to_num(result.range_m) / config.range_resolution_m).astype(np.int64) % \
        config.samples_per_ramp
    det = Detections(result.range_m, np.rad2deg(angle), x, y, amp, bins, result.statistic_db)
    return det if result.present.all() else det.masked(result.present)


def model_frames(range_m: np.ndarray, amplitudes: np.ndarray, config: RadarConfig, ramps: int) -> np.ndarray:
    """``Gamma_{m,p} = sum_t a_{t,p} exp(-i 4 pi f_m r_t / c)`` for ``ramps`` whole ramps.

    range_m : (B, K), m; amplitudes : (B, K, 2) complex. Returns (B, ramps N, 2) complex.
    """
    f = config.frequencies_hz(np.arange(config.samples_per_ramp))
    steer = range_phase(f[None, :, None], np.asarray(range_m, dtype=float)[:, None, :], config)  # (B, N, K)
    ramp = np.einsum("bnk,bkp->bnp", steer, np.asarray(amplitudes, dtype=complex))
    return np.tile(ramp, (1, ramps, 1))


# -- the likelihood ---------------------------------------------------------------------
class _Codes:
    """The measurements of a batch as real arrays (B, R, N, 2 antennas, 2 re/im) and the
    negative log-likelihood (NLL) of a model ``mu`` (B, N, 2, 2) repeated on every ramp.

    Quantized frames are held in float32 work arrays: float32 resolves 1e-7 of delta, far
    below the finest sigma_eff (delta / M), and halves the cost of the likelihood, which is
    evaluated about 20 times."""

    def __init__(self, z: np.ndarray, xi: np.ndarray | None, delta: np.ndarray | None, bits: int | None,
                 n: int):
        b, m, _ = z.shape
        self.bits, self.ramps, self.n = bits, m // n, n
        shape = (b, self.ramps, n, 2, 2)
        zr = np.ascontiguousarray(z, dtype=complex).view(float).reshape(shape)
        if bits is None:
            self.data = z  # what detection and amplitudes back-project
            self.y = zr
            self.kind = 0  # the kernels' LSQ
            self.ka = self.kb = zr.reshape(b, self.ramps, n, 4)  # the kernels' arrays
            return
        self.data = z - xi
        xr = np.ascontiguousarray(xi, dtype=complex).view(float).reshape(shape)
        d = delta[:, None, None, None, None]
        half = 1 << (bits - 1)
        q = np.rint(zr / d - 0.5)  # zr = (q + 1/2) delta
        self.work = [np.empty(shape, dtype=np.float32) for _ in range(3)]
        if bits == 1:
            s = np.where(q >= 0, 1.0, -1.0)  # the sign of lambda + xi
            self.s = s.astype(np.float32)
            self.so = (s * xr).astype(np.float32)
            self.half_s = 0.5 * s.sum(axis=1)
            self.kind = 1  # ONE_BIT
            self.ka, self.kb = self.s.reshape(b, self.ramps, n, 4), self.so.reshape(b, self.ramps, n, 4)
            return
        self.lo = (np.where(q <= -half, -np.inf, q * d) - xr).astype(np.float32)  # lambda's cell: [lo, hi)
        self.hi = (np.where(q >= half - 1, np.inf, (q + 1) * d) - xr).astype(np.float32)
        self.kind = 2  # MULTI_BIT
        self.ka, self.kb = self.lo.reshape(b, self.ramps, n, 4), self.hi.reshape(b, self.ramps, n, 4)

    def evaluate(self, mu: np.ndarray, sigma: np.ndarray, likelihood: str = DEFAULT_LIKELIHOOD):
        """NLL (B,) and its first and second derivatives in each real measurement, summed
        over the ramps (B, N, 2, 2). mu : (B, N, 2, 2); sigma : (B,) the noise std of the
        likelihood (the logistic's scale is ``sigma / LOGISTIC_PER_SIGMA``)."""
        if self.bits is None:
            r = mu[:, None] - self.y
            return 0.5 * np.einsum("brnpc,brnpc->b", r, r), r.sum(axis=1), np.full(mu.shape, float(self.ramps))
        if likelihood == "gaussian":
            return self._gaussian(mu, sigma)
        scale = sigma / LOGISTIC_PER_SIGMA
        mu = mu[:, None].astype(np.float32)
        inv = (1.0 / scale).astype(np.float32)[:, None, None, None, None]
        u = self.work[0]
        if self.bits == 1:
            np.multiply(self.s, mu, out=u)
            u += self.so
            u *= inv  # s (mu + xi) / T: the margin, > 0 for a code the model gets right
            nll, g, h = self._softplus(u, self.s)
        else:
            # -log(F(c) - F(a)) = -log F(-a) - log F(c) + const, a = (lo - mu) / T, c = (hi - mu) / T
            np.subtract(mu, self.lo, out=u)
            u *= inv
            nll, g, h = self._softplus(u, 1.0)
            np.subtract(self.hi, mu, out=u)
            u *= inv
            nll_c, g_c, h_c = self._softplus(u, -1.0)
            nll, g, h = nll + nll_c, g + g_c, h + h_c
        inv = inv[:, 0].astype(float)
        return nll, g * inv, h * (inv * inv)

    def _gaussian(self, mu: np.ndarray, sigma: np.ndarray):
        """:meth:`evaluate` with the exact Gaussian likelihood (float64, scipy's log_ndtr)."""
        from scipy.special import log_ndtr  # here: importing scipy costs the others' start-up

        b = mu.shape[0]
        inv = (1.0 / sigma)[:, None, None, None, None]
        mu = mu[:, None]
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            if self.bits == 1:
                s = self.s.astype(float)
                v = (s * mu + self.so) * inv  # the margin in units of sigma
                lp = log_ndtr(v)
                r = np.exp(-0.5 * v * v - _LOG_SQRT_2PI - lp)  # phi(v) / Phi(v)
                nll, dv, d2v = -lp, -r * s, r * (v + r)
            else:
                a = (self.lo - mu) * inv
                c = (self.hi - mu) * inv
                flip = a + c > 0.0  # the upper tail: Phi(c) - Phi(a) = Phi(-a) - Phi(-c)
                a2, c2 = np.where(flip, -c, a), np.where(flip, -a, c)
                lh = log_ndtr(c2)
                ld = lh + np.log1p(-np.exp(log_ndtr(a2) - lh))  # log(Phi(c) - Phi(a))
                pa = np.where(np.isfinite(a), np.exp(-0.5 * a * a - _LOG_SQRT_2PI - ld), 0.0)  # phi(a) / P
                pc = np.where(np.isfinite(c), np.exp(-0.5 * c * c - _LOG_SQRT_2PI - ld), 0.0)
                dv = pc - pa
                d2v = dv * dv + np.where(np.isfinite(c), c * pc, 0.0) - np.where(np.isfinite(a), a * pa, 0.0)
                nll = -ld
        inv = inv[:, 0]
        return nll.reshape(b, -1).sum(axis=1), dv.sum(axis=1) * inv, d2v.sum(axis=1) * (inv * inv)

    def _softplus(self, u, sign):
        """Sum per frame of ``-log F(u)`` (B,), and its first and second derivatives in
        lambda times T and T^2, summed over the ramps (B, N, 2, 2), where
        ``u = sign lambda / T + const``; ``sign`` is +-1 or an array. Overwrites work arrays."""
        b = u.shape[0]
        e, t = self.work[1], self.work[2]
        np.abs(u, out=e)
        np.minimum(e, 40.0, out=e)  # exp(-40) ~ 4e-18: no float32 subnormals (slow) downstream
        np.negative(e, out=e)
        np.exp(e, out=e)  # exp(-|u|)
        np.minimum(u, 0.0, out=t)
        nll = -t.reshape(b, -1).sum(axis=1, dtype=float)
        np.log1p(e, out=t)
        nll += t.reshape(b, -1).sum(axis=1, dtype=float)  # -log F(u) = max(-u, 0) + log(1 + exp(-|u|))
        np.add(e, 1.0, out=t)
        np.reciprocal(t, out=t)
        np.multiply(e, t, out=e)  # q = F(-|u|)
        np.multiply(e, t, out=t)  # F(u) F(-u) = q (1 - q)
        h = t.sum(axis=1, dtype=float)
        np.subtract(0.5, e, out=e)
        np.copysign(e, u, out=e)  # F(-u) = 1/2 - copysign(1/2 - q, u)
        if np.isscalar(sign):  # d(-log F(u)) / d lambda = -sign F(-u) / T
            g = sign * (e.sum(axis=1, dtype=float) - 0.5 * self.ramps)
        else:
            e *= sign
            g = e.sum(axis=1, dtype=float) - self.half_s
        return nll, g, h

    def wrong_rms(self, mu: np.ndarray) -> np.ndarray:
        """RMS distance (B,) of the codes that ``mu`` gets wrong to their cells, frame
        units (0 when none is wrong); unquantized frames: RMS of the residual."""
        b = mu.shape[0]
        if self.bits is None:
            return np.sqrt(np.mean((mu[:, None] - self.y).reshape(b, -1) ** 2, axis=1))
        mu = mu[:, None].astype(np.float32)
        v, t = self.work[0], self.work[1]
        if self.bits == 1:
            np.multiply(self.s, mu, out=v)
            v += self.so
            np.minimum(v, 0.0, out=v)
        else:
            np.subtract(self.lo, mu, out=v)
            np.maximum(v, 0.0, out=v)
            np.subtract(mu, self.hi, out=t)
            np.maximum(t, 0.0, out=t)
            v += t
        miss = v.reshape(b, -1)
        wrong = np.count_nonzero(miss, axis=1)
        return np.sqrt(np.einsum("bj,bj->b", miss, miss, dtype=float) / np.maximum(wrong, 1))


# -- the range gate -----------------------------------------------------------------------
class _Gate:
    """A range gate in cml's terms: its ends in bins ``lo``, ``hi`` and ``outside`` (L,)
    bool, the points of the oversampled detection grid (``oversample`` a bin) beyond it."""

    def __init__(self, gate: RangeGate, config: RadarConfig, oversample: int):
        self.lo, self.hi = gate.bins(config)
        grid = np.arange(oversample * config.samples_per_ramp) / oversample
        eps = 1e-9
        self.outside = (grid < self.lo - eps) | (grid > self.hi + eps)
        if self.outside.all():  # a gate narrower than the grid's step: its nearest point
            self.outside[np.argmin(np.abs(grid - 0.5 * (self.lo + self.hi)))] = False
        #: the bins the detection search spans (the count test's cells)
        self.width_bins = min(float(config.samples_per_ramp), max(self.hi - self.lo, 1.0 / oversample))


# -- the model and its derivatives -------------------------------------------------------
def _atoms(nu: np.ndarray, kc: np.ndarray) -> np.ndarray:
    """``exp(-i 2 pi kc nu / N)``: ranges (..., K) in bins -> (..., K, N), from two short
    tables (index n1 j + i) rather than K N complex exponentials a frame."""
    n = kc.size
    n1 = int(np.ceil(np.sqrt(n)))
    n2 = -(-n // n1)
    ph = (-2j * np.pi / n) * nu[..., None]
    outer = np.exp(ph * (n1 * np.arange(n2)))
    inner = np.exp(ph * (np.arange(n1) + kc[0]))
    return (outer[..., :, None] * inner[..., None, :]).reshape(nu.shape + (n1 * n2,))[..., :n]


def _coefficients(amp: np.ndarray) -> np.ndarray:
    """Z (B, 4, 4K, 5K): the derivative of part c (0 real, 1 imaginary) of the model on
    antenna p in the parameters is ``R^T Z[2p + c]`` (see :meth:`_Fit.step`)."""
    b, k, _ = amp.shape
    z = np.zeros((b, 4, 4 * k, 5 * k))
    t = np.arange(k)
    for p in range(2):
        re, im = 2 * p, 2 * p + 1
        # a parameter moves mu_p along A v: Re b_tp: v = e_t; Im b_tp: v = i e_t; nu_t:
        # v = b_tp e_{K+t}. Re(A v) = Re A Re v - Im A Im v, Im(A v) = Re A Im v + Im A Re v;
        # rows [0, 2K) of R are Re A, rows [2K, 4K) Im A.
        z[:, re, t, 5 * t + 1 + 2 * p] = 1.0
        z[:, im, 2 * k + t, 5 * t + 1 + 2 * p] = 1.0
        z[:, re, 2 * k + t, 5 * t + 2 + 2 * p] = -1.0
        z[:, im, t, 5 * t + 2 + 2 * p] = 1.0
        a = amp[:, :, p]
        z[:, re, k + t, 5 * t] = a.real
        z[:, re, 3 * k + t, 5 * t] = -a.imag
        z[:, im, k + t, 5 * t] = a.imag
        z[:, im, 3 * k + t, 5 * t] = a.real
    return z


class _Fit:
    """The targets found so far, the model and the likelihood at them, and
    Levenberg--Marquardt steps on all of them at once.

    A target's parameters are [nu, Re b1, Im b1, Re b2, Im b2]: range in bins and the
    amplitudes referred to mid-sweep; on one ramp the model is
    ``mu_{n,p} = sum_t b_{t,p} w_t[n]`` with ``w_t[n] = exp(-i 2 pi kc_n nu_t / N)``."""

    def __init__(self, codes: _Codes, kc: np.ndarray, b: int, gate: _Gate | None = None,
                 engine: str = DEFAULT_ENGINE, likelihood: str = DEFAULT_LIKELIHOOD):
        self.codes, self.kc, self.gate = codes, kc, gate
        self.engine, self.likelihood = engine, likelihood
        self.set(np.zeros((b, 0)), np.zeros((b, 0, 2), dtype=complex), np.zeros((b, 0), dtype=bool))

    def set(self, nu: np.ndarray, amp: np.ndarray, live: np.ndarray) -> None:
        """Targets (B, K) in bins, amplitudes (B, K, 2); ``live`` (B, K): the targets
        that move (the others stay where they are: zero amplitude, past a frame's count)."""
        self.nu, self.amp, self.live = nu, amp, live
        self.w = _atoms(nu, self.kc)
        self.mu = self._mu(self.w, amp)
        self.lm = np.full(nu.shape[0], 1e-3)  # damping, per frame

    @staticmethod
    def _mu(w: np.ndarray, amp: np.ndarray) -> np.ndarray:
        mu = np.matmul(w.transpose(0, 2, 1), amp)  # (B, N, 2) complex
        return mu.view(float).reshape(mu.shape + (2,))

    def model(self) -> np.ndarray:
        """One ramp of the model, (B, N, 2) complex."""
        return self.mu.view(complex)[..., 0]

    def evaluate(self, sigma: np.ndarray) -> None:
        """The likelihood at noise std ``sigma`` (B,) and its derivatives at the model."""
        self.sigma = np.asarray(sigma, dtype=float)
        if self.engine == "numpy":
            self.nll, self.g, self.h = self.codes.evaluate(self.mu, self.sigma, self.likelihood)
            return
        b, n = self.mu.shape[:2]
        self.g, self.h = np.empty((b, n, 2, 2)), np.empty((b, n, 2, 2))
        self.nll = _kernels().evaluate(self.codes.kind, _LIK[self.likelihood], self.codes.ka, self.codes.kb,
                                     np.ascontiguousarray(self.mu).reshape(b, n, 4), self.sigma,
                                     self.g.reshape(b, n, 4), self.h.reshape(b, n, 4))

    def run(self, levels: np.ndarray, amp_cap: np.ndarray, adapt: bool = False) -> None:
        """One step a level: at noise std ``levels[:, j]`` (B, S) (``adapt``: not below
        the noise the model leaves, ``wrong_rms / WRONG_RMS_PER_SIGMA``), the likelihood
        evaluated again where the level changed, then :meth:`step`."""
        b = self.nu.shape[0]
        if self.engine == "numpy" or self.nu.shape[1] == 0:
            for j in range(levels.shape[1]):
                sigma = levels[:, j]
                if adapt:
                    sigma = np.maximum(sigma, self.codes.wrong_rms(self.mu) / WRONG_RMS_PER_SIGMA)
                if not np.array_equal(sigma, self.sigma):
                    self.evaluate(sigma)
                self.step(amp_cap)
            return
        n = self.kc.size
        nu, amp = np.ascontiguousarray(self.nu, dtype=float), np.ascontiguousarray(self.amp, dtype=complex)
        mu, g, h = (np.ascontiguousarray(v, dtype=float).reshape(b, n, 4) for v in (self.mu, self.g, self.h))
        nll, sigma, lm = self.nll.astype(float), self.sigma.astype(float), self.lm.astype(float)
        gate = self.gate
        _kernels().refine(self.codes.kind, _LIK[self.likelihood], self.codes.ka, self.codes.kb, self.kc, nu, amp,
                        np.ascontiguousarray(self.live), lm, np.ascontiguousarray(levels, dtype=float), adapt,
                        WRONG_RMS_PER_SIGMA, np.ascontiguousarray(amp_cap, dtype=float),
                        0.0 if gate is None else float(gate.lo), 0.0 if gate is None else float(gate.hi),
                        gate is not None, MAX_RANGE_STEP_BINS, mu, g, h, nll, sigma)
        self.nu, self.amp, self.lm, self.nll, self.sigma = nu, amp, lm, nll, sigma
        self.mu, self.g, self.h = (v.reshape(b, n, 2, 2) for v in (mu, g, h))
        self.w = None  # stale: only the numpy step reads it


    def step(self, amp_cap: np.ndarray) -> None:
        """One Levenberg--Marquardt step of every frame at the current scale; a frame
        keeps its step only if its likelihood improves. amp_cap : (B,) largest amplitude
        change of a target."""
        b, k = self.nu.shape
        if k == 0:  # no target found in the whole block (K auto)
            return
        n = self.kc.size
        # the Jacobian of part c of mu_p is R^T Z[2p + c]: R (4K, N) holds the real and the
        # imaginary parts of the atoms w_t and of dw_t / dnu; Z how each parameter mixes them
        dw = self.w * ((-2j * np.pi / n) * self.kc)
        r = np.concatenate([self.w.real, dw.real, self.w.imag, dw.imag], axis=1)  # (B, 4K, N)
        r32 = r.astype(np.float32)
        hw = np.ascontiguousarray(self.h.reshape(b, n, 4).transpose(0, 2, 1), dtype=np.float32)
        gram = np.matmul(r32[:, None] * hw[:, :, None], np.ascontiguousarray(r32.transpose(0, 2, 1))[:, None])
        zc = _coefficients(self.amp)
        hess = np.matmul(zc.transpose(0, 1, 3, 2), np.matmul(gram.astype(float), zc)).sum(axis=1)
        proj = np.matmul(r, self.g.reshape(b, n, 4)).transpose(0, 2, 1)[..., None]  # (B, 4, 4K, 1)
        grad = np.matmul(zc.transpose(0, 1, 3, 2), proj).sum(axis=1)[..., 0]
        diag = np.diagonal(hess, axis1=1, axis2=2)
        damp = self.lm[:, None] * diag + 1e-9 * diag.max(axis=1, keepdims=True) + 1e-300
        step = -np.linalg.solve(hess + damp[:, :, None] * np.eye(5 * k), grad[..., None])[..., 0]
        step = step.reshape(b, k, 5)
        step[~self.live] = 0.0
        step[..., 0] = np.clip(step[..., 0], -MAX_RANGE_STEP_BINS, MAX_RANGE_STEP_BINS)
        norm = np.linalg.norm(step[..., 1:], axis=2)
        step[..., 1:] *= np.minimum(1.0, amp_cap[:, None] / np.maximum(norm, 1e-300))[..., None]
        nu = self.nu + step[..., 0]
        if self.gate is not None:  # a target may not leave the gate
            nu = np.clip(nu, self.gate.lo, self.gate.hi)
        amp = self.amp + (step[..., 1::2] + 1j * step[..., 2::2])
        w = _atoms(nu, self.kc)
        mu = self._mu(w, amp)
        nll, g, h = self.codes.evaluate(mu, self.sigma, self.likelihood)
        ok = nll <= self.nll
        self.lm = np.clip(np.where(ok, self.lm / 3.0, self.lm * 8.0), 1e-9, 1e9)
        bad = np.flatnonzero(~ok)  # frames that keep their parameters (few)
        for new, old in ((nu, self.nu), (amp, self.amp), (w, self.w), (mu, self.mu), (g, self.g), (h, self.h),
                         (nll, self.nll)):
            new[bad] = old[bad]
        self.nu, self.amp, self.w, self.mu, self.g, self.h, self.nll = nu, amp, w, mu, g, h, nll


# -- checks -------------------------------------------------------------------------------
def _is_int(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def _per_frame(name: str, value, b: int, positive: bool) -> np.ndarray:
    """A scalar or (B,) array of finite values > 0 (``positive``) or >= 0, as (B,) floats."""
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


def _check(z, xi, delta, bits, config, k, noise_sigma, iters, anneal, oversample, gate=None):
    z = np.asarray(z)
    if z.ndim != 3 or z.shape[-1] != 2:
        raise ParameterError(f"cml: Z must have shape (B, M, 2), got {z.shape}")
    if not np.issubdtype(z.dtype, np.number):
        raise ParameterError(f"cml: Z must be numbers, got dtype {z.dtype}")
    b, m, _ = z.shape
    n = config.samples_per_ramp
    if m == 0 or m % n:
        raise ParameterError(f"cml: M={m} is not a whole number of ramps of N={n} samples")
    if not np.all(np.isfinite(z)):
        raise ParameterError("cml: Z holds values that are not finite")
    if not _is_int(k) or not 1 <= k <= n // 2:
        raise ParameterError(f"cml: k={k!r} must be an integer in [1, N/2 = {n // 2}]")
    for name, value, lo in (("iters", iters, 0), ("anneal", anneal, 0), ("oversample", oversample, 1)):
        if not _is_int(value) or not lo <= value <= 1000:
            raise ParameterError(f"cml: {name}={value!r} must be an integer in [{lo}, 1000]")
    if noise_sigma is not None:
        noise_sigma = _per_frame("noise_sigma", noise_sigma, b, positive=False)
    if check_gate(gate) is not None:
        gate.check(config)
    z = z.astype(complex)
    if bits is None:
        return z, None, None, noise_sigma
    if not _is_int(bits) or not 1 <= bits <= MAX_BITS:
        raise ParameterError(f"cml: bits={bits!r} must be None (unquantized) or an integer in [1, {MAX_BITS}]")
    xi = np.zeros_like(z) if xi is None else np.asarray(xi)
    if xi.shape != z.shape:
        raise ParameterError(f"cml: dither shape {xi.shape} does not match Z {z.shape}")
    if not np.all(np.isfinite(xi)):
        raise ParameterError("cml: the dither holds values that are not finite")
    d = _per_frame("delta", delta, b, positive=True)
    level = np.stack([z.real, z.imag]) / d[None, :, None, None] - 0.5  # an integer in [-2^(b-1), 2^(b-1))
    half = 1 << (bits - 1)
    if level.size and (np.any(np.abs(level - np.rint(level)) > 1e-6) or level.min() < -half - 1e-6
                       or level.max() > half - 1 + 1e-6):
        raise ParameterError(f"cml: Z is not a {bits}-bit quantized frame of step delta: its real and imaginary "
                             f"parts must be delta (q + 1/2) with q an integer in [{-half}, {half - 1}]")
    return z, xi.astype(complex), d, noise_sigma


# -- the decoder ----------------------------------------------------------------------------
def cml(z: np.ndarray, xi: np.ndarray | None, delta, bits: int | None, config: RadarConfig, k: int, *,
        noise_sigma=None, iters: int = 3, anneal: int = 6, oversample: int = 8,
        pfa: float | None = None, gate: RangeGate | None = None, engine: str | None = None,
        likelihood: str | None = None, init_range_m: np.ndarray | None = None) -> CmlResult:
    """Greedy continuous-range maximum likelihood decoder (see the module docstring).

    Parameters
    ----------
    z : (B, M, 2) complex, M = R N (whole ramps): quantized values ``Q_b(Gamma + xi)``
        (``bits`` >= 1) or full-resolution frames (``bits=None``: least squares).
    xi : (B, M, 2) complex, the dither added before quantization (None: no dither);
        ignored when ``bits`` is None.
    delta : quantizer step, scalar or (B,), frame units; ignored when ``bits`` is None.
    bits : bits per real value, or None for unquantized frames.
    config : the radar configuration (N, frequencies, c).
    k : targets per frame, 1 <= k <= N/2; with ``pfa``, the most a frame can have.
    noise_sigma : std of the sensor noise on each real part, frame units, scalar or (B,);
        None: estimated from the frame. The likelihood is never sharper than the noise.
    iters : refinement steps after each detection.
    anneal : final levels of ``sigma_eff``, falling geometrically to its floor (one
        refinement step each); unquantized frames: more least-squares steps.
    oversample : detection grid of ``oversample * N`` ranges.
    pfa : None (exactly ``k`` targets), or decide each frame's count: before each
        detection, the peak over the mean of the joint energy of the residual's back
        projection (away from the targets found) must reach the threshold whose
        false-alarm probability on a target-free residual is ``pfa`` per frame and test
        (:func:`pipeline.localize.cfar_threshold` over ``SEARCH_CELLS_PER_BIN * N``
        cells, N the bins of the gate), on the linear residual and on the likelihood's
        score both (:func:`_count_statistic`); the first miss ends the frame's targets.
    gate : a :class:`~pipeline.gate.RangeGate`: targets are sought, tested and refined
        only inside it, and their ranges stay in it (None: the whole, circular, range axis).

    engine : "numba" (compiled kernels, :mod:`pipeline.cml_kernels`; the default when numba
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
    batch (about 1e-5 m in range and 1 % in amplitude in a 4-bit case). About 20 evaluations of the
    likelihood and 12 Gauss--Newton systems for K = 2: ~1 ms a frame (M = 512).
    """
    z, xi, delta, noise_sigma = _check(z, xi, delta, bits, config, k, noise_sigma, iters, anneal, oversample, gate)
    engine = DEFAULT_ENGINE if engine is None else engine
    likelihood = DEFAULT_LIKELIHOOD if likelihood is None else likelihood
    if engine not in ENGINES or (engine == "numba" and not HAVE_NUMBA):
        raise ParameterError(f"cml: engine={engine!r} is not available; available: "
                             f"{', '.join(e for e in ENGINES if e != 'numba' or HAVE_NUMBA)}")
    if likelihood not in LIKELIHOODS:
        raise ParameterError(f"cml: likelihood={likelihood!r} is not known; available: {', '.join(LIKELIHOODS)}")
    cgate = None if gate is None else _Gate(gate, config, oversample)
    search_bins = config.samples_per_ramp if cgate is None else cgate.width_bins
    threshold = None if pfa is None else cfar_threshold(pfa, SEARCH_CELLS_PER_BIN * search_bins)
    if z.shape[0] == 0:
        return CmlResult(np.zeros((0, k)), np.zeros((0, k, 2), dtype=complex), np.zeros((0, k)), np.zeros(0),
                         np.zeros((0, k), dtype=bool))
    if init_range_m is not None:
        return _warm_or_cold(z, xi, delta, bits, config, k, noise_sigma, iters, anneal, oversample, threshold, cgate,
                             engine, likelihood, _check_init(init_range_m, z.shape[0], k, config, gate))
    parts = []
    for lo in range(0, z.shape[0], BLOCK_FRAMES):  # blocks small enough for the work arrays to stay in cache
        sl = slice(lo, lo + BLOCK_FRAMES)
        parts.append(_decode(z[sl], None if xi is None else xi[sl], None if delta is None else delta[sl], bits,
                             config, k, None if noise_sigma is None else noise_sigma[sl], iters, anneal, oversample,
                             threshold, cgate, engine, likelihood))
    if len(parts) == 1:
        return parts[0]
    return CmlResult(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(CmlResult)))


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
    search_bins = config.samples_per_ramp if cgate is None else cgate.width_bins
    warm_threshold = cfar_threshold(WARM_PFA, SEARCH_CELLS_PER_BIN * search_bins)
    warm = ~np.isnan(init).all(axis=1)
    out = [None] * b
    cold = np.flatnonzero(~warm)

    def sub(idx):
        return (z[idx], None if xi is None else xi[idx], None if delta is None else delta[idx],
                None if noise_sigma is None else noise_sigma[idx])

    widx = np.flatnonzero(warm)
    if widx.size:
        for lo in range(0, widx.size, BLOCK_FRAMES):
            idx = widx[lo:lo + BLOCK_FRAMES]
            zz, xx, dd, nn = sub(idx)
            res, misfit = _refine_warm(zz, xx, dd, bits, config, k, nn, anneal, threshold, cgate, engine, likelihood,
                                       init[idx], oversample, warm_threshold)
            for j, i in enumerate(idx.tolist()):
                out[i] = None if misfit[j] else _row(res, j)
        cold = np.flatnonzero([o is None for o in out])
    for lo in range(0, cold.size, BLOCK_FRAMES):
        idx = cold[lo:lo + BLOCK_FRAMES]
        zz, xx, dd, nn = sub(idx)
        res = _decode(zz, xx, dd, bits, config, k, nn, iters, anneal, oversample, threshold, cgate, engine, likelihood)
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
    b, m, _ = z.shape
    n = config.samples_per_ramp
    codes = _Codes(z, xi, delta, bits, n)
    fit = _Fit(codes, np.arange(n) - (n - 1) / 2.0, b, gate, engine, likelihood)
    if bits is None:  # least squares: the scale plays no part
        return codes, fit, np.ones(b), None, np.full(b, np.inf)
    noise = np.zeros(b) if noise_sigma is None else noise_sigma
    return (codes, fit, np.maximum(SIGMA_START * delta, noise), np.maximum(delta / m, noise),
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
    for t in range(int(live_all.sum(axis=1).max())):  # amplitudes one at a time in the residual
        amp0 = np.where(live_all[:, t, None], _amplitude_at(codes, fit, nu_all[:, t]), 0.0)
        fit.set(nu_all[:, :t + 1], np.concatenate([fit.amp, amp0[:, None]], axis=1), live_all[:, :t + 1])
    fit.evaluate(sigma)
    fit.run(np.repeat(sigma[:, None], WARM_STEPS, axis=1), amp_cap)
    if bits is not None and anneal:
        levels_n = min(anneal, WARM_ANNEAL)
        ratio = (floor / sigma) ** (1.0 / levels_n)
        levels = sigma[:, None] * ratio[:, None] ** np.arange(1, levels_n + 1)
        fit.run(levels, amp_cap, adapt=noise_sigma is None)
        sigma = fit.sigma
    if bits is None:
        fit.run(np.ones((b, anneal)), amp_cap)
        sigma = codes.wrong_rms(fit.mu)
    res = _result(fit, codes, config, sigma, k)
    count = fit.live.sum(axis=1)
    # the residual (and the likelihood's score, at the last level) holds a peak the targets do
    # not explain: a target appeared, or one moved beyond the refinement's reach
    unexplained = _count_statistic(fit, codes, oversample) >= (warm_threshold if threshold is None else threshold)
    if threshold is None:  # k targets a frame, whatever their strength
        misfit = (count < k) | unexplained
    else:
        weakest = np.where(res.present, res.statistic_db, np.inf).min(axis=1)
        misfit = ((count < k) & unexplained) | (weakest < to_db(np.asarray(threshold, dtype=float)))  # or vanished
    return res, misfit


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
        if threshold is not None:
            active &= _count_statistic(fit, codes, oversample) >= threshold
            if not active.any():
                break
        nu0 = _detect(fit, codes, oversample)
        amp0 = np.where(active[:, None], _amplitude_at(codes, fit, nu0), 0.0)
        fit.set(np.concatenate([fit.nu, nu0[:, None]], axis=1), np.concatenate([fit.amp, amp0[:, None]], axis=1),
                np.concatenate([fit.live, active[:, None]], axis=1))
        fit.evaluate(sigma)
        fit.run(np.repeat(sigma[:, None], iters, axis=1), amp_cap)
    if bits is not None and anneal:
        ratio = (floor / sigma) ** (1.0 / anneal)
        levels = np.empty((b, anneal))
        level = sigma
        for j in range(anneal):
            level = level * ratio
            levels[:, j] = level
        fit.run(levels, amp_cap, adapt=noise_sigma is None)  # adapt: not sharper than the noise the model leaves
        sigma = fit.sigma
    if bits is None:
        fit.run(np.ones((b, anneal)), amp_cap)  # least squares: polish
        sigma = codes.wrong_rms(fit.mu)
    return _result(fit, codes, config, sigma, k)


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
    b = fit.nu.shape[0]
    return codes.data.reshape(b, codes.ramps, codes.n, 2).sum(axis=1) - codes.ramps * fit.model()


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


def _result(fit: _Fit, codes: _Codes, config: RadarConfig, sigma: np.ndarray, k: int) -> CmlResult:
    """The fit in the model's terms, its statistic, padded to ``k`` targets (absent ones
    last), present ones strongest first."""
    n, ramps = codes.n, codes.ramps
    b, t = fit.nu.shape
    # the axis is circular; inside a gate (within [0, N] bins) a range is not wrapped
    range_m = (fit.nu if fit.gate is not None else fit.nu % n) * config.range_resolution_m
    # a = mu at k = 0 over the carrier term there, exp(-i 4 pi f0 r / c)
    amp = fit.amp * (np.exp((-2j * np.pi / n) * fit.nu * fit.kc[0]) / range_phase(config.f0_hz, range_m, config))[
        ..., None]
    noise = (np.abs(np.fft.ifft(_residual(codes, fit), axis=1) / ramps) ** 2).sum(axis=2).mean(axis=1)  # a bin
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
