"""Dithered uniform quantization of radar frames (paper Sec. 3, Sec. 6) and code packing.

``Q(lambda) = delta * floor(lambda / delta) + delta / 2`` applied to the real and the
imaginary part separately, after adding a dither ``xi = alpha * delta * u`` with
``u ~ U[-1/2, 1/2) + i U[-1/2, 1/2)`` i.i.d. per measurement, antenna and I/Q.

A b-bit quantizer keeps the 2**b levels ``delta * (q + 1/2)``, ``q`` in
``[-2**(b-1), 2**(b-1) - 1]``, saturating outside; b = 1 gives +-delta/2. Codes are the
unsigned level numbers ``q + 2**(b-1)`` in ``[0, 2**b)``.

Shapes: frames are (B, M, 2) complex (batch, measurement, antenna); codes are
(B, M, 2, 2) unsigned integers (batch, measurement, antenna, I/Q); ``delta`` is a
scalar or (B,). The dither of a frame is reproducible from ``(dither_seed, seq)``,
independent of delta and alpha, so a decoder that knows the seed, the sequence number,
delta, alpha and the generator regenerates xi exactly. Two generators draw ``u`` (the
wire format's version says which, docs/wire-formats.md):

* ``"counter"`` (:data:`DITHER_COUNTER`, the default, wire version 2): counter-based
  SplitMix64, vectorized over frames in uint64 arithmetic (mod 2**64). With
  ``mix(z)``: ``z ^= z >> 30; z *= 0xBF58476D1CE4E5B9; z ^= z >> 27;
  z *= 0x94D049BB133111EB; z ^= z >> 31`` and ``G = 0x9E3779B97F4A7C15``, frame
  ``(seed, seq)`` has the key ``k = mix(seed ^ mix(seq + G))`` and the 2M words
  ``x_w = mix(k + (w + 1) G)``, ``w = 0 .. 2M - 1`` (the SplitMix64 stream from state
  ``k``); each word gives two 32-bit values, its low half ``v_2w = x_w mod 2**32`` then
  its high half ``v_2w+1 = x_w >> 32``, and ``u_i = v_i * 2**-32 - 1/2``,
  ``i = 0 .. 4M - 1`` (compiled, :mod:`pipeline.dsp.dither`: ~2 us a frame of M = 512, ~7 us a
  batch of one; its numpy reference ~9 us a frame in batches of 16).
* ``"seedseq"`` (:data:`DITHER_SEEDSEQ`, wire version 1, every recording made before
  the counter generator): ``numpy.random.default_rng(SeedSequence(dither_seed,
  spawn_key=(seq,))).random(4M) - 1/2``, one generator per frame (~30 us a frame).

Both lay the 4M values out alike: the real parts of the (M, 2) array first, then the
imaginary parts, each in C order.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, replace
from functools import partial
from typing import Literal, Sequence

import numpy as np

from radar_driver.limits import MAX_BITS
from radar_driver.limits import check_bits as _check_bits

from pipeline.defaults import DEFAULT_ALPHA
from pipeline.errors import ParameterError
from pipeline.dsp.noise import auto_alpha
from pipeline.dsp.dither import SPLITMIX_C1, SPLITMIX_C2, SPLITMIX_GAMMA, counter_dither, counter_keys  # noqa: F401

DITHER_SEEDSEQ = "seedseq"
DITHER_COUNTER = "counter"
DITHER_GENERATORS = (DITHER_SEEDSEQ, DITHER_COUNTER)


# -- parameter checks ---------------------------------------------------------------
def check_bits(bits: int) -> int:
    """``bits`` as an int in [1, MAX_BITS] (radar_driver.limits), else a ParameterError."""
    return _check_bits(bits, ParameterError)


#: the largest quantizer step a quantized frame may carry, in full-scale units: a sensor's
#: frames lie within +-1 a part (12-bit ADC), a simulated scene's within its summed
#: amplitudes, so 1-bit steps stay far below; beyond is a forged or corrupt frame
MAX_DELTA = 1000.0


#: ``alpha="auto"``: the dither scale from the noise the quantizer estimates in each
#: sensor's frames (:func:`pipeline.dsp.noise.auto_alpha`)
AUTO_ALPHA = "auto"


def parse_alpha(text: str) -> float | str:
    """A command line's ``--alpha``: ``auto`` or a number in [0, 1]."""
    if text.strip().lower() == AUTO_ALPHA:
        return AUTO_ALPHA
    try:
        value = float(text)
    except ValueError:
        raise ParameterError(f"alpha={text!r} must be 'auto' or a number in [0, 1]") from None
    if not 0.0 <= value <= 1.0:
        raise ParameterError(f"alpha={text!r} must be 'auto' or a number in [0, 1]")
    return value


