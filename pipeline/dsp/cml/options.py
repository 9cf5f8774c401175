"""cml's options (:class:`CmlOptions`) and the constants of its schedule."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.errors import ParameterError

#: the implementations of the per-frame work: "numba" (compiled, one frame at a time,
#: :mod:`pipeline.dsp.cml.compiled`) or "numpy" (vectorized over a block; the reference the
#: compiled one is tested against, :mod:`pipeline.dsp.cml.reference`); which one runs:
#: :func:`pipeline.dsp.cml.engine.resolve`
ENGINES = ("numba", "numpy")
#: likelihoods of a code: "logistic" (scaled logistic in place of the Gaussian CDF) or
#: "gaussian" (the exact Gaussian CDF of the noise: ``Phi((hi - l) / s) - Phi((lo - l) / s)``)
LIKELIHOODS = ("logistic", "gaussian")
DEFAULT_LIKELIHOOD = "logistic"

#: refinement steps after each detection: one is enough, the annealing refines all the targets
#: together after the last detection (measured, 2 000 off-grid scenes a case, K 1-3, K auto,
#: alpha 1 and 0.45, sigma 0-0.1, unquantized: errors the same or smaller than with 3 steps;
#: with none the weaker of two targets is found worse at alpha 0.45)
DEFAULT_ITERS = 1
#: ... but quantized frames without a dither, whose codes do not fix the amplitudes' scale,
#: need three (K = 2 with one: median error 0.69 -> 0.76 m on the grid, 0.46 -> 0.51 m off it)
UNDITHERED_ITERS = 3
#: frames decoded at once: the likelihood's work arrays (B x 4M float32 each) stay in cache
BLOCK_FRAMES = 64
#: the most bytes of a block's back projections, the count test's inverse FFTs (the residual's
#: and the likelihood score's, each model ramp and antenna, COARSE_PER_BIN N complex points a
#: frame): past it the block's temporaries are large enough that the C library maps them
#: afresh at each call. With the phase step's two model ramps and a count test, blocks of 64
#: frames (4 MiB of them) took 11 100 minor page faults a 256-frame call, and 0.53-0.56 ms a
#: frame; blocks of 32, none and 0.45-0.48 ms (`--K auto`, positions only, a process holding
#: that decoder alone, 2026-11-29)
BLOCK_SOURCE_BYTES = 2 << 20
#: logistic scale of a Gaussian of unit std (Phi(x) ~ F(1.702 x))
LOGISTIC_PER_SIGMA = 1.702
#: largest range change of one refinement step, range bins
MAX_RANGE_STEP_BINS = 0.5
#: largest change of a phase step between ramps in one refinement step, rad
MAX_PHASE_STEP_RAD = 1.0
#: RMS distance of the wrong codes to their cells, in units of the noise std
WRONG_RMS_PER_SIGMA = math.sqrt(2.0 / 3.0)


def is_int(v) -> bool:
    """Whether ``v`` is an integer (a Python or numpy one, not a bool)."""
    return type(v) is int or (isinstance(v, (int, np.integer)) and not isinstance(v, bool))


@dataclass(frozen=True)
class CmlOptions:
    """How :func:`pipeline.dsp.cml.cml` decodes.

    engine : "numba" (compiled kernels; the default when numba imports) or "numpy" (the
        vectorized reference); None: the default (:func:`pipeline.dsp.cml.engine.resolve`).
    likelihood : "logistic" or "gaussian" (the exact Gaussian likelihood of a code given the
        dither and the noise).
    iters : refinement steps after each detection; None: ``DEFAULT_ITERS``, or
        ``UNDITHERED_ITERS`` for quantized frames without a dither.
    anneal : final levels of ``sigma_eff``, falling geometrically to its floor (one
        refinement step each); unquantized frames: more least-squares steps.
    oversample : detection grid of ``oversample * N`` ranges.
    motion : each target has a phase step between consecutive ramps (its radial velocity,
        :mod:`pipeline.dsp.cml`), found by detection and refined with the rest; False: the
        paper's static model (every ramp of a frame the same; blind to targets whose phase
        turns by pi between ramps). Frames of one ramp are static whatever it says.
    """

    engine: str | None = None
    likelihood: str = DEFAULT_LIKELIHOOD
    iters: int | None = None
    anneal: int = 6
    oversample: int = 8
    motion: bool = True

    def __post_init__(self) -> None:
        if self.engine not in (None, *ENGINES):
            raise ParameterError(f"cml: engine={self.engine!r} is not known; available: {', '.join(ENGINES)}")
        if self.likelihood not in LIKELIHOODS:
            raise ParameterError(f"cml: likelihood={self.likelihood!r} is not known; available: "
                                 f"{', '.join(LIKELIHOODS)}")
        if not isinstance(self.motion, bool):
            raise ParameterError(f"cml: motion={self.motion!r} must be True or False")
        for name, value, lo in (("iters", self.iters, 0), ("anneal", self.anneal, 0),
                                ("oversample", self.oversample, 1)):
            if (value is not None or name != "iters") and (not is_int(value) or not lo <= value <= 1000):
                raise ParameterError(f"cml: {name}={value!r} must be an integer in [{lo}, 1000]")

    def iters_for(self, bits: int | None, dithered: bool) -> int:
        """The refinement steps after each detection for frames of ``bits`` (None:
        unquantized), ``dithered`` or not."""
        if self.iters is not None:
            return int(self.iters)
        return UNDITHERED_ITERS if bits is not None and not dithered else DEFAULT_ITERS
