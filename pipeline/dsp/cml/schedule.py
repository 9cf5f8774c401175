"""cml's schedule of the likelihood's scale ``sigma_eff``: where it starts, its floor, the
annealing's levels between them, and the noise the model leaves (which no level goes below
when the noise is not given).

Without a dither and without the noise, 1-bit codes (not b-bit: their cells are a scale) fix the amplitudes and the noise only
together (``sign(Gamma + n)`` is that of ``c Gamma + c n``): a lower ``sigma_eff`` is a larger
amplitude for the same codes, so annealing would only rescale the fit, and a fit left behind
its scale (its amplitudes grew 7-18 times at the greedy stage's scale, measured at noise 0.01
of the target) leaves a score the count test reads as the quantizer's harmonics; there
``sigma_eff`` stays at its start and the amplitudes take the scale (their steps uncapped).

``sigma_eff`` (frame units) starts at ``max(delta / 4, noise_sigma)`` for the greedy stage,
then falls geometrically over ``anneal`` levels (one step each) to its floor
``max(delta / M, noise_sigma)`` (``delta / M``: the size of the cell of amplitudes consistent
with M codes). When ``noise_sigma`` is not given, no level is sharper than the noise estimated
from the codes the current model gets wrong (:func:`wrong_codes_rms`): under Gaussian noise of
std sigma (and a dither or signal spread wider than sigma) their RMS distance to their cell is
``sigma sqrt(2/3)``."""

from __future__ import annotations

import numpy as np

from pipeline.dsp.cml.checks import Frames

#: first sigma_eff, in units of delta
SIGMA_START = 0.25
#: refinement steps of a warm start at the greedy stage's scale, before the annealing
WARM_STEPS = 1
#: levels of the warm start's annealing (at most ``anneal``): from the greedy stage's scale
#: to the floor in fewer, larger steps, the ranges being close already
WARM_ANNEAL = 4


def start(frames: Frames) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """The first likelihood scale sigma_eff (B,), its floor (B,; None unquantized) and the
    largest amplitude change of a step (the quantizer's half range; unquantized: none) of
    checked ``frames``."""
    b, m = frames.z.shape[:2]
    if frames.bits is None:  # least squares: the scale plays no part
        return np.ones(b), None, np.full(b, np.inf)
    delta, noise_sigma, cap = frames.delta, frames.noise_sigma, frames.delta * (1 << (frames.bits - 1))
    if noise_sigma is None and not frames.dithered and frames.bits == 1:  # codes fix Gamma / sigma alone
        sigma = SIGMA_START * delta
        return sigma, sigma, np.full(b, np.inf)
    if noise_sigma is None:  # delta > 0: the maxima with a noise of 0, without computing them
        return SIGMA_START * delta, delta / m, cap
    return np.maximum(SIGMA_START * delta, noise_sigma), np.maximum(delta / m, noise_sigma), cap


def anneal_levels(sigma: np.ndarray, floor: np.ndarray, anneal: int) -> np.ndarray:
    """The annealing's levels (B, ``anneal``): ``sigma ratio^j``, j = 0 .. anneal - 1, as
    repeated products, ``ratio`` taking ``sigma`` (B,) to ``floor`` (B,) at the last."""
    b = sigma.shape[0]
    ratio = (floor / sigma) ** (1.0 / anneal)
    levels = np.empty((b, anneal))
    levels[:] = ratio[:, None]
    levels[:, 0] *= sigma
    np.multiply.accumulate(levels, axis=1, out=levels)
    return levels


def warm_levels(sigma: np.ndarray, floor: np.ndarray, anneal: int) -> np.ndarray:
    """The warm start's annealing levels (B, min(anneal, WARM_ANNEAL)), from ``sigma`` to ``floor``."""
    levels_n = min(anneal, WARM_ANNEAL)
    return sigma[:, None] * ((floor / sigma) ** (1.0 / levels_n))[:, None] ** np.arange(1, levels_n + 1)


def wrong_codes_rms(a: np.ndarray, b: np.ndarray, bits: int, mu: np.ndarray) -> np.ndarray:
    """RMS distance (B,) of the codes that the model ``mu`` (B, Rm, N, 2, 2) (Rm = 1: every
    ramp's) gets wrong to their cells, frame units (0 when none is wrong), in float32 as the
    likelihood: ``a``, ``b`` (B, R, N, 2, 2) float32 the codes' arrays (1 bit: the sign s and
    ``s xi``; b bits: the cell ``[lo, hi)`` of lambda)."""
    nb = mu.shape[0]
    mu = mu.astype(np.float32)
    v = np.empty(a.shape, dtype=np.float32)
    if bits == 1:
        np.multiply(a, mu, out=v)
        v += b
        np.minimum(v, 0.0, out=v)
    else:
        t = np.empty(a.shape, dtype=np.float32)
        np.subtract(a, mu, out=v)
        np.maximum(v, 0.0, out=v)
        np.subtract(mu, b, out=t)
        np.maximum(t, 0.0, out=t)
        v += t
    miss = v.reshape(nb, -1)
    wrong = np.count_nonzero(miss, axis=1)
    return np.sqrt(np.einsum("bj,bj->b", miss, miss, dtype=float) / np.maximum(wrong, 1))


def residual_rms(y: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """RMS (B,) of the residual of unquantized frames ``y`` (B, R, N, 2, 2) less the model
    ``mu`` (B, Rm, N, 2, 2) of each ramp (Rm = 1: every ramp's) (their sigma_eff)."""
    b = mu.shape[0]
    return np.sqrt(np.mean((mu - y).reshape(b, -1) ** 2, axis=1))
