"""cml's compiled engine (``engine="numba"``): a block of frames decoded by a few kernel calls
(:mod:`pipeline.dsp.cml.kernels`), one frame at a time inside each (so a frame costs the same
in a batch of 1 or of 64), with the tables and work buffers it keeps between calls."""

from __future__ import annotations

import numpy as np

from radar_driver.model import RadarConfig

from pipeline.dsp.cml.checks import Frames
from pipeline.dsp.cml.count import COUNT_GUARD_BINS
from pipeline.dsp.cml.detect import Buffers, Search, add_target, count_floor, decision, settled_score, statistic
from pipeline.dsp.cml.fit import empty_fit, finish_fit, fit_result, new_fit, report, run, steps, targets
from pipeline.dsp.cml.grid import COARSE_PER_BIN, COARSE_RHO, MIN_SEPARATION_BINS, SearchGrid, run_tables, twiddles
from pipeline.dsp.cml.kernels.layout import Gate, Grid
from pipeline.dsp.cml.kernels.search import gate_edge, gate_weights
from pipeline.dsp.cml.kernels.entry import warm
from pipeline.dsp.cml.likelihood import block_codes, check_in_kernel, evaluate_fit
from pipeline.dsp.cml.options import CmlOptions
from pipeline.dsp.cml.result import CmlResult
from pipeline.dsp.cml.schedule import WARM_STEPS, anneal_levels, residual_rms, start, warm_levels


