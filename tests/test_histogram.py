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


def _state(h):
    return h.counts.tolist(), h.count, h.total, h.max, h.min


def test_bins_then_add_binned_is_add_value_for_value():
    """A batch's bins found at once (what a node's record_latencies does) fill a histogram
    exactly as add() one value at a time: bin edges, clipping, NaN and inf included."""
    rng = np.random.default_rng(2)
    h = LogHistogram()
    edges = 10 ** (h._log_lo + np.arange(h.n_bins + 1) / h._per_decade)  # on and next to every bin edge
    v = np.concatenate([rng.lognormal(1.0, 3.0, 20000), edges, np.nextafter(edges, 0), np.nextafter(edges, np.inf),
                        [0.0, -0.0, -3.0, 1e-300, 1e300, np.nan, np.inf, -np.inf, h.lo, h.hi]])
    one, batch = LogHistogram(), LogHistogram()
    for x in v.tolist():
        one.add(x)
    for x, i in zip(v.tolist(), batch.bins(v).tolist()):
        batch.add_binned(x, i)
    assert _state(batch) == _state(one)


def test_a_nodes_latencies_of_a_batch_are_added_per_sensor():
    from pipeline.nodes.counters import Counters

    c, ref = Counters(), Counters()
    ids = ["a", "b", "a", "c", "b"]
    lat = np.array([1.5, 20.0, np.nan, 0.2, 1e6])
    c.record_latencies(ids, lat)
    for sid, x in zip(ids, lat.tolist()):
        ref.sensor_stats(sid).latency.add(x)
    for sid in "abc":
        assert _state(c.stats[sid].latency) == _state(ref.stats[sid].latency)
    c.record_latencies([], np.array([]))
    small, ref_small = Counters(), Counters()  # fewer than 4 frames: one at a time, the same
    small.record_latencies(ids[:2], lat[:2])
    for sid, x in zip(ids[:2], lat[:2].tolist()):
        ref_small.sensor_stats(sid).latency.add(x)
    assert all(_state(small.stats[s].latency) == _state(ref_small.stats[s].latency) for s in "ab")
