"""What a recording's topics read as: arrays of one sensor's messages, batch first
(:class:`Frames`, :class:`Quantized`, :class:`Targets`, :class:`Tracks`), and the same as
tables, columns of equal length (:func:`joined`), what ``pandas.DataFrame`` takes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.dsp.quantize import QuantizedFrames
from pipeline.wire import HEALTH_LOSS_FIELDS, TARGET_FIELDS, TRACK_FIELDS, HealthMsg

#: the topics :func:`joined` makes a table of
TABLE_TOPICS = ("raw", "quantized", "targets", "tracks", "health")
#: the columns of text (object arrays)
TEXT_COLUMNS = ("sensor_id", "node", "algo")


@dataclass(frozen=True)
class _Messages:
    """Messages of one sensor in sequence order: ``seq`` (F,) uint64, ``timestamp_ns`` (F,)
    int64 (the sensor's clock), ``t_s`` (F,) float64 (when the recorder logged each, s from
    the recording's start: the clock ``open_recording``'s ``start`` / ``end`` select on)."""

    sensor_id: str
    seq: np.ndarray
    timestamp_ns: np.ndarray
    t_s: np.ndarray

    def __len__(self) -> int:
        return len(self.seq)


@dataclass(frozen=True)
class _Stream(_Messages):
    """Frames of one sensor (:class:`_Messages`), made with the radar configuration ``config_id``."""

    config_id: int


@dataclass(frozen=True)
class Frames(_Stream):
    """Full-resolution frames of one sensor: ``data`` (F, M, 2) complex64 (measurement,
    antenna; full-scale units)."""

    data: np.ndarray


@dataclass(frozen=True)
class Quantized(_Stream):
    """Quantized frames of one sensor as the stream carried them: ``frames``, the codes
    (F, M, 2, 2) and each frame's delta, alpha and dither seed
    (:class:`pipeline.dsp.quantize.QuantizedFrames`)."""

    frames: QuantizedFrames


@dataclass(frozen=True)
class Targets(_Messages):
    """Targets of one sensor per frame (:class:`_Messages`), padded with NaN to the most
    targets of a frame: ``range_m``, ``angle_deg``, ``x_m``, ``y_m``, ``amplitude`` (F, K)
    float; ``count`` (F,) targets in each frame; ``published_ns`` (F,) int64 (the localizer's
    clock: latency = published - timestamp); ``algo`` the decoder that found them."""

    published_ns: np.ndarray
    count: np.ndarray
    range_m: np.ndarray
    angle_deg: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    amplitude: np.ndarray
    algo: str = ""


@dataclass(frozen=True)
class Tracks(_Messages):
    """The confirmed tracks of one sensor (``--track``), one row per track per tracks
    message; a track is the rows of one ``track_id``. Per row (N,): ``frame`` (the index of
    its message in the per-message arrays), ``track_id`` and ``hits`` int64, ``range_m``,
    ``angle_deg``, ``x_m``, ``y_m``, ``vx_mps``, ``vy_mps``, ``sigma_m``, ``age_s`` float,
    ``static`` bool, ``radial_velocity_mps`` float (the Doppler's, ambiguity resolved; NaN
    while unresolved, without Doppler, or in older recordings). Per message (F,), in sequence
    order (:class:`_Messages`), and ``published_ns``, ``count`` (its tracks)."""

    published_ns: np.ndarray
    count: np.ndarray
    frame: np.ndarray
    track_id: np.ndarray
    range_m: np.ndarray
    angle_deg: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    vx_mps: np.ndarray
    vy_mps: np.ndarray
    sigma_m: np.ndarray
    age_s: np.ndarray
    hits: np.ndarray
    static: np.ndarray
    radial_velocity_mps: np.ndarray


def frames_table(frames: Frames | Quantized) -> dict[str, np.ndarray]:
    """A row per frame: ``sensor_id``, ``seq``, ``timestamp_ns``, ``t_s``, ``config_id``,
    then ``M`` (raw) or ``bits``, ``alpha``, ``delta``, ``dither_seed`` (quantized)."""
    n = len(frames)
    head = {"sensor_id": np.full(n, frames.sensor_id, dtype=object), "seq": frames.seq,
            "timestamp_ns": frames.timestamp_ns, "t_s": frames.t_s, "config_id": np.full(n, frames.config_id)}
    if isinstance(frames, Frames):
        return head | {"M": np.full(n, frames.data.shape[1])}
    q = frames.frames
    return head | {"bits": np.full(n, q.bits), "alpha": np.broadcast_to(q.alpha, (n,)).astype(float),
                   "delta": q.delta, "dither_seed": np.broadcast_to(np.asarray(q.dither_seed, np.uint64), (n,)).copy()}


def targets_table(t: Targets) -> dict[str, np.ndarray]:
    """A row per target: ``sensor_id``, ``seq``, ``timestamp_ns``, ``t_s``, ``published_ns``,
    ``algo``, ``target`` (its rank in its frame, strongest 0) and the target's fields."""
    f, k = np.nonzero(np.arange(t.range_m.shape[1])[None, :] < t.count[:, None])
    return {"sensor_id": np.full(len(f), t.sensor_id, dtype=object), "seq": t.seq[f],
            "timestamp_ns": t.timestamp_ns[f], "t_s": t.t_s[f], "published_ns": t.published_ns[f],
            "algo": np.full(len(f), t.algo, dtype=object), "target": k,
            **{name: getattr(t, name)[f, k] for name in TARGET_FIELDS}}


