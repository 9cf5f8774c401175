#!/usr/bin/env python3
"""Soak: ``qradar run`` for a long time (default 30 min) under a flooding fake sensor,
with a localize node killed and restarted half-way; memory, losses and crashes.

One soak starts fresh processes and ends them all (not part of ``make test``):

1. the main job, ``qradar run --duration D --sensors S --listen tcp/127.0.0.1:<free port>
   --json --record <tmp>/soak.mcap`` (simulated K-MD2s, their driver processes,
   quantize, localize, recorder and monitor);
2. a flooding fake sensor (benchmarks/soak_flood.py), a zenoh client of that port,
   publishing ``radar/evil/raw`` at ``--flood-rate`` messages/s: valid frames, NaN
   frames, frames of an unknown config id, wrong lengths, and one-byte puts on
   ``radar/junk<i>/raw``;
3. an external chain on the same zenoh, prefix ``soak``, each a client of the run's port:
   ``qradar source --sensors 2 --rate 20`` -> ``qradar quantize`` -> ``qradar localize``.
   At D/2 the localize process is killed (SIGKILL) and a new one is started
   ``--restart-gap`` s later;
4. an observer in this process (a zenoh client too) counts the targets of every sensor
   and the gaps in their sequence numbers, and keeps the last health of each node and
   sensor.

Every ``--sample`` s the RSS (VmRSS) of each process is read: the run, its driver
processes, the flood and the external nodes. Reported per process: RSS at the end of
its warm-up (``--warmup`` s after it started), in the middle and at the end (before the
flood stops), the growth end - start and the slope (MB/min, least squares over the
samples after warm-up). Aim: growth within 5 MB.

Losses, per sensor (the run's kmd2-<i>, the flood's evil, the chain's sim<i>):
``unaccounted`` = frames published with a sequence number at or after the first target
the observer received - targets received - gaps counted (a loss no gap shows: at the
tail); ``restart loss`` = the gap at each external sensor's first target from the new
localize; ``counted by nodes`` = what the localize node(s) said they lost or saw missing
upstream (health: frames_missing, drops, errors; the killed one's last health);
``unexplained`` = gaps + unaccounted - restart loss - counted by nodes. For evil,
``unexplained`` balances the run's final totals instead: numbered frames sent - targets
received - queue drops - invalid frames (less the flood's unnumbered messages) - errors -
frames missing at the quantizer. Every loss counted: unexplained 0. The run's simulated
sensors also lose frames before their driver (its ``dropped``, shown beside published).

Crashes: a process that exits before it is stopped (but the killed localize), or a run
that ends without rc 0 and its JSON summary.

    .venv/bin/python benchmarks/soak.py [--duration 1800] [--warmup 60] [--sensors 2] \\
        [--flood-rate 2000] [--out soak.json]

At the end the flood and the external source stop ``--tail`` s before the run's own
end, the external nodes 5 s later; each stop is SIGTERM, then SIGKILL after 10 s; the
run gets 120 s past its duration. ``--malloc-arena-max 2`` runs every process with
MALLOC_ARENA_MAX=2: RSS that grows with glibc's default arenas and not with 2 is heap
held by per-thread arenas (zenoh's and Python's threads), not Python objects.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict, deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from harness import cpu_s, free_port, rss_mb, wait_port
from pipeline.bus.session import BusConfig
from replay.progress import Progress
from qradar.drivers import last_json_object

HERE = Path(__file__).resolve().parents[1]
FLOOD = Path(__file__).resolve().parent / "soak_flood.py"
START_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 10.0
RUN_GRACE_S = 120.0
DRAIN_S = 5.0
AIM_MB = 5.0  # growth after warm-up the soak aims to stay within
LOSS_FIELDS = ("drops", "decode_errors", "invalid_frames", "processing_errors", "frames_missing")


# -- processes -------------------------------------------------------------------------------
def children_of(pid: int) -> list[int]:
    out: list[int] = []
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            out += [int(x) for x in (task / "children").read_text().split()]
    except OSError:
        pass
    return out


class Child:
    """A child process in a session of its own; stdout kept (bounded), stderr tailed."""

    def __init__(self, name: str, cmd: list[str], env: dict, t0: float, cwd: Path = HERE):
        self.name, self.cmd = name, cmd
        self.proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, start_new_session=True)
        self.pid = self.proc.pid
        self.started_s = time.monotonic() - t0
        self.stdout: deque[str] = deque(maxlen=50)
        self.stderr_tail: deque[str] = deque(maxlen=30)
        self.stopping = False  # we asked it to end: an exit is no crash
        self.exited_s: float | None = None
        self.cpu_s: float | None = None
        self._t0 = t0
        self._threads = [threading.Thread(target=self._read, args=(self.proc.stdout, self.stdout), daemon=True),
                         threading.Thread(target=self._read, args=(self.proc.stderr, self.stderr_tail), daemon=True)]
        for t in self._threads:
            t.start()

    @staticmethod
    def _read(stream, sink: deque) -> None:
        for line in stream:
            sink.append(line.rstrip("\n"))

    @property
    def returncode(self) -> int | None:
        return self.proc.returncode

    def poll(self) -> int | None:
        if self.proc.returncode is None:
            c = cpu_s(self.pid)
            if c is not None:
                self.cpu_s = c
        rc = self.proc.poll()
        if rc is not None and self.exited_s is None:
            self.exited_s = time.monotonic() - self._t0
            for t in self._threads:
                t.join(5.0)
        return rc

    def wait(self, timeout_s: float) -> int | None:
        deadline = time.monotonic() + timeout_s
        while self.poll() is None:
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.05)
        return self.returncode

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = STOP_TIMEOUT_S) -> int | None:
        """``sig``, then SIGKILL to its process group after ``timeout_s``."""
        self.stopping = True
        if self.poll() is None:
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:
                pass
            if self.wait(timeout_s) is None:
                try:
                    os.killpg(self.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                self.wait(timeout_s)
        return self.returncode

    def last_json(self) -> dict:
        return last_json_object(list(self.stdout))


# -- the observer ------------------------------------------------------------------------------
@dataclass
class TargetCount:
    """Targets of one sensor as the observer received them."""

    first_seq: int | None = None
    last_seq: int | None = None
    received: int = 0
    gaps: int = 0
    gap_events: int = 0
    seq_resets: int = 0
    first_t_s: float | None = None
    restart_pending: bool = False
    restart_loss: int | None = None

    def note(self, seq: int, t_s: float) -> None:
        self.received += 1
        if self.first_seq is None:
            self.first_seq, self.first_t_s = seq, t_s
        gap = 0
        if self.last_seq is not None:
            if seq > self.last_seq + 1:
                gap = seq - self.last_seq - 1
                self.gaps += gap
                self.gap_events += 1
            elif seq <= self.last_seq:
                self.seq_resets += 1
        if self.restart_pending and self.last_seq is not None:
            self.restart_loss, self.restart_pending = gap, False
        self.last_seq = seq if self.last_seq is None or seq > self.last_seq else self.last_seq


class Observer:
    """A zenoh client in this process: the targets (sequence numbers) and the last health
    of every node and sensor under each prefix."""

    def __init__(self, endpoint: str, prefixes: tuple[str, ...], t0: float):
        self.session = BusConfig(mode="client", connect=(endpoint,)).open()
        self.t0 = t0
        self.targets: dict[tuple[str, str], TargetCount] = defaultdict(TargetCount)
        self.health: dict[tuple[str, str, str], dict] = {}
        self.health_count = 0
        self.undecodable = 0
        self._lock = threading.Lock()
        self._subs = []
        for p in prefixes:
            self._subs.append(self.session.declare_subscriber(f"{p}/*/targets", self._on_targets))
            self._subs.append(self.session.declare_subscriber(f"{p}/*/health", self._on_health))

    def _on_targets(self, sample) -> None:
        key = str(sample.key_expr)
        try:
            obj = json.loads(sample.payload.to_bytes())
            seq = int(obj["seq"])
        except (ValueError, KeyError, TypeError):
            with self._lock:
                self.undecodable += 1
            return
        prefix, sensor, _ = key.rsplit("/", 2)
        with self._lock:
            self.targets[(prefix, sensor)].note(seq, time.monotonic() - self.t0)

    def _on_health(self, sample) -> None:
        key = str(sample.key_expr)
        try:
            obj = json.loads(sample.payload.to_bytes())
            node = str(obj["node"])
        except (ValueError, KeyError, TypeError):
            with self._lock:
                self.undecodable += 1
            return
        prefix, sensor, _ = key.rsplit("/", 2)
        obj["_t_s"] = round(time.monotonic() - self.t0, 1)
        with self._lock:
            self.health_count += 1
            self.health[(prefix, node, sensor)] = obj

    def arm_restart(self, prefix: str) -> None:
        """The next target of each sensor under ``prefix`` measures the restart's gap."""
        with self._lock:
            for (p, _), tc in self.targets.items():
                if p == prefix:
                    tc.restart_pending = True

    def junk_with_health(self, since_s: float) -> dict[str, int]:
        """Per node: the radar/junk<i> sensors it published health for since ``since_s``."""
        out: dict[str, int] = defaultdict(int)
        with self._lock:
            for (p, n, s), h in self.health.items():
                if p == "radar" and s.startswith("junk") and h["_t_s"] >= since_s:
                    out[n] += 1
        return dict(out)

    def health_of(self, prefix: str, node: str) -> dict[str, dict]:
        with self._lock:
            return {s: dict(h) for (p, n, s), h in self.health.items() if p == prefix and n == node}

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # the run's end may have closed the link already
                pass
        self.session.close()


