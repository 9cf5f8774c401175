#!/usr/bin/env python3
"""Shared parts of the streaming benchmarks (bench_stream.py, bench_multihost.py).

One *step* = fresh node processes (a hub, quantize and localize nodes, a sink), a
simulated source of N sensors at 20 frames/s for warm-up + measured seconds, then every
process stopped and its totals read. Where each process runs and how it reaches the hub
is a :class:`Topology` (loopback here; network namespaces in bench_multihost.py).

The sink is a process of its own (``python streamlib.py sink ...``): its zenoh callback
only appends the payload to a list, a thread parses the list every 0.2 s, so it cannot
drop (the localizers publish with BLOCK: a slow sink would slow them, which its own CPU
figure shows). It counts targets per (sensor, seq) and the latency published_ns -
timestamp_ns of frames past the warm-up. ``bare-pub`` / ``bare-sub`` are the bare-zenoh
baseline: the step's messages (same count per second, same sizes) between two processes.
``player`` sends frames made before the step (:func:`make_premade`) in place of ``qradar
source``, with the same pacing, each timestamp rewritten to its send time.

CPU per process: utime + stime from /proc/<pid>/stat over the measured window (the
source's warm-up excluded), as % of one core.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import shlex
import signal
import subprocess
import sys
import tempfile
import threading
import time
from array import array
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from harness import cpu_s, free_port, wait_port

ROOT = Path(__file__).resolve().parents[1]

RATE_HZ = 20.0
MAX_P99_MS = 20.0
#: node totals that must stay 0 for a step to pass
LOSS_COUNTERS = ("drops", "decode_errors", "invalid_frames", "processing_errors", "frames_missing", "seq_resets",
                 "over_budget", "refused",
                 "worker_restarts")
#: a sink above this CPU (% of one core) may be holding the chain back: the step is flagged
SINK_CPU_FLAG = 80.0
#: the source must send at least this fraction of the offered frames per second
PACE_MIN = 0.98
#: the simulated sensors' ids are <prefix>0, <prefix>1, ...
SENSOR_ID_PREFIX = "b"
TARGETS_BYTES = 330  # a targets message of K = 2 (JSON), for the bare baseline

#: a step's busy process (``--busy``): a loop its own command line names (a test finds it by that,
#: not another busy loop on the host)
BUSY_LOOP = "while True: pass  # bench_stream busy"


# -- processes -----------------------------------------------------------------------------
def last_json(text: str) -> dict | None:
    """The last line of ``text`` that is a JSON object."""
    for line in reversed(text.strip().splitlines()):
        line = line.strip()
        if line.startswith("{"):
            try:
                return json.loads(line)
            except json.JSONDecodeError:
                continue
    return None


class Proc:
    """A benchmark process: stdout and stderr into files of ``logdir``."""

    def __init__(self, name: str, argv: list[str], logdir: Path, cwd: Path = ROOT):
        self.name = name
        self.argv = argv
        self.out_path, self.err_path = logdir / f"{name}.out", logdir / f"{name}.err"
        self._out, self._err = open(self.out_path, "w"), open(self.err_path, "w")
        env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}
        self.popen = subprocess.Popen(argv, stdout=self._out, stderr=self._err, stdin=subprocess.DEVNULL,
                                      cwd=cwd, env=env, start_new_session=True)
        self.pid = self.popen.pid
        self.totals: dict | None = None

    def alive(self) -> bool:
        return self.popen.poll() is None

    def stdout(self) -> str:
        return self.out_path.read_text()

    def stderr_tail(self, n: int = 3) -> str:
        lines = [ln for ln in self.err_path.read_text(errors="replace").splitlines() if ln.strip()]
        return " | ".join(lines[-n:])

    def stop(self, timeout_s: float = 15.0) -> dict | None:
        """SIGTERM (if still running), wait up to ``timeout_s``, then SIGKILL; the last JSON
        line of its stdout (a node's totals)."""
        if self.alive():
            self.popen.send_signal(signal.SIGTERM)
        try:
            self.popen.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.kill()
        for f in (self._out, self._err):
            f.close()
        self.totals = last_json(self.stdout())
        return self.totals

    def kill(self) -> None:
        if self.alive():
            try:
                os.killpg(self.pid, signal.SIGKILL)  # its own session: the process and any child
            except ProcessLookupError:
                pass
        try:
            self.popen.wait(10)
        except subprocess.TimeoutExpired:
            pass


# -- what a step runs, and where ------------------------------------------------------------
@dataclass(frozen=True)
class StepSpec:
    """One trial. case: central (source raw -> quantize -> localize) or edge (source
    --quantized -> localize). send: burst (every sensor at the tick) or spread."""

    case: str
    send: str
    algo: str
    sensors: int
    seconds: float
    warmup_s: float = 3.0
    localizers: int = 1
    quantizers: int = 1
    alpha: float = 1.0
    bits: int = 1
    k: int = 2
    scene: str = "chamber"
    hub: str = "node"  # node: the first downstream node listens; router: a qradar router
    baseline_s: float = 0.0  # > 0: the bare-zenoh baseline first, that long
    source_args: tuple[str, ...] = ()
    #: edge only: a file of frames made before the step (:func:`make_premade`), sent by a
    #: ``player`` instead of ``qradar source`` (the sensors' work done off this host)
    premade: str = ""
    #: processes that spin on the CPU for the whole step (a busy host), started first
    busy: int = 0
    quantize_args: tuple[str, ...] = ()
    localize_args: tuple[str, ...] = ()

    @property
    def frames(self) -> int:
        return int(round((self.warmup_s + self.seconds) * RATE_HZ))

    @property
    def warmup_frames(self) -> int:
        return int(round(self.warmup_s * RATE_HZ))

    def label(self) -> str:
        shards = (f" {self.quantizers}q" if self.case == "central" and self.quantizers > 1 else "") + \
            (f" {self.localizers}l" if self.localizers > 1 else "")
        return (f"{self.case}/{self.send}/{self.algo}{shards}" + (" premade" if self.premade else "")
                + (f" +{self.busy} busy" if self.busy else ""))


class Topology:
    """Where processes run and how they reach each other: a command prefix per role
    (e.g. ``ip netns exec NS``) and the zenoh endpoint each role connects to. Roles:
    router, source, quantize, localize, sink, bare-pub, bare-sub."""

    python = sys.executable

    def prefix(self, role: str) -> list[str]:
        return []

    def listen(self, role: str) -> list[str]:
        """Endpoints the hub (a router, or the listening node) listens on."""
        raise NotImplementedError

    def connect(self, role: str) -> str:
        raise NotImplementedError

    def argv(self, role: str, args: list[str]) -> list[str]:
        return [*self.prefix(role), self.python, *args]

    def wait_listening(self, role: str, alive, timeout_s: float = 30.0) -> bool:
        """Wait until the hub ``role`` listens (here: a fixed second; a topology that can
        reach its port does better)."""
        time.sleep(1.0)
        return alive()


class Loopback(Topology):
    """Everything on this host, zenoh TCP on 127.0.0.1 at one free port."""

    def __init__(self):
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.bare = f"tcp/127.0.0.1:{free_port()}"

    def listen(self, role: str) -> list[str]:
        return [self.bare if role.startswith("bare") else self.endpoint]

    def connect(self, role: str) -> str:
        return self.bare if role.startswith("bare") else self.endpoint

    def wait_listening(self, role: str, alive, timeout_s: float = 30.0) -> bool:
        """Until the hub's port takes a TCP connection (a localizer loading cml's kernels
        takes a while) or its process ended."""
        host, port = self.listen(role)[0].split("/", 1)[1].rsplit(":", 1)
        try:
            wait_port(int(port), host, timeout_s, alive)
        except RuntimeError:
            return False
        return True


@functools.lru_cache(maxsize=None)
def frame_sizes(spec: StepSpec) -> dict[str, int]:
    """Bytes of one raw and one quantized frame of the step's scene, and a targets message."""
    from pipeline.dsp.quantize import packed_size
    from pipeline.wire import HEADER_LEN, QUANT_HEADER_LEN
    from radar_driver.scene import resolve_scene
    radar = resolve_scene(spec.scene).radar
    m = radar.ramps_per_frame * radar.samples_per_ramp
    return {"raw": HEADER_LEN + m * 16, "quantized": QUANT_HEADER_LEN + packed_size(4 * m, spec.bits),
            "targets": TARGETS_BYTES}


# -- one step -------------------------------------------------------------------------------
def _bus(topo: Topology, role: str, listener: bool) -> list[str]:
    if listener:
        return [a for ep in topo.listen(role) for a in ("--listen", ep)]
    return ["--mode", "client", "--connect", topo.connect(role)]


def _quant_args(spec: StepSpec) -> list[str]:
    return ["--alpha", str(spec.alpha), "--bits", str(spec.bits)]


def _shard(i: int, n: int) -> list[str]:
    return ["--shard", f"{i}/{n}"] if n > 1 else []


def node_commands(spec: StepSpec, topo: Topology, sid_prefix: str) -> tuple[list[tuple[str, str, list[str]]], list]:
    """(name, role, argv) of the nodes started before the source, hub first; and the
    source's (name, role, argv)."""
    q = ["-m", "qradar"]
    nodes: list[tuple[str, str, list[str]]] = []
    hub_is_router = spec.hub == "router"
    if hub_is_router:
        nodes.append(("router", "router", q + ["router", *_bus(topo, "router", True)]))
    if spec.case == "central":
        for i in range(spec.quantizers):
            listener = not hub_is_router and not nodes
            nodes.append((f"quantize{i}", "quantize",
                          q + ["quantize", *_quant_args(spec), *_shard(i, spec.quantizers),
                               *spec.quantize_args, *_bus(topo, "quantize", listener)]))
    for i in range(spec.localizers):
        listener = not hub_is_router and not nodes
        nodes.append((f"localize{i}", "localize",
                      q + ["localize", "--algo", spec.algo, "--K", str(spec.k), *_shard(i, spec.localizers),
                           *spec.localize_args, *_bus(topo, "localize", listener)]))
    src = q + ["source", "--scene", spec.scene, "--sensors", str(spec.sensors), "--rate", str(RATE_HZ),
               "--frames", str(spec.frames), "--id-prefix", sid_prefix, *spec.source_args]
    if spec.case == "edge":
        src += ["--quantized", *_quant_args(spec)]
    if spec.send == "spread":
        src += ["--send", "spread"]
    if spec.premade:
        if spec.case != "edge":
            raise ValueError("premade frames are 1-bit frames: the edge case only")
        src = [str(Path(__file__).resolve()), "player", "--file", spec.premade, "--sensors", str(spec.sensors),
               "--frames", str(spec.frames), "--id-prefix", sid_prefix, "--send", spec.send]
    src += _bus(topo, "source", False)
    return [(n, r, topo.argv(r, a)) for n, r, a in nodes], ("source", "source", topo.argv("source", src))


def _sink_argv(spec: StepSpec, topo: Topology, sid_prefix: str) -> list[str]:
    expect = {"localize": spec.localizers}
    if spec.case == "central":
        expect["quantize"] = spec.quantizers
    return topo.argv("sink", [str(Path(__file__).resolve()), "sink", "--connect", topo.connect("sink"),
                              "--expect", ",".join(f"{k}={v}" for k, v in expect.items()),
                              "--id-prefix", sid_prefix, "--sensors", str(spec.sensors),
                              "--frames", str(spec.frames), "--warmup", str(spec.warmup_frames)])


def _read_line(proc: Proc, timeout_s: float, pred: Callable[[dict], bool]) -> dict | None:
    """Poll ``proc``'s stdout file for a JSON line satisfying ``pred`` (bounded)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for line in proc.stdout().splitlines():
            if line.startswith("{"):
                try:
                    obj = json.loads(line)
                except json.JSONDecodeError:
                    continue
                if pred(obj):
                    return obj
        if not proc.alive():
            return None
        time.sleep(0.1)
    return None


def _wait_text(proc: Proc, text: str, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.alive():
        if text in proc.stdout():
            return True
        time.sleep(0.1)
    return text in proc.stdout()


def run_step(spec: StepSpec, topo: Topology, logdir: Path | None = None, progress: bool = False) -> dict:
    """Run one step with fresh processes; its figures (see module doc) and ``ok``."""
    row: dict = {"case": spec.case, "send": spec.send, "algo": spec.algo, "sensors": spec.sensors, "busy": spec.busy,
                 "localizers": spec.localizers, "quantizers": spec.quantizers if spec.case == "central" else 0,
                 "seconds": spec.seconds, "warmup_s": spec.warmup_s, "hub": spec.hub,
                 "offered_fps": spec.sensors * RATE_HZ, "loadavg_start": [round(x, 2) for x in os.getloadavg()]}
    own_logdir = logdir is None
    logdir = Path(tempfile.mkdtemp(prefix="qr-bench-")) if own_logdir else logdir
    logdir.mkdir(parents=True, exist_ok=True)
    if spec.baseline_s > 0:
        row["bare"] = run_bare(spec, topo, logdir)
    sid_prefix = SENSOR_ID_PREFIX
    node_cmds, src_cmd = node_commands(spec, topo, sid_prefix)
    procs: list[Proc] = []
    reasons: list[str] = []
    busy = [Proc(f"busy{i}", [sys.executable, "-c", BUSY_LOOP], logdir) for i in range(spec.busy)]
    try:
        for i, (name, role, argv) in enumerate(node_cmds):
            procs.append(Proc(name, argv, logdir))
            if i == 0:  # the hub listens before anyone connects (a client that finds none exits)
                if name == "router":
                    if not _wait_text(procs[0], "listening", 30.0):
                        raise StepError(f"router not listening: {procs[0].stderr_tail()}")
                elif not topo.wait_listening(role, procs[0].alive):
                    raise StepError(f"{name} (the hub) not listening: {procs[0].stderr_tail()}")
        sink = Proc("sink", _sink_argv(spec, topo, sid_prefix), logdir)
        procs.append(sink)
        ready = _read_line(sink, 60.0, lambda o: "ready" in o)
        dead = [p.name for p in procs if not p.alive()]
        if not ready or not ready["ready"] or dead:
            why = f"nodes not ready ({ready}; dead: {dead})"
            for p in procs:
                if p.name in dead:
                    why += f"; {p.name}: {p.stderr_tail()}"
            raise StepError(why)
        time.sleep(0.5)  # the subscribers are declared right after the liveliness tokens
        source = Proc(src_cmd[0], src_cmd[2], logdir)
        procs.append(source)
        window = measure_window(procs, source, spec, progress)
        # the source is done: wait for the sink to have every frame (it exits by itself)
        drain_s = 5.0 + spec.sensors * 0.01
        try:
            sink.popen.wait(drain_s)
        except subprocess.TimeoutExpired:
            pass
    except StepError as exc:
        reasons.append(str(exc))
        window = None
    finally:
        for p in reversed(procs):  # the sink first, then the nodes downstream-first
            if p.name != "source":
                p.stop()
        for p in procs:
            if p.name == "source":
                p.stop(5.0 + spec.seconds)
        for p in busy:
            p.stop(2.0)
    row.update(collect(spec, procs, window, reasons))
    add_bare_ratio(row)
    row["logs"] = str(logdir)
    return row


class StepError(RuntimeError):
    pass


def measure_window(procs: list[Proc], source: Proc, spec: StepSpec, progress: bool) -> dict:
    """CPU of every process from the end of the source's warm-up to its last reading
    before the source exits; bounded by 3 x the trial's length + 30 s."""
    from replay.progress import Progress
    t_start = time.monotonic() + spec.warmup_s
    deadline = t_start + 3 * spec.seconds + 30
    while time.monotonic() < t_start and source.alive():
        time.sleep(0.05)
    first = {p.name: cpu_s(p.pid) for p in procs}
    t0 = time.monotonic()
    last, t1 = dict(first), t0
    with Progress(int(spec.seconds), f"{spec.label()} {spec.sensors:>4} sensors", "s",
                  enabled=progress) as bar:
        while source.alive() and time.monotonic() < deadline:
            time.sleep(0.25)
            snap = {p.name: cpu_s(p.pid) for p in procs}
            if source.alive() and snap["source"] is not None:
                last, t1 = snap, time.monotonic()
            bar.update(int(t1 - t0) - bar.done)
    if source.alive():
        raise StepError(f"source still running {deadline - t_start:.0f} s after its warm-up")
    span = max(t1 - t0, 1e-9)
    cpu = {n: (round(100 * (last[n] - first[n]) / span, 1) if first[n] is not None and last[n] is not None
               else None) for n in first}
    return {"cpu_pct": cpu, "window_s": round(span, 2)}


def collect(spec: StepSpec, procs: list[Proc], window: dict | None, reasons: list[str]) -> dict:
    """The step's figures from the processes' final JSON lines, and whether it passes."""
    by = {p.name: p for p in procs}
    out: dict = {}
    src = by.get("source")
    src_t = (src.totals or {}) if src else {}
    sink_t = (by["sink"].totals or {}) if "sink" in by else {}
    sent = spec.sensors * spec.frames if src_t else 0
    out["sent"] = sent
    out["source_frames_out"] = src_t.get("frames_out")
    out["late_ticks"] = src_t.get("late_ticks")
    elapsed = src_t.get("elapsed_s")
    out["achieved_fps"] = round(sent / elapsed, 1) if elapsed else None
    out["received"] = sink_t.get("distinct")
    out["lost"] = sink_t.get("missing")
    out["lost_warmup"] = sink_t.get("missing_warmup")
    out["duplicates"] = sink_t.get("duplicates")
    out["unexpected"] = sink_t.get("unexpected")
    lat = sink_t.get("latency_ms") or {}
    out["p50_ms"], out["p99_ms"], out["max_ms"] = lat.get("p50"), lat.get("p99"), lat.get("max")
    nodes = {}
    for p in procs:
        t = p.totals or {}
        nodes[p.name] = {"cpu_pct": (window or {}).get("cpu_pct", {}).get(p.name),
                         **{k: t[k] for k in ("frames_in", "frames_out", *LOSS_COUNTERS) if k in t}}
        if p.name not in ("sink", "router") and not t:
            reasons.append(f"{p.name}: no totals (exit {p.popen.returncode}; {p.stderr_tail()})")
    out["nodes"] = nodes
    out["window_s"] = (window or {}).get("window_s")
    losses = {f"{n}.{k}": v[k] for n, v in nodes.items() for k in LOSS_COUNTERS if v.get(k)}
    out["node_losses"] = losses
    flags = []
    sink_cpu = nodes.get("sink", {}).get("cpu_pct")
    if sink_cpu is not None and sink_cpu >= SINK_CPU_FLAG:
        flags.append(f"sink at {sink_cpu:.0f} % CPU: it may hold the chain back")
    out["flags"] = flags
    if not sink_t:
        reasons.append(f"sink: no report ({by['sink'].stderr_tail() if 'sink' in by else 'not started'})")
    else:
        if out["lost"]:
            reasons.append(f"{out['lost']} frames without targets")
        if out["duplicates"]:
            reasons.append(f"{out['duplicates']} frames with targets more than once")
        if out["p99_ms"] is None or out["p99_ms"] > MAX_P99_MS:
            reasons.append(f"p99 {out['p99_ms']} ms > {MAX_P99_MS:g} ms")
    if losses:
        reasons.append("node counters: " + ", ".join(f"{k}={v}" for k, v in losses.items()))
    if out["achieved_fps"] is not None and out["achieved_fps"] < PACE_MIN * spec.sensors * RATE_HZ:
        reasons.append(f"source behind its pace: {out['achieved_fps']} of {spec.sensors * RATE_HZ:g} frames/s")
    total_cpu = [v["cpu_pct"] for n, v in nodes.items() if n != "sink" and v["cpu_pct"] is not None]
    out["cpu_total_pct"] = round(sum(total_cpu), 1) if total_cpu else None
    return {**out, "ok": not reasons, "reasons": reasons}


def add_bare_ratio(row: dict) -> None:
    """The chain's CPU (every process but the sink) over bare zenoh's for the same messages."""
    bare = row.get("bare") or {}
    if row.get("cpu_total_pct") and bare.get("cpu_total_pct"):
        row["cpu_vs_bare"] = round(row["cpu_total_pct"] / bare["cpu_total_pct"], 1)


# -- the bare-zenoh baseline ---------------------------------------------------------------
def bare_sizes(spec: StepSpec) -> list[int]:
    """The sizes of the messages one frame makes on the wire in this case."""
    s = frame_sizes(spec)
    return [s["raw"], s["quantized"], s["targets"]] if spec.case == "central" else [s["quantized"], s["targets"]]


def run_bare(spec: StepSpec, topo: Topology, logdir: Path) -> dict:
    """The step's messages (one of each size per sensor per tick, 20 ticks/s) from a bare
    zenoh publisher process to a subscriber process, for ``spec.baseline_s`` seconds."""
    sizes = ",".join(map(str, bare_sizes(spec)))
    me = str(Path(__file__).resolve())
    ticks = int(round(spec.baseline_s * RATE_HZ))
    sub = Proc("bare-sub", topo.argv("bare-sub", [me, "bare-sub", *[a for ep in topo.listen("bare-sub")
                                                                    for a in ("--listen", ep)],
                                                    "--expect", str(ticks * spec.sensors * len(sizes.split(",")))]),
               logdir)
    procs = [sub]
    try:
        if not _read_line(sub, 30.0, lambda o: "ready" in o):
            return {"error": f"bare-sub not ready: {sub.stderr_tail()}"}
        pub = Proc("bare-pub", topo.argv("bare-pub", [me, "bare-pub", "--connect", topo.connect("bare-pub"),
                                                      "--sensors", str(spec.sensors), "--sizes", sizes,
                                                      "--ticks", str(ticks), *(["--spread"] if spec.send == "spread"
                                                                               else [])]), logdir)
        procs.append(pub)
        if not _read_line(pub, 30.0, lambda o: "ready" in o):
            return {"error": f"bare-pub not ready: {pub.stderr_tail()}"}
        time.sleep(0.4)  # its first tick is 0.5 s after the line
        c0 = {p.name: cpu_s(p.pid) for p in procs}  # from its first tick, after start-up
        t0, last, t1 = time.monotonic(), dict(c0), time.monotonic()
        deadline = t0 + 3 * spec.baseline_s + 20
        while pub.alive() and time.monotonic() < deadline:
            time.sleep(0.1)
            snap = {p.name: cpu_s(p.pid) for p in procs}
            if pub.alive() and snap["bare-pub"] is not None:
                last, t1 = snap, time.monotonic()
        try:
            sub.popen.wait(5.0)
        except subprocess.TimeoutExpired:
            pass
    finally:
        for p in procs:
            p.stop()
    span = max(t1 - t0, 1e-9)
    r = sub.totals or {}
    cpu = {n: round(100 * (last[n] - c0[n]) / span, 1) if c0[n] is not None and last[n] is not None else None
           for n in c0}
    p = pub.totals or {}
    return {"msgs_per_s": round(spec.sensors * RATE_HZ * len(sizes.split(",")), 1), "sizes": sizes,
            "sent": p.get("sent"), "achieved_msgs_per_s": round(p["sent"] / p["elapsed_s"], 1) if p.get("elapsed_s")
            else None, "received": r.get("received"), "p99_ms": r.get("p99_ms"),
            "cpu_pct": cpu, "cpu_total_pct": round(sum(v for v in cpu.values() if v is not None), 1)}


def _open(args, listener: bool):
    from pipeline.bus.session import BusConfig
    if listener:
        return BusConfig(listen=tuple(args.listen)).open()
    return BusConfig(mode="client", connect=(args.connect,)).open()


def main_bare_pub(args) -> None:
    import zenoh
    session = _open(args, False)
    sizes = [int(s) for s in args.sizes.split(",")]
    pubs = [[session.declare_publisher(f"bare/{i}/{j}", congestion_control=zenoh.CongestionControl.BLOCK)
             for j in range(len(sizes))] for i in range(args.sensors)]
    bodies = [bytearray(s) for s in sizes]
    sent = 0
    period = 1.0 / RATE_HZ
    t0 = time.monotonic() + 0.5
    print(json.dumps({"ready": True}), flush=True)
    for k in range(args.ticks):
        for i in range(args.sensors):
            at = t0 + k * period + (i * period / args.sensors if args.spread else 0.0)
            delay = at - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            stamp = time.time_ns().to_bytes(8, "little")
            for j, body in enumerate(bodies):
                body[:8] = stamp
                pubs[i][j].put(bytes(body))
                sent += 1
    elapsed = time.monotonic() - t0
    session.close()
    print(json.dumps({"sent": sent, "elapsed_s": round(elapsed, 3)}), flush=True)


def main_bare_sub(args) -> None:
    session = _open(args, True)
    lat = array("q")
    done = threading.Event()

    def on(sample):
        lat.append(time.time_ns() - int.from_bytes(sample.payload.to_bytes()[:8], "little"))
        if len(lat) >= args.expect:
            done.set()

    sub = session.declare_subscriber("bare/**", on)
    print(json.dumps({"ready": True}), flush=True)
    install_stop(done)
    done.wait(600)
    sub.undeclare()
    import numpy as np
    a = np.frombuffer(lat, dtype=np.int64) / 1e6 if len(lat) else np.zeros(0)
    print(json.dumps({"received": int(a.size), "p99_ms": round(float(np.percentile(a, 99)), 2) if a.size else None}),
          flush=True)
    session.close()


def install_stop(event: threading.Event) -> None:
    signal.signal(signal.SIGTERM, lambda *_: event.set())
    signal.signal(signal.SIGINT, lambda *_: event.set())


# -- pre-made edge frames: the sensors' work done before the step -----------------------------
def make_premade(path: Path, scene: str, sensors: int, frames: int, alpha: float, bits: int, id_prefix: str,
                 progress: bool = False) -> Path:
    """The 1-bit frames ``qradar source --quantized --rate 0`` publishes (same simulation,
    noise, dither seed rule and quantizer), for ``sensors`` x ``frames``, into a ``.npy``
    of shape (frames, sensors, payload bytes): a player sends them later with only the
    timestamp rewritten, so a step measures the localizer's host without the sensors'
    simulation and quantization on its cores."""
    import numpy as np
    from replay.progress import Progress
    from pipeline.dsp.quantize import QuantizerConfig, quantize_frames, sensor_dither_seeds
    from pipeline.wire import FrameHeaders, encode_quantized_batch
    from radar_driver.scene import resolve_scene
    from radar_driver.source import SimSourceConfig, SimulatedSource
    cfg = QuantizerConfig(bits=bits, alpha=alpha)
    size = frame_sizes(StepSpec("edge", "burst", "pbp", sensors, 0.0, bits=bits, scene=scene))["quantized"]
    tmp = path.with_suffix(".part.npy")
    out = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=(frames, sensors, size))
    src = SimulatedSource(SimSourceConfig(resolve_scene(scene), sensors=sensors, rate_hz=0.0, frames=frames,
                                          id_prefix=id_prefix))
    seeds = None
    with Progress(frames, f"pre-made frames, {sensors} sensors", "frames per sensor", enabled=progress) as bar:
        for k, batch in enumerate(src.frame_batches()):  # burst: one batch per tick, every sensor
            headers = FrameHeaders([f.sensor_id for f in batch], [f.seq for f in batch],
                                   [f.timestamp_ns for f in batch], [f.config_id for f in batch])
            if seeds is None:
                seeds = sensor_dither_seeds(cfg.dither_seed, headers.sensor_id)
            data = np.stack([f.data for f in batch]).astype(np.complex128)
            q = quantize_frames(data, cfg, headers.seq, dither_seed=seeds)
            out[k] = np.frombuffer(b"".join(encode_quantized_batch(headers, q)), dtype=np.uint8).reshape(-1, size)
            bar.update(1)
    out.flush()
    del out
    os.replace(tmp, path)
    return path


