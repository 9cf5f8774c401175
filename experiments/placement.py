"""Where the Monte Carlo's continuous scenes put their targets in range
(:class:`experiments.montecarlo.SceneSpec`, ``ranges="continuous"``)."""

from __future__ import annotations

import numpy as np

from pipeline.errors import ParameterError


def separated_ranges(n_runs: int, k: int, rng: np.random.Generator, lo: float, hi: float, min_separation_m: float,
                     max_rounds: int = 200) -> np.ndarray:
    """(n_runs, K) ranges (m) uniform in [``lo``, ``hi``], every pair at least
    ``min_separation_m`` apart: runs that break it are drawn again (at most ``max_rounds``
    times, then a ParameterError)."""
    r = rng.uniform(lo, hi, (n_runs, k))
    for _ in range(max_rounds):
        gaps = np.diff(np.sort(r, axis=1), axis=1)
        bad = np.flatnonzero((gaps < min_separation_m).any(axis=1)) if k > 1 else np.array([], int)
        if bad.size == 0:
            return r
        r[bad] = rng.uniform(lo, hi, (bad.size, k))
    raise ParameterError(f"could not place {k} targets {min_separation_m} m apart in [{lo}, {hi}] m "
                         f"in {max_rounds} rounds")
