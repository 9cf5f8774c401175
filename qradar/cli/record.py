"""Recording commands: ``record`` (zenoh -> MCAP), ``recover`` (a cut-short MCAP -> a
complete one) and ``replay`` (MCAP -> zenoh)."""

from __future__ import annotations

import json
import sys
import threading
from pathlib import Path

from radar_driver.scene import resolve_scene
from replay.mcapio import recover
from replay.player import PlayConfig, play
from replay.recorder import RecorderNode

from .common import bus_from_args, bus_options, install_sigterm
from .stream import serve


def add_commands(sub) -> None:
    p = sub.add_parser("record", help="record radar/** from zenoh into MCAP")
    p.add_argument("-o", "--output", type=Path, required=True, help="FILE.mcap")
    p.add_argument("--topics", default=None, help="key expression (default <prefix>/**)")
    p.add_argument("--split-size", type=float, default=None, metavar="MB", help="new file every MB megabytes")
    p.add_argument("--split-duration", type=float, default=None, metavar="S", help="new file every S seconds")
    p.add_argument("--scene", default=None, help="ground-truth scene to store in the metadata (simulated sensor)")
    p.add_argument("--duration", type=float, default=None, help="stop after S seconds (default: Ctrl-C)")
    bus_options(p)
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("recover", help="rewrite a cut-short MCAP (e.g. after SIGKILL) as a complete, indexed file")
    p.add_argument("file", type=Path)
    p.add_argument("-o", "--output", type=Path, required=True)
    p.set_defaults(func=cmd_recover)

    p = sub.add_parser("replay", help="publish an MCAP recording back onto zenoh")
    p.add_argument("file", type=Path)
    g = p.add_mutually_exclusive_group()
    g.add_argument("--rate", type=float, default=1.0, help="speed factor of the original timing (default 1)")
    g.add_argument("--fast", action="store_true", help="as fast as subscribers take it (publishers block, no drops)")
    p.add_argument("--loop", action="store_true")
    p.add_argument("--start", type=float, default=None, help="seconds from the start of the file")
    p.add_argument("--end", type=float, default=None, help="seconds from the start of the file")
    p.add_argument("--topics", default=None, help="key expression of the channels to play")
    p.add_argument("--replay-prefix", dest="replay_prefix", default=None,
                   help="publish under this key prefix instead of the recorded one (e.g. replay)")
    bus_options(p)
    p.set_defaults(func=cmd_replay)


def cmd_record(args) -> int:
    meta = {}
    if args.scene:
        meta["qradar.scene"] = {"scene": json.dumps(resolve_scene(args.scene).to_dict()), "simulated": "true"}
    node = RecorderNode(bus_from_args(args), args.output, topics=args.topics, split_size_mb=args.split_size,
                        split_duration_s=args.split_duration, metadata=meta)
    print(f"recording {node.topics} to {args.output}; Ctrl-C to stop", file=sys.stderr, flush=True)
    serve(node, args.duration)
    print(json.dumps({"files": [str(p) for p in node.paths], "written": node.written}), flush=True)
    return 0


def cmd_recover(args) -> int:
    r = recover(args.file, args.output)
    print(json.dumps({"file": str(args.output), **r}))
    return 0


def cmd_replay(args) -> int:
    cfg = PlayConfig(rate=args.rate, fast=args.fast, loop=args.loop, start_s=args.start, end_s=args.end,
                     topics=args.topics, prefix=args.replay_prefix)
    install_sigterm()
    try:
        result = play(args.file, bus_from_args(args), cfg, stop=threading.Event())
    except KeyboardInterrupt:
        return 0
    print(json.dumps({"published": result.published, "loops": result.loops, "truncated": result.truncated,
                      "seconds": round(result.seconds, 3)}))
    return 0
