#!/usr/bin/env python3
"""Streaming throughput: source, quantize and localize nodes in three processes over
loopback (zenoh TCP on 127.0.0.1), for 1, 10 and 100 simulated sensors.

For each sensor count the offered load (frames/s per sensor) is raised step by step;
a step passes when every frame sent comes out as targets, no node counted a drop and
the latency p99 stays under MAX_P99_MS (a growing backlog is not keeping up).
The achieved aggregate rate is frames sent / the source's elapsed time (the source
process may fall behind its schedule; its late ticks are reported). The table gives the
highest passing step, its latency (sensor timestamp -> targets published) p50/p99, and
the bit-rates on the wire at that rate for raw and 1-bit quantized frames.

    .venv/bin/python benchmarks/bench_stream.py [--sensors 1 10 100] [--seconds 5]
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.bus import BusConfig  # noqa: E402
from pipeline.wire import decode_health, decode_targets  # noqa: E402

RATES_PER_SENSOR = {1: [20, 100, 200, 400, 800, 1600, 3200], 10: [20, 40, 80, 160, 320, 640],
                    100: [5, 10, 20, 40, 80]}
MAX_P99_MS = 200.0  # beyond this the pipeline is queueing, not keeping up


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cli(*args) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "qradar", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)


class Sink:
    def __init__(self, session):
        self.lock = threading.Lock()
        self.reset()
        self.sub = session.declare_subscriber("radar/**", self.on)

    def reset(self):
        with getattr(self, "lock", threading.Lock()):
            self.targets, self.latency, self.drops, self.bytes = 0, [], {}, {"raw": [], "quantized": []}

    def on(self, sample):
        key = str(sample.key_expr)
        topic = key.rsplit("/", 1)[-1]
        payload = sample.payload.to_bytes()
        with self.lock:
            if topic == "targets":
                m = decode_targets(payload)
                self.targets += 1
                self.latency.append((m.published_ns - m.timestamp_ns) / 1e6)
            elif topic == "health":
                h = decode_health(payload)
                self.drops[(h.node, h.sensor_id)] = h.drops
            elif topic in self.bytes and len(self.bytes[topic]) < 10:
                self.bytes[topic].append(len(payload))


def trial(ep: str, sink: Sink, sensors: int, rate: float, seconds: float) -> dict:
    frames = max(1, int(rate * seconds))
    sink.reset()
    src = cli("source", "--connect", ep, "--sensors", str(sensors), "--rate", str(rate), "--frames", str(frames),
              "--scene", "chamber", "--id-prefix", f"b{sensors}x{int(rate)}s")
    out, _ = src.communicate(timeout=seconds * 4 + 60)
    report = json.loads(out.strip().splitlines()[-1])
    expected = sensors * frames
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and sink.targets < expected:
        time.sleep(0.05)
    time.sleep(1.2)  # one more health period
    with sink.lock:
        lat = np.array(sink.latency)
        drops = sum(v for (node, sid), v in sink.drops.items() if sid.startswith(f"b{sensors}x{int(rate)}s"))
        got = sink.targets
        sizes = {k: (v[0] if v else None) for k, v in sink.bytes.items()}
    p99 = float(np.percentile(lat, 99)) if lat.size else float("inf")
    ok = got == expected and drops == 0 and p99 <= MAX_P99_MS
    return {"sensors": sensors, "rate_per_sensor": rate, "offered_fps": sensors * rate,
            "aggregate_fps": round(expected / max(report["elapsed_s"], 1e-9), 1), "sent": expected,
            "targets": got, "drops": drops, "late_ticks": report["late_ticks"], "ok": ok,
            "latency_p50_ms": round(float(np.median(lat)), 2) if lat.size else None,
            "latency_p99_ms": round(float(np.percentile(lat, 99)), 2) if lat.size else None,
            "bytes_raw": sizes["raw"], "bytes_quantized": sizes["quantized"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sensors", type=int, nargs="+", default=[1, 10, 100])
    ap.add_argument("--seconds", type=float, default=5.0)
    args = ap.parse_args()
    ep = f"tcp/127.0.0.1:{free_port()}"
    nodes = [cli("quantize", "--listen", ep, "--queue", "4096"), cli("localize", "--connect", ep, "--queue", "4096")]
    time.sleep(2.0)
    session = BusConfig(mode="client", connect=(ep,)).open()  # a client: the listening quantizer routes targets to it
    sink = Sink(session)
    rows, best = [], {}
    try:
        for n in args.sensors:
            for rate in RATES_PER_SENSOR.get(n, [20]):
                r = trial(ep, sink, n, rate, args.seconds)
                rows.append(r)
                print(json.dumps(r), file=sys.stderr, flush=True)
                if not r["ok"]:
                    break
                best[n] = r
    finally:
        session.close()
        for p in nodes:
            p.terminate()
            p.wait(20)
    table = []
    for r in best.values():
        table.append({**r, "raw_mbit_s": round(r["aggregate_fps"] * r["bytes_raw"] * 8 / 1e6, 3),
                      "quantized_mbit_s": round(r["aggregate_fps"] * r["bytes_quantized"] * 8 / 1e6, 3)})
    print(json.dumps({"best": table, "trials": rows}, indent=1))


if __name__ == "__main__":
    main()
