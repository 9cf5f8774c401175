"""Detection and the count test of the compiled engine: the residuals a greedy stage
back-projects (written by one kernel into zero-padded buffers, one inverse FFT of the block),
then one kernel call for the count test, the detection, the new target's amplitudes and its
refinement (:func:`pipeline.dsp.cml.kernels.stages.add_target`).

Detection (greedy, as in NOMP, Mamandipoor et al., arXiv 1509.01942): back-project a residual
(each ramp's, zero-padded inverse FFT of ``oversample * N`` points; the static model: folded
over the ramps) and take the peak of the joint energy ``|U1|^2 + |U2|^2`` at least a range
bin away from the targets already found (inside the range gate); with a phase step between
ramps the energy of a range is its largest over the phase step (two ramps, U and V:
``|U|^2 + |V|^2 + 2 |U1* V1 + U2* V2|``, :func:`pipeline.dsp.cml.kernels.doppler.doppler`),
and the new target's phase step is where it peaks. The residual is ``Z - xi`` for the first target (full
frames: ``Z``), then the score of the likelihood in each measurement: for quantized codes it
sits on the few codes the current model gets wrong, which is far less noisy than
``Z - xi - model``."""

from __future__ import annotations

import threading
from typing import NamedTuple

import numpy as np

from pipeline.dsp.cml.count import information_floor, precision_floor
from pipeline.dsp.cml.grid import COARSE_PER_BIN, SearchGrid
from pipeline.dsp.cml.fit import new_fit
from pipeline.dsp.cml.kernels import entry, stages
from pipeline.dsp.cml.kernels.layout import Decision, Fit
from pipeline.dsp.cml.likelihood import BlockCodes



class Buffers:
    """The zero-padded inverse FFT's input buffers of one decoder, per thread: a (B, S, Rm, 2,
    L) complex buffer whose points beyond N stay zero (only the first ``n`` points of each row
    are ever written), the first B frames of one buffer per (S, Rm, L, n), as large as the
    largest block seen (8 MB for 64 frames, S = 2, Rm = 1, L = 2048)."""

    def __init__(self):
        self._local = threading.local()

    def padded(self, shape: tuple[int, int, int, int, int], n: int) -> np.ndarray:
        """A zeroed-beyond-``n`` buffer of ``shape`` (B, S, Rm, 2, L)."""
        cache = getattr(self._local, "cache", None)
        if cache is None:
            cache = self._local.cache = {}
        b, key = shape[0], shape[1:] + (n,)
        buf = cache.get(key)
        if buf is None or buf.shape[0] < b:
            if buf is None and len(cache) >= 4:  # a few grids live at once: keep the memory bounded
                cache.clear()
            buf = cache[key] = np.zeros(shape, dtype=complex)
        return buf[:b]


class Search(NamedTuple):
    """A detection grid as the kernels read it: the grid (:class:`~pipeline.dsp.cml.grid.SearchGrid`),
    its range gate, its constants and what a result needs of the radar (the kernels'
    :data:`~pipeline.dsp.cml.kernels.layout.Gate`, :data:`~pipeline.dsp.cml.kernels.layout.Grid`
    and :data:`~pipeline.dsp.cml.kernels.layout.Report` as plain tuples, as the entry kernels
    take them, :mod:`pipeline.dsp.cml.kernels.entry`) and the decoder's buffers."""

    grid: SearchGrid
    gate: tuple
    kernel: tuple
    report: tuple
    buffers: Buffers
    seed_gate: tuple


def ifft(x: np.ndarray) -> np.ndarray:
    """Inverse FFT along the last axis: numpy's (scipy's is the same pocketfft at the same cost
    a call at these shapes, B = 1 and 64, measured 2026-11-29, and importing scipy.fft costs each
    localizer's start-up 0.07 s of CPU)."""
    return np.fft.ifft(x, axis=-1)


