"""Loading :func:`pipeline.dsp.cml.cml`'s compiled kernels ahead of the first frame: from numba's
on-disk cache (``make`` compiles them at install) or compiled, in a daemon thread, the
kernels of 1-bit codes with the default likelihood first (what live sensors send)."""

from __future__ import annotations

import threading

import numpy as np

from radar_driver.model import RadarConfig

from pipeline.dsp.cml_fit import DEFAULT_LIKELIHOOD, HAVE_NUMBA, LIKELIHOODS
from pipeline.dsp.gate import RangeGate

_ready = threading.Event()  # every kind of frame
_common_ready = threading.Event()  # 1-bit codes, the default likelihood: what live sensors send
_warming_lock = threading.Lock()
_warming: list[threading.Thread] = []


def kernels_ready(common: bool = False) -> bool:
    """Whether :func:`warm_up_kernels` has compiled (or loaded from numba's cache) the kernels
    (``common``: those of 1-bit codes with the default likelihood)."""
    return HAVE_NUMBA and (_common_ready if common else _ready).is_set()


def warm_up_kernels(decoder, wait: bool | str = False) -> None:
    """Compile ``decoder``'s (:func:`pipeline.dsp.cml.cml`) kernels for every kind of frame (or
    load them from numba's on-disk cache: about 1.5 s; a first compile takes a minute or more),
    in a daemon thread started once, the
    kernels of 1-bit codes with the default likelihood first; ``wait``: True until all are
    done, ``"common"`` until those first ones are (the others go on loading: a frame of
    another kind decoded meanwhile waits for numba's lock, with the same engine)."""
    if not HAVE_NUMBA:
        return
    with _warming_lock:
        if not _warming:
            _warming.append(threading.Thread(target=_compile_all, args=(decoder,), name="cml-jit", daemon=True))
            _warming[0].start()
    if wait == "common":
        while not _common_ready.wait(0.05) and _warming[0].is_alive():
            pass
    elif wait:
        _warming[0].join()


def _compile_all(cml) -> None:
    """Decode a frame of each kind with ``cml`` (:func:`pipeline.dsp.cml.cml`, passed in: it
    imports this module)."""
    cfg = RadarConfig()
    n = cfg.samples_per_ramp
    rng = np.random.default_rng(0)
    g = 0.3 * np.exp(2j * np.pi * rng.random((1, 2 * n, 2)))
    xi = 0.25 * (rng.random(g.shape) - 0.5 + 1j * (rng.random(g.shape) - 0.5))
    gate = RangeGate(5.0, 100.0)
    kinds = [(1, DEFAULT_LIKELIHOOD)] + [(b, lik) for b in (1, 3, None) for lik in LIKELIHOODS
                                         if (b, lik) != (1, DEFAULT_LIKELIHOOD)]
    for bits, lik in kinds:
        delta = 1.0 if bits is None else 1.0 / (1 << (bits - 1))
        half = 0 if bits is None else 1 << (bits - 1)
        z = g if bits is None else delta * (np.clip(np.floor((g + xi).real / delta), -half, half - 1) + 0.5 + 1j * (
            np.clip(np.floor((g + xi).imag / delta), -half, half - 1) + 0.5))
        cml(z, xi, delta, bits, cfg, 2, engine="numba", likelihood=lik)
        cml(z, xi, delta, bits, cfg, 2, engine="numba", likelihood=lik, pfa=1e-3, gate=gate,
            init_range_m=np.array([[30.0, np.nan]]))
        if bits is not None and lik == DEFAULT_LIKELIHOOD:  # the quantizer's codes (uint8)
            codes = np.rint(np.stack([z.real, z.imag], axis=-1) / delta - 0.5 + half).astype(np.uint8)
            cml(codes, xi, delta, bits, cfg, 2, engine="numba")
            cml(codes, xi, delta, bits, cfg, 2, engine="numba", pfa=1e-3, gate=gate,
                init_range_m=np.array([[30.0, np.nan]]))
        if (bits, lik) == (1, DEFAULT_LIKELIHOOD):
            _common_ready.set()
    _ready.set()
