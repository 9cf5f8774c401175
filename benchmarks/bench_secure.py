#!/usr/bin/env python3
"""What ``--secure`` (mutual TLS + zenoh access control) costs on the bus.

A ``qradar router`` in its own process; a publisher and a subscriber, zenoh clients in
this process, exchange raw frames (8 240 B) as fast as the publisher can put them with
``CongestionControl.BLOCK``. The same in plain TCP (the baseline) and with ``--secure``
(certificates made by ``qradar security init`` in a temporary directory), alternating
``--rounds`` times; prints messages/s of each and the ratio secure / plain.

    .venv/bin/python benchmarks/bench_secure.py [--messages 50000] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from harness import emit, free_port
from pipeline.bus.session import BusConfig
from pipeline.errors import BusError
from pipeline.bus.security import SecureConfig
from pipeline.wire import RawFrameMsg, encode_raw


def connect(bus: BusConfig, timeout_s: float = 20.0) -> zenoh.Session:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return bus.open()
        except BusError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def trial(pki: Path | None, n: int) -> float:
    """Messages per second from a publisher client to a subscriber client through a router."""
    proto = "tls" if pki is not None else "tcp"
    ep = f"{proto}/127.0.0.1:{free_port()}"
    argv = [sys.executable, "-m", "qradar", "router", "--listen", ep]
    if pki is not None:
        argv += ["--secure", str(pki)]
    router = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    sec = (lambda name: SecureConfig(pki, name)) if pki is not None else (lambda name: None)
    try:
        sub = connect(BusConfig(mode="client", connect=(ep,), secure=sec("viewer")))
        pub = connect(BusConfig(mode="client", connect=(ep,), secure=sec("sensor-b0")))
        got, done = [0], threading.Event()

        def on(_sample):
            got[0] += 1
            if got[0] >= n:
                done.set()

        subscriber = sub.declare_subscriber("radar/b0/raw", on)
        publisher = pub.declare_publisher("radar/b0/raw", congestion_control=zenoh.CongestionControl.BLOCK)
        payload = encode_raw(RawFrameMsg("b0", 0, 0, 7, np.zeros((512, 2), np.complex64)))
        time.sleep(1.0)  # the subscription has reached the publisher
        t0 = time.perf_counter()
        for _ in range(n):
            publisher.put(payload)
        done.wait(60)
        rate = got[0] / (time.perf_counter() - t0)
        subscriber.undeclare()
        for s in (pub, sub):
            s.close()
        return rate
    finally:
        router.terminate()
        router.wait(20)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--messages", type=int, default=50000)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="qradar-bench-secure-") as tmp:
        pki = Path(tmp) / "pki"
        subprocess.run([sys.executable, "-m", "qradar", "security", "init", str(pki), "--sensors", "b0"],
                       check=True, stdout=subprocess.DEVNULL)
        plain, secure = [], []
        for r in range(args.rounds):
            plain.append(trial(None, args.messages))
            secure.append(trial(pki, args.messages))
            print(json.dumps({"round": r, "plain_msgs_s": round(plain[-1]), "secure_msgs_s": round(secure[-1])}),
                  file=sys.stderr, flush=True)
    p, s = float(np.median(plain)), float(np.median(secure))
    size = len(encode_raw(RawFrameMsg("b0", 0, 0, 7, np.zeros((512, 2), np.complex64))))
    emit({"messages": args.messages, "bytes": size, "plain_msgs_s": round(p),
          "secure_msgs_s": round(s), "secure_over_plain": round(s / p, 3)}, indent=1)


if __name__ == "__main__":
    main()
