"""The likelihood of the codes, as the compiled engine holds it: a block's measurements as the
kernels' arrays (:class:`BlockCodes`), built and checked by one kernel pass, and the
negative log-likelihood (NLL) of a model with its derivatives
(:mod:`pipeline.dsp.cml.kernels.likelihood`).

Likelihood of each real measurement ``lambda = Re/Im (Gamma_model + xi)``, with the
logistic ``F(x) = 1 / (1 + exp(-x))`` of scale ``T = sigma_eff / 1.702`` (the logistic
closest to a Gaussian of std ``sigma_eff``):

* b bits (b >= 1): ``P(code) = F((hi - lambda) / T) - F((lo - lambda) / T)`` for the
  code's cell ``[lo, hi)``, the two saturated end cells open (1 bit: ``F(s lambda / T)``
  for the sign ``s``);
* unquantized (``bits=None``): least squares.

``likelihood="gaussian"`` uses the exact ``Phi((hi - lambda) / s) - Phi((lo - lambda) / s)``
instead (a stable log in both tails); measured, it is no more accurate than the logistic
under noise (README) and costs more, so the logistic is the default. Quantized frames are
held in float32: float32 resolves 1e-7 of delta, far below the finest sigma_eff (delta / M),
and halves the cost of the likelihood, which is evaluated about 20 times a frame."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from pipeline.dsp.cml.checks import NOT_FINITE, NOT_FINITE_DITHER, NOT_LEVELS, Frames
from pipeline.dsp.cml.kernels.layout import Codes, Fit
from pipeline.dsp.cml.kernels.entry import evaluate
from pipeline.dsp.cml.kernels.likelihood import GAUSSIAN, LOGISTIC, LSQ, MULTI_BIT, ONE_BIT
from pipeline.dsp.cml.kernels.stages import codes_arrays, frame_faults
from pipeline.errors import ParameterError

#: the kernels' codes of the likelihoods
LIKELIHOOD_CODES = {"logistic": LOGISTIC, "gaussian": GAUSSIAN}


def array(x, dtype) -> np.ndarray:
    """``x`` as a kernel takes it: C-contiguous, aligned and writeable, of ``dtype`` (a copy
    only if it is not one already), so that a kernel's compiled signature does not depend on
    its caller's arrays."""
    if type(x) is np.ndarray and x.dtype == dtype:
        flags = x.flags
        if flags.c_contiguous and flags.aligned and flags.writeable:  # the common case, without np.require's checks
            return x
    return np.require(x, dtype, ("C", "A", "W"))


class BlockCodes(NamedTuple):
    """A block's measurements for the kernels: ``kernel`` (the
    :data:`~pipeline.dsp.cml.kernels.layout.Codes`), ``bits`` (None: unquantized), ``ramps``,
    ``n`` (samples a ramp) and ``rm`` (the model's ramps: ``ramps`` with a phase step, 1
    static), and unquantized the frames as reals ``y`` (B, R, N, 2, 2)."""

    kernel: Codes
    bits: int | None
    ramps: int
    n: int
    rm: int
    y: np.ndarray | None = None

    @property
    def args(self) -> tuple:
        """``kernel`` as a plain tuple, as the entry kernels take it (:mod:`pipeline.dsp.cml.kernels.entry`)."""
        return tuple(self.kernel)


def model_ramps(ramps: int, motion: bool) -> int:
    """The model's ramps of frames of ``ramps`` ramps: each ramp its own with a phase step
    between ramps (``motion``), else one for all (the static model)."""
    return ramps if motion else 1


def block_codes(frames: Frames, n: int, likelihood: str, motion: bool) -> BlockCodes:
    """The kernels' arrays of checked ``frames`` of N = ``n`` samples a ramp, for the model
    with a phase step between ramps (``motion``) or the static one: quantized, built by one
    kernel pass (:func:`~pipeline.dsp.cml.kernels.stages.codes_arrays`; the quantizer's codes
    taken as they are, values turned back into codes); unquantized, the frames as they are."""
    z, bits = frames.z, frames.bits
    b, m = z.shape[:2]
    ramps = m // n
    rm = model_ramps(ramps, motion)
    shape = (b, ramps, n, 4)
    lik = LIKELIHOOD_CODES[likelihood]
    if bits is None:
        zr = array(z, complex).view(float).reshape(b, ramps, n, 2, 2)
        data = z.reshape(b, ramps, n, 2)
        data = data if rm > 1 else data.sum(axis=1, keepdims=True)  # static: Z summed over the ramps
        kernel = Codes(LSQ, lik, zr.reshape(shape), zr.reshape(shape),
                       array(np.ascontiguousarray(data, dtype=complex).view(float).reshape(b, rm, n, 4), float))
        return BlockCodes(kernel, None, ramps, n, rm, zr)
    from_codes = z.ndim == 4
    if from_codes:
        zk = array(z if z.dtype == np.uint8 else z.astype(np.int64), z.dtype if z.dtype == np.uint8 else np.int64)
        zk = zk.reshape(shape)
    else:
        zk = array(z, complex).view(float).reshape(shape)
    ka, kb = np.empty(shape, dtype=np.float32), np.empty(shape, dtype=np.float32)
    data = np.empty((b, rm, n, 4))
    codes_arrays(zk, from_codes, array(frames.xi, complex).view(float).reshape(shape), array(frames.delta, float), bits,
                 ka, kb, data)
    return BlockCodes(Codes(ONE_BIT if bits == 1 else MULTI_BIT, lik, ka, kb, data), bits, ramps, n, rm)


def check_in_kernel(z, xi, delta, bits: int, codes: bool) -> np.ndarray:
    """The finite and level checks of B quantized frames ``z`` (values (B, M, 2) complex, or
    ``codes``) and their dither ``xi`` (B, M, 2) complex in one compiled pass
    (:func:`~pipeline.dsp.cml.kernels.stages.frame_faults`); returns ``z`` (values:
    C-contiguous) or raises ParameterError."""
    b, half = z.shape[0], 1 << (bits - 1)
    z = z if codes else np.ascontiguousarray(z)
    zr = np.empty((b, 0)) if codes else array(z, complex).view(float).reshape(b, -1)
    fault = frame_faults(zr, array(xi, complex).view(float).reshape(b, -1), array(delta, float), half)
    if fault:
        raise ParameterError({1: NOT_FINITE, 2: NOT_FINITE_DITHER}.get(fault) or
                             NOT_LEVELS.format(bits=bits, lo=-half, hi=half - 1))
    return z


def evaluate_fit(codes: BlockCodes, fit: Fit, sigma: np.ndarray) -> Fit:
    """``fit`` with the NLL, its derivatives ``g``, ``h`` at its model and noise std ``sigma`` (B,)."""
    g, h = np.empty(fit.mu.shape), np.empty(fit.mu.shape)
    sigma = array(sigma, float)
    nll = evaluate(codes.args, fit.mu, sigma, g, h)
    return fit._replace(nll=nll, sigma=sigma, g=g, h=h)