def check_alpha(alpha: float) -> float:
    if not (isinstance(alpha, (int, float, np.floating)) and 0.0 <= float(alpha) <= 1.0):
        raise ParameterError(f"alpha={alpha!r} must be a number in [0, 1]")
    return float(alpha)


def check_delta(delta, batch: int | None = None) -> np.ndarray:
    """delta as a float array of shape () or (B,); every value finite and > 0."""
    d = np.asarray(delta, dtype=float)
    if d.ndim > 1 or (d.ndim == 1 and batch is not None and d.shape[0] != batch):
        raise ParameterError(f"delta must be a scalar or of shape ({batch},), got shape {d.shape}")
    if not np.all(np.isfinite(d)) or np.any(d <= 0):
        bad = d[~(np.isfinite(d) & (d > 0))] if d.ndim else d
        raise ParameterError(f"delta must be finite and > 0, got {np.ravel(bad)[:4].tolist()}")
    return d


def check_frames(frames: np.ndarray, name: str = "frames") -> np.ndarray:
    """frames as a complex (B, M, 2) array; a single (M, 2) frame is not accepted here."""
    f = np.asarray(frames)
    if f.ndim != 3 or f.shape[-1] != 2:
        raise ParameterError(f"{name} must have shape (B, M, 2), got {f.shape}")
    if not np.iscomplexobj(f):
        f = f.astype(complex)
    return f


def as_int_array(values) -> np.ndarray:
    """``values`` as an array, lists and tuples as Python objects (numpy would turn a list
    mixing ints beyond int64 with others into floats)."""
    return np.array(values, dtype=object) if isinstance(values, (list, tuple)) else np.asarray(values)


def check_uint64(values, name: str) -> np.ndarray:
    """An int or a 1-D sequence of ints as a (B,) uint64 array; each must be in
    [0, 2**64), the wire format's range."""
    a = as_int_array(values)
    if a.ndim > 1:
        ok = False
    elif np.issubdtype(a.dtype, np.signedinteger):
        ok = not a.size or a.min() >= 0
    elif a.dtype == object:  # Python ints beyond int64
        ok = all(isinstance(x, (int, np.integer)) and not isinstance(x, bool) and 0 <= x < 2**64
                 for x in a.ravel())
    else:
        ok = np.issubdtype(a.dtype, np.unsignedinteger)
    if not ok:
        raise ParameterError(f"{name} must be integers in [0, 2**64), one or a 1-D array of them, "
                             f"got {np.ravel(a)[:4].tolist()} of shape {a.shape}")
    return np.atleast_1d(a.astype(np.uint64))


def check_seq(seq) -> np.ndarray:
    """Sequence numbers (an int or a 1-D sequence of them) as a (B,) uint64 array."""
    return check_uint64(seq, "seq")


def check_generator(generator, batch: int | None = None) -> str | np.ndarray:
    """A dither generator name, or one per frame ((B,) array of names)."""
    if isinstance(generator, str):
        ok = generator in DITHER_GENERATORS
    else:
        generator = np.asarray(generator, dtype=object)
        ok = generator.ndim == 1 and (batch is None or generator.shape == (batch,)) and all(
            isinstance(g, str) and g in DITHER_GENERATORS for g in set(generator.tolist()))
    if not ok:
        raise ParameterError(f"generator={generator!r} must be one of {DITHER_GENERATORS}, "
                             f"or one per frame ({batch})")
    return generator


def _per_frame(delta: np.ndarray, ndim: int) -> np.ndarray:
    """Reshape a () or (B,) delta to broadcast against an array of ``ndim`` dims."""
    return delta.reshape(delta.shape + (1,) * (ndim - delta.ndim)) if delta.ndim else delta


# -- the quantizer --------------------------------------------------------------------
def quantize_real(lam: np.ndarray, delta) -> np.ndarray:
    """The paper's Q(lambda) = delta floor(lambda / delta) + delta / 2 (unbounded), real."""
    d = np.asarray(delta, dtype=float)
    return d * np.floor(lam / d) + d / 2.0


