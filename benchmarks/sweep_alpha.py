"""The dither scale against the sensor noise: the Monte Carlo sweep behind
:func:`pipeline.dsp.noise.auto_alpha` (issue 24).

For each noise sigma (std of I and of Q relative to the strongest target) and each alpha,
1-bit M = 512 frames of continuous (off-grid) scenes decoded by cml, K = 1 and 2, and the
unquantized frames by cml as the reference line; also the noise relative to the 1-bit
step, ``rho = sigma / delta`` (median over the runs), the variable of the rule. Prints
the table (median error, K = 1; K = 2 weakest mean) and the best alpha per sigma, and
writes JSON and a PNG::

    .venv/bin/python benchmarks/sweep_alpha.py --runs 2000 --out out/sweep_alpha
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from experiments.montecarlo import MonteCarloConfig, SceneSpec, draw_scenes, run_montecarlo
from pipeline.dsp.quantize import auto_delta
from radar_driver.model import RadarConfig, simulate_frames

SIGMAS = (0.0, 0.01, 0.03, 0.1, 0.3)
ALPHAS = (0.0, 0.1, 0.2, 0.3, 0.45, 0.6, 0.8, 1.0)
SCENE = dict(ranges="continuous", max_angle_deg=60.0, min_amplitude=0.1)


def scheme(alpha: float) -> str:
    return "nodither_m512" if alpha == 0 else "dither_m512" if alpha == 1 else f"dither_a{alpha:g}_m512"


def median_rho(sigma: float, k: int, runs: int, seed: int) -> float:
    """Median of sigma / delta over scenes like the Monte Carlo's (delta: the 1-bit step of
    the noisy frame)."""
    cfg = RadarConfig()
    rng = np.random.default_rng(seed)
    _, _, r, a, x = draw_scenes(runs, k, rng, cfg, scene=SceneSpec(**SCENE, noise_sigma=sigma))
    g = simulate_frames(r, a, x, cfg)
    g = g + sigma * (rng.standard_normal(g.shape) + 1j * rng.standard_normal(g.shape))
    return float(np.median(sigma / auto_delta(g)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=2000)
    ap.add_argument("--sigmas", type=float, nargs="+", default=list(SIGMAS))
    ap.add_argument("--alphas", type=float, nargs="+", default=list(ALPHAS))
    ap.add_argument("--ks", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--decoder-noise", default="codes", choices=["codes", "true", "frames"])
    ap.add_argument("--extra-schemes", nargs="*", default=[], help="e.g. dither_aauto_m512")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("out/sweep_alpha"))
    ap.add_argument("--replot", type=Path, default=None, help="redraw from a sweep.json, run nothing")
    args = ap.parse_args()
    if args.replot:
        return replot(args.replot)
    args.out.mkdir(parents=True, exist_ok=True)
    schemes = [scheme(a) for a in args.alphas] + list(args.extra_schemes) + ["32bit_m512"]
    rows = []
    for sigma in args.sigmas:
        cfg = MonteCarloConfig(ks=tuple(args.ks), runs=args.runs, schemes=tuple(schemes), seed=args.seed,
                               algos=("cml",), scene=SceneSpec(**SCENE, noise_sigma=sigma), workers=args.workers,
                               decoder_noise=args.decoder_noise)
        summ = run_montecarlo(cfg, progress=False).summary
        for k in args.ks:
            rho = median_rho(sigma, k, 2000, args.seed)
            for s in schemes:
                st = summ[f"K{k}"][f"{s}@cml"]
                rows.append({"sigma": sigma, "K": k, "rho": rho, "scheme": s, "median_m": st["median_m"],
                             "weak_mean_m": st["weak_mean_m"], "mean_m": st["mean_m"], "p90_m": st["p90_m"]})
        print(f"sigma {sigma:g} done ({summ['seconds']:.0f} s)", flush=True)
    (args.out / "sweep.json").write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                                     "rows": rows}, indent=1) + "\n")
    report(rows, args)
    plot(rows, args)


def report(rows: list[dict], args) -> None:
    for k in args.ks:
        print(f"\nK = {k}: {'median' if k == 1 else 'median / weakest mean'} error (m), cml, decoder noise "
              f"{args.decoder_noise}")
        names = sorted({r["scheme"] for r in rows}, key=lambda s: [r["scheme"] for r in rows].index(s))
        print(f"{'sigma':>6} {'rho':>7} " + " ".join(f"{n.replace('_m512', ''):>14}" for n in names) + "  best")
        for sigma in args.sigmas:
            sel = {r["scheme"]: r for r in rows if r["sigma"] == sigma and r["K"] == k}
            cells = [f"{sel[n]['median_m']:.3f}" + (f"/{sel[n]['weak_mean_m']:.2f}" if k > 1 else "") for n in names]
            fixed = [n for n in names if n.startswith(("dither", "nodither"))]
            best = min(fixed, key=lambda n: sel[n]["median_m"])
            rho = next(iter(sel.values()))["rho"]
            print(f"{sigma:>6g} {rho:>7.4f} " + " ".join(f"{c:>14}" for c in cells) + f"  {best}")


def plot(rows: list[dict], args) -> None:
    """Three panels: K = 1 median, K = 2 median, K = 2 weakest mean against alpha, one
    curve per sigma; dotted: cml on the unquantized frames (0 without noise: not drawn);
    a star at the right end: alpha auto."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(k, "median_m", "median") for k in args.ks] + ([(2, "weak_mean_m", "weakest target's mean")]
                                                            if 2 in args.ks else [])
    fig, axes = plt.subplots(1, len(panels), figsize=(5.6 * len(panels), 4.8), squeeze=False)
    colors = plt.cm.viridis(np.linspace(0, 0.9, len(args.sigmas)))
    for ax, (k, key, what) in zip(axes[0], panels):
        for c, sigma in zip(colors, args.sigmas):
            sel = [r for r in rows if r["sigma"] == sigma and r["K"] == k]
            vals = [next(r[key] for r in sel if r["scheme"] == scheme(a)) for a in args.alphas]
            ax.plot(args.alphas, vals, "o-", color=c, ms=4, label=f"σ = {sigma:g} (σ/δ = {sel[0]['rho']:.3f})")
            ref = next(r[key] for r in sel if r["scheme"] == "32bit_m512")
            if ref > 0.005:
                ax.axhline(ref, color=c, ls=":", lw=1.2)
            auto = [r for r in sel if "auto" in r["scheme"]]
            if auto:
                ax.plot([1.06], [auto[0][key]], "*", color=c, ms=12)
        ax.set_yscale("log")
        ax.set_xlabel("dither scale α (0 = no dither; ★ right of 1: α auto)")
        ax.set_ylabel(f"{what} position error, m")
        ax.set_title(f"K = {k}, {what}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"cml, 1-bit M = 512, continuous (off-grid) scenes, {args.runs} runs a point, decoder noise: "
                 f"{args.decoder_noise}; dotted: cml on the unquantized frames", fontsize=10)
    fig.tight_layout()
    path = args.out / "sweep_alpha.png"
    fig.savefig(path, dpi=110)
    print(f"\nwrote {path} and {args.out / 'sweep.json'}")
    plot_rows(rows, args)


