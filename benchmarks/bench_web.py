#!/usr/bin/env python3
"""The web view's cost (``qradar view --web``): the view process's CPU per sensor, and the
page's frame time in headless chromium, at N sensors of 20 frames/s each.

For each N, a fresh ``qradar view --web 0 --listen tcp/127.0.0.1:P`` process (the view alone
in its process, range profiles of every frame: its default), N simulated sensors (the
``chamber-ideal`` scene, two reflectors) through a quantizer and a PBP localizer with tracks
in this process, connected to it, and one headless chromium page on it
(tests/chromium.py). After ``--warmup`` s, for ``--seconds``: the view's CPU (user +
system, from /proc), the page's frame time (its own work per frame: the events it handled
since the last frame and the drawing, ``performance.now()``), the interval between its
animation frames, the frames the browser itself counts over 50 ms (Long Animation Frames),
the targets each sensor got through, and the events the view dropped for the page. N = 0 is
the view and the page with nothing to show. Prints one JSON object (``harness.emit``), each
count's figures under ``sensors_<N>``.

    .venv/bin/python benchmarks/bench_web.py [--sensors 0 1 3 6] [--seconds 10] [--warmup 3]
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import threading
import time

import harness
from harness import ROOT, cpu_s, emit, free_port, machine
from pipeline.bus.session import BusConfig
from pipeline.dsp.quantize import QuantizerConfig
from pipeline.dsp.track import TrackerConfig
from pipeline.nodes.stream import LocalizeNode, LocalizerConfig, QuantizeNode, SourceNode, run_nodes
from radar_driver.scene import resolve_scene
from radar_driver.source import SimSourceConfig, SimulatedSource

RATE_HZ = 20.0


def start_view(zenoh_port: int) -> tuple[subprocess.Popen, str]:
    """``qradar view --web 0`` listening for zenoh on ``zenoh_port``; (process, page URL)."""
    proc = subprocess.Popen([str(ROOT / ".venv" / "bin" / "qradar"), "view", "--web", "0", "--listen",
                             f"tcp/127.0.0.1:{zenoh_port}"], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    for _ in range(50):
        line = proc.stderr.readline()
        m = re.search(r"web page on (\S+) ", line)
        if m:
            threading.Thread(target=proc.stderr.read, daemon=True).start()  # drained, never blocks the view
            return proc, m.group(1).rstrip(";")
        if not line:
            break
    proc.kill()
    raise RuntimeError(f"qradar view --web did not start: {line!r}")


def measure(n: int, seconds: float, warmup: float, browser) -> dict:
    zport = free_port()
    view, url = start_view(zport)
    stop = threading.Event()
    job = None
    try:
        page = browser.open(url)
        page.wait_for("window.qradarView && window.qradarView.stats().connected", 15.0, "the page to connect")
        if n:
            bus = BusConfig(connect=(f"tcp/127.0.0.1:{zport}",))
            session = bus.open()
            nodes = [LocalizeNode(bus, LocalizerConfig(k=2, algo="pbp"), session=session, tracking=TrackerConfig()),
                     QuantizeNode(bus, QuantizerConfig(alpha=1.0, dither_seed=3), session=session),
                     SourceNode(bus, SimulatedSource(SimSourceConfig(resolve_scene("chamber-ideal"), sensors=n,
                                                                     rate_hz=RATE_HZ, id_prefix="b")),
                                session=session)]
            job = threading.Thread(target=run_nodes, args=(nodes, None, stop), daemon=True)
            job.start()
            page.wait_for(f"Object.values(window.qradarView.stats().sensors).filter(s => s.profile).length === {n}",
                          30.0, f"{n} sensors on the page")
        time.sleep(warmup)
        page.evaluate("window.qradarView.resetTimings()")
        before, c0, t0 = page.evaluate("window.qradarView.stats()"), cpu_s(view.pid), time.monotonic()
        time.sleep(seconds)
        after, c1, t1 = page.evaluate("window.qradarView.stats()"), cpu_s(view.pid), time.monotonic()
    finally:
        stop.set()
        if job is not None:
            job.join(30)
            session.close()
        view.terminate()
        view.wait(30)
    wall = t1 - t0
    got = {s: round((after["sensors"][s]["frames"] - before["sensors"][s]["frames"]) / wall, 1)
           for s in after["sensors"]}
    r = lambda v: None if v is None else round(v, 2)  # noqa: E731
    return {"sensors": n, "seconds": round(wall, 2), "view_cpu_pct": round(100 * (c1 - c0) / wall, 1),
            "page": {"frame_ms": {k: r(after["frame"][k]) for k in ("p50", "p99", "max")},
                     "drawing_ms": {k: r(after["render"][k]) for k in ("p50", "p99", "max")},
                     "interval_ms": {k: r(after["interval"][k]) for k in ("p50", "p99", "max")},
                     "frames": after["interval"]["n"], "frames_over_50ms": after["longFrames"],
                     "targets_hz": got, "dropped_by_view": after["dropped"] - before["dropped"],
                     "first_targets_ms": r(after["firstTargetsMs"])}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sensors", type=int, nargs="+", default=[0, 1, 3, 6], help="sensor counts (0: idle view)")
    ap.add_argument("--seconds", type=float, default=10.0, help="measured seconds per count")
    ap.add_argument("--warmup", type=float, default=3.0, help="seconds before measuring")
    args = ap.parse_args()
    chromium = harness.tests_module("chromium")
    runs = []
    with chromium.Chromium() as browser:
        for n in args.sensors:
            runs.append(measure(n, args.seconds, args.warmup, browser))
            print(f"bench_web: {n} sensor(s): view {runs[-1]['view_cpu_pct']} % of a core, page frame time p99 "
                  f"{runs[-1]['page']['frame_ms']['p99']} ms", file=sys.stderr, flush=True)
    idle = next((x["view_cpu_pct"] for x in runs if x["sensors"] == 0), None)
    for x in runs:
        if x["sensors"]:
            x["view_cpu_pct_per_sensor"] = round(x["view_cpu_pct"] / x["sensors"], 2)
            if idle is not None:
                x["view_cpu_pct_per_sensor_above_idle"] = round((x["view_cpu_pct"] - idle) / x["sensors"], 2)
    emit({"machine": machine(), "rate_hz": RATE_HZ, **{f"sensors_{x['sensors']}": flat(x) for x in runs}})


def flat(run: dict) -> dict:
    """One count's figures, one level: the page's as ``page_<figure>[_<p50|p99|max>]``, the
    targets each sensor got through as ``targets_hz_<sensor>``."""
    out = {k: v for k, v in run.items() if k != "page"}
    for k, v in run["page"].items():
        if k == "targets_hz":
            out |= {f"targets_hz_{sensor}": hz for sensor, hz in v.items()}
        elif isinstance(v, dict):
            out |= {f"page_{k}_{stat}": x for stat, x in v.items()}
        else:
            out[f"page_{k}"] = v
    return out


if __name__ == "__main__":
    main()
