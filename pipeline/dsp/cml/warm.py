"""cml's warm start: frames that come with ranges to start from (e.g. the previous frame's
targets) are refined from them instead of searched from scratch: their amplitudes estimated
at those ranges (a target's phase turns by ``4 pi dr / lambda``, 5 rad for 5 mm at 24 GHz: the
previous amplitudes say little), then :data:`~pipeline.dsp.cml.schedule.WARM_STEPS` refinement
steps and :data:`~pipeline.dsp.cml.schedule.WARM_ANNEAL` levels of the annealing. A frame
without one, or whose warm fit the model no longer explains, is decoded from scratch: the
count test (at the frame's threshold, else :data:`~pipeline.dsp.cml.count.WARM_PFA`) finds a
peak in the residual (a target appeared or moved beyond the steps' reach), or with a count
test a target's statistic fell below the test's threshold (it vanished)."""

from __future__ import annotations

import numpy as np

from pipeline.dsp.cml.checks import Frames
from pipeline.dsp.cml.grid import SearchGrid
from pipeline.dsp.cml.result import CmlResult
from pipeline.dsp.localize import to_db


def misfit(res: CmlResult, count: np.ndarray, stat: np.ndarray, k: int, threshold: float | None,
           at: float) -> np.ndarray:
    """The warm frames (B,) bool the model no longer explains. Without a count test
    (``threshold`` None): a frame holds fewer than ``k`` targets (``count`` (B,)) or its
    residual's count-test statistic ``stat`` (B,) reaches ``at`` (linear). With one: it holds
    fewer than ``k`` and the statistic reaches ``at`` (a target appeared), or a target's
    statistic fell below the threshold (it vanished)."""
    unexplained = stat >= at
    if threshold is None:  # k targets a frame, whatever their strength
        return (count < k) | unexplained
    weakest = np.where(res.present, res.statistic_db, np.inf).min(axis=1)
    return ((count < k) & unexplained) | (weakest < to_db(np.asarray(threshold, dtype=float)))  # or vanished


def warm_or_cold(blocks, frames: Frames, k: int, iters: int, grid: SearchGrid, threshold: float | None,
                 init: np.ndarray, warm_threshold: float, block: int) -> CmlResult:
    """:func:`pipeline.dsp.cml.cml` of checked ``frames`` with starting ranges ``init`` (B, k)
    m (NaN: none) by the engine's ``blocks``, ``block`` frames at a time: warm frames refined
    from them, the others and the warm ones the model no longer explains from scratch."""
    b = frames.z.shape[0]
    warm = ~np.isnan(init).all(axis=1)
    out: list[CmlResult | None] = [None] * b
    cold = np.flatnonzero(~warm)
    widx = np.flatnonzero(warm)
    if widx.size:
        whole = widx.size == b <= block  # one block of warm frames (a live node's call): no copies
        for lo in range(0, widx.size, block):
            idx = widx[lo:lo + block]
            part, start = (frames, init) if whole else (frames.part(idx), init[idx])
            at = warm_threshold if threshold is None else threshold  # the statistic only decides stat >= at
            res, count, stat = blocks.warm(part, k, start, grid, at)
            bad = misfit(res, count, stat, k, threshold, at)
            if whole and not bad.any():
                return res
            for j, i in enumerate(idx.tolist()):
                out[i] = None if bad[j] else res.row(j)
        cold = np.flatnonzero([o is None for o in out])
    whole = cold.size == b <= block  # one block, every frame from scratch: no copies
    for lo in range(0, cold.size, block):
        idx = cold[lo:lo + block]
        res = blocks.decode(frames if whole else frames.part(idx), k, iters, grid, threshold)
        if whole:
            return res
        for j, i in enumerate(idx.tolist()):
            out[i] = res.row(j)
    return CmlResult.stack(out)
