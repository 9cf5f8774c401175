"""cml's count test (``pfa``: each frame's count decided): before each detection, the peak
over the mean of the joint energy of a residual's back projection, away from the targets
found and inside the range gate, must reach the threshold whose false-alarm probability on a
target-free residual is ``pfa`` per frame and test; the test runs on two residuals, the
linear one ``Z - xi - model`` and the likelihood's score, and a frame passes only if both
show a peak (the statistic is the smaller ratio), so the false-alarm rate holds wherever
either residual is white. The statistic is computed by the engine
(:mod:`pipeline.dsp.cml.kernels.detect`, :mod:`pipeline.dsp.cml.reference`)."""

from __future__ import annotations

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
