#!/usr/bin/env python3
"""Isolation under a flood: does one sensor (or a crowd of new ones) stall an honest one?

One case = fresh processes on 127.0.0.1, each a zenoh client of a ``qradar router``:

- ``qradar quantize --alpha 0.55`` and ``qradar localize --algo pbp --K 2`` (the nodes under test);
- the honest sensor, ``qradar source --sensors 1 --rate 20 --id-prefix honest`` (raw frames
  -> quantize -> localize);
- a flood (this script's ``flood`` command, a process of its own):
  - ``quantized``: valid 1-bit frames of the chamber scene (the project's own quantizer)
    on ``radar/evil/quantized`` at ``--rate`` messages/s, straight into localize;
  - ``raw``: valid raw frames on ``radar/evil/raw``, into quantize;
  - ``new-ids``: one valid raw frame from each of ``--ids`` new sensor ids
    (``radar/n<i>/raw``) at ``--rate``, into quantize;
- an observer in this process that stamps each honest targets message on arrival.

Reported: the honest sensor's latency (arrival at the observer - the frame's timestamp,
frames after ``--warmup`` s), its frames lost (sent by the source, never seen as targets),
and the flood's accounting at the node it hits: sent = taken in + refused at arrival
(over budget, unknown ids) + queue drops + invalid; ``unaccounted`` must be 0.

``restarts``: ``qradar source --frames 40`` started ``--restarts`` times against one router
and quantize; their RSS (VmRSS) after the first and after the last.

    .venv/bin/python benchmarks/bench_isolation.py [--case quantized raw new-ids restarts] \\
        [--seconds 30] [--rate 5000]

A JSON line a case, the table, then the figures as one JSON object (``harness.emit``), keyed
by case (``quantized``, ``raw``, ``new_ids``, ``restarts``).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import tempfile
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np

from harness import cpu_s, emit, free_port, rss_mb, wait_port
from streamlib import Proc

CASES = ("quantized", "raw", "new-ids", "restarts")
P99_GOAL_MS = 50.0
RSS_GOAL_MB = 10.0
#: a node's counters of frames it took in and did not pass on
LOSS_KINDS = ("over_budget", "refused", "drops", "invalid_frames", "decode_errors", "processing_errors")
HONEST = "honest0"
PY = sys.executable


# -- the flood ---------------------------------------------------------------------------------
def flood_payloads(kind: str, ids: int) -> tuple[list[bytes], bool]:
    """Payloads to send: a pool of valid frames of one sensor (``quantized``/``raw``; seq and
    timestamp rewritten per send) or one raw frame per new id (``new-ids``)."""
    from pipeline.dsp.quantize import QuantizerConfig, quantize_frames, sensor_dither_seeds
    from pipeline.wire import FrameHeaders, encode_quantized_batch, encode_raw_batch
    from radar_driver.scene import resolve_scene
    from radar_driver.source import SimSourceConfig, SimulatedSource
    src = SimulatedSource(SimSourceConfig(resolve_scene("chamber"), sensors=1, rate_hz=0.0, frames=8,
                                          id_prefix="evil"))
    frames = [f for batch in src.frame_batches() for f in batch]
    data = np.stack([f.data for f in frames])
    if kind == "new-ids":
        sids = [f"n{i}" for i in range(ids)]
        headers = FrameHeaders(sids, np.zeros(ids, np.uint64), np.zeros(ids, np.int64),
                               np.full(ids, frames[0].config_id, np.uint32))
        return encode_raw_batch(headers, np.broadcast_to(data[:1], (ids, *data.shape[1:]))), False
    headers = FrameHeaders(["evil"] * len(frames), np.arange(len(frames), dtype=np.uint64),
                           np.zeros(len(frames), np.int64), np.array([f.config_id for f in frames], np.uint32))
    if kind == "raw":
        return encode_raw_batch(headers, data), True
    cfg = QuantizerConfig(alpha=0.55)
    q = quantize_frames(data.astype(np.complex128), cfg, headers.seq,
                        dither_seed=sensor_dither_seeds(cfg.dither_seed, headers.sensor_id))
    return encode_quantized_batch(headers, q), True


def main_flood(args) -> None:
    """Publish ``args.kind`` messages at ``args.rate`` a second until SIGTERM; print what was sent."""
    import zenoh
    from pipeline.wire import COMMON_DTYPE
    pool, one_sensor = flood_payloads(args.kind, args.ids)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/shared_memory/enabled", "false")
    session = zenoh.open(conf)
    topic = "quantized" if args.kind == "quantized" else "raw"
    block = zenoh.CongestionControl.BLOCK
    pub = session.declare_publisher(f"radar/evil/{topic}", congestion_control=block) if one_sensor else None
    seq_at = COMMON_DTYPE.fields["seq"][1]
    ts_at = COMMON_DTYPE.fields["timestamp_ns"][1]
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    sent, t0 = 0, time.monotonic()
    limit = len(pool) if not one_sensor else None
    while not stop.is_set() and (limit is None or sent < limit):
        due = t0 + sent / args.rate
        delay = due - time.monotonic()
        if delay > 0:
            stop.wait(min(delay, 0.05))
            continue
        for _ in range(200):  # a burst, then the clock again
            if limit is not None and sent >= limit or time.monotonic() < t0 + sent / args.rate:
                break
            if one_sensor:
                buf = bytearray(pool[sent % len(pool)])
                buf[seq_at:seq_at + 8] = int(sent).to_bytes(8, "little")
                buf[ts_at:ts_at + 8] = time.time_ns().to_bytes(8, "little")
                pub.put(bytes(buf))
            else:
                payload = pool[sent]
                session.put(f"radar/n{sent}/raw", payload, congestion_control=block)
            sent += 1
    elapsed = time.monotonic() - t0
    session.close()
    print(json.dumps({"sent": sent, "elapsed_s": round(elapsed, 3), "rate": round(sent / max(elapsed, 1e-9), 1)}),
          flush=True)


# -- the observer ----------------------------------------------------------------------------------
class Observer:
    """A zenoh client that stamps the honest sensor's targets on arrival."""

    def __init__(self, endpoint: str):
        import zenoh
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("transport/shared_memory/enabled", "false")
        self.session = zenoh.open(conf)
        self.inbox: deque = deque()
        self.quantized: deque = deque()
        self.sub = self.session.declare_subscriber(
            f"radar/{HONEST}/targets", lambda s: self.inbox.append((time.time_ns(), s.payload.to_bytes())))
        self.qsub = self.session.declare_subscriber(  # where the delay forms: before or after quantize
            f"radar/{HONEST}/quantized", lambda s: self.quantized.append((time.time_ns(), s.payload.to_bytes()[:48])))

    def close(self) -> tuple[dict[int, int], dict[int, int]]:
        """seq -> latency (ns) of each honest targets message, and of each honest quantized frame."""
        from pipeline.wire import COMMON_DTYPE
        self.sub.undeclare()
        self.qsub.undeclare()
        self.session.close()
        out = {}
        for t, payload in self.inbox:
            obj = json.loads(payload)
            out[obj["seq"]] = t - obj["timestamp_ns"]
        quant = {}
        for t, head in self.quantized:
            h = np.frombuffer(head, dtype=COMMON_DTYPE)[0]
            quant[int(h["seq"])] = t - int(h["timestamp_ns"])
        return out, quant