# -- memory -----------------------------------------------------------------------------------------
def memory_figures(samples: list[tuple[float, float]], start_s: float, warmup_s: float) -> dict:
    """RSS at the end of the warm-up, in the middle and at the end, MB; growth and slope."""
    if not samples:
        return {"samples": 0}
    post = [(t, r) for t, r in samples if t >= start_s + warmup_s]
    out = {"samples": len(samples), "first_mb": round(samples[0][1], 1),
           "peak_mb": round(max(r for _, r in samples), 1)}
    if len(post) < 2:
        return out | {"note": "fewer than 2 samples after warm-up"}
    t = np.array([p[0] for p in post])
    r = np.array([p[1] for p in post])
    mid = int(np.argmin(np.abs(t - (t[0] + t[-1]) / 2)))
    slope = float(np.polyfit(t / 60.0, r, 1)[0])
    return out | {"start_mb": round(r[0], 1), "middle_mb": round(r[mid], 1), "end_mb": round(r[-1], 1),
                  "growth_mb": round(r[-1] - r[0], 2), "slope_mb_per_min": round(slope, 3),
                  "window_s": [round(t[0], 1), round(t[-1], 1)]}


# -- one soak -----------------------------------------------------------------------------------------
def wait_run_port(port: int, run: Child, timeout_s: float) -> None:
    """Until ``qradar run`` listens on ``port``; RuntimeError with its stderr if it exits first."""
    try:
        wait_port(port, timeout_s=timeout_s, alive=lambda: run.poll() is None, what="qradar run")
    except RuntimeError as e:
        if run.poll() is None:
            raise
        raise RuntimeError(f"qradar run exited ({run.returncode}) before listening: "
                           f"{' | '.join(run.stderr_tail)}") from e


