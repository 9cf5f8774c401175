"""The counter generator's dither (:mod:`pipeline.dsp.quantize`) as one compiled (numba)
kernel: a frame's 2M SplitMix64 words hashed, split into their 32-bit halves and scaled in
one pass, with no (B, 2M) uint64 temporaries. The numpy code of
:func:`pipeline.dsp.dither.counter_dither_numpy` is the reference this kernel is tested
against, bit for bit (tests/test_quantize_kernels.py). Its constants are repeated here, not
imported: numba's on-disk cache is keyed on this file alone.

Compiled on first use and cached on disk (``cache=True``: ``__pycache__`` beside this
file, or ``NUMBA_CACHE_DIR``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

_U64 = np.uint64
_GAMMA = _U64(0x9E3779B97F4A7C15)
_C1 = _U64(0xBF58476D1CE4E5B9)
_C2 = _U64(0x94D049BB133111EB)
_LOW = _U64(0xFFFFFFFF)
#: flips the top bit of each 32-bit half: v becomes v - 2**31 read as an int32
_HALVES = _U64(0x8000000080000000)
#: u = (v - 2**31) 2**-32 in [-1/2, 1/2), exactly
_SCALE = 2.0**-32


@njit(cache=True, nogil=True, error_model="numpy")
def _mix(z):
    """SplitMix64's finalizer of one uint64 (products wrap mod 2**64)."""
    z = (z ^ (z >> _U64(30))) * _C1
    z = (z ^ (z >> _U64(27))) * _C2
    return z ^ (z >> _U64(31))


@njit(cache=True, nogil=True, error_model="numpy")
def counter_dither_into(seeds, seqs, scale, out):
    """The counter generator's dither of frames (seeds[b], seqs[b]) ((B,) uint64 each),
    times ``scale`` (B,) float64 (alpha delta, or 1 for the unit dither), into ``out``
    (B, 4M) float64: the (B, M, 2) complex array's real and imaginary parts interleaved.
    Frame b's key is ``k_b = mix(seed ^ mix(seq + G))``
    (:func:`pipeline.dsp.dither.counter_keys`), its word w < 2M ``x_w = mix(k_b + (w + 1) G)``;
    its low then high 32-bit halves are the values 2w and 2w + 1; value i < 2M is the real
    part of entry i, value 2M + i its imaginary part. So words w and M + w give entries 2w
    and 2w + 1, four consecutive floats (AVX2: 4 words a step). ``u = (v - 2**31) 2**-32`` is exact and ``scale * u`` rounded once, as numpy's."""
    half = out.shape[1] // 4  # = M
    for b in range(seqs.shape[0]):
        s = scale[b] * _SCALE  # scale times a power of two: exact (scale is a normal float)
        row = out[b]
        z0 = _mix(seeds[b] ^ _mix(seqs[b] + _GAMMA))
        for w in range(half):
            re = _mix(z0 + _U64(w + 1) * _GAMMA) ^ _HALVES  # each half: v - 2**31 as an int32
            im = _mix(z0 + _U64(w + 1 + half) * _GAMMA) ^ _HALVES
            row[4 * w] = s * np.float64(np.int32(re & _LOW))
            row[4 * w + 1] = s * np.float64(np.int32(im & _LOW))
            row[4 * w + 2] = s * np.float64(np.int32(re >> _U64(32)))
            row[4 * w + 3] = s * np.float64(np.int32(im >> _U64(32)))
