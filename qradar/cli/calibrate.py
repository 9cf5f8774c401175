"""``qradar calibrate``: the front end's background, I/Q and receiver-2 corrections from two
short recordings (docs/chamber.md)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from replay.calibrate import CalibrateConfig, calibrate


def add_commands(sub) -> None:
    p = sub.add_parser(
        "calibrate", help="front-end calibration (background, I/Q, receiver 2) from recordings",
        description="Estimates, per sensor and radar config, the background (the empty scene's mean frame: DC, "
        "TX leakage and static clutter), and with a reflector at a measured position the I/Q imbalance and the "
        "gain and phase of receiver 2; writes a new calibration file for --calibration.")
    p.add_argument("--empty", type=Path, required=True, metavar="EMPTY.mcap",
                   help="a recording of the empty scene (a few seconds: `qradar run --empty` on the simulator)")
    p.add_argument("--reflector", type=Path, default=None, metavar="REF.mcap",
                   help="a recording of one reflector at --range-m and --angle-deg (else: background only)")
    p.add_argument("--range-m", type=float, default=None, help="the reflector's measured range, m (a tape is "
                   "enough: it is refined within 1.5 range bins)")
    p.add_argument("--angle-deg", type=float, default=0.0,
                   help="the reflector's angle, deg, positive towards receiver 2 (default 0: boresight)")
    p.add_argument("--sensor", action="append", default=None, metavar="ID",
                   help="calibrate this sensor (repeatable; default: every sensor of the empty recording)")
    p.add_argument("--out", type=Path, required=True, metavar="CAL.json", help="the calibration file (made new)")
    p.set_defaults(func=cmd_calibrate)


def cmd_calibrate(args) -> int:
    cfg = CalibrateConfig(args.empty, args.out, args.reflector, args.range_m, args.angle_deg,
                          tuple(args.sensor) if args.sensor else None)
    entries = calibrate(cfg)
    for e in entries:
        s = e.summary()
        line = f"{e.sensor_id} (config {e.config_id:#010x}): background rms {s['background_rms']:.4g} full scale"
        if "frames_reflector" in s:
            line += (f"; I/Q gain {s['iq_gain_db']:+.3f} dB, phase {s['iq_phase_deg']:+.2f} deg; receiver 2 gain "
                     f"{s['rx2_gain_db']:+.3f} dB, phase {s['rx2_phase_deg']:+.2f} deg; reflector at "
                     f"{s['reflector_range_fit_m']:.4f} m (given {s['reflector_range_m']:g}); fit residual "
                     f"{s['fit_residual_db']:.1f} dB")
        print(line, file=sys.stderr)
    print(json.dumps({"calibration": str(args.out), "entries": [e.summary() for e in entries]}), flush=True)
    return 0