def auto_delta(frames: np.ndarray, margin: float = 0.0, bits: int = 1) -> np.ndarray:
    """Smallest step per frame whose ``2^bits`` levels hold the frame and a dither of up to
    one step, ``2 max(|Re Gamma|, |Im Gamma|) (1 + margin) / (2^bits - 1)``: one bit, the
    paper's ``2 max`` (the levels' half-width ``2^(bits-1) delta`` is the peak plus half a
    step; the same ``delta`` at more bits left all but the middle two levels unused).

    ``frames``: (B, M, 2). Returns (B,). An all-zero frame gets the smallest positive
    float (its codes then carry only the dither).
    """
    f = check_frames(frames)
    if not (np.isfinite(margin) and margin >= 0):
        raise ParameterError(f"margin={margin!r} must be finite and >= 0")
    return _auto_delta(f, margin, check_bits(bits))


def _auto_delta(f: np.ndarray, margin: float, bits: int) -> np.ndarray:
    """:func:`auto_delta` of checked arguments (a configured quantizer's: checked once, at its edge)."""
    return np.maximum(2.0 * frame_peak(f) * (1.0 + margin) / ((1 << bits) - 1), np.finfo(float).tiny)


def frame_peak(f: np.ndarray) -> np.ndarray:
    """The largest real or imaginary part of each frame of ``f`` (B, ...) complex: (B,)."""
    f = np.asarray(f)
    axes = tuple(range(1, f.ndim))
    return np.maximum(np.abs(f.real).max(axis=axes), np.abs(f.imag).max(axis=axes))


def quantize(frames: np.ndarray, delta, bits: int, dither: np.ndarray | None = None) -> np.ndarray:
    """b-bit codes of ``frames + dither``.

    frames, dither : (B, M, 2) complex (dither in the same units as frames, or None).
    delta : scalar or (B,). Returns (B, M, 2, 2) codes, uint8 (uint16 for bits > 8).
    """
    bits = check_bits(bits)
    f = check_frames(frames)
    d = check_delta(delta, f.shape[0])
    if dither is not None:
        dither = np.asarray(dither)
        if dither.shape != f.shape:
            raise ParameterError(f"dither shape {dither.shape} does not match frames shape {f.shape}")
    return _quantize(f, d, bits, dither)


def _quantize(f: np.ndarray, d: np.ndarray, bits: int, dither: np.ndarray | None) -> np.ndarray:
    """:func:`quantize` of checked arguments: ``f`` (B, M, 2) complex, ``d`` () or (B,)."""
    # the one complex128 copy of the frames (none when they are complex128 and not dithered)
    c = np.ascontiguousarray(f, dtype=np.complex128) if dither is None else np.add(f, dither, dtype=np.complex128)
    lam = c.view(np.float64).reshape(f.shape + (2,))  # (B, M, 2, 2)
    scaled = np.divide(lam, _per_frame(d, 4), out=None if np.may_share_memory(c, f) else lam)  # frames kept
    if bits == 1:  # floor(x) clipped to [-1, 0], plus 1: 1 exactly where x >= 0 (-0.0 included)
        return np.greater_equal(scaled, 0.0).view(np.uint8)
    half = 1 << (bits - 1)
    q = np.floor(scaled, out=scaled)
    np.clip(q, -half, half - 1, out=q)
    q += half
    return q.astype(np.uint8 if bits <= 8 else np.uint16)


def dequantize(codes: np.ndarray, delta, bits: int) -> np.ndarray:
    """Complex quantized values Z from (B, M, 2, 2) codes: ``delta (code - 2**(b-1) + 1/2)``.

    Returns (B, M, 2) complex128.
    """
    bits = check_bits(bits)
    c = np.asarray(codes)
    if c.ndim != 4 or c.shape[-2:] != (2, 2):
        raise ParameterError(f"codes must have shape (B, M, 2, 2), got {c.shape}")
    if c.size and int(c.max()) >= (1 << bits):
        raise ParameterError(f"codes hold {int(c.max())}, beyond the {1 << bits} levels of {bits} bits")
    return _dequantize(c, check_delta(delta, c.shape[0]), bits)


