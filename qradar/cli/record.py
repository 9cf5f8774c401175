"""Recording commands: ``record`` (zenoh -> MCAP; ``record --verify`` checks files),
``recover`` (a cut-short or damaged MCAP -> a complete one of what reads), ``replay``
(MCAP -> zenoh) and ``info`` (what a recording holds)."""

from __future__ import annotations

import json
import sys
import threading
from pathlib import Path

from pipeline.bus import audit
from pipeline.nodes.status import StatusLines
from pipeline.nodes.stream import run_nodes
from radar_driver.scene import resolve_scene
from replay.errors import ReplayError
from replay.mcapinfo import describe, format_info
from replay.mcapio import McapFile, recover
from replay.player import PlayConfig, play
from replay.recorder import OnWriteError, RecorderNode, RecordingState

from .common import (StopOnSignals, bus_from_args, bus_options, force_option, install_sigterm, intake_budget,
                     intake_options, pos_float)


def add_commands(sub) -> None:
    p = sub.add_parser("record", help="record radar/** from zenoh into MCAP (or --verify recordings)")
    p.add_argument("-o", "--output", type=Path, default=None, help="FILE.mcap (required unless --verify)")
    p.add_argument("--verify", type=Path, nargs="+", default=None, metavar="FILE",
                   help="record nothing: read each MCAP file whole, every chunk's CRC checked, and print what it "
                   "holds and lost (one JSON line each); exit 1 if any is damaged, cut short or lost messages")
    p.add_argument("--topics", default=None, help="key expression (default <prefix>/**)")
    p.add_argument("--split-size", type=float, default=None, metavar="MB", help="new file every MB megabytes")
    p.add_argument("--split-duration", type=float, default=None, metavar="S", help="new file every S seconds")
    p.add_argument("--scene", default=None, help="ground-truth scene to store in the metadata (simulated sensor)")
    p.add_argument("--duration", type=float, default=None, help="stop after S seconds (default: Ctrl-C)")
    write_error_options(p, "exit with status 2 (a recorder with nothing left to record ends)")
    force_option(p, "the -o file")
    p.add_argument("--quiet", action="store_true", help="no status line every few seconds on stderr")
    intake_options(p)
    bus_options(p)
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("recover", help="rewrite a cut-short or damaged MCAP (e.g. after SIGKILL) as a complete, "
                       "indexed file of every message that reads back (damaged chunks are left out, and named)")
    p.add_argument("file", type=Path, help="the cut-short or damaged MCAP file (read, never changed)")
    p.add_argument("-o", "--output", type=Path, required=True, help="the recovered FILE.mcap (a new file)")
    force_option(p, "the -o file")
    p.set_defaults(func=cmd_recover)

    p = sub.add_parser("replay", help="publish an MCAP recording back onto zenoh")
    p.add_argument("file", type=Path, help="a qradar MCAP recording")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--rate", type=float, default=1.0, help="speed factor of the original timing (default 1)")
    g.add_argument("--fast", action="store_true", help="as fast as subscribers take it (publishers block, no drops)")
    p.add_argument("--loop", action="store_true", help="play the file again from its start, until Ctrl-C")
    p.add_argument("--start", type=float, default=None, help="seconds from the start of the file")
    p.add_argument("--end", type=float, default=None, help="seconds from the start of the file")
    p.add_argument("--topics", default=None, help="key expression of the channels to play")
    p.add_argument("--replay-prefix", dest="replay_prefix", default=None,
                   help="publish under this key prefix instead of the recorded one (e.g. replay)")
    bus_options(p)
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("info", help="what a recording holds: sensors, topics with counts and rates, time span, the "
                       "radar, quantizer, decoder, calibration and truth, the losses recorded, recovery, split files",
                       description="Describe MCAP recordings from their summary and metadata alone (no message is "
                       "read: an hour in well under a second). A file without a summary (cut short by a kill, its "
                       "summary damaged) is read whole, every chunk's CRC checked, and says so.")
    p.add_argument("file", type=Path, nargs="+", help="MCAP recordings")
    p.add_argument("--json", action="store_true", help="one JSON object per file (what qradar.open_recording("
                   "FILE).info() returns)")
    p.add_argument("--check", action="store_true", help="also read every chunk, its CRC checked, and report the "
                   "damage found (as `qradar record --verify`; takes as long as reading the file)")
    p.set_defaults(func=cmd_info)