def main_player(args) -> None:
    """Send pre-made 1-bit frames on <prefix>/<id>/quantized at 20 frames/s per sensor,
    paced as ``qradar source`` paces (burst or spread groups, the same late-tick rule), each
    frame's timestamp rewritten to the time its group is due; then the source's totals."""
    import numpy as np
    import zenoh
    from pipeline.wire import COMMON_DTYPE
    from radar_driver.source import send_groups
    frames = np.load(args.file, mmap_mode="r")
    n, k_max = args.sensors, args.frames
    if n > frames.shape[1] or k_max > frames.shape[0]:
        sys.exit(f"player: {args.file} holds {frames.shape[1]} sensors x {frames.shape[0]} frames, fewer than "
                 f"--sensors {n} x --frames {k_max}")
    session = _open(args, False)
    octets = zenoh.Encoding("application/octet-stream")
    pubs = [session.declare_publisher(f"{args.prefix}/{args.id_prefix}{i}/quantized", encoding=octets,
                                      congestion_control=zenoh.CongestionControl.BLOCK) for i in range(n)]
    stop = threading.Event()
    install_stop(stop)
    ts_at = COMMON_DTYPE.fields["timestamp_ns"][1]
    period = 1.0 / RATE_HZ
    groups = send_groups(n, RATE_HZ, args.send)
    slots = len(groups)
    sent = late = 0
    t0 = time.monotonic()
    t0_ns = time.time_ns()
    for k in range(k_max):
        if stop.is_set():
            break
        tick = np.array(frames[k, :n])  # writable, in memory
        stamps = tick[:, ts_at:ts_at + 8].view("<i8")
        for j, group in enumerate(groups):
            due = t0 + (k + j / slots) * period
            delay = due - time.monotonic()
            if delay > 0:
                if stop.wait(delay):
                    break
                ts = t0_ns + int((due - t0) * 1e9)
            else:
                if j == 0 and delay < -period:
                    late += 1
                ts = time.time_ns()
            stamps[group.start:group.stop] = ts
            for i in group:
                pubs[i].put(tick[i].tobytes())
            sent += len(group)
    elapsed = time.monotonic() - t0
    session.close()
    print(json.dumps({"frames_out": sent, "late_ticks": late, "elapsed_s": round(elapsed, 3)}), flush=True)