def back_projections(codes: BlockCodes, fit: Fit, search: Search, count: bool, given: bool, decide: bool,
                     score: np.ndarray | None = None) -> tuple:
    """What the detect kernel reads (a :data:`~pipeline.dsp.cml.kernels.layout.Sources` as a
    plain tuple): the linear residual, the inverse FFTs of the sources it
    needs (the linear residual for the count test or the first detection; the likelihood's
    score for the count test of quantized frames and later detections), how many the count
    test reads (``count``) and which one detection reads (``given``: none, the range is
    given), on the coarse grid (COARSE_PER_BIN points a bin) when the grid allows it, unless
    the count test only decides (``decide``) with the range given (the exact statistic of a
    residual without a target is cheaper on the full grid: the coarse search then sums many
    cells). ``score``: the NLL's derivatives to take the score from (B, N, 4) (the settled
    fit's efficient score, :func:`settled_score`), None: ``fit.g``."""
    on_score = codes.bits is not None and not given and fit.nu.shape[1] > 0  # detection on the likelihood's score
    with_residual = count or (not given and not on_score)
    with_score = codes.bits is not None and (count or on_score)
    coarse = (not given or decide) and search.grid.coarse
    b, rm, n = fit.mu.shape[:3]
    y = np.empty((b, rm, n, 2), dtype=complex)
    buf = search.buffers.padded((b, int(with_residual) + int(with_score), rm, 2, (COARSE_PER_BIN if coarse else
                                                                                search.grid.oversample) * n), n)
    g = fit.g if score is None else score
    stages.sources(codes.kernel.data, fit.mu, g if with_score else fit.mu, float(codes.ramps), with_residual,
                   with_score, y.view(float).reshape(b, rm, n, 4), buf)
    count_sources = buf.shape[1]
    u = ifft(buf) if count_sources else buf
    # the kernels' Sources, as a plain tuple (the entry kernels take those)
    return u, buf, y, codes.ramps, count_sources if count else 0, -1 if given else count_sources - 1 if on_score else 0


def decision(b: int, threshold: float | None, active: np.ndarray, floor: np.ndarray) -> Decision:
    """The count test's ``threshold`` (linear; None: none), ``active`` (B,) bool and ``floor``
    (B, 2) (:func:`count_floor`), and the arrays detection writes, for ``b`` frames (reused by
    the greedy stages of a decode)."""
    return Decision(-1.0 if threshold is None else float(threshold), active, np.zeros(b), np.empty(b),
                    np.empty((b, 2), dtype=complex), floor, np.zeros(b))


def count_floor(codes: BlockCodes, fit: Fit, oversample: int, out: np.ndarray | None = None) -> np.ndarray:
    """The count test's floors (B, 2) of a block's two residuals (into ``out``): the linear
    residual's, the frames' precision unquantized (:func:`pipeline.dsp.cml.count.precision_floor`;
    none, 0, for codes); the likelihood's score's, the information of a target's amplitude at
    ``fit`` (:func:`pipeline.dsp.cml.count.information_floor`; 0 unquantized)."""
    b = fit.mu.shape[0]
    if out is None:
        out = np.zeros((b, 2))
        if codes.bits is None:
            out[:, 0] = precision_floor(codes.y, oversample)
    if codes.bits is not None:
        out[:, 1] = information_floor(fit.h, codes.n, oversample) if fit.nu.shape[1] else 0.0
    return out


def settled_score(codes: BlockCodes, fit: Fit) -> np.ndarray | None:
    """The efficient score's ``g`` (B, Rm, N, 4) of a settled fit of quantized frames
    (:func:`pipeline.dsp.cml.kernels.refine.settled_score`), what its count test reads; None
    unquantized (the linear residual is the test's)."""
    if codes.bits is None:
        return None
    ge = np.empty(fit.g.shape)
    entry.settled_score(tuple(fit), ge)
    return ge


def add_target(codes: BlockCodes, fit: Fit, search: Search, found: tuple, plan: tuple,
               sigma: np.ndarray, score: np.ndarray | None = None) -> tuple[bool, Fit]:
    """One greedy stage: the count test (the :func:`decision` ``found``, as a plain tuple:
    its threshold) updating its ``active`` (B,) bool in place, the detection of a new target,
    its amplitudes (into ``found``) and the refinement steps ``plan`` (a plain tuple) at
    ``sigma`` (B,) of all the targets (``score``: as :func:`back_projections` takes it). Returns
    whether a frame holds a new target, and the fit (unchanged when none does)."""
    src = back_projections(codes, fit, search, found[0] >= 0.0, False, True, score)
    found[2].fill(0.0)  # the statistic
    if found[0] >= 0.0:
        count_floor(codes, fit, search.grid.oversample, found[5])
    b, t = fit.nu.shape
    new = new_fit(b, t + 1, fit.mu.shape[2], fit.mu.shape[1])
    grew = entry.add_target(src, search.kernel, search.gate, search.seed_gate, tuple(fit), codes.args, plan, sigma,
                            found, tuple(new))
    return grew, (new if grew else fit)


def statistic(codes: BlockCodes, fit: Fit, search: Search, at: float) -> np.ndarray:
    """The count test's statistic (B,) of ``fit``'s residuals, decided at ``at`` (linear): it
    reaches ``at`` exactly when the exact statistic does (cheaper)."""
    src = back_projections(codes, fit, search, True, True, True, settled_score(codes, fit))
    b = fit.nu.shape[0]
    test = Decision(float(at), np.ones(b, dtype=bool), np.zeros(b), np.zeros(b), np.empty((b, 2), dtype=complex),
                    count_floor(codes, fit, search.grid.oversample), np.zeros(b))
    entry.detect(src, search.kernel, search.gate, search.seed_gate, fit.nu, fit.live, tuple(test))
    return test.stat
