"""cml's count test (``pfa``: each frame's count decided): before each detection, the peak
over the mean of the joint energy of a residual's back projection, away from the targets
found and inside the range gate, must reach the threshold whose false-alarm probability on a
target-free residual is ``pfa`` per frame and test; the test runs on two residuals, the
linear one ``Z - xi - model`` and the likelihood's score, and a frame passes only if both
show a peak (the statistic is the smaller ratio), so the false-alarm rate holds wherever
either residual is white. The statistic is computed by the engine
(:mod:`pipeline.dsp.cml.kernels.detect`, :mod:`pipeline.dsp.cml.reference`)."""

from __future__ import annotations

import numpy as np

from radar_driver.model import RadarConfig

from pipeline.dsp.cml.grid import SearchGrid
from pipeline.dsp.localize import cfar_threshold

#: independent cells a bin of the count test's search is worth (its peak is sought on the
#: oversampled grid, between the bins too); measured on target-free residuals (README)
SEARCH_CELLS_PER_BIN = 3.0
#: the count test looks for a peak this far from the targets found, range bins (a guard
#: band: a strong target's 1-bit fit leaves residual energy up to ~2 bins away)
COUNT_GUARD_BINS = 2.0
#: without a count test (k given), a warm frame goes back to a full search when its residual
#: has a peak the count test would take for a target at this false-alarm probability
WARM_PFA = 1e-3


#: independent cells the search over the phase step between ramps is worth, by the model's
#: ramps (the peak over range and phase step over its mean): measured on target-free
#: residuals (README); more ramps: one cell a ramp
DOPPLER_CELLS = {1: 1.0, 2: 2.0}


def doppler_cells(rm: int) -> float:
    """The cells (:data:`DOPPLER_CELLS`) of a search over the phase step of ``rm`` model ramps."""
    return DOPPLER_CELLS.get(rm, float(rm))


def threshold(pfa: float, config: RadarConfig, grid: SearchGrid, rm: int = 1) -> float:
    """The count test's threshold (linear) at false-alarm probability ``pfa`` over the
    bins the search spans and, with ``rm`` > 1 model ramps, the phase steps
    (:func:`pipeline.dsp.localize.cfar_threshold`)."""
    search_bins = config.samples_per_ramp if grid.gate is None else grid.width_bins
    return cfar_threshold(pfa, SEARCH_CELLS_PER_BIN * search_bins * doppler_cells(rm))


#: the unit roundoff of the frames on the wire (complex64, docs/design.md): an unquantized
#: residual at this level relative to its frame is the frames' own rounding (and the fit's
#: arithmetic), not a noise a target could stand above
FRAME_ROUNDOFF = 2.0 ** -24


def precision_floor(y: np.ndarray, oversample: int) -> np.ndarray:
    """The least mean joint energy (B,) the count test takes an unquantized residual's back
    projection to have, in the detection grid's scale (``oversample`` points a bin, the
    zero-padded inverse FFT's 1 / L): that of a white residual of std ``FRAME_ROUNDOFF`` times
    the RMS of the frames' real parts, ``y`` (B, R, N, 2, 2) (summed over the R ramps, or the
    total over the R ramps of a model with a phase step: ``4 N R v / L^2``, L = ``oversample``
    N). Without it a noiseless frame's residual (the rounding, structured by the targets)
    reads as targets: 0.99 false targets a frame (K = 1, complex64 frames; 3 with complex128)."""
    b, ramps, n = y.shape[:3]
    flat = y.reshape(b, -1)
    v = np.einsum("bj,bj->b", flat, flat) / flat.shape[1] * FRAME_ROUNDOFF ** 2
    return 4.0 * ramps * v / (n * oversample ** 2)


def information_floor(h: np.ndarray, n: int, oversample: int) -> np.ndarray:
    """The least mean joint energy (B,) the count test takes the likelihood's score's back
    projection to have: the Fisher information of a target's amplitudes at the fit (the
    score test's denominator, :math:`\\sum h / L^2` over the 4N real parts of ``h`` (B, Rm, N,
    2, 2 or 4) of each model ramp, the NLL's second derivatives (Rm = 1: summed over the
    ramps; with a phase step the total over the ramps, as the test's mean); L = ``oversample``
    N, N = ``n``). Where the model fits the codes with margins far beyond the likelihood's
    scale (1-bit codes without a dither at low noise), the score is a numerical remainder
    shaped by the targets' own crossings and its own mean says nothing; a target must then
    raise the likelihood by as much as the information allows."""
    b = h.shape[0]
    return h.reshape(b, -1).sum(axis=1) / float(oversample * n) ** 2
