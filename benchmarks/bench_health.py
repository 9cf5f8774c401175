#!/usr/bin/env python3
"""Cost of a node's health publication with 500 sensors (each with a latency histogram of
5 000 values): one slice (a tenth of the sensors, what the health thread publishes every
tenth of a period) against every sensor at once (what a period cost before slices).

    .venv/bin/python benchmarks/bench_health.py
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import time  # noqa: E402

import numpy as np  # noqa: E402

from pipeline.bus import BusConfig  # noqa: E402
from pipeline.stream_nodes import LocalizeNode, LocalizerConfig  # noqa: E402
bus = BusConfig(); s = bus.open()
node = LocalizeNode(bus, LocalizerConfig(), session=s)
rng = np.random.default_rng(0)
for i in range(500):
    st = node.sensor_stats(f"h{i}")
    st.latency.add_many(rng.uniform(1, 30, 5000))
t = []
for part in list(range(10)) * 5:
    t0 = time.perf_counter(); node._publish_health(part); t.append(time.perf_counter() - t0)
t0 = time.perf_counter(); node._publish_health(None); full = time.perf_counter() - t0
print(f"500 sensors: one slice (50 sensors) median {np.median(t)*1e3:.2f} ms, max {max(t)*1e3:.2f} ms; all at once {full*1e3:.1f} ms")
s.close()
