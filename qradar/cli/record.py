"""Recording commands: ``record`` (zenoh -> MCAP; ``record --verify`` checks files),
``recover`` (a cut-short or damaged MCAP -> a complete one of what reads), ``replay``
(MCAP -> zenoh) and ``info`` (what a recording holds)."""

from __future__ import annotations

import json
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

from pipeline.bus import audit
from pipeline.nodes.status import StatusLines
from pipeline.nodes.stream import run_nodes
from radar_driver.lifetime import watch_parent
from radar_driver.scene import resolve_scene
from replay.errors import ReplayError
from replay.mcapinfo import describe, format_info, split_note
from replay.mcapio import McapFile, recover
from replay.player import PlayConfig, play
from replay.recorder import RecorderNode, RecordingState
from radar_driver.options import META, option, pos_float

from ..run import RunConfig
from .common import StopOnSignals, bus_from_args, install_sigterm, intake_budget, nothing_heard
from .parts import INTAKE, force_help, node_part, switches, zenoh_parts
from .schema import Part, add_command


@dataclass(frozen=True)
class Record:
    """Where ``qradar record`` writes and what it records."""

    output: Path | None = option(None, "FILE.mcap (required unless --verify)", aliases=("-o",))
    verify: tuple[Path, ...] | None = option(None, "record nothing: read each MCAP file whole, every chunk's CRC "
                                             "checked, and print what it holds and lost (one JSON line each); exit 1 "
                                             "if any is damaged, cut short or lost messages", many="+",
                                             metavar="FILE")
    topics: str | None = option(None, "key expression (default <prefix>/**)")
    split_size_mb: float | None = option(None, "new file every MB megabytes", flag="--split-size", metavar="MB",
                                         parse=pos_float)
    split_duration_s: float | None = option(None, "new file every S seconds", flag="--split-duration", metavar="S",
                                            parse=pos_float)
    scene: str | None = option(None, "ground-truth scene to store in the metadata (simulated sensor)")
    setup: Path | None = option(None, "a JSON file of metadata records ({name: {key: text}}) to write into each "
                                "file: the set-up's radar, quantizer, decoder, calibration, sensors and truth "
                                "(`qradar up` writes it for its recorder)", metavar="FILE.json")


@dataclass(frozen=True)
class Recover:
    """``qradar recover FILE -o NEW``."""

    file: Path = option(help="the cut-short or damaged MCAP file (read, never changed)", positional=True,
                        required=True)
    output: Path = option(help="the recovered FILE.mcap (a new file)", aliases=("-o",), required=True)


@dataclass(frozen=True)
class Recording:
    """A recording to read."""

    file: Path = option(help="a qradar MCAP recording", positional=True, required=True)


@dataclass(frozen=True)
class Recordings:
    """Recordings to read."""

    file: tuple[Path, ...] = option(help="MCAP recordings", positional=True, required=True, many="+")


@dataclass(frozen=True)
class Info:
    """``qradar info``'s check."""

    check: bool = option(False, "also read every chunk, its CRC checked, and report the damage found (as `qradar "
                         "record --verify`, status 1 when a file is not intact; takes as long as reading the file)")


def write_error_part(on_stop: str, table: str | None = "recording") -> Part:
    """--on-write-error and --write-retry (``record``, ``run``); ``on_stop``: what the command does then."""
    help = RunConfig.__dataclass_fields__["record_on_error"].metadata[META].help
    return Part(RunConfig, table, only=("record_on_error", "record_retry_s"), change={"record_on_error": {
        "help": help.replace("go on without it (the pipeline keeps running; the summary says so)", on_stop)}})


RECORD_PARTS = [
    Part(Record, only=("output", "verify", "topics", "split_size_mb", "split_duration_s", "scene", "setup")),
    node_part("duration_s"), write_error_part("exit with status 2 (a recorder with nothing left to record ends)"),
    switches(force=force_help("the -o file")),
    node_part("quiet", "parent_pid", quiet="no status line every few seconds on stderr"), INTAKE, *zenoh_parts()]


