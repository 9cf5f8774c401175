"""The figures of a re-processing (:mod:`replay.reprocess`): the mean position error against
alpha (Fig. 5a) and each target's estimates in the plane, of its
sweep results (:class:`~replay.reprocess.SweepResult`, by decoder)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from radar_driver.model import polar_to_xy

from .outputs import pyplot


def plot_alpha_sweep(results: dict, path: Path) -> Path:
    """Fig. 5a: mean position error against alpha. One decoder: a curve per target and
    their mean; several: the mean of the targets, one curve per decoder (each target's
    curve dotted, in the decoder's colour), each decoder's best alpha marked."""
    plt = pyplot()
    first = next(iter(results.values()))
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=110)
    if len(results) == 1:
        me = first.mean_error_m
        for i, t in enumerate(first.truth):
            ax.plot(first.alphas, me[:, i], marker="o", ms=3,
                    label=f"target {i + 1}: {t['range_m']:.2f} m, {t['angle_deg']:+.0f}°")
        ax.plot(first.alphas, me.mean(axis=1), "k--", lw=1, label="mean of targets")
    for n, (algo, result) in enumerate(results.items()):
        me = result.mean_error_m
        best = result.best_index
        color = "grey" if len(results) == 1 else f"C{n}"
        if len(results) > 1:
            ax.plot(result.alphas, me.mean(axis=1), "-", marker="o", ms=3, color=color,
                    label=f"{algo}, mean of targets: best α = {result.alphas[best]:.2f}, {me[best].mean():.3f} m")
            for i in range(me.shape[1]):
                ax.plot(result.alphas, me[:, i], ":", lw=0.8, color=color)
        else:
            ax.annotate(f"best α = {result.alphas[best]:.2f}", (result.alphas[best], me.mean(axis=1)[best]),
                        textcoords="offset points", xytext=(8, 12), fontsize=8)
        ax.axvline(result.alphas[best], color=color, lw=0.8, ls=":")
    if len(results) > 1 and any(np.any(np.isfinite(r.mean_error_m) & (r.mean_error_m > 0))
                                for r in results.values()):
        ax.set_yscale("log")
        ax.plot([], [], ":", color="0.4", lw=0.8, label="each target")
    ax.set_xlabel("dither scale α")
    ax.set_ylabel("mean position error (m)")
    p = first.params
    ax.set_title(f"{first.rec.sensor_id}: {first.rec.frames.shape[0]} frames, {p['bits']}-bit, "
                 f"{', '.join(a.upper() for a in results)}, K = {'auto, at most ' if p['K_auto'] else ''}{p['K']}",
                 fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="best", framealpha=0.9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _ellipse(ax, mean_xy, cov, color, ls):
    vals, vecs = np.linalg.eigh(cov)
    vals = np.maximum(vals, 0)
    t = np.linspace(0, 2 * np.pi, 100)
    circle = np.stack([np.cos(t), np.sin(t)])
    pts = (vecs @ (2 * np.sqrt(vals)[:, None] * circle)).T + mean_xy  # 2 sigma
    ax.plot(pts[:, 1], pts[:, 0], color=color, ls=ls, lw=1)


def plot_reconstructions(result, path: Path) -> Path:
    """Mean estimated position of each target with its 2-sigma ellipse over the frames,
    alpha = 0 (or the smallest alpha) against the best alpha; truth as crosses. A moving
    target: its estimates alone, and its true path from the cross (at the file's first
    frame). Lateral y (m) across, boresight x (m) up; the radar at (0, 0)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.6, 5.6), dpi=110)
    first = int(np.argmin(result.alphas))
    cases = [(result.best_index, "tab:blue", "-", "o"), (first, "tab:red", "--", "s")]
    for idx, color, ls, marker in cases:
        r = result.results[idx]
        ax.plot([], [], marker, color=color, ms=6, mfc="none" if marker == "s" else color, label=f"α = {r.alpha:.2f}")
        for i in range(len(result.truth)):
            xy = r.nearest_xy[:, i]
            xy = xy[np.all(np.isfinite(xy), axis=1)]  # frames without any target (K auto) have no estimate
            if not xy.shape[0]:
                continue
            ax.scatter(xy[:, 1], xy[:, 0], s=4, color=color, alpha=0.25)
            if result.moving(i):  # a mean over a path says nothing: the estimates alone
                continue
            mean = xy.mean(axis=0)
            cov = np.cov(xy.T) if xy.shape[0] > 1 else np.zeros((2, 2))
            ax.plot(mean[1], mean[0], marker, color=color, ms=6, mfc="none" if marker == "s" else color)
            _ellipse(ax, mean, cov, color, ls)
    for i, t in enumerate(result.truth):
        x, y = polar_to_xy(t["range_m"], np.deg2rad(t["angle_deg"]))
        ax.plot(y, x, "kx", ms=9, mew=2, label="truth" if i == 0 else None)
        if result.moving(i):
            px, py = polar_to_xy(result.positions[0][:, i], np.deg2rad(result.positions[1][:, i]))
            ax.plot(py, px, "k-", lw=1, label=None if any(map(result.moving, range(i))) else "true path")
    ax.plot(0, 0, "k^", ms=8, label="radar")
    ax.set_xlabel("y (m), across boresight (+ = antenna 2 side)")
    ax.set_ylabel("x (m), along boresight")
    ax.set_title(f"{result.params['algo'].upper()}, {result.rec.frames.shape[0]} frames: mean of the estimate "
                 "nearest each target, 2σ ellipses", fontsize=9)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
