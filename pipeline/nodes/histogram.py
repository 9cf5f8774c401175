"""Fixed-size histograms for long-running statistics (latency, position error).

A :class:`LogHistogram` keeps counts in log-spaced bins between ``lo`` and ``hi``
(values below ``lo`` go to the first bin, above ``hi`` to the last), so its memory is
fixed however long a node runs, adding is O(1) per value (vectorized for arrays) and a
percentile costs one cumulative sum over the bins, never a sort of the history. With
the default 60 bins per decade a percentile is within 2 % of the exact value.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from pipeline.errors import ParameterError


class LogHistogram:
    """Counts of positive values in log-spaced bins over [lo, hi] (units are the caller's).

    Not thread-safe by itself; :class:`SharedHistogram` adds a lock."""

    def __init__(self, lo: float = 1e-3, hi: float = 1e5, bins_per_decade: int = 60):
        if not (0 < lo < hi) or bins_per_decade < 1:
            raise ParameterError(f"histogram range [{lo}, {hi}] and {bins_per_decade} bins per decade are invalid")
        self.lo, self.hi = float(lo), float(hi)
        self._log_lo = math.log10(self.lo)
        self._per_decade = float(bins_per_decade)
        self.n_bins = int(math.ceil((math.log10(hi) - self._log_lo) * bins_per_decade)) + 1
        self.counts = np.zeros(self.n_bins, dtype=np.int64)
        self.count = 0
        self.total = 0.0
        self.max = -math.inf
        self.min = math.inf

    def _index(self, v: np.ndarray) -> np.ndarray:
        v = np.clip(v, self.lo, self.hi)
        return np.minimum(((np.log10(v) - self._log_lo) * self._per_decade).astype(np.int64), self.n_bins - 1)

    def add(self, value: float) -> None:
        """One value; NaN and inf are ignored."""
        if not math.isfinite(value):
            return
        v = min(max(value, self.lo), self.hi)
        # numpy's log10, as :meth:`bins` (math's may differ by an ulp where numpy's is SIMD: a bin edge)
        i = min(int((float(np.log10(v)) - self._log_lo) * self._per_decade), self.n_bins - 1)
        self.counts[i] += 1
        self.count += 1
        self.total += value
        self.max = max(self.max, value)
        self.min = min(self.min, value)

    def bins(self, values: np.ndarray) -> np.ndarray:
        """The bin of each of ``values`` (n,) float as :meth:`add` finds it, -1 for NaN and
        inf (which add ignores): (n,) int64, one vectorized pass for a batch whose values go
        to several histograms of this binning (:meth:`add_binned`)."""
        v = np.asarray(values, dtype=float)
        ok = np.isfinite(v)
        return np.where(ok, self._index(np.where(ok, v, self.lo)), -1)

    def add_binned(self, value: float, index: int) -> None:
        """:meth:`add` of ``value`` whose bin ``index`` was found by :meth:`bins` of a
        histogram of the same binning (-1: ignored)."""
        if index < 0:
            return
        self.counts[index] += 1
        self.count += 1
        self.total += value
        if value > self.max:
            self.max = value
        if value < self.min:
            self.min = value

    def add_many(self, values) -> None:
        """An array of values; NaN and inf are ignored."""
        v = np.asarray(values, dtype=float).ravel()
        v = v[np.isfinite(v)]
        if not v.size:
            return
        np.add.at(self.counts, self._index(v), 1)
        self.count += int(v.size)
        self.total += float(v.sum())
        self.max = max(self.max, float(v.max()))
        self.min = min(self.min, float(v.min()))

    def merge(self, other: "LogHistogram") -> None:
        if other.n_bins != self.n_bins or other.lo != self.lo:
            raise ParameterError("histograms of different binning cannot be merged")
        self.counts += other.counts
        self.count += other.count
        self.total += other.total
        self.max = max(self.max, other.max)
        self.min = min(self.min, other.min)

    def reset(self) -> None:
        self.counts[:] = 0
        self.count, self.total, self.max, self.min = 0, 0.0, -math.inf, math.inf

    def percentile(self, q: float) -> float | None:
        """The q-th percentile (0-100), the geometric centre of its bin clipped to the
        observed min and max; None when empty."""
        return self.percentiles((q,))[0]

    def percentiles(self, qs) -> list[float | None]:
        """Several percentiles (0-100) from one cumulative sum over the bins."""
        if not self.count:
            return [None] * len(qs)
        ranks = [max(1, int(math.ceil(q / 100.0 * self.count))) for q in qs]
        idx = np.searchsorted(np.cumsum(self.counts), ranks).tolist()
        return [float(min(max(10 ** (self._log_lo + (i + 0.5) / self._per_decade), self.min), self.max))
                for i in idx]

    def mean(self) -> float | None:
        return self.total / self.count if self.count else None

    def summary(self, digits: int = 3) -> dict[str, float | None]:
        """{"p50", "p99"} rounded, None when empty."""
        return {name: None if p is None else round(p, digits)
                for name, p in zip(("p50", "p99"), self.percentiles((50, 99)))}


class SharedHistogram(LogHistogram):
    """A :class:`LogHistogram` whose add/percentile take a lock (zenoh callbacks vs readers)."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self._hlock = threading.RLock()

    def add(self, value: float) -> None:
        with self._hlock:
            super().add(value)

    def add_many(self, values) -> None:
        with self._hlock:
            super().add_many(values)

    def percentiles(self, qs) -> list[float | None]:
        with self._hlock:
            return super().percentiles(qs)

    def summary(self, digits: int = 3) -> dict[str, float | None]:
        with self._hlock:
            return super().summary(digits)