def _dequantize(c: np.ndarray, d: np.ndarray, bits: int) -> np.ndarray:
    """:func:`dequantize` of checked arguments (codes within 2**bits, ``d`` () or (B,))."""
    v = np.subtract(c, (1 << (bits - 1)) - 0.5, dtype=np.float64)  # (B, M, 2, 2): code - 2**(b-1) + 1/2, exact
    v *= _per_frame(d, 4)
    return v.view(np.complex128).reshape(c.shape[:3])


# -- the dither -------------------------------------------------------------------------
def _seedseq_dither(seeds: np.ndarray, seqs: np.ndarray, n_measurements: int) -> np.ndarray:
    """The SeedSequence generator's unit dither (one numpy generator per frame)."""
    out = np.empty((seqs.size, n_measurements, 2), dtype=complex)
    for i, (seed, s) in enumerate(zip(seeds.tolist(), seqs.tolist())):
        rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(int(s),)))
        u = rng.random((2, n_measurements, 2)) - 0.5
        out[i] = u[0] + 1j * u[1]
    return out


def unit_dither(dither_seed, seq, n_measurements: int, generator=DITHER_COUNTER, engine: str = "numpy") -> np.ndarray:
    """Unit dither ``u`` of frames ``seq`` (int or (B,) ints in [0, 2**64)): (B, M, 2)
    complex, Re and Im i.i.d. U[-1/2, 1/2), real parts of all M x 2 entries drawn first,
    then imaginary parts. ``dither_seed``: one seed, or one per frame ((B,) uint64, for a
    batch of several sensors). ``generator``: :data:`DITHER_COUNTER` (vectorized),
    :data:`DITHER_SEEDSEQ` (``SeedSequence(dither_seed, spawn_key=(seq,))`` per frame), or
    one per frame ((B,) array of names). See the module docstring for both. ``engine``: how
    the counter generator draws (:data:`pipeline.dsp.dither.DITHER_ENGINES`; the same bits)."""
    seqs = check_seq(seq)
    seeds = check_uint64(dither_seed, "dither_seed")
    if seeds.size != seqs.size:
        if seeds.size != 1:
            raise ParameterError(f"dither_seed has {seeds.size} values, expected 1 or one per frame ({seqs.size})")
        seeds = np.broadcast_to(seeds, seqs.shape)
    if isinstance(n_measurements, bool) or not isinstance(n_measurements, (int, np.integer)) or n_measurements < 0:
        raise ParameterError(f"n_measurements={n_measurements!r} must be an integer >= 0")
    generator = check_generator(generator, seqs.size)
    counter = partial(counter_dither, engine=engine)
    if isinstance(generator, str):
        gen = counter if generator == DITHER_COUNTER else _seedseq_dither
        return gen(seeds, seqs, int(n_measurements))
    out = np.empty((seqs.size, int(n_measurements), 2), dtype=complex)
    for name, gen in ((DITHER_COUNTER, counter), (DITHER_SEEDSEQ, _seedseq_dither)):
        mask = generator == name
        if mask.any():
            out[mask] = gen(seeds[mask], seqs[mask], int(n_measurements))
    return out


def sensor_dither_seed(seed: int, sensor_id: str) -> int:
    """Dither seed of one sensor: ``seed * 2**32 + crc32(sensor_id)`` (mod 2**64), so that
    sensors with the same frame numbers get independent dithers. Every quantizer of a
    sensor's frames (the quantize node, offline re-processing) uses this rule."""
    return (int(seed) * 2**32 + zlib.crc32(sensor_id.encode())) % 2**64


def sensor_dither_seeds(seed: int, sensor_ids: Sequence[str]) -> np.ndarray:
    """:func:`sensor_dither_seed` of each of ``sensor_ids``: (B,) uint64 (one crc32 per
    distinct id)."""
    crc = {s: zlib.crc32(s.encode()) for s in set(sensor_ids)}
    low = np.fromiter((crc[s] for s in sensor_ids), dtype=np.uint64, count=len(sensor_ids))
    return low | np.uint64(int(seed) * 2**32 % 2**64)


def batch_unit_dither(shape: tuple[int, ...], rng: np.random.Generator, scale=None) -> np.ndarray:
    """Unit dither for a Monte Carlo batch from one generator: complex array of ``shape``,
    times ``scale`` (real, broadcast to ``shape``; None: 1) in place (no second complex array)."""
    shape = tuple(shape)
    u = rng.random((2,) + shape)  # the real parts, then the imaginary ones
    out = np.empty(shape, dtype=complex)
    parts = out.view(np.float64).reshape(shape + (2,))
    np.subtract(u[0], 0.5, out=parts[..., 0])
    np.subtract(u[1], 0.5, out=parts[..., 1])
    if scale is not None:
        parts *= np.asarray(scale, dtype=float)[..., None]
    return out


