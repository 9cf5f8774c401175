#!/usr/bin/env python3
"""The benchmarks ``make bench`` runs, each in a fresh process, one after the other: every
script of docs/benchmarks.md that runs alone on one host. ``--short`` gives each its
shortest options (a smoke run of a few seconds each, its figures not worth quoting);
without it each runs with its defaults (the documented figures; bench_stream.py's sweep
alone takes 1-2 h). Left out, each run by hand with its own command in docs/benchmarks.md:
bench_multihost.py (root, network namespaces), bench_ser2net.py (ser2net installed),
bench_driver_load.py and soak.py (load trials of 10 min and more), bench_web_plotlib.py (npm and the
registry), and the accuracy studies
(cml_likelihood.py, chamber_frontend.py, sweep_alpha.py, track_integration.py).

    .venv/bin/python benchmarks/suite.py [--short] [--only bench_pbp bench_cml ...] [--list] [--results DIR]

Each script writes its figures, with the run's date, host and command, to ``<DIR>/<script>.json``
(``harness.emit``; DIR is ``benchmarks/results`` for a full run, ``out/bench-short`` with
``--short``, whose figures are not worth quoting). docs/benchmarks.md's current figures are made
from ``benchmarks/results``: ``.venv/bin/python benchmarks/figures.py --update docs/benchmarks.md``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from harness import RESULTS_ENV

HERE = Path(__file__).resolve().parent
#: where a full run's result files go (committed: docs/benchmarks.md's current figures read them)
RESULTS = HERE / "results"
#: where a short (smoke) run's go, never over the quoted ones
SHORT_RESULTS = HERE.parent / "out" / "bench-short"


@dataclass(frozen=True)
class Step:
    """One script of the suite: its file in benchmarks/ and its arguments in short mode."""

    script: str
    short: tuple[str, ...] = ()


#: the suite, in the order it runs (the one list `make bench` and docs/benchmarks.md refer to)
SUITE: tuple[Step, ...] = (
    Step("bench_pbp.py", ("--batch", "256", "--single", "20", "--repeat", "1")),
    Step("bench_cml.py", ("--seconds", "2", "--batch", "16")),
    Step("bench_decoders.py", ("--batches", "1,16", "--repeats", "1", "--algos", "pbp")),
    Step("bench_driver.py", ("--frames", "100")),
    Step("bench_codec.py", ("--repeat", "1")),
    Step("bench_wire.py", ("--repeat", "1")),
    Step("bench_noise.py", ("--repeat", "1")),
    Step("bench_track.py", ("--seconds", "1", "--frames", "40")),
    Step("bench_localize_steps.py", ("--frames", "64", "--batches", "1,16", "--passes", "1")),
    Step("bench_nodes.py", ("--sensors", "20", "--frames", "400")),
    Step("bench_health.py"),
    Step("bench_expiry.py", ("--ids", "500", "--rounds", "1")),
    Step("bench_receive.py", ("--messages", "1500", "--rate", "3000", "--rounds", "1")),
    Step("bench_record.py", ("--sensors", "10", "--seconds", "1", "--rates", "10")),
    Step("bench_reading.py", ("--minutes", "2", "--repeat", "1")),
    Step("bench_secure.py", ("--messages", "2000", "--rounds", "1")),
    Step("bench_stream.py", ("--quick",)),
    Step("bench_isolation.py", ("--case", "quantized", "--seconds", "3", "--warmup", "3", "--rate", "1000")),
    Step("bench_web.py", ("--sensors", "0", "3", "--seconds", "2", "--warmup", "1")),
)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--short", action="store_true", help="each script with its shortest options")
    ap.add_argument("--only", nargs="+", default=None, metavar="NAME", help="these scripts only (bench_pbp ...)")
    ap.add_argument("--list", action="store_true", help="print the commands and run nothing")
    ap.add_argument("--results", type=Path, default=None, metavar="DIR",
                    help=f"each script's figures as DIR/<script>.json (default: {RESULTS.relative_to(HERE.parent)}, "
                         f"with --short {SHORT_RESULTS.relative_to(HERE.parent)})")
    args = ap.parse_args()
    results = args.results or (SHORT_RESULTS if args.short else RESULTS)
    env = {**os.environ, RESULTS_ENV: str(results.resolve())}
    steps = list(SUITE)
    if args.only is not None:
        names = {s.script.removesuffix(".py") for s in SUITE}
        unknown = sorted(set(args.only) - names)
        if unknown:
            raise SystemExit(f"suite: --only {' '.join(unknown)}: not in the suite ({', '.join(sorted(names))})")
        steps = [s for s in SUITE if s.script.removesuffix(".py") in args.only]
    failed = []
    for step in steps:
        cmd = [sys.executable, str(HERE / step.script), *(step.short if args.short else ())]
        print(f"== benchmarks/{step.script} {' '.join(cmd[2:])}", flush=True)
        if args.list:
            continue
        t0 = time.monotonic()
        rc = subprocess.run(cmd, check=False, env=env).returncode
        print(f"== {step.script}: exit {rc}, {time.monotonic() - t0:.1f} s", flush=True)
        if rc != 0:
            failed.append(step.script)
    if not args.list:
        print(f"suite: figures in {results}", flush=True)
        if results.resolve() == RESULTS.resolve() and not failed:
            # docs/benchmarks.md's current figures, from the result files just written
            rc = subprocess.run([sys.executable, str(HERE / "figures.py"), "--update",
                                 str(HERE.parent / "docs" / "benchmarks.md")], check=False).returncode
            if rc != 0:
                failed.append("figures.py")
    if failed:
        print(f"suite: {len(failed)} of {len(steps)} failed: {' '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