# -- one case -----------------------------------------------------------------------------------------
def node_argv(cmd: str, endpoint: str, *extra: str) -> list[str]:
    return [PY, "-m", "qradar", cmd, "--mode", "client", "--connect", endpoint, *extra]


def start_router(logdir: Path) -> tuple[str, Proc]:
    """A ``qradar router`` on a free port of 127.0.0.1, listening: (its endpoint, the process)."""
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    router = Proc("router", [PY, "-m", "qradar", "router", "--listen", ep], logdir)
    try:
        wait_port(port)
    except RuntimeError:
        router.stop(10)
        raise
    return ep, router


def flood_case(kind: str, args, logdir: Path) -> dict:
    procs: list[Proc] = []
    try:
        ep, router = start_router(logdir)
        procs.append(router)
        quantize = Proc("quantize", node_argv("quantize", ep, "--alpha", "0.55", *args.node_args), logdir)
        localize = Proc("localize", node_argv("localize", ep, "--algo", "pbp", "--K", "2", *args.node_args,
                                              *args.localize_args),
                        logdir)
        procs += [quantize, localize]
        obs = Observer(ep)
        time.sleep(2.0)  # the nodes' subscriptions reach the router
        total = args.warmup + args.seconds + 2.0
        honest = Proc("honest", node_argv("source", ep, "--sensors", "1", "--rate", "20", "--id-prefix", "honest",
                                          "--duration", f"{total:.1f}"), logdir)
        procs.append(honest)
        time.sleep(args.warmup)
        flood = Proc("flood", [PY, __file__, "flood", "--connect", ep, "--kind", kind, "--rate", str(args.rate),
                               "--ids", str(args.ids)], logdir)
        procs.append(flood)
        t_flood = time.monotonic()
        cpu0 = {p.name: cpu_s(p.pid) for p in procs}
        deadline = t_flood + args.seconds
        while time.monotonic() < deadline and flood.alive():
            time.sleep(0.2)
        span = time.monotonic() - t_flood
        cpu = {p.name: round(100 * (cpu_s(p.pid) - cpu0[p.name]) / span) for p in procs
               if cpu0[p.name] is not None and cpu_s(p.pid) is not None}
        flood_out = flood.stop(30)
        flood_s = time.monotonic() - t_flood
        honest.popen.wait(60)
        honest_out = honest.stop()
        time.sleep(2.0)  # the last targets arrive
        lat, qlat = obs.close()
        q_out, l_out = quantize.stop(30), localize.stop(30)
    finally:
        for p in reversed(procs):
            p.stop(10)
    sent_honest = (honest_out or {}).get("frames_out")
    warm_seq = int(args.warmup * 20)
    ms = np.array([v for s, v in lat.items() if s >= warm_seq], dtype=float) / 1e6
    base = np.array([v for s, v in lat.items() if 20 <= s < warm_seq], dtype=float) / 1e6
    qms = np.array([v for s, v in qlat.items() if s >= warm_seq], dtype=float) / 1e6
    hit = l_out if kind == "quantized" else q_out
    flood_sent = (flood_out or {}).get("sent")
    acc = {}
    if hit and flood_sent is not None and sent_honest is not None:
        taken = hit["frames_out"] + sum(hit.get(k, 0) for k in LOSS_KINDS)
        acc = {"flood_excess_counted": sum(hit.get(k, 0) for k in ("over_budget", "refused", "drops")),
               "unaccounted": flood_sent + sent_honest - hit["frames_in"],  # sent, never counted in
               "node_balance": hit["frames_in"] - taken}  # counted in, neither out nor counted lost
    return {
        "case": kind, "flood_rate": args.rate, "flood_sent": (flood_out or {}).get("sent"),
        "flood_rate_achieved": (flood_out or {}).get("rate"), "flood_s": round(flood_s, 1),
        "honest_sent": sent_honest, "honest_targets": len(lat),
        "honest_lost": None if sent_honest is None else sent_honest - len(lat),
        "honest_p50_ms": round(float(np.percentile(ms, 50)), 1) if ms.size else None,
        "honest_p99_ms": round(float(np.percentile(ms, 99)), 1) if ms.size else None,
        "honest_max_ms": round(float(ms.max()), 1) if ms.size else None,
        "baseline_p50_ms": round(float(np.percentile(base, 50)), 1) if base.size else None,
        "baseline_p99_ms": round(float(np.percentile(base, 99)), 1) if base.size else None,
        "honest_quantized_p99_ms": round(float(np.percentile(qms, 99)), 1) if qms.size else None,
        "node": "localize" if kind == "quantized" else "quantize", "cpu_percent": cpu, **acc,
        "node_totals": hit, "quantize_totals": q_out, "localize_totals": l_out,
    }


