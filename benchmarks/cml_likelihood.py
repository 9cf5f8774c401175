#!/usr/bin/env python3
"""Accuracy of cml's two likelihoods of a 1-bit code under sensor noise: the scaled logistic
and the exact Gaussian (``Phi`` of the margin over the noise std), the noise std estimated
from the codes or given, against cml on the unquantized frames of the same scenes.

Scenes: the Monte Carlo's continuous ones (``qradar montecarlo --ranges continuous``: K
targets, ranges uniform over 3-150 m, angles in +-90 deg, the strongest amplitude 1),
complex white Gaussian noise of std ``sigma`` on I and on Q, 1-bit dithered frames of
M = 512 (delta the smallest 1-bit step of each noisy frame, dither scale ``--alpha``).

    .venv/bin/python benchmarks/cml_likelihood.py [--runs 400] [--K 1] [--alpha 1] [--sigmas 0.03 0.1 0.3]

Prints one JSON object: the median (and 90th percentile) position error, m, per noise
sigma and decoder, and the ratio of each 1-bit median to the unquantized one.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from pipeline.dsp.cml import CmlOptions, cml
from pipeline.dsp.localize import nearest_estimates
from experiments.montecarlo import SceneSpec, draw_scenes
from pipeline.dsp.quantize import auto_delta, batch_unit_dither, dequantize, quantize
from radar_driver.model import RadarConfig, simulate_frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=400)
    ap.add_argument("--K", type=int, default=1)
    ap.add_argument("--alpha", type=float, default=1.0)
    ap.add_argument("--sigmas", type=float, nargs="+", default=[0.03, 0.1, 0.3])
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()
    cfg = RadarConfig()
    out = {"runs": args.runs, "K": args.K, "alpha": args.alpha, "median_m": {}, "p90_m": {}, "ratio_to_unquantized": {}}
    for sigma in args.sigmas:
        rng = np.random.default_rng(args.seed)
        _, _, r, a, x = draw_scenes(args.runs, args.K, rng, cfg, scene=SceneSpec(ranges="continuous"))
        clean = simulate_frames(r, a, x, cfg)
        g = clean + sigma * (rng.standard_normal(clean.shape) + 1j * rng.standard_normal(clean.shape))
        delta = auto_delta(g)
        xi = args.alpha * delta[:, None, None] * batch_unit_dither(g.shape, rng)
        z = dequantize(quantize(g, delta, 1, xi), delta, 1)

        def error(res):
            det = res.detections(cfg)
            return nearest_estimates(r, a, det.range_m, det.angle_deg)[0]

        errs = {"unquantized": error(cml(g, None, None, None, cfg, args.K))}
        for lik in ("logistic", "gaussian"):
            for given in (False, True):
                name = f"1bit_{lik}" + ("_sigma_given" if given else "")
                errs[name] = error(cml(z, xi, delta, 1, cfg, args.K, options=CmlOptions(likelihood=lik),
                                       noise_sigma=sigma if given else None))
        key = f"{sigma:g}"
        out["median_m"][key] = {k: round(float(np.median(v)), 4) for k, v in errs.items()}
        out["p90_m"][key] = {k: round(float(np.percentile(v, 90)), 4) for k, v in errs.items()}
        base = np.median(errs["unquantized"])
        out["ratio_to_unquantized"][key] = {k: round(float(np.median(v) / base), 2) for k, v in errs.items()
                                            if k != "unquantized"}
        print(json.dumps({key: out["median_m"][key]}), file=sys.stderr, flush=True)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