# -- packing ----------------------------------------------------------------------------
def packed_size(n_codes: int, bits: int) -> int:
    """Bytes holding ``n_codes`` codes of ``bits`` bits: ceil(n_codes * bits / 8)."""
    return (n_codes * check_bits(bits) + 7) // 8


def pack_codes(codes: np.ndarray, bits: int) -> np.ndarray:
    """Pack codes of ``bits`` bits, most significant bit first, into bytes.

    ``codes``: (B, ...) unsigned; each frame's codes are taken in C order.
    Returns (B, ceil(L * bits / 8)) uint8 with L codes per frame; trailing pad bits are 0.
    """
    bits = check_bits(bits)
    c = np.asarray(codes)
    if c.ndim < 1:
        raise ParameterError("codes must have a batch axis")
    if not np.issubdtype(c.dtype, np.integer):
        raise ParameterError(f"codes must be integers, got dtype {c.dtype}")
    return pack_codes_unchecked(c, bits)


def pack_codes_unchecked(codes: np.ndarray, bits: int) -> np.ndarray:
    """:func:`pack_codes` for a caller that checked ``bits`` and the codes' shape and
    dtype (the wire encoder); the codes' range is still checked (one pass)."""
    flat = codes.reshape(codes.shape[0], -1)
    if flat.size and (flat.min() < 0 or int(flat.max()) >= (1 << bits)):
        raise ParameterError(f"codes must lie in [0, {1 << bits}) for bits={bits}")
    if bits == 1:
        return np.packbits(flat.astype(np.uint8, copy=False), axis=1)
    shifts = np.arange(bits - 1, -1, -1, dtype=np.uint32)
    bitplanes = ((flat.astype(np.uint32)[..., None] >> shifts) & 1).astype(np.uint8)
    return np.packbits(bitplanes.reshape(flat.shape[0], -1), axis=1)


def unpack_codes(packed: np.ndarray, bits: int, n_codes: int) -> np.ndarray:
    """Inverse of :func:`pack_codes`: (B, nbytes) uint8 -> (B, n_codes) codes."""
    bits = check_bits(bits)
    p = np.asarray(packed)
    if p.ndim != 2 or p.dtype != np.uint8:
        raise ParameterError(f"packed must be a (B, nbytes) uint8 array, got {p.shape} {p.dtype}")
    need = packed_size(n_codes, bits)
    if p.shape[1] != need:
        raise ParameterError(f"{n_codes} codes of {bits} bits need {need} bytes, got {p.shape[1]}")
    return unpack_codes_unchecked(p, bits, n_codes)


def unpack_codes_unchecked(packed: np.ndarray, bits: int, n_codes: int) -> np.ndarray:
    """:func:`unpack_codes` for a caller that checked ``bits`` and the length (the wire
    decoder, which checked the frame's header and size)."""
    planes = np.unpackbits(packed, axis=1, count=n_codes * bits)
    if bits == 1:
        return planes
    weights = (1 << np.arange(bits - 1, -1, -1)).astype(np.uint32)
    codes = planes.reshape(packed.shape[0], n_codes, bits).astype(np.uint32) @ weights
    return codes.astype(np.uint8 if bits <= 8 else np.uint16)


