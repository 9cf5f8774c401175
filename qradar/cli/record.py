"""Recording commands: ``record`` (zenoh -> MCAP), ``recover`` (a cut-short MCAP -> a
complete one) and ``replay`` (MCAP -> zenoh)."""

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
from replay.mcapio import recover
from replay.player import PlayConfig, play
from replay.recorder import OnWriteError, RecorderNode, RecordingState

from .common import (StopOnSignals, bus_from_args, bus_options, force_option, install_sigterm, intake_budget,
                     intake_options, pos_float)


def add_commands(sub) -> None:
    p = sub.add_parser("record", help="record radar/** from zenoh into MCAP")
    p.add_argument("-o", "--output", type=Path, required=True, help="FILE.mcap")
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

    p = sub.add_parser("recover", help="rewrite a cut-short MCAP (e.g. after SIGKILL) as a complete, indexed file")
    p.add_argument("file", type=Path, help="the cut-short MCAP file (read, never changed)")
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


def write_error_options(p, on_stop: str) -> None:
    """--on-write-error and --write-retry (``record``, ``run``); ``on_stop``: what the command does then."""
    p.add_argument("--on-write-error", choices=[m.value for m in OnWriteError], default=OnWriteError.RESUME.value,
                   help="after a write error (a full disk, EFBIG, EIO, a removed folder) the file is closed up to "
                   "its last flushed chunk; resume: keep running, count the messages that cannot be written (by "
                   "topic) and go on in a new file (NAME_0001.mcap, ...) when space returns; stop: end the "
                   f"recording and {on_stop}. A file that cannot be created at the start is an error either way")
    p.add_argument("--write-retry", type=pos_float, default=5.0, metavar="S",
                   help="while paused after a write error, look for space every S seconds")


def cmd_record(args) -> int:
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
    print(json.dumps({"file": str(args.output), **r}))
    return 0


def cmd_replay(args) -> int:
    cfg = PlayConfig(rate=args.rate, fast=args.fast, loop=args.loop, start_s=args.start, end_s=args.end,
                     topics=args.topics, prefix=args.replay_prefix)
    stop = threading.Event()
    signals = StopOnSignals(stop, "replay")  # Ctrl-C ends the replay, which still says what it published
    result = play(args.file, bus_from_args(args), cfg, stop=stop)
    print(json.dumps({"published": result.published, "loops": result.loops, "truncated": result.truncated,
                      "seconds": round(result.seconds, 3), "interrupted": signals.interrupted is not None,
                      **audit.finish()}))
    return 0
