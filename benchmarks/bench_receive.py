#!/usr/bin/env python3
"""CPU per message of receiving through zenoh-python, in a subscriber process, with the
messages paced (not in bursts) from a publisher process over zenoh TCP on 127.0.0.1.

Three ways to hand a message to a worker thread, each in a fresh subscriber process:

* ``notify``: a callback puts (key, payload) in a deque and notifies a condition the idle
  worker waits on (a wake-up per message when the worker waits, as a node's input queue);
* ``poll``: a callback appends to a deque, the worker empties it every 1 ms;
* ``fifo``: zenoh's ``FifoChannel`` handler, the worker drains it with ``try_recv``.

The figure is the subscriber process's CPU time (process_time, all its threads) over the
messages, in µs per message; the ratio is to ``poll`` of the same round.

    .venv/bin/python benchmarks/bench_receive.py [--messages 100000] [--rate 10000] [--rounds 2]

A JSON line a subscriber on stderr; the table, then the figures (``harness.emit``) on stdout.
"""

from __future__ import annotations

import argparse
import collections
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

from harness import emit

ROOT = Path(__file__).resolve().parents[1]

MODES = ("notify", "poll", "fifo")
SENSORS = 400  # keys radar/s<i>/quantized, as many sensors
SIZE = 320  # a 1-bit frame's payload, bytes


def publish(endpoint: str, messages: int, rate: float) -> None:
    import zenoh

    from pipeline.bus.session import BusConfig
    session = BusConfig(mode="client", connect=(endpoint,)).open()
    pubs = [session.declare_publisher(f"radar/s{i}/quantized", congestion_control=zenoh.CongestionControl.BLOCK)
            for i in range(SENSORS)]
    body = bytes(SIZE)
    t0 = time.monotonic()
    for k in range(messages):
        delay = t0 + k / rate - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        pubs[k % SENSORS].put(body)
    time.sleep(0.5)
    session.close()


def subscribe(mode: str, messages: int, rate: float) -> dict:
    import zenoh

    from pipeline.bus.session import BusConfig
    from harness import free_port
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = BusConfig(listen=(endpoint,)).open()
    got, done = [0], threading.Event()

    def count(n: int) -> None:
        got[0] += n
        if got[0] >= messages:
            done.set()

    if mode == "notify":
        queue, cond = collections.deque(), threading.Condition()

        def on(sample):
            item = (str(sample.key_expr), sample.payload.to_bytes())
            with cond:
                queue.append(item)
                cond.notify()
        sub = session.declare_subscriber("radar/*/quantized", on)

        def worker():
            while not done.is_set():
                with cond:
                    while not queue and not done.is_set():
                        cond.wait(0.1)
                    n = len(queue)
                    queue.clear()
                count(n)
    elif mode == "poll":
        queue = collections.deque()
        sub = session.declare_subscriber("radar/*/quantized",
                                         lambda s: queue.append((str(s.key_expr), s.payload.to_bytes())))

        def worker():
            while not done.is_set():
                n = len(queue)
                for _ in range(n):
                    queue.popleft()
                count(n)
                if not n:
                    time.sleep(0.001)
    else:
        sub = session.declare_subscriber("radar/*/quantized", zenoh.handlers.FifoChannel(1 << 16))

        def worker():
            while not done.is_set():
                n = 0
                while (sample := sub.try_recv()) is not None:
                    str(sample.key_expr), sample.payload.to_bytes()
                    n += 1
                count(n)
                if not n:
                    time.sleep(0.001)
    threading.Thread(target=worker, daemon=True).start()
    pub = subprocess.Popen([sys.executable, __file__, "--publish", endpoint, "--messages", str(messages),
                            "--rate", str(rate)])
    try:
        deadline = time.monotonic() + 30
        while not got[0] and time.monotonic() < deadline and pub.poll() is None:  # the publisher is connected
            time.sleep(0.005)
        c0, t0, n0 = time.process_time(), time.monotonic(), got[0]  # the idle wait before is not counted
        finished = done.wait(messages / rate * 3 + 30)
        c1, t1 = time.process_time(), time.monotonic()
        pub.wait(30)
    finally:
        if pub.poll() is None:
            pub.kill()
            pub.wait(10)
        sub.undeclare()
        session.close()
    counted = got[0] - n0
    return {"mode": mode, "received": got[0], "complete": finished, "wall_s": round(t1 - t0, 2),
            "cpu_us_per_msg": round((c1 - c0) / max(counted, 1) * 1e6, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--messages", type=int, default=100_000)
    ap.add_argument("--rate", type=float, default=10_000.0, help="messages per second")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--publish", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--subscribe", choices=MODES, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.publish:
        publish(args.publish, args.messages, args.rate)
        return
    if args.subscribe:
        print(json.dumps(subscribe(args.subscribe, args.messages, args.rate)), flush=True)
        return
    rows = []
    for r in range(args.rounds):
        base = None
        for mode in ("poll", "notify", "fifo"):  # each in a fresh process
            out = subprocess.run([sys.executable, __file__, "--subscribe", mode, "--messages", str(args.messages),
                                  "--rate", str(args.rate)], capture_output=True, text=True, timeout=600)
            row = json.loads(out.stdout.strip().splitlines()[-1]) if out.returncode == 0 else \
                {"mode": mode, "error": out.stderr.strip().splitlines()[-1:]}
            row["round"] = r
            if mode == "poll":
                base = row.get("cpu_us_per_msg")
            if base and row.get("cpu_us_per_msg"):
                row["ratio_to_poll"] = round(row["cpu_us_per_msg"] / base, 2)
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    print(f"\n{args.messages} messages of {SIZE} B at {args.rate:g}/s, subscriber CPU per message:\n")
    print("| round | hand-off | µs per message | × poll | complete |")
    print("|---|---|---|---|---|")
    for row in rows:
        print(f"| {row['round']} | {row['mode']} | {row.get('cpu_us_per_msg', '–')} | {row.get('ratio_to_poll', '–')} "
              f"| {row.get('complete', row.get('error'))} |")
    by_mode = {mode: [row for row in rows if row["mode"] == mode] for mode in ("poll", "notify", "fifo")}
    best = {mode: min((x["cpu_us_per_msg"] for x in mine if x.get("cpu_us_per_msg")), default=None)
            for mode, mine in by_mode.items()}
    emit({"messages": args.messages, "rate_msgs_per_s": args.rate, "payload_bytes": SIZE, "rounds": args.rounds,
          "cpu_us_per_msg_best": best,
          "ratio_best_to_poll_best": {m: round(v / best["poll"], 2) if v and best["poll"] else None
                                      for m, v in best.items()},
          "cpu_us_per_msg": {m: [x.get("cpu_us_per_msg") for x in mine] for m, mine in by_mode.items()},
          "ratio_to_poll": {m: [x.get("ratio_to_poll") for x in mine] for m, mine in by_mode.items()},
          "complete": {m: all(x.get("complete", False) for x in mine) for m, mine in by_mode.items()}})


if __name__ == "__main__":
    main()
