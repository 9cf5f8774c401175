"""Recording commands: ``record`` (zenoh -> MCAP), ``recover`` (a cut-short MCAP -> a
complete one) and ``replay`` (MCAP -> zenoh)."""

from __future__ import annotations

import json
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

from pipeline.bus import audit
from pipeline.nodes.status import StatusLines
from pipeline.nodes.stream import run_nodes
from radar_driver.scene import resolve_scene
from replay.errors import ReplayError
from replay.mcapio import recover
from replay.player import PlayConfig, play
from replay.recorder import RecorderNode, RecordingState

from radar_driver.options import META, option, pos_float

from ..run import RunConfig
from .common import StopOnSignals, bus_from_args, install_sigterm, intake_budget, watch_parent
from .parts import INTAKE, force_help, node_part, switches, zenoh_parts
from .schema import Part, add_command


@dataclass(frozen=True)
class Record:
    """Where ``qradar record`` writes and what it records."""

    output: Path = option(help="FILE.mcap", aliases=("-o",), required=True)
    topics: str | None = option(None, "key expression (default <prefix>/**)")
    split_size_mb: float | None = option(None, "new file every MB megabytes", flag="--split-size", metavar="MB",
                                         parse=pos_float)
    split_duration_s: float | None = option(None, "new file every S seconds", flag="--split-duration", metavar="S",
                                            parse=pos_float)
    scene: str | None = option(None, "ground-truth scene to store in the metadata (simulated sensor)")


@dataclass(frozen=True)
class Recover:
    """``qradar recover FILE -o NEW``."""

    file: Path = option(help="the cut-short MCAP file (read, never changed)", positional=True, required=True)
    output: Path = option(help="the recovered FILE.mcap (a new file)", aliases=("-o",), required=True)


@dataclass(frozen=True)
class Recording:
    """A recording to read."""

    file: Path = option(help="a qradar MCAP recording", positional=True, required=True)


def write_error_part(on_stop: str, table: str | None = "recording") -> Part:
    """--on-write-error and --write-retry (``record``, ``run``); ``on_stop``: what the command does then."""
    help = RunConfig.__dataclass_fields__["record_on_error"].metadata[META].help
    return Part(RunConfig, table, only=("record_on_error", "record_retry_s"), change={"record_on_error": {
        "help": help.replace("go on without it (the pipeline keeps running; the summary says so)", on_stop)}})


RECORD_PARTS = [
    Part(Record, only=("output", "topics", "split_size_mb", "split_duration_s", "scene")),
    node_part("duration_s"), write_error_part("exit with status 2 (a recorder with nothing left to record ends)"),
    switches(force=force_help("the -o file")),
    node_part("quiet", "parent_pid", quiet="no status line every few seconds on stderr"), INTAKE, *zenoh_parts()]


def add_commands(sub) -> None:
    add_command(sub, "record", RECORD_PARTS, cmd_record, config_json=True, help="record radar/** from zenoh into MCAP")
    add_command(sub, "recover", [Part(Recover), switches(force=force_help("the -o file"))], cmd_recover,
                help="rewrite a cut-short MCAP (e.g. after SIGKILL) as a complete, indexed file")
    add_command(sub, "replay", [Part(Recording), Part(PlayConfig, exclusive=(("rate", "fast"),), dests={"prefix": "replay_prefix"}), *zenoh_parts()],
                cmd_replay, help="publish an MCAP recording back onto zenoh")


def cmd_record(args) -> int:
    meta = {}
    if args.scene:
        meta["qradar.scene"] = {"scene": json.dumps(resolve_scene(args.scene).to_dict()), "simulated": "true"}
    node = RecorderNode(bus_from_args(args), args.output, topics=args.topics, split_size_mb=args.split_size_mb,
                        split_duration_s=args.split_duration_s, metadata=meta, on_write_error=args.record_on_error,
                        retry_s=args.record_retry_s, intake=intake_budget(args), overwrite=args.force)
    print(f"recording {node.topics} to {args.output}; Ctrl-C to stop", file=sys.stderr, flush=True)
    install_sigterm("record")
    if args.parent_pid is not None:
        watch_parent(args.parent_pid, "record")
    status = StatusLines(node, quiet=args.quiet, announce=False).start()
    try:
        run_nodes([node], args.duration_s, node.recording_ended)  # ends early when recording stops for good
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
    cfg = args.schema.build(PlayConfig, args)
    stop = threading.Event()
    signals = StopOnSignals(stop, "replay")  # Ctrl-C ends the replay, which still says what it published
    result = play(args.file, bus_from_args(args), cfg, stop=stop)
    print(json.dumps({"published": result.published, "loops": result.loops, "truncated": result.truncated,
                      "seconds": round(result.seconds, 3), "interrupted": signals.interrupted is not None,
                      **audit.finish()}))
    return 0
