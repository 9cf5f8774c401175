"""Loading :func:`pipeline.dsp.cml.cml`'s compiled kernels ahead of the first frame: from numba's
on-disk cache (``make`` compiles them at install) or compiled, in a daemon thread, the
kernels of 1-bit codes with the default likelihood first (what live sensors send)."""

from __future__ import annotations

import threading
import time

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


#: the kinds of frame whose kernels are compiled, in order: (bits, likelihood), None bits for
#: unquantized frames; the first is what live sensors send
KINDS = [(1, DEFAULT_LIKELIHOOD)] + [(b, lik) for b in (1, 3, None) for lik in LIKELIHOODS
                                     if (b, lik) != (1, DEFAULT_LIKELIHOOD)]


def kind_label(bits: int | None, likelihood: str) -> str:
    return f"{'unquantized' if bits is None else f'{bits}-bit'} frames, {likelihood} likelihood"


#: a first compile of each kind, (least, most) s, measured on 2 cores shared with other jobs
#: (2026-11-28: 60-66 s at load 2.7, 116 s from a fresh clone at load 3.5; 14-24 s for
#: unquantized frames; the other kinds reuse these kernels); from numba's cache about 0.2 s each
EXPECTED_COMPILE_S = {0: (60.0, 120.0), 4: (14.0, 25.0)}


def _span(lo: float, hi: float) -> str:
    return f"{lo / 60:.0f}-{hi / 60:.0f} min" if lo >= 60 else f"{lo:.0f}-{hi:.0f} s"


def compile_verbose(decoder, stream=None) -> float:
    """Compile (or load) ``decoder``'s (:func:`pipeline.dsp.cml.cml`) kernels for every kind,
    saying each step with its expected time as it starts and its time when done (``make``
    runs this once, at install). Returns the seconds."""
    import sys

    out = stream or sys.stdout
    lo, hi = (sum(v[i] for v in EXPECTED_COMPILE_S.values()) for i in (0, 1))
    print(f"compiling cml's kernels into numba's cache, {len(KINDS)} kinds of frame: {lo / 60:.1f}-{hi / 60:.1f} min "
          "the first time on a busy 2-core host (then ~1 s: a node loads them from the cache)", file=out, flush=True)
    t_start = time.monotonic()

    def step(i, bits, lik, seconds):
        if seconds is None:
            expect = EXPECTED_COMPILE_S.get(i)
            print(f"  [{i + 1}/{len(KINDS)}] {kind_label(bits, lik)}: expect "
                  f"{'under a second (the kernels above)' if expect is None else _span(*expect)} ... ",
                  end="", file=out, flush=True)
        else:
            print(f"{seconds:.1f} s", file=out, flush=True)

    _compile_all(decoder, step)
    return time.monotonic() - t_start


def _compile_all(cml, on_step=None) -> None:
    """Decode a frame of each kind with ``cml`` (:func:`pipeline.dsp.cml.cml`, passed in: it
    imports this module); ``on_step(i, bits, likelihood, seconds)`` before each kind (seconds
    None) and after it (i from 0)."""
    cfg = RadarConfig()
    n = cfg.samples_per_ramp
    rng = np.random.default_rng(0)
    g = 0.3 * np.exp(2j * np.pi * rng.random((1, 2 * n, 2)))
    xi = 0.25 * (rng.random(g.shape) - 0.5 + 1j * (rng.random(g.shape) - 0.5))
    gate = RangeGate(5.0, 100.0)
    for i, (bits, lik) in enumerate(KINDS):
        if on_step is not None:
            on_step(i, bits, lik, None)
        t0 = time.monotonic()
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
        if on_step is not None:
            on_step(i, bits, lik, time.monotonic() - t0)
    _ready.set()
