"""Front-end calibration: what two short recordings show about a sensor, and its removal.

A real FMCW front end adds to the targets' signal, before the ADC (the order the
simulated sensor follows, ``radar_driver``'s ``[frontend]``): a gain and phase of receiver
2 relative to receiver 1; an I/Q imbalance (the Q path's gain and phase relative to the I
path, the same on both receivers), which puts a mirror of each target at the other end
of the range axis; a TX-to-RX leakage (a return at a few tens of centimetres, through the
same chain); a DC offset per receiver. The calibration estimates, per sensor and radar
configuration:

- the **background** ``b`` (M, 2): the mean frame of the empty scene, which holds the DC,
  the leakage and the static clutter together (all three are the same in every frame);
- the **I/Q imbalance** as the real-linear map it is, ``Q' = alpha I + beta Q`` with
  ``I' = I`` (the simulated front end's ``Q' = g (Q cos(phi) - I sin(phi))``: ``beta =
  g cos(phi)``, ``alpha = -g sin(phi)``, gain ``g`` and phase ``phi`` of the Q path,
  :mod:`radar_driver.frontend`), from one reflector at a known range: receiver by receiver, the I channel
  of the background-free mean frame is fitted by ``Re(c t(R))``, ``t`` the model's ideal
  return of a reflector at range R (which is refined around the measured one, so a tape
  measure is enough), then the Q channel by ``alpha Re(c t) + beta Im(c t)``: two linear
  least-squares fits, exact without noise, and free of the bias a statistic over a
  non-whole number of cycles would have;
- the **receiver-2 correction** ``rx2`` (complex): the ratio of the two receivers'
  complex amplitudes of that reflector, corrected for I/Q, over the ratio its known angle
  gives (the angle convention of :func:`radar_driver.model.antenna_phase_rad`).

Removal (:func:`correct_frames`), vectorized over a batch of frames of many sensors:
``z = y - b``; ``Q = (Q' - alpha I') / beta``; receiver 2 divided by ``rx2``.

The file (:func:`save` / :func:`load`, JSON, ``"type": "qradar.calibration"``,
``"version": 1``) holds one entry per (sensor id, config id); see docs/chamber.md.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from radar_driver.model import RadarConfig, antenna_phase_rad, simulate_frames

from pipeline.dsp.gate import LEAKAGE_BINS
from pipeline.dsp.localize import back_project_ramps, joint_energy
from pipeline.errors import CalibrationError

CAL_TYPE = "qradar.calibration"
CAL_VERSION = 1
#: the reflector's range is searched this many range bins either side of the given one
RANGE_SEARCH_BINS = 1.5
#: the checks of a calibration (FrontEndCorrection.problems): a fit residual above this (the
#: energy one reflector's model leaves, over the reflector frame's, dB: -20 to -40 dB for one
#: clean reflector in the simulated chamber, +2 dB with --range-m 7 for a reflector at 3.1 m)
#: says the inputs are wrong
MAX_RESIDUAL_DB = -15.0
#: the reflector's return (its recording's mean frame less the empty scene's) must stand this
#: much over the two means' noise, dB: below it the recording holds no reflector (a fit of it
#: would leave a residual far above MAX_RESIDUAL_DB)
RETURN_OVER_NOISE_DB = 10.0
#: the fitted range may move at most this many range bins from the given one (a tape's error)
MAX_RANGE_SHIFT_BINS = 1.0
#: an empty recording whose strongest return beyond its first and last EMPTY_SKIP_BINS range bins
#: (the leakage and its sidelobes) is within this of the reflector's (or, without one, of the
#: leakage) holds something: a reflector left in the beam, or the recordings swapped, dB
MAX_EMPTY_RETURN_DB = -10.0
EMPTY_SKIP_BINS = LEAKAGE_BINS + 1


@dataclass(frozen=True)
class FrontEndCorrection:
    """The calibration of one sensor in one radar configuration.

    background: (M, 2) complex, full scale; iq_alpha, iq_beta: ``Q' = alpha I + beta Q``;
    rx2: receiver 2 over receiver 1 (measured / expected); info: how it was made (frames,
    the reflector's range and angle, the fits' residuals)."""

    sensor_id: str
    config_id: int
    background: np.ndarray
    iq_alpha: float = 0.0
    iq_beta: float = 1.0
    rx2: complex = 1.0 + 0.0j
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        bg = np.asarray(self.background)
        if bg.ndim != 2 or bg.shape[1] != 2 or not np.all(np.isfinite(bg)):
            raise CalibrationError(f"calibration of {self.sensor_id!r}: background must be finite (M, 2), "
                                   f"got {bg.shape}")
        if not (math.isfinite(self.iq_alpha) and math.isfinite(self.iq_beta) and self.iq_beta > 0.1):
            raise CalibrationError(f"calibration of {self.sensor_id!r}: I/Q map alpha={self.iq_alpha!r}, "
                                   f"beta={self.iq_beta!r} is implausible (beta must be > 0.1)")
        rx2 = complex(self.rx2)
        if not (math.isfinite(rx2.real) and math.isfinite(rx2.imag) and 0.1 < abs(rx2) < 10):
            raise CalibrationError(f"calibration of {self.sensor_id!r}: receiver-2 ratio {rx2!r} is implausible "
                                   "(|rx2| must be within 20 dB of 1)")

    @property
    def m(self) -> int:
        return int(np.asarray(self.background).shape[0])

    @property
    def iq_gain_db(self) -> float:
        return 20.0 * math.log10(math.hypot(self.iq_alpha, self.iq_beta))

    @property
    def iq_phase_deg(self) -> float:
        return math.degrees(math.atan2(-self.iq_alpha, self.iq_beta))  # radar_driver.frontend's sign

    @property
    def rx2_gain_db(self) -> float:
        return 20.0 * math.log10(abs(complex(self.rx2)))

    @property
    def rx2_phase_deg(self) -> float:
        return math.degrees(math.atan2(complex(self.rx2).imag, complex(self.rx2).real))

    def problems(self, radar: RadarConfig | None = None) -> list[str]:
        """What says the inputs were wrong (MAX_RESIDUAL_DB, MAX_RANGE_SHIFT_BINS,
        MAX_EMPTY_RETURN_DB), one sentence each; [] for a plausible calibration."""
        i, out = self.info, []
        dr = (radar or RadarConfig()).range_resolution_m
        if i.get("fit_residual_db", -np.inf) > MAX_RESIDUAL_DB:
            out.append(f"the fit residual {i['fit_residual_db']:+.1f} dB is above {MAX_RESIDUAL_DB:g} dB: one reflector "
                       f"at {i['reflector_range_m']:g} m, {i['reflector_angle_deg']:+g} deg does not explain the "
                       "reflector recording (a wrong --range-m or --angle-deg, a second object in the beam, the "
                       "recordings swapped, clipping)")
        if "reflector_range_fit_m" in i:
            shift = abs(i["reflector_range_fit_m"] - i["reflector_range_m"])
            if shift > MAX_RANGE_SHIFT_BINS * dr:
                out.append(f"the reflector fits best at {i['reflector_range_fit_m']:.2f} m, {shift:.2f} m "
                           f"({shift / dr:.1f} range bins) from the given {i['reflector_range_m']:g} m: more than "
                           f"{MAX_RANGE_SHIFT_BINS:g} bin; measure its range again (apex to the antennas' plane)")
        if i.get("empty_return_db", -np.inf) > MAX_EMPTY_RETURN_DB:
            out.append(f"the empty recording holds a return at {i['empty_return_m']:.1f} m only "
                       f"{-i['empty_return_db']:.1f} dB below the {i['empty_return_ref']}: it is not empty (a "
                       "reflector left in the beam, or the two recordings swapped)")
        return out

    def summary(self) -> dict[str, Any]:
        """The estimates in units people read (dB, deg), for logs and metadata."""
        return {"sensor_id": self.sensor_id, "config_id": self.config_id,
                "iq_gain_db": round(self.iq_gain_db, 4), "iq_phase_deg": round(self.iq_phase_deg, 4),
                "rx2_gain_db": round(self.rx2_gain_db, 4), "rx2_phase_deg": round(self.rx2_phase_deg, 4),
                "background_rms": float(np.sqrt(np.mean(np.abs(self.background) ** 2))), **self.info}


# -- estimation (pure functions on arrays) ------------------------------------------------------
def estimate_background(frames: np.ndarray) -> np.ndarray:
    """The mean frame (M, 2) of frames (B, M, 2) of the empty scene."""
    frames = np.asarray(frames)
    if frames.ndim != 3 or frames.shape[-1] != 2 or frames.shape[0] < 1:
        raise CalibrationError(f"empty-scene frames must have shape (B >= 1, M, 2), got {frames.shape}")
    return frames.mean(axis=0)


def _template(config: RadarConfig, range_m: np.ndarray, m: int) -> np.ndarray:
    """The ideal return of a unit reflector at each range, antenna 1: (C, M) complex."""
    ramps = m // config.samples_per_ramp
    t = simulate_frames(np.asarray(range_m, float)[:, None], np.zeros((len(range_m), 1)),
                        np.ones((len(range_m), 1)), config, ramps=ramps)
    return t[:, :, 0]


def _fit_i(z_i: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares of the I channels z_i (M, 2) by Re(c t) for each template t (C, M):
    c (C, 2) complex and the residual energy (C,)."""
    basis = np.stack([t.real, -t.imag], axis=-1)  # (C, M, 2 coefficients)
    gram = np.einsum("cmk,cml->ckl", basis, basis)  # (C, 2, 2)
    rhs = np.einsum("cmk,mr->ckr", basis, z_i)  # (C, 2, receivers)
    coef = np.linalg.solve(gram + 1e-12 * np.eye(2), rhs)  # (C, 2, receivers)
    fit = np.einsum("cmk,ckr->cmr", basis, coef)
    resid = np.sum((z_i[None] - fit) ** 2, axis=(1, 2))
    return coef[:, 0, :] + 1j * coef[:, 1, :], resid


