"""Found rate, median position error and median radial-velocity error (modulo the ambiguity
interval) of ``cml`` against the radial speed of one target, with the phase step between
ramps (the default) and with the static model (``CmlOptions(motion=False)``), and of PBP
and ``qiht``, which keep the paper's static model:

    python -m experiments.speeds [--frames 600] [--pair-frames 300] [--seed 1]

Off-grid ranges uniform in 3-150 m, angles in +-60 deg, unit amplitudes, a random sign of
the velocity, noise sigma 0.1 (I and Q), 1-bit codes at the default alpha, K = 1; found: the
range within 0.6 m (one bin). Prints two Markdown tables (docs/design.md, "Targets that move
between ramps"): that one, and one of a static and a moving target in each frame
(:func:`pair_table`: cml told K = 2, cml deciding the count, PBP). Also the Monte Carlo's speeds (``qradar montecarlo --speeds``:
:func:`parse_speeds`, :func:`draw_speeds`)."""

from __future__ import annotations

import argparse

import numpy as np

from pipeline.defaults import DEFAULT_ALPHA
from pipeline.dsp.cml import CmlOptions, cml
from pipeline.dsp.decode import DecoderConfig, decode
from pipeline.dsp.localize import nearest_estimates
from pipeline.dsp.quantize import auto_delta, batch_unit_dither, dequantize, quantize
from radar_driver.model import RadarConfig, simulate_frames, wrap_velocity
from radar_driver.options import finite_float

#: the speeds of the table (m/s; "0:3": uniform in 0-3 m/s)
SPEEDS = ("0", "0.0625", "0.125", "0.375", "1.125", "1.5", "0:3")
#: the noise std of I and Q, full scale
SIGMA = 0.1


def frames(speed: str, b: int, seed: int, config: RadarConfig):
    """1-bit frames of ``b`` one-target scenes at ``speed``: (z, xi, delta, r, angle, v)."""
    rng = np.random.default_rng(seed)
    r, a = rng.uniform(3, 150, (b, 1)), rng.uniform(-60, 60, (b, 1))
    x = np.exp(2j * np.pi * rng.random((b, 1)))
    v = rng.uniform(0, 3, (b, 1)) if speed == "0:3" else np.full((b, 1), float(speed))
    v = v * rng.choice([-1.0, 1.0], (b, 1))
    return (*noisy_codes(simulate_frames(r, a, x, config, velocity_mps=v), rng), r, a, v)


def noisy_codes(g: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frames ``g`` (B, M, 2) in noise SIGMA, quantized to 1 bit at the default alpha:
    (codes' values z, dither xi, delta), as the decoders take them."""
    g = g + SIGMA * (rng.standard_normal(g.shape) + 1j * rng.standard_normal(g.shape))
    delta = auto_delta(g)
    xi = DEFAULT_ALPHA * delta[:, None, None] * batch_unit_dither(g.shape, rng)
    return dequantize(quantize(g, delta, 1, xi), delta, 1), xi, delta


def parse_speeds(text: str) -> tuple[float, float]:
    """A command line's ``--speeds``: ``LO:HI`` (m/s, 0 <= LO <= HI) or one speed."""
    parts = text.split(":")
    if len(parts) > 2:
        raise ValueError(f"{text!r} is not LO:HI (m/s)")
    lo, hi = (finite_float(p) for p in (parts * 2)[:2])
    if not 0 <= lo <= hi:
        raise ValueError(f"{text!r}: LO:HI needs 0 <= LO <= HI")
    return lo, hi


def draw_speeds(n_runs: int, k: int, seed: int, chunk: int, speeds: tuple[float, float] | None) -> np.ndarray | None:
    """The Monte Carlo's targets' radial velocities (n_runs, K) m/s of a chunk, uniform in
    ``speeds`` (lo, hi) with a random sign (None: static, None), from their own generator
    (the static scenes' draws stay as they were)."""
    if speeds is None:
        return None
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(k, chunk, 2)))
    lo, hi = speeds
    return rng.uniform(lo, hi, (n_runs, k)) * rng.choice([-1.0, 1.0], (n_runs, k))


#: the rows: cml with the phase step, cml's static model, the paper's decoders
DECODERS = ("cml", "cml_static", "pbp", "qiht")


def figures(speed: str, b: int, seed: int, decoder: str, config: RadarConfig) -> tuple[float, float, float]:
    """(found rate, median position error m, median |velocity error| m/s modulo V; NaN for
    a static model) of ``decoder`` (:data:`DECODERS`) at ``speed``."""
    z, xi, delta, r, a, v = frames(speed, b, seed, config)
    motion = decoder == "cml"
    if decoder.startswith("cml"):
        det = cml(z, xi, delta, 1, config, 1, options=CmlOptions(motion=motion)).detections(config)
    else:
        det = decode(z, xi, delta, 1, config, 1, DecoderConfig(algo=decoder, uncertainty=False))
    err, _ = nearest_estimates(r, a, det.range_m, det.angle_deg)
    found = float(np.mean(np.abs(det.range_m[:, 0] - r[:, 0]) <= 0.6))
    dv = np.abs(wrap_velocity(det.radial_velocity_mps[:, 0] - v[:, 0], config))
    return found, float(np.median(err)), float(np.median(dv)) if motion else float("nan")


