"""Foxglove's view of qradar's messages, made from the one definition of their fields
(:mod:`pipeline.wire.fields`): a targets message as the points of a ``foxglove.PointCloud``
(:func:`target_points`: every number of a target a float32 field), in its JSON flavour for
recordings (:func:`pointcloud_json`; :mod:`qradar.view` packs the same points into the
protobuf one); a tracks message, and targets that carry their uncertainty, as the
ellipses of a ``foxglove.SceneUpdate`` (JSON, :func:`scene_json`); a range profile as the
JSON of :data:`~pipeline.wire.fields.PROFILE` (:func:`profile_json`).

The JSON Schemas written into recordings for these channels are here too (code, not a
file beside the package: a recording's bytes do not depend on how qradar was installed).
Foxglove recognizes ``foxglove.PointCloud`` and ``foxglove.SceneUpdate`` by their names;
tests/js/mcap_check.mjs checks what is written against Foxglove's own schemas
(``@foxglove/schemas``)."""

from __future__ import annotations

import base64
import json
import math

import numpy as np

from pipeline.dsp.ellipse import ellipses, polar_covariance_to_xy
from pipeline.wire.fields import PROFILE, TARGETS, Format, point_fields
from pipeline.wire.messages import TargetsMsg, TracksMsg, write_value
from radar_driver.model import polar_to_xy

#: a target's uncertainty, when its message carries it: σ of the range (m), of the angle
#: (deg) and the range–angle covariance (m·deg); absent fields count as 0 (their fields join
#: pipeline.wire.fields.TARGET_ITEM, optional, when the localizer writes them)
TARGET_SIGMA_FIELDS = ("sigma_range_m", "sigma_angle_deg", "cov_range_angle")
#: the float32 fields of a target's point, in order (4 bytes each)
POINT_FIELDS = point_fields(TARGETS)
FLOAT32 = 7  # foxglove.NumericType.FLOAT32
#: how long an entity of a scene stays without a newer message, ns
ENTITY_LIFETIME_NS = 500_000_000
#: colours (RGBA, 0..1): a static track, a moving one, a target's ellipse
STATIC_COLOR = (0.2, 0.8, 0.3, 0.9)
MOVING_COLOR = (1.0, 0.55, 0.1, 0.9)
TARGET_COLOR = (0.3, 0.6, 1.0, 0.5)
#: the smallest diameter of an ellipse drawn, m
MIN_SIZE_M = 0.2


def point_dtype(fmt: Format = TARGETS) -> np.dtype:
    """The packed point of a target: a little-endian float32 per field of :func:`point_fields`."""
    return np.dtype([(f, "<f4") for f in point_fields(fmt)])


def target_points(msg: TargetsMsg, fmt: Format = TARGETS) -> np.ndarray:
    """The targets as packed points, (K,) of :func:`point_dtype`: x, y (m) by
    :func:`~radar_driver.model.polar_to_xy` of range_m and angle_deg, z = 0, then each
    number of a target (NaN where an optional one is absent)."""
    dtype = point_dtype(fmt)
    pts = np.zeros(len(msg.targets), dtype=dtype)
    if not msg.targets:
        return pts
    for name in dtype.names[3:]:
        pts[name] = [t.get(name, np.nan) for t in msg.targets]
    pts["x"], pts["y"] = polar_to_xy(np.array([t["range_m"] for t in msg.targets]),
                                     np.radians([t["angle_deg"] for t in msg.targets]))
    return pts


def _stamp(ns: int) -> dict:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


_POSE = {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}


def pointcloud_json(msg: TargetsMsg, frame_id: str = "radar", fmt: Format = TARGETS) -> bytes:
    """``foxglove.PointCloud`` (JSON) of one targets message: the points of :func:`target_points`."""
    pts = target_points(msg, fmt)
    obj = {"timestamp": _stamp(msg.timestamp_ns), "frame_id": frame_id, "pose": _POSE,
           "point_stride": pts.dtype.itemsize,
           "fields": [{"name": f, "offset": pts.dtype.fields[f][1], "type": FLOAT32} for f in pts.dtype.names],
           "data": base64.b64encode(pts.tobytes()).decode("ascii")}
    return json.dumps(obj, separators=(",", ":")).encode()


