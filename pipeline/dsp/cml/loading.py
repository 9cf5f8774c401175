"""cml's compiled kernels loaded ahead of the first frame: from numba's on-disk cache (``make``
compiles them at install) or compiled, by decoding a frame of each kind, the kernels of 1-bit
codes with the default likelihood first (what live sensors send)."""

from __future__ import annotations

import sys
import time

import numpy as np

from radar_driver.model import RadarConfig, simulate_frames

from pipeline.dsp.cml.decoder import CmlDecoder
from pipeline.dsp.cml.engine import HAVE_NUMBA
from pipeline.dsp.cml.options import DEFAULT_LIKELIHOOD, LIKELIHOODS, CmlOptions
from pipeline.dsp.gate import RangeGate

#: the kinds of frames (bits, likelihood; None bits: unquantized) whose kernels are loaded, in
#: order, 1-bit codes with the default likelihood first (what live sensors send)
KINDS = ((1, DEFAULT_LIKELIHOOD),) + tuple((b, lik) for b in (1, 3, None) for lik in LIKELIHOODS
                                           if (b, lik) != (1, DEFAULT_LIKELIHOOD))
#: a first compile of each kind, (least, most) s, on a 2-core host (fresh clones with the motion
#: model: 230 s for the first, 30 s for unquantized frames on 2026-11-28's host; 354-402 s and 54 s
#: on 2026-11-29's, a slower one: a `qradar run --frames 20` took 2.0 s of CPU there against 1.46 s;
#: the other kinds reuse these kernels); from numba's cache about 0.2 s each
EXPECTED_COMPILE_S = {0: (180.0, 420.0), 4: (20.0, 60.0)}


def kind_of(bits: int | None, likelihood: str = DEFAULT_LIKELIHOOD) -> tuple[int | None, str]:
    """The kind of :data:`KINDS` whose kernels decode frames of ``bits`` (None: unquantized)
    with ``likelihood``: codes of 2 to 16 bits share the 3-bit kind's kernels."""
    return (bits if bits in (None, 1) else 3, likelihood)


def kind_label(bits: int | None, likelihood: str) -> str:
    """A kind of frame in words."""
    return f"{'unquantized' if bits is None else f'{bits}-bit'} frames, {likelihood} likelihood"


def load_kernels(common: bool = False, on_step=None, kinds: tuple | None = None, count: bool = True,
                 warm: bool = True) -> None:
    """Load (or compile) the compiled engine's kernels for every kind of frame (``common``:
    1-bit codes with the default likelihood alone; ``kinds``: these (bits, likelihood) of
    :data:`KINDS` alone): about 1 s from numba's cache, a first compile a minute or more;
    nothing without numba. The decodes loaded: K given, in a range gate with a return outside
    it, always; with a count test (``count``, ``--K auto``) and from a warm start (``warm``)
    when asked (a node with K given and no warm start: 0.3 s less CPU at its start; ``make``
    compiles them all). A caller that cannot wait runs it in a thread of its own (a frame
    of a kind not loaded yet meanwhile waits for numba's lock). ``on_step(i, bits,
    likelihood, seconds)`` before each kind (seconds None) and after it."""
    if not HAVE_NUMBA:
        return
    if kinds is not None and not set(kinds) <= set(KINDS):
        raise ValueError(f"kinds {sorted(set(kinds) - set(KINDS), key=str)} are none of cml's {KINDS}")
    cfg = RadarConfig()
    rng = np.random.default_rng(0)
    # a target at 30 m and a return at 2 m, outside the gate (what a decode in a range gate models
    # and does not report), beside a return of random phases (what a count test finds, and settles)
    g = simulate_frames(np.array([[30.0, 2.0]]), np.array([[10.0, -20.0]]), np.ones((1, 2), dtype=complex), cfg)
    g = g + 0.3 * np.exp(2j * np.pi * rng.random(g.shape))
    xi = 0.25 * (rng.random(g.shape) - 0.5 + 1j * (rng.random(g.shape) - 0.5))
    chosen = KINDS[:1] if common else KINDS if kinds is None else tuple(k for k in KINDS if k in kinds)
    for i, (bits, lik) in enumerate(chosen):
        if on_step is not None:
            on_step(i, bits, lik, None)
        t0 = time.monotonic()
        _decode_kind(CmlDecoder(cfg, CmlOptions(engine="numba", likelihood=lik)), g, xi, bits, lik, count, warm)
        if on_step is not None:
            on_step(i, bits, lik, time.monotonic() - t0)


def _decode_kind(decoder: CmlDecoder, g: np.ndarray, xi: np.ndarray, bits: int | None, lik: str, count: bool = True,
                 warm: bool = True) -> None:
    """Frames ``g`` (1, M, 2) of one kind (quantized with dither ``xi`` to ``bits``) decoded the
    ways a node decodes them: values and (the default likelihood) the quantizer's codes, K given
    (alone and in a gate), then in a gate K auto from a warm start (``warm``) and from scratch
    (``count``)."""
    delta = 1.0 if bits is None else 1.0 / (1 << (bits - 1))
    half = 0 if bits is None else 1 << (bits - 1)
    z = g if bits is None else delta * (np.clip(np.floor((g + xi).real / delta), -half, half - 1) + 0.5 + 1j * (
        np.clip(np.floor((g + xi).imag / delta), -half, half - 1) + 0.5))
    frames = [z]
    if bits is not None and lik == DEFAULT_LIKELIHOOD:  # the quantizer's codes (uint8)
        frames.append(np.rint(np.stack([z.real, z.imag], axis=-1) / delta - 0.5 + half).astype(np.uint8))
    gate = RangeGate(5.0, 100.0)
    for zz in frames:
        decoder.decode(zz, xi, delta, bits, 2)
        decoder.decode(zz, xi, delta, bits, 2, gate=gate)  # the return at 2 m modelled: stages settled
        if warm:
            decoder.decode(zz, xi, delta, bits, 2, pfa=1e-3, gate=gate, init_range_m=np.array([[30.0, np.nan]]))
        if count:  # a full search with a count test: the fit settled (refined) between its stages
            decoder.decode(zz, xi, delta, bits, 2, pfa=1e-3, gate=gate)


def _span(lo: float, hi: float) -> str:
    return f"{lo / 60:.0f}-{hi / 60:.0f} min" if lo >= 60 else f"{lo:.0f}-{hi:.0f} s"


def compile_verbose(stream=None) -> float:
    """:func:`load_kernels` of every kind, saying each step with its expected time as it starts
    and its time when done (``make`` runs this once, at install). Returns the seconds."""
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

    load_kernels(on_step=step)
    return time.monotonic() - t_start
