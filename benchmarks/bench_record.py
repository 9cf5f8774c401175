#!/usr/bin/env python3
"""Recorder and player throughput.

- recorder: ``qradar record`` in its own process, fed over zenoh TCP on 127.0.0.1 with
  the traffic of 100 sensors (raw 8 240 B + quantized 320 B + targets JSON per frame),
  at rising frame rates; a step passes when the file holds every message and the
  recorder counted no drop. Baseline in the same run: McapSink writing the same
  messages in process, without zenoh.
- player: ``replay --fast`` of the last file into a subscriber, messages/s.
- ``--index``: what a recording's index costs per chunk, on a real recording: ``qradar
  run --sensors N --record`` (simulated sensors: raw, quantized, targets, pointcloud and
  health of each) for ``--seconds``, or ``--index-of FILE``. In the file: the message
  index records after each chunk and the chunk index records of the summary, and the
  file's size minus its chunk records, per chunk. In memory: what the ``mcap`` writer
  keeps until the file ends (a chunk index per chunk), measured with tracemalloc while
  McapSink writes the same chunks again (the growth from one pass over them to three).
- ``--long FILE``: write a long recording (``--minutes``, default 60) of what ``qradar run
  --record`` records of one simulated sensor at 20 frames/s (raw, quantized, PBP targets,
  pointcloud, the nodes' health at 1 Hz; the chamber scene), with the metadata of a real run
  (recordings/chamber.mcap's) and a chunk a recorded second, as the recorder flushes; made
  in process (McapSink), faster than real time: the subject of bench_reading.py.

    .venv/bin/python benchmarks/bench_record.py [--sensors 100] [--seconds 4]
    .venv/bin/python benchmarks/bench_record.py --index [--sensors 3] [--seconds 20] [--index-of FILE]
    .venv/bin/python benchmarks/bench_record.py --long /tmp/hour.mcap [--minutes 60]

The recorder and player figures end with one JSON object (``harness.emit``, which also
writes the suite's result file); ``--index`` and ``--long`` print theirs only.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import struct
import subprocess
import sys
import tempfile
import threading
import time
import tracemalloc
from collections import Counter
from pathlib import Path

import numpy as np
import zenoh
from mcap.opcode import Opcode
from mcap.records import Channel, Message, MessageIndex
from mcap.stream_reader import StreamReader

from harness import emit, free_port
from pipeline.bus.session import BusConfig
from pipeline.dsp.decode import Algo
from pipeline.errors import BusError
from pipeline.keys import DERIVED_TOPICS
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from pipeline.wire import QuantizedFrameMsg, RawFrameMsg, TargetsMsg, encode_quantized, encode_raw
from radar_driver.model import RadarConfig
from replay.mcapio import McapFile, McapSink
from replay.player import PlayConfig, play


#: the frames' radar config id: the default K-MD2's (M = 512), which the recorder, as the nodes, announces
CONFIG_ID = RadarConfig().config_id()


def messages(sensors: int) -> list[tuple[str, bytes]]:
    rng = np.random.default_rng(0)
    data = (0.3 * (rng.standard_normal((sensors, 512, 2)) + 1j * rng.standard_normal((sensors, 512, 2))))
    q = quantize_frames(data, QuantizerConfig(), np.arange(sensors))
    out = []
    for s in range(sensors):
        sid = f"r{s}"
        out.append((f"radar/{sid}/raw", encode_raw(RawFrameMsg(sid, 0, 0, CONFIG_ID, data[s].astype(np.complex64)))))
        out.append((f"radar/{sid}/quantized", encode_quantized(QuantizedFrameMsg(
            sid, 0, 0, CONFIG_ID, 1, q.alpha, float(q.delta[s]), 1, q.codes[s]))))
        t = TargetsMsg(sid, 0, 0, CONFIG_ID, Algo.PBP, 2, "quantized",
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
    # what was sent: not what the recorder derives (pointcloud, scene, profile) nor the nodes' health
    written = sum(1 for ch, _ in f.messages() if ch.topic.rsplit("/", 1)[-1] not in (*DERIVED_TOPICS, "health"))
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


def record_sizes(path: Path) -> tuple[Counter, Counter, int]:
    """(bytes, count) of the file's top-level records by opcode name, and its size."""
    data = Path(path).read_bytes()
    size, count = Counter(), Counter()
    pos = 8  # after the magic
    while pos + 9 <= len(data) - 8:  # opcode (1 B), length (8 B), content; the closing magic
        name, n = Opcode(data[pos]).name, 9 + struct.unpack_from("<Q", data, pos + 1)[0]
        size[name] += n
        count[name] += 1
        pos += n
    return size, count, len(data)


