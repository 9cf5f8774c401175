"""Integration in time: T quantized frames of a static scene decoded as one (issue 25).

Each frame of whole ramps carries its own dither, so T frames of R ramps of the same
static scene are one frame of T R ramps (:mod:`pipeline.cml`'s model: every ramp sees
the same N frequencies, the dither is known per measurement): the codes of the T frames
and their dithers are stacked along the measurement axis and decoded together by
:func:`pipeline.cml.cml`, whose error falls with the number of codes (off the grid, like
1/M without noise).

One-bit frames whose step ``delta`` differs from frame to frame (``delta = "auto"``) stack
exactly: a 1-bit code is the sign of ``Re/Im (Gamma + xi)``, which does not depend on
delta, and each frame keeps its own dither ``xi``; the stacked frame is given one common
step (the median) for cml's schedule. Frames of more bits must share one delta.
"""

from __future__ import annotations

import numpy as np

from radar_driver.model import RadarConfig

from .cml import cml
from .errors import ParameterError
from .gate import RangeGate
from .localize import Detections
from .quantize import QuantizedFrames


def stack_frames(frames: QuantizedFrames) -> tuple[np.ndarray, np.ndarray, float]:
    """T dithered frames (B = T) -> one frame: Z (1, T M, 2), its dither xi (1, T M, 2)
    and its step delta (frame units), for :func:`pipeline.cml.cml`."""
    if frames.codes.shape[0] == 0:
        raise ParameterError("integrate: no frames to stack")
    xi = frames.dither()
    if xi is None:
        raise ParameterError("integrate: the frames must all be dithered (alpha > 0): the codes of a static "
                             "scene without dither repeat, and stacking them adds nothing")
    delta = np.asarray(frames.delta, dtype=float)
    z = frames.values()
    if frames.bits == 1:
        common = float(np.median(delta))
        z = (np.sign(z.real) + 1j * np.sign(z.imag)) * (0.5 * common)  # the signs, on one step
    else:
        common = float(delta[0])
        if not np.allclose(delta, common, rtol=1e-6, atol=0):
            raise ParameterError(f"integrate: {frames.bits}-bit frames must share one step delta to be stacked, "
                                 f"got {delta.min():g} to {delta.max():g}")
    t, m, _ = z.shape
    return z.reshape(1, t * m, 2), xi.reshape(1, t * m, 2), common


def integrate(frames: QuantizedFrames, radar: RadarConfig, k: int, gate: RangeGate | None = None,
              pfa: float | None = None) -> Detections:
    """Targets (1, k) of T dithered frames (B = T, each of whole ramps of ``radar``) of a
    static scene, decoded together by cml (``pfa``: its count test, None: exactly k;
    ``gate``: the range gate it searches inside)."""
    n = radar.samples_per_ramp
    if frames.codes.shape[1] % n:
        raise ParameterError(f"integrate: M={frames.codes.shape[1]} is not a whole number of ramps of {n}")
    z, xi, delta = stack_frames(frames)
    g = None if gate is None else gate.check(radar)
    return cml(z, xi, delta, frames.bits, radar, k, pfa=pfa, gate=g, iters=INTEGRATE_ITERS,
               anneal=anneal_levels(z.shape[1])).detections(radar)


#: cml's refinement steps after each detection on stacked frames: the annealing that follows
#: does the work there (measured: 1, 2 or 3 give the same positions to the last digit on the
#: chamber's 20-frame windows and the Monte Carlo in time, and 1 costs 0.73 of 3)
INTEGRATE_ITERS = 1


def anneal_levels(m: int) -> int:
    """cml's annealing levels for a frame of M measurements: each level at most halves its
    sigma_eff on the way from delta / 4 to delta / M (at least cml's default, 6). Measured
    (one target off the grid, no noise, alpha 0.45, T = 1..32 frames): 6 levels whatever T
    give an error slope of -0.60 against T, these -0.88 (README, Tracks)."""
    return max(6, int(np.ceil(np.log2(max(m, 4) / 4.0))))


def concat_frames(parts: list[QuantizedFrames]) -> QuantizedFrames:
    """Frames of several batches (same M and bits) as one batch, each field per frame."""
    if not parts:
        raise ParameterError("integrate: no frames")
    b = [p.codes.shape[0] for p in parts]

    def per_frame(name, dtype=None):
        return np.concatenate([np.broadcast_to(np.asarray(getattr(p, name), dtype=dtype), (n,))
                               for p, n in zip(parts, b)])

    first = parts[0]
    return QuantizedFrames(np.concatenate([p.codes for p in parts]), per_frame("delta", float), first.bits,
                           per_frame("alpha", float), per_frame("dither_seed", np.uint64), per_frame("seq", np.uint64),
                           per_frame("generator"))