def fit_reflector_range(z: np.ndarray, config: RadarConfig, range_m: float) -> float:
    """The range (m) near ``range_m`` whose ideal return best explains the I channels of
    the background-free reflector frame z (M, 2) (the I path is the imbalance's reference)."""
    dr = config.range_resolution_m
    r = float(range_m)
    for half, points in ((RANGE_SEARCH_BINS * dr, 301), (dr / 100, 101), (dr / 5000, 101)):
        grid = np.clip(np.linspace(r - half, r + half, points), 0.0, None)
        _, resid = _fit_i(z.real, _template(config, grid, z.shape[0]))
        r = float(grid[int(np.argmin(resid))])
    return r


def estimate_front_end(empty: np.ndarray, reflector: np.ndarray | None, config: RadarConfig,
                       range_m: float | None = None, angle_deg: float = 0.0, sensor_id: str = "",
                       config_id: int | None = None) -> FrontEndCorrection:
    """The calibration from frames (B, M, 2) of the empty scene and, optionally, of one
    reflector at ``range_m`` (m, measured) and ``angle_deg`` (deg, positive towards
    receiver 2): the background always, the I/Q and receiver-2 corrections with the
    reflector (else the identity)."""
    background = estimate_background(empty)
    info: dict[str, Any] = {"frames_empty": int(np.asarray(empty).shape[0])}
    cid = config.config_id() if config_id is None else int(config_id)
    profile, skip = _range_profile(background, config), EMPTY_SKIP_BINS
    beyond = profile.copy()
    beyond[:skip], beyond[len(beyond) - skip:] = 0.0, 0.0
    if reflector is None:
        info.update(_empty_return(beyond, profile[:skip].max() if skip else 0.0, "leakage", config))
        return FrontEndCorrection(sensor_id, cid, background, info=info)
    reflector = np.asarray(reflector)
    if reflector.ndim != 3 or reflector.shape[1:] != background.shape:
        raise CalibrationError(f"reflector frames {reflector.shape} do not match the empty scene's "
                               f"(B, {background.shape[0]}, 2)")
    if range_m is None or not (0 < range_m < config.range_grid_m()[-1]):
        raise CalibrationError(f"the reflector's range {range_m!r} m must be within (0, "
                               f"{config.range_grid_m()[-1]:.2f}) m")
    if not -90 < angle_deg < 90:
        raise CalibrationError(f"the reflector's angle {angle_deg!r} deg must be within (-90, 90)")
    mean = reflector.mean(axis=0)
    z = mean - background  # (M, 2)
    power, floor = float(np.mean(np.abs(z) ** 2)), _return_floor((empty, background), (reflector, mean))
    if not power > floor:
        how = ("is the empty one's" if power == 0 else f"differs from the empty one's by "
               f"{10 * math.log10(power * 10 ** (RETURN_OVER_NOISE_DB / 10) / floor):+.1f} dB over the two means' "
               f"noise, under {RETURN_OVER_NOISE_DB:g} dB")
        raise CalibrationError(f"the reflector's frames hold nothing beside the empty scene's (their mean frame "
                               f"{how}): is the reflector in its recording, or is that the empty scene's again?")
    r_fit = fit_reflector_range(z, config, range_m)
    t = _template(config, np.array([r_fit]), z.shape[0])[0]  # (M,)
    c, resid_i = _fit_i(z.real, t[None])
    c = c[0]  # (2,) per receiver: I' = Re(c t)
    p = (c[None, :] * t[:, None])  # (M, 2): the clean signal per receiver, before I/Q
    # Q' = alpha Re(p) + beta Im(p), one (alpha, beta) for both receivers
    a = np.stack([p.real.ravel(), p.imag.ravel()], axis=-1)
    (alpha, beta), *_ = np.linalg.lstsq(a, z.imag.ravel(), rcond=None)
    zc = _iq_correct(z, alpha, beta)
    amp = (np.conj(t) @ zc) / np.vdot(t, t)  # (2,) complex amplitudes per receiver
    expected = np.exp(1j * antenna_phase_rad(np.deg2rad(angle_deg), config))
    rx2 = complex(amp[1] / amp[0] / expected)
    signal = float(np.sum(np.abs(z) ** 2))
    model = np.stack([amp[0] * t, amp[1] * t], axis=-1)
    resid = float(np.sum(np.abs(zc - model) ** 2))
    info.update({"frames_reflector": int(reflector.shape[0]), "reflector_range_m": float(range_m),
                 "reflector_range_fit_m": r_fit, "reflector_angle_deg": float(angle_deg),
                 "fit_residual_db": round(10 * math.log10(max(resid, 1e-300) / max(signal, 1e-300)), 2)})
    info.update(_empty_return(beyond, _range_profile(z, config).max(), "reflector's return", config))
    return FrontEndCorrection(sensor_id, cid, background, float(alpha), float(beta), rx2, info)


