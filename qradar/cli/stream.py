"""Stream commands: the nodes (``source``, ``quantize``, ``localize``), a zenoh
``router``, and ``run``, the main job."""

from __future__ import annotations

import json
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

from pipeline.bus import audit
from pipeline.bus.session import BusConfig
from pipeline.dsp.decode import DEFAULT_ALGO, DEFAULT_ALPHA, default_alpha
from pipeline.errors import ParameterError
from pipeline.nodes.intake import INPUT_MODES
from pipeline.nodes.status import STATUS_PERIOD_S, StatusLines
from pipeline.nodes.stream import DEFAULT_FULL_SEARCH_EVERY, LocalizeNode, LocalizerConfig, QuantizeNode, SourceNode, run_nodes
from pipeline.wire import check_sensor_id
from radar_driver.scene import resolve_scene
from radar_driver.source import SEND_MODES, SimSourceConfig, SimulatedSource
from replay.recorder import default_recording_path
from replay.source import RecordingSource

from ..view import load_poses
from ..run import RunConfig, print_json, remove_run_dirs, run
from .common import (
    force_option,
    ALPHA_HELP,
    algo_option,
    bus_from_args,
    count_from_args,
    count_options,
    bus_options,
    edge_quantizer,
    edge_quantizer_options,
    gate_options,
    install_sigterm,
    intake_budget,
    intake_options,
    nonneg_float,
    nonneg_int,
    pos_float,
    pos_int,
    quantizer_config,
    quantizer_options,
    sensor_pattern_arg,
    shard_arg,
    StopOnSignals,
    track_options,
    tracker_config,
    calibration_option,
    load_calibration,
)
from .record import write_error_options
from .view import foxglove_arg, poses_option, web_config, web_options