def table(frames_a_speed: int = 600, seed: int = 1, config: RadarConfig = RadarConfig()) -> str:
    """The speed table (Markdown) of ``frames_a_speed`` frames a speed."""
    rows = {d: [figures(s, frames_a_speed, seed, d, config) for s in SPEEDS] for d in DECODERS}
    names = {"cml": "`cml`", "cml_static": "`cml`, static model", "pbp": "PBP", "qiht": "`qiht`"}
    lines = ["| radial speed (m/s) | " + " | ".join("uniform 0–3" if s == "0:3" else s for s in SPEEDS) + " |",
             "|---|" + "---|" * len(SPEEDS)]
    for d in DECODERS:
        lines.append(f"| {names[d]}: found | " + " | ".join(f"{100 * f:.1f} %" for f, _, _ in rows[d]) + " |")
        lines.append(f"| {names[d]}: median error | " + " | ".join(f"{e:.3g} m" for _, e, _ in rows[d]) + " |")
    lines.append("| `cml`: median velocity error | " + " | ".join(f"{d:.4f} m/s" for _, _, d in rows["cml"]) + " |")
    return "\n".join(lines)


#: the moving target's speeds of the pair table (m/s; "0:3": uniform in 0-3 m/s)
PAIR_SPEEDS = ("0.125", "0.375", "1.125", "0:3")
#: the pair table's decoders: cml told K = 2, cml deciding the count (at most 4), PBP told K = 2
PAIR_DECODERS = ("cml", "cml_auto", "pbp")
#: the least range between the pair's targets, m (a bin is 0.6 m: closer ones are one peak)
PAIR_MIN_SEPARATION_M = 1.5


def pair_frames(speed: str, b: int, seed: int, config: RadarConfig):
    """1-bit frames of ``b`` scenes of two targets, the first static, the second at
    ``speed`` (random sign): off-grid ranges in 3-150 m at least PAIR_MIN_SEPARATION_M apart,
    angles in +-60 deg, unit amplitudes of random phase, noise SIGMA. (z, xi, delta, r, a)."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(3, 150, (b, 2))
    close = np.abs(r[:, 0] - r[:, 1]) < PAIR_MIN_SEPARATION_M
    while close.any():  # bounded in practice: a pair is close with chance ~2 %
        r[close, 1] = rng.uniform(3, 150, int(close.sum()))
        close = np.abs(r[:, 0] - r[:, 1]) < PAIR_MIN_SEPARATION_M
    a = rng.uniform(-60, 60, (b, 2))
    x = np.exp(2j * np.pi * rng.random((b, 2)))
    lo, hi = (0.0, 3.0) if speed == "0:3" else (float(speed),) * 2
    v = np.zeros((b, 2))
    v[:, 1] = rng.uniform(lo, hi, b) * rng.choice([-1.0, 1.0], b)
    return (*noisy_codes(simulate_frames(r, a, x, config, velocity_mps=v), rng), r, a)


def pair_figures(speed: str, b: int, seed: int, decoder: str, config: RadarConfig) -> tuple[float, float, float]:
    """(static target found, moving target found, both found) rates of ``decoder``
    (:data:`PAIR_DECODERS`) on :func:`pair_frames`; found: an estimate within 0.6 m in range."""
    z, xi, delta, r, a = pair_frames(speed, b, seed, config)
    algo, auto = decoder.removesuffix("_auto"), decoder.endswith("_auto")
    det = decode(z, xi, delta, 1, config, 4 if auto else 2, DecoderConfig(algo=algo, auto_k=auto, uncertainty=False))
    gap = np.abs(det.range_m[:, None, :] - r[:, :, None])  # (B, 2, L)
    found = np.nanmin(np.where(np.isnan(gap), np.inf, gap), axis=2) <= 0.6  # (B, 2)
    return float(found[:, 0].mean()), float(found[:, 1].mean()), float(found.all(axis=1).mean())


def pair_table(frames_a_speed: int = 300, seed: int = 1, config: RadarConfig = RadarConfig()) -> str:
    """The table (Markdown) of one static and one moving target: found rates of each and
    of both, ``frames_a_speed`` frames a speed."""
    names = {"cml": "`cml`, K = 2", "cml_auto": "`cml`, `--K auto`", "pbp": "PBP, K = 2"}
    lines = ["| the moving target's speed (m/s) | " + " | ".join("uniform 0–3" if s == "0:3" else s
                                                                 for s in PAIR_SPEEDS) + " |",
             "|---|" + "---|" * len(PAIR_SPEEDS)]
    for d in PAIR_DECODERS:
        cells = [pair_figures(s, frames_a_speed, seed, d, config) for s in PAIR_SPEEDS]
        lines.append(f"| {names[d]}: static / moving / both found | "
                     + " | ".join(f"{100 * f0:.1f} / {100 * f1:.1f} / {100 * both:.1f} %" for f0, f1, both in cells)
                     + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=600, help="frames a speed")
    ap.add_argument("--pair-frames", type=int, default=300, help="frames a speed of the pair table")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    print(table(args.frames, args.seed))
    print()
    print(pair_table(args.pair_frames, args.seed))


if __name__ == "__main__":
    main()
