#!/usr/bin/env python3
"""The streaming chain at 20 frames/s per sensor: the largest sensor count that loses no
frame with latency p99 <= 20 ms, on this host, zenoh TCP on 127.0.0.1.

Cases: ``central`` (``qradar source`` raw -> ``quantize`` -> ``localize``) and ``edge``
(``qradar source --quantized`` -> ``localize``), sensors sending in one burst per tick or
spread over the period (``--send``), decoders ``--algo pbp qiht cml``; ``--localizers N``
(``--shard i/N``) and ``--quantizers N``. Every step starts fresh processes (the hub, the
nodes, a sink process on radar/*/targets, the source), runs ``--warmup`` s not counted then
``--seconds`` measured, and stops them all. A step passes when every frame past the
warm-up has its targets exactly once, every node's totals count no drop, error or missing
frame, the latency p99 (sensor timestamp -> targets published) is <= 20 ms and the
source kept its pace. Per step: p50/p99/max latency, frames sent/received, late ticks of
the source, CPU per process over the measured window (% of one core), the load average at
the start; with ``--baseline``, the same messages (count per second, sizes) through a bare
zenoh publisher -> subscriber pair of processes just before the step.

``--premade`` (edge only) separates the sensors from the host under test: every frame of
the sweep is simulated and quantized first, exactly as ``qradar source --quantized`` makes
it (``streamlib.make_premade``, ~70 µs a frame, with a progress bar), and a player process
sends them with the same pacing, each timestamp rewritten to its send time. The two cores
then carry the localizer, the sink and the sending alone, as a localizer host does whose
sensors quantize on their own hardware. ``--busy N`` runs N processes spinning on the CPU
through every step (started first, killed last): a host busy with other work.

Steps: ``--sensors`` in order, stopping at the first failure; ``--bisect`` then halves
the gap between the last pass and the first failure down to ``--resolution`` sensors.

    .venv/bin/python benchmarks/bench_stream.py                       # the full sweep (~1-2 h)
    .venv/bin/python benchmarks/bench_stream.py --case edge --algo pbp --sensors 300 400 500 --bisect
    .venv/bin/python benchmarks/bench_stream.py --case edge --send spread --premade --sensors 300 500 --bisect
    .venv/bin/python benchmarks/bench_stream.py --quick                # 5 sensors, 3 s, pbp: < 1 min

After the tables, the summary's figures as one JSON object (``harness.emit``), each keyed by
the case/send/decoder label as a name (``edge_burst_pbp``, ``central_spread_cml_2l_premade_1_busy`` ...).
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import sys
import tempfile
from pathlib import Path

import streamlib as sl
from harness import emit


def sweep(base: sl.StepSpec, counts: list[int], topo_factory, bisect: bool, resolution: int,
          progress: bool, on_row) -> list[dict]:
    """Steps of ``base`` at ``counts`` until the first failure (then bisect, if asked)."""
    rows: list[dict] = []

    def step(n: int) -> dict:
        spec = sl.StepSpec(**{**base.__dict__, "sensors": n})
        r = {"label": spec.label(), **sl.run_step(spec, topo_factory(), progress=progress)}
        rows.append(r)
        on_row(r)
        return r

    best, fail = 0, None
    for n in counts:
        r = step(n)
        if not r["ok"]:
            fail = n
            break
        best = n
    if bisect and fail is not None:
        lo, hi = best, fail
        for _ in range(12):  # bounded: 12 halvings
            if hi - lo <= resolution:
                break
            mid = (lo + hi) // 2
            if step(mid)["ok"]:
                lo = mid
            else:
                hi = mid
    return rows


def summary(rows: list[dict]) -> list[dict]:
    """Per case/send/algo: the largest passing step and the first failing one."""
    out = {}
    for r in rows:
        s = out.setdefault(r["label"], {"label": r["label"], "best": None, "first_fail": None})
        if r["ok"] and (s["best"] is None or r["sensors"] > s["best"]["sensors"]):
            s["best"] = r
        elif not r["ok"] and (s["first_fail"] is None or r["sensors"] < s["first_fail"]["sensors"]):
            s["first_fail"] = r
    return list(out.values())


def summary_markdown(summ: list[dict]) -> str:
    headers = ("case / send / decoder", "largest passing sensor count", "frames/s", "p50 / p99 (ms)",
               "CPU % of a core (at that count)", "next step: why it failed")
    rows = []
    for s in summ:
        b, f = s["best"], s["first_fail"]
        fail = f"{f['sensors']}: {'; '.join(f['reasons'])}" if f else "none failed"
        if b is None:
            rows.append([s["label"], "none", "–", "–", "–", fail])
        else:
            rows.append([s["label"], str(b["sensors"]), sl.fmt(b["offered_fps"], 0),
                         f"{sl.fmt(b['p50_ms'], 2)} / {sl.fmt(b['p99_ms'], 2)}", sl.cpu_cell(b), fail])
    return sl.markdown(headers, rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", nargs="+", choices=["central", "edge"], default=["central", "edge"])
    ap.add_argument("--send", nargs="+", choices=["burst", "spread"], default=["burst", "spread"])
    ap.add_argument("--algo", nargs="+", choices=["pbp", "qiht", "cml"], default=["pbp", "qiht", "cml"])
    ap.add_argument("--sensors", type=int, nargs="+", default=[50, 100, 200, 300, 400, 500])
    ap.add_argument("--seconds", type=float, default=60.0, help="measured seconds per step (default 60)")
    ap.add_argument("--warmup", type=float, default=5.0, help="seconds of traffic not counted (default 5)")
    ap.add_argument("--localizers", type=int, default=1, help="localize processes, each --shard i/N")
    ap.add_argument("--quantizers", type=int, default=1, help="quantize processes (central), each --shard i/N")
    ap.add_argument("--hub", choices=["node", "router"], default="node",
                    help="node: the first quantize (central) or localize (edge) listens and the others connect "
                    "to it; router: a `qradar router` listens and every node is its client")
    ap.add_argument("--alpha", type=float, default=1.0, help="dither scale of the quantizer (default 1)")
    ap.add_argument("--bisect", action="store_true", help="after the first failure, bisect down to --resolution")
    ap.add_argument("--resolution", type=int, default=10)
    ap.add_argument("--baseline", action="store_true", help="bare zenoh with the step's messages before each step")
    ap.add_argument("--baseline-seconds", type=float, default=5.0)
    ap.add_argument("--source-args", default=None, help="more options for `qradar source` (one string)")
    ap.add_argument("--quantize-args", default=None)
    ap.add_argument("--localize-args", default=None)
    ap.add_argument("--premade", action="store_true",
                    help="edge only: the sensors' frames are made (simulated and quantized) before the sweep "
                    "and a player sends them, timestamps rewritten: the host's cores carry only the sending, "
                    "the localizer and the sink, as with sensors on their own hardware")
    ap.add_argument("--busy", type=int, default=0,
                    help="this many processes spinning on the CPU through every step (a busy host)")
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run: 5 sensors, 3 s after 2 s of warm-up, pbp, burst (each unless given)")
    ap.add_argument("--json", type=Path, default=None, help="write every step and the summary here")
    args = ap.parse_args()
    if args.quick:
        given = set(a.split("=")[0] for a in sys.argv[1:])
        if "--sensors" not in given:
            args.sensors = [5]
        if "--seconds" not in given:
            args.seconds = 3.0
        if "--warmup" not in given:
            args.warmup = 2.0
        if "--algo" not in given:
            args.algo = ["pbp"]
        if "--send" not in given:
            args.send = ["burst"]
    progress = sys.stderr.isatty()
    if args.premade and args.case != ["edge"]:
        ap.error("--premade sends 1-bit frames: use it with --case edge")
    if args.premade and args.source_args:
        ap.error("--premade replaces `qradar source` (chamber scene, 1 bit): --source-args would be ignored")
    rows: list[dict] = []
    premade_dir = Path(tempfile.mkdtemp(prefix="qr-premade-")) if args.premade else None
    try:
        rows = run_sweeps(args, premade_dir, progress)
    finally:
        if premade_dir is not None:
            shutil.rmtree(premade_dir, ignore_errors=True)
    report(args, rows)


def run_sweeps(args, premade_dir: Path | None, progress: bool) -> list[dict]:
    rows: list[dict] = []
    premade = ""
    if premade_dir is not None:
        frames = int(round((args.warmup + args.seconds) * sl.RATE_HZ))
        premade = str(sl.make_premade(premade_dir / "frames.npy", "chamber", max(args.sensors), frames, args.alpha,
                                      1, sl.SENSOR_ID_PREFIX, progress=True))
    for case in args.case:
        for send in args.send:
            for algo in args.algo:
                base = sl.StepSpec(case=case, send=send, algo=algo, sensors=0, seconds=args.seconds,
                                   warmup_s=args.warmup, localizers=args.localizers, quantizers=args.quantizers,
                                   alpha=args.alpha, hub=args.hub,
                                   baseline_s=args.baseline_seconds if args.baseline else 0.0,
                                   source_args=sl.split_args(args.source_args),
                                   quantize_args=sl.split_args(args.quantize_args),
                                   localize_args=sl.split_args(args.localize_args), premade=premade,
                                   busy=args.busy)
                rows += sweep(base, args.sensors, sl.Loopback, args.bisect, args.resolution, progress,
                              lambda r: print(sl.step_line(r), file=sys.stderr, flush=True))
    return rows


def report(args, rows: list[dict]) -> None:
    summ = summary(rows)
    print(f"\n{len(rows)} steps, {args.seconds:g} s measured each after {args.warmup:g} s of warm-up, "
          f"20 frames/s per sensor; pass = 0 frames lost and p99 <= {sl.MAX_P99_MS:g} ms\n")
    print(summary_markdown(summ))
    print()
    print(sl.markdown(sl.STEP_COLUMNS, [sl.step_cells(r) for r in rows]))
    emit(figures(args, rows, summ))
    if args.json is not None:
        args.json.write_text(json.dumps({"summary": [{"label": s["label"], "best": (s["best"] or {}).get("sensors"),
                                                      "first_fail": (s["first_fail"] or {}).get("sensors"),
                                                      }
                                                     for s in summ],
                                         "steps": rows}, indent=1))


def figures(args, rows: list[dict], summ: list[dict]) -> dict:
    """The summary table's figures, two levels: per label (as a name, ``edge_burst_pbp``) the
    largest passing sensor count and, at that count, frames/s, p50/p99 latency and each
    process's CPU (key ``<label>_<process>``); the first failing count (None: none failed)."""
    def name(label: str) -> str:
        return re.sub(r"[^a-z0-9]+", "_", label.lower()).strip("_")

    fig: dict = {"steps": len(rows), "seconds_measured": args.seconds, "warmup_s": args.warmup,
                 "max_p99_ms": sl.MAX_P99_MS, "largest_passing_sensors": {}, "first_failing_sensors": {},
                 "frames_per_s_at_largest": {}, "p50_ms_at_largest": {}, "p99_ms_at_largest": {},
                 "cpu_pct_of_core_at_largest": {}}
    for s in summ:
        key, b, f = name(s["label"]), s["best"] or {}, s["first_fail"]
        fig["largest_passing_sensors"][key] = b.get("sensors")
        fig["first_failing_sensors"][key] = f["sensors"] if f else None
        fig["frames_per_s_at_largest"][key] = b.get("offered_fps")
        fig["p50_ms_at_largest"][key] = b.get("p50_ms")
        fig["p99_ms_at_largest"][key] = b.get("p99_ms")
        for proc, v in b.get("nodes", {}).items():
            fig["cpu_pct_of_core_at_largest"][f"{key}_{name(proc)}"] = v.get("cpu_pct")
    return fig


if __name__ == "__main__":
    try:
        main()
    except KeyboardInterrupt:
        sys.exit("interrupted: every process stopped" + (" and every namespace deleted" if "multihost" in __file__
                                                         else ""))
