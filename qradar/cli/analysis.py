"""Analysis commands: ``montecarlo`` (the paper's Sec. 5), ``montecarlo-time`` (T frames of
a static scene decoded together, error against T) and ``reprocess`` (a recording's raw
frames quantized and localized again, the alpha sweep of Sec. 6)."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

from pipeline.dsp.gate import RangeGate
from pipeline.errors import ParameterError
from pipeline.dsp.integrate import time_monte_carlo
from pipeline.dsp.quantize import QuantizerConfig
from experiments.montecarlo import CountSpec, MonteCarloConfig, SceneSpec, run_montecarlo
from experiments.report import prepare_out_dir, write_outputs
from experiments.plots import error_vs_frames_figure
from radar_driver.model import RadarConfig
from radar_driver.options import nonneg_float, nonneg_int, option, pos_int
from replay.reprocess import DEFAULT_SWEEP, ReprocessConfig, parse_alphas
from replay.reprocess import run as run_reprocess

from .parts import CALIBRATION, GATE, QUANTIZER, TRACKS, count_of, decoder_parts, force_help, switches, tracker_of
from .schema import Part, add_command


@dataclass(frozen=True)
class MonteCarlo:
    """What ``qradar montecarlo`` takes besides its config's fields."""

    range_interval: tuple[float, float] = option(
        (SceneSpec.range_min_m, SceneSpec.range_max_m), "with --ranges continuous (default 3 150)", many=2,
        metavar=("MIN_M", "MAX_M"), parse=nonneg_float)
    count: str = option("auto" if CountSpec.auto else "given", "auto: the decoders (pbp, cml) decide each frame's "
                        "count, as with localize --K auto; the summary adds detection probabilities and false targets "
                        "per frame", choices=("given", "auto"))
    min_range_m: float | None = option(None, "the decoders search only ranges >= M (as the live localizer does, whose "
                                       "default is 1.2)", metavar="M", parse=nonneg_float)
    max_range_m: float | None = option(None, "the decoders search only ranges <= M (the live localizer's default: "
                                       "152.4)", metavar="M", parse=nonneg_float)
    out: Path = option(Path("montecarlo_out"), "output folder")
    no_plots: bool = option(False, "skip the PNG maps")
    quiet: bool = option(False, "no progress bar")


@dataclass(frozen=True)
class TimeMonteCarlo:
    """``qradar montecarlo-time``: T frames of a static scene decoded together."""

    runs: int = option(200, "scenes per noise level (default 200)", parse=pos_int)
    frames: tuple[int, ...] = option((1, 2, 4, 8, 16, 32), "the T to decode (default 1 2 4 8 16 32)", many="+",
                                     parse=pos_int)
    noise_sigma: tuple[float, ...] = option((0.1, 0.0), "noise std of I and Q relative to the amplitude, one curve "
                                            "each (default 0.1 0)", many="+", parse=nonneg_float)
    alpha: float | None = option(None, "dither scale (default: the default decoder's)", parse=nonneg_float)
    seed: int = option(0, "random seed (runs are reproducible for a seed)", parse=nonneg_int)
    out: Path = option(Path("out/montecarlo-time"), "folder for time.json and time.png")


@dataclass(frozen=True)
class Sweep:
    """``qradar reprocess``'s sweep of alpha."""

    alpha: str = option(DEFAULT_SWEEP, "start:stop:step, a,b,c or one value (default 0:1:0.05)")


def add_montecarlo(sub) -> None:
    add_command(sub, "montecarlo", [
        Part(MonteCarloConfig, only=("ks", "runs", "schemes", "seed", "algos", "fallback_pbp", "off_grid")),
        Part(SceneSpec, "scene", only=("ranges",), group="scenes (defaults: the paper's protocol)"),
        Part(MonteCarlo, "scene", only=("range_interval",), group="scenes (defaults: the paper's protocol)"),
        Part(SceneSpec, "scene", only=("min_separation_m", "max_angle_deg", "min_amplitude", "noise_sigma", "speeds"),
             group="scenes (defaults: the paper's protocol)"),
        Part(MonteCarloConfig, "scene", only=("decoder_noise",), group="scenes (defaults: the paper's protocol)"),
        Part(MonteCarlo, "count", only=("count",), group="target count (default: each decoder is told the scene's K)"),
        Part(CountSpec, "count", only=("max_targets", "pfa", "gate_m"),
             group="target count (default: each decoder is told the scene's K)"),
        Part(MonteCarlo, "gate", only=("min_range_m", "max_range_m"),
             group="range gate (default: the whole range axis, the paper's protocol)"),
        Part(MonteCarloConfig, only=("workers",)), Part(MonteCarlo, only=("out",)),
        switches(force=force_help("the outputs of an earlier run in --out")),
        Part(MonteCarlo, only=("no_plots", "quiet"))], cmd_montecarlo,
        help="reproduce the paper's Monte Carlo (Sec. 5, Figs. 2-4)",
        description="Monte Carlo of PBP localization with the protocol of docs/design.md; writes summary.json, "
        "maps.npz and polar error maps (PNG) to --out.")


