#!/usr/bin/env python3
"""Cost of a node's health publication with 500 sensors (each with a latency histogram of
5 000 values): one slice (a tenth of the sensors, what the health thread publishes every
tenth of a period) against every sensor at once (what a period cost before slices).

    .venv/bin/python benchmarks/bench_health.py

After the line, the same figures as one JSON object (``harness.emit``).
"""

import itertools

import numpy as np

from harness import emit, time_calls
from pipeline.bus.session import BusConfig
from pipeline.nodes.stream import LocalizeNode, LocalizerConfig


def main() -> None:
    bus = BusConfig()
    s = bus.open()
    try:
        node = LocalizeNode(bus, LocalizerConfig(), session=s)
        rng = np.random.default_rng(0)
        for i in range(500):
            node.sensor_stats(f"h{i}").latency.add_many(rng.uniform(1, 30, 5000))
        parts = itertools.cycle(range(10))
        t = time_calls(lambda: node._publish_health(next(parts)), 50).wall_s
        full = time_calls(lambda: node._publish_health(None), 1).wall_s[0]
        print(f"500 sensors: one slice (50 sensors) median {np.median(t)*1e3:.2f} ms, max {max(t)*1e3:.2f} ms; "
              f"all at once {full*1e3:.1f} ms")
    finally:
        s.close()
    emit({"sensors": 500, "slice_sensors": 50, "latency_values_per_sensor": 5000,
          "slice_median_ms": round(float(np.median(t)) * 1e3, 3), "slice_max_ms": round(float(max(t)) * 1e3, 3),
          "all_at_once_ms": round(float(full) * 1e3, 3)})


if __name__ == "__main__":
    main()
