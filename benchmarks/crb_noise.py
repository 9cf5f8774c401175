#!/usr/bin/env python3
"""What any unbiased decoder can do with 1-bit dithered codes in sensor noise: the
Cramer-Rao bound (:mod:`pipeline.dsp.crb`) on the position error of the Monte Carlo's
continuous K = 1 scenes, 1-bit against unquantized, beside the ``cml`` decoder's measured
median errors on the same scenes.

Scenes: ``qradar montecarlo --ranges continuous --K 1`` (ranges uniform over 3-150 m,
angles over +-90 deg, amplitude 1, uniform phase), drawn exactly as the Monte Carlo draws
them for ``--seed``; noise of std sigma on I and on Q; the 1-bit step delta of each scene
is the smallest 1-bit step of one noisy draw of its frame (``auto_delta``), the dither
``alpha delta u`` with u uniform on [-1/2, 1/2) (alpha 0: no dither). For each sigma and
alpha the bound gives each scene's position covariance; the table shows the median over
the scenes of its RMS (sqrt of the trace), and the median error of an efficient estimator
(errors drawn from each scene's bound covariance, pooled; comparable to a median error).

Measured: ``run_montecarlo`` (the API of ``qradar montecarlo``) with ``--algos cml
--schemes nodither_m512 dither_a<alpha>_m512 32bit_m512 --noise-sigma S --ranges
continuous --K 1 --runs R --seed SEED`` (alpha <= 1, the quantizer's range). Results are
kept in ``--out`` so a second run (or ``--replot``) reuses them::

    .venv/bin/python benchmarks/crb_noise.py --runs 2000 --workers 2
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.dsp.crb import (crb, fisher, position_bound, position_covariance, position_rms,  # noqa: E402
                          signal_jacobian, weights_1bit_expected, weights_unquantized)
from experiments.montecarlo import (CHUNK_RUNS, MonteCarloConfig, SceneSpec, draw_scenes,  # noqa: E402
                                 run_montecarlo)
from replay.progress import Progress  # noqa: E402
from pipeline.dsp.quantize import auto_delta  # noqa: E402
from radar_driver.model import RadarConfig, simulate_frames  # noqa: E402

SIGMAS = (0.03, 0.1, 0.3)
BOUND_ALPHAS = tuple(np.round(np.arange(0.0, 2.0001, 0.1), 2))
MEASURED_ALPHAS = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)
GOAL_RATIO = 2.0
BLOCK = 250  # scenes per block of the bound (ds of a block: 250 x 2048 x 4 floats)


def scheme(alpha: float) -> str:
    return "nodither_m512" if alpha == 0 else "dither_m512" if alpha == 1 else f"dither_a{alpha:g}_m512"


def scenes(runs: int, seed: int, radar: RadarConfig, max_angle_deg: float = 90.0):
    """The Monte Carlo's K = 1 continuous scenes of ``seed``: range_m, angle_deg, amplitude (runs, 1)."""
    parts = []
    for c, start in enumerate(range(0, runs, CHUNK_RUNS)):
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(1, c)))
        parts.append(draw_scenes(min(CHUNK_RUNS, runs - start), 1, rng, radar,
                                 scene=SceneSpec(ranges="continuous", max_angle_deg=max_angle_deg))[2:])
    return tuple(np.concatenate(p) for p in zip(*parts))


def bounds(r, a_deg, x, radar: RadarConfig, sigmas, alphas, seed: int) -> dict:
    """{sigma: {"unq": (B,) RMS, "unq_cov": (B, 2, 2), alpha: ..., "cov:alpha": ...}} position bounds, m."""
    th = np.deg2rad(a_deg)
    n = r.shape[0]
    out = {s: {} for s in sigmas}
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(99,)))
    with Progress(n, "bounds", unit="scenes") as bar:
        for lo in range(0, n, BLOCK):
            sl = slice(lo, lo + BLOCK)
            s, ds = signal_jacobian(r[sl], th[sl], x[sl], radar)
            clean = simulate_frames(r[sl], a_deg[sl], x[sl], radar)
            for sigma in sigmas:
                noisy = clean + sigma * (rng.standard_normal(clean.shape) + 1j * rng.standard_normal(clean.shape))
                delta = auto_delta(noisy)
                cells = {"unq": weights_unquantized(sigma)}
                cells.update({al: weights_1bit_expected(s, al * delta, sigma) for al in alphas})
                for key, w in cells.items():
                    cov = position_covariance(crb(fisher(ds, w)), r[sl], th[sl])[:, 0]
                    out[sigma].setdefault(key, []).append(cov)
            bar.update(min(BLOCK, n - lo))
    return {s: {k: np.concatenate(v) for k, v in d.items()} for s, d in out.items()}


def median_rms(cov: np.ndarray) -> float:
    """Median over scenes of the bound's RMS position error (cov (B, 2, 2)), m; inf where undefined."""
    return float(np.median(np.nan_to_num(position_rms(cov), nan=np.inf)))