def add_montecarlo_time(sub) -> None:
    add_command(sub, "montecarlo-time", [Part(TimeMonteCarlo), switches(force=force_help("time.json and time.png in "
                                                                                          "--out"))],
                cmd_montecarlo_time,
                help="the Monte Carlo in time: T 1-bit frames of a static scene decoded together, error against T",
                description="Random static scenes of one target off the grid (range uniform in 3-150 m, angle in "
                "+-60 deg), each seen in T frames with a fresh dither (and fresh noise), decoded together by cml "
                "(pipeline.dsp.integrate); writes time.json and time.png to --out and prints the median error "
                "against T and its slope in log-log.")


def cmd_montecarlo_time(args) -> int:
    twice = sorted({s for s in args.noise_sigma if args.noise_sigma.count(s) > 1})
    if twice:  # one curve each: a level given twice drew two identical curves
        raise ParameterError(f"--noise-sigma {' '.join(f'{s:g}' for s in args.noise_sigma)}: "
                             f"{', '.join(f'{s:g}' for s in twice)} given twice; give each noise level once")
    with prepare_out_dir(args.out, ("time.json", "time.png"), args.force):  # before the work: a bad --out is one line
        results = [time_monte_carlo(args.runs, tuple(args.frames), s, args.alpha, args.seed) for s in args.noise_sigma]
    (args.out / "time.json").write_text(json.dumps(results, indent=2) + "\n")
    error_vs_frames_figure(args.out / "time.png", results)
    for r in results:
        slope = "" if r["slope"] is None else f"; slope {r['slope']:.2f}"
        print(f"noise sigma {r['noise_sigma']:g}: median error " + ", ".join(
            f"T={t} {e:.4f} m" for t, e in zip(r["T"], r["median_m"])) + slope)
    print(f"wrote {args.out / 'time.json'}, {args.out / 'time.png'}")
    return 0


def add_reprocess(sub) -> None:
    add_command(sub, "reprocess", [
        Part(ReprocessConfig, only=("file",)), Part(Sweep), Part(QuantizerConfig, only=("bits",), options=QUANTIZER),
        *decoder_parts("targets (default: the truth's count)", algo_help=None, k_default=None),
        Part(ReprocessConfig, only=("algos", "seed", "sensor", "truth")), CALIBRATION,
        Part(ReprocessConfig, only=("out", "mcap", "force", "progress")), GATE, *TRACKS], cmd_reprocess,
        help="re-quantize and re-localize a recording's raw frames offline (alpha sweep)")


def cmd_montecarlo(args) -> int:
    build = args.schema.build
    cfg = build(
        MonteCarloConfig, args, radar=RadarConfig(),
        scene=build(SceneSpec, args, range_min_m=args.range_interval[0], range_max_m=args.range_interval[1]),
        count=build(CountSpec, args, auto=args.count == "auto"),
        gate=None if args.min_range_m is None and args.max_range_m is None else RangeGate(
            0.0 if args.min_range_m is None else args.min_range_m,
            RadarConfig().max_range_m if args.max_range_m is None else args.max_range_m))
    with prepare_out_dir(args.out, force=args.force):
        result = run_montecarlo(cfg, progress=not args.quiet)
    print("\n".join(write_outputs(result, args.out, cfg.radar.max_range_m, plots=not args.no_plots)))
    return 0


def cmd_reprocess(args) -> int:
    k, auto = count_of(args)
    cfg = args.schema.build(ReprocessConfig, args, alphas=tuple(parse_alphas(args.alpha)), bits=args.bits, k=k,
                            auto_k=auto, pfa=args.pfa, calibration=args.calibration, min_range_m=args.min_range_m,
                            max_range_m=args.max_range_m, tracking=tracker_of(args))
    result = run_reprocess(cfg)
    for note in result.notes:
        print(note, file=sys.stderr)
    print("\n".join(result.lines))
    return 0