def _return_floor(*recordings: tuple[np.ndarray, np.ndarray]) -> float:
    """The least mean power a sample of the reflector's return (its mean frame less the empty
    one's) must have: :data:`RETURN_OVER_NOISE_DB` over the two means' noise (each of the
    ``recordings``' frames (B, M, 2) spread about their mean frame (M, 2), over B), and above
    the rounding of the empty scene's mean (the first)."""
    noise = sum(float(np.mean(np.abs(np.asarray(frames) - mean) ** 2)) / len(frames) for frames, mean in recordings)
    rounding = 1e-24 * float(np.mean(np.abs(recordings[0][1]) ** 2)) + 1e-300
    return 10 ** (RETURN_OVER_NOISE_DB / 10) * noise + rounding


def _range_profile(frame: np.ndarray, config: RadarConfig) -> np.ndarray:
    """The joint energy (N,) of the back projection of one frame (M, 2) of whole ramps."""
    return joint_energy(back_project_ramps(np.asarray(frame)[None], config))[0]


def _empty_return(beyond: np.ndarray, reference: float, what: str, config: RadarConfig) -> dict[str, Any]:
    """The empty scene's strongest return beyond the leakage bins (``beyond``: its range
    profile, zero there): its range and its energy over ``reference``'s, dB."""
    k = int(np.argmax(beyond))
    db = 10 * math.log10(max(float(beyond[k]), 1e-300) / max(float(reference), 1e-300))
    return {"empty_return_m": round(float(config.range_grid_m()[k]), 3), "empty_return_db": round(db, 2),
            "empty_return_ref": what}


