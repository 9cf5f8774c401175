#!/usr/bin/env python3
"""Sensor frames dropped by the K-MD2 driver while other work keeps both cores busy,
for the code before the reader-thread redesign (commit 28790cf) and after it.

Each trial starts fresh processes and ends them all:

1. ``--load`` busy loops (``python -c "while True: pass"``), started first and killed
   last; their CPU seconds over the trial's wall seconds (from /proc/<pid>/stat) say
   whether they really ran at ~100 % each;
2. for the driver steps, the simulated K-MD2 in its own process
   (``qradar sim --link <tmp>/kmd2 --rate 20 --scene chamber``);
3. the driver, ``qradar drive --port <url> --frames N --json --quiet`` (an embedded zenoh
   peer with no listener: every frame is still put), over

   - ``pty``: the simulator's pty link;
   - ``ser2net``: ser2net raw, ``tcp(nodelay)``, in front of that pty (the current
     driver stays at 115200 on a socket:// link by itself; the old one is told
     ``--baud 115200``);
   - ``pty-nopub`` / ``ser2net-nopub``: the same with ``--no-publish``;

4. or ``qradar run --frames N --no-record --json`` (``run``: its driver in its own
   process after the redesign, a thread of the run before it; ``run-in-process``: the
   current run with ``--driver-in-process``), whose simulator is a thread of the run.

The baseline in the same process is ``--load 0`` (a quiet machine). Code "before" is a
worktree at 28790cf, "after" this tree: each runs as ``python -m qradar`` with its tree
as the working directory and PYTHONPATH.

Counters: the old driver's ``dropped`` counted RADCs (ramps); here ``dropped_radcs``
is that figure, and its dropped frames are derived the way the current driver counts
them: (RADC gaps + RADCs discarded with a partial frame) // ramps per frame.

    .venv/bin/python benchmarks/bench_driver_load.py [--frames 2000] [--load 2] \\
        [--steps pty:before pty:after ser2net run ...] [--out results.json]

A step that does not end within frames/rate*1.5+60 s is stopped (SIGTERM, then SIGKILL)
and reported as timed out, with the counters it printed if any.
"""

from __future__ import annotations

import argparse
import bisect
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from pathlib import Path

from qradar.drivers import last_json_object

HERE = Path(__file__).resolve().parents[1]
CLK_TCK = os.sysconf("SC_CLK_TCK")
LINKS = ("pty", "ser2net", "pty-nopub", "ser2net-nopub", "run", "run-in-process")
CODES = ("before", "after")
DEFAULT_STEPS = ("pty:before", "pty:after", "ser2net:before", "ser2net:after", "run:before", "run:after")
BEFORE_COMMIT = "28790cf"
PROBE = Path(__file__).resolve().parent / "load_probe"
BUSY = "while True: pass"
#: --busy numpy: a matrix product loop (one BLAS thread each), the load of a lab laptop's other work
BUSY_NUMPY = ("import os; os.environ['OPENBLAS_NUM_THREADS'] = '1'\nimport numpy as np\n"
              "a = np.random.rand(300, 300)\nwhile True: a @ a")
PROGRESS_S = 20.0
#: each process in a session of its own (and so, with CONFIG_SCHED_AUTOGROUP, a scheduling
#: group of its own, like programs started from different terminals); --same-session: all
#: in the benchmark's session and group
NEW_SESSION = True
#: --latency-probe: a process that sleeps 2 ms at a time and reports how late it woke
LATENCY_PROBE = """
import json, signal, sys, time
late = []
signal.signal(signal.SIGTERM, lambda *a: (print(json.dumps(late)), sys.exit(0)))
while True:
    t = time.monotonic()
    time.sleep(0.002)
    late.append(round((time.monotonic() - t - 0.002) * 1e3, 3))
"""
START_TIMEOUT_S = 20.0
STOP_TIMEOUT_S = 10.0


