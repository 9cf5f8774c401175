"""The ``qradar`` command: one entry point with subcommands."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

from .errors import PipelineError

log = logging.getLogger("qradar")


def _nonneg_int(text: str) -> int:
    v = int(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 0")
    return v


def _pos_int(text: str) -> int:
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 1")
    return v


def _add_montecarlo(sub) -> None:
    from .montecarlo import DEFAULT_SCHEMES

    p = sub.add_parser(
        "montecarlo",
        help="reproduce the paper's Monte Carlo (Sec. 5, Figs. 2-4)",
        description="Monte Carlo of PBP localization with the DESIGN.md protocol; writes "
        "summary.json, maps.npz and polar error maps (PNG) to --out.",
    )
    p.add_argument("--K", dest="ks", type=_pos_int, nargs="+", default=[1, 2], help="sparsities (default 1 2)")
    p.add_argument("--runs", type=_pos_int, default=None,
                   help="runs per scheme and K (default: the paper's 320000 x K)")
    p.add_argument("--schemes", nargs="+", default=list(DEFAULT_SCHEMES),
                   help="dither_m<M>, nodither_m<M>, 32bit_m<M> (default: the paper's four)")
    p.add_argument("--seed", type=_nonneg_int, default=0)
    p.add_argument("--off-grid", action="store_true", help="keep range cell centres off the range grid")
    p.add_argument("--workers", type=_pos_int, default=None, help="worker processes (default: all cores)")
    p.add_argument("--out", type=Path, default=Path("montecarlo_out"), help="output folder")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG maps")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_montecarlo)


def _cmd_montecarlo(args) -> int:
    from radar_driver.model import RadarConfig

    from .montecarlo import MonteCarloConfig, format_table, run_montecarlo
    from .plots import montecarlo_figures

    cfg = MonteCarloConfig(
        ks=tuple(args.ks), runs=args.runs, schemes=tuple(args.schemes), seed=args.seed,
        off_grid=args.off_grid, workers=args.workers, radar=RadarConfig(),
    )
    args.out.mkdir(parents=True, exist_ok=True)
    result = run_montecarlo(cfg, progress=not args.quiet)
    (args.out / "summary.json").write_text(json.dumps(result.summary, indent=2) + "\n")
    (args.out / "config.json").write_text(json.dumps(result.run_config, indent=2) + "\n")
    np.savez_compressed(args.out / "maps.npz", **result.maps)
    pngs = [] if args.no_plots else montecarlo_figures(args.out, result.summary, result.maps, cfg.radar.max_range_m)
    print(format_table(result.summary))
    print(f"\n{sum(result.run_config['runs_per_k'].values()) * len(cfg.schemes)} runs in "
          f"{result.summary['seconds']:.1f} s; wrote {args.out}/summary.json, maps.npz"
          + (f" and {len(pngs)} PNG maps" if pngs else ""))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="qradar", description="1-bit dithered FMCW radar localization: simulation, streaming, replay."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_montecarlo(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except (PipelineError, ValueError) as exc:
        print(f"qradar {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"qradar {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