def add_commands(sub) -> None:
    add_command(sub, "record", RECORD_PARTS, cmd_record, config_json=True,
                help="record radar/** from zenoh into MCAP (or --verify recordings)")
    add_command(sub, "recover", [Part(Recover), switches(force=force_help("the -o file"))], cmd_recover,
                help="rewrite a cut-short or damaged MCAP (e.g. after SIGKILL) as a complete, indexed file of every "
                "message that reads back (damaged chunks are left out, and named)")
    add_command(sub, "replay", [Part(Recording), Part(PlayConfig, exclusive=(("rate", "fast"),),
                                                      dests={"prefix": "replay_prefix"}), *zenoh_parts()],
                cmd_replay, help="publish an MCAP recording back onto zenoh")
    add_command(sub, "info", [Part(Recordings), switches(json="one JSON object per file (what "
                                                                "qradar.open_recording(FILE).info() returns)"),
                              Part(Info)], cmd_info,
                help="what a recording holds: sensors, topics with counts and rates, time span, the radar, "
                "quantizer, decoder, calibration and truth, the losses recorded, recovery, split files",
                description="Describe MCAP recordings from their summary and metadata alone (no message is read: an "
                "hour in well under a second). A file without a summary (cut short by a kill, its summary damaged) "
                "is read whole, every chunk's CRC checked, and says so.")


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


def read_setup(path: Path) -> dict[str, dict[str, str]]:
    """``--setup``'s metadata records: a JSON object of objects of strings; a ReplayError
    naming the file otherwise."""
    try:
        data = json.loads(Path(path).read_text())
    except OSError as exc:
        raise ReplayError(f"--setup {path}: cannot read it: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise ReplayError(f"--setup {path}: not JSON: {exc}") from None
    if not (isinstance(data, dict) and all(isinstance(v, dict) and all(isinstance(x, str) for x in v.values())
                                           for v in data.values())):
        raise ReplayError(f"--setup {path}: must be a JSON object of metadata records, {{name: {{key: text}}}}")
    return data


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
    if args.setup is not None:
        meta.update(read_setup(args.setup))
    node = RecorderNode(bus_from_args(args), args.output, topics=args.topics, split_size_mb=args.split_size_mb,
                        split_duration_s=args.split_duration_s, metadata=meta, on_write_error=args.record_on_error,
                        retry_s=args.record_retry_s, intake=intake_budget(args), overwrite=args.force)
    print(f"recording {node.topics} to {args.output}; Ctrl-C to stop", file=sys.stderr, flush=True)
    install_sigterm("record")
    if args.parent_pid is not None:
        watch_parent(args.parent_pid, "record")
    status = StatusLines(node, quiet=args.quiet, announce=False).start()
    interrupted = False
    try:
        run_nodes([node], args.duration_s, node.recording_ended)  # ends early when recording stops for good
    except KeyboardInterrupt:
        interrupted = True
    finally:
        status.stop()
    totals = node.totals()
    print(json.dumps({"node": node.name, **totals, **node.summary(), **audit.finish()}), flush=True)
    if node.state is RecordingState.STOPPED:
        raise ReplayError(f"recording stopped after a write error: {node.error} (--on-write-error stop)")
    if not totals["frames_in"]:  # a recording of nothing: most often another prefix, or no router in common
        return nothing_heard("record", f"nothing came on {node.topics}: {args.output} holds no message", "recorder",
                             interrupted)  # stopped (Ctrl-C, SIGTERM) before anything came: said, not a failure
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
    damaged = []
    for i, path in enumerate(args.file):
        info = describe(path, check=args.check)
        if args.json:
            print(json.dumps(info), flush=True)
        else:
            print(("\n" if i else "") + format_info(info), flush=True)
        losses = info["losses"]
        if args.check and (info["truncated"] or losses["damage"] or losses["lost"]):
            damaged.append(f"{path} ({losses['lost'] or 0} messages lost" + (", cut short" if info["truncated"]
                                                                              else "") + ")")
    if damaged:  # as record --verify
        print(f"qradar info --check: not intact: {', '.join(damaged)}; qradar recover writes what reads back",
              file=sys.stderr, flush=True)
        return 1
    return 0


def cmd_replay(args) -> int:
    cfg = args.schema.build(PlayConfig, args)
    stop = threading.Event()
    signals = StopOnSignals(stop, "replay")  # Ctrl-C ends the replay, which still says what it published
    split = split_note(args.file, "replay")
    if split is not None:
        print(f"qradar replay: {split}", file=sys.stderr, flush=True)
    result = play(args.file, bus_from_args(args), cfg, stop=stop)
    print(json.dumps({"published": result.published, "loops": result.loops, "truncated": result.truncated,
                      "lost": result.lost, "damaged_chunks": result.damaged,
                      "seconds": round(result.seconds, 3), "interrupted": signals.interrupted is not None,
                      **audit.finish()}))
    return 0
