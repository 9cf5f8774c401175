"""cml's compiled kernels loaded ahead of the first frame: from numba's on-disk cache (``make``
compiles them at install) or compiled, by decoding a frame of each kind, the kernels of 1-bit
codes with the default likelihood first (what live sensors send)."""

from __future__ import annotations

import numpy as np

from radar_driver.model import RadarConfig

from pipeline.dsp.cml.decoder import CmlDecoder
from pipeline.dsp.cml.engine import HAVE_NUMBA
from pipeline.dsp.cml.options import DEFAULT_LIKELIHOOD, LIKELIHOODS, CmlOptions
from pipeline.dsp.gate import RangeGate

#: the kinds of frames (bits, likelihood), 1-bit codes with the default likelihood first
KINDS = ((1, DEFAULT_LIKELIHOOD),) + tuple((b, lik) for b in (1, 3, None) for lik in LIKELIHOODS
                                           if (b, lik) != (1, DEFAULT_LIKELIHOOD))


def load_kernels(common: bool = False) -> None:
    """Load (or compile) the compiled engine's kernels for every kind of frame (``common``:
    1-bit codes with the default likelihood alone): about 1.5 s from numba's cache, a first
    compile a minute or more; nothing without numba. A caller that cannot wait runs it in a
    thread of its own (a frame of a kind not loaded yet meanwhile waits for numba's lock)."""
    if not HAVE_NUMBA:
        return
    cfg = RadarConfig()
    n = cfg.samples_per_ramp
    rng = np.random.default_rng(0)
    g = 0.3 * np.exp(2j * np.pi * rng.random((1, 2 * n, 2)))
    xi = 0.25 * (rng.random(g.shape) - 0.5 + 1j * (rng.random(g.shape) - 0.5))
    gate = RangeGate(5.0, 100.0)
    for bits, lik in KINDS[:1] if common else KINDS:
        decoder = CmlDecoder(cfg, CmlOptions(engine="numba", likelihood=lik))
        delta = 1.0 if bits is None else 1.0 / (1 << (bits - 1))
        half = 0 if bits is None else 1 << (bits - 1)
        z = g if bits is None else delta * (np.clip(np.floor((g + xi).real / delta), -half, half - 1) + 0.5 + 1j * (
            np.clip(np.floor((g + xi).imag / delta), -half, half - 1) + 0.5))
        frames = [z]
        if bits is not None and lik == DEFAULT_LIKELIHOOD:  # the quantizer's codes (uint8)
            frames.append(np.rint(np.stack([z.real, z.imag], axis=-1) / delta - 0.5 + half).astype(np.uint8))
        for zz in frames:
            decoder.decode(zz, xi, delta, bits, 2)
            decoder.decode(zz, xi, delta, bits, 2, pfa=1e-3, gate=gate, init_range_m=np.array([[30.0, np.nan]]))
