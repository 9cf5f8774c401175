"""Stream commands: the nodes (``source``, ``quantize``, ``localize``) and a zenoh ``router``
(``run``, the main job: :mod:`.run_command`)."""

from __future__ import annotations

import json
import sys
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

from pipeline.bus import audit
from pipeline.nodes.intake import QueueConfig, ServeConfig
from pipeline.nodes.status import StatusLines
from pipeline.nodes.transport import Audience
from pipeline.nodes.stream import LocalizeNode, LocalizerConfig, QuantizeNode, SourceNode, run_nodes
from pipeline.wire import check_sensor_id
from radar_driver.lifetime import watch_parent
from radar_driver.options import nonneg_float, option
from radar_driver.scene import DEFAULT_SCENE, SIM_RATE_HZ, resolve_scene
from radar_driver.source import SimSourceConfig, SimulatedSource

from .common import bus_from_args, install_sigterm, intake_budget, load_calibration, nothing_heard
from .parts import (CALIBRATION, GATE, INTAKE, QUEUE, SERVE, TRACKS, count_of, decoder_parts, edge_parts,
                    edge_quantizer, node_part, quantizer_of, quantizer_part, tracker_of, zenoh_parts)
from .schema import Part, add_command

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
        from replay.source import RecordingSource  # the MCAP reader: only a source of a recording loads it

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
    audience = Audience(node.transport, source_keys(node, None if args.recording is not None else cfg.sensor_ids))
    child = args.parent_pid is not None  # of `qradar up`, which reads a node that ends with 1 as one to restart
    status = StatusLines(node, quiet=args.quiet).start()
    interrupted = False
    try:
        run_nodes([node], args.duration_s, stop)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        status.stop()
        heard = audience.matched()
        audience.close()
    extra = {"late_ticks": source.late_ticks, "elapsed_s": round(source.elapsed_s, 3)} \
        if isinstance(source, SimulatedSource) else {"source": source.stats()}
    totals = node.totals()
    print(json.dumps({"node": node.name, **extra, **totals, "subscribed": heard, **noise_summary(node),
                      **audit.finish()}), flush=True)
    if totals["frames_out"] and not heard:  # frames to nobody: another --prefix, or no router in common
        topics = " or ".join(node.topics)
        return nothing_heard("source", f"nothing subscribed to {node.bus.prefix}/<sensor>/{topics}: its "
                             f"{totals['frames_out']} frames reached no node", "source", interrupted or child)
    return 0


#: a source of at most this many sensors is heard on its own keys (a node's --sensors pattern
#: may leave its ids out); more, or a recording's (its ids met as it is read): on the prefix's
#: wildcard, where any node of the prefix counts
AUDIENCE_KEYS_MAX = 64


def source_keys(node: SourceNode, sensor_ids: list[str] | None) -> list[str]:
    """The keys a source's audience is looked for on: each topic it publishes (raw, quantized)
    of each of its ``sensor_ids`` (None: not known ahead), or of any sensor."""
    topics = node.topics
    if sensor_ids is None or len(sensor_ids) > AUDIENCE_KEYS_MAX:
        return [node.bus.wildcard(t) for t in topics]
    return [node.bus.key(sid, t) for sid in sensor_ids for t in topics]


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