# -- the sink -------------------------------------------------------------------------------
def main_sink(args) -> None:
    """Subscribe <prefix>/*/targets; report once every expected frame has its targets, or
    at SIGTERM: frames with targets, missing, duplicates, latency of those past warm-up."""
    import numpy as np
    session = _open(args, False)
    expect = {k: int(v) for k, v in (kv.split("=") for kv in args.expect.split(",") if kv)}
    inbox: deque[bytes] = deque()  # append and popleft are atomic: the callback never waits
    stop = threading.Event()
    install_stop(stop)
    sub = session.declare_subscriber(f"{args.prefix}/*/targets", lambda s: inbox.append(s.payload.to_bytes()))
    # readiness: every expected node's liveliness token is seen (bounded)
    seen: dict[str, int] = {}
    deadline = time.monotonic() + args.ready_timeout
    while time.monotonic() < deadline and not stop.is_set():
        seen = {}
        for reply in session.liveliness().get(f"{args.prefix}/alive/**", timeout=1.0):
            if reply.ok is not None:
                node = str(reply.ok.key_expr).split("/")[-2]
                seen[node] = seen.get(node, 0) + 1
        if all(seen.get(k, 0) >= v for k, v in expect.items()):
            break
        time.sleep(0.2)
    ready = all(seen.get(k, 0) >= v for k, v in expect.items())
    print(json.dumps({"ready": ready, "seen": seen}), flush=True)
    if not ready:
        session.close()
        return
    n, frames, warm = args.sensors, args.frames, args.warmup
    counts = [bytearray(frames) for _ in range(n)]
    lat = array("q")
    distinct = duplicates = unexpected = 0
    plen = len(args.id_prefix)
    while True:
        stopping = stop.wait(0.2)
        for _ in range(len(inbox)):
            payload = inbox.popleft()
            obj = json.loads(payload)
            sid, seq = obj["sensor_id"], obj["seq"]
            idx = sid[plen:]
            i = int(idx) if sid.startswith(args.id_prefix) and idx.isdigit() else -1
            if not (0 <= i < n and 0 <= seq < frames):
                unexpected += 1
                continue
            c = counts[i][seq]
            if c:
                duplicates += 1
            else:
                distinct += 1
            counts[i][seq] = min(c + 1, 255)
            if seq >= warm:
                lat.append(obj["published_ns"] - obj["timestamp_ns"])
        if stopping or distinct >= n * frames:
            break
    sub.undeclare()
    session.close()
    c = np.frombuffer(b"".join(counts), dtype=np.uint8).reshape(n, frames)
    a = np.frombuffer(lat, dtype=np.int64) / 1e6 if len(lat) else np.zeros(0)
    pct = (lambda q: round(float(np.percentile(a, q)), 2) if a.size else None)
    print(json.dumps({"distinct": distinct, "missing": int((c[:, warm:] == 0).sum()),
                      "missing_warmup": int((c[:, :warm] == 0).sum()), "duplicates": duplicates,
                      "unexpected": unexpected,
                      "latency_ms": {"p50": pct(50), "p99": pct(99), "max": round(float(a.max()), 2) if a.size
                                     else None, "n": int(a.size)}}), flush=True)


