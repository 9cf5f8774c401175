"""The fit of the compiled engine: the targets found so far (a
:data:`~pipeline.dsp.cml.kernels.layout.Fit`), Levenberg--Marquardt steps on all of them at
once (:func:`pipeline.dsp.cml.kernels.refine.refine`) and the result in the model's terms.

Refinement: Levenberg--Marquardt steps (Gauss--Newton, a step kept only when the likelihood
improves) on the negative log-likelihood of the codes given the known dither, over all the
parameters of all the targets found so far at once (6 reals a target: range, two complex
amplitudes and the phase step between ramps, :data:`pipeline.dsp.cml.kernels.model.PARAMS`;
the static model keeps the phase step at 0). This joint step does what NOMP's
cyclic re-refinement does -- a strong off-grid target's sidelobes no longer hide a weak one --
with one likelihood evaluation a step for all the targets.

Internally ranges are in bins (``nu = r / dR``) and amplitudes are referred to the middle
of the sweep (``b = a exp(-i 2 pi nu (f0 / B + (N - 1) / (2 N)))``), which decorrelates
range from phase, and to the middle of the frame (ramp r's is ``b exp(i (r - (R - 1) / 2)
phi)``), which decorrelates the phase step from the phase; the result gives them in the
model's terms."""

from __future__ import annotations

import numpy as np

from radar_driver.model import RadarConfig

from pipeline.dsp.cml.grid import INSIDE_TOLERANCE_BINS, SearchGrid
from pipeline.dsp.cml.kernels.layout import Fit, Report, Steps, Targets
from pipeline.dsp.cml.kernels.entry import finish, refine, result
from pipeline.dsp.cml.kernels.stages import sources
from pipeline.dsp.cml.likelihood import BlockCodes, array, evaluate_fit
from pipeline.dsp.cml.options import MAX_PHASE_STEP_RAD, MAX_RANGE_STEP_BINS, WRONG_RMS_PER_SIGMA
from pipeline.dsp.cml.result import CmlResult
from pipeline.dsp.cml.schedule import residual_rms, wrong_codes_rms
from pipeline.dsp.localize import STATISTIC_CAP_DB


def empty_fit(b: int, n: int, rm: int) -> Fit:
    """No target yet in a block of ``b`` frames of ``n`` samples a ramp, ``rm`` model ramps:
    the model is 0."""
    fit = new_fit(b, 0, n, rm)
    fit.mu.fill(0.0)
    fit.nll.fill(np.nan)
    return fit


def new_fit(b: int, t: int, n: int, rm: int) -> Fit:
    """A fit of ``t`` targets to be filled by a kernel (``lm`` 1e-3, ``nll`` 0, ``sigma`` NaN: no
    level evaluated yet, the first refinement step evaluates)."""
    lm, nll, sigma = np.empty(b), np.zeros(b), np.empty(b)
    lm.fill(1e-3)
    sigma.fill(np.nan)
    return Fit(np.empty((b, t)), np.empty((b, t)), np.empty((b, t, 2), dtype=complex), np.empty((b, t), dtype=bool),
               lm, nll, sigma, np.empty((b, rm, n, 4)), np.empty((b, rm, n, 4)), np.empty((b, rm, n, 4)))


def steps(levels: np.ndarray, amp_cap: np.ndarray, adapt: bool = False) -> Steps:
    """Refinement steps at the noise std ``levels`` (B, S) (``adapt``: not below the noise the
    model leaves), amplitude changes capped at ``amp_cap`` (B,)."""
    return Steps(array(levels, float), adapt, array(amp_cap, float), MAX_RANGE_STEP_BINS, WRONG_RMS_PER_SIGMA,
                 MAX_PHASE_STEP_RAD)


def run(codes: BlockCodes, fit: Fit, plan: Steps) -> Fit:
    """``fit`` after the refinement steps ``plan``, its ``sigma`` the last level. Without a
    target only the level moves (not below the noise of the empty model when adapted)."""
    if fit.nu.shape[1]:
        refine(codes.args, tuple(fit), tuple(plan))
        return fit
    if plan.levels.shape[1] == 0:
        return fit
    sigma = plan.levels[:, -1]
    if plan.adapt:
        b, rm, n = fit.mu.shape[:3]
        shape = (b, codes.ramps, n, 2, 2)
        noise = wrong_codes_rms(codes.kernel.a.reshape(shape), codes.kernel.b.reshape(shape), codes.bits,
                                fit.mu.reshape(b, rm, n, 2, 2))
        sigma = np.maximum(sigma, noise / WRONG_RMS_PER_SIGMA)
    return evaluate_fit(codes, fit, sigma)


def report(config: RadarConfig, grid: SearchGrid) -> Report:
    """What a result needs of the radar ``config`` and the detection ``grid``'s range gate."""
    return Report(config.range_resolution_m, 4.0 * np.pi / config.c_m_s * config.f0_hz, grid.use,
                  float(grid.lo) - INSIDE_TOLERANCE_BINS, float(grid.hi) + INSIDE_TOLERANCE_BINS, STATISTIC_CAP_DB)


def targets(b: int, k: int) -> Targets:
    """A result's arrays for ``b`` frames of ``k`` targets."""
    return Targets(np.empty((b, k)), np.empty((b, k, 2), dtype=complex), np.empty((b, k)), np.empty((b, k), dtype=bool),
                   np.empty((b, k)))


def finish_fit(codes: BlockCodes, fit: Fit, plan: Steps, about: tuple, k: int) -> CmlResult:
    """The annealing's steps ``plan`` and the result (``k`` targets a frame; ``about``:
    the radar's :func:`report`), in one kernel call (the kernels' namedtuples as plain tuples)."""
    out = targets(fit.nu.shape[0], k)
    finish(codes.args, tuple(fit), tuple(plan), about, tuple(out))
    return CmlResult(out.range_m, out.amp, out.stat, fit.sigma, out.present, out.phi)


def fit_result(codes: BlockCodes, fit: Fit, about: tuple, k: int, sigma: np.ndarray | None) -> CmlResult:
    """The fit in the model's terms (``about``: the radar's :func:`report`, a plain tuple), its
    statistic, padded to ``k`` targets (absent ones last), present ones strongest first, with
    sigma_eff ``sigma`` (None: unquantized, the RMS of the residual)."""
    b, rm, n = fit.mu.shape[:3]
    y = np.empty((b, rm, n, 2), dtype=complex)
    sources(codes.kernel.data, fit.mu, fit.mu, float(codes.ramps), False, False, y.view(float).reshape(b, rm, n, 4),
            np.zeros((b, 0, rm, 2, n), dtype=complex))
    out = targets(b, k)
    result(tuple(fit), y, codes.ramps, about, tuple(out))
    if sigma is None:
        sigma = residual_rms(codes.y, fit.mu.reshape(b, rm, n, 2, 2))
    return CmlResult(out.range_m, out.amp, out.stat, sigma, out.present, out.phi)
