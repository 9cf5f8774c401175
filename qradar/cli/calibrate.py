"""``qradar calibrate``: the front end's background, I/Q and receiver-2 corrections from two
short recordings (docs/chamber.md)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from pipeline.dsp.calibration import MAX_EMPTY_RETURN_DB, MAX_RANGE_SHIFT_BINS, MAX_RESIDUAL_DB
from replay.calibrate import CalibrateConfig, calibrate


def residual_meaning(residual_db: float) -> str:
    """What a fit residual says (the energy one reflector's model leaves of the reflector
    recording, over its energy)."""
    if residual_db > MAX_RESIDUAL_DB:
        return (f"above {MAX_RESIDUAL_DB:g} dB, one reflector at the given range and angle does not explain the "
                "recording: the inputs are wrong")
    return (f"below {MAX_RESIDUAL_DB:g} dB, one reflector explains the recording (the rest: noise, "
            f"{'clean' if residual_db < -20 else 'some clutter or noise'})")


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
    p.add_argument("--force", action="store_true",
                   help=f"write the calibration even when its checks say the inputs are wrong (a fit residual above "
                   f"{MAX_RESIDUAL_DB:g} dB, the reflector fitted more than {MAX_RANGE_SHIFT_BINS:g} range bin from "
                   f"--range-m, a return in the empty recording within {-MAX_EMPTY_RETURN_DB:g} dB of the reflector's), "
                   "and replace an existing --out")
    p.set_defaults(func=cmd_calibrate)


def cmd_calibrate(args) -> int:
    cfg = CalibrateConfig(args.empty, args.out, args.reflector, args.range_m, args.angle_deg,
                          tuple(args.sensor) if args.sensor else None, force=args.force)
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