def add_commands(sub) -> None:
    p = sub.add_parser("quantize", help="node: radar/*/raw -> dithered b-bit quantization -> radar/<sensor>/quantized")
    quantizer_options(p, DEFAULT_ALPHA, ALPHA_HELP)
    calibration_option(p)
    queue_options(p)
    serve_options(p)
    p.add_argument("--duration", type=float, default=None, help="stop after S seconds (default: Ctrl-C)")
    quiet_option(p)
    bus_options(p)
    p.set_defaults(func=cmd_quantize)

    p = sub.add_parser("localize", help="node: radar/*/quantized (or raw) -> a decoder -> radar/<sensor>/targets")
    count_options(p, 2, "targets per frame (default 2)")
    algo_option(p, "cml: continuous ranges (the most accurate off the range grid); pbp: the paper's; qiht: "
                "dither-aware on the range grid (needs dithered frames)")
    gate_options(p)
    p.add_argument("--fallback-pbp", action="store_true", help="with qiht: decode frames without dither by PBP")
    p.add_argument("--source", choices=["quantized", "raw"], default="quantized",
                   help="raw = the full-resolution baseline")
    track_options(p)
    p.add_argument("--full-search-every", type=pos_int, default=DEFAULT_FULL_SEARCH_EVERY,
                   help="cml: start each sensor's frame from its last targets (warm start) and search from scratch "
                        f"every N frames (and when the fit no longer explains the codes); 1 = always (default "
                        f"{DEFAULT_FULL_SEARCH_EVERY})")
    queue_options(p)
    serve_options(p)
    p.add_argument("--duration", type=float, default=None, help="stop after S seconds (default: Ctrl-C)")
    quiet_option(p)
    bus_options(p)
    p.set_defaults(func=cmd_localize)

    p = sub.add_parser("source", help="node: in-process simulated sensors (or a recording) -> radar/<id>/raw",
                       description="Simulated sensors that publish raw frames of a scene directly, bypassing "
                       "the serial protocol: for benchmarks and many-sensor set-ups. With --recording, the raw "
                       "frames of an MCAP file instead.")
    p.add_argument("--scene", default="chamber", help="scene file or packaged name")
    p.add_argument("--sensors", type=pos_int, default=1, help="simulated sensors at once")
    p.add_argument("--rate", type=nonneg_float, default=None,
                   help="frames per second per sensor (default 20; 0 = as fast as read); with --recording, "
                   "the speed factor of the recorded pace (default 1; 0 = as fast as read)")
    p.add_argument("--id-prefix", default="sim", help="sensor ids are <prefix>0, <prefix>1, ...")
    p.add_argument("--frames", type=pos_int, default=None,
                   help="frames per sensor, then stop (with --recording: frames in all)")
    p.add_argument("--seed", type=nonneg_int, default=0, help="noise seed (sensor i draws as a K-MD2 of seed + i)")
    p.add_argument("--send", choices=list(SEND_MODES), default="burst",
                   help="burst: every sensor's frame at the start of each period (sensors on one clock); spread: "
                   "the sensors' send times spread evenly over the period, in groups 2 ms apart (independent sensors)")
    edge_quantizer_options(p, "--quantized")
    p.add_argument("--recording", type=Path, default=None,
                   help="publish the raw frames of this MCAP file (at --rate times the recorded pace) instead")
    p.add_argument("--duration", type=float, default=None, help="stop after S seconds (default: Ctrl-C)")
    quiet_option(p)
    bus_options(p)
    p.set_defaults(func=cmd_source)

    p = sub.add_parser("router", help="a zenoh router for multi-host set-ups",
                       description="A zenoh router the nodes join as clients (--mode client --connect ...). It "
                       f"listens on --listen, else on the --zenoh-config file's listen/endpoints, else on "
                       f"{ROUTER_LISTEN} ({ROUTER_LISTEN_SECURE} with --secure).")
    p.add_argument("--duration", type=float, default=None, help="stop after S seconds (default: Ctrl-C)")
    bus_options(p, modes=("router",))
    p.set_defaults(func=cmd_router)

    p = sub.add_parser("run", help="the main job: K-MD2 (simulated, or real with --sensor) -> driver -> quantize -> "
                       "localize over zenoh",
                       description="Simulated K-MD2(s) on ptys, or real sensors on their ports (--sensor), the serial "
                       f"driver of each, the 1-bit dithered quantizer and the localizer (--algo, default {DEFAULT_ALGO}) "
                       "over an embedded zenoh peer; live targets beside the true positions (the simulated scene's, "
                       "or --truth's), then a summary.")
    p.add_argument("--sensor", dest="sensor_specs", action="append", default=[], metavar="URL,id=NAME[,KEY=VALUE]",
                   help="a real sensor instead of the simulated ones (repeatable, one each): a pyserial URL (a device "
                   "path, socket://HOST:PORT, rfc2217://HOST:PORT) or auto (the one K-MD2 that answers on this "
                   "host's serial adapters, probed with INIT and GBYE as `qradar ports --probe` does), then its id "
                   "(required) and the driver's "
                   "options: profile=NAME|FILE (default kmd2-blocks), baud=B (default 2000000; a socket:// link stays "
                   "at 115200), ramps=R (default 2), chirp-select=first|stride; e.g. "
                   "/dev/ttyUSB0,id=kmd2-0,profile=kmd2-blocks. Not with --scene, --sensors, --rate")
    calibration_option(p)
    p.add_argument("--truth", default=None, metavar="SCENE.toml",
                   help="a scene file whose targets are the reflectors' true (measured) positions: the live lines and "
                   "the summary give the position errors against them (only the targets' ranges and angles count). "
                   "Default: the simulated scene; with --sensor, no error")
    p.add_argument("--scene", default=None, help="the simulated sensors' scene: file or packaged name (default chamber)")
    p.add_argument("--empty", action="store_true",
                   help="the scene without its targets: the empty chamber, front end (DC, leakage) and noise only "
                   "(simulated sensors; for `qradar calibrate --empty`)")
    p.add_argument("--sensors", type=pos_int, default=None, help="simulated sensors at once (default 1)")
    p.add_argument("--duration", type=float, default=15.0, help="seconds (default 15); Ctrl-C or SIGTERM ends the run earlier, normally: the same summary (with \"interrupted\": true) and status 0; a second one while it stops exits at once with 130")
    p.add_argument("--rate", type=float, default=None, help="frames per second per simulated sensor (default 20)")
    p.add_argument("--outstanding", type=int, choices=(1, 2), default=None,
                   help="GNFD requests each driver keeps in flight: 2 lets the sensor hold one while its driver is "
                   "late on a busy host (the simulator queues a second GNFD; a real K-MD2 is assumed to). Default 2 "
                   "with simulated sensors, 1 with --sensor")
    quantizer_options(p, None, f"dither scale (default: the --algo's best, pipeline.defaults.BEST_ALPHA: "
                      f"{default_alpha('cml'):g} with cml, its best on the off-grid chamber; {default_alpha('pbp'):g} "
                      f"with pbp, the paper's best for its noisy chamber; {default_alpha('qiht'):g} with qiht, which "
                      "wants the full dither)")
    count_options(p, None, "targets per frame (default: the simulated scene's count; with --sensor, the --truth "
                  "file's, else 2)")
    algo_option(p, "decoder of the localizer")
    gate_options(p)
    track_options(p)
    p.add_argument("--json", action="store_true", help="print exactly one JSON summary object on stdout")
    p.add_argument("--record", type=Path, default=None,
                   help="MCAP file to record to, made new (an existing file is refused); default recordings/run-<date>-<time>-<ms>.mcap, -1, -2, ... when taken")
    p.add_argument("--no-record", action="store_true", help="do not record")
    force_option(p, "--record's file")
    p.add_argument("--split-size", type=pos_float, default=None, metavar="MB",
                   help="record into a new file every MB megabytes (NAME_0001.mcap, ...): the MCAP writer keeps "
                   "each chunk's index in memory until its file ends: at most 0.7 KB a chunk (one a second, or each MB) "
                   "plus 70 B for each channel in it")
    write_error_options(p, "go on without it (the pipeline keeps running; the summary says so)")
    p.add_argument("--frames", type=pos_int, default=None, help="stop after N frames per sensor")
    p.add_argument("--driver-in-process", action="store_true",
                   help="run the serial drivers as threads of this process (default: a process each)")
    p.add_argument("--foxglove", type=foxglove_arg, default=None, metavar="[HOST:]PORT",
                   help="also serve the live stream to Foxglove (as `qradar view`) on HOST:PORT (host default "
                   "127.0.0.1)")
    poses_option(p)
    web_options(p)
    bus_options(p)
    p.set_defaults(func=cmd_run)


