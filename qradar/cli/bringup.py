"""Bring-up commands for a sensor whose wire layout is unknown: ``capture`` (record the
raw bytes of a session) and ``inspect`` (list a capture's messages and find the sensor
profile that reads it)."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

from radar_driver.capture import MODES, Capture, CaptureConfig, run_capture
from radar_driver.inspection import Reflector, format_report, inspect_capture
from radar_driver.profile import CHIRP_SELECT, packaged_profiles
from replay.errors import ReplayError
from replay.mcapcheck import MAGIC as MCAP_MAGIC
from replay.outputs import check_new_file

from .common import force_option, pos_int

#: how long a capture runs without --seconds: without --frames, and as a bound with them, s
DEFAULT_SECONDS = 10.0
DEFAULT_SECONDS_WITH_FRAMES = 60.0


def pos_float(text: str) -> float:
    v = float(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
    return v


def add_commands(sub) -> None:
    p = sub.add_parser("capture", help="record the raw bytes of a session with a K-MD2, with timestamps",
                       description="Talk to a sensor on any pyserial URL and record every byte each way, every\n"
                       "line-speed change and every port opening, with the host's time, to FILE (format:\n"
                       "docs/capture-format.md). The driver runs with --profile; if it decodes no frame (an\n"
                       "unknown layout), a raw poller (INIT, a GNFD per DONE, GBYE) captures on without\n"
                       "decoding. Then `qradar inspect FILE`.")
    p.add_argument("--port", required=True, help="pyserial URL or device path")
    p.add_argument("-o", "--out", type=Path, required=True, help="capture file to write")
    p.add_argument("--profile", default=None,
                   help=f"sensor profile for the driver: a packaged name ({', '.join(packaged_profiles())}) or a "
                   "TOML file (default kmd2-blocks); its baud codes and GNFD bits also serve the raw poller")
    p.add_argument("--frames", type=pos_int, default=None,
                   help="stop after N frames (the raw poller: N x --ramps GNFD answers)")
    p.add_argument("--seconds", type=pos_float, default=None,
                   help=f"stop after S seconds (default {DEFAULT_SECONDS:g}; with --frames, "
                   f"{DEFAULT_SECONDS_WITH_FRAMES:g} at most)")
    p.add_argument("--baud", type=int, default=None,
                   help="rate after INIT (default 2000000 on a link that can change speed)")
    p.add_argument("--ramps", type=pos_int, default=2, help="ramps per frame (default 2)")
    p.add_argument("--timeout", type=pos_float, default=0.5, help="seconds to wait for a GNFD answer")
    p.add_argument("--mode", choices=MODES, default="auto",
                   help="auto: the driver, then the raw poller if it decodes no frame; session: the driver "
                   "only; raw: the raw poller only (default auto)")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    force_option(p, "the -o file")
    p.set_defaults(func=cmd_capture)

    p = sub.add_parser("inspect", help="list a capture's messages and find the sensor profile that reads it",
                       description="Split the sensor's bytes of a capture into messages without a profile\n"
                       "(headers, lengths, counts, garbage), then decode them with every shipped profile (and\n"
                       "--profile ones) and score the frames as a single static reflector: a sharp range peak\n"
                       "without images and a steady angle. Exit status 0 when a profile fits, 1 when none does.")
    p.add_argument("file", type=Path, help="a file of `qradar capture`")
    p.add_argument("--profile", action="append", default=[], metavar="NAME|PATH",
                   help="also try this profile (repeatable)")
    p.add_argument("--ramps", type=pos_int, default=2, help="ramps per frame (default 2)")
    p.add_argument("--chirp-select", choices=CHIRP_SELECT, default="first",
                   help="with several chirps per RADC: the first --ramps, or a stride (default first)")
    p.add_argument("--range-m", type=float, default=None, help="the reflector's range if known, m")
    p.add_argument("--angle-deg", type=float, default=None,
                   help="the reflector's angle if known, deg (positive: antenna 2's side)")
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    p.set_defaults(func=cmd_inspect)


def cmd_capture(args) -> int:
    seconds = args.seconds or (DEFAULT_SECONDS if args.frames is None else DEFAULT_SECONDS_WITH_FRAMES)
    cfg = CaptureConfig(args.port, profile=args.profile, frames=args.frames, seconds=seconds, baud=args.baud,
                        ramps_per_frame=args.ramps, timeout_s=args.timeout, mode=args.mode)
    check_new_file(args.out, args.force, "capture")  # before the port opens
    stop = threading.Event()
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):  # Ctrl-C ends the capture cleanly, with its summary
            previous[sig] = signal.signal(sig, lambda *_: stop.set())
    try:
        summary = run_capture(cfg, args.out, stop)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print(json.dumps(summary.to_dict()) if args.json else summary.line(), flush=True)
    return 0


def cmd_inspect(args) -> int:
    try:
        with open(args.file, "rb") as fh:
            head = fh.read(len(MCAP_MAGIC))
    except OSError:
        head = b""  # Capture.read says why it cannot be read
    if head == MCAP_MAGIC:
        raise ReplayError(f"{args.file} is an MCAP recording, not a capture of `qradar capture`: "
                          f"`qradar info {args.file}` says what it holds")
    capture = Capture.read(args.file)
    profiles = packaged_profiles() + [p for p in args.profile if p not in packaged_profiles()] if args.profile else None
    report = inspect_capture(capture, profiles, ramps_per_frame=args.ramps, chirp_select=args.chirp_select,
                             reflector=Reflector(args.range_m, args.angle_deg))
    if args.json:
        print(json.dumps(report.to_dict()))
    else:
        print(format_report(report))
    if capture.truncated:
        print(f"qradar inspect: warning: {args.file} ends early: {capture.truncated}", file=sys.stderr)
    return 0 if report.best is not None else 1