# -- removal ----------------------------------------------------------------------------------------------
def _iq_correct(z: np.ndarray, alpha, beta) -> np.ndarray:
    return z.real + 1j * ((z.imag - alpha * z.real) / beta)


def correct_frames(frames: np.ndarray, background: np.ndarray, iq_alpha, iq_beta, rx2) -> np.ndarray:
    """Frames (B, M, 2) with the front end removed: background (M, 2) or (B, M, 2),
    iq_alpha / iq_beta / rx2 scalars or (B,) (one per frame, for a batch of many
    sensors). Returns complex128 (B, M, 2)."""
    z = np.asarray(frames, dtype=np.complex128) - background
    alpha = np.asarray(iq_alpha, dtype=float)
    beta = np.asarray(iq_beta, dtype=float)
    if alpha.ndim:
        alpha, beta = alpha[:, None, None], beta[:, None, None]
    z = _iq_correct(z, alpha, beta)
    rx2 = np.asarray(rx2, dtype=complex)
    z[..., 1] /= rx2[:, None] if rx2.ndim else rx2
    return z


class Calibration:
    """The corrections of a file, by (sensor id, config id); applied to batches of frames."""

    def __init__(self, entries: list[FrontEndCorrection], source: str = "<memory>", meta: dict | None = None):
        self.source = source
        self.meta = meta or {}
        self.entries = {(e.sensor_id, e.config_id): e for e in entries}
        if len(self.entries) != len(entries):
            raise CalibrationError(f"{source}: two entries for one (sensor id, config id)")
        self.sensors = {e.sensor_id for e in entries}

    def check_sensor(self, sensor_id: str) -> None:
        """Refuse a sensor the file has no entry for (one line naming both)."""
        if sensor_id not in self.sensors:
            raise CalibrationError(f"calibration {self.source} is for sensor(s) {sorted(self.sensors)}, not "
                                   f"{sensor_id!r}")

    def lookup(self, sensor_id: str, config_id: int) -> FrontEndCorrection | None:
        return self.entries.get((sensor_id, int(config_id)))

    def mismatch(self, sensor_id: str, config_id: int, m: int) -> str | None:
        """None when the file has an entry for frames of ``sensor_id``, ``config_id`` and M
        = ``m``, else one line saying what the frames are and what the file holds."""
        e = self.lookup(sensor_id, config_id)
        if e is not None and e.m == m:
            return None
        held = ", ".join(f"{x.sensor_id} config {x.config_id:#010x} M = {x.m}" for x in self.entries.values())
        return (f"calibration {self.source} does not fit the frames of sensor {sensor_id!r} (radar config "
                f"{int(config_id):#010x}, M = {m}): it holds {held}; calibrate this sensor in this configuration "
                f"(`qradar calibrate`, docs/chamber.md section 7)")

    def apply(self, frames: np.ndarray, sensor_ids: list[str], config_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frames (B, M, 2) of the given sensors and config ids, corrected; and a (B,) bool
        of the frames that had an entry of the right length (the others are returned as
        they came, for the caller to count and drop)."""
        b = len(sensor_ids)
        m = np.asarray(frames).shape[1]
        found = [self.lookup(s, c) for s, c in zip(sensor_ids, np.asarray(config_ids).tolist())]
        ok = np.array([e is not None and e.m == m for e in found], dtype=bool)
        out = np.array(frames, dtype=np.complex128, copy=True)
        if not ok.any():
            return out, ok
        idx = np.flatnonzero(ok)
        uniq: dict[int, int] = {}
        entries = [found[i] for i in idx]
        which = np.array([uniq.setdefault(id(e), len(uniq)) for e in entries])
        table = list({id(e): e for e in entries}.values())
        bg = np.stack([e.background for e in table])[which]
        alpha = np.array([e.iq_alpha for e in table])[which]
        beta = np.array([e.iq_beta for e in table])[which]
        rx2 = np.array([complex(e.rx2) for e in table])[which]
        out[idx] = correct_frames(out[idx], bg, alpha, beta, rx2)
        assert out.shape[0] == b
        return out, ok

    def summary(self) -> dict[str, Any]:
        return {"source": self.source, "entries": [e.summary() for e in self.entries.values()], **self.meta}


# -- the file ----------------------------------------------------------------------------------------------
def to_json(entries: list[FrontEndCorrection], meta: dict | None = None) -> str:
    out = {"type": CAL_TYPE, "version": CAL_VERSION, "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
           **(meta or {}), "entries": []}
    for e in entries:
        bg = np.asarray(e.background)
        out["entries"].append({
            "sensor_id": e.sensor_id, "config_id": e.config_id, "m": e.m,
            "background_re": bg.real.T.round(9).tolist(), "background_im": bg.imag.T.round(9).tolist(),
            "iq": {"alpha": e.iq_alpha, "beta": e.iq_beta, "gain_db": e.iq_gain_db, "phase_deg": e.iq_phase_deg},
            "rx2": {"re": complex(e.rx2).real, "im": complex(e.rx2).imag, "gain_db": e.rx2_gain_db,
                    "phase_deg": e.rx2_phase_deg},
            "info": e.info})
    return json.dumps(out, indent=1)


def save(path: str | Path, entries: list[FrontEndCorrection], meta: dict | None = None,
         overwrite: bool = False) -> Path:
    """Write a new calibration file (an existing file is refused unless ``overwrite``)."""
    path = Path(path)
    with open(path, "w" if overwrite else "x") as f:
        f.write(to_json(entries, meta) + "\n")
    return path


def load(path: str | Path) -> Calibration:
    """Read and check a calibration file; CalibrationError names the file and what is wrong."""
    path = Path(path)
    try:
        obj = json.loads(path.read_text())
    except OSError as exc:
        raise CalibrationError(f"calibration {path}: cannot read ({exc.strerror or exc})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"calibration {path}: not JSON ({exc})") from None
    if not isinstance(obj, dict) or obj.get("type") != CAL_TYPE:
        raise CalibrationError(f"calibration {path}: not a qradar calibration (\"type\" must be {CAL_TYPE!r})")
    if obj.get("version") != CAL_VERSION:
        raise CalibrationError(f"calibration {path}: version {obj.get('version')!r}, this qradar reads "
                               f"{CAL_VERSION}")
    entries = []
    for i, e in enumerate(obj.get("entries") or []):
        try:
            bg = (np.asarray(e["background_re"], float) + 1j * np.asarray(e["background_im"], float)).T
            if bg.shape != (int(e["m"]), 2):
                raise ValueError(f"background of shape {bg.shape}, m = {e['m']}")
            entries.append(FrontEndCorrection(str(e["sensor_id"]), int(e["config_id"]), bg,
                                              float(e["iq"]["alpha"]), float(e["iq"]["beta"]),
                                              complex(float(e["rx2"]["re"]), float(e["rx2"]["im"])),
                                              dict(e.get("info", {}))))
        except CalibrationError as exc:
            raise CalibrationError(f"calibration {path}, entry {i}: {exc}") from None
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationError(f"calibration {path}, entry {i}: missing or bad field ({exc})") from None
    if not entries:
        raise CalibrationError(f"calibration {path}: no entries")
    meta = {k: obj[k] for k in ("created_utc", "recordings") if k in obj}
    return Calibration(entries, str(path), meta)
