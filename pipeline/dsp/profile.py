"""Range profiles: |U| = |Φ*Z/M| of frames against range, per receiver, in dB of full
scale (what PBP thresholds; Z the dequantized codes, the dither not removed), and their
reduction to what a plot needs. Pure numpy, batch axis first; the live views
(qradar.liveview) and the recorder (replay.recorder) both draw on it."""

from __future__ import annotations

import numpy as np

from radar_driver.model import RadarConfig

from pipeline.errors import ParameterError

from .localize import back_project

#: profile values below this magnitude (full-scale units) are shown as it: -240 dB
PROFILE_FLOOR = 1e-12


def profile_magnitude(z: np.ndarray, radar: RadarConfig) -> np.ndarray:
    """|U| of (B, M, 2) complex frames Z (full-scale units): (B, N, 2), one column per receiver."""
    return np.abs(back_project(z, radar))


def to_db(magnitude: np.ndarray) -> np.ndarray:
    """20 log10 of a magnitude, floored at PROFILE_FLOOR (-240 dB)."""
    return 20.0 * np.log10(np.maximum(magnitude, PROFILE_FLOOR))


def profile_db(magnitude: np.ndarray, bins: int | None = None) -> np.ndarray:
    """(B, N, 2) magnitudes -> (B, bins, 3) dB of full scale: the joint magnitude
    sqrt((|U1|² + |U2|²) / 2) (the scale of a target's ``amplitude``), receiver 1, receiver 2.
    ``bins`` (a divisor of N; None: N): each value the largest of its N / bins adjacent
    range bins, so a target's peak survives the reduction."""
    mag = np.asarray(magnitude, dtype=float)
    b, n, _ = mag.shape
    joint = np.sqrt((mag ** 2).sum(axis=-1, keepdims=True) / 2.0)
    out = np.concatenate([joint, mag], axis=-1)  # (B, N, 3)
    bins = n if bins is None else bins
    if not (isinstance(bins, int) and bins >= 1 and n % bins == 0):
        raise ParameterError(f"profile bins={bins!r} must be a divisor of N={n}")
    if bins != n:
        out = out.reshape(b, bins, n // bins, 3).max(axis=2)
    return to_db(out)


def profile_ranges(radar: RadarConfig, bins: int | None = None) -> np.ndarray:
    """The range of each of ``bins`` profile values (m): the first range bin each covers."""
    grid = radar.range_grid_m()
    step = 1 if bins is None else len(grid) // bins
    return grid[::step]
