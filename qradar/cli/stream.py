"""Stream commands: the nodes (``source``, ``quantize``, ``localize``), a zenoh
``router``, and ``run``, the main job."""

from __future__ import annotations

import inspect
import json
import sys
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

from pipeline.bus import audit
from pipeline.bus.session import BusConfig
from pipeline.dsp.decode import DEFAULT_ALGO, default_alpha
from pipeline.errors import ParameterError
from pipeline.nodes.intake import QueueConfig, ServeConfig
from pipeline.nodes.status import StatusLines
from pipeline.nodes.stream import LocalizeNode, LocalizerConfig, QuantizeNode, SourceNode, run_nodes
from pipeline.wire import check_sensor_id
from radar_driver.options import nonneg_float, option
from radar_driver.scene import DEFAULT_SCENE, SIM_RATE_HZ, resolve_scene
from radar_driver.source import SimSourceConfig, SimulatedSource
from replay.recorder import default_recording_path
from replay.source import RecordingSource

from ..run import RunConfig, print_json, remove_run_dirs, run
from ..view import ViewConfig, parse_endpoint
from . import lab
from .common import StopOnSignals, bus_from_args, install_sigterm, intake_budget, load_calibration, watch_parent
from .parts import (CALIBRATION, GATE, HOSTS, INTAKE, QUEUE, SERVE, TRACKS, count_of, decoder_parts, edge_parts,
                    edge_quantizer, force_help, node_part, quantizer_of, quantizer_part, switches, tracker_of,
                    zenoh_parts)
from .schema import Part, add_command, values_of
from .view import Views, poses_of, web_config

NODE_HELP = {
    "quantize": "node: radar/*/raw -> dithered b-bit quantization -> radar/<sensor>/quantized",
    "localize": "node: radar/*/quantized (or raw) -> a decoder -> radar/<sensor>/targets",
    "source": "node: in-process simulated sensors (or a recording) -> radar/<id>/raw",
}


@dataclass(frozen=True)
class Source:
    """What ``qradar source`` publishes: a scene's simulated sensors, or a recording."""

    scene: str = option(DEFAULT_SCENE, "scene file or packaged name")
    rate: float | None = option(None, f"frames per second per sensor (default {SIM_RATE_HZ:g}; 0 = as fast as read); "
                                "with --recording, the speed factor of the recorded pace (default 1; 0 = as fast as "
                                "read)", parse=nonneg_float)
    recording: Path | None = option(None, "publish the raw frames of this MCAP file (at --rate times the recorded "
                                    "pace) instead")


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


QUANTIZE_PARTS = [quantizer_part(), CALIBRATION, QUEUE, INTAKE, SERVE, node_part(), *zenoh_parts()]
LOCALIZE_PARTS = [
    *decoder_parts(algo_help="cml: continuous ranges (the most accurate off the range grid); pbp: the paper's; "
                   "qiht: dither-aware on the range grid (needs dithered frames)",
                   extra=("fallback_pbp", "source", "full_search_every", "uncertainty")),
    GATE, *TRACKS, QUEUE, INTAKE, SERVE, node_part(), *zenoh_parts()]
SOURCE_PARTS = [Part(Source, only=("scene",)), Part(SimSourceConfig, "source"), Part(Source, only=("rate",)),
                *edge_parts("--quantized"), Part(Source, only=("recording",)), node_part(), *zenoh_parts()]
ROUTER_PARTS = [node_part("duration_s", "parent_pid"), *zenoh_parts(modes=("router",))]


def add_commands(sub) -> None:
    add_command(sub, "quantize", QUANTIZE_PARTS, cmd_quantize, config_json=True, help=NODE_HELP["quantize"])
    add_command(sub, "localize", LOCALIZE_PARTS, cmd_localize, config_json=True, help=NODE_HELP["localize"])
    add_command(sub, "source", SOURCE_PARTS, cmd_source, config_json=True, help=NODE_HELP["source"],
                description="Simulated sensors that publish raw frames of a scene directly, bypassing the serial "
                "protocol: for benchmarks and many-sensor set-ups. With --recording, the raw frames of an MCAP file "
                "instead.")
    add_command(sub, "router", ROUTER_PARTS, cmd_router, config_json=True, help="a zenoh router for multi-host set-ups",
                description="A zenoh router the nodes join as clients (--mode client --connect ...). It listens on "
                f"--listen, else on the --zenoh-config file's listen/endpoints, else on {ROUTER_LISTEN} "
                f"({ROUTER_LISTEN_SECURE} with --secure).")
    add_command(
        sub, "run", RUN_PARTS, cmd_run, lab=True,
        help="the main job: K-MD2 (simulated, or real with --sensor) -> driver -> quantize -> localize over zenoh",
        description="Simulated K-MD2(s) on ptys, or real sensors on their ports (--sensor), the serial driver of "
        f"each, the 1-bit dithered quantizer and the localizer (--algo, default {DEFAULT_ALGO}) over an embedded "
        "zenoh peer; live targets beside the true positions (the simulated scene's, or --truth's), then a summary. "
        "A lab file (LAB.toml) holds any of the options as keys; the command line overrides it (docs/lab.md).")


