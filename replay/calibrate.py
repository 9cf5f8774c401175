"""``qradar calibrate``: a front-end calibration from recordings of the empty scene and of
one reflector at a known position (the estimates are :mod:`pipeline.dsp.calibration`'s)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pipeline.dsp.calibration import (MAX_EMPTY_RETURN_DB, MAX_RANGE_SHIFT_BINS, MAX_RESIDUAL_DB, FrontEndCorrection,
                                      estimate_front_end, save)
from radar_driver.model import RadarConfig
from radar_driver.options import option

from .errors import CalibrationRefused, ReplayError
from .outputs import check_new_file
from .reprocess import load_raw, radar_for


@dataclass(frozen=True)
class CalibrateConfig:
    """empty: recording of the empty scene; reflector: of one reflector at ``range_m`` (m)
    and ``angle_deg`` (deg, positive towards receiver 2), or None (background only);
    sensors: the sensor ids to calibrate (None: every sensor of the empty recording)."""

    empty: Path = option(help="a recording of the empty scene (a few seconds: `qradar run --empty` on the "
                         "simulator)", metavar="EMPTY.mcap", required=True)
    out: Path = option(help="the calibration file (made new)", metavar="CAL.json", required=True)
    reflector: Path | None = option(None, "a recording of one reflector at --range-m and --angle-deg (else: "
                                    "background only)", metavar="REF.mcap")
    range_m: float | None = option(None, "the reflector's measured range, m (a tape is enough: it is refined within "
                                   "1.5 range bins)")
    angle_deg: float = option(0.0, "the reflector's angle, deg, positive towards receiver 2 (default 0: boresight)")
    sensors: tuple[str, ...] | None = option(None, "calibrate this sensor (repeatable; default: every sensor of the "
                                             "empty recording)", flag="--sensor", many="append", metavar="ID")
    radar: RadarConfig = RadarConfig()
    # write a calibration whose checks fail, and replace an existing out
    force: bool = option(False, f"write the calibration even when its checks say the inputs are wrong (a fit residual "
                         f"above {MAX_RESIDUAL_DB:g} dB, the reflector fitted more than {MAX_RANGE_SHIFT_BINS:g} range "
                         f"bin from --range-m, a return in the empty recording within {-MAX_EMPTY_RETURN_DB:g} dB of "
                         "the reflector's), and replace an existing --out")

    def __post_init__(self) -> None:
        if self.reflector is not None and self.range_m is None:
            raise ReplayError("--reflector needs --range-m (the reflector's measured range, m)")
        if self.reflector is None and self.range_m is not None:
            raise ReplayError("--range-m is the reflector's range: give --reflector REF.mcap too")
        if self.reflector is None and self.angle_deg != 0.0:
            raise ReplayError(f"--angle-deg {self.angle_deg:g} is the reflector's angle: give --reflector REF.mcap "
                              "and --range-m too")
        check_new_file(self.out, self.force, "calibration", inputs=(self.empty, self.reflector))


def calibrate(cfg: CalibrateConfig) -> list[FrontEndCorrection]:
    """The calibration of every sensor (and its radar config) of the recordings, written to
    ``cfg.out``; a sensor of the empty recording missing from the reflector's is an error.
    A calibration whose checks say the inputs are wrong (:meth:`FrontEndCorrection.problems`:
    the fit's residual, the reflector's fitted range, a return in the empty recording) is
    refused, nothing written, unless ``cfg.force``."""
    first = load_raw(cfg.empty)
    sensors = list(cfg.sensors or first.sensors)
    entries = []
    for sid in sensors:
        empty = load_raw(cfg.empty, sid)
        radar = radar_for(empty, cfg.radar)
        refl = None
        if cfg.reflector is not None:
            refl = load_raw(cfg.reflector, sid)
            if refl.config_id != empty.config_id or refl.frames.shape[1:] != empty.frames.shape[1:]:
                raise ReplayError(f"{cfg.reflector}: sensor {sid}'s frames (config id {refl.config_id:#010x}, "
                                  f"M = {refl.frames.shape[1]}) are not those of {cfg.empty} (config id "
                                  f"{empty.config_id:#010x}, M = {empty.frames.shape[1]})")
        entries.append(estimate_front_end(empty.frames, None if refl is None else refl.frames, radar,
                                          cfg.range_m, cfg.angle_deg, sid, empty.config_id))
    problems = [f"{e.sensor_id}: {p}" for e in entries for p in e.problems(cfg.radar)]
    if problems and not cfg.force:
        raise CalibrationRefused(f"calibration refused, {cfg.out} not written: " + "; ".join(problems)
                                 + " (--force writes it anyway)")
    recordings = {"empty": str(cfg.empty), **({"reflector": str(cfg.reflector)} if cfg.reflector else {})}
    save(cfg.out, entries, {"recordings": recordings, **({"forced_past": problems} if problems else {})},
         overwrite=cfg.force)
    return entries