def restarts_case(args, logdir: Path) -> dict:
    procs: list[Proc] = []
    try:
        ep, router = start_router(logdir)
        procs.append(router)
        quantize = Proc("quantize", node_argv("quantize", ep, "--alpha", "0.55"), logdir)
        procs.append(quantize)
        time.sleep(2.0)
        rss = []
        for i in range(args.restarts):
            src = Proc(f"source{i}", node_argv("source", ep, "--sensors", "1", "--rate", "0", "--frames", "40",
                                               "--id-prefix", "r"), logdir)
            src.popen.wait(120)
            src.stop()
            time.sleep(0.5)
            rss.append((rss_mb(router.pid), rss_mb(quantize.pid)))
    finally:
        for p in reversed(procs):
            p.stop(10)
    (r0, q0), (r1, q1) = rss[0], rss[-1]
    return {"case": "restarts", "restarts": args.restarts, "router_mb": [round(r0, 1), round(r1, 1)],
            "quantize_mb": [round(q0, 1), round(q1, 1)], "router_growth_mb": round(r1 - r0, 1),
            "quantize_growth_mb": round(q1 - q0, 1)}


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "flood":
        p = argparse.ArgumentParser(prog="bench_isolation.py flood")
        p.add_argument("flood")
        p.add_argument("--connect", required=True)
        p.add_argument("--kind", choices=("quantized", "raw", "new-ids"), required=True)
        p.add_argument("--rate", type=float, default=5000.0)
        p.add_argument("--ids", type=int, default=10000)
        main_flood(p.parse_args())
        return
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--case", nargs="+", choices=CASES, default=list(CASES))
    p.add_argument("--seconds", type=float, default=30.0, help="flood duration (s)")
    p.add_argument("--warmup", type=float, default=10.0, help="honest sensor alone (s): the baseline")
    p.add_argument("--rate", type=float, default=None, help="flood messages/s (default 5000; new-ids 1000)")
    p.add_argument("--ids", type=int, default=10000)
    p.add_argument("--restarts", type=int, default=20)
    p.add_argument("--node-args", default="", help="extra options for quantize and localize")
    p.add_argument("--localize-args", default="", help="extra options for localize, e.g. '--algo cml'")
    p.add_argument("--logdir", type=Path, default=None)
    args = p.parse_args()
    args.node_args = args.node_args.split()
    args.localize_args = args.localize_args.split()
    logdir = args.logdir or Path(tempfile.mkdtemp(prefix="bench-isolation-"))
    logdir.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in args.case:
        if case == "restarts":
            row = restarts_case(args, logdir)
        else:
            a = argparse.Namespace(**vars(args))
            a.rate = args.rate or (1000.0 if case == "new-ids" else 5000.0)
            if case == "new-ids":
                a.seconds = min(args.seconds, args.ids / a.rate)
            row = flood_case(case, a, logdir)
        print(json.dumps(row), flush=True)
        rows.append(row)
    print(table(rows))
    emit(figures(rows))
    print(f"logs: {logdir}", file=sys.stderr)


