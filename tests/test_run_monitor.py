"""``qradar run``'s monitor keeps fixed-size statistics: its memory does not grow with the
messages it has seen, and its percentiles stay within 2 % of the exact ones."""

import sys
import tracemalloc

import numpy as np
import pytest

from pipeline.bus.session import BusConfig
from pipeline.nodes.histogram import LogHistogram
from pipeline.wire import TargetsMsg
from qradar.monitor import Monitor
from radar_driver.scene import resolve_scene

T0_NS = 1_700_000_000_000_000_000
#: messages a batch: 3000 messages leave 3-4 kB (the monitor's fixed structures), a leak of one
#: 16-byte object a message would leave 48 kB against the 16 kB bound
BATCH = 3_000
#: batches fed after the first before the last one is measured
WARM_BATCHES = 2


def targets_batch(scene, start: int, n: int, rng) -> tuple[list[bytes], np.ndarray, np.ndarray]:
    """``n`` targets messages of the scene's truth with each range off by a known amount:
    (payloads, latency_ms (n,), position error_m (n, K))."""
    truth = scene.truth(0.0)
    off_m = rng.uniform(-0.9, 0.9, (n, len(truth))) * rng.choice([1e-3, 1e-1, 1.0], (n, 1))
    latency_ms = rng.lognormal(np.log(40.0), 0.5, n)
    payloads = []
    for i in range(n):
        ts = T0_NS + (start + i) * 50_000_000
        est = [{**t, "range_m": t["range_m"] + float(off_m[i, j])} for j, t in enumerate(truth)]
        payloads.append(TargetsMsg("m0", start + i, ts, 7, "cml", len(truth), "quantized", est,
                                   ts + int(latency_ms[i] * 1e6)).to_json())
    return payloads, latency_ms, np.abs(off_m)  # same angle: the error is the range offset


def state_bytes(mon: Monitor) -> int:
    """Bytes the monitor holds for its statistics (its containers, deeply; a histogram's bins)."""
    def deep(v) -> int:
        if isinstance(v, LogHistogram):
            return sys.getsizeof(v) + v.counts.nbytes
        if isinstance(v, dict):
            return sys.getsizeof(v) + sum(deep(k) + deep(x) for k, x in v.items())
        if isinstance(v, (list, tuple, set)):
            return sys.getsizeof(v) + sum(deep(x) for x in v)
        return sys.getsizeof(v)
    skip = {"bus", "session", "truth", "live", "_lock", "_sub"}
    return sum(deep(v) for k, v in vars(mon).items() if k not in skip)


@pytest.mark.measure
def test_monitor_memory_is_flat_and_its_percentiles_are_right():
    scene = resolve_scene("chamber")
    assert scene.truth(0.0) == scene.truth(1e4)  # a static scene: the truth of every message is known
    mon = Monitor(BusConfig(), None, scene, T0_NS, live=None)
    rng = np.random.default_rng(12)
    lat, err = [], []

    def feed(start: int) -> None:
        payloads, la, er = targets_batch(scene, start, BATCH, rng)
        for p in payloads:
            mon.on_message("radar/m0/targets", p)
        lat.append(la)
        err.append(er)

    feed(0)  # warm-up: every lazily made object exists now
    held = state_bytes(mon)
    for b in range(1, WARM_BATCHES + 1):  # past every amortized growth (dicts, histograms' arrays)
        feed(b * BATCH)
    tracemalloc.start()  # everything the last BATCH messages leave allocated, wherever it is
    try:
        before = tracemalloc.get_traced_memory()[0]
        feed((WARM_BATCHES + 1) * BATCH)
        for i in range(2000):  # unknown topics are counted together, not one entry each
            mon.on_message(f"radar/m0/junk{i}", b"x")
        grown = tracemalloc.get_traced_memory()[0] - before - lat[-1].nbytes - err[-1].nbytes  # but the test's own
    finally:
        tracemalloc.stop()
    n = (WARM_BATCHES + 2) * BATCH
    assert grown < 16_000, f"the monitor grew by {grown} bytes over {BATCH} messages"
    assert state_bytes(mon) - held < 200  # the one "other" count
    assert mon.latency_ms.count == n and mon.errors_m.count == n * len(scene.targets)
    assert mon.count["targets"] == n and mon.count["other"] == 2000 and set(mon.count) == {"targets", "other"}

    lat, err = np.concatenate(lat), np.concatenate(err).ravel()
    for q in (50, 99):
        assert mon.latency_ms.percentile(q) == pytest.approx(np.percentile(lat, q), rel=0.02)
    for q in (50, 90):
        assert mon.errors_m.percentile(q) == pytest.approx(np.percentile(err, q), rel=0.02)
    assert mon.errors_m.mean() == pytest.approx(err.mean(), rel=1e-6)
    assert mon.latency_ms.mean() == pytest.approx(lat.mean(), rel=1e-3)  # published_ns is rounded to 1 ns


@pytest.mark.parametrize("per_sensor", [True, False])
def test_a_moving_targets_truth_starts_with_each_simulated_sensors_first_frame(per_sensor):
    """A simulated K-MD2's scene starts moving with its first measured frame, seconds
    after the run started (its driver connects first): the monitor takes the truth of a
    frame at its time since that sensor's first frame; a real sensor's at the run's start."""
    scene = resolve_scene("walker")
    assert scene.truth(0.0) != scene.truth(2.0)
    start_ns = T0_NS - 2_000_000_000  # the run started 2 s before the sensor's first frame
    mon = Monitor(BusConfig(), None, scene, start_ns, live=None, clock_per_sensor=per_sensor)
    for seq in range(40):  # 2 s of frames, each with the scene's exact truth at its own time
        t_s = seq * 0.05
        mon.on_message("radar/w0/targets", TargetsMsg("w0", seq, T0_NS + seq * 50_000_000, 7, "cml", 2, "quantized",
                                                      scene.truth(t_s), T0_NS + seq * 50_000_000 + 1).to_json())
    if per_sensor:
        assert mon.errors_m.percentile(99) < 1e-3
    else:  # 2 s ahead of the scene: the walker's own 2 s of walking
        assert mon.errors_m.percentile(90) > 1.0