class CompiledBlocks:
    """The compiled engine of a :class:`pipeline.dsp.cml.decoder.CmlDecoder` (radar ``config``,
    ``options``): decodes blocks of checked frames; keeps the coarse grid's tables and each
    range gate's arrays on the grid, and the zero-padded buffers of each thread."""

    #: the finite and level checks of quantized frames, in one kernel pass
    in_kernel = staticmethod(check_in_kernel)

    def __init__(self, config: RadarConfig, options: CmlOptions):
        self.config, self.options = config, options
        self._buffers = Buffers()
        self._tables: dict[str, np.ndarray] = {}
        self._searches: dict[int, tuple[SearchGrid, Search]] = {}

    def search(self, grid: SearchGrid) -> Search:
        """``grid`` as the kernels read it, built once per grid (the decoder keeps its grids)."""
        kept = self._searches.get(id(grid))
        if kept is not None and kept[0] is grid:
            return kept[1]
        n, lc = self.config.samples_per_ramp, COARSE_PER_BIN * self.config.samples_per_ramp
        table, tables = np.zeros(0, dtype=complex), np.zeros((0, 0))
        weights, inside, edges = np.zeros(1), 0, np.zeros(0, dtype=bool)
        outside = np.zeros(1, dtype=bool) if grid.outside is None else grid.outside
        if grid.coarse:
            table, tables = self._coarse_tables(n, grid.size, lc)
            if grid.use:
                weights, edges = np.empty(lc + 1), np.empty(lc, dtype=bool)
                inside = int(gate_weights(outside, tables, lc, weights))
                gate_edge(outside, lc, edges)
        gate = Gate(grid.use, float(grid.lo), float(grid.hi), outside, edges)
        whole = Gate(False, 0.0, 0.0, np.zeros(1, dtype=bool), np.zeros(0, dtype=bool))  # detection's: the whole axis
        kernel = Grid(grid.oversample, COUNT_GUARD_BINS, MIN_SEPARATION_BINS, COARSE_RHO, table, tables, weights,
                      inside)
        search = Search(grid, tuple(gate), tuple(kernel), tuple(report(self.config, grid)), self._buffers, tuple(whole))
        if len(self._searches) >= 16:
            self._searches.clear()
        self._searches[id(grid)] = (grid, search)
        return search

    def _coarse_tables(self, n: int, size: int, lc: int) -> tuple[np.ndarray, np.ndarray]:
        """The fine grid's twiddles and the run tables (:mod:`pipeline.dsp.cml.grid`), once."""
        if "table" not in self._tables:
            self._tables["table"], self._tables["runs"] = twiddles(size), run_tables(n, size, lc)
        return self._tables["table"], self._tables["runs"]

    def decode(self, frames: Frames, k: int, iters: int, grid: SearchGrid, threshold: float | None,
               nuisance: bool = False) -> CmlResult:
        """One block of checked ``frames`` from scratch: up to ``k`` greedy stages (count test at
        ``threshold``, linear; None: exactly ``k`` targets), each followed by ``iters``
        refinement steps, then the annealing (:mod:`pipeline.dsp.cml.schedule`). With a count
        test or ``nuisance`` the fit settles (the annealing) before each stage and, with a range
        gate, a frame takes up to :data:`~pipeline.dsp.cml.grid.NUISANCE_STAGES` more stages
        while it holds fewer than ``k`` targets inside the gate (the others modelled, not
        reported)."""
        b = frames.z.shape[0]
        n, anneal = self.config.samples_per_ramp, self.options.anneal
        search = self.search(grid)
        codes = block_codes(frames, n, self.options.likelihood, self.options.motion)
        fit = empty_fit(b, n, codes.rm)
        sigma, floor, amp_cap = start(frames)
        # active: the frames whose residual may still hold a target; as plain tuples, read by the kernels only
        found = tuple(decision(b, threshold, np.ones(b, dtype=bool), count_floor(codes, fit, grid.oversample)))
        if threshold is not None:
            fit = evaluate_fit(codes, fit, sigma)  # the score of the empty model, for the first count test
        settle = self._settle(frames, sigma, floor, amp_cap) if threshold is not None or nuisance else None
        greedy = tuple(steps(np.repeat(sigma[:, None], iters, axis=1), amp_cap))
        settled = False  # the fit annealed since its last target (what the count test reads)
        for _ in range(k + (grid.stages if settle is not None else 0)):
            score = None
            if settle is not None and fit.nu.shape[1]:  # the residuals of the settled fit
                fit = run(codes, fit, settle)
                settled = True
                score = settled_score(codes, fit) if threshold is not None else None
            if settle is not None and grid.use:  # a frame with k targets inside the gate is done
                found[1][:] &= (fit.live & grid.inside(fit.nu)).sum(axis=1) < k
                if not found[1].any():
                    break
            grew, fit = add_target(codes, fit, search, found, greedy, sigma, score)
            if not grew:
                break
            settled = False
        if settled:
            return fit_result(codes, fit, search.report, k, fit.sigma if frames.bits is not None else None)
        if frames.bits is not None and anneal:
            plan = steps(anneal_levels(sigma, floor, anneal), amp_cap, adapt=frames.noise_sigma is None)
            if fit.nu.shape[1]:  # the annealing and the result in one kernel call
                return finish_fit(codes, fit, plan, search.report, k)
            fit = run(codes, fit, plan)
            sigma = fit.sigma
        if frames.bits is None:
            fit = run(codes, fit, steps(np.ones((b, anneal)), amp_cap))  # least squares: polish
            sigma = None
        return fit_result(codes, fit, search.report, k, sigma)

    def _settle(self, frames: Frames, sigma: np.ndarray, floor, amp_cap: np.ndarray):
        """The steps that settle a fit before a count test, as at the end of a decode: the
        annealing (quantized; adapted to the noise the model leaves when it is not given), or
        least-squares steps (unquantized) (:meth:`pipeline.dsp.cml.reference.ReferenceBlocks._settle`)."""
        b, anneal = frames.z.shape[0], self.options.anneal
        if frames.bits is None:
            return steps(np.ones((b, anneal)), amp_cap)
        return steps(anneal_levels(sigma, floor, anneal) if anneal else np.empty((b, 0)), amp_cap,
                     adapt=frames.noise_sigma is None)

    def warm(self, frames: Frames, k: int, init: np.ndarray, grid: SearchGrid,
             at: float) -> tuple[CmlResult, np.ndarray, np.ndarray]:
        """One block of checked ``frames`` refined from the ranges ``init`` (B, k) m (NaN:
        absent; at least one a frame): their amplitudes one at a time in the residual,
        :data:`~pipeline.dsp.cml.schedule.WARM_STEPS` refinement steps, the warm start's
        annealing, in one kernel call. Returns the result, the targets a frame (B,) and the
        count test's statistic (B,) of the final residual, decided at ``at`` (linear)."""
        b = frames.z.shape[0]
        n, anneal = self.config.samples_per_ramp, self.options.anneal
        search = self.search(grid)
        codes = block_codes(frames, n, self.options.likelihood, self.options.motion)
        sigma, floor, amp_cap = start(frames)
        live_all = ~np.isnan(init)
        order = np.argsort(~live_all, axis=1, kind="stable")  # the given ranges first
        init = np.take_along_axis(init, order, axis=1)
        live_all = np.take_along_axis(live_all, order, axis=1)
        nu_all = np.nan_to_num(init) / self.config.range_resolution_m
        if frames.bits is None:  # least squares: the polish's steps
            plan = steps(np.ones((b, anneal)), amp_cap)
        else:
            plan = steps(warm_levels(sigma, floor, anneal) if anneal else np.empty((b, 0)), amp_cap,
                         adapt=frames.noise_sigma is None)
        out = targets(b, k)
        fit = new_fit(b, int(live_all.sum(axis=1).max()), n, codes.rm)
        first = steps(np.repeat(sigma[:, None], WARM_STEPS, axis=1), amp_cap)
        warm(codes.args, (nu_all, live_all), tuple(first), tuple(plan), sigma, search.report, tuple(out),
             tuple(fit))
        sigma = fit.sigma if frames.bits is not None else residual_rms(codes.y, fit.mu.reshape(b, codes.rm, n, 2, 2))
        res = CmlResult(out.range_m, out.amp, out.stat, sigma, out.present, out.phi)
        return res, (fit.live & grid.inside(fit.nu)).sum(axis=1), statistic(codes, fit, search, at)