def serve(node, duration: float | None, stop: threading.Event | None = None, quiet: bool = False) -> int:
    """Run one node until ``duration``, ``stop`` or Ctrl-C, saying where it listens and what
    it reads and writes, then a status line every few seconds (unless ``quiet``, on stderr);
    print its totals as JSON."""
    install_sigterm(node.name)
    status = StatusLines(node, quiet=quiet).start()
    try:
        run_nodes([node], duration, stop)
    except KeyboardInterrupt:
        pass
    finally:
        status.stop()
    print(json.dumps({"node": node.name, **node.totals(), **noise_summary(node), **audit.finish()}), flush=True)
    return 0


def noise_summary(node) -> dict:
    """With --alpha auto: ``{"noise": {sensor: {"noise_sigma", "noise_frames", "alpha"}}}``
    for a command's summary (the sensors not expired), else {}."""
    noise = getattr(node, "noise", None)
    return {} if noise is None else {"noise": noise.snapshot()}


def node_kwargs(args) -> dict:
    """The input queue, sensors served and intake budgets of a processing node."""
    build = args.schema.build
    return {**build(QueueConfig, args).node_kwargs(), **build(ServeConfig, args).node_kwargs(),
            "intake": intake_budget(args)}


def watch(args, name: str) -> None:
    """``--parent-pid``: this node stops once that process is gone (a child of ``up``)."""
    if args.parent_pid is not None:
        watch_parent(args.parent_pid, name)


def cmd_quantize(args) -> int:
    node = QuantizeNode(bus_from_args(args), quantizer_of(args), calibration=load_calibration(args.calibration),
                        **node_kwargs(args))
    watch(args, "quantize")
    return serve(node, args.duration_s, quiet=args.quiet)


def cmd_localize(args) -> int:
    k, auto = count_of(args)
    cfg = args.schema.build(LocalizerConfig, args, k=k, auto_k=auto)
    node = LocalizeNode(bus_from_args(args), cfg, tracking=tracker_of(args), **node_kwargs(args))
    watch(args, "localize")
    return serve(node, args.duration_s, quiet=args.quiet)


def cmd_source(args) -> int:
    if args.recording is not None:
        rate = 1.0 if args.rate is None else args.rate
        source = RecordingSource(args.recording, rate=rate or None)
        limit = args.frames
    else:
        cfg = args.schema.build(SimSourceConfig, args, scene=resolve_scene(args.scene),
                                rate_hz=SIM_RATE_HZ if args.rate is None else args.rate)
        for sid in cfg.sensor_ids:
            check_sensor_id(sid)
        source = SimulatedSource(cfg)
        limit = None
    quantizer, raw_every = edge_quantizer(args)
    calibration = load_calibration(args.calibration, [] if args.recording is not None else cfg.sensor_ids)
    node = SourceNode(bus_from_args(args), source, frames=limit, quantizer=quantizer, raw_every=raw_every,
                      calibration=calibration)
    stop = threading.Event()
    threading.Thread(target=lambda: (node.done.wait(), stop.set()), daemon=True).start()
    install_sigterm("source")
    watch(args, "source")
    status = StatusLines(node, quiet=args.quiet).start()
    try:
        run_nodes([node], args.duration_s, stop)
    except KeyboardInterrupt:
        pass
    finally:
        status.stop()
    extra = {"late_ticks": source.late_ticks, "elapsed_s": round(source.elapsed_s, 3)} \
        if isinstance(source, SimulatedSource) else {"source": source.stats()}
    print(json.dumps({"node": node.name, **extra, **node.totals(), **noise_summary(node), **audit.finish()}),
          flush=True)
    return 0


ROUTER_LISTEN = "tcp/0.0.0.0:7447"
ROUTER_LISTEN_SECURE = "tls/0.0.0.0:7447"


def cmd_router(args) -> int:
    bus = replace(bus_from_args(args, mode="router"), alone_warning=None)  # a router waiting for its clients is normal
    if not bus.listen_endpoints():  # neither --listen nor the config file says where
        bus = replace(bus, listen=(ROUTER_LISTEN_SECURE if bus.secure is not None else ROUTER_LISTEN,))
    install_sigterm("router")
    watch(args, "router")
    session = None
    try:
        session = bus.open()  # (a router takes a moment to open: a SIGTERM meanwhile is a clean stop too)
        secure = "" if bus.secure is None else f" (mTLS and access control as {bus.secure.identity!r})"
        print(f"zenoh router {session.zid()} listening on {bus.listen_endpoints()}{secure}; Ctrl-C to stop",
              flush=True)
        deadline = None if args.duration_s is None else time.monotonic() + args.duration_s
        while deadline is None or time.monotonic() < deadline:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        if session is not None:
            session.close()
    final = audit.stop()  # under --secure: the last summaries on stderr, then the counts
    if final is not None:
        print(f"qradar router: audit: {audit.format_counts(final)} in all", file=sys.stderr, flush=True)
        print(json.dumps({"node": "router", "audit": final}), flush=True)
    return 0


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
    return 0
