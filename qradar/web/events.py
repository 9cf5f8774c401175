"""The web page's events: what the view sends the page for each message of the stream, as
JSON-ready dicts, and the maths behind them (pure numpy, a batch of targets first).

Positions are in the world frame (each sensor at its pose, :func:`qradar.liveview.to_world`),
m, rounded to 1 mm; a 1-σ uncertainty ellipse is ``[a_m, b_m, phi_rad]``: semi-axes a >= b
and the angle of a from the world's x axis, counter-clockwise. The formats are written down
in docs/stream.md (section "Live view in the browser")."""

from __future__ import annotations

import math

import numpy as np

from pipeline.dsp.ellipse import ellipses, polar_covariance_to_xy, rotate_covariance  # noqa: F401 (the page's maths)
from pipeline.wire import HealthMsg, TargetsMsg, TracksMsg
from pipeline.wire.foxglove import TARGET_SIGMA_FIELDS
from radar_driver.model import RadarConfig, polar_to_xy

from ..liveview import to_db, to_world

#: a target's fields as the page names them, with the digits kept (negative: significant digits); a field
#: of the definition (pipeline.wire.fields.TARGET_ITEM) not named here goes to the page under its own name,
#: 4 significant digits; None: not sent (the position goes as the world's x, y)
PAGE_FIELDS = {"range_m": ("r", 3), "angle_deg": ("a", 2), "amplitude": ("amp", -4), "statistic_db": ("stat", 1),
               "x_m": (None, 0), "y_m": (None, 0)}
#: digits kept: positions (m) and profile values (dB)
XY_DIGITS = 3
DB_DIGITS = 1


def _round(values: np.ndarray, digits: int) -> list:
    return np.round(values, digits).tolist()


def target_sigmas(msg: TargetsMsg, raw: list | None = None) -> np.ndarray | None:
    """(K, 3) of the targets' TARGET_SIGMA_FIELDS (absent: 0), or None when no target has
    any. ``raw``: the message's targets as its JSON holds them, for fields the wire decoder
    does not keep."""
    rows = raw if raw is not None and len(raw) == len(msg.targets) else msg.targets
    if not any(isinstance(t, dict) and any(f in t for f in TARGET_SIGMA_FIELDS) for t in rows):
        return None
    out = np.zeros((len(rows), len(TARGET_SIGMA_FIELDS)))
    for i, t in enumerate(rows):
        for j, f in enumerate(TARGET_SIGMA_FIELDS):
            v = t.get(f, 0.0) if isinstance(t, dict) else 0.0
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                return None  # not a number: no ellipse rather than a wrong one
            out[i, j] = v
    if np.any(out[:, :2] < 0):
        return None
    return out


def targets_event(msg: TargetsMsg, pose: tuple[float, float, float] | None, truth: list[dict] | None = None,
                  raw: list | None = None) -> dict:
    """One targets message for the page: per target its world x, y (m), range (m), angle
    (deg), amplitude, statistic (dB, when given), any other field of the definition it
    carries (PAGE_FIELDS) and 1-σ ellipse (when the message carries the targets' σ);
    ``truth``: the true targets (range_m, angle_deg) as world [x, y] pairs."""
    k = len(msg.targets)
    rng = np.array([t["range_m"] for t in msg.targets], dtype=float)
    ang = np.array([t["angle_deg"] for t in msg.targets], dtype=float)
    x, y = to_world(*polar_to_xy(rng, np.radians(ang)), pose)
    sig = target_sigmas(msg, raw) if k else None
    ell = None
    if sig is not None:
        cov = rotate_covariance(polar_covariance_to_xy(rng, ang, *sig.T), pose[2] if pose else 0.0)
        ell = _round(ellipses(cov), 4)
    xs, ys = _round(x, XY_DIGITS), _round(y, XY_DIGITS)
    targets = []
    for i, t in enumerate(msg.targets):
        item = {"x": xs[i], "y": ys[i]}
        for name, value in t.items():  # the fields the wire decoder kept (pipeline.wire.fields), each once
            key, digits = PAGE_FIELDS.get(name, (name, -4))
            if key is not None:
                item[key] = round(value, digits) if digits >= 0 else float(f"{value:.{-digits}g}")
        if ell is not None:
            item["ell"] = ell[i]
        targets.append(item)
    event = {"s": msg.sensor_id, "seq": msg.seq, "t": msg.timestamp_ns, "targets": targets}
    if truth is not None:
        tr = np.array([t["range_m"] for t in truth], dtype=float)
        ta = np.radians([t["angle_deg"] for t in truth])
        tx, ty = to_world(*polar_to_xy(tr, ta), pose)
        event["truth"] = [[a, b] for a, b in zip(_round(tx, XY_DIGITS), _round(ty, XY_DIGITS))]
    return event


def tracks_event(msg: TracksMsg, pose: tuple[float, float, float] | None) -> dict:
    """One tracks message for the page: per track its id, world x, y (m), velocity (m/s,
    world), σ (m: a circle), hits, age (s), whether it is static, and ``vr``, the Doppler's
    radial velocity (m/s, + = away) once its ambiguity is resolved."""
    n = len(msg.tracks)
    x, y = to_world(np.array([t["x_m"] for t in msg.tracks], dtype=float),
                    np.array([t["y_m"] for t in msg.tracks], dtype=float), pose)
    vx, vy = to_world(np.array([t["vx_mps"] for t in msg.tracks], dtype=float),
                      np.array([t["vy_mps"] for t in msg.tracks], dtype=float),
                      None if pose is None else (0.0, 0.0, pose[2]))  # a velocity turns, it does not move
    cols = [_round(c, XY_DIGITS) for c in (x, y, vx, vy)]
    tracks = [{"id": t["track_id"], "x": cols[0][i], "y": cols[1][i], "vx": cols[2][i], "vy": cols[3][i],
               "sigma": round(t["sigma_m"], 4), "hits": t["hits"], "age": round(t["age_s"], 2),
               "static": t["static"], **({"vr": round(t["radial_velocity_mps"], 4)}
                                         if "radial_velocity_mps" in t else {})}
              for i, t in enumerate(msg.tracks)] if n else []
    return {"s": msg.sensor_id, "seq": msg.seq, "t": msg.timestamp_ns, "tracks": tracks}


def profile_event(sensor: str, seq: int, timestamp_ns: int, magnitude: np.ndarray, radar: RadarConfig) -> dict:
    """One range profile for the page: |U| (N, 2) of :func:`qradar.liveview.profile_magnitude`
    as dB of full scale per receiver (``rx1``, ``rx2``, 0.1 dB steps) over the range bins
    ``r0 + n·dr`` (m)."""
    db = np.round(to_db(magnitude), DB_DIGITS)
    grid = radar.range_grid_m()
    return {"s": sensor, "seq": seq, "t": timestamp_ns, "r0": float(grid[0]),
            "dr": round(float(grid[1] - grid[0]), 6), "rx1": db[:, 0].tolist(), "rx2": db[:, 1].tolist()}


def health_event(sensor: str, msg: HealthMsg) -> dict:
    """One node's health for the page: its counters as on the wire (docs/wire-formats.md),
    ``extra`` included (e.g. a calibration state)."""
    from dataclasses import asdict

    out = asdict(msg)
    out["s"], out["t"] = sensor, out.pop("timestamp_ns")
    out.pop("sensor_id")
    return out
