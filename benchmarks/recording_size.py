#!/usr/bin/env python3
"""A recording's size per sensor-second, and what each topic holds before compression
(docs/recording.md, "What Foxglove shows"): for each MCAP file given, its size over the
span of its raw frames (first to last timestamp plus one frame period at 20 Hz), summed
over its sensors, and each topic's messages and uncompressed KiB a sensor-second.

    .venv/bin/qradar run --duration 15 [--track] --record out/run.mcap
    .venv/bin/python benchmarks/recording_size.py out/run.mcap [more.mcap ...]
"""

from __future__ import annotations

import argparse
import os
from collections import Counter

from replay.mcapio import McapFile

FRAME_PERIOD_S = 1 / 20


def size_per_sensor_second(path: str) -> dict:
    """{"bytes", "frames", "sensor_s", "kib_per_sensor_s", "messages" by topic, "kib_per_sensor_s_by_topic"}."""
    f = McapFile(path)
    count, size = Counter(), Counter()
    span: dict[str, list[int]] = {}
    for ch, m in f.messages():
        topic = ch.topic.rsplit("/", 1)[-1]
        count[topic] += 1
        size[topic] += len(m.data)
        if topic == "raw":
            t = span.setdefault(ch.topic, [m.publish_time, m.publish_time])
            t[0], t[1] = min(t[0], m.publish_time), max(t[1], m.publish_time)
    sensor_s = sum((hi - lo) / 1e9 + FRAME_PERIOD_S for lo, hi in span.values())
    total = os.path.getsize(path)
    return {"bytes": total, "frames": count["raw"], "sensor_s": round(sensor_s, 2),
            "kib_per_sensor_s": round(total / sensor_s / 1024, 1), "messages": dict(count),
            "kib_per_sensor_s_by_topic": {k: round(v / sensor_s / 1024, 2) for k, v in size.items()}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("files", nargs="+")
    for path in parser.parse_args().files:
        r = size_per_sensor_second(path)
        print(f"{path}: {r['bytes']} B, {r['frames']} frames over {r['sensor_s']} sensor-s: "
              f"{r['kib_per_sensor_s']} KiB per sensor-second; messages {r['messages']}; before compression, "
              f"KiB per sensor-second {r['kib_per_sensor_s_by_topic']}")


if __name__ == "__main__":
    main()
