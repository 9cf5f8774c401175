"""Does ``--K auto`` keep its promise beside real targets? False targets a frame (estimates
farther than MATCH_BINS range bins from every true target) of cml's count test at the
configured pfa, beside ``k`` strong targets (amplitude 1, 5-145 m, at least 10 m apart,
+-50 deg), 1-bit at a dither scale alpha or unquantized, in complex Gaussian noise.

Run ``python -m experiments.false_alarms`` for the table of the README's headline row,
``python -m experiments.false_alarms --grid pbp`` (or ``cml``) for a decoder over K, alpha and
noise, ``python -m experiments.false_alarms --accuracy`` for ``--K auto``'s error on the targets
it keeps against the count given's, on the same frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radar_driver.model import RadarConfig, simulate_frames

from pipeline.defaults import DEFAULT_ALPHA
from pipeline.dsp.decode import Decoder, DecoderConfig
from pipeline.dsp.localize import DEFAULT_PFA
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from experiments.coverage import scenes

#: an estimate this many range bins from a true target is that target
MATCH_BINS = 1.0
#: the most targets a frame K auto may report
MAX_K = 4


@dataclass(frozen=True)
class AlarmCase:
    """``k`` strong targets, noise ``sigma``, ``bits`` 1 at ``alpha`` or None (unquantized),
    ``frames`` frames, ``seed``, the count test's ``pfa``, the decoder ``algo`` (cml or pbp)."""

    k: int
    sigma: float
    bits: int | None = 1
    alpha: float = DEFAULT_ALPHA
    frames: int = 2000
    seed: int = 0
    pfa: float = DEFAULT_PFA
    algo: str = "cml"


def case_frames(case: AlarmCase, config: RadarConfig):
    """``case``'s true ranges (m) and angles (deg) (B, k) and its frames: complex (B, M, 2) in
    noise, or their QuantizedFrames when ``case.bits`` is set."""
    rng = np.random.default_rng(case.seed)
    r, a, x = scenes(case, rng) if case.k else (np.zeros((case.frames, 0)),) * 3
    g = simulate_frames(r, a, x, config) if case.k else np.zeros((case.frames, config.n_measurements, 2), complex)
    g = g + case.sigma * (rng.standard_normal(g.shape) + 1j * rng.standard_normal(g.shape))
    if case.bits is None:
        return r, a, g
    return r, a, quantize_frames(g, QuantizerConfig(alpha=case.alpha, bits=case.bits), np.arange(case.frames))


def frames_label(case: AlarmCase) -> str:
    """The tables' "frames" cell of ``case``: ``unquantized`` or ``1-bit, α 0.45``."""
    return "unquantized" if case.bits is None else f"{case.bits}-bit, α {case.alpha:g}"


def false_targets(case: AlarmCase, config: RadarConfig | None = None) -> tuple[float, float]:
    """(false targets a frame, share of the true targets found) of ``case`` decoded by its
    decoder with ``--K auto`` (at most MAX_K a frame)."""
    config = RadarConfig() if config is None else config
    r, _, frames = case_frames(case, config)
    decoder = Decoder(DecoderConfig(algo=case.algo, auto_k=True, pfa=case.pfa, uncertainty=False))  # positions
    det = decoder.decode_batch(frames, config, MAX_K)
    dist = np.abs(det.range_m[:, :, None] - r[:, None, :]) / config.range_resolution_m  # (B, MAX_K, k)
    near = (dist <= MATCH_BINS) & det.present[:, :, None]
    false = det.present & ~near.any(axis=2)
    found = near.any(axis=1).mean() if case.k else 1.0
    return float(false.sum() / case.frames), float(found)


#: the README's cases: one strong target at the default alpha, noise 0 to 0.3, cml; then PBP's
#: (its count test on the residual of a tone model of the targets found: pipeline.dsp.residual)
CASES = tuple(AlarmCase(1, s, seed=i) for i, s in enumerate((0.0, 0.01, 0.03, 0.1, 0.3))) + tuple(
    AlarmCase(k, s, alpha=a, seed=10 + i, algo="pbp") for i, (k, a, s) in enumerate(
        ((1, 0.45, 0.0), (1, 0.45, 0.1), (1, 1.0, 0.0), (1, 1.0, 0.1), (2, 0.45, 0.03), (1, 0.0, 0.03))))


