"""The fixed-size histogram behind every long-running percentile."""

import numpy as np
import pytest

from pipeline.errors import ParameterError
from pipeline.nodes.histogram import LogHistogram, SharedHistogram


def test_percentiles_within_two_percent_of_exact():
    rng = np.random.default_rng(1)
    v = rng.lognormal(mean=1.0, sigma=1.0, size=20000)
    h = LogHistogram()
    h.add_many(v[:10000])
    for x in v[10000:]:
        h.add(float(x))
    assert h.count == v.size
    for q in (1, 50, 90, 99, 99.9):
        assert h.percentile(q) == pytest.approx(np.percentile(v, q), rel=0.02)
    assert h.mean() == pytest.approx(v.mean())


def test_memory_is_fixed_and_outliers_clip():
    h = LogHistogram(lo=0.01, hi=1000)
    n = h.counts.nbytes
    h.add_many([1e-9, 0.0, -5.0, 1e12, np.nan, np.inf])
    assert h.counts.nbytes == n and h.count == 4  # NaN and inf ignored
    assert h.percentile(100) >= 1000 and h.percentile(0) <= 0.011  # out-of-range values sit in the end bins
    assert h.max == 1e12 and h.min == -5.0


def test_empty_and_merge_and_reset():
    a, b = SharedHistogram(), SharedHistogram()
    assert a.percentile(50) is None and a.summary() == {"p50": None, "p99": None}
    a.add_many([1.0, 2.0])
    b.add_many([3.0, 4.0])
    a.merge(b)
    assert a.count == 4 and a.max == 4.0
    a.reset()
    assert a.count == 0 and a.percentile(99) is None
    with pytest.raises(ParameterError):
        a.merge(LogHistogram(lo=1.0, hi=10.0))
