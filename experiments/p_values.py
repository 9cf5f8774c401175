"""Are cml's p-values honest? (:mod:`pipeline.dsp.significance`.) The share of targets whose
p-value lies below a level, over that level (1: exact; below 1: conservative), for the
target of noise-only frames decoded with K = 1, and for the weaker target beside a strong
one (amplitude 1, 5-140 m, -50..50 deg) with K = 2; noise std 0.1 a real part by default,
the live gate (1.2-150 m), 1 bit at an alpha or unquantized, the phase-step model or the
static one.

Run ``python -m experiments.p_values`` for the table of docs/science.md (``--frames``,
``--sigma``, ``--seed``); tests/test_p_value_cml.py re-runs its cases.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np

from radar_driver.model import RadarConfig, simulate_frames

from pipeline.dsp.decode import Decoder, DecoderConfig
from pipeline.dsp.gate import RangeGate
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from replay.progress import Progress

#: the p-value levels of the table
LEVELS = (0.001, 0.01, 0.05, 0.1, 0.5)
#: a decoded target is the strong target's estimate when it is the nearer one and within this, m
MATCH_M = 0.6


@dataclass(frozen=True)
class Case:
    """``alpha`` None: unquantized, else 1-bit dithered at it; ``strong``: beside a target of
    amplitude 1 (K = 2), else noise alone (K = 1); ``motion``: cml's phase-step model."""

    alpha: float | None
    strong: bool = False
    motion: bool = True

    def label(self) -> tuple[str, str]:
        frames = "unquantized" if self.alpha is None else f"1-bit, α {self.alpha:g}"
        return (frames + ("" if self.motion else ", the static model"),
                "beside a target of amplitude 1, K = 2" if self.strong else "noise alone, K = 1")


CASES = (Case(None), Case(None, strong=True), Case(None, motion=False), Case(0.45), Case(0.45, strong=True),
         Case(1.0), Case(1.0, strong=True))


def frames_of(frames: int, seed: int, alpha: float | None, strong: bool = False, sigma: float = 0.1,
              config: RadarConfig = RadarConfig()):
    """Noise of std ``sigma`` on each real part (and, ``strong``, one target of amplitude 1 at
    5-140 m, -50..50 deg), 1-bit at ``alpha`` (None: unquantized); and the true ranges (B, 1)."""
    rng = np.random.default_rng(seed)
    r, th = rng.uniform(5, 140, (frames, 1)), rng.uniform(-50, 50, (frames, 1))
    shape = (frames, config.n_measurements, 2)
    g = sigma * (rng.standard_normal(shape) + 1j * rng.standard_normal(shape))
    if strong:
        g = g + simulate_frames(r, th, np.ones((frames, 1)), config)
    return (g if alpha is None else quantize_frames(g, QuantizerConfig(alpha=alpha, bits=1), np.arange(frames))), r


def shares(p: np.ndarray, levels=LEVELS) -> list[float]:
    """The share of ``p`` below each level over the level."""
    return [float((p < a).mean() / a) for a in levels]


def p_values(case: Case, frames: int, seed: int, sigma: float = 0.1, config: RadarConfig = RadarConfig()):
    """The p-values of ``case``'s tested targets (noise alone: the target; beside a strong
    one: the other one) and those of the strong target's estimates (empty for noise alone)."""
    batch, r = frames_of(frames, seed, case.alpha, case.strong, sigma, config)
    decoder = Decoder(DecoderConfig(algo="cml", gate=RangeGate.default(config), motion=case.motion))
    det = decoder.decode_batch(batch, config, 2 if case.strong else 1)
    if not case.strong:
        return det.p_value[:, 0], np.zeros(0)
    err = np.abs(det.range_m - r)
    true = np.arange(2)[None, :] == np.argmin(err, axis=1)[:, None]  # the target's estimate: the nearer one
    return det.p_value[~true & det.present], det.p_value[true][err[true] < MATCH_M]


def table(frames: int = 2000, seed: int = 3, sigma: float = 0.1, cases=CASES) -> str:
    """A markdown table of :func:`shares` for ``cases``."""
    head = " | ".join(f"p < {a:g}" for a in LEVELS)
    lines = [f"| frames | target | {head} |", "|---|---|" + "---|" * len(LEVELS)]
    with Progress(len(cases), "p-values", unit="cases") as bar:
        for case in cases:
            p, _ = p_values(case, frames, seed, sigma)
            lines.append("| {} | {} ({} frames) | ".format(*case.label(), frames)
                         + " | ".join(f"{s:.2f} ×" for s in shares(p)) + " |")
            bar.update()
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=2000, help="frames a case (default 2000)")
    ap.add_argument("--sigma", type=float, default=0.1, help="noise std a real part (default 0.1)")
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args(argv)
    print(f"noise σ {args.sigma:g}, seed {args.seed}")
    print(table(args.frames, args.seed, args.sigma))


if __name__ == "__main__":
    main()