def per_sensor_published(total: int, sensors: list[str]) -> dict[str, int]:
    """Frames of each sensor of a SimulatedSource that made ``total`` in all: it makes one
    frame per sensor per tick, in id order."""
    n = len(sensors)
    return {s: total // n + (1 if i < total % n else 0) for i, s in enumerate(sensors)}


def accounting(tc: TargetCount | None, published: int | None) -> dict:
    """Targets received, gaps and what no gap explains, for a sensor whose sequence numbers
    run 0 .. published-1."""
    if tc is None:
        return {"published": published, "received": 0}
    out = {"published": published, "first_seq": tc.first_seq, "last_seq": tc.last_seq, "received": tc.received,
           "gaps": tc.gaps, "gap_events": tc.gap_events, "seq_resets": tc.seq_resets}
    if published is not None and tc.first_seq is not None:
        out["published_after_first"] = published - tc.first_seq
        out["unaccounted"] = published - tc.first_seq - tc.received - tc.gaps
    if tc.restart_loss is not None or tc.restart_pending:
        out["restart_loss"] = tc.restart_loss
    return out


def node_view(health: dict | None) -> dict:
    """A node's loss counters for one sensor from its last health, its latency (ms) and when
    the observer received that health (s from the start)."""
    if not health:
        return {}
    return {k: int(health.get(k, 0)) for k in ("frames_in", "frames_out", *LOSS_FIELDS)} | {
        "latency_ms": health.get("latency_ms"), "health_t_s": health.get("_t_s")}


def counted(health: dict | None) -> int:
    """Frames a localize node saw lost upstream or lost itself: frames_missing, drops, errors."""
    return sum(int(health.get(k, 0)) for k in LOSS_FIELDS) if health else 0


def explain(acc: dict, *localizers: dict | None) -> dict:
    """``acc`` plus what the localize node(s) counted and what neither they nor the
    restart explain: gaps + unaccounted - restart loss - counted (0: every loss counted)."""
    n = sum(counted(h) for h in localizers)
    acc = acc | {"counted_by_nodes": n, "localize": [node_view(h) for h in localizers]}
    if "unaccounted" in acc:
        acc["unexplained"] = acc["gaps"] + acc["unaccounted"] - (acc.get("restart_loss") or 0) - n
    return acc


def evil_balance(losses: dict, summary: dict, flood: dict) -> int | None:
    """The flooding sensor's numbered frames (valid, nan, badcfg) not explained by the run's
    final totals: sent - targets received - queue drops - invalid - errors - frames missing
    at the quantizer. The totals are the run's (its summary), less the other sensors' share
    (from their health) and less the flood's unnumbered messages (short, junk), which the
    quantizer counts as invalid too."""
    if not summary or "seq_next" not in flood:
        return None
    d, fm = summary["drops_detail"], summary["frames_missing"]
    real = [v for k, v in losses.items() if k.startswith("radar/kmd2-")]
    real_drops = sum((v.get("quantize") or {}).get("drops", 0) + (v["localize"][0] or {}).get("drops", 0)
                     for v in real)
    real_invalid = sum((v.get("quantize") or {}).get("invalid_frames", 0)
                       + (v["localize"][0] or {}).get("invalid_frames", 0) for v in real)
    kinds = flood.get("sent_by_kind", {})
    received = losses.get("radar/evil", {}).get("received", 0)
    return (flood["seq_next"] - received - (d["node_queues"] - real_drops)
            - (d["invalid_frames"] - real_invalid - kinds.get("short", 0) - kinds.get("junk", 0))
            - d["decode_errors"] - d["processing_errors"] - fm["quantize"])


def soak(args) -> dict:
    tree = args.tree.resolve()
    env = dict(os.environ, PYTHONPATH=str(tree), PYTHONUNBUFFERED="1")
    if args.malloc_arena_max:
        env["MALLOC_ARENA_MAX"] = str(args.malloc_arena_max)
    py = [args.python, "-m", "qradar"]
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    client = ["--mode", "client", "--connect", ep]
    D = float(args.duration)
    t_kill = D / 2
    t_stop = D - args.tail
    out: dict = {"duration_s": D, "warmup_s": args.warmup, "sensors": args.sensors, "flood_rate_hz": args.flood_rate,
                 "flood_mix": args.flood_mix, "junk_ids": args.junk_ids, "ext_sensors": args.ext_sensors,
                 "ext_rate_hz": args.ext_rate, "restart_gap_s": args.restart_gap, "sample_s": args.sample,
                 "tail_s": args.tail, "malloc_arena_max": args.malloc_arena_max or None, "endpoint": ep, "tree": str(tree), "cpus": os.cpu_count(),
                 "loadavg_start": Path("/proc/loadavg").read_text().split()[:3]}
    children: list[Child] = []
    crashes: list[dict] = []
    samples: dict[str, list[tuple[float, float]]] = defaultdict(list)
    started_s: dict[str, float] = {}
    events: list[dict] = []
    health_series: list[tuple[float, int, dict]] = []  # (t, health messages so far, junk sensors with health)
    observer = None
    tmp = Path(tempfile.mkdtemp(prefix="qradar-soak-", dir=args.tmp))
    rec = tmp / "soak.mcap"
    t0 = time.monotonic()

    def start(name: str, cmd: list[str]) -> Child:
        c = Child(name, cmd, env, t0, tree)
        children.append(c)
        started_s[name] = c.started_s
        events.append({"t_s": round(c.started_s, 1), "event": f"start {name}"})
        return c

    def check_crashes() -> None:
        for c in children:
            if not c.stopping and c.poll() is not None and not any(x["process"] == c.name for x in crashes):
                crashes.append({"process": c.name, "rc": c.returncode, "t_s": round(c.exited_s, 1),
                                "stderr": list(c.stderr_tail)[-5:]})
                events.append({"t_s": round(c.exited_s, 1), "event": f"CRASH {c.name} rc {c.returncode}"})

    def sample(now_s: float) -> None:
        health_series.append((round(now_s, 1), observer.health_count if observer else 0,
                              observer.junk_with_health(now_s - 3.0) if observer else {}))
        for c in children:
            if c.poll() is None:
                r = rss_mb(c.pid)
                if r is not None:
                    samples[c.name].append((now_s, r))
                if c.name == "run":
                    for i, pid in enumerate(sorted(children_of(c.pid))):
                        r = rss_mb(pid)
                        if r is not None:
                            name = f"run-driver-{i}"
                            started_s.setdefault(name, now_s)
                            samples[name].append((now_s, r))

    try:
        run = start("run", py + ["run", "--duration", f"{D:g}", "--sensors", str(args.sensors), "--listen", ep,
                                 "--json", *(["--no-record"] if args.no_record else ["--record", str(rec)]),
                                 "--scene", args.scene])
        wait_run_port(port, run, START_TIMEOUT_S)
        observer = Observer(ep, ("radar", "soak"), t0)
        ext_loc = start("ext-localize#1", py + ["localize", "--algo", "pbp", "--prefix", "soak", *client])
        ext_q = start("ext-quantize", py + ["quantize", "--prefix", "soak", *client])
        flood = start("flood", [args.python, str(FLOOD), "--connect", ep, "--rate", f"{args.flood_rate:g}",
                                "--mix", args.flood_mix, "--junk-ids", str(args.junk_ids), "--scene", args.scene,
                                "--duration", f"{D + 60:g}"])
        time.sleep(3.0)  # let the external nodes subscribe before the source publishes
        ext_src = start("ext-source", py + ["source", "--prefix", "soak", "--sensors", str(args.ext_sensors),
                                            "--rate", f"{args.ext_rate:g}", "--scene", args.scene,
                                            "--duration", f"{D + 60:g}", *client])
        killed = restarted = stopped = False
        ext_loc1_health: dict = {}
        next_sample = 0.0
        with Progress(int(D), "soak", unit="s", enabled=not args.quiet) as bar:
            while True:
                now = time.monotonic() - t0
                bar.update(int(min(now, D)) - bar.done)
                check_crashes()
                if now >= next_sample and not stopped:
                    sample(now)
                    next_sample = now + args.sample
                if not killed and now >= t_kill:
                    ext_loc1_health = observer.health_of("soak", "localize")
                    ext_loc.stop(signal.SIGKILL)
                    events.append({"t_s": round(now, 1), "event": "SIGKILL ext-localize#1"})
                    killed = True
                if killed and not restarted and now >= t_kill + args.restart_gap:
                    observer.arm_restart("soak")  # targets in flight at the kill have arrived by now
                    ext_loc = start("ext-localize#2", py + ["localize", "--algo", "pbp", "--prefix", "soak", *client])
                    restarted = True
                if not stopped and now >= t_stop:
                    events.append({"t_s": round(now, 1), "event": "stop flood and ext-source"})
                    flood.stop()
                    ext_src.stop()
                    time.sleep(DRAIN_S)
                    ext_q.stop()
                    ext_loc.stop()
                    events.append({"t_s": round(time.monotonic() - t0, 1), "event": "external nodes stopped"})
                    run.stopping = True  # it ends at its own duration from now on
                    stopped = True
                if stopped:
                    break
                time.sleep(0.5)
            # the run ends at its own duration
            while run.poll() is None and time.monotonic() - t0 < D + RUN_GRACE_S:
                bar.update(int(min(time.monotonic() - t0, D)) - bar.done)
                time.sleep(0.5)
        if run.poll() is None:
            events.append({"t_s": round(time.monotonic() - t0, 1), "event": "run did not end: stopped"})
            crashes.append({"process": "run", "rc": None, "t_s": round(time.monotonic() - t0, 1),
                            "stderr": [f"did not end within {RUN_GRACE_S} s of its duration"]})
            run.stop()
        else:
            events.append({"t_s": round(run.exited_s, 1), "event": f"run exited rc {run.returncode}"})
        time.sleep(1.0)  # the last health on the wire
    finally:
        for c in reversed(children):
            if c.poll() is None:
                c.stop()
        if observer is not None:
            try:
                observer.close()
            except Exception as exc:  # the run has gone: nothing to close against
                events.append({"t_s": round(time.monotonic() - t0, 1), "event": f"observer close: {exc}"})
    check_crashes()
    summary = run.last_json()
    if run.returncode != 0 or not summary:
        if not any(x["process"] == "run" for x in crashes):
            crashes.append({"process": "run", "rc": run.returncode, "t_s": round(run.exited_s or 0, 1),
                            "stderr": list(run.stderr_tail)[-8:], "summary": bool(summary)})
    out["run"] = {k: summary.get(k) for k in ("seconds", "frames_raw", "frames_quantized", "frames_targets", "drops",
                                               "drops_detail", "frames_missing", "worker_restarts", "latency_ms",
                                               "position_error_m", "driver", "recording")}
    out["run_rc"] = run.returncode
    out["recording_mb"] = round(rec.stat().st_size / 1e6, 1) if rec.exists() else None
    flood_out = flood.last_json()
    out["flood"] = flood_out
    src_out, q_out = ext_src.last_json(), ext_q.last_json()
    loc_out = ext_loc.last_json()
    out["ext"] = {"source": src_out, "quantize": q_out, "localize#2": loc_out}
    # losses per sensor
    tcounts = dict(observer.targets) if observer is not None else {}
    losses: dict[str, dict] = {}
    driver = summary.get("driver") or {}
    run_q, run_l = observer.health_of("radar", "quantize"), observer.health_of("radar", "localize")
    for i in range(args.sensors):
        sid = f"kmd2-{i}"
        acc = accounting(tcounts.get(("radar", sid)), (driver.get(sid) or {}).get("frames"))
        losses[f"radar/{sid}"] = explain(acc, run_l.get(sid)) | {
            "sensor_frames_dropped": (driver.get(sid) or {}).get("dropped"), "quantize": node_view(run_q.get(sid))}
    losses["radar/evil"] = accounting(tcounts.get(("radar", "evil")), flood_out.get("seq_next")) | {
        "quantize": node_view(run_q.get("evil")), "localize": node_view(run_l.get("evil"))}
    losses["radar/evil"]["unexplained"] = evil_balance(losses, summary, flood_out)
    ext_ids = [f"sim{i}" for i in range(args.ext_sensors)]
    published = per_sensor_published(src_out["frames_out"], ext_ids) if "frames_out" in src_out else {}
    ext_q_h = observer.health_of("soak", "quantize")
    ext_l2_h = observer.health_of("soak", "localize")
    for sid in ext_ids:
        acc = explain(accounting(tcounts.get(("soak", sid)), published.get(sid)), ext_loc1_health.get(sid),
                      ext_l2_h.get(sid))
        losses[f"soak/{sid}"] = acc | {"quantize": node_view(ext_q_h.get(sid))}
    out["losses"] = losses
    out["health_series"] = [{"t_s": t, "health_msgs": n, "junk_sensors_with_health": j} for t, n, j in health_series]
    out["health_messages"] = observer.health_count if observer else 0
    out["observer_undecodable"] = observer.undecodable if observer else 0
    # memory
    mem = {}
    for name, s in samples.items():
        until = [(t, r) for t, r in s if t < t_stop]
        mem[name] = memory_figures(until, started_s.get(name, 0.0), args.warmup)
    out["memory"] = mem
    out["rss_samples"] = {k: [[round(t, 1), round(r, 2)] for t, r in v] for k, v in samples.items()}
    out["cpu_s"] = {c.name: round(c.cpu_s, 1) if c.cpu_s is not None else None for c in children}
    out["crashes"] = crashes
    out["events"] = events
    out["total_wall_s"] = round(time.monotonic() - t0, 1)
    out["loadavg_end"] = Path("/proc/loadavg").read_text().split()[:3]
    if args.keep:
        out["tmp"] = str(tmp)
    else:
        for p in sorted(tmp.rglob("*"), reverse=True):
            p.unlink() if p.is_file() else p.rmdir()
        tmp.rmdir()
    return out


# -- the report -----------------------------------------------------------------------------------------
def table(r: dict) -> str:
    run = r.get("run") or {}
    fl = r.get("flood") or {}
    hs = [h for h in r.get("health_series", []) if h["t_s"] < r["duration_s"] - r["tail_s"]]
    junk = hs[-1]["junk_sensors_with_health"] if hs else {}
    rate = (hs[-1]["health_msgs"] - hs[0]["health_msgs"]) / (hs[-1]["t_s"] - hs[0]["t_s"]) if len(hs) > 1 else None
    lines = ["| figure | value |", "|---|---|",
             f"| duration / warm-up | {r['duration_s']:g} s / {r['warmup_s']:g} s |",
             f"| sensors: run / external chain | {r['sensors']} / {r['ext_sensors']} at {r['ext_rate_hz']:g} Hz |",
             f"| flood sent (rate achieved) | {fl.get('sent', '–')} ({fl.get('rate_achieved_hz', '–')} msg/s): "
             f"{fl.get('sent_by_kind', {})} |",
             f"| run rc; frames raw / quantized / targets | {r.get('run_rc')}; {run.get('frames_raw')} / "
             f"{run.get('frames_quantized')} / {run.get('frames_targets')} |",
             f"| run drops | {run.get('drops')} {run.get('drops_detail')} |",
             f"| run frames_missing | {run.get('frames_missing')} |",
             f"| run worker_restarts | {run.get('worker_restarts')} |",
             f"| run latency ms (all sensors) | {run.get('latency_ms')} |",
             f"| recording | {r.get('recording_mb')} MB |",
             f"| health messages/s seen; junk sensors with health (by node) | "
             f"{round(rate) if rate is not None else '–'}; {junk} |",
             f"| crashes | {len(r['crashes'])} {[c['process'] for c in r['crashes']] or ''} |"]
    lines += ["", "| sensor | published | received | gaps | unaccounted | restart loss | counted by nodes | "
              "unexplained | localize latency ms p50 / p99 |", "|---|---|---|---|---|---|---|---|---|"]
    for name, a in r.get("losses", {}).items():
        loc = a.get("localize")
        locs = loc if isinstance(loc, list) else [loc]
        lat = "; ".join(f"{(v.get('latency_ms') or {}).get('p50')} / {(v.get('latency_ms') or {}).get('p99')}"
                        for v in locs if v)
        pub = a.get("published")
        if a.get("sensor_frames_dropped"):
            pub = f"{pub} (+{a['sensor_frames_dropped']} lost at the sensor, counted by its driver)"
        lines.append(f"| {name} | {pub} | {a.get('received')} | {a.get('gaps', '–')} | "
                     f"{a.get('unaccounted', '–')} | {a.get('restart_loss', '–')} | "
                     f"{a.get('counted_by_nodes', '–')} | {a.get('unexplained', '–')} | {lat or '–'} |")
    lines += ["", f"| process | RSS start MB | middle | end | growth MB | slope MB/min | peak | CPU s | "
              f"growth within {AIM_MB:g} MB |", "|---|---|---|---|---|---|---|---|---|"]
    for name, m in r.get("memory", {}).items():
        lines.append(f"| {name} | {m.get('start_mb', '–')} | {m.get('middle_mb', '–')} | {m.get('end_mb', '–')} | "
                     f"{m.get('growth_mb', '–')} | {m.get('slope_mb_per_min', '–')} | {m.get('peak_mb', '–')} | "
                     f"{r.get('cpu_s', {}).get(name, '–')} | "
                     f"{('yes' if abs(m['growth_mb']) <= AIM_MB else 'NO') if 'growth_mb' in m else '–'} |")
    return "\n".join(lines)


def isolation_cases(args) -> int:
    """The flood-beside-honest and restart cases, run by benchmarks/bench_isolation.py."""
    cases = ["quantized", "raw", "new-ids"] if args.case == "flood-beside-honest" else ["restarts"]
    argv = [args.python, str(Path(__file__).resolve().parent / "bench_isolation.py"), "--case", *cases,
            "--seconds", str(min(args.duration, 600.0))]
    return subprocess.run(argv, cwd=HERE).returncode


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=1800.0, help="seconds of the run (default 1800)")
    ap.add_argument("--warmup", type=float, default=60.0, help="seconds after a process starts before its memory "
                    "counts (default 60)")
    ap.add_argument("--sample", type=float, default=10.0, help="seconds between RSS samples (default 10)")
    ap.add_argument("--sensors", type=int, default=2, help="simulated K-MD2s of the run (default 2)")
    ap.add_argument("--scene", default="chamber")
    ap.add_argument("--flood-rate", type=float, default=2000.0, help="flood messages/s in all (default 2000)")
    ap.add_argument("--flood-mix", default=None, help="kind=share,... (default: soak_flood.py's)")
    ap.add_argument("--junk-ids", type=int, default=1000, help="distinct junk<i> sensor ids (default 1000)")
    ap.add_argument("--ext-sensors", type=int, default=2, help="sensors of the external chain (default 2)")
    ap.add_argument("--ext-rate", type=float, default=20.0, help="their frames/s each (default 20)")
    ap.add_argument("--restart-gap", type=float, default=5.0, help="seconds without a localize (default 5)")
    ap.add_argument("--tail", type=float, default=15.0, help="stop the flood and the external chain this many "
                    "seconds before the run's end (default 15)")
    ap.add_argument("--python", default=sys.executable, help="the interpreter with qradar's dependencies")
    ap.add_argument("--tree", type=Path, default=HERE, help="the qradar tree the run and the nodes come from "
                    "(default: this one; the flood is always this tree's)")
    ap.add_argument("--malloc-arena-max", type=int, default=0, metavar="N",
                    help="MALLOC_ARENA_MAX for every process (glibc's malloc arenas; 0: glibc's default, 8 per "
                    "core): tells native heap growth from a leak")
    ap.add_argument("--tmp", default=None, help="directory for the recording (default: the system's temp)")
    ap.add_argument("--keep", action="store_true", help="keep the recording")
    ap.add_argument("--no-record", action="store_true",
                    help="the run records nothing (tells the recorder's memory from the rest's)")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    ap.add_argument("--case", choices=("soak", "flood-beside-honest", "restarts"), default="soak",
                    help="soak: the run above (default); flood-beside-honest: an honest sensor at 20 Hz beside "
                    "5 000 valid frames/s of one sensor (quantized, then raw) and 10 000 new ids at 1 000/s, "
                    "--duration s each (benchmarks/bench_isolation.py); restarts: 20 publisher restarts against "
                    "one router and quantize, their RSS")
    args = ap.parse_args()
    if args.case != "soak":
        sys.exit(isolation_cases(args))
    if args.flood_mix is None:
        from soak_flood import DEFAULT_MIX

        args.flood_mix = DEFAULT_MIX
    if not (args.duration > 2 * (args.tail + DRAIN_S + args.restart_gap) and args.duration > args.warmup):
        raise SystemExit(f"--duration {args.duration:g} s is too short for --warmup {args.warmup:g}, --tail "
                         f"{args.tail:g} and --restart-gap {args.restart_gap:g}")
    result = soak(args)
    text = json.dumps(result, indent=1)
    if args.out is not None:
        args.out.write_text(text + "\n")
    else:
        print(text)
    print()
    print(table(result))


if __name__ == "__main__":
    main()