def plot_rows(rows: list[dict], args) -> None:
    """The Monte Carlo's noise rows: error against sigma for each 1-bit scheme (alpha auto
    bold), cml on the unquantized frames (black) and twice it (the issue's line, dotted)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sigmas = [x for x in args.sigmas if x > 0]
    panels = [(k, "median_m", "median") for k in args.ks] + ([(2, "weak_mean_m", "weakest target's mean")]
                                                            if 2 in args.ks else [])
    names = list(dict.fromkeys(r["scheme"] for r in rows))
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4.4), squeeze=False)
    for ax, (k, key, what) in zip(axes[0], panels):
        def line(name):
            return [next(r[key] for r in rows if r["sigma"] == x and r["K"] == k and r["scheme"] == name)
                    for x in sigmas]
        ref = line("32bit_m512")
        ax.plot(sigmas, ref, "k-o", ms=4, label="cml, unquantized")
        ax.plot(sigmas, [2 * v for v in ref], "k:", label="2 × unquantized")
        for name in names:
            if name == "32bit_m512":
                continue
            auto = "auto" in name
            ax.plot(sigmas, line(name), "-o" if auto else "--o", ms=4 if auto else 3, lw=2.2 if auto else 1,
                    color="C3" if auto else None, label=f"1-bit, α {'auto' if auto else _alpha(name):g}"
                    if not auto else "1-bit, α auto")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("noise σ (std of I and of Q, strongest amplitude 1)")
        ax.set_ylabel(f"{what} position error, m")
        ax.set_title(f"K = {k}, {what}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"cml, M = 512, continuous (off-grid) scenes, {args.runs} runs a point", fontsize=10)
    fig.tight_layout()
    path = args.out / "rows.png"
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def replot(path: Path) -> None:
    """Redraw a sweep's PNG and table from its sweep.json."""
    data = json.loads(path.read_text())
    rows = data["rows"]
    ns = argparse.Namespace(ks=sorted({r["K"] for r in rows}), sigmas=sorted({r["sigma"] for r in rows}),
                            alphas=sorted({_alpha(r["scheme"]) for r in rows} - {None}),
                            runs=data["args"]["runs"], decoder_noise=data["args"]["decoder_noise"], out=path.parent)
    report(rows, ns)
    plot(rows, ns)


def _alpha(name: str) -> float | None:
    if name == "nodither_m512":
        return 0.0
    if name == "dither_m512":
        return 1.0
    if name.startswith("dither_a") and "auto" not in name:
        return float(name[len("dither_a"):-len("_m512")])
    return None


if __name__ == "__main__":
    main()
