"""The counter generator of the dither (:mod:`pipeline.dsp.quantize`'s module docstring
gives its definition): the frames' keys, the numpy reference :func:`counter_dither_numpy`
and :func:`counter_dither`, which runs it or the compiled kernel of
:mod:`pipeline.dsp.dither_kernels`, as its caller chooses, bit for bit the same."""

from __future__ import annotations

import numpy as np

from pipeline.errors import ParameterError

#: the counter generator's constants: SplitMix64's increment (2**64 / golden ratio) and
#: the multipliers of its finalizer (Stafford's "Mix13")
SPLITMIX_GAMMA = 0x9E3779B97F4A7C15
SPLITMIX_C1 = 0xBF58476D1CE4E5B9
SPLITMIX_C2 = 0x94D049BB133111EB
_U64 = np.uint64
_GAMMA, _C1, _C2 = _U64(SPLITMIX_GAMMA), _U64(SPLITMIX_C1), _U64(SPLITMIX_C2)
#: 64-bit words per block of the counter generator (a block stays in the CPU cache)
_BLOCK = 1 << 15
_HALVES = _U64(0x8000000080000000)


def _mix64(z: np.ndarray, tmp: np.ndarray) -> np.ndarray:
    """SplitMix64's finalizer on a uint64 array, in place (``tmp``: scratch of its shape);
    products wrap mod 2**64."""
    np.right_shift(z, _U64(30), out=tmp)
    z ^= tmp
    z *= _C1
    np.right_shift(z, _U64(27), out=tmp)
    z ^= tmp
    z *= _C2
    np.right_shift(z, _U64(31), out=tmp)
    z ^= tmp
    return z


def _counter_offsets(n_words: int) -> np.ndarray:
    """``(w + 1) G`` mod 2**64 for the words w = 0 .. n_words - 1 of a frame."""
    return (np.arange(n_words, dtype=np.uint64) + _U64(1)) * _GAMMA


def counter_keys(seeds: np.ndarray, seqs: np.ndarray) -> np.ndarray:
    """Frame keys of the counter generator, ``mix(seed ^ mix(seq + G))``: (B,) uint64."""
    key = seqs.astype(np.uint64) + _GAMMA
    tmp = np.empty_like(key)
    _mix64(key, tmp)
    key ^= seeds.astype(np.uint64, copy=False)
    return _mix64(key, tmp)


#: how :func:`counter_dither` draws: "numpy" (:func:`counter_dither_numpy`) or "numba" (one compiled
#: pass, :mod:`pipeline.dsp.dither_kernels`: importing numba costs a process ~1 s and ~100 MB, so
#: the quantizer and edge sensors draw in numpy and a decoder that runs numba anyway in numba)
DITHER_ENGINES = ("numpy", "numba")


def counter_dither(seeds: np.ndarray, seqs: np.ndarray, n_measurements: int, scale: np.ndarray | None = None,
                   engine: str = "numpy") -> np.ndarray:
    """The counter generator's dither of frames (seeds[b], seqs[b]) times ``scale`` (B,)
    float (None: the unit dither): (B, M, 2) complex, drawn by ``engine`` (one of
    :data:`DITHER_ENGINES`), bit for bit the same either way (``scale * u`` rounded once)."""
    if engine not in DITHER_ENGINES:
        raise ParameterError(f"counter_dither: engine={engine!r} is not one of {', '.join(DITHER_ENGINES)}")
    if engine == "numpy":
        u = counter_dither_numpy(seeds, seqs, n_measurements)
        return u if scale is None else scale[:, None, None] * u
    b = seqs.size
    if np.size(seeds) != b or (scale is not None and np.size(scale) != b):
        raise ParameterError(f"counter_dither: {np.size(seeds)} seeds and "
                             f"{'no' if scale is None else np.size(scale)} scales for {b} frames")
    try:
        from pipeline.dsp.dither_kernels import counter_dither_into
    except ImportError:
        raise ParameterError("counter_dither: engine 'numba' needs numba, which does not import") from None
    out = np.empty((b, 4 * n_measurements))
    # contiguous and writeable (a read-only view, e.g. np.broadcast_to, is another compiled signature)
    counter_dither_into(np.require(seeds, np.uint64, "CW").reshape(b), np.require(seqs, np.uint64, "CW").reshape(b),
                        np.ones(b) if scale is None else np.require(scale, float, "CW").reshape(b), out)
    return out.view(complex).reshape(b, n_measurements, 2)


def load_kernel() -> None:
    """Load the compiled dither from numba's on-disk cache (or compile it: about 1 s), so that
    the first frame a decoder draws in numba does not wait for it."""
    counter_dither(np.zeros(1, np.uint64), np.zeros(1, np.uint64), 1, np.ones(1), engine="numba")


def counter_dither_numpy(seeds: np.ndarray, seqs: np.ndarray, n_measurements: int) -> np.ndarray:
    """The counter generator's unit dither of frames (seeds[b], seqs[b]) in numpy: (B, M, 2) complex.

    Words ``x_w = mix(k + (w + 1) G)``, w < 2M, give the 4M 32-bit values
    ``v_2w = x_w mod 2**32``, ``v_2w+1 = x_w >> 32`` (the words' little-endian halves);
    ``u_i = v_i 2**-32 - 1/2``: real parts u_0 .. u_2M-1, imaginary parts u_2M .. u_4M-1."""
    keys = counter_keys(seeds, seqs)
    n = 2 * n_measurements  # words per frame = entries of the (M, 2) array
    offsets = _counter_offsets(n)
    out = np.empty((keys.size, 2 * n), dtype=float)  # Re, Im interleaved: a complex (B, M, 2)
    rows = max(1, _BLOCK // max(n, 1))
    z = np.empty((min(rows, keys.size), n), dtype=np.uint64)
    tmp = np.empty_like(z)
    for start in range(0, keys.size, rows):  # blocks of frames, not one frame at a time
        k = keys[start:start + rows]
        zz, tt, oo = z[:k.size], tmp[:k.size], out[start:start + rows]
        np.add(k[:, None], offsets, out=zz)
        _mix64(zz, tt)
        zz ^= _HALVES  # v_i - 2**31 as int32: (v_i - 2**31) 2**-32 = u_i, exactly
        v = zz.view("<i4")  # (rows, 4M) 32-bit values
        np.multiply(v[:, :n], 2.0**-32, out=oo[:, 0::2])
        np.multiply(v[:, n:], 2.0**-32, out=oo[:, 1::2])
    return out.view(complex).reshape(keys.size, n_measurements, 2)


