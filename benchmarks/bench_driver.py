#!/usr/bin/env python3
"""K-MD2 codec and driver throughput, each against a baseline in the same process.

- codec: StreamDecoder frames/s (a frame = 2 x (RESP + RADC + DONE), fed in 4 KiB
  chunks), against the bare ``np.frombuffer`` of the same RADC payloads;
- driver: frames/s of SensorSession over a real pty from the simulated K-MD2 running
  as fast as polled (rate 0), against the raw pty: the same bytes per frame pushed
  through a pty and read back, with no protocol.

    .venv/bin/python benchmarks/bench_driver.py [--frames 2000]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from harness import emit
from radar_driver.profile import DEFAULT_PROFILE
from radar_driver.protocol import Done, Radc, Resp, StreamDecoder, encode
from radar_driver.scene import resolve_scene
from radar_driver.session import SensorSession, SessionConfig
from radar_driver.simulator import SimulatorServer


LAYOUT = DEFAULT_PROFILE.radc  # one ramp per RADC: words (receivers, chirps, samples, I/Q) = (2, 1, 256, 2)
RAMP_LEN = len(encode(Resp(0))) + 8 + LAYOUT.payload_len + len(encode(Done(0)))  # RESP, RADC, DONE: bytes


def frame_bytes(seed: int) -> bytes:
    rng = np.random.default_rng(seed)
    out = b""
    for r in range(2):
        words = rng.integers(LAYOUT.min_word, LAYOUT.max_word + 1, LAYOUT.words_shape).astype(np.uint16)
        out += encode(Resp(0)) + encode(Radc(words, LAYOUT)) + encode(Done(2 * seed + r))
    return out


def bench_codec(frames: int) -> dict:
    stream = b"".join(frame_bytes(i % 64) for i in range(frames))
    chunks = [stream[i : i + 4096] for i in range(0, len(stream), 4096)]
    t0 = time.perf_counter()
    d = StreamDecoder()
    n = sum(len(d.feed(c)) for c in chunks)
    codec_s = time.perf_counter() - t0
    assert n == frames * 6, n
    # baseline: just view the RADC payloads as words
    words = LAYOUT.payload_len // 2
    payload_offsets = [len(encode(Resp(0))) + 8 + k * 2 * RAMP_LEN for k in range(frames)]
    t0 = time.perf_counter()
    for off in payload_offsets:
        np.frombuffer(stream, dtype="<u2", count=words, offset=off).max()
        np.frombuffer(stream, dtype="<u2", count=words, offset=off + RAMP_LEN).max()
    base_s = time.perf_counter() - t0
    return {"codec_frames_per_s": frames / codec_s, "codec_mb_per_s": len(stream) / codec_s / 1e6,
            "frombuffer_frames_per_s": frames / base_s, "codec_over_frombuffer": base_s / codec_s}


def bench_pty_raw(frames: int, frame_len: int) -> float:
    master, slave = os.openpty()
    import tty

    tty.setraw(slave)
    data = bytes(frame_len)
    t0 = time.perf_counter()
    for _ in range(frames):
        view = memoryview(data)
        got = 0
        while view:
            n = os.write(master, view[:4096])
            view = view[n:]
            while got < frame_len - len(view):
                got += len(os.read(slave, 65536))
    s = time.perf_counter() - t0
    os.close(master)
    os.close(slave)
    return frames / s


def bench_driver(frames: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        link = Path(tmp) / "kmd2"
        with SimulatorServer(resolve_scene("single"), link_path=link, rate_hz=0) as sim:
            with SensorSession(SessionConfig(str(link))) as s:
                list(s.frames(20))  # warm up
                t0 = time.perf_counter()
                got = sum(1 for _ in s.frames(frames))
                elapsed = time.perf_counter() - t0
            assert not sim.errors
    raw = bench_pty_raw(frames, len(frame_bytes(0)))
    return {"driver_frames_per_s": got / elapsed, "raw_pty_frames_per_s": raw,
            "driver_over_raw_pty": got / elapsed / raw, "driver_counters": s.counters.as_dict()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=2000)
    args = ap.parse_args()
    out = bench_codec(args.frames)
    out.update(bench_driver(args.frames))
    emit({k: (round(v, 3) if isinstance(v, float) else v) for k, v in out.items()})


if __name__ == "__main__":
    main()