def _color(rgba) -> dict:
    return dict(zip("rgba", rgba))


def _entity(stamp: dict, frame_id: str, ident: str, x: float, y: float, ellipse, color, label: str) -> dict:
    """A scene entity: a flat cylinder over the 1-σ ellipse ``[a, b, phi]`` at (x, y), and a label."""
    a, b = (max(2.0 * float(v), MIN_SIZE_M) for v in ellipse[:2])
    phi = float(ellipse[2])
    turn = {"x": 0.0, "y": 0.0, "z": math.sin(phi / 2.0), "w": math.cos(phi / 2.0)}
    return {"timestamp": stamp, "frame_id": frame_id, "id": ident,
            "lifetime": {"sec": 0, "nsec": ENTITY_LIFETIME_NS}, "frame_locked": True, "metadata": [],
            "arrows": [], "cubes": [], "spheres": [], "lines": [], "triangles": [], "models": [],
            "cylinders": [{"pose": {"position": {"x": x, "y": y, "z": 0.0}, "orientation": turn},
                           "size": {"x": a, "y": b, "z": 0.02}, "bottom_scale": 1.0, "top_scale": 1.0,
                           "color": _color(color)}],
            "texts": [{"pose": {"position": {"x": x, "y": y, "z": 0.5}, "orientation": _POSE["orientation"]},
                       "billboard": True, "font_size": 14.0, "scale_invariant": True,
                       "color": _color((1.0, 1.0, 1.0, 1.0)), "text": label}]}


def track_label(track: dict) -> str:
    """``#3 1.52 m/s σ 0.041 m`` (``static`` instead of the speed while static), and the
    Doppler's radial velocity once resolved: ``#3 1.52 m/s radial +1.498 m/s σ 0.041 m``."""
    speed = "static" if track["static"] else f"{math.hypot(track['vx_mps'], track['vy_mps']):.2f} m/s"
    vr = track.get("radial_velocity_mps")
    radial = "" if vr is None else f" radial {vr:+.3f} m/s"
    return f"#{track['track_id']} {speed}{radial} σ {track['sigma_m']:.3f} m"


def target_ellipses(msg: TargetsMsg) -> np.ndarray | None:
    """(K, 3) 1-σ ellipses of the targets in the sensor's frame, or None when no target
    carries its uncertainty (TARGET_SIGMA_FIELDS; absent ones count as 0)."""
    if not msg.targets or not any(f in t for t in msg.targets for f in TARGET_SIGMA_FIELDS):
        return None
    rng = np.array([t["range_m"] for t in msg.targets])
    ang = np.array([t["angle_deg"] for t in msg.targets])
    sig = np.array([[t.get(f, 0.0) for f in TARGET_SIGMA_FIELDS] for t in msg.targets], dtype=float)
    return ellipses(polar_covariance_to_xy(rng, ang, *sig.T))


def scene_json(tracks: TracksMsg | None = None, targets: TargetsMsg | None = None, frame_id: str = "radar") -> bytes:
    """``foxglove.SceneUpdate`` (JSON): each track an entity ``track-<id>`` (its 1-σ circle,
    radius ``sigma_m``, green while static, orange while moving, and a label), and each
    target that carries its uncertainty an entity ``target-<i>`` (its 1-σ ellipse)."""
    entities = []
    if tracks is not None:
        stamp = _stamp(tracks.timestamp_ns)
        for t in tracks.tracks:
            entities.append(_entity(stamp, frame_id, f"track-{t['track_id']}", t["x_m"], t["y_m"],
                                    (t["sigma_m"], t["sigma_m"], 0.0),
                                    STATIC_COLOR if t["static"] else MOVING_COLOR, track_label(t)))
    ell = None if targets is None else target_ellipses(targets)
    if ell is not None:
        stamp = _stamp(targets.timestamp_ns)
        for i, (t, e) in enumerate(zip(targets.targets, ell)):
            entities.append(_entity(stamp, frame_id, f"target-{i}", t["x_m"], t["y_m"], e, TARGET_COLOR,
                                    f"{t['range_m']:.2f} m {t['angle_deg']:.1f}°"))
    return json.dumps({"deletions": [], "entities": entities}, separators=(",", ":"), ensure_ascii=False).encode()