def queue_options(p) -> None:
    """The input queue and per-sensor state of a processing node."""
    g = p.add_argument_group("input queue")
    g.add_argument("--queue", type=pos_int, default=8192, help="frames waiting, in all (the bytes bound --queue-mb holds too)")
    g.add_argument("--sensor-queue", type=pos_int, default=128,
                   help="frames waiting of one sensor (a flooding sensor loses its own frames beyond this)")
    g.add_argument("--queue-mb", type=pos_float, default=64.0, help="payload megabytes waiting, in all")
    g.add_argument("--sensor-expiry", type=pos_float, default=60.0,
                   help="forget a sensor silent this many seconds (its counters stay in the totals)")
    g.add_argument("--batch-linger", type=nonneg_float, default=None, metavar="MS",
                   help="once a frame waits, wait up to MS ms for a full batch while frames keep coming (default 2): "
                   "longer saves CPU on a busy host (a call costs ~1 ms however few its frames) but adds latency")
    g.add_argument("--input", choices=INPUT_MODES, default="callback",
                   help="callback: zenoh's callback thread hands over each message (default); pull: the worker "
                   "drains zenoh's FIFO of up to 1024 messages itself, saving the GIL changing hands per message "
                   "(at 450 sensors 69 %% of a core against 81 %%), but a full FIFO makes zenoh wait: for a "
                   "node with its process to itself")
    intake_options(p)


def serve_options(p) -> None:
    """Which sensors a processing node serves: by key pattern and/or by shard."""
    g = p.add_argument_group("sensors served", "several processes (on one host or many) share the sensors")
    g.add_argument("--sensors", type=sensor_pattern_arg, default="*", metavar="PATTERN",
                   help="only the sensors whose id matches this key chunk, e.g. 'b1*' (zenoh filters the others "
                   "before they reach this process; default *)")
    g.add_argument("--shard", type=shard_arg, default=None, metavar="I/N",
                   help="only the sensors with crc32(id) mod N == I: N processes with 0/N .. N-1/N serve each "
                   "sensor exactly once (the others' frames still arrive and are dropped unread)")


def queue_kwargs(args) -> dict:
    return {"queue_size": args.queue, "sensor_queue_size": min(args.sensor_queue, args.queue),
            "queue_bytes": int(args.queue_mb * 1e6), "sensor_expiry_s": args.sensor_expiry,
            "sensors": args.sensors, "shard": args.shard,
            "batch_linger_s": None if args.batch_linger is None else args.batch_linger / 1e3,
            "input_mode": args.input, "intake": intake_budget(args)}



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