# -- tables ---------------------------------------------------------------------------------
def fmt(v, digits: int = 1) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def cpu_cell(row: dict) -> str:
    """CPU % of one core per node, e.g. 'source 40, quantize0 55, localize0 30 (sink 5)'."""
    nodes = row.get("nodes", {})
    main = [f"{n} {fmt(v['cpu_pct'], 0)}" for n, v in nodes.items() if n != "sink"]
    sink = nodes.get("sink", {}).get("cpu_pct")
    return ", ".join(main) + (f" (sink {fmt(sink, 0)})" if sink is not None else "")


STEP_COLUMNS = ("case", "sensors", "result", "sent / received", "lost", "p50 / p99 / max (ms)", "late ticks",
                "CPU % of a core", "load avg", "bare zenoh: p99 ms, CPU % (the chain's CPU × bare's)")


def step_cells(r: dict) -> list[str]:
    result = "pass" if r["ok"] else "FAIL"
    if r.get("flags"):
        result += " ⚑"
    bare = r.get("bare")
    bare_txt = (f"{fmt(bare.get('p99_ms'), 2)}, {fmt(bare.get('cpu_total_pct'), 0)} (chain × "
                f"{fmt(r.get('cpu_vs_bare'))})") if bare and "error" not in bare else "–"
    return [r.get("label", ""), str(r["sensors"]), result, f"{fmt(r.get('sent'))} / {fmt(r.get('received'))}",
            f"{fmt(r.get('lost'))}" + (f" (+{sum(r['node_losses'].values())} counted)" if r.get("node_losses")
                                       else ""),
            f"{fmt(r.get('p50_ms'), 2)} / {fmt(r.get('p99_ms'), 2)} / {fmt(r.get('max_ms'), 1)}",
            fmt(r.get("late_ticks")), cpu_cell(r), fmt(r["loadavg_start"][0], 2), bare_txt]


