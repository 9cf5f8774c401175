"""The curves a researcher expects of the decoders, from seeded simulations: detection
probability against SNR (``pbp`` and ``cml`` with ``--K auto``, 1-bit at alpha 0.45 and 1,
unquantized), false targets a frame beside one strong target against the noise for alpha 0,
0.45 and 1 (:mod:`.false_alarms`), and the targets' ellipse coverage (:mod:`.coverage`).

``python -m experiments.curves OUT_DIR`` writes ``detection_vs_snr.png``,
``false_targets.png``, ``ellipse_coverage.png`` and ``curves.json`` (their numbers) there;
``make docs-figures`` writes them to docs/figures/ (docs/science.md shows them).
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radar_driver.model import RadarConfig, simulate_frames

from pipeline.dsp.decode import Decoder, DecoderConfig
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from replay.outputs import pyplot
from experiments.coverage import CASES as COVERAGE_CASES, coverage, scenes
from experiments.false_alarms import AlarmCase, MATCH_BINS, false_targets

#: SNR of a target per complex sample and receiver, |A|^2 / (2 sigma^2), dB
SNR_DB = tuple(range(-26, -5, 2))
#: the frames' kinds: (label, bits, alpha)
SCHEMES = (("1-bit, α 0.45", 1, 0.45), ("1-bit, α 1", 1, 1.0), ("unquantized", None, 0.0))
ALGOS = ("pbp", "cml")
#: false targets a frame: the noise levels and the dither scales
ALARM_SIGMAS = (0.0, 0.01, 0.03, 0.1, 0.3)
ALARM_ALPHAS = (0.0, 0.45, 1.0)


@dataclass(frozen=True)
class CurveConfig:
    """Frames a point of each curve and the seed."""

    frames: int = 300
    alarm_frames: int = 1000
    seed: int = 0


def detection(algo: str, bits: int | None, alpha: float, snr_db: float, frames: int, seed: int,
              config: RadarConfig | None = None) -> float:
    """Share of frames in which ``algo`` with ``--K auto`` (pfa 1e-3) finds one target of
    amplitude 1 (within MATCH_BINS range bins) at ``snr_db``."""
    config = RadarConfig() if config is None else config
    rng = np.random.default_rng(seed)
    case = AlarmCase(1, 0.0, frames=frames)
    r, a, x = scenes(case, rng)
    sigma = np.sqrt(0.5 * 10.0 ** (-snr_db / 10.0))
    g = simulate_frames(r, a, x, config)
    g = g + sigma * (rng.standard_normal(g.shape) + 1j * rng.standard_normal(g.shape))
    dec = Decoder(DecoderConfig(algo=algo, auto_k=True, uncertainty=False))
    det = dec.decode_batch(g if bits is None else quantize_frames(g, QuantizerConfig(alpha=alpha, bits=bits),
                                                                   np.arange(frames)), config, 4)
    near = det.present & (np.abs(det.range_m - r) <= MATCH_BINS * config.range_resolution_m)
    return float(near.any(axis=1).mean())


def compute(cfg: CurveConfig = CurveConfig()) -> dict:
    """Every curve's numbers (JSON-ready)."""
    pd = {algo: {label: [detection(algo, bits, alpha, s, cfg.frames, cfg.seed + i) for i, s in enumerate(SNR_DB)]
                 for label, bits, alpha in SCHEMES} for algo in ALGOS}
    alarms = {f"{a:g}": [false_targets(AlarmCase(1, s, alpha=a, frames=cfg.alarm_frames, seed=cfg.seed + i))[0]
                         for i, s in enumerate(ALARM_SIGMAS)] for a in ALARM_ALPHAS}
    cov = [dict(k=c.k, sigma=c.sigma, bits=c.bits, inside=coverage(c)[:2]) for c in COVERAGE_CASES]
    return {"snr_db": list(SNR_DB), "detection": pd, "alarm_sigmas": list(ALARM_SIGMAS), "false_targets": alarms,
            "coverage": cov}


def plot(data: dict, out: Path) -> list[Path]:
    """The three PNGs of ``data`` (:func:`compute`) into ``out``."""
    plt = pyplot()
    paths = []
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for algo, style in zip(ALGOS, ("--", "-")):
        for (label, _, _), color in zip(SCHEMES, ("C0", "C1", "C2")):
            ax.plot(data["snr_db"], data["detection"][algo][label], style, color=color, marker="o", ms=3,
                    label=f"{algo}, {label}")
    ax.set(xlabel="SNR per complex sample and receiver, dB", ylabel="detection probability (K auto, pfa 1e-3)",
           ylim=(-0.02, 1.02))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    paths.append(_save(fig, out / "detection_vs_snr.png"))
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    floor = 0.5 / 1000  # zeros drawn at half a false target in the frames run
    for (a, values), mark, size in zip(data["false_targets"].items(), ("o", "s", "^"), (9, 6, 4)):
        ax.plot([max(s, 1e-3) for s in data["alarm_sigmas"]], [max(v, floor) for v in values], marker=mark, ms=size,
                label=f"1-bit, α {a}")
    ax.axhline(1e-3, color="k", lw=0.8, ls=":", label="pfa 1e-3")
    ax.axhline(2e-3, color="r", lw=0.8, ls=":", label="2 × pfa")
    ax.set(xscale="log", yscale="log", xlabel="noise σ per real part (0 drawn at 1e-3)",
           ylabel="false targets a frame (cml, K auto; 0 drawn at 5e-4)", title="beside one strong target")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    paths.append(_save(fig, out / "false_targets.png"))
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for k, bits, mark in ((1, 1, "o"), (1, None, "s"), (2, 1, "^"), (2, None, "v")):
        rows = [c for c in data["coverage"] if c["k"] == k and c["bits"] == bits]
        label = f"K {k}, {'1-bit α 0.45' if bits else 'unquantized'}"
        for level, color in ((0, "C0"), (1, "C1")):
            ax.plot([c["sigma"] for c in rows], [100 * c["inside"][level] for c in rows], marker=mark, color=color,
                    ls="-" if bits else "--", label=label if level == 0 else None)
    for target in (39.3, 86.5):
        ax.axhspan(target - 3, target + 3, color="0.85", zorder=0)
    ax.set(xscale="log", xlabel="noise σ per real part", ylabel="true position inside the ellipse, %",
           title="1σ (lower) and 2σ (upper) ellipses of cml's targets", ylim=(0, 100))
    ax.legend(fontsize=7)
    paths.append(_save(fig, out / "ellipse_coverage.png"))
    return paths


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    fig.clf()
    return path


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    data = compute()
    (out / "curves.json").write_text(json.dumps(data, indent=1) + "\n")
    for p in plot(data, out):
        print(f"wrote {p}")


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "out/curves"))
