#!/usr/bin/env python3
"""Decode cost per frame of pbp, qiht and cml at several batch sizes: 1-bit dithered frames
(alpha = 1, M = 512 = 2 ramps x 256 samples, 2 antennas) of off-grid scenes (ranges
uniform over 3-150 m, |theta| <= 60 deg, K = 2), each decoder told K. Only
``pipeline.dsp.decode.Decoder.decode`` (a decoder held across calls, as a node holds it) is
timed: the codes and the dither are made beforehand (the
dither's regeneration from its seed is not counted).

Each (decoder, batch) figure is the best, over ``--repeats`` calls, of the CPU time of
one call (process time) divided by the batch size; every call gets a fresh batch (its own scenes,
noise and dither seeds). The best of several is the figure least disturbed by the other
processes of a shared machine.

    .venv/bin/python benchmarks/bench_decoders.py [--batches 1,16,64,256] [--repeats 7]
        [--algos pbp,qiht,cml] [--baseline /work/main] [--rounds 2] [--json]

``--baseline DIR`` also times the code of another checkout (e.g. main) in a subprocess,
the two taking turns for ``--rounds`` rounds (best over the rounds), and prints both and
the speedup. ``--code DIR`` times the checkout at DIR instead of this one.

The figures (``harness.emit``, after the table; alone with ``--json``) are keyed
``<algo>_b<batch>``: ``ms_per_frame``, with ``--baseline`` also ``baseline_ms_per_frame``
and ``speedup`` (baseline over this).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from functools import partial
from pathlib import Path

from harness import RESULTS_ENV, emit, machine, time_calls

HERE = Path(__file__).resolve().parents[1]


def _parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batches", default="1,16,64,256", help="batch sizes, comma-separated")
    ap.add_argument("--repeats", type=int, default=7, help="calls per (decoder, batch), each on fresh frames")
    ap.add_argument("--algos", default="pbp,qiht,cml", help="decoders, comma-separated")
    ap.add_argument("--K", type=int, default=2, help="targets per frame")
    ap.add_argument("--code", type=Path, default=HERE, help="checkout whose pipeline is timed")
    ap.add_argument("--baseline", type=Path, default=None, help="checkout to compare with (e.g. /work/main)")
    ap.add_argument("--rounds", type=int, default=2, help="turns each checkout takes with --baseline")
    ap.add_argument("--json", action="store_true", help="print one JSON object only")
    args = ap.parse_args(argv)
    args.batch_list = [int(b) for b in args.batches.split(",")]
    args.algo_list = args.algos.split(",")
    if args.repeats < 1 or args.rounds < 1 or min(args.batch_list) < 1:
        ap.error("--repeats, --rounds and every batch size must be >= 1")
    return args


def measure(code: Path, batches: list[int], algos: list[str], repeats: int, k: int) -> dict[str, dict[str, float]]:
    """Best ms per frame {algo: {batch: ms}} of the pipeline in ``code``, in this process."""
    sys.path.insert(0, str(code))
    import numpy as np

    from pipeline.dsp import decode as decoders
    from pipeline.dsp.decode import DecoderConfig
    try:
        from experiments.montecarlo import SceneSpec, draw_scenes
    except ImportError:  # a checkout from before the Monte Carlo moved out of replay/
        from replay.montecarlo import SceneSpec, draw_scenes
    from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
    from radar_driver.model import RadarConfig, simulate_frames

    cfg = RadarConfig()
    scene = SceneSpec(ranges="continuous", max_angle_deg=60.0, min_amplitude=0.1)

    def frames(b: int, seed: int):
        _, _, r, a, x = draw_scenes(b, k, np.random.default_rng(seed), cfg, scene=scene)
        q = quantize_frames(simulate_frames(r, a, x, cfg), QuantizerConfig(alpha=1.0), np.arange(b) + seed * b)
        return q.values(), q.dither(), q.delta

    out: dict[str, dict[str, float]] = {algo: {} for algo in algos}
    for b in batches:
        data = [frames(b, 1000 + i) for i in range(repeats)]
        for algo in algos:
            # a decoder held across calls, as a node holds it (a checkout before pipeline.dsp.decode.Decoder: decode)
            held = getattr(decoders, "Decoder", None)
            decode = held(DecoderConfig(algo=algo)).decode if held else partial(decoders.decode,
                                                                               decoder=DecoderConfig(algo=algo))
            decode(*data[0][:2], data[0][2], 1, cfg, k)  # warm-up (tables, first-call costs)
            rounds = iter(data)

            def one() -> None:
                z, xi, delta = next(rounds)
                decode(z, xi, delta, 1, cfg, k)

            best = time_calls(one, len(data)).cpu_s.min()  # CPU s, each round on frames of its own
            out[algo][str(b)] = round(best / b * 1e3, 4)
    return out


def _run(code: Path, args: argparse.Namespace) -> dict[str, dict[str, float]]:
    """:func:`measure` of ``code`` in a fresh Python process."""
    cmd = [sys.executable, __file__, "--code", str(code), "--json", "--batches", args.batches, "--repeats",
           str(args.repeats), "--algos", args.algos, "--K", str(args.K)]
    env = {k: v for k, v in os.environ.items() if k != RESULTS_ENV}  # the child writes no result file
    res = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
    if res.returncode:
        raise SystemExit(f"bench_decoders: timing {code} failed:\n{res.stderr}")
    return _nested(json.loads(res.stdout)["ms_per_frame"])


def _flat(ms: dict[str, dict[str, float]]) -> dict[str, float]:
    """{algo: {batch: v}} -> {"<algo>_b<batch>": v} (the figures' keys)."""
    return {f"{algo}_b{b}": v for algo, row in ms.items() for b, v in row.items()}


def _nested(flat: dict[str, float]) -> dict[str, dict[str, float]]:
    """The inverse of :func:`_flat`."""
    out: dict[str, dict[str, float]] = {}
    for key, v in flat.items():
        algo, b = key.rsplit("_b", 1)
        out.setdefault(algo, {})[b] = v
    return out


def _best(a: dict, b: dict) -> dict:
    return {algo: {bs: min(a[algo][bs], b[algo][bs]) for bs in a[algo]} for algo in a}


def _table(ms: dict, base: dict | None) -> str:
    batches = list(next(iter(ms.values())))
    head = "decoder  " + "".join(f"{'B=' + b:>24s}" if base else f"{'B=' + b:>10s}" for b in batches)
    lines = [head, "(ms per frame" + (": baseline -> this, speedup)" if base else ")")]
    for algo, row in ms.items():
        cells = [f"{base[algo][b]:8.3f} ->{row[b]:7.3f} x{base[algo][b] / row[b]:4.1f}" if base else f"{row[b]:10.3f}"
                 for b in batches]
        lines.append(f"{algo:8s} " + "".join(f"{c:>24s}" if base else c for c in cells))
    return "\n".join(lines)


def main(argv=None) -> None:
    args = _parse_args(argv)
    if args.baseline is None:
        ms = measure(args.code, args.batch_list, args.algo_list, args.repeats, args.K)
        base = None
    else:
        ms = base = None
        for _ in range(args.rounds):  # the two checkouts take turns: a busy spell slows both
            b = _run(args.baseline, args)
            m = _run(args.code, args)
            base = b if base is None else _best(base, b)
            ms = m if ms is None else _best(ms, m)
    report = {"machine": machine(),
              "code": str(args.code), "K": args.K, "repeats": args.repeats, "ms_per_frame": _flat(ms)}
    if base is not None:
        report |= {"baseline": str(args.baseline), "rounds": args.rounds, "baseline_ms_per_frame": _flat(base),
                   "speedup": _flat({a: {b: round(base[a][b] / ms[a][b], 2) for b in ms[a]} for a in ms})}
    if args.json:
        emit(report, indent=None)
        return
    print(_table(ms, base))
    emit(report, indent=1)


if __name__ == "__main__":
    main()
