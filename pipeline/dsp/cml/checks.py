"""The checks of cml's input at its public entry: frames, their dither and step, the
targets, the noise and the warm start's ranges, each as the decoder takes it (:class:`Frames`)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from radar_driver.limits import MAX_BITS
from radar_driver.model import RadarConfig

from pipeline.dsp.cml.options import is_int
from pipeline.dsp.gate import RangeGate
from pipeline.errors import ParameterError

NOT_FINITE = "cml: Z holds values that are not finite"
NOT_FINITE_DITHER = "cml: the dither holds values that are not finite"
NOT_LEVELS = ("cml: Z is not a {bits}-bit quantized frame of step delta: its real and imaginary parts must be "
              "delta (q + 1/2) with q an integer in [{lo}, {hi}]")


class Frames(NamedTuple):
    """Checked frames: ``z`` (B, M, 2) complex or the quantizer's codes (B, M, 2, 2) integers,
    their dither ``xi`` (B, M, 2) complex (zeros without one) and step ``delta`` (B,) (both
    None unquantized), ``bits`` (None: unquantized), ``noise_sigma`` (B,) or None, and
    whether they came with a dither."""

    z: np.ndarray
    xi: np.ndarray | None
    delta: np.ndarray | None
    bits: int | None
    noise_sigma: np.ndarray | None
    dithered: bool

    def part(self, index) -> "Frames":
        """The frames at ``index`` (a slice or indices along the batch)."""
        take = lambda a: None if a is None else a[index]  # noqa: E731
        return Frames(self.z[index], take(self.xi), take(self.delta), self.bits, take(self.noise_sigma),
                      self.dithered)


_MIN, _MAX = np.minimum.reduce, np.maximum.reduce  # ndarray.min and max without their Python wrappers


def per_frame(name: str, value, b: int, positive: bool) -> np.ndarray:
    """A scalar or (B,) array of finite values > 0 (``positive``) or >= 0, as (B,) floats (the
    common case, (B,) float64, as it is, by two reductions: NaN fails both)."""
    if type(value) is np.ndarray and value.dtype == np.float64 and value.shape == (b,) and b and (
            (_MIN(value) > 0.0) if positive else (_MIN(value) >= 0.0)) and _MAX(value) < np.inf:
        return value
    try:
        v = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ParameterError(f"cml: {name}={value!r} must be a number or ({b},) numbers") from None
    bad = ~np.isfinite(v) | ((v <= 0) if positive else (v < 0))
    if v.ndim > 1 or (v.ndim == 1 and v.shape != (b,)) or np.any(bad):
        raise ParameterError(f"cml: {name} must be a finite value {'> 0' if positive else '>= 0'} or ({b},) of "
                             f"them, got shape {v.shape}" + (f", values {v[bad][:3].tolist()}" if v.ndim <= 1 and
                                                             np.any(bad) else ""))
    return np.broadcast_to(v, (b,)).astype(float)


def check_frames(z, xi, delta, bits, config: RadarConfig, k, noise_sigma, in_kernel=None) -> Frames:
    """``z``, ``xi``, ``delta``, ``bits`` (see :func:`pipeline.dsp.cml.cml`) checked against
    ``config`` (whole ramps), with ``k`` targets a frame and ``noise_sigma``. ``in_kernel``:
    the compiled engine's check of quantized values and dithers (finite, on the quantizer's
    levels) in one pass, ``in_kernel(z, xi, delta, bits, codes) -> z`` (None: numpy's)."""
    z = np.asarray(z)
    codes = z.ndim == 4 and z.dtype.kind in "iu"  # the quantizer's codes
    if codes and (z.shape[-2:] != (2, 2) or bits is None):
        raise ParameterError(f"cml: codes must have shape (B, M, 2, 2) and bits given, got {z.shape}, bits={bits!r}")
    if not codes and (z.ndim != 3 or z.shape[-1] != 2):
        raise ParameterError(f"cml: Z must have shape (B, M, 2) (or codes (B, M, 2, 2) integers), got {z.shape}")
    if z.dtype.kind not in "iufc":
        raise ParameterError(f"cml: Z must be numbers, got dtype {z.dtype}")
    b, m = z.shape[:2]
    n = config.samples_per_ramp
    if m == 0 or m % n:
        raise ParameterError(f"cml: M={m} is not a whole number of ramps of N={n} samples")
    in_kernel = in_kernel if bits is not None else None
    if not codes and in_kernel is None and not np.all(np.isfinite(z)):
        raise ParameterError(NOT_FINITE)
    if not is_int(k) or not 1 <= k <= n // 2:
        raise ParameterError(f"cml: k={k!r} must be an integer in [1, N/2 = {n // 2}]")
    if noise_sigma is not None:
        noise_sigma = per_frame("noise_sigma", noise_sigma, b, positive=False)
    z = z if codes else np.asarray(z, dtype=complex)
    if bits is None:
        return Frames(z, None, None, None, noise_sigma, False)
    return _quantized(z, xi, delta, bits, codes, noise_sigma, in_kernel)


def _quantized(z, xi, delta, bits, codes: bool, noise_sigma, in_kernel) -> Frames:
    """:func:`check_frames` of quantized frames (``codes``: the quantizer's integer codes)."""
    if not is_int(bits) or not 1 <= bits <= MAX_BITS:
        raise ParameterError(f"cml: bits={bits!r} must be None (unquantized) or an integer in [1, {MAX_BITS}]")
    dithered = xi is not None
    xi = np.zeros(z.shape[:3], dtype=complex) if xi is None else np.asarray(xi, dtype=complex)
    if xi.shape != z.shape[:3]:
        raise ParameterError(f"cml: dither shape {xi.shape} does not match Z {z.shape[:3]}")
    if in_kernel is None and not np.all(np.isfinite(xi)):
        raise ParameterError(NOT_FINITE_DITHER)
    b = z.shape[0]
    d = per_frame("delta", delta, b, positive=True)
    half = 1 << (bits - 1)
    if in_kernel is not None and b:
        z = in_kernel(z, xi, d, bits, codes)
    if codes and z.size and ((z.dtype.kind != "u" and z.min() < 0) or z.max() >= 1 << bits):  # levels: the range
        raise ParameterError(f"cml: codes must be integers in [0, {(1 << bits) - 1}] for {bits} bits, got "
                             f"[{z.min()}, {z.max()}]")
    if not (codes or in_kernel is not None):
        level = np.stack([z.real, z.imag]) / d[None, :, None, None] - 0.5  # an integer in [-2^(b-1), 2^(b-1))
        if level.size and (np.any(np.abs(level - np.rint(level)) > 1e-6) or level.min() < -half - 1e-6
                           or level.max() > half - 1 + 1e-6):
            raise ParameterError(NOT_LEVELS.format(bits=bits, lo=-half, hi=half - 1))
    return Frames(z, xi, d, bits, noise_sigma, dithered)


def check_init(init, b: int, k: int, config: RadarConfig, gate: RangeGate | None) -> np.ndarray:
    """``init_range_m`` as (B, k) floats in the range axis (inside the gate), NaN padded."""
    try:
        r = np.asarray(init, dtype=float)
    except (TypeError, ValueError):
        raise ParameterError(f"cml: init_range_m must be ({b}, J) numbers, got {init!r}") from None
    if r.ndim != 2 or r.shape[0] != b or r.shape[1] > k:
        raise ParameterError(f"cml: init_range_m must have shape ({b}, J) with J <= k={k}, got {r.shape}")
    top = config.samples_per_ramp * config.range_resolution_m
    if np.any(np.isinf(r)) or np.any((r < 0) | (r > top)):
        raise ParameterError(f"cml: init_range_m must be NaN or in [0, {top:g}] m")
    if gate is not None:
        r = np.where(np.isnan(r), np.nan, np.clip(r, gate.min_range_m, gate.max_range_m))
    return np.concatenate([r, np.full((b, k - r.shape[1]), np.nan)], axis=1)
