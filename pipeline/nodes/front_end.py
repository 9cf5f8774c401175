"""What a node knows of its sensors' front ends: the localizer looks, in a sample of each
sensor's frames, for a return in the first range bins (DC, TX-to-RX leakage) within 10 dB of
the frame's strongest (:func:`pipeline.dsp.localize.leakage_return`), and publishes the counts
in the sensor's health (``front_end``: ``checked``, ``leakage``). In most frames: the sensor's frames are
not calibrated, or by a calibration of another front end (docs/chamber.md, section 7)."""

from __future__ import annotations

import math
import threading

import numpy as np

from radar_driver.model import RadarConfig

from pipeline.dsp.gate import LEAKAGE_BINS
from pipeline.dsp.localize import LEAKAGE_POWER_SHARE, leakage_return
from pipeline.dsp.quantize import QuantizedFrames

#: each sensor's first FRONT_END_FIRST frames are checked, then one of every FRONT_END_EVERY
#: (a back projection each: negligible beside a decoder)
FRONT_END_FIRST = 20
FRONT_END_EVERY = 20


#: a sensor's front end shows (a warning) once this many of its frames were checked and more
#: than LEAKAGE_SHARE of them had a return in the first range bins within 10 dB of their strongest
#: (:func:`~pipeline.dsp.localize.leakage_return`)
LEAKAGE_MIN_CHECKED = 10
LEAKAGE_SHARE = 0.5
#: how far below a frame's strongest return a leakage is seen (dB), as the warning says it
LEAKAGE_DB = round(-10.0 * math.log10(LEAKAGE_POWER_SHARE), 1)
#: where a warning about the front end sends the user
CALIBRATE_HINT = "`qradar calibrate` (docs/chamber.md, section 7)"


def leakage_shown(front: dict) -> bool:
    """Whether a sensor's front-end state (``checked``, ``leakage`` frames) shows its front end."""
    return front.get("checked", 0) >= LEAKAGE_MIN_CHECKED and front.get("leakage", 0) > LEAKAGE_SHARE * front["checked"]


def front_end_warning(sensor_id: str, front: dict, radar: RadarConfig | None = None) -> str:
    """The one warning of a sensor whose frames show its front end (:func:`leakage_shown`)."""
    near = LEAKAGE_BINS * (radar or RadarConfig()).range_resolution_m
    seen = (f"a return within the first {near:g} m (DC offset, TX-to-RX leakage), {LEAKAGE_DB:g} dB or less below "
            f"its strongest, in {100 * front['leakage'] / front['checked']:.1f} % of {front['checked']} frames checked")
    if front.get("calibrated"):
        return (f"{sensor_id}: calibrated with {front['calibrated']}, yet {seen}: the calibration does not fit this "
                f"sensor's front end (made on another sensor, radome or configuration?); make its own with "
                f"{CALIBRATE_HINT}")
    return (f"{sensor_id}: uncalibrated: {seen}; targets at the range gate's ends are that leakage and angles "
            f"carry the receivers' mismatch: run {CALIBRATE_HINT} and give --calibration")


class FrontEndCheck:
    """Per sensor: frames seen, frames checked, frames with a return in the first (or last)
    range bins within 10 dB of their strongest. Thread-safe; bounded by the caller's :meth:`forget`."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._state: dict[str, list[int]] = {}  # sensor -> [seen, checked, leakage]

    def check(self, radar: RadarConfig, sensors: list[str], frames, known=lambda sid: True) -> None:
        """Check the frames (B, M, 2) values or :class:`QuantizedFrames` of ``sensors``
        that are due; ``known(sensor)``: False for a sensor whose state is not to be kept."""
        due = []
        with self._lock:
            for i, sid in enumerate(sensors):
                st = self._state.get(sid)
                if st is None:
                    if not known(sid):
                        continue
                    st = self._state[sid] = [0, 0, 0]
                if st[0] < FRONT_END_FIRST or st[0] % FRONT_END_EVERY == 0:
                    due.append(i)
                st[0] += 1
        if not due or radar.n_measurements % radar.samples_per_ramp:
            return
        idx = np.array(due)
        sign_codes: bool | np.ndarray = False  # 1-bit codes without a dither: their quantizer's harmonic
        if isinstance(frames, QuantizedFrames):
            sub = frames.take(idx)
            values, sign_codes = sub.values(), (sub.bits == 1) & (np.asarray(sub.alpha) == 0.0)
        else:
            values = np.asarray(frames)[idx]
        seen = leakage_return(values, radar, sign_codes=sign_codes).tolist()
        with self._lock:
            for i, hit in zip(due, seen):
                st = self._state.get(sensors[i])
                if st is not None:
                    st[1] += 1
                    st[2] += hit

    def health(self, sensor_id: str) -> dict:
        """``{"front_end": {"checked": n, "leakage": m}}`` once the sensor was seen, else {}."""
        with self._lock:
            st = self._state.get(sensor_id)
            return {} if st is None else {"front_end": {"checked": st[1], "leakage": st[2]}}

    def forget(self, sensor_id: str) -> None:
        with self._lock:
            self._state.pop(sensor_id, None)
