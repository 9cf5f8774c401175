"""``qradar calibrate``: the front end's background, I/Q and receiver-2 corrections from two
short recordings (docs/chamber.md)."""

from __future__ import annotations

import json
import sys

from pipeline.dsp.calibration import MAX_RESIDUAL_DB
from replay.calibrate import CalibrateConfig, calibrate

from .schema import Part, add_command


def residual_meaning(residual_db: float) -> str:
    """What a fit residual says (the energy one reflector's model leaves of the reflector
    recording, over its energy)."""
    if residual_db > MAX_RESIDUAL_DB:
        return (f"above {MAX_RESIDUAL_DB:g} dB, one reflector at the given range and angle does not explain the "
                "recording: the inputs are wrong")
    return (f"below {MAX_RESIDUAL_DB:g} dB, one reflector explains the recording (the rest: noise, "
            f"{'clean' if residual_db < -20 else 'some clutter or noise'})")


def add_commands(sub) -> None:
    add_command(sub, "calibrate", [Part(CalibrateConfig, only=("empty", "reflector", "range_m", "angle_deg", "sensors",
                                                                "out", "force"))], cmd_calibrate,
                help="front-end calibration (background, I/Q, receiver 2) from recordings",
                description="Estimates, per sensor and radar config, the background (the empty scene's mean frame: "
                "DC, TX leakage and static clutter), and with a reflector at a measured position the I/Q imbalance "
                "and the gain and phase of receiver 2; writes a new calibration file for --calibration.")


def cmd_calibrate(args) -> int:
    cfg = args.schema.build(CalibrateConfig, args)
    entries = calibrate(cfg)
    for e in entries:
        s = e.summary()
        line = f"{e.sensor_id} (config {e.config_id:#010x}): background rms {s['background_rms']:.3g} full scale"
        if "frames_reflector" in s:
            line += (f"; I/Q gain {s['iq_gain_db']:+.2f} dB, phase {s['iq_phase_deg']:+.1f} deg; receiver 2 gain "
                     f"{s['rx2_gain_db']:+.2f} dB, phase {s['rx2_phase_deg']:+.1f} deg; reflector at "
                     f"{s['reflector_range_fit_m']:.3f} m (given {s['reflector_range_m']:g}); fit residual "
                     f"{s['fit_residual_db']:.1f} dB: " + residual_meaning(s["fit_residual_db"]))
        print(line, file=sys.stderr)
        for p in e.problems():  # only with --force: a refused calibration ends in calibrate()
            print(f"warning: {e.sensor_id}: {p} (written anyway: --force)", file=sys.stderr)
    print(json.dumps({"calibration": str(args.out), "entries": [e.summary() for e in entries]}), flush=True)
    return 0
