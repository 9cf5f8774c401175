"""PNG figures: polar error maps like the paper's Figs. 2-4."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.dsp.decode import Algo
from replay.outputs import pyplot


ERROR_SCALE_MIN_M = 0.01


def shared_error_scale_m(maps: list[np.ndarray]) -> tuple[float, float]:
    """One logarithmic colour scale (vmin, vmax) in m for a set of error maps: from
    1 cm to the largest finite cell rounded up to a power of ten (at least 1 m).

    Logarithmic because the maps span four decades: centimetres (32-bit, full ramp),
    metres (dithered noise, non-dithered artifacts) and hundreds of metres (arcsin
    wraps near +-90 deg)."""
    vals = [m[np.isfinite(m)] for m in maps]
    top = max((float(v.max()) for v in vals if v.size), default=1.0)
    top = max(top, 1.0)
    return ERROR_SCALE_MIN_M, float(10 ** np.ceil(np.log10(top)))


class PolarErrorMaps:
    """Polar heat maps of (n_range, n_angle) mean-error maps (m) sharing one shape, range and
    colour scale: the figure (axes, grid, colour bar, layout) is built once and each map only
    swaps its cells and title before it is written (a run's maps: ~3x less CPU than a figure
    each, most of which was the layout).

    Cells span ranges [0, max_range_m] and angles [-90, 90] deg; boresight points up,
    positive angles to the right (antenna 2's side). ``scale_m`` = (vmin, vmax) of the
    logarithmic colour scale; smaller errors get the lowest colour. Empty cells stay white."""

    def __init__(self, shape: tuple[int, int], max_range_m: float, scale_m: tuple[float, float]):
        self._plt = plt = pyplot()
        from matplotlib.colors import LogNorm

        n_r, n_a = shape
        self.shape = shape
        theta_edges = np.deg2rad(np.linspace(-90.0, 90.0, n_a + 1))
        r_edges = np.linspace(0.0, max_range_m, n_r + 1)
        self.fig = fig = plt.figure(figsize=(6.4, 3.9), dpi=110)
        ax = fig.add_subplot(projection="polar")
        ax.set_theta_zero_location("N")
        ax.set_theta_direction(-1)  # positive angles clockwise from boresight: to the right
        ax.set_thetamin(-90)
        ax.set_thetamax(90)
        self._vmin, vmax = scale_m
        empty = np.ma.masked_all(shape)
        self._mesh = ax.pcolormesh(theta_edges, r_edges, empty, cmap="viridis", norm=LogNorm(self._vmin, vmax),
                                   shading="flat")
        self._title = ax.set_title(self._title_text(""), fontsize=9, pad=14)
        ax.set_thetagrids(np.arange(-90, 91, 30), [f"{a}°" for a in range(-90, 91, 30)])
        ax.set_rlabel_position(-90)
        ax.text(np.deg2rad(-90), max_range_m * 1.02, "range R (m)", ha="center", va="top", fontsize=8)
        ax.tick_params(labelsize=7)
        cbar = fig.colorbar(self._mesh, ax=ax, shrink=0.75, pad=0.08, extend="both")
        cbar.set_label("mean position error (m, log scale)")
        fig.tight_layout()  # once: the title's two lines are the same height for every map

    @staticmethod
    def _title_text(title: str) -> str:
        return f"{title}\nangle θ (deg) around, range R (m) outwards"

    def write(self, path: Path, error_map_m: np.ndarray, title: str) -> Path:
        """Write the map ``error_map_m`` (n_range, n_angle), m, titled ``title``, to ``path`` (PNG)."""
        if error_map_m.shape != self.shape:
            raise ValueError(f"an error map of shape {error_map_m.shape} in maps of shape {self.shape}")
        self._mesh.set_array(np.ma.masked_invalid(np.clip(error_map_m, self._vmin, None)))
        self._title.set_text(self._title_text(title))
        path = Path(path)
        self.fig.savefig(path)
        return path

    def close(self) -> None:
        self._plt.close(self.fig)


def map_figures(summary: dict) -> list[tuple[str, str, str]]:
    """The polar maps of a Monte Carlo ``summary``: (map key, PNG file name, title) for every
    scheme and K (all targets), and for K >= 2 the strongest and the weakest target."""
    wanted: list[tuple[str, str, str]] = []
    for kkey, block in summary.items():
        if not (kkey.startswith("K") and kkey[1:].isdigit() and isinstance(block, dict)):
            continue
        k = int(kkey[1:])
        for scheme in block:
            base = f"{kkey}_{scheme}"
            wanted.append((f"{base}_all", f"{base}.png", f"{scheme}, K = {k}" + (": all targets" if k > 1 else "")))
            if k > 1:
                wanted.append((f"{base}_strong", f"{base}_strong.png", f"{scheme}, K = {k}: strongest target"))
                wanted.append((f"{base}_weak", f"{base}_weak.png", f"{scheme}, K = {k}: weakest target"))
    return wanted


def montecarlo_figures(out_dir: Path, summary: dict, maps: dict[str, np.ndarray], max_range_m: float) -> list[Path]:
    """Polar maps for every scheme and K (all targets), and for K >= 2 the strongest and
    the weakest target separately, on one shared colour scale (:func:`map_figures`).
    Returns the PNG paths."""
    wanted = map_figures(summary)
    scale = shared_error_scale_m([maps[key] for key, _, _ in wanted])
    paths = []
    figures: dict[tuple[int, int], PolarErrorMaps] = {}  # one figure a shape of map
    try:
        for key, name, title in wanted:
            shape = maps[key].shape
            if shape not in figures:
                figures[shape] = PolarErrorMaps(shape, max_range_m, scale)
            paths.append(figures[shape].write(Path(out_dir) / name, maps[key], title))
    finally:
        for figure in figures.values():
            figure.close()
    return paths


def error_vs_m(summary: dict, stat: str = "median_m") -> dict[str, dict]:
    """For every K and decoder with dithered 1-bit schemes at two or more M: the error
    ``stat`` against M and the least-squares slope of log(error) on log(M).

    Returns {"K1 pbp": {"M": [...], "error_m": [...], "slope": s}, ...}."""
    import re

    pat = re.compile(r"^dither_m(\d+)(?:@(\w+))?$")
    series: dict[str, dict[int, float]] = {}
    for kkey, block in summary.items():
        if not (kkey.startswith("K") and isinstance(block, dict)):
            continue
        for name, st in block.items():
            m = pat.match(name)
            if m:
                series.setdefault(f"{kkey} {m.group(2) or Algo.PBP}", {})[int(m.group(1))] = st[stat]
    out = {}
    for label, pts in sorted(series.items()):
        if len(pts) < 2:
            continue
        ms = np.array(sorted(pts))
        errs = np.array([pts[m] for m in ms])
        slope = float(np.polyfit(np.log(ms), np.log(errs), 1)[0]) if np.all(errs > 0) else float("nan")
        out[label] = {"M": ms.tolist(), "error_m": errs.tolist(), "slope": round(slope, 3)}
    return out


def error_vs_m_figure(path: Path, series: dict[str, dict], stat: str = "median") -> Path:
    """Log-log plot of the error against M with the fitted slopes in the legend."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.0, 4.2), dpi=110)
    for label, s in series.items():
        ls = "-" if label.endswith(Algo.PBP) else "--"
        ax.loglog(s["M"], s["error_m"], ls, marker="o", label=f"{label}: slope {s['slope']:+.2f}")
    ax.set_xlabel("measurements M (whole ramps of 256)")
    ax.set_ylabel(f"{stat} position error (m)")
    ax.set_title("1-bit dithered: error against M", fontsize=10)
    ms = sorted({m for s in series.values() for m in s["M"]})
    from matplotlib.ticker import NullFormatter

    ax.set_xticks(ms)
    ax.set_xticklabels([str(m) for m in ms])
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


def detection_figure(path: Path, summary: dict) -> Path | None:
    """K auto: the weakest target's detection probability against its amplitude, one
    curve per (K > 1, scheme, decoder), with the false targets per frame in the legend.
    None when the summary has no such curve."""
    curves = [(f"K={key[1:]} {name}", st) for key, block in summary.items()
              if key.startswith("K") and isinstance(block, dict) and key != "K1"
              for name, st in block.items() if "pd_weak_by_amplitude" in st]
    if not curves:
        return None
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.0, 4.2), dpi=110)
    for label, st in curves:
        pts = np.array(st["pd_weak_by_amplitude"], dtype=float)
        ax.plot(pts[:, 0] + 0.05, pts[:, 1], "-o", ms=3,
                label=f"{label}: {st['false_targets_per_frame']:.3f} false targets/frame")
    ax.axhline(0.95, color="0.5", lw=0.8, ls=":")
    ax.set_xlabel("amplitude of the weakest target (strongest = 1), bin centres")
    ax.set_ylabel("detection probability")
    ax.set_ylim(0, 1.02)
    ax.set_xlim(0, 1)
    ax.set_title(f"K auto (pfa {summary['count']['pfa']:g}, at most {summary['count']['max_targets']} targets)",
                 fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


def draw_error_vs_frames(ax, results: list[dict], title: str) -> None:
    """On ``ax``: median position error against T frames decoded together, one curve per
    result (noise level, its slope), log-log, with 1/T and 1/sqrt(T) guides from the first
    curve's T = 1."""
    for r in results:
        slope = "" if r.get("slope") is None else f": slope {r['slope']:.2f}"
        ax.loglog(r["T"], r["median_m"], "o-", label=f"noise sigma {r['noise_sigma']:g}{slope}")
    t = np.array(results[0]["T"], dtype=float)
    ax.loglog(t, results[0]["median_m"][0] / t, "k:", lw=0.8, label="1/T")
    ax.loglog(t, results[0]["median_m"][0] / np.sqrt(t), "k--", lw=0.8, label="1/sqrt(T)")
    ax.set_xlabel("T frames decoded together (fresh dither each)")
    ax.set_ylabel("median position error, m")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)


def error_vs_frames_figure(path: Path, results: list[dict]) -> Path:
    """The Monte Carlo in time (:func:`pipeline.dsp.integrate.time_monte_carlo`) as a PNG
    (:func:`draw_error_vs_frames`)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    draw_error_vs_frames(ax, results, f"1 bit, one static target off the grid, {results[0]['runs']} runs")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
