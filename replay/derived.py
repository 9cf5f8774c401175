"""The channels a recording derives from a sensor's messages, so that Foxglove shows a
recording on its own (docs/recording.md, "What Foxglove shows"): beside each admitted
message of ``<prefix>/<sensor>/<topic>``,

- a targets message: ``<prefix>/<sensor>/pointcloud`` (``foxglove.PointCloud``, JSON), and
  ``<prefix>/<sensor>/scene`` when its targets carry their uncertainty;
- a tracks message: ``<prefix>/<sensor>/scene`` (``foxglove.SceneUpdate``, JSON: each
  track's 1-σ circle and label);
- a quantized frame, at most ``profile_rate_hz`` a second per sensor (sensor time) and
  ``profile_budget_hz`` a second in all (wall time: a crowd of sensors, or of forged ids,
  each sending one 320-byte frame, must not make the file grow by a 3-KB profile each):
  ``<prefix>/<sensor>/profile`` (``qradar.RangeProfile``: |Φ*Z/M| per receiver and joint,
  dB of full scale, 0.1 dB steps, reduced to ``profile_bins`` values by the largest of each
  group of adjacent range bins).

Why here, in the recorder, and not in the localizer: the recorder decodes every quantized
frame it admits already (the typed batch is in hand), so a profile costs one back
projection of one frame per sensor and period and nothing on the localizer's path, whose
latency is the stream's; the profile is of the very codes the file holds (a reader can
recompute it); and it is the live views' profile (:mod:`pipeline.dsp.profile`, one
function). Nothing here does I/O."""

from __future__ import annotations

import time
from dataclasses import dataclass

from pipeline.dsp.profile import profile_db, profile_magnitude, profile_ranges
from pipeline.errors import ParameterError
from pipeline.wire import QuantizedGroup, TargetsMsg, TracksMsg
from pipeline.wire.foxglove import pointcloud_json, profile_json, scene_json, target_ellipses
from radar_driver.model import RadarConfig

from .admission import Admitted


@dataclass(frozen=True)
class DerivedConfig:
    """``profile_rate_hz``: range profiles a second per sensor at most (sensor time; 0:
    none); ``profile_budget_hz``: range profiles a second over all sensors at most (wall
    time, a burst of one second's); ``profile_bins``: values per profile (a divisor of the
    radar's N; None: N)."""

    profile_rate_hz: float = 2.0
    profile_budget_hz: float = 64.0
    profile_bins: int | None = 128

    def __post_init__(self) -> None:
        for name in ("profile_rate_hz", "profile_budget_hz"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and v >= 0):
                raise ParameterError(f"{name}={v!r} must be a number >= 0")


def profile_values(group: QuantizedGroup, row: int, radar: RadarConfig, bins: int | None) -> dict:
    """The fields of a range profile (pipeline.wire.fields.PROFILE) of frame ``row`` of a
    decoded quantized group."""
    h, q = group.headers, group.frames
    frames = q.take([row])
    db = profile_db(profile_magnitude(frames.values(), radar), bins)[0]  # (bins, 3)
    alpha = q.alpha[row] if getattr(q.alpha, "ndim", 0) else q.alpha
    return {"sensor_id": h.sensor_id[row], "seq": int(h.seq[row]), "timestamp_ns": int(h.timestamp_ns[row]),
            "config_id": int(h.config_id[row]), "bits": int(q.bits), "alpha": float(alpha),
            "delta": float(q.delta[row]), "range_m": profile_ranges(radar, bins).round(4),
            "profile_db": db[:, 0], "antenna1_db": db[:, 1], "antenna2_db": db[:, 2]}


class Derivations:
    """What to write beside each admitted message (:meth:`of`), with the per-sensor state
    of the profiles' rate (:meth:`forget` a sensor when it expires). Not locked: one worker."""

    def __init__(self, configs: dict[int, RadarConfig], config: DerivedConfig = DerivedConfig(),
                 clock=time.monotonic):
        self.configs = configs
        self.config = config
        self._period_ns = int(1e9 / config.profile_rate_hz) if config.profile_rate_hz > 0 else None
        self._last_profile: dict[str, int] = {}  # sensor -> the sensor time of its last profile, ns
        self._clock = clock
        self._tokens, self._filled = config.profile_budget_hz, clock()  # the budget's bucket
        self.profiles_skipped = 0  # due by the sensor's rate, skipped by the budget

    def _take_token(self) -> bool:
        """One profile of the budget (a bucket of profile_budget_hz tokens, refilled at that rate)."""
        now, budget = self._clock(), self.config.profile_budget_hz
        self._tokens = min(budget, self._tokens + (now - self._filled) * budget)
        self._filled = now
        if self._tokens < 1.0:
            return False
        self._tokens -= 1.0
        return True

    def forget(self, sensor_id: str) -> None:
        self._last_profile.pop(sensor_id, None)

    def of(self, key: str, admitted: Admitted) -> list[tuple[str, bytes]]:
        """(key, payload) of the derived messages of the message admitted on ``key``."""
        base = key.rsplit("/", 1)[0]
        msg = admitted.message
        if isinstance(msg, TargetsMsg):
            out = [(base + "/pointcloud", pointcloud_json(msg))]
            if target_ellipses(msg) is not None:
                out.append((base + "/scene", scene_json(targets=msg)))
            return out
        if isinstance(msg, TracksMsg):
            return [(base + "/scene", scene_json(tracks=msg))]
        if admitted.frames is not None and self._period_ns is not None:
            return self._profile(base, admitted.frames, admitted.row)
        return []

    def _profile(self, base: str, group: QuantizedGroup, row: int) -> list[tuple[str, bytes]]:
        sensor, ts = group.headers.sensor_id[row], int(group.headers.timestamp_ns[row])
        last = self._last_profile.get(sensor)
        if last is not None and 0 <= ts - last < self._period_ns:
            return []
        radar = self.configs.get(int(group.headers.config_id[row]))
        if radar is None:  # (admitted frames have an announced config)
            return []
        if not self._take_token():
            self.profiles_skipped += 1
            return []
        self._last_profile[sensor] = ts
        return [(base + "/profile", profile_json(profile_values(group, row, radar, self.config.profile_bins)))]