def markdown(headers, rows) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def step_line(r: dict) -> str:
    """The one-line progress report of a step (stderr)."""
    res = "pass" if r["ok"] else "FAIL"
    bare = r.get("bare") or {}
    return (f"{r['label']:<24} {r['sensors']:>4} sensors: {res}  sent {r.get('sent')} received {r.get('received')} "
            f"lost {r.get('lost')}  p50/p99/max {r.get('p50_ms')}/{r.get('p99_ms')}/{r.get('max_ms')} ms  "
            f"late ticks {r.get('late_ticks')}  CPU {cpu_cell(r)}  load {r['loadavg_start'][0]}"
            + (f"  bare p99 {bare.get('p99_ms')} ms CPU {bare.get('cpu_total_pct')} % (chain x{r.get('cpu_vs_bare')})"
               if bare else "")
            + ("" if r["ok"] else f"  [{'; '.join(r['reasons'])}]")
            + (f"  flags: {'; '.join(r['flags'])}" if r.get("flags") else ""))


def split_args(text: str | None) -> tuple[str, ...]:
    return tuple(shlex.split(text)) if text else ()


def main() -> None:
    ap = argparse.ArgumentParser(description="helper processes of the stream benchmarks")
    sub = ap.add_subparsers(dest="what", required=True)
    p = sub.add_parser("sink")
    p.add_argument("--connect", required=True)
    p.add_argument("--prefix", default="radar")
    p.add_argument("--expect", default="", help="node=count,... liveliness tokens to wait for")
    p.add_argument("--id-prefix", required=True)
    p.add_argument("--sensors", type=int, required=True)
    p.add_argument("--frames", type=int, required=True)
    p.add_argument("--warmup", type=int, default=0)
    p.add_argument("--ready-timeout", type=float, default=45.0)
    p.set_defaults(func=main_sink)
    p = sub.add_parser("player")
    p.add_argument("--connect", required=True)
    p.add_argument("--mode", default="client")
    p.add_argument("--prefix", default="radar")
    p.add_argument("--file", required=True)
    p.add_argument("--sensors", type=int, required=True)
    p.add_argument("--frames", type=int, required=True)
    p.add_argument("--id-prefix", required=True)
    p.add_argument("--send", choices=["burst", "spread"], default="burst")
    p.set_defaults(func=main_player)
    p = sub.add_parser("bare-pub")
    p.add_argument("--connect", required=True)
    p.add_argument("--sensors", type=int, required=True)
    p.add_argument("--sizes", required=True)
    p.add_argument("--ticks", type=int, required=True)
    p.add_argument("--spread", action="store_true")
    p.set_defaults(func=main_bare_pub)
    p = sub.add_parser("bare-sub")
    p.add_argument("--listen", action="append", required=True)
    p.add_argument("--expect", type=int, required=True)
    p.set_defaults(func=main_bare_sub)
    args = ap.parse_args()
    args.func(args)


if __name__ == "__main__":
    main()

