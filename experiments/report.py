"""What a Monte Carlo run writes (summary.json, config.json, maps.npz, the PNG maps,
error_vs_m) and the text table it prints."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.errors import PipelineError
from experiments.montecarlo import PD_AMPLITUDE, MonteCarloResult
from replay.outputs import output_folder

#: the files a Monte Carlo run writes whatever its options (a folder holding one is refused unless --force)
OUTPUT_FILES = ("summary.json", "config.json", "maps.npz")


def prepare_out_dir(out_dir: Path, names: tuple[str, ...] = OUTPUT_FILES, force: bool = False):
    """The output folder checked before a long run, so that a bad path or an earlier run's
    outputs (unless ``force``) fail at once; made (its own folder only) for the ``with``
    block's work, and removed again if that fails before writing into it
    (:func:`replay.outputs.output_folder`)."""
    return output_folder(out_dir, names, force)


#: the files a Monte Carlo run writes as its options ask, besides OUTPUT_FILES and the maps
OPTIONAL_FILES = ("detection.png", "error_vs_m.json", "error_vs_m.png")


def earlier_outputs(out_dir: Path) -> set[str]:
    """The files of ``out_dir`` that an earlier Monte Carlo run wrote there, by its
    summary.json (none: no summary, or not one of a Monte Carlo)."""
    from experiments.plots import map_figures

    try:
        summary = json.loads((Path(out_dir) / "summary.json").read_text())
    except (OSError, ValueError):
        return set()
    if not isinstance(summary, dict):
        return set()
    names = {name for _, name, _ in map_figures(summary)} | set(OPTIONAL_FILES)
    return {n for n in names if (Path(out_dir) / n).is_file()}


def write_outputs(result: MonteCarloResult, out_dir: Path, max_range_m: float, plots: bool = True) -> list[str]:
    """Write summary.json, config.json, maps.npz, the polar error maps (PNG, unless
    ``plots`` is False) and, when the schemes span several M, error_vs_m.json/.png to
    ``out_dir``; then remove what an earlier run wrote there that this one did not (a
    folder taken over with ``--force``: no map of another run left beside these results).
    Returns the report lines (the table, the slopes, what was written and removed)."""
    from experiments.plots import detection_figure, error_vs_m, error_vs_m_figure, montecarlo_figures

    out_dir = Path(out_dir)
    earlier = earlier_outputs(out_dir)
    try:
        (out_dir / "summary.json").write_text(json.dumps(result.summary, indent=2) + "\n")
        (out_dir / "config.json").write_text(json.dumps(result.run_config, indent=2) + "\n")
        np.savez_compressed(out_dir / "maps.npz", **result.maps)
        pngs = montecarlo_figures(out_dir, result.summary, result.maps, max_range_m) if plots else []
        if plots and result.summary.get("count", {}).get("auto"):
            pd_png = detection_figure(out_dir / "detection.png", result.summary)
            pngs += [pd_png] if pd_png else []
        slopes = error_vs_m(result.summary)
        if slopes:
            (out_dir / "error_vs_m.json").write_text(json.dumps(slopes, indent=2) + "\n")
            if plots:
                pngs.append(error_vs_m_figure(out_dir / "error_vs_m.png", slopes))
        stale = sorted(earlier - {Path(p).name for p in pngs} - ({"error_vs_m.json"} if slopes else set()))
        for name in stale:
            (out_dir / name).unlink(missing_ok=True)
    except OSError as exc:
        raise PipelineError(f"cannot write the Monte Carlo results to {out_dir}: {exc.strerror or exc}") from None
    lines = [f"{label}: median error {s['error_m']} m at M = {s['M']}: slope {s['slope']:+.2f}"
             for label, s in slopes.items()]
    rc = result.run_config
    lines += [format_table(result.summary), "",
              f"{sum(rc['runs_per_k'].values()) * len(rc['schemes'])} runs (x {len(rc['algos'])} decoders) in "
              f"{result.summary['seconds']:.1f} s; wrote {out_dir}/summary.json, maps.npz"
              + (f" and {len(pngs)} PNG maps" if pngs else "")]
    if stale:
        lines.append(f"removed an earlier run's {', '.join(stale)} from {out_dir}")
    return lines


def format_table(summary: dict) -> str:
    """The summary as a fixed-width text table (one row per K and scheme; with K auto
    the detection columns too)."""
    cols = ["mean_m", "median_m", "p90_m", "median_within_60deg_m", "cells_over_5m_within_60deg",
            "strong_mean_m", "weak_mean_m"]
    heads = ["mean", "median", "p90", "med|θ|<60", "cells>5m", "strong", "weak"]
    pd_cols = ["pd_strong", "pd_weak", f"pd_weak_amp_ge_{PD_AMPLITUDE}", "false_targets_per_frame"]
    # Pd: a detection within --gate-m of a target's range finds it, the unclaimed are false (in range alone);
    # the score's: within 1 m in the plane (pipeline.dsp.score). Two counts of false targets, two names (FA: false
    # alarms, in range).
    pd_heads = ["Pd strong", "Pd weak", f"Pd w≥{PD_AMPLITUDE}", "Pd FA/fr"]
    auto = bool(summary.get("count", {}).get("auto"))
    score_heads = ["found str", "found weak", "false/fr"]  # the honest score: within 1 m in the plane
    lines = [f"{'K':<3} {'scheme':<22}" + "".join(f"{h:>11}" for h in heads + (pd_heads if auto else [])
                                                  + score_heads)]
    for key, block in summary.items():
        if not (key.startswith("K") and isinstance(block, dict)):
            continue
        for scheme, st in block.items():
            vals = []
            for c in cols:
                v = st[c]
                vals.append(f"{v:>10.1%} " if c == "cells_over_5m_within_60deg" else f"{v:>9.3f}m ")
            if auto:
                vals += [f"{st[c]:>10.3f} " if c == "false_targets_per_frame" else f"{st[c]:>10.1%} "
                         for c in pd_cols]
            sc = st.get("score")
            if sc is not None:
                rates = [t["detection_rate"] for t in sc["targets"]]
                vals += [f"{v:>10.1%} " if v is not None else f"{'n/a':>10} " for v in (rates[0], rates[-1])]
                vals.append(f"{sc['false_targets_per_frame']:>10.3f} ")
            lines.append(f"{key[1:]:<3} {scheme:<22}" + "".join(vals))
    return "\n".join(lines)
