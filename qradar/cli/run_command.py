"""``qradar run``, the main job: simulated or real sensors, their drivers, the quantizer and the
localizer over one zenoh session (a module of its own: the nodes' commands in :mod:`.stream` do
not load what only ``run`` uses, the recorder, the views and the run's summary)."""

from __future__ import annotations

import inspect
import sys
import threading
from dataclasses import dataclass, replace
from pathlib import Path

from pipeline.bus import audit
from pipeline.bus.session import BusConfig
from pipeline.dsp.decode import DEFAULT_ALGO, default_alpha
from pipeline.errors import ParameterError
from radar_driver.options import option
from replay.recorder import default_recording_path

from ..run import RunConfig, check_offline, print_json, remove_run_dirs, run
from ..view import ViewConfig, parse_endpoint
from . import lab
from .common import StopOnSignals, bus_from_args
from .parts import (CALIBRATION, GATE, HOSTS, TRACKS, count_of, decoder_parts, force_help, quantizer_of,
                    quantizer_part, switches, tracker_of, zenoh_parts)
from .schema import Part, add_command, values_of
from .view import Views, poses_of, web_config


@dataclass(frozen=True)
class Recording:
    """Where ``qradar run`` records: a file, or a new one in a folder; or nowhere."""

    record: Path | None = option(None, "MCAP file to record to, made new (an existing file is refused); default "
                                 "<--record-folder>/run-<date>-<time>-<ms>.mcap, -1, -2, ... when taken")
    folder: Path = option(inspect.signature(default_recording_path).parameters["folder"].default,
                          "the folder of the recordings named by date (without --record)", flag="--record-folder",
                          metavar="DIR")
    no_record: bool = option(False, "do not record")
    force: bool = option(False, force_help("--record's file"))


RUN_ALPHA_HELP = (f"dither scale (default: the --algo's best, pipeline.defaults.BEST_ALPHA: {default_alpha('cml'):g} "
                  f"with cml, its best on the off-grid chamber; {default_alpha('pbp'):g} with pbp, the paper's best "
                  f"for its noisy chamber; {default_alpha('qiht'):g} with qiht, which wants the full dither)")

#: the parts of ``qradar run``: every one of its options is a key of a lab file
RUN_PARTS = [
    Part(RunConfig, only=("sensor_specs",)), CALIBRATION,
    Part(RunConfig, only=("truth", "scene", "empty", "sensors", "duration_s", "rate_hz", "outstanding", "frames",
                          "driver_process")),
    quantizer_part(alpha_help=RUN_ALPHA_HELP, alpha=None),
    *decoder_parts("targets per frame (default: the simulated scene's count; with --sensor, the --truth file's, "
                   "else 2)", "decoder of the localizer", k_default=None),
    GATE, *TRACKS,
    switches(json="print exactly one JSON summary object on stdout"),
    Part(Recording, "recording", only=("record", "folder", "no_record", "force")),
    Part(RunConfig, "recording", only=("record_split_mb", "record_on_error", "record_retry_s")),
    Part(Views, "views"), *zenoh_parts(), HOSTS,
]


def add_commands(sub) -> None:
    add_command(
        sub, "run", RUN_PARTS, cmd_run, lab=True,
        help="the main job: K-MD2 (simulated, or real with --sensor) -> driver -> quantize -> localize over zenoh",
        description="Simulated K-MD2(s) on ptys, or real sensors on their ports (--sensor), the serial driver of "
        f"each, the 1-bit dithered quantizer and the localizer (--algo, default {DEFAULT_ALGO}) over an embedded "
        "zenoh peer; live targets beside the true positions (the simulated scene's, or --truth's), then a summary. "
        "A lab file (LAB.toml) holds any of the options as keys; the command line overrides it (docs/lab.md).")


def run_bus(args) -> BusConfig:
    """run's bus: its nodes share one in-process session, alone on purpose unless given
    endpoints (then it says if it reaches nobody, as every stand-alone command)."""
    bus = bus_from_args(args)
    return bus if bus.connect or bus.listen_endpoints() else replace(bus, alone_warning=None)


def run_alpha(args) -> float:
    """run's dither scale: --alpha, else the --algo's best (:func:`pipeline.dsp.decode.default_alpha`)."""
    return default_alpha(args.algo) if args.alpha is None else args.alpha


def run_config(args) -> RunConfig:
    """The RunConfig of ``qradar run``'s parsed options."""
    record = None if args.no_record else args.record or default_recording_path(args.folder)
    if args.secure is not None and args.mode == "client":
        raise ParameterError("qradar run --secure runs as a peer (its drivers join it over a private unix socket); "
                             "drop --mode client, and give --listen tls/... to serve other nodes")
    k, auto = count_of(args)
    if args.sensor_poses is not None and args.foxglove is None and args.web is None:
        raise ParameterError(f"--sensor-poses {args.sensor_poses} places each sensor in a view (--web, --foxglove); "
                             "this run has none, so it would do nothing: give a view or leave it out")
    foxglove = None
    if args.foxglove is not None:
        host, port = parse_endpoint(args.foxglove)
        foxglove = ViewConfig(host=host, port=port, poses=poses_of(args, args.sensor_specs))
    return args.schema.build(
        RunConfig, args, quantizer=quantizer_of(args, run_alpha(args)), k=k, auto_k=auto, algo=args.algo,
        pfa=args.pfa, bus=run_bus(args), record=record, record_new_name_if_taken=args.record is None,
        record_overwrite=args.force, calibration=args.calibration, min_range_m=args.min_range_m,
        max_range_m=args.max_range_m, tracking=tracker_of(args), foxglove=foxglove, web=web_config(args))


def cmd_run(args) -> int:
    cfg = run_config(args)  # checked before it is printed
    if args.print_config:
        check_offline(cfg)
        print(lab.dumps(args.schema.mapping(values_of(args, args.schema)),
                        "the effective lab file of `qradar run` (docs/lab.md); `qradar run FILE` runs it"), end="")
        return 0
    stop = threading.Event()
    signals = StopOnSignals(stop, "run", json_error=args.json, on_force=remove_run_dirs)
    summary = run(cfg, live=sys.stderr if args.json else sys.stdout, stop=stop)
    if signals.interrupted is not None:  # Ctrl-C or SIGTERM: the normal end of a live run
        summary.interrupted = True
    summary.audit = audit.finish().get("audit")  # under --secure: the counts
    if args.json:
        print_json(summary)
    else:
        print(summary.format())
    if summary.produced_nothing and not summary.interrupted:
        print(f"qradar run: error: {summary.nothing_reason()}", file=sys.stderr, flush=True)
        return 1
    if summary.sensors_lost and not summary.interrupted:  # the run's data end where its sensor went
        print(f"qradar run: error: {', '.join(summary.sensors_lost)} lost and not back at the end of the run: its "
              "frames stop there (the lines above say since when and why)", file=sys.stderr, flush=True)
        return 1
    return 0
