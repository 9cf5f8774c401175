"""Bring-up commands for a sensor whose wire layout is unknown: ``capture`` (record the
raw bytes of a session) and ``inspect`` (list a capture's messages and find the sensor
profile that reads it)."""

from __future__ import annotations

import json
import signal
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

from radar_driver.capture import Capture, CaptureConfig, run_capture
from radar_driver.inspection import Reflector, format_report, inspect_capture
from radar_driver.options import like, option
from radar_driver.profile import packaged_profiles
from radar_driver.session import SessionConfig
from replay.errors import ReplayError
from replay.mcapcheck import MAGIC as MCAP_MAGIC
from replay.outputs import check_new_file

from .parts import force_help, switches
from .schema import Part, add_command

#: how long a capture runs without --seconds: without --frames, and as a bound with them, s
DEFAULT_SECONDS = CaptureConfig.seconds
DEFAULT_SECONDS_WITH_FRAMES = 60.0


@dataclass(frozen=True)
class CaptureFile:
    """Where ``qradar capture`` writes."""

    out: Path = option(help="capture file to write", aliases=("-o",), required=True)


@dataclass(frozen=True)
class Inspect:
    """What ``qradar inspect`` reads and tries."""

    file: Path = option(help="a file of `qradar capture`", positional=True, required=True)
    profile: tuple[str, ...] = option((), "also try this profile (repeatable)", many="append", metavar="NAME|PATH")
    ramps: int = like(SessionConfig, "ramps_per_frame", flag="--ramps", help="ramps per frame (default 2)")
    chirp_select: str = like(SessionConfig, "chirp_select", help="with several chirps per RADC: the first --ramps, "
                             "or a stride (default first)")
    range_m: float | None = option(None, "the reflector's range if known, m")
    angle_deg: float | None = option(None, "the reflector's angle if known, deg (positive: antenna 2's side)")


CAPTURE_SECONDS = {"help": f"stop after S seconds (default {DEFAULT_SECONDS:g}; with --frames, "
                           f"{DEFAULT_SECONDS_WITH_FRAMES:g} at most)"}


def add_commands(sub) -> None:
    add_command(sub, "capture", [
        Part(CaptureConfig, only=("url",)), Part(CaptureFile),
        Part(CaptureConfig, only=("profile", "frames", "seconds", "baud", "ramps_per_frame", "timeout_s", "mode"),
             defaults={"seconds": None}, change={"seconds": CAPTURE_SECONDS}),
        switches(json="print the summary as one JSON object", force=force_help("the -o file"))], cmd_capture,
        help="record the raw bytes of a session with a K-MD2, with timestamps",
        description="Talk to a sensor on any pyserial URL and record every byte each way, every\n"
        "line-speed change and every port opening, with the host's time, to FILE (format:\n"
        "docs/capture-format.md). The driver runs with --profile; if it decodes no frame (an\n"
        "unknown layout), a raw poller (INIT, a GNFD per DONE, GBYE) captures on without\n"
        "decoding. Then `qradar inspect FILE`.")
    add_command(sub, "inspect", [Part(Inspect), switches(json="print the report as one JSON object")], cmd_inspect,
                help="list a capture's messages and find the sensor profile that reads it",
                description="Split the sensor's bytes of a capture into messages without a profile\n"
                "(headers, lengths, counts, garbage), then decode them with every shipped profile (and\n"
                "--profile ones) and score the frames as a single static reflector: a sharp range peak\n"
                "without images and a steady angle. Exit status 0 when a profile fits, 1 when none does.")


def cmd_capture(args) -> int:
    seconds = args.seconds or (DEFAULT_SECONDS if args.frames is None else DEFAULT_SECONDS_WITH_FRAMES)
    cfg = args.schema.build(CaptureConfig, args, seconds=seconds)
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