# -- processes and their CPU -------------------------------------------------------------------
def proc_cpu_s(pid: int, children: bool = False) -> float | None:
    """utime + stime of a live (or zombie) process, s (with ``children``: and of the
    children it has reaped); None once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    n = 4 if children else 2
    return sum(int(x) for x in fields[11:11 + n]) / CLK_TCK  # fields 14-17 of stat(5)


def machine_busy_s() -> tuple[float, float]:
    """CPU seconds all cores spent running something since boot (user nice system irq
    softirq), and the seconds the hypervisor took from this machine (steal)."""
    f = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    return (f[0] + f[1] + f[2] + f[5] + f[6]) / CLK_TCK, (f[7] if len(f) > 7 else 0) / CLK_TCK


class Child:
    """A child process whose CPU time is taken from wait4 (its own and that of the
    children it reaped), with stdout kept and stderr tailed in threads."""

    def __init__(self, name: str, cmd: list[str], cwd: Path, env: dict, count_prefix: str | None = None):
        self.name, self.cmd = name, cmd
        self.proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, start_new_session=NEW_SESSION)
        self.t0 = time.monotonic()
        self.stdout: list[str] = []
        self.stderr_tail: deque[str] = deque(maxlen=40)
        self.count_prefix, self.counted = count_prefix, 0
        self.cpu_s: float | None = None
        self.wall_s: float | None = None
        self.returncode: int | None = None
        self._threads = [threading.Thread(target=self._read_out, daemon=True),
                         threading.Thread(target=self._read_err, daemon=True)]
        for t in self._threads:
            t.start()

    def _read_out(self) -> None:
        for line in self.proc.stdout:
            self.stdout.append(line)

    def _read_err(self) -> None:
        for line in self.proc.stderr:
            if self.count_prefix is not None and line.startswith(self.count_prefix):
                self.counted += 1  # the old drive's line per frame
            else:
                self.stderr_tail.append(line.rstrip("\n"))

    def poll(self) -> int | None:
        """The exit code once it has ended (reaped here with its rusage), else None."""
        if self.returncode is not None:
            return self.returncode
        pid, status, ru = os.wait4(self.proc.pid, os.WNOHANG)
        if pid == 0:
            return None
        self.returncode = self.proc.returncode = os.waitstatus_to_exitcode(status)
        self.cpu_s = ru.ru_utime + ru.ru_stime
        self.wall_s = time.monotonic() - self.t0
        for t in self._threads:
            t.join(5.0)
        return self.returncode

    def wait(self, timeout_s: float) -> int | None:
        deadline = time.monotonic() + timeout_s
        while self.poll() is None:
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.05)
        return self.returncode

    def stop(self, sig: int = signal.SIGTERM) -> int:
        """``sig``, then SIGKILL to the process group after STOP_TIMEOUT_S."""
        if self.poll() is None:
            try:
                os.kill(self.proc.pid, sig)
            except ProcessLookupError:
                pass
            if self.wait(STOP_TIMEOUT_S) is None:
                try:
                    if NEW_SESSION:
                        os.killpg(self.proc.pid, signal.SIGKILL)
                    else:
                        self.proc.kill()
                except ProcessLookupError:
                    pass
                self.wait(STOP_TIMEOUT_S)
        return self.returncode

    def last_json(self) -> dict:
        return last_json_object(self.stdout)


class BusyLoops:
    """``n`` busy-loop processes; ``share()`` is each one's CPU s / wall s."""

    def __init__(self, n: int, code: str = BUSY):
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
        self.procs = [subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.DEVNULL, env=env,
                                       start_new_session=NEW_SESSION) for _ in range(n)]
        self.t0 = time.monotonic()
        self.cpu_s: list[float] = []
        self.wall_s = 0.0

    def stop(self) -> None:
        self.wall_s = time.monotonic() - self.t0
        self.cpu_s = [proc_cpu_s(p.pid) or 0.0 for p in self.procs]
        for p in self.procs:
            p.kill()
        for p in self.procs:
            p.wait(STOP_TIMEOUT_S)

    def shares(self) -> list[float]:
        return [round(c / self.wall_s, 3) for c in self.cpu_s] if self.wall_s else []


# -- counters ------------------------------------------------------------------------------
def normalize(counters: dict, ramps: int = 2) -> dict:
    """The figures of the table from a driver's counters, old or new."""
    if not counters:
        return {}
    if "dropped_radcs" in counters:  # the current driver counts both
        return {"dropped_frames": counters["dropped"], "dropped_radcs": counters["dropped_radcs"],
                "dropped_frames_derived": False}
    # the old driver: ``dropped`` were RADC gaps; frames as the current one counts them
    return {"dropped_frames": (counters["dropped"] + counters.get("discarded_ramps", 0)) // ramps,
            "dropped_radcs": counters["dropped"], "dropped_frames_derived": True}


