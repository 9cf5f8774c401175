"""Continuous maximum likelihood (CML): off-grid ranges from quantized or full frames.

Model (DESIGN.md, eq. 2), for frames of whole ramps (``M = R N``,
``f_m = f0 + B (m mod N) / N``)::

    Gamma_{m,p} = sum_t a_{t,p} exp(-i 4 pi f_m r_t / c),   r_t in [0, N dR)

with one continuous range ``r_t`` and one complex amplitude per antenna ``a_{t,1}``,
``a_{t,2}`` per target (angle = :func:`radar_driver.model.angle_from_antennas_rad`).

Decoding is greedy, as in NOMP (Mamandipoor et al., arXiv 1509.01942): **detect** a target
on the back projection of a residual (:mod:`.detect`; with ``pfa`` after the count test,
:mod:`.count`), then **refine** all the targets found so far at once by Levenberg--Marquardt
steps on the negative log-likelihood of the codes given the known dither (:mod:`.fit`, the
likelihood: :mod:`.likelihood`); after the last detection the likelihood's scale anneals to
its floor (:mod:`.schedule`). Frames that come with ranges start from them (:mod:`.warm`).
With a range gate (:mod:`pipeline.dsp.gate`) detection looks only at the points of the
oversampled grid inside it (:mod:`.grid`), the count test's peak and mean are taken there,
and every refinement step is clamped to it: a target never leaves the gate (ranges then in
``[min_range_m, max_range_m]``, not wrapped).

The modules: :mod:`.decoder` (:class:`CmlDecoder`, what a decoder keeps between calls),
:mod:`.checks` (the input), :mod:`.options` (:class:`CmlOptions`), :mod:`.result`
(:class:`CmlResult`), :mod:`.engine` (the one place the engine is chosen), the compiled
engine (:mod:`.compiled` and its kernels, :mod:`.kernels`) and the numpy reference it is
tested against (:mod:`.reference`), :mod:`.loading` (the kernels ahead of the first frame).

Shapes: frames (B, M, 2) complex (measurement, antenna); per-target arrays (B, K),
strongest first; amplitudes (B, K, 2).
"""

from __future__ import annotations

import numpy as np

from radar_driver.model import RadarConfig

from pipeline.dsp.cml.engine import DEFAULT_ENGINE, HAVE_NUMBA
from pipeline.dsp.cml.options import (BLOCK_FRAMES, DEFAULT_ITERS, DEFAULT_LIKELIHOOD, ENGINES, LIKELIHOODS,
                                      UNDITHERED_ITERS, CmlOptions)
from pipeline.dsp.cml.result import CmlResult, cml_detections, model_frames
from pipeline.dsp.gate import RangeGate

__all__ = ["BLOCK_FRAMES", "DEFAULT_ENGINE", "DEFAULT_ITERS", "DEFAULT_LIKELIHOOD", "ENGINES", "HAVE_NUMBA",
           "LIKELIHOODS", "UNDITHERED_ITERS", "CmlDecoder", "CmlOptions", "CmlResult", "cml", "cml_detections",
           "load_kernels", "model_frames"]


#: the names whose modules load the compiled kernels (numba, ~0.25 s): imported on first use, so
#: that a process that never decodes with cml (a router, a driver, the quantizer) does not pay it
_LAZY = {"CmlDecoder": "pipeline.dsp.cml.decoder", "load_kernels": "pipeline.dsp.cml.loading"}


def __getattr__(name: str):
    """``CmlDecoder`` and ``load_kernels``, from their modules on first use (PEP 562)."""
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def cml(z: np.ndarray, xi: np.ndarray | None, delta, bits: int | None, config: RadarConfig, k: int, *,
        noise_sigma=None, pfa: float | None = None, gate: RangeGate | None = None,
        init_range_m: np.ndarray | None = None, options: CmlOptions | None = None) -> CmlResult:
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
    pfa : None (exactly ``k`` targets), or decide each frame's count by the count test
        (:mod:`pipeline.dsp.cml.count`) at false-alarm probability ``pfa`` per frame and test;
        the first miss ends the frame's targets.
    gate : a :class:`~pipeline.dsp.gate.RangeGate`: targets are sought, tested and refined
        only inside it, and their ranges stay in it (None: the whole, circular, range axis).
    init_range_m : (B, J) ranges (m) to start from, NaN for none (e.g. the previous
        frame's targets: warm start, :mod:`pipeline.dsp.cml.warm`), J <= k.
    options : the engine, the likelihood, the refinement steps, the annealing's levels and
        the detection grid (:class:`CmlOptions`; None: the defaults).

    Returns
    -------
    CmlResult, targets strongest first (with ``pfa``: the present ones first).

    The batch is decoded in blocks of ``BLOCK_FRAMES`` frames: with a fixed ``k`` a frame's
    result does not depend on the others. With ``pfa``, a frame whose count is decided keeps
    taking refinement steps while others of its block look for more targets, so its
    estimates can move slightly with the batch (about 1e-5 m in range and 1 % in amplitude in
    a 4-bit case). About 14 evaluations of the likelihood and 8 Gauss--Newton systems for
    K = 2 (M = 512). A call builds its decoder's tables (about 0.8 ms): where calls follow
    one another, hold a :class:`CmlDecoder`.
    """
    from pipeline.dsp.cml.decoder import CmlDecoder

    decoder = CmlDecoder(config, CmlOptions() if options is None else options)
    return decoder.decode(z, xi, delta, bits, k, noise_sigma=noise_sigma, pfa=pfa, gate=gate,
                          init_range_m=init_range_m)
