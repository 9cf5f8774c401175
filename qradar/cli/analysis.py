"""Analysis commands: ``montecarlo`` (the paper's Sec. 5), ``montecarlo-time`` (T frames of
a static scene decoded together, error against T) and ``reprocess`` (a recording's raw
frames quantized and localized again, the alpha sweep of Sec. 6)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from pipeline.dsp.decode import ALGOS, DEFAULT_ALGO, Algo
from pipeline.dsp.gate import RangeGate
from pipeline.dsp.integrate import time_monte_carlo
from pipeline.dsp.localize import DEFAULT_PFA
from replay.montecarlo import (DECODER_NOISE, DEFAULT_SCHEMES, RANGE_PLACEMENTS, CountSpec, MonteCarloConfig, SceneSpec,
                                 run_montecarlo)
from replay.montecarlo_report import prepare_out_dir, write_outputs
from replay.plots import error_vs_frames_figure
from radar_driver.model import RadarConfig
from replay.reprocess import ReprocessConfig, parse_alphas
from replay.reprocess import run as run_reprocess

from .common import (BITS_HELP, count_from_args, count_options, gate_options, nonneg_float, nonneg_int, pfa_arg,
                     pos_int)
from .common import calibration_option, force_option, track_options, tracker_config


def add_montecarlo(sub) -> None:
    p = sub.add_parser(
        "montecarlo",
        help="reproduce the paper's Monte Carlo (Sec. 5, Figs. 2-4)",
        description="Monte Carlo of PBP localization with the protocol of docs/design.md; writes "
        "summary.json, maps.npz and polar error maps (PNG) to --out.",
    )
    p.add_argument("--K", dest="ks", type=pos_int, nargs="+", default=[1, 2], help="sparsities (default 1 2)")
    p.add_argument("--runs", type=pos_int, default=None,
                   help="runs per scheme and K (default: the paper's 320000 x K)")
    p.add_argument("--schemes", nargs="+", default=list(DEFAULT_SCHEMES),
                   help="dither_m<M>, dither_a<alpha>_m<M>, dither_aauto_m<M> (alpha from the noise the quantizer "
                   "estimates in each frame), nodither_m<M>, 32bit_m<M> (default: the paper's four)")
    p.add_argument("--seed", type=nonneg_int, default=0, help="random seed (runs are reproducible for a seed)")
    p.add_argument("--algos", nargs="+", default=[Algo.PBP.value],
                   help=f"decoders: {', '.join(ALGOS)} (default {Algo.PBP}); "
                   "non-PBP results appear as <scheme>@<algo>")
    p.add_argument("--fallback-pbp", action="store_true", help="decode schemes without dither with PBP "
                   "when a dither-aware algo is asked for")
    p.add_argument("--off-grid", action="store_true", help="keep range cell centres off the range grid "
                   "(the same as --ranges cells)")
    g = p.add_argument_group("scenes (defaults: the paper's protocol)")
    g.add_argument("--ranges", choices=list(RANGE_PLACEMENTS), default="grid",
                   help="grid: cell centres on the range grid; cells: cell centres; continuous: uniform over "
                   "--range-interval (default grid)")
    g.add_argument("--range-interval", type=nonneg_float, nargs=2, default=[3.0, 150.0], metavar=("MIN_M", "MAX_M"),
                   help="with --ranges continuous (default 3 150)")
    g.add_argument("--min-separation-m", type=nonneg_float, default=1.5,
                   help="with --ranges continuous: targets at least this far apart (default 1.5)")
    g.add_argument("--max-angle-deg", type=nonneg_float, default=90.0, help="angles within +-this (default 90)")
    g.add_argument("--min-amplitude", type=nonneg_float, default=0.0,
                   help="weaker targets' amplitudes uniform in [this, 1] (default 0)")
    g.add_argument("--noise-sigma", type=nonneg_float, default=0.0,
                   help="sensor noise before quantization: std of I and of Q relative to the strongest target "
                   "(default 0)")
    g.add_argument("--decoder-noise", choices=list(DECODER_NOISE), default="codes",
                   help="what cml is told of the noise: codes (it estimates it from the codes, as live), true (the "
                   "scene's --noise-sigma), frames (the quantizer's estimate from the full frames) (default codes)")
    g = p.add_argument_group("target count (default: each decoder is told the scene's K)")
    g.add_argument("--count", choices=["given", "auto"], default="given",
                   help="auto: the decoders (pbp, cml) decide each frame's count, as with localize --K auto; the "
                   "summary adds detection probabilities and false targets per frame")
    g.add_argument("--max-targets", type=pos_int, default=4, help="with --count auto: the most a frame has (default 4)")
    g.add_argument("--pfa", type=pfa_arg, default=DEFAULT_PFA,
                   help=f"with --count auto: false-alarm probability per frame and test (default {DEFAULT_PFA:g})")
    g.add_argument("--gate-m", type=nonneg_float, default=0.6,
                   help="with --count auto: a true target is found by a detection within this range of it "
                   "(default 0.6, one range bin)")
    g = p.add_argument_group("range gate (default: the whole range axis, the paper's protocol)")
    g.add_argument("--min-range-m", type=nonneg_float, default=None, metavar="M",
                   help="the decoders search only ranges >= M (as the live localizer does, whose default is 1.2)")
    g.add_argument("--max-range-m", type=nonneg_float, default=None, metavar="M",
                   help="the decoders search only ranges <= M (the live localizer's default: 152.4)")
    p.add_argument("--workers", type=pos_int, default=None, help="worker processes (default: all cores)")
    p.add_argument("--out", type=Path, default=Path("montecarlo_out"), help="output folder")
    force_option(p, "the outputs of an earlier run in --out")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG maps")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_montecarlo)


def add_montecarlo_time(sub) -> None:
    p = sub.add_parser(
        "montecarlo-time",
        help="the Monte Carlo in time: T 1-bit frames of a static scene decoded together, error against T",
        description="Random static scenes of one target off the grid (range uniform in 3-150 m, angle in +-60 deg), "
        "each seen in T frames with a fresh dither (and fresh noise), decoded together by cml "
        "(pipeline.dsp.integrate); writes time.json and time.png to --out and prints the median error against T and "
        "its slope in log-log.")
    p.add_argument("--runs", type=pos_int, default=200, help="scenes per noise level (default 200)")
    p.add_argument("--frames", type=pos_int, nargs="+", default=[1, 2, 4, 8, 16, 32],
                   help="the T to decode (default 1 2 4 8 16 32)")
    p.add_argument("--noise-sigma", type=nonneg_float, nargs="+", default=[0.1, 0.0],
                   help="noise std of I and Q relative to the amplitude, one curve each (default 0.1 0)")
    p.add_argument("--alpha", type=nonneg_float, default=None, help="dither scale (default: the default decoder's)")
    p.add_argument("--seed", type=nonneg_int, default=0, help="random seed (runs are reproducible for a seed)")
    p.add_argument("--out", type=Path, default=Path("out/montecarlo-time"), help="folder for time.json and time.png")
    force_option(p, "time.json and time.png in --out")
    p.set_defaults(func=cmd_montecarlo_time)


def cmd_montecarlo_time(args) -> int:
    prepare_out_dir(args.out, ("time.json", "time.png"), args.force)  # before the work: a bad --out is one line
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
    p = sub.add_parser("reprocess", help="re-quantize and re-localize a recording's raw frames offline (alpha sweep)")
    p.add_argument("file", type=Path, help="a qradar MCAP recording with raw frames")
    p.add_argument("--alpha", default="0:1:0.05", help="start:stop:step, a,b,c or one value (default 0:1:0.05)")
    p.add_argument("--bits", type=pos_int, default=1, help=BITS_HELP)
    count_options(p, None, "targets (default: the truth's count)")
    p.add_argument("--algos", "--algo", dest="algos", nargs="+", choices=list(ALGOS), default=[DEFAULT_ALGO.value],
                   help=f"decoders, one alpha sweep and one curve each (default {DEFAULT_ALGO}); qiht decodes "
                   "alpha = 0 with PBP (there is no dither to use)")
    p.add_argument("--seed", type=nonneg_int, default=0, help="random seed (runs are reproducible for a seed)")
    p.add_argument("--sensor", default=None, help="sensor id (default: the first)")
    p.add_argument("--truth", type=Path, default=None, help="scene TOML with the true positions (real recordings)")
    calibration_option(p)
    p.add_argument("--out", type=Path, default=Path("out/reprocess"), help="folder for results.json and the plots")
    p.add_argument("--mcap", type=Path, default=None, help="also write the best alpha's targets to this MCAP")
    force_option(p, "results.json, the plots and the --mcap file")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    gate_options(p)
    track_options(p)
    p.set_defaults(func=cmd_reprocess)


def cmd_montecarlo(args) -> int:
    cfg = MonteCarloConfig(
        ks=tuple(args.ks), runs=args.runs, schemes=tuple(args.schemes), seed=args.seed,
        off_grid=args.off_grid, workers=args.workers, radar=RadarConfig(), algos=tuple(args.algos),
        fallback_pbp=args.fallback_pbp,
        scene=SceneSpec(ranges=args.ranges, range_min_m=args.range_interval[0], range_max_m=args.range_interval[1],
                        min_separation_m=args.min_separation_m, max_angle_deg=args.max_angle_deg,
                        min_amplitude=args.min_amplitude, noise_sigma=args.noise_sigma),
        decoder_noise=args.decoder_noise,
        count=CountSpec(auto=args.count == "auto", max_targets=args.max_targets, pfa=args.pfa, gate_m=args.gate_m),
        gate=None if args.min_range_m is None and args.max_range_m is None else RangeGate(
            0.0 if args.min_range_m is None else args.min_range_m,
            RadarConfig().max_range_m if args.max_range_m is None else args.max_range_m),
    )
    prepare_out_dir(args.out, force=args.force)
    result = run_montecarlo(cfg, progress=not args.quiet)
    print("\n".join(write_outputs(result, args.out, cfg.radar.max_range_m, plots=not args.no_plots)))
    return 0


def cmd_reprocess(args) -> int:
    k, auto = count_from_args(args)
    cfg = ReprocessConfig(file=args.file, alphas=tuple(parse_alphas(args.alpha)), bits=args.bits, k=k,
                          algos=tuple(args.algos), seed=args.seed, sensor=args.sensor, truth=args.truth, out=args.out,
                          mcap=args.mcap, progress=not args.quiet, auto_k=auto, pfa=args.pfa,
                          calibration=args.calibration, min_range_m=args.min_range_m,
                          max_range_m=args.max_range_m, tracking=tracker_config(args), force=args.force)
    result = run_reprocess(cfg)
    for note in result.notes:
        print(note, file=sys.stderr)
    print("\n".join(result.lines))
    return 0