def _rewrite(path: Path, sink: McapSink) -> int:
    """Write every message of ``path`` into ``sink``, flushing where each of its chunks
    ended (the message index records that follow a chunk); the chunks written."""
    chunks, pending, topics = 0, 0, {}
    with open(path, "rb") as fh:
        for rec in StreamReader(fh).records:
            if isinstance(rec, Channel):
                topics[rec.id] = rec.topic
            elif isinstance(rec, Message):
                sink.write(topics[rec.channel_id], rec.data, rec.log_time, rec.publish_time, rec.sequence)
                pending += 1
            elif isinstance(rec, MessageIndex) and pending:
                sink.flush()
                chunks, pending = chunks + 1, 0
    if pending:
        sink.flush()
        chunks += 1
    return chunks


def index_cost(path: Path) -> dict:
    """What the index of the recording ``path`` costs per chunk: in the file (message
    index and chunk index records; the file minus its chunk records) and in the memory of
    the writer until the file ends (the traced memory added by writing its chunks two
    more times, per chunk)."""
    size, count, total = record_sizes(path)
    chunks = count["CHUNK"]
    index = size["MESSAGE_INDEX"] + size["CHUNK_INDEX"]
    with tempfile.TemporaryDirectory() as tmp:
        sink = McapSink(Path(tmp) / "copy.mcap")
        tracemalloc.start()
        try:
            first = _rewrite(path, sink)
            gc.collect()
            held_1 = tracemalloc.get_traced_memory()[0]
            more = _rewrite(path, sink) + _rewrite(path, sink)
            gc.collect()
            held_3 = tracemalloc.get_traced_memory()[0]
        finally:
            tracemalloc.stop()
            sink.close()
    f = McapFile(path)
    messages = f.scan()
    return {"path": str(path), "bytes": total, "chunks": chunks, "messages": messages,
            "channels": len(f.channels), "messages_per_chunk": round(messages / chunks, 1),
            "message_index_records_per_chunk": round(count["MESSAGE_INDEX"] / chunks, 1),
            "file_index_bytes_per_chunk": round(index / chunks),
            "file_message_index_bytes_per_chunk": round(size["MESSAGE_INDEX"] / chunks),
            "file_chunk_index_bytes_per_chunk": round(size["CHUNK_INDEX"] / chunks),
            "file_minus_chunks_bytes_per_chunk": round((total - size["CHUNK"]) / chunks),
            "memory_index_bytes_per_chunk": round((held_3 - held_1) / more), "chunks_rewritten": first + more}