def quiet_option(p) -> None:
    p.add_argument("--quiet", action="store_true",
                   help=f"no start line and no status line every {STATUS_PERIOD_S:g} s on stderr (rates, sensors, "
                   "losses, the last targets)")


def noise_summary(node) -> dict:
    """With --alpha auto: ``{"noise": {sensor: {"noise_sigma", "noise_frames", "alpha"}}}``
    for a command's summary (the sensors not expired), else {}."""
    noise = getattr(node, "noise", None)
    return {} if noise is None else {"noise": noise.snapshot()}


def cmd_quantize(args) -> int:
    return serve(QuantizeNode(bus_from_args(args), quantizer_config(args), calibration=load_calibration(args.calibration),
                              **queue_kwargs(args)), args.duration, quiet=args.quiet)


def cmd_localize(args) -> int:
    k, auto = count_from_args(args)
    cfg = LocalizerConfig(k=k, algo=args.algo, source=args.source, fallback_pbp=args.fallback_pbp, auto_k=auto,
                          pfa=args.pfa, min_range_m=args.min_range_m, max_range_m=args.max_range_m,
                          full_search_every=args.full_search_every)
    return serve(LocalizeNode(bus_from_args(args), cfg, tracking=tracker_config(args), **queue_kwargs(args)),
                 args.duration, quiet=args.quiet)


def cmd_source(args) -> int:
    if args.recording is not None:
        rate = 1.0 if args.rate is None else args.rate
        source = RecordingSource(args.recording, rate=rate or None)
        limit = args.frames
    else:
        cfg = SimSourceConfig(resolve_scene(args.scene), sensors=args.sensors, id_prefix=args.id_prefix,
                              rate_hz=20.0 if args.rate is None else args.rate, seed=args.seed, frames=args.frames,
                              send=args.send)
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
    status = StatusLines(node, quiet=args.quiet).start()
    try:
        run_nodes([node], args.duration, stop)
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
    bus = replace(bus_from_args(args), alone_warning=None)  # a router waiting for its clients is normal
    if not bus.listen_endpoints():  # neither --listen nor the config file says where
        bus = replace(bus, listen=(ROUTER_LISTEN_SECURE if bus.secure is not None else ROUTER_LISTEN,))
    install_sigterm("router")
    session = None
    try:
        session = bus.open()  # (a router takes a moment to open: a SIGTERM meanwhile is a clean stop too)
        secure = "" if bus.secure is None else f" (mTLS and access control as {bus.secure.identity!r})"
        print(f"zenoh router {session.zid()} listening on {bus.listen_endpoints()}{secure}; Ctrl-C to stop",
              flush=True)
        deadline = None if args.duration is None else time.monotonic() + args.duration
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


def cmd_run(args) -> int:
    record = None
    if not args.no_record:
        record = args.record or default_recording_path()
    if args.secure is not None and args.mode == "client":
        raise ParameterError("qradar run --secure runs as a peer (its drivers join it over a private unix socket); "
                             "drop --mode client, and give --listen tls/... to serve other nodes")
    alpha = run_alpha(args)
    k, auto = count_from_args(args)
    cfg = RunConfig(scene=args.scene, sensors=args.sensors, duration_s=args.duration, rate_hz=args.rate,
                    quantizer=quantizer_config(args, alpha), k=k, algo=args.algo, bus=run_bus(args),
                    record=record, frames=args.frames, auto_k=auto, pfa=args.pfa,
                    foxglove=args.foxglove if args.foxglove is None or args.sensor_poses is None else replace(
                        args.foxglove, poses=load_poses(args.sensor_poses)), driver_process=not args.driver_in_process,
                    record_on_error=args.on_write_error, record_retry_s=args.write_retry,
                    record_split_mb=args.split_size, record_new_name_if_taken=args.record is None,
                    record_overwrite=args.force,
                    outstanding=args.outstanding, sensor_specs=tuple(args.sensor_specs), truth=args.truth,
                    calibration=args.calibration, empty=args.empty, min_range_m=args.min_range_m,
                    max_range_m=args.max_range_m, tracking=tracker_config(args), web=web_config(args))
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
    return 0
