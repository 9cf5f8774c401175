#!/usr/bin/env python3
"""Recorder and player throughput.

- recorder: ``qradar record`` in its own process, fed over zenoh TCP on 127.0.0.1 with
  the traffic of 100 sensors (raw 8 240 B + quantized 320 B + targets JSON per frame),
  at rising frame rates; a step passes when the file holds every message and the
  recorder counted no drop. Baseline in the same run: McapSink writing the same
  messages in process, without zenoh.
- player: ``replay --fast`` of the last file into a subscriber, messages/s.

    .venv/bin/python benchmarks/bench_record.py [--sensors 100] [--seconds 4]
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.bus import BusConfig  # noqa: E402
from pipeline.decode import Algo  # noqa: E402
from pipeline.errors import BusError  # noqa: E402
from pipeline.quantize import QuantizerConfig, quantize_frames  # noqa: E402
from pipeline.wire import QuantizedFrameMsg, RawFrameMsg, TargetsMsg, encode_quantized, encode_raw  # noqa: E402
from replay.mcapio import McapFile, McapSink  # noqa: E402
from replay.player import PlayConfig, play  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def messages(sensors: int) -> list[tuple[str, bytes]]:
    rng = np.random.default_rng(0)
    data = (0.3 * (rng.standard_normal((sensors, 512, 2)) + 1j * rng.standard_normal((sensors, 512, 2))))
    q = quantize_frames(data, QuantizerConfig(), np.arange(sensors))
    out = []
    for s in range(sensors):
        sid = f"r{s}"
        out.append((f"radar/{sid}/raw", encode_raw(RawFrameMsg(sid, 0, 0, 7, data[s].astype(np.complex64)))))
        out.append((f"radar/{sid}/quantized", encode_quantized(QuantizedFrameMsg(
            sid, 0, 0, 7, 1, q.alpha, float(q.delta[s]), 1, q.codes[s]))))
        t = TargetsMsg(sid, 0, 0, 7, Algo.PBP, 2, "quantized",
                       [{"range_m": 9.0, "angle_deg": 15.0, "x_m": 8.7, "y_m": 2.3, "amplitude": 0.4}] * 2, 0)
        out.append((f"radar/{sid}/targets", t.to_json()))
    return out


def baseline_sink(msgs, repeats: int) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        sink = McapSink(Path(tmp) / "b.mcap")
        t0 = time.perf_counter()
        for r in range(repeats):
            for k, p in msgs:
                sink.write(k, p, r, r, r)
        sink.close()
        return len(msgs) * repeats / (time.perf_counter() - t0)


def trial(msgs, rate: float, seconds: float, tmp: Path) -> dict:
    ep = f"tcp/127.0.0.1:{free_port()}"
    path = tmp / f"rec_{rate:g}.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "qradar", "record", "-o", str(path), "--listen", ep,
                             "--topics", "radar/*/*"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    session = None
    deadline = time.monotonic() + 20
    while session is None:
        try:
            session = BusConfig(connect=(ep,)).open()
        except BusError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)
    while not any(r.ok is not None for r in session.liveliness().get("radar/alive/record/**", timeout=1.0)):
        if time.monotonic() > deadline:
            raise RuntimeError(f"the recorder on {ep} did not come up within 20 s")
        time.sleep(0.1)
    pubs = {k: session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK) for k, _ in msgs}
    frames = int(rate * seconds)
    t0 = time.monotonic()
    late = 0
    for i in range(frames):
        due = t0 + i / rate
        d = due - time.monotonic()
        if d > 0:
            time.sleep(d)
        elif d < -1 / rate:
            late += 1
        for k, p in msgs:
            pubs[k].put(p)
    elapsed = time.monotonic() - t0
    time.sleep(2.5)
    session.close()
    proc.terminate()
    out, _ = proc.communicate(timeout=60)
    f = McapFile(path)
    written = sum(1 for ch, _ in f.messages() if not ch.topic.endswith(("pointcloud", "health")))
    counters = f.metadata_dict().get("qradar.recorder_counters", {})
    sent = frames * len(msgs)
    return {"frames_per_s_per_sensor": rate, "messages_per_s": round(sent / elapsed, 1), "sent": sent,
            "in_file": written, "dropped": int(counters.get("dropped", -1)), "late": late,
            "ok": written == sent and int(counters.get("dropped", -1)) == 0, "path": str(path)}


def bench_replay(path: str) -> dict:
    bus = BusConfig()
    session = bus.open()
    count = [0]
    lock = threading.Lock()

    def on(_s):
        with lock:
            count[0] += 1

    sub = session.declare_subscriber("bench/**", on)
    r = play(path, bus, PlayConfig(fast=True, prefix="bench"), session=session)
    time.sleep(0.5)
    sub.undeclare()
    session.close()
    return {"replay_fast_messages_per_s": round(r.published / r.seconds, 1), "published": r.published,
            "received": count[0]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sensors", type=int, default=100)
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--rates", type=float, nargs="+", default=[10, 20, 40, 80, 160])
    args = ap.parse_args()
    msgs = messages(args.sensors)
    out = {"sensors": args.sensors, "bytes_per_frame_set": sum(len(p) for _, p in msgs) // args.sensors,
           "mcapsink_in_process_messages_per_s": round(baseline_sink(msgs, 20), 1), "trials": []}
    best = None
    with tempfile.TemporaryDirectory() as tmp:
        for rate in args.rates:
            r = trial(msgs, rate, args.seconds, Path(tmp))
            print(json.dumps(r), file=sys.stderr, flush=True)
            out["trials"].append(r)
            if not r["ok"]:
                break
            best = r
        if best is not None:
            out["best"] = best
            out["recorder_over_mcapsink"] = round(best["messages_per_s"] / out["mcapsink_in_process_messages_per_s"], 3)
            out.update(bench_replay(best["path"]))
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