# -- the configured quantizer -------------------------------------------------------------
@dataclass(frozen=True)
class QuantizerConfig:
    """A dithered b-bit quantizer.

    bits : bits per real value (1 = the paper's 1-bit scheme).
    alpha : dither scale in [0, 1] (0 = no dither, 1 = the paper's full dither), or
        ``"auto"`` (:data:`AUTO_ALPHA`: per frame from the sensor's noise,
        :func:`pipeline.dsp.noise.auto_alpha`); default :data:`pipeline.defaults.DEFAULT_ALPHA`.
    delta : quantizer step (same units as the frames) or ``"auto"`` = the smallest step of
        each frame at ``bits`` (:func:`auto_delta`) times ``1 + delta_margin``.
    dither_seed : seed from which, with the frame sequence number, the dither is drawn.
    """

    bits: int = 1
    alpha: float | Literal["auto"] = DEFAULT_ALPHA
    delta: float | Literal["auto"] = "auto"
    delta_margin: float = 0.0
    dither_seed: int = 0

    def __post_init__(self) -> None:
        check_bits(self.bits)
        if self.alpha != AUTO_ALPHA:
            if isinstance(self.alpha, str):
                raise ParameterError(f"alpha={self.alpha!r} must be 'auto' or a number in [0, 1]")
            check_alpha(self.alpha)
        if self.delta != "auto":
            if isinstance(self.delta, str):
                raise ParameterError(f"delta={self.delta!r} must be 'auto' or a number > 0")
            check_delta(self.delta)
            if self.delta > MAX_DELTA:
                raise ParameterError(f"delta={self.delta!r} must be at most {MAX_DELTA:g} (full-scale units)")
        if not (np.isfinite(self.delta_margin) and self.delta_margin >= 0):
            raise ParameterError(f"delta_margin={self.delta_margin!r} must be finite and >= 0")
        if isinstance(self.dither_seed, bool) or not isinstance(self.dither_seed, int) or self.dither_seed < 0:
            raise ParameterError(f"dither_seed={self.dither_seed!r} must be an integer >= 0")


@dataclass(frozen=True)
class QuantizedFrames:
    """Quantizer output for a batch: codes (B, M, 2, 2), delta (B,), and what a decoder
    needs to regenerate the dither (alpha, dither_seed, seq (B,), generator). ``alpha``,
    ``dither_seed`` and ``generator`` are one value for the batch or one per frame (B,)."""

    codes: np.ndarray
    delta: np.ndarray
    bits: int
    alpha: float | np.ndarray
    dither_seed: int | np.ndarray
    seq: np.ndarray
    generator: str | np.ndarray = DITHER_COUNTER

    def values(self) -> np.ndarray:
        """Z, the quantized complex values, (B, M, 2) complex128 (the batch was checked
        where it was made: by the quantizer or the wire decoder)."""
        return _dequantize(np.asarray(self.codes), np.asarray(self.delta, dtype=float), self.bits)

    def take(self, index) -> "QuantizedFrames":
        """The frames ``index`` of the batch (an int index array): per-frame fields are
        subset, per-batch ones (a scalar alpha, seed or generator) kept."""
        def sub(v):
            return v[index] if np.ndim(v) else v
        return replace(self, codes=self.codes[index], delta=self.delta[index], alpha=sub(self.alpha),
                       dither_seed=sub(self.dither_seed), seq=self.seq[index], generator=sub(self.generator))

    def ramp_mean(self, n: int) -> np.ndarray:
        """The mean of Z over the frame's ramps of ``n`` measurements (M = R n), (B, n, 2)
        complex: the codes are summed over the ramps as integers first, so only n x 2
        values per frame are made (what back projection on whole ramps needs)."""
        b, m = self.codes.shape[:2]
        if m % n:
            raise ParameterError(f"M={m} is not a whole number of ramps of {n}")
        r = m // n
        ramps = np.asarray(self.codes).reshape(b, r, n, 2, 2)
        small = ramps.dtype in (np.uint8, np.bool_) and r * 255 < 1 << 16  # uint16 sums then exact, any codes
        total = ramps[:, 0].astype(np.uint16 if small else np.int64)
        for j in range(1, r):  # ramps, not frames: one add over the batch each
            np.add(total, ramps[:, j], out=total, casting="unsafe")
        total = np.ascontiguousarray(total, dtype=np.float64)  # (B, n, 2, 2)
        total *= 1.0 / r
        total -= (1 << (self.bits - 1)) - 0.5
        total *= _per_frame(check_delta(self.delta, b), 4)
        return total.view(np.complex128).reshape(b, n, 2)

    @property
    def dithered(self) -> bool:
        """True when every frame is dithered (alpha > 0); a decoder can then regenerate xi."""
        alpha = self.alpha
        return alpha > 0 if isinstance(alpha, float) else bool(np.all(np.asarray(alpha) > 0))

    def dither(self, engine: str = "numpy") -> np.ndarray | None:
        """The dither xi added before quantization, regenerated from the seeds: (B, M, 2);
        None when the frames are not all dithered (there is no dither to use). ``engine``:
        how the counter generator draws (:data:`pipeline.dsp.dither.DITHER_ENGINES`; the same
        bits; "numba" where the process runs numba anyway, a decoder)."""
        if not self.dithered:
            return None
        seed, seq, gen = self.dither_seed, self.seq, self.generator
        if isinstance(gen, np.ndarray) and gen.size and (gen == gen.flat[0]).all():
            gen = str(gen.flat[0])  # one name for the batch: one call, no per-generator masks
        scale = np.asarray(self.alpha, dtype=float) * self.delta  # (B,): alpha one for the batch, or (B,)
        seeds = None
        if isinstance(gen, str) and gen == DITHER_COUNTER and isinstance(seq, np.ndarray) \
                and seq.dtype == np.uint64 and seq.ndim == 1:  # what unit_dither does, without its checks
            if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool) and 0 <= seed < 2**64:
                seeds = np.full(seq.shape, seed, dtype=np.uint64)
            elif isinstance(seed, np.ndarray) and seed.dtype == np.uint64 and seed.shape == seq.shape:
                seeds = seed
        if seeds is not None and scale.shape == seq.shape:
            return counter_dither(seeds, seq, self.codes.shape[1], scale, engine)  # scaled in the same pass
        return scale[:, None, None] * unit_dither(seed, seq, self.codes.shape[1], gen, engine)


