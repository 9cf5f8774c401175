"""Are the targets' uncertainties honest? The share of targets whose true position lies inside
their 1-sigma and 2-sigma ellipses (:mod:`pipeline.dsp.uncertainty`, in (range, angle)):
39.3 % and 86.5 % when the reported covariance is the estimate's. Off-grid scenes of K
unit-amplitude targets (5-145 m, at least 10 m apart, +-50 deg) in complex Gaussian noise,
decoded by cml with the decoder's defaults (1 bit at the default alpha, or unquantized).

Run ``python -m experiments.coverage`` for the table of docs/science.md and the README.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radar_driver.model import RadarConfig, simulate_frames

from pipeline.defaults import DEFAULT_ALPHA
from pipeline.dsp.decode import Decoder, DecoderConfig
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames

#: a true target matches the estimate nearest in range when within this, m (else: outside)
MATCH_M = 1.0
#: 2-D probability of the 1- and 2-sigma ellipses of a Gaussian
EXPECTED = (1.0 - np.exp(-0.5), 1.0 - np.exp(-2.0))


@dataclass(frozen=True)
class CoverageCase:
    """One case: ``k`` targets a frame, noise std ``sigma`` per real part (frame units),
    ``bits`` 1 (dithered at ``alpha``) or None (unquantized), ``frames`` frames, ``seed``."""

    k: int
    sigma: float
    bits: int | None = 1
    alpha: float = DEFAULT_ALPHA
    frames: int = 1000
    seed: int = 0


def scenes(case: CoverageCase, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ranges (m), angles (deg) and amplitudes (B, K) of ``case``'s frames."""
    b, k = case.frames, case.k
    r = np.empty((b, k))
    r[:, 0] = rng.uniform(5.0, 145.0, b)
    for j in range(1, k):  # at least 10 m from the others, on the 5-145 m span
        r[:, j] = 5.0 + (r[:, j - 1] - 5.0 + rng.uniform(10.0, 130.0, b)) % 140.0
    return r, rng.uniform(-50.0, 50.0, (b, k)), np.exp(2j * np.pi * rng.random((b, k)))


def inside(err: np.ndarray, var_r: np.ndarray, var_a: np.ndarray, cov: np.ndarray, level: float) -> np.ndarray:
    """Whether errors ``err`` (..., 2) (m, deg) lie inside the ``level``-sigma ellipse of the
    covariance ``[[var_r, cov], [cov, var_a]]`` (each (...)): ``err^T C^-1 err <= level^2``."""
    det = var_r * var_a - cov * cov
    q = (var_a * err[..., 0] ** 2 - 2.0 * cov * err[..., 0] * err[..., 1] + var_r * err[..., 1] ** 2) / det
    return np.isfinite(q) & (det > 0) & (q <= level * level)


def coverage(case: CoverageCase, config: RadarConfig | None = None) -> tuple[float, float, int]:
    """(share inside the 1-sigma ellipse, inside the 2-sigma one, targets) of ``case``: every
    true target counts, one the decoder missed (no estimate within MATCH_M) as outside."""
    config = RadarConfig() if config is None else config
    rng = np.random.default_rng(case.seed)
    r, a, x = scenes(case, rng)
    g = simulate_frames(r, a, x, config)
    g = g + case.sigma * (rng.standard_normal(g.shape) + 1j * rng.standard_normal(g.shape))
    dec = Decoder(DecoderConfig(algo="cml", p_values=False))  # the ellipses only
    if case.bits is None:
        det = dec.decode_batch(g, config, case.k)
    else:
        det = dec.decode_batch(quantize_frames(g, QuantizerConfig(alpha=case.alpha, bits=case.bits),
                                               np.arange(case.frames)), config, case.k)
    rows = np.arange(case.frames)[:, None]
    near = np.argmin(np.abs(np.where(det.present, det.range_m, np.inf)[:, None, :] - r[:, :, None]), axis=2)
    er = det.range_m[rows, near] - r
    err = np.stack([er, det.angle_deg[rows, near] - a], axis=-1)
    cols = (det.sigma_range_m[rows, near] ** 2, det.sigma_angle_deg[rows, near] ** 2, det.cov_range_angle[rows, near])
    matched = np.abs(er) < MATCH_M
    one, two = (np.mean(matched & inside(err, *cols, level)) for level in (1.0, 2.0))
    return float(one), float(two), int(r.size)


#: the cases of the docs' table (and tests/test_uncertainty.py)
CASES = tuple(CoverageCase(k, s, bits, frames=3000 // k, seed=10 * k + i)
              for k in (1, 2) for bits in (1, None) for i, s in enumerate((0.03, 0.1, 0.3)))


def table(cases=CASES) -> str:
    """A markdown table of :func:`coverage` for ``cases``."""
    lines = ["| K | frames | noise σ | 1σ ellipse (39.3 %) | 2σ ellipse (86.5 %) | targets |", "|---|---|---|---|---|---|"]
    for c in cases:
        one, two, n = coverage(c)
        what = "unquantized" if c.bits is None else f"{c.bits}-bit, α {c.alpha:g}"
        lines.append(f"| {c.k} | {what} | {c.sigma:g} | {100 * one:.1f} % | {100 * two:.1f} % | {n} |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(table())