def record_run(path: Path, sensors: int, seconds: float) -> None:
    """A real recording: ``qradar run --sensors N --duration S --record path``."""
    proc = subprocess.run([sys.executable, "-m", "qradar", "run", "--sensors", str(sensors), "--duration", str(seconds),
                           "--record", str(path), "--json"], capture_output=True, text=True, timeout=seconds + 120,
                          stdin=subprocess.DEVNULL, cwd=Path(__file__).resolve().parents[1],
                          env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    if proc.returncode != 0:
        raise RuntimeError(f"qradar run failed ({proc.returncode}): {proc.stderr[-2000:]}")


#: a recording of a real run, whose metadata a long recording takes
CHAMBER = Path(__file__).resolve().parents[1] / "recordings" / "chamber.mcap"


def write_long_recording(path: Path, seconds: float, rate_hz: float = 20.0, sensor: str = "kmd2-0",
                         start_ns: int = 1_795_290_714_000_000_000, progress: bool = True) -> dict:
    """A recording of ``seconds`` of one simulated sensor as ``qradar run --record`` writes it
    (see the module's docstring), made in process; returns {"path", "bytes", "messages",
    "seconds_to_make"}. Frames: the chamber scene's, with its noise; targets: PBP on the
    quantized frames; times: the frame clock from ``start_ns``, each message logged 5-30 ms
    after its frame, health at each second's end."""
    from pipeline.dsp.decode import DecoderConfig, decode_batch
    from pipeline.wire import FrameHeaders, HealthMsg, decode_targets, encode_quantized_batch, encode_raw_batch, \
        encode_targets_batch
    from radar_driver.scene import resolve_scene
    from replay.mcapio import pointcloud_json

    t0 = time.perf_counter()
    scene = resolve_scene("chamber")
    radar = scene.radar
    qcfg = QuantizerConfig(alpha=0.55)
    rng = np.random.default_rng(0)
    per_s = int(round(rate_hz))
    meta = McapFile(CHAMBER)
    meta.scan()
    sink = McapSink(Path(path))
    try:
        for name, data in meta.metadata_dict().items():
            if name != "qradar.recorder_counters":
                sink.metadata(name, data)
        seq = 0
        n_seconds = int(seconds)
        for s in range(n_seconds):
            seqs = np.arange(seq, seq + per_s)
            t_s = seqs / rate_hz
            ramp_t = np.repeat(t_s, radar.ramps_per_frame) + np.tile(np.arange(radar.ramps_per_frame), per_s) * 0.025
            frames = scene.ramps(ramp_t, rng).reshape(per_s, -1, 2)
            stamp = start_ns + (t_s * 1e9).astype(np.int64)
            headers = FrameHeaders([sensor] * per_s, seqs, stamp, [radar.config_id()] * per_s)
            q = quantize_frames(frames, qcfg, seqs)
            det = decode_batch(q, radar, 2, DecoderConfig(algo=Algo.PBP))
            published = stamp + 25_000_000
            raw = encode_raw_batch(headers, frames.astype(np.complex64))
            quantized = encode_quantized_batch(headers, q)
            targets = encode_targets_batch(headers, det, "pbp", 2, "quantized", published)
            for i in range(per_s):
                ts = int(stamp[i])
                sink.write(f"radar/{sensor}/raw", raw[i], ts + 5_000_000, ts, seq + i)
                sink.write(f"radar/{sensor}/quantized", quantized[i], ts + 12_000_000, ts, seq + i)
                sink.write(f"radar/{sensor}/targets", targets[i], ts + 28_000_000, ts, seq + i)
                sink.write(f"radar/{sensor}/pointcloud", pointcloud_json(decode_targets(targets[i])),
                           ts + 28_000_000, ts, seq + i)
            end_ns = start_ns + (s + 1) * 1_000_000_000 - 1_000_000
            for node in ("driver", "quantize", "localize", "record"):
                h = HealthMsg(node, sensor, end_ns, frames_in=seq + per_s, frames_out=seq + per_s,
                              latency_ms={"p50": 28.0, "p99": 60.0})
                sink.write(f"radar/{sensor}/health", h.to_json(), end_ns, end_ns, s)
            sink.flush()  # the recorder's chunk a second
            seq += per_s
            if progress and (s + 1) % 300 == 0:
                print(f"long recording: {s + 1} of {n_seconds} s written ({sink.size / 1e6:.0f} MB, "
                      f"{time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
        sink.metadata("qradar.recorder_counters", {
            "received": str(sink.messages), "written": str(sink.readable), "dropped": "0", "lost": "0",
            "verify_errors": "0", "refused_time": "0", "refused_size": "0", "refused_shape": "0",
            "refused_topic": "0"})
        sink.close()
    except BaseException:
        sink.abort()
        Path(path).unlink(missing_ok=True)
        raise
    return {"path": str(path), "bytes": Path(path).stat().st_size, "messages": sink.messages,
            "recorded_s": n_seconds, "seconds_to_make": round(time.perf_counter() - t0, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sensors", type=int, default=None, help="default 100 (3 with --index)")
    ap.add_argument("--seconds", type=float, default=None, help="default 4 (20 with --index)")
    ap.add_argument("--rates", type=float, nargs="+", default=[10, 20, 40, 80, 160])
    ap.add_argument("--index", action="store_true", help="measure the index cost per chunk of a real recording "
                    "(qradar run --sensors N for --seconds; defaults 3 and 20 with --index)")
    ap.add_argument("--index-of", type=Path, default=None, metavar="FILE", help="--index of this recording")
    ap.add_argument("--long", type=Path, default=None, metavar="FILE",
                    help="write a long recording of one simulated sensor (a new FILE; keep it out of the repository)")
    ap.add_argument("--minutes", type=float, default=60.0, help="with --long: the recorded minutes")
    args = ap.parse_args()
    if args.long is not None:
        print(json.dumps(write_long_recording(args.long, args.minutes * 60)), flush=True)
        return
    if args.index or args.index_of:
        if args.index_of is not None:
            print(json.dumps(index_cost(args.index_of), indent=1))
            return
        sensors = 3 if args.sensors is None else args.sensors
        seconds = 20.0 if args.seconds is None else args.seconds
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "run.mcap"
            record_run(path, sensors, seconds)
            print(json.dumps({"sensors": sensors, "seconds": seconds, **index_cost(path)}, indent=1))
        return
    args.sensors = 100 if args.sensors is None else args.sensors
    args.seconds = 4.0 if args.seconds is None else args.seconds
    msgs = messages(args.sensors)
    out = {"sensors": args.sensors, "seconds": args.seconds,
           "bytes_per_frame_set": sum(len(p) for _, p in msgs) // args.sensors,
           "mcapsink_in_process_messages_per_s": round(baseline_sink(msgs, 20), 1)}
    trials = []
    best = None
    with tempfile.TemporaryDirectory() as tmp:
        for rate in args.rates:
            r = trial(msgs, rate, args.seconds, Path(tmp))
            print(json.dumps(r), file=sys.stderr, flush=True)
            trials.append(r)
            if not r["ok"]:
                break
            best = r
        # each trial's figures as a list, one a rate in order (two levels; the file's path left out)
        out["trials"] = {k: [t[k] for t in trials] for k in trials[0] if k != "path"} if trials else {}
        if best is not None:
            out["best"] = {k: v for k, v in best.items() if k != "path"}
            out["recorder_over_mcapsink"] = round(best["messages_per_s"] / out["mcapsink_in_process_messages_per_s"], 3)
            out.update(bench_replay(best["path"]))
    emit(out, indent=1)


if __name__ == "__main__":
    main()