def tracks_table(tr: Tracks) -> dict[str, np.ndarray]:
    """A row per track and message: ``sensor_id``, ``seq``, ``timestamp_ns``, ``t_s``,
    ``published_ns`` and the track's fields."""
    f = tr.frame
    return {"sensor_id": np.full(len(f), tr.sensor_id, dtype=object), "seq": tr.seq[f],
            "timestamp_ns": tr.timestamp_ns[f], "t_s": tr.t_s[f], "published_ns": tr.published_ns[f],
            **{name: getattr(tr, name) for name in TRACK_FIELDS}}


def health_table(health: list[HealthMsg], t_s: np.ndarray) -> dict[str, np.ndarray]:
    """A row per health message (logged at ``t_s``): ``sensor_id``, ``node``, ``timestamp_ns``,
    ``t_s``, the counters, ``latency_p50_ms`` and ``latency_p99_ms`` (NaN: none)."""
    cols: dict[str, list] = {"sensor_id": [h.sensor_id for h in health], "node": [h.node for h in health],
                             "timestamp_ns": [h.timestamp_ns for h in health], "t_s": list(t_s)}
    for name in ("frames_in", "frames_out", "drops", "decode_errors", *HEALTH_LOSS_FIELDS, "bytes_in_per_s",
                 "bytes_out_per_s"):
        cols[name] = [getattr(h, name) for h in health]
    for q in ("p50", "p99"):
        cols[f"latency_{q}_ms"] = [np.nan if h.latency_ms.get(q) is None else h.latency_ms[q] for h in health]
    return columns(cols)


def empty_table(topic: str) -> dict[str, np.ndarray]:
    """The columns of a table of ``topic`` without rows."""
    head = ["sensor_id", "seq", "timestamp_ns", "t_s"]
    more = {"raw": ["config_id", "M"], "quantized": ["config_id", "bits", "alpha", "delta", "dither_seed"],
            "targets": ["published_ns", "algo", "target", *TARGET_FIELDS],
            "tracks": ["published_ns", *TRACK_FIELDS]}[topic]
    return columns({name: [] for name in head + more})


def joined(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Tables of the same columns as one, rows in ``t_s`` order (stable)."""
    out = columns({k: np.concatenate([p[k] for p in parts]) for k in parts[0]})
    idx = np.argsort(out["t_s"], kind="stable")
    return {k: v[idx] for k, v in out.items()}


def columns(cols: dict) -> dict[str, np.ndarray]:
    """Columns as arrays (text as object arrays)."""
    return {k: np.asarray(v, dtype=object) if k in TEXT_COLUMNS else np.asarray(v) for k, v in cols.items()}