def accuracy(case: AlarmCase, config: RadarConfig | None = None) -> tuple[float, float]:
    """The median position error (m) of the true targets of ``case``'s frames that both runs
    find (an estimate within MATCH_BINS), with the count given (``case.k``) and with ``--K
    auto`` (at most MAX_K), on the same frames: (given, auto). A target counts only where
    both find it, so the figure compares the estimates, not the detections."""
    config = RadarConfig() if config is None else config
    r, a, frames = case_frames(case, config)
    errs, found = [], []
    for auto, k in ((False, case.k), (True, MAX_K)):
        decoder = Decoder(DecoderConfig(algo=case.algo, auto_k=auto, pfa=case.pfa, uncertainty=False))
        det = decoder.decode_batch(frames, config, k)
        t = r * np.exp(1j * np.deg2rad(a))  # (B, k) positions
        e = np.where(det.present, det.range_m * np.exp(1j * np.deg2rad(det.angle_deg)), np.nan)  # (B, L)
        dist = np.abs(t[:, :, None] - e[:, None, :])  # (B, k, L)
        near = np.abs(det.range_m[:, None, :] - r[:, :, None]) / config.range_resolution_m <= MATCH_BINS
        near &= det.present[:, None, :]
        errs.append(np.where(near, dist, np.inf).min(axis=2))
        found.append(near.any(axis=2))
    both = found[0] & found[1]
    return float(np.median(errs[0][both])), float(np.median(errs[1][both]))


#: the cases of the accuracy table: cml and PBP, one and two strong targets, 1 bit at the
#: default alpha and unquantized, noise 0.01-0.1
ACCURACY_CASES = tuple(AlarmCase(k, s, bits=bits, seed=20 + i, algo=algo, frames=1000) for i, (algo, k, bits, s) in
                       enumerate((a, k, b, s) for a in ("cml", "pbp") for k in (1, 2) for b in (1, None)
                                 for s in (0.01, 0.1)))


def accuracy_table(cases=ACCURACY_CASES) -> str:
    """A markdown table of :func:`accuracy` for ``cases``: ``--K auto``'s median error over the
    count given's."""
    lines = ["| decoder | K | frames | noise σ | median error, K given | median error, `--K auto` | ratio |",
             "|---|---|---|---|---|---|---|"]
    for c in cases:
        given, auto = accuracy(c)
        lines.append(f"| {c.algo} | {c.k} | {frames_label(c)} | {c.sigma:g} | {given:.4f} m | {auto:.4f} m "
                     f"| {auto / given:.2f} |")
    return "\n".join(lines)


def table(cases=CASES) -> str:
    """A markdown table of :func:`false_targets` for ``cases``."""
    lines = ["| decoder | K | frames | noise σ | pfa | false targets a frame | targets found |",
             "|---|---|---|---|---|---|---|"]
    for c in cases:
        f, found = false_targets(c)
        lines.append(f"| {c.algo} | {c.k} | {frames_label(c)} | {c.sigma:g} | {c.pfa:g} | {f:.4f} ({c.frames} frames) | {100 * found:.1f} % |")
    return "\n".join(lines)


def grid(algo: str = "pbp", frames: int = 1000) -> str:
    """False targets a frame / targets found of ``algo`` over K 0-2, 1-bit alpha 0, 0.45 and 1,
    noise sigma 0-0.3 (one row a K and alpha), as a markdown table."""
    sigmas = (0.0, 0.01, 0.03, 0.1, 0.3)
    lines = ["| K | α | " + " | ".join(f"σ {s:g}" for s in sigmas) + " |", "|---|---|" + "---|" * len(sigmas)]
    for k in (0, 1, 2):
        for alpha in (0.0, 0.45, 1.0):
            cells = [false_targets(AlarmCase(k, s, alpha=alpha, seed=100 + i, algo=algo, frames=frames))
                     for i, s in enumerate(sigmas)]
            lines.append(f"| {k} | {alpha:g} | " + " | ".join(f"{f:.3f} ({100 * found:.1f} %)" for f, found in cells)
                         + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    import sys

    if sys.argv[1:2] == ["--grid"]:
        print(grid(sys.argv[2]))
    elif sys.argv[1:2] == ["--accuracy"]:
        print(accuracy_table())
    else:
        print(table())