#: a flood case's figures (the table's), from its row
FLOOD_FIGURES = ("flood_rate", "flood_sent", "flood_rate_achieved", "flood_s", "honest_sent", "honest_targets",
                 "honest_lost", "honest_p50_ms", "honest_p99_ms", "honest_max_ms", "baseline_p50_ms",
                 "baseline_p99_ms", "honest_quantized_p99_ms", "node", "flood_excess_counted", "unaccounted",
                 "node_balance")


def figures(rows: list[dict]) -> dict:
    """The cases' figures, two levels: by case (``new-ids`` as ``new_ids``), each the table's
    numbers; a flood case's CPU as ``cpu_pct_<process>`` (% of a core over the flood)."""
    out = {}
    for r in rows:
        if r["case"] == "restarts":
            fig = {"restarts": r["restarts"], "router_mb_first": r["router_mb"][0], "router_mb_last": r["router_mb"][1],
                   "quantize_mb_first": r["quantize_mb"][0], "quantize_mb_last": r["quantize_mb"][1],
                   "router_growth_mb": r["router_growth_mb"], "quantize_growth_mb": r["quantize_growth_mb"]}
        else:
            units = {"flood_rate": "flood_rate_per_s", "flood_rate_achieved": "flood_rate_achieved_per_s"}
            fig = {units.get(k, k): r.get(k) for k in FLOOD_FIGURES}
            fig["over_budget_at_node"] = (r.get("node_totals") or {}).get("over_budget")
            fig |= {f"cpu_pct_{proc}": v for proc, v in r.get("cpu_percent", {}).items()}
        out[r["case"].replace("-", "_")] = fig | {"passed": passed(r)}
    return out


def passed(row: dict) -> bool:
    if row["case"] == "restarts":
        return row["router_growth_mb"] <= RSS_GOAL_MB and row["quantize_growth_mb"] <= RSS_GOAL_MB
    return (row["honest_p99_ms"] is not None and row["honest_p99_ms"] <= P99_GOAL_MS and row["honest_lost"] == 0
            and row.get("unaccounted") == 0 and row.get("node_balance") == 0)


def table(rows: list[dict]) -> str:
    out = ["| case | flood sent (rate) | honest p50 / p99 / max ms (alone: p50 / p99) | honest lost | flood's "
           "excess counted at | unaccounted | CPU % router / node / flood | pass |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["case"] == "restarts":
            out.append(f"| {r['restarts']} publisher restarts | — | router {r['router_mb'][0]} → {r['router_mb'][1]} MB, "
                       f"quantize {r['quantize_mb'][0]} → {r['quantize_mb'][1]} MB | — | — | — | — | "
                       f"{'yes' if passed(r) else 'NO'} |")
            continue
        cpu = r.get("cpu_percent", {})
        out.append(f"| {r['case']} | {r['flood_sent']} ({r['flood_rate_achieved']}/s) | {r['honest_p50_ms']} / "
                   f"{r['honest_p99_ms']} / {r['honest_max_ms']} ({r['baseline_p50_ms']} / {r['baseline_p99_ms']}) | "
                   f"{r['honest_lost']} of {r['honest_sent']} | {r['node']}: {r.get('flood_excess_counted')} | "
                   f"{r.get('unaccounted')} | {cpu.get('router')} / {cpu.get(r['node'])} / {cpu.get('flood')} | "
                   f"{'yes' if passed(r) else 'NO'} |")
    return "\n".join(out)


if __name__ == "__main__":
    main()