# -- one trial -------------------------------------------------------------------------------
def load_ser2net(path: str | None):
    """The Ser2net class of tests/ser2net_helpers.py (this tree's, or ``path``'s)."""
    for d in ([Path(path)] if path else []) + [HERE / "tests", Path("/work/wt-s2n/tests")]:
        if (d / "ser2net_helpers.py").is_file():
            sys.path.insert(0, str(d))
            import ser2net_helpers

            return ser2net_helpers.Ser2net
    raise SystemExit("tests/ser2net_helpers.py not found (give --ser2net-helpers DIR)")


def wait_for_link(sim: Child, link: Path) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while not (link.is_symlink() and sim.stdout):
        if sim.poll() is not None:
            raise RuntimeError(f"qradar sim exited ({sim.returncode}): {' | '.join(sim.stderr_tail)}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"qradar sim made no link {link} within {START_TIMEOUT_S} s")
        time.sleep(0.05)


def trial(step: str, args, trees: dict[str, Path], ser2net_cls) -> dict:
    link_kind, code = step.split(":")
    tree = trees[code]
    env = dict(os.environ, PYTHONPATH=str(tree), PYTHONUNBUFFERED="1")
    trace_dir = None
    if args.trace is not None:
        trace_dir = args.trace / f"{step.replace(':', '-')}-load{args.load}-{time.strftime('%H%M%S')}"
        trace_dir.mkdir(parents=True, exist_ok=True)
        env.update(PYTHONPATH=f"{tree}{os.pathsep}{PROBE}", QRADAR_PROBE_DIR=str(trace_dir))
    py = (["chrt", "-f", str(args.chrt)] if args.chrt else []) + [args.python, "-m", "qradar"]
    limit_s = args.frames / args.rate * 1.5 + 60
    out: dict = {"step": step, "link": link_kind, "code": code, "frames_wanted": args.frames, "load": args.load,
                 "loadavg_start": Path("/proc/loadavg").read_text().split()[:3]}
    busy_before = machine_busy_s()
    t_trial = time.monotonic()
    busy = BusyLoops(args.load, BUSY_NUMPY if args.busy == "numpy" else BUSY)
    sim = s2n = driver = lat = None
    other = None
    if args.other:
        other = subprocess.Popen(["bash", "-c", f"while true; do {args.other}; done"], cwd=HERE,
                                 stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                 start_new_session=True)
    if args.latency_probe:
        lat = Child("latency", [args.python, "-c", LATENCY_PROBE], HERE, dict(os.environ))
    time.sleep(0.5)  # let the busy loops take the cores
    try:
        with tempfile.TemporaryDirectory(prefix="qradar-bench-load-") as tmp:
            tmp = Path(tmp)
            if link_kind.startswith("run"):
                cmd = py + ["run", "--frames", str(args.frames), "--rate", str(args.rate), "--scene", args.scene,
                            "--no-record", "--json", "--duration", str(round(limit_s - 30, 1))]
                if link_kind == "run-in-process":
                    if code == "before":
                        raise ValueError("run-in-process:before is run:before (the old run had no driver process)")
                    cmd.append("--driver-in-process")
            else:
                link = tmp / "kmd2"
                sim_tree, sim_env = (trees["after"], dict(env, PYTHONPATH=env["PYTHONPATH"].replace(
                    str(tree), str(trees["after"]), 1))) if args.sim_after else (tree, env)
                sim = Child("sim", py + ["sim", "--link", str(link), "--rate", str(args.rate), "--scene",
                                         args.scene, *args.sim_args.split()], sim_tree, sim_env)
                wait_for_link(sim, link)
                url = str(link)
                if link_kind.startswith("ser2net"):
                    s2n = ser2net_cls(link, "raw", tmp).start()
                    url = s2n.url
                cmd = py + ["drive", "--port", url, "--frames", str(args.frames), "--json"]
                if code == "after":
                    cmd.append("--quiet")
                if code == "before" and link_kind.startswith("ser2net"):
                    cmd += ["--baud", "115200"]  # the old driver would switch the sensor to 2 Mbd
                if link_kind.endswith("-nopub"):
                    cmd.append("--no-publish")
                if code == "after":
                    cmd += args.drive_args.split()
            out["cmd"] = " ".join(cmd[cmd.index("-m"):])
            driver = Child("driver", cmd, tree, env, count_prefix="frame " if code == "before" else None)
            next_progress = time.monotonic() + PROGRESS_S
            timed_out = False
            while driver.poll() is None:
                now = time.monotonic()
                if now - driver.t0 > limit_s:
                    timed_out = True
                    driver.stop()
                    break
                if now >= next_progress:
                    next_progress += PROGRESS_S
                    seen = f", {driver.counted} frames so far" if driver.counted else ""
                    print(f"  [{step}] {now - driver.t0:5.0f} s{seen}", file=sys.stderr, flush=True)
                time.sleep(0.1)
            out["timed_out"] = timed_out
            out["exit_code"] = driver.returncode
            out["wall_s"] = round(driver.wall_s, 2)
            out["driver_cpu_s"] = round(driver.cpu_s, 2)
            result = driver.last_json()
            if link_kind.startswith("run"):
                counters = next(iter(result.get("driver", {}).values()), {})
                out["run"] = {k: result.get(k) for k in ("seconds", "frames_raw", "frames_quantized",
                                                          "frames_targets", "drops", "drops_detail", "latency_ms",
                                                          "frames_missing", "simulator")}
                out["run_sensor_frames_reported"] = (result.get("drops_detail") or {}).get("sensor_frames")
            else:
                counters = {k: v for k, v in result.items() if isinstance(v, int)}
            if "error" in result:
                out["error"] = result["error"]
            out["counters"] = counters
            out.update(normalize(counters))
            if not counters:
                out["stderr_tail"] = list(driver.stderr_tail)[-10:]
    finally:
        for child in (driver,):
            if child is not None:
                child.stop()
        if s2n is not None:
            s2n.stop()
        if sim is not None:
            sim.stop()
            out["sim_cpu_s"] = round(sim.cpu_s or 0.0, 2)
            out["sim_warnings"] = [ln for ln in sim.stderr_tail if "WARNING" in ln][-5:]
            out["sim_said"] = [ln.rstrip() for ln in sim.stdout[1:]]  # after its start-up line
        if lat is not None:
            lat.stop()
            try:
                late = sorted(json.loads(lat.stdout[-1]))
                out["wake_late_ms"] = {"n": len(late), "p50": late[len(late) // 2], "p99": late[int(len(late) * .99)],
                                       "max": late[-1], "over_10ms": sum(x > 10 for x in late),
                                       "over_25ms": sum(x > 25 for x in late)}
            except (IndexError, ValueError):
                out["wake_late_ms"] = None
        busy.stop()
        if other is not None:
            out["other_work_cpu_s"] = round(proc_cpu_s(other.pid, children=True) or 0.0, 1)
            os.killpg(other.pid, signal.SIGKILL)
            other.wait(STOP_TIMEOUT_S)
    out["trial_wall_s"] = round(time.monotonic() - t_trial, 2)
    out["busy_cpu_s"] = [round(c, 1) for c in busy.cpu_s]
    out["busy_share"] = busy.shares()
    total, steal = (a - b for a, b in zip(machine_busy_s(), busy_before))
    ours = sum(busy.cpu_s) + ((lat.cpu_s or 0.0) if lat else 0.0) + ((driver.cpu_s or 0.0) if driver else 0.0) + ((sim.cpu_s or 0.0) if sim else 0.0)
    out["machine_cpu_share"] = round(total / out["trial_wall_s"] / os.cpu_count(), 3)
    # CPU used by the rest of the machine: --other, ser2net, and whatever else runs on it
    out["others_cpu_s"] = round(max(0.0, total - ours), 1)
    out["steal_s"] = round(steal, 2)
    out["loadavg_end"] = Path("/proc/loadavg").read_text().split()[:3]
    if trace_dir is not None:
        out["trace_dir"] = str(trace_dir)
        out["trace"] = analyze_trace(trace_dir, args.rate * 2)
    return out


# -- the probe's timings ---------------------------------------------------------------------------
def _after(times: list[float], t: float) -> float | None:
    i = bisect.bisect_left(times, t)
    return times[i] if i < len(times) else None


def _pcts(v: list[float]) -> dict:
    if not v:
        return {}
    v = sorted(v)
    q = lambda p: round(v[min(len(v) - 1, int(p * len(v)))] * 1e3, 2)  # noqa: E731
    return {"p50_ms": q(0.5), "p99_ms": q(0.99), "p999_ms": q(0.999), "max_ms": round(v[-1] * 1e3, 2)}


def analyze_trace(trace_dir: Path, radc_rate_hz: float) -> dict:
    """Each GNFD cycle of the trial, from the probe's timings (benchmarks/load_probe): the
    simulated sensor wrote DONE k at ``w`` (``sim_late`` = w - the time RADC k was due),
    the driver read it at ``r`` (``to_host`` = r - w: the host's wake-up, its GIL, and
    ser2net's relay when there is one), wrote the next GNFD at ``p`` (``host`` = p - r),
    the simulator read it at ``g`` (``to_sim`` = g - p) and answered from its clock at
    ``now``. RADC k+1 was due 1/radc_rate after RADC k: a GNFD read after that finds
    the counter advanced (a drop). Each drop is listed with these parts, the driver's
    GC passes and publishes that overlap [w, p], and where it happened: ``sim`` when the
    simulator's own parts (sim_late + to_sim) outweigh the host's (to_host + host), a
    simulated sensor starved by the load where a real one, on its own clock, would not
    have been; ``host`` otherwise; ``?`` when the GNFD had gone out before DONE k was read
    (two in flight, ``drive --outstanding 2``), where there is no such chain."""
    ev: dict[str, list] = {}
    driver_gc: list = []
    for f in sorted(trace_dir.glob("*.json")):
        d = json.loads(f.read_text())
        for k in ("gnfd_in", "ramp", "done_out", "done_in", "gnfd_out", "publish"):
            ev.setdefault(k, []).extend(d.get(k, []))
        if d.get("done_in"):
            driver_gc.extend(d.get("gc", []))
    if not ev.get("ramp") or not ev.get("done_in"):
        return {"error": f"no probe data in {trace_dir}"}
    period = 1.0 / radc_rate_hz
    due = {r[2]: r[3] for r in ev["ramp"] if r[3] is not None}
    wrote = {c: t1 for _, t1, c, _ in ev["done_out"]}
    read = {}
    for t, c, _ in ev["done_in"]:
        read.setdefault(c, t)
    polls = sorted(t0 for t0, _ in ev["gnfd_out"])
    gin = sorted(ev["gnfd_in"])
    parts: dict[str, list[float]] = {k: [] for k in ("sim_late", "to_host", "host", "to_sim", "slack")}
    drops = []
    for now, before, idx, *rest in ev["ramp"]:
        next_due = rest[1] if len(rest) > 1 and rest[1] is not None else None
        if before < 0 or before not in due or before not in wrote or before not in read:
            continue
        w, r = wrote[before], read[before]
        p = _after(polls, r)
        g = _after(gin, p) if p is not None else None
        if p is None or g is None or g > now + 1e-3:
            # the GNFD answered here went out before DONE k was read (drive --outstanding 2):
            # no chain to take apart, only whether it was late
            if idx > before + 1:
                drops.append({"counter": before, "lost": idx - before - 1, "where": "?",
                              "sim_late_ms": round((w - due[before]) * 1e3, 2)})
            continue
        row = {"sim_late": w - due[before], "to_host": r - w, "host": p - r, "to_sim": g - p,
               "slack": (next_due if next_due is not None else due[before] + period) - now}
        for k, v in row.items():
            parts[k].append(v)
        if idx > before + 1:
            at_sim = row["sim_late"] + row["to_sim"] >= row["to_host"] + row["host"]
            gcs = [round((b - a) * 1e3, 2) for a, b, _ in driver_gc if b > w and a < p]
            pubs = [round((b - a) * 1e3, 2) for a, b in ev["publish"] if b > w and a < p]
            drops.append({"counter": before, "lost": idx - before - 1, "where": "sim" if at_sim else "host",
                          "at_s": round(due[before] - due.get(0, due[before]), 1),
                          **{k + "_ms": round(v * 1e3, 2) for k, v in row.items()},
                          "gc_ms": gcs, "publish_ms": pubs})
    return {"cycles": len(parts["slack"]),
            "lost_radcs_by": {w: sum(d["lost"] for d in drops if d["where"] == w) for w in ("sim", "host", "?")},
            "drops": drops, "parts": {k: _pcts(v) for k, v in parts.items()},
            "driver_gc_passes": len(driver_gc), "driver_gc_max_ms": round(max(((b - a) for a, b, _ in driver_gc),
                                                                                default=0) * 1e3, 2)}


# -- the report -------------------------------------------------------------------------------
def table(rows: list[dict]) -> str:
    head = ("| step | link | code | frames | dropped frames | dropped RADCs | timeouts | reconnects | wall s "
            "| busy-loop CPU share | other CPU s | lost RADCs at sim / host | wake-up late > 25 ms "
            "| run: sim late writes / driver drops / node queue drops |")
    lines = [head, "|" + "|".join("---" for _ in range(head.count("|") - 1)) + "|"]
    for r in rows:
        c = r.get("counters", {})
        frames = c.get("frames", "–")
        dropped = r.get("dropped_frames", "–")
        if r.get("dropped_frames_derived"):
            dropped = f"{dropped}*"
        note = " (timed out)" if r.get("timed_out") else (f" ({r['error']})" if r.get("error") else "")
        share = " / ".join(f"{s:.2f}" for s in r.get("busy_share", [])) or "–"
        by = (r.get("trace") or {}).get("lost_radcs_by")
        where = (f"{by['sim']} / {by['host']}" + (f" (+{by['?']} ?)" if by.get("?") else "")) if by else "–"
        late = (r.get("wake_late_ms") or {}).get("over_25ms", "–")
        run = r.get("run") or {}
        by_where = "–"
        if run:
            sim_late = (run.get("simulator") or {}).get("late_writes", "– (no hold)")
            d = run.get("drops_detail") or {}
            by_where = f"{sim_late} / {d.get('sensor_frames', '–')} / {d.get('node_queues', '–')}"
        lines.append(f"| {r['step']}{note} | {r['link']} | {r['code']} | {frames} | {dropped} | "
                     f"{r.get('dropped_radcs', '–')} | {c.get('timeouts', '–')} | {c.get('reconnects', '–')} | "
                     f"{r.get('wall_s', '–')} | {share} | {r.get('others_cpu_s', '–')} | {where} | {late} "
                     f"| {by_where} |")
    return "\n".join(lines)


def parse_steps(tokens: list[str]) -> list[str]:
    steps = []
    for tok in tokens:
        link, _, code = tok.partition(":")
        if link not in LINKS or (code and code not in CODES):
            raise SystemExit(f"--steps {tok!r}: LINK[:CODE] with LINK in {LINKS}, CODE in {CODES}")
        for c in ([code] if code else [c for c in CODES if not (link == "run-in-process" and c == "before")]):
            steps.append(f"{link}:{c}")
    return steps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=2000, help="frames per trial")
    ap.add_argument("--rate", type=float, default=20.0, help="the simulated sensor's frames/s")
    ap.add_argument("--scene", default="chamber")
    ap.add_argument("--load", type=int, default=2, help="busy-loop processes (0: a quiet baseline)")
    ap.add_argument("--busy", choices=("python", "numpy"), default="python",
                    help="what a busy loop runs: a bare Python loop, or numpy matrix products (one BLAS thread)")
    ap.add_argument("--steps", nargs="+", default=list(DEFAULT_STEPS),
                    help=f"LINK[:CODE], LINK in {', '.join(LINKS)}; CODE before|after (both if omitted)")
    ap.add_argument("--before", type=Path, default=Path("/work/wt-before"),
                    help=f"a worktree at {BEFORE_COMMIT} (git worktree add DIR {BEFORE_COMMIT})")
    ap.add_argument("--after", type=Path, default=HERE, help="the tree of the current code (default: this one)")
    ap.add_argument("--sim-after", action="store_true",
                    help="the current simulator for the before steps too (default: each tree its own)")
    ap.add_argument("--sim-args", default="", metavar="ARGS",
                    help="more arguments for qradar sim (e.g. '--line-rate'; one the old sim lacks needs --sim-after)")
    ap.add_argument("--drive-args", default="", metavar="ARGS",
                    help="more arguments for the current qradar drive (the after steps over pty and ser2net)")
    ap.add_argument("--python", default=sys.executable, help="the interpreter with qradar's dependencies")
    ap.add_argument("--ser2net-helpers", default=None, help="directory of ser2net_helpers.py")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    ap.add_argument("--latency-probe", action="store_true",
                    help="also run a process that sleeps 2 ms at a time and report how late it woke (the machine's "
                         "scheduling noise, beside the driver's)")
    ap.add_argument("--chrt", type=int, default=0, metavar="PRIO",
                    help="run the simulator and the driver (or the run) SCHED_FIFO at PRIO (chrt -f; root): "
                         "tells scheduling delays from stalls below the scheduler (0: normal priority)")
    ap.add_argument("--other", default=None, metavar="CMD",
                    help="other work beside the busy loops: a shell command run over and over during each trial "
                         "(e.g. '.venv/bin/python -m qradar montecarlo --K 1 2 --runs 20000 --out /tmp/mc --quiet "
                         "--no-plots')")
    ap.add_argument("--same-session", action="store_true",
                    help="start every process in the benchmark's session (one autogroup) instead of one each")
    ap.add_argument("--trace", type=Path, default=None,
                    help="time each GNFD cycle (benchmarks/load_probe) into DIR and report where drops come from")
    args = ap.parse_args()
    global NEW_SESSION
    NEW_SESSION = not args.same_session
    steps = parse_steps(args.steps)
    trees = {"before": args.before.resolve(), "after": args.after.resolve()}
    for code in {s.split(":")[1] for s in steps}:
        if not (trees[code] / "qradar" / "__main__.py").is_file():
            raise SystemExit(f"{trees[code]} is no qradar tree (--{code})")
    ser2net_cls = load_ser2net(args.ser2net_helpers) if any("ser2net" in s for s in steps) else None
    rows, t0 = [], time.monotonic()
    for i, step in enumerate(steps, 1):
        print(f"[{i}/{len(steps)}] {step}, load {args.load}, {args.frames} frames at {args.rate:g}/s ...",
              file=sys.stderr, flush=True)
        try:
            r = trial(step, args, trees, ser2net_cls)
        except Exception as exc:  # one failed step does not lose the others
            r = {"step": step, "link": step.split(":")[0], "code": step.split(":")[1], "error": str(exc)}
        except BaseException as exc:  # pytest.fail from the ser2net helper
            if isinstance(exc, KeyboardInterrupt):
                raise
            r = {"step": step, "link": step.split(":")[0], "code": step.split(":")[1], "error": str(exc)}
        rows.append(r)
        print(f"[{i}/{len(steps)}] {step}: frames {r.get('counters', {}).get('frames')}, dropped frames "
              f"{r.get('dropped_frames')}, dropped RADCs {r.get('dropped_radcs')}, wall {r.get('wall_s')} s, "
              f"busy {r.get('busy_share')}{' TIMED OUT' if r.get('timed_out') else ''}"
              f"{' error: ' + r['error'] if r.get('error') else ''}", file=sys.stderr, flush=True)
    result = {"frames": args.frames, "rate_hz": args.rate, "load": args.load, "busy": args.busy, "scene": args.scene,
              "other": args.other, "chrt": args.chrt, "same_session": args.same_session, "sim_after": args.sim_after,
              "sim_args": args.sim_args, "drive_args": args.drive_args,
              "cpus": os.cpu_count(), "before_tree": str(trees["before"]), "after_tree": str(trees["after"]),
              "total_wall_s": round(time.monotonic() - t0, 1), "trials": rows}
    text = json.dumps(result, indent=2)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")
    print()
    print(table(rows))
    print("\n* derived: the old driver counted RADCs; frames = (RADC gaps + discarded RADCs) // 2")


if __name__ == "__main__":
    main()