def write_error_options(p, on_stop: str) -> None:
    """--on-write-error and --write-retry (``record``, ``run``); ``on_stop``: what the command does then."""
    p.add_argument("--on-write-error", choices=[m.value for m in OnWriteError], default=OnWriteError.RESUME.value,
                   help="after a write error (a full disk, EFBIG, EIO, a removed folder) the file is closed up to "
                   "its last flushed chunk; resume: keep running, count the messages that cannot be written (by "
                   "topic) and go on in a new file (NAME_0001.mcap, ...) when space returns; stop: end the "
                   f"recording and {on_stop}. A file that cannot be created at the start is an error either way")
    p.add_argument("--write-retry", type=pos_float, default=5.0, metavar="S",
                   help="while paused after a write error, look for space every S seconds")


def cmd_verify(paths: list[Path]) -> int:
    """``record --verify``: one JSON line per file on stdout, one line per damage on stderr;
    1 when a file is not intact."""
    bad = 0
    for path in paths:
        f = McapFile(path)
        f.scan()
        for line in f.damage_lines():
            print(f"qradar record --verify: {path}: {line}", file=sys.stderr)
        if f.truncated:
            print(f"qradar record --verify: {path}: {f.truncation_reason} (qradar recover completes it)",
                  file=sys.stderr)
        bad += not f.intact
        print(json.dumps(f.report()), flush=True)
    return 1 if bad else 0


def cmd_record(args) -> int:
    if args.verify is not None:
        if args.output is not None:
            raise ReplayError("--verify checks files and records nothing: give -o or --verify, not both")
        return cmd_verify(args.verify)
    if args.output is None:
        raise ReplayError("give -o FILE.mcap to record to (or --verify FILE to check a recording)")
    meta = {}
    if args.scene:
        meta["qradar.scene"] = {"scene": json.dumps(resolve_scene(args.scene).to_dict()), "simulated": "true"}
    node = RecorderNode(bus_from_args(args), args.output, topics=args.topics, split_size_mb=args.split_size,
                        split_duration_s=args.split_duration, metadata=meta, on_write_error=args.on_write_error,
                        retry_s=args.write_retry, intake=intake_budget(args), overwrite=args.force)
    print(f"recording {node.topics} to {args.output}; Ctrl-C to stop", file=sys.stderr, flush=True)
    install_sigterm("record")
    status = StatusLines(node, quiet=args.quiet, announce=False).start()
    try:
        run_nodes([node], args.duration, node.recording_ended)  # ends early when recording stops for good
    except KeyboardInterrupt:
        pass
    finally:
        status.stop()
    print(json.dumps({"node": node.name, **node.totals(), **node.summary(), **audit.finish()}), flush=True)
    if node.state is RecordingState.STOPPED:
        raise ReplayError(f"recording stopped after a write error: {node.error} (--on-write-error stop)")
    return 0


def cmd_recover(args) -> int:
    r = recover(args.file, args.output, overwrite=args.force)
    if r["lost"] or r["damaged_chunks"] or r["problems"]:
        print(f"qradar recover: {args.file}: {len(r['damaged_chunks'])} damaged chunk(s) left out of {args.output}, "
              f"{r['lost']} messages lost {r['lost_by_topic']}; each named in the JSON line and in its "
              "qradar.recovery metadata", file=sys.stderr)
    print(json.dumps({**r, "source": str(args.file), "file": str(args.output)}))
    return 0


def cmd_info(args) -> int:
    for i, path in enumerate(args.file):
        info = describe(path, check=args.check)
        if args.json:
            print(json.dumps(info), flush=True)
        else:
            print(("\n" if i else "") + format_info(info), flush=True)
    return 0


def cmd_replay(args) -> int:
    cfg = PlayConfig(rate=args.rate, fast=args.fast, loop=args.loop, start_s=args.start, end_s=args.end,
                     topics=args.topics, prefix=args.replay_prefix)
    stop = threading.Event()
    signals = StopOnSignals(stop, "replay")  # Ctrl-C ends the replay, which still says what it published
    result = play(args.file, bus_from_args(args), cfg, stop=stop)
    print(json.dumps({"published": result.published, "loops": result.loops, "truncated": result.truncated,
                      "lost": result.lost, "damaged_chunks": result.damaged,
                      "seconds": round(result.seconds, 3), "interrupted": signals.interrupted is not None,
                      **audit.finish()}))
    return 0