def two_bit(r, a_deg, x, radar: RadarConfig, sigmas, seed: int, scenes_n: int = 250) -> list[str]:
    """Lines: the 2-bit bound against the unquantized one on the first ``scenes_n`` scenes,
    step a quarter of the 1-bit step (thresholds 0 and +-delta/4), alpha 0 and 0.5."""
    sl = slice(0, scenes_n)
    th = np.deg2rad(a_deg[sl])
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(97,)))
    clean = simulate_frames(r[sl], a_deg[sl], x[sl], radar)
    lines = []
    for sigma in sigmas:
        noisy = clean + sigma * (rng.standard_normal(clean.shape) + 1j * rng.standard_normal(clean.shape))
        step = auto_delta(noisy) / 4
        unq = median_rms(position_bound(r[sl], th, x[sl], radar, sigma))
        ratios = [median_rms(position_bound(r[sl], th, x[sl], radar, sigma, al, step, 2)) / unq for al in (0.0, 0.5)]
        lines.append(f"sigma {sigma:g}: 2-bit codes, step = 1-bit step / 4: bound ratio {ratios[0]:.2f} (alpha 0), "
                     f"{ratios[1]:.2f} (alpha 0.5), {scenes_n} scenes")
    return lines


def efficient_median(cov: np.ndarray, seed: int, draws: int = 64) -> float:
    """Median of |e| over e ~ N(0, cov_b) pooled over scenes b (cov (B, 2, 2)), m; the same
    normal draws for every call of a seed (smooth curves over alpha)."""
    ok = np.isfinite(cov).all(axis=(1, 2))  # a scene at +-90 deg has no angle information: error inf
    lam, vec = np.linalg.eigh(np.where(ok[:, None, None], cov, 0.0))
    root = vec * np.sqrt(np.clip(lam, 0.0, None))[:, None, :]  # root @ root.T = cov
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(98,)))
    e = np.einsum("bij,bdj->bdi", root, rng.standard_normal((cov.shape[0], draws, 2)))
    err = np.where(ok[:, None], np.linalg.norm(e, axis=-1), np.inf)
    return float(np.median(err))


def measure(sigma: float, alphas, runs: int, seed: int, workers: int, out: Path, max_angle_deg: float = 90.0) -> dict:
    """cml median errors (m) per scheme on the Monte Carlo's scenes; cached in ``out``."""
    path = out / (f"measured_sigma{sigma:g}_runs{runs}_seed{seed}" + (
        f"_angle{max_angle_deg:g}.json" if max_angle_deg != 90 else ".json"))
    have = json.loads(path.read_text()) if path.exists() else {}
    want = [scheme(a) for a in alphas] + ["32bit_m512"]
    todo = [s for s in want if s not in have]
    if todo:
        cfg = MonteCarloConfig(ks=(1,), runs=runs, schemes=tuple(todo), seed=seed, algos=("cml",),
                               scene=SceneSpec(ranges="continuous", noise_sigma=sigma, max_angle_deg=max_angle_deg),
                               workers=workers)
        t0 = time.perf_counter()
        summ = run_montecarlo(cfg, progress=True).summary
        for s in todo:
            have[s] = summ["K1"][f"{s}@cml"]["median_m"]
        path.write_text(json.dumps(have, indent=1) + "\n")
        print(f"sigma {sigma:g}: measured {len(todo)} schemes in {time.perf_counter() - t0:.0f} s", flush=True)
    return have


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sigmas", type=float, nargs="+", default=list(SIGMAS))
    ap.add_argument("--alphas", type=float, nargs="+", default=list(BOUND_ALPHAS), help="alphas of the bound")
    ap.add_argument("--measure-alphas", type=float, nargs="*", default=list(MEASURED_ALPHAS),
                    help="alphas (<= 1) measured with cml; none: the bound only")
    ap.add_argument("--max-angle-deg", type=float, default=90.0, help="scene angles within +-this")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("out/crb_noise"))
    ap.add_argument("--figure", type=Path, default=Path("docs/figures/crb_noise.png"))
    ap.add_argument("--replot", action="store_true", help="redraw from --out/crb_noise.json, compute nothing")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    table_path = args.out / ("crb_noise.json" if args.max_angle_deg == 90 else
                             f"crb_noise_angle{args.max_angle_deg:g}.json")
    if args.replot:
        data = json.loads(table_path.read_text())
        rows, extra = data["rows"], data.get("two_bit", [])
    else:
        print(f"seed {args.seed}, runs {args.runs}, K 1, continuous scenes, |angle| <= {args.max_angle_deg:g} deg",
              flush=True)
        radar = RadarConfig()
        measured = {s: measure(s, args.measure_alphas, args.runs, args.seed, args.workers, args.out,
                               args.max_angle_deg)
                    for s in args.sigmas} if args.measure_alphas else {}
        r, a_deg, x = scenes(args.runs, args.seed, radar, args.max_angle_deg)
        b = bounds(r, a_deg, x, radar, args.sigmas, args.alphas, args.seed)
        rows = []
        for sigma in args.sigmas:
            unq = b[sigma]["unq"]
            unq_rms, unq_eff = median_rms(unq), efficient_median(unq, args.seed)
            m = measured.get(sigma, {})
            for al in args.alphas:
                cov = b[sigma][al]
                one_rms, one_eff = median_rms(cov), efficient_median(cov, args.seed)
                rows.append({"sigma": sigma, "alpha": al, "bound_rms_1bit": one_rms, "bound_rms_unq": unq_rms,
                             "ratio_rms": one_rms / unq_rms, "eff_median_1bit": one_eff, "eff_median_unq": unq_eff,
                             "ratio_eff": one_eff / unq_eff, "cml_1bit": m.get(scheme(al)),
                             "cml_unq": m.get("32bit_m512")})
        extra = two_bit(r, a_deg, x, radar, args.sigmas, args.seed)
        table_path.write_text(json.dumps({"seed": args.seed, "runs": args.runs, "rows": rows, "two_bit": extra},
                                         indent=1) + "\n")
    report(rows)
    print("\n".join(extra))
    plot(rows, args.figure)