def profile_json(values: dict, fmt: Format = PROFILE, digits: int = 1) -> bytes:
    """A range profile's JSON (the fields of ``fmt`` in order, from ``values``: the
    top-level fields by name, arrays of numbers rounded to ``digits`` decimals)."""
    parts = ['"version":1,"type":%s' % json.dumps(fmt.type)]
    for f in fmt.fields[2:]:
        v = values[f.name]
        if f.type == "array":
            text = json.dumps(np.round(np.asarray(v, dtype=float), digits).tolist(), separators=(",", ":"))
        elif f.type == "number":
            text = repr(float(v))
        else:
            text = write_value(v, f)
        parts.append(f'"{f.name}":{text}')
    return ("{" + ",".join(parts) + "}").encode()


# -- the JSON Schemas of these channels (subsets of Foxglove's, with what qradar writes) ----------
_XYZ = {"type": "object", "properties": {a: {"type": "number"} for a in "xyz"}}
_QUAT = {"type": "object", "properties": {a: {"type": "number"} for a in "xyzw"}}
_TIME = {"type": "object", "properties": {"sec": {"type": "integer", "minimum": 0},
                                          "nsec": {"type": "integer", "minimum": 0}}}
_POSE_SCHEMA = {"type": "object", "properties": {"position": _XYZ, "orientation": _QUAT}}
_RGBA = {"type": "object", "properties": {a: {"type": "number"} for a in "rgba"}}

# foxglove.PointCloud, JSON flavour (https://docs.foxglove.dev/docs/visualization/message-schemas/point-cloud)
POINTCLOUD_SCHEMA = {
    "title": "foxglove.PointCloud", "type": "object",
    "properties": {
        "timestamp": _TIME, "frame_id": {"type": "string"}, "pose": _POSE_SCHEMA,
        "point_stride": {"type": "integer", "minimum": 0},
        "fields": {"type": "array", "items": {"type": "object", "properties": {
            "name": {"type": "string"}, "offset": {"type": "integer", "minimum": 0},
            "type": {"type": "integer", "description": "foxglove.NumericType; 7 = FLOAT32"}}}},
        "data": {"type": "string", "contentEncoding": "base64"},
    },
}
# foxglove.SceneUpdate, JSON flavour, with the primitives qradar draws (cylinders, texts)
SCENE_UPDATE_SCHEMA = {
    "title": "foxglove.SceneUpdate", "type": "object",
    "properties": {
        "deletions": {"type": "array", "items": {"type": "object"}},
        "entities": {"type": "array", "items": {"type": "object", "properties": {
            "timestamp": _TIME, "frame_id": {"type": "string"}, "id": {"type": "string"},
            "lifetime": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
            "frame_locked": {"type": "boolean"}, "metadata": {"type": "array"},
            **{k: {"type": "array"} for k in ("arrows", "cubes", "spheres", "lines", "triangles", "models")},
            "cylinders": {"type": "array", "items": {"type": "object", "properties": {
                "pose": _POSE_SCHEMA, "size": _XYZ, "bottom_scale": {"type": "number"},
                "top_scale": {"type": "number"}, "color": _RGBA}}},
            "texts": {"type": "array", "items": {"type": "object", "properties": {
                "pose": _POSE_SCHEMA, "billboard": {"type": "boolean"}, "font_size": {"type": "number"},
                "scale_invariant": {"type": "boolean"}, "color": _RGBA, "text": {"type": "string"}}}}}}},
    },
}