def quantize_frames(frames: np.ndarray, config: QuantizerConfig, seq, dither_seed=None,
                    generator=DITHER_COUNTER, noise_sigma=None) -> QuantizedFrames:
    """Dither and quantize frames (B, M, 2) with sequence numbers ``seq`` ((B,) or int).

    ``noise_sigma``: the sensor noise of each frame (scalar or (B,), std of I and of Q,
    frame units), which ``config.alpha == "auto"`` needs: alpha is then
    :func:`pipeline.dsp.noise.auto_alpha` of it and of each frame's delta, one per frame.

    delta and alpha are rounded to float32 first, as the wire format carries them, so a
    decoder regenerates exactly the dither used here. ``dither_seed`` overrides the
    config's: one int, or one per frame ((B,) uint64: a batch of several sensors, see
    :func:`sensor_dither_seeds`). ``generator``: the dither generator (see
    :func:`unit_dither`)."""
    f = check_frames(frames)
    seqs = check_seq(seq)
    if seqs.shape != (f.shape[0],):
        raise ParameterError(f"seq has shape {seqs.shape}, expected ({f.shape[0]},) for {f.shape[0]} frames")
    generator = check_generator(generator, f.shape[0])
    seed = config.dither_seed if dither_seed is None else dither_seed
    if np.ndim(seed):
        seed = check_uint64(seed, "dither_seed")
        if seed.shape != seqs.shape:
            raise ParameterError(f"dither_seed has shape {seed.shape}, expected () or ({f.shape[0]},)")
    else:
        seed = int(check_uint64(seed, "dither_seed")[0])
    if config.delta == "auto":
        delta = _auto_delta(f, config.delta_margin, config.bits)
    else:
        delta = np.full(f.shape[0], float(config.delta))
    delta = np.maximum(delta.astype(np.float32), np.finfo(np.float32).tiny).astype(float)
    if config.alpha == AUTO_ALPHA:
        if noise_sigma is None:
            raise ParameterError("alpha 'auto' needs the frames' noise_sigma (pipeline.dsp.noise.NoiseTracker)")
        alpha = auto_alpha(np.broadcast_to(np.asarray(noise_sigma, dtype=float), delta.shape), delta)
        alpha = alpha.astype(np.float32).astype(float)
        dithered = bool(np.any(alpha > 0))
    else:
        alpha = float(np.float32(config.alpha))
        dithered = alpha > 0
    dither = None
    if dithered and isinstance(generator, str) and generator == DITHER_COUNTER:  # scaled as it is drawn
        seeds = np.broadcast_to(np.asarray(seed, dtype=np.uint64), seqs.shape)
        dither = counter_dither(seeds, seqs, f.shape[1], np.broadcast_to(alpha * delta, seqs.shape))
    elif dithered:
        dither = unit_dither(seed, seqs, f.shape[1], generator)
        dither *= (alpha * delta)[:, None, None]
    codes = _quantize(f, delta, config.bits, dither)  # bits checked by the config, delta made here
    return QuantizedFrames(codes, delta, config.bits, alpha, seed, seqs, generator)