def report(rows: list[dict]) -> None:
    print(f"{'sigma':>6} {'alpha':>6} | {'bound RMS 1bit':>14} {'unq':>7} {'ratio':>6} | {'eff.median 1bit':>15} "
          f"{'unq':>7} {'ratio':>6} | {'cml 1bit':>9} {'cml unq':>8} {'ratio':>6}")
    for r in rows:
        cml = (f"{r['cml_1bit']:>8.3f}m {r['cml_unq']:>7.3f}m {r['cml_1bit'] / r['cml_unq']:>6.2f}"
               if r["cml_1bit"] is not None else f"{'':>9} {'':>8} {'':>6}")
        print(f"{r['sigma']:>6g} {r['alpha']:>6.2f} | {r['bound_rms_1bit']:>13.4f}m {r['bound_rms_unq']:>6.4f}m "
              f"{r['ratio_rms']:>6.2f} | {r['eff_median_1bit']:>14.4f}m {r['eff_median_unq']:>6.4f}m "
              f"{r['ratio_eff']:>6.2f} | {cml}")
    for sigma in sorted({r["sigma"] for r in rows}):
        sub = [r for r in rows if r["sigma"] == sigma]
        best = min(sub, key=lambda r: r["ratio_eff"])
        meas = [r for r in sub if r["cml_1bit"] is not None]
        line = f"sigma {sigma:g}: best bound ratio {best['ratio_eff']:.2f} at alpha {best['alpha']:g}"
        if meas:
            bm = min(meas, key=lambda r: r["cml_1bit"])
            line += (f"; cml best {bm['cml_1bit']:.3f} m at alpha {bm['alpha']:g} = {bm['cml_1bit'] / bm['cml_unq']:.2f}"
                     f" x cml unquantized, {bm['cml_1bit'] / bm['eff_median_1bit']:.2f} x the 1-bit bound's median there")
        print(line)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    for i, sigma in enumerate(sorted({r["sigma"] for r in rows})):
        sub = [r for r in rows if r["sigma"] == sigma]
        col = f"C{i}"
        al = [r["alpha"] for r in sub]
        ax1.plot(al, [r["ratio_eff"] for r in sub], "-", color=col, label=f"bound, σ = {sigma:g}")
        meas = [r for r in sub if r["cml_1bit"] is not None]
        ax1.plot([r["alpha"] for r in meas], [r["cml_1bit"] / r["cml_unq"] for r in meas], "o--", color=col,
                 label=f"cml measured, σ = {sigma:g}")
        ax2.plot(al, [r["eff_median_1bit"] for r in sub], "-", color=col, label=f"1-bit bound, σ = {sigma:g}")
        ax2.axhline(sub[0]["eff_median_unq"], color=col, ls=":", lw=1)
        ax2.plot([r["alpha"] for r in meas], [r["cml_1bit"] for r in meas], "o--", color=col,
                 label=f"1-bit cml, σ = {sigma:g}")
        if meas:
            ax2.plot([0], [meas[0]["cml_unq"]], "s", color=col, mfc="none")
    ax1.axhline(GOAL_RATIO, color="k", lw=0.8, ls="-.", label="goal 2x")
    ax1.set(xlabel="dither scale α (dither width α δ)", ylabel="median error, 1-bit / unquantized",
            title="1-bit cost: Cramér–Rao bound and cml", yscale="log")
    ax2.set(xlabel="dither scale α", ylabel="median position error, m", yscale="log",
            title="median error (dotted: unquantized bound, □: its cml)")
    ax1.set_ylim(1.4, 16.0)
    ax1.set_yticks([1.5, 2, 3, 4, 6, 8, 12])
    ax1.legend(fontsize=7, ncol=2, loc="upper left")
    ax2.legend(fontsize=7)
    for ax in (ax1, ax2):
        ax.grid(True, which="both", alpha=0.3)
        ax.yaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
