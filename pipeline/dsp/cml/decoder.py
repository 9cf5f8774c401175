"""The decoder: :class:`CmlDecoder`, cml for one radar configuration and its options, with what
it keeps between calls (the detection grid of each range gate, the count test's thresholds,
the engine's tables and work buffers)."""

from __future__ import annotations

import numpy as np

from radar_driver.model import RadarConfig

from pipeline.dsp.cml import engine
from pipeline.dsp.cml.checks import check_frames, check_init
from pipeline.dsp.cml.count import WARM_PFA, threshold
from pipeline.dsp.cml.grid import COARSE_PER_BIN, SearchGrid
from pipeline.dsp.cml.likelihood import model_ramps
from pipeline.dsp.cml.options import BLOCK_FRAMES, BLOCK_SOURCE_BYTES, CmlOptions
from pipeline.dsp.cml.result import CmlResult
from pipeline.dsp.cml.warm import warm_or_cold
from pipeline.dsp.gate import RangeGate, check_gate

#: grids and thresholds a decoder keeps (a live node uses one gate and one pfa)
KEPT = 16


def block_frames(n: int, rm: int, sources: int) -> int:
    """Frames decoded at once: :data:`BLOCK_FRAMES`, halved (down to 8) while a block's back
    projections (``sources`` inverse FFTs a frame of ``rm`` model ramps, 2 antennas,
    COARSE_PER_BIN ``n`` complex128 points each) exceed :data:`BLOCK_SOURCE_BYTES`."""
    frames = BLOCK_FRAMES
    while frames > 8 and frames * sources * rm * 2 * COARSE_PER_BIN * n * 16 > BLOCK_SOURCE_BYTES:
        frames //= 2
    return frames


class CmlDecoder:
    """cml (:func:`pipeline.dsp.cml.cml`) for frames of radar ``config`` with ``options``.
    Hold one where calls follow one another (a node, a re-processing run, a benchmark): it
    keeps each range gate's detection grid and the count test's thresholds, and its engine
    the coarse grid's tables (about 0.8 ms to build) and each thread's work buffers. Its
    calls may come from several threads."""

    def __init__(self, config: RadarConfig, options: CmlOptions = CmlOptions()):
        self.config, self.options = config, options
        self.engine = engine.resolve(options.engine)
        self._blocks = engine.blocks(self.engine, config, options)
        self._grids: dict[RangeGate | None, SearchGrid] = {}
        self._thresholds: dict[tuple, float] = {}

    def grid(self, gate: RangeGate | None) -> SearchGrid:
        """The detection grid with the range ``gate`` (None: the whole axis), checked against
        the radar and built once per gate."""
        grid = self._grids.get(check_gate(gate))
        if grid is None:
            grid = SearchGrid(None if gate is None else gate.check(self.config), self.config, self.options.oversample)
            if len(self._grids) >= KEPT:
                self._grids.clear()
            self._grids[gate] = grid
        return grid

    def threshold(self, pfa: float, grid: SearchGrid, rm: int = 1) -> float:
        """The count test's threshold (linear) at ``pfa`` on ``grid`` with ``rm`` model ramps
        (:mod:`pipeline.dsp.cml.count`)."""
        key = (pfa, grid.gate, rm)
        value = self._thresholds.get(key)
        if value is None:
            value = threshold(pfa, self.config, grid, rm)
            if len(self._thresholds) >= KEPT:
                self._thresholds.clear()
            self._thresholds[key] = value
        return value

    def decode(self, z: np.ndarray, xi: np.ndarray | None, delta, bits: int | None, k: int, *, noise_sigma=None,
               pfa: float | None = None, gate: RangeGate | None = None,
               init_range_m: np.ndarray | None = None) -> CmlResult:
        """:func:`pipeline.dsp.cml.cml` of ``z``, ``xi``, ``delta``, ``bits`` with ``k`` targets
        (see there for the arguments)."""
        frames = check_frames(z, xi, delta, bits, self.config, k, noise_sigma, self._blocks.in_kernel)
        grid = self.grid(gate)
        rm = model_ramps(frames.z.shape[1] // self.config.samples_per_ramp, self.options.motion)
        limit = None if pfa is None else self.threshold(pfa, grid, rm)
        iters = self.options.iters_for(frames.bits, frames.dithered)
        b = frames.z.shape[0]
        if b == 0:
            return CmlResult.empty(k)
        # a count test (or a warm start's statistic) reads the likelihood's score besides the residual
        counting = (limit is not None or init_range_m is not None) and frames.bits is not None
        block = block_frames(self.config.samples_per_ramp, rm, 2 if counting else 1)
        if init_range_m is not None:
            init = check_init(init_range_m, b, k, self.config, grid.gate)
            return warm_or_cold(self._blocks, frames, k, iters, grid, limit, init, self.threshold(WARM_PFA, grid, rm),
                                block)
        if b <= block:  # one block: the arrays as they are
            res = self._blocks.decode(frames, k, iters, grid, limit)
        else:
            res = CmlResult.concatenate([self._blocks.decode(frames.part(slice(lo, lo + block)), k, iters, grid,
                                                             limit) for lo in range(0, b, block)])
        if limit is None and grid.use:
            return self._short_frames(res, frames, k, iters, grid)
        return res

    def _short_frames(self, res: CmlResult, frames, k: int, iters: int, grid: SearchGrid) -> CmlResult:
        """``res`` of K given targets in a range gate, its frames that hold fewer than ``k``
        inside the gate (a stage went to a return outside it) decoded again with room for
        those returns (:data:`~pipeline.dsp.cml.grid.NUISANCE_STAGES` more stages, the fit
        settled before each: modelled, not reported); the others as they are."""
        short = np.flatnonzero(res.present.sum(axis=1) < k)
        if short.size == 0:
            return res
        rows = [res.row(j) for j in range(res.range_m.shape[0])]
        for lo in range(0, short.size, BLOCK_FRAMES):
            idx = short[lo:lo + BLOCK_FRAMES]
            again = self._blocks.decode(frames.part(idx), k, iters, grid, None, nuisance=True)
            for j, i in enumerate(idx.tolist()):
                rows[i] = again.row(j)
        return CmlResult.stack(rows)
