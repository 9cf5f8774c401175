"""The honest score of targets against the true positions: the one function every command
that compares with a truth uses (``qradar run``'s summary, ``reprocess``'s results, the
Monte Carlo's summary, :func:`qradar.score`).

The distance from each true target to its *nearest* target (the paper's error) costs
nothing for a false target and hides a missed target behind a found one: a decoder that
reports four ghosts a frame scores as well as one that reports the two reflectors. So the
targets of a frame are first matched one to one with the true targets (pairs taken in
order of distance in the plane, each true target and each target at most once, a pair
only within ``distance_m``), and the score counts:

- per true target, its **detection rate** (frames in which a target was matched to it)
  and the **median error of its detections** (the matched targets' distances, m);
- **false targets a frame**: targets matched to no true target (near none);
- **targets a frame**: every target reported;
- beside them, the **median of the nearest** (each true target to the nearest target,
  matched or not), the paper's figure, never the only one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radar_driver.model import polar_to_plane

from pipeline.errors import ParameterError

#: a true target counts as detected in a frame when a target lies within this distance of it
#: in the plane, m (a bit less than two range bins of the K-MD2's 0.6 m)
DETECTION_DISTANCE_M = 1.0


@dataclass(frozen=True)
class FrameScores:
    """The score of each frame of a batch (B frames, K true targets).

    error_m (B, K): distance from each true target to the target matched to it, m (NaN:
    not detected); nearest_m (B, K): to the nearest target, matched or not, m (inf: the
    frame has none); false_targets (B,): targets matched to no true target; targets (B,):
    targets in the frame; distance_m: the matching distance, m."""

    error_m: np.ndarray
    nearest_m: np.ndarray
    false_targets: np.ndarray
    targets: np.ndarray
    distance_m: float

    @property
    def detected(self) -> np.ndarray:
        """(B, K) bool: a target was matched to the true target."""
        return np.isfinite(self.error_m)


def score_frames(true_range_m, true_angle_deg, est_range_m, est_angle_deg,
                 distance_m: float = DETECTION_DISTANCE_M) -> FrameScores:
    """Match each frame's targets to its true targets one to one in the plane and score them.

    true_* : (B, K) ranges (m) and angles (deg) of the true targets; est_* : (B, L) of the
    targets reported (NaN: absent, as :class:`~pipeline.dsp.localize.Detections` of
    ``K auto`` holds them). Pairs are taken in order of their distance, each true target
    and each target once, only within ``distance_m`` (m)."""
    if not (isinstance(distance_m, (int, float)) and not isinstance(distance_m, bool)
            and np.isfinite(distance_m) and distance_m > 0):
        raise ParameterError(f"distance_m={distance_m!r} must be a finite number of metres > 0")
    tr, ta = np.atleast_2d(np.asarray(true_range_m, float)), np.atleast_2d(np.asarray(true_angle_deg, float))
    er, ea = np.atleast_2d(np.asarray(est_range_m, float)), np.atleast_2d(np.asarray(est_angle_deg, float))
    if tr.shape != ta.shape or er.shape != ea.shape or tr.ndim != 2 or er.ndim != 2 or tr.shape[0] != er.shape[0]:
        raise ParameterError(f"true targets {tr.shape} / {ta.shape} and estimates {er.shape} / {ea.shape} must be "
                             "(B, K) and (B, L) arrays of the same B")
    t = polar_to_plane(tr, np.deg2rad(ta))
    e = polar_to_plane(er, np.deg2rad(ea))
    present = np.isfinite(e)
    dist = np.abs(t[:, :, None] - e[:, None, :])  # (B, K, L)
    dist = np.where(present[:, None, :] & np.isfinite(dist), dist, np.inf)
    b, k, n_est = dist.shape
    nearest = dist.min(axis=2) if n_est else np.full((b, k), np.inf)
    error = np.full((b, k), np.nan)
    if n_est and k:
        left = np.where(dist <= distance_m, dist, np.inf)
        rows = np.arange(b)
        for _ in range(min(k, n_est)):  # the closest pair left in each frame, K times at most
            flat = left.reshape(b, -1).argmin(axis=1)
            ti, ei = np.divmod(flat, n_est)
            d = left[rows, ti, ei]
            hit = np.isfinite(d)
            if not hit.any():
                break
            h = rows[hit]
            error[h, ti[hit]] = d[hit]
            left[h, ti[hit], :] = np.inf  # that true target and that target are taken
            left[h, :, ei[hit]] = np.inf
    targets = present.sum(axis=1)
    return FrameScores(error, nearest, targets - np.isfinite(error).sum(axis=1), targets, float(distance_m))


@dataclass(frozen=True)
class Score:
    """The score of many frames (:func:`summarize`): per true target (K,) its
    ``detection_rate`` and the ``median_error_m`` of its detections (NaN: never
    detected); ``false_targets_per_frame``, ``targets_per_frame``; ``median_nearest_m``
    (the median over true targets and frames of the distance to the nearest target)."""

    distance_m: float
    frames: int
    detection_rate: np.ndarray
    median_error_m: np.ndarray
    false_targets_per_frame: float
    targets_per_frame: float
    median_nearest_m: float

    def to_dict(self, truth: list[dict] | None = None) -> dict:
        """JSON-ready (null for no figure): ``truth``, each true target's ``range_m`` and
        ``angle_deg``, names the rows of ``targets``."""
        def num(v, digits=4):
            return round(float(v), digits) if np.isfinite(v) else None

        rows = []
        for i in range(len(self.detection_rate)):
            row = {} if truth is None else {"range_m": truth[i]["range_m"], "angle_deg": truth[i]["angle_deg"]}
            rows.append({**row, "detection_rate": num(self.detection_rate[i]),
                         "median_error_m": num(self.median_error_m[i])})
        return {"distance_m": self.distance_m, "frames": self.frames, "targets": rows,
                "false_targets_per_frame": num(self.false_targets_per_frame),
                "targets_per_frame": num(self.targets_per_frame), "median_nearest_m": num(self.median_nearest_m)}


def summarize(scores: FrameScores) -> Score:
    """The :class:`Score` of every frame of ``scores``."""
    b, k = scores.error_m.shape
    with np.errstate(invalid="ignore"):
        rate = scores.detected.mean(axis=0) if b else np.full(k, np.nan)
    med = np.array([np.median(col[np.isfinite(col)]) if np.isfinite(col).any() else np.nan
                    for col in scores.error_m.T])
    near = scores.nearest_m[np.isfinite(scores.nearest_m)]
    return Score(scores.distance_m, b, rate, med,
                 float(scores.false_targets.mean()) if b else float("nan"),
                 float(scores.targets.mean()) if b else float("nan"),
                 float(np.median(near)) if near.size else float("nan"))


def score(true_range_m, true_angle_deg, est_range_m, est_angle_deg, distance_m: float = DETECTION_DISTANCE_M) -> Score:
    """:func:`score_frames` then :func:`summarize`: the score of a batch of frames."""
    return summarize(score_frames(true_range_m, true_angle_deg, est_range_m, est_angle_deg, distance_m))


def score_text(score: dict) -> str:
    """One line of a :meth:`Score.to_dict`: each true target's detection rate and median error,
    then false targets and targets a frame ("n/a" where there is no figure)."""
    def pct(v):
        return "n/a" if v is None else f"{100 * v:.1f} %"

    def num(v, unit=""):
        return "n/a" if v is None else f"{v:.3g}{unit}"

    rows = []
    for i, t in enumerate(score["targets"]):
        where = f" ({t['range_m']:.2f} m, {t['angle_deg']:+.1f}°)" if "range_m" in t else ""
        rows.append(f"target {i + 1}{where} found in {pct(t['detection_rate'])} of frames, median error "
                    f"{num(t['median_error_m'], ' m')}")
    return (f"within {score['distance_m']:g} m: " + "; ".join(rows) + f"; {num(score['false_targets_per_frame'])} "
            f"false targets a frame (near no true target), {num(score['targets_per_frame'])} targets a frame")
