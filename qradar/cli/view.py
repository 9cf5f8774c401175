"""``qradar view``: the live stream in Foxglove (a Foxglove WebSocket server, qradar.view)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from pipeline.bus import audit
from pipeline.errors import ParameterError, PipelineError

from ..view import FoxgloveView, ViewConfig, load_poses, parse_endpoint
from .common import bus_from_args, bus_options, install_sigterm, intake_budget, intake_options, nonneg_float, pos_int

LAYOUT = "docs/foxglove-layout.json"


def foxglove_arg(text: str) -> ViewConfig:
    """``[HOST:]PORT`` (host default 127.0.0.1) for ``run --foxglove``: the view's config."""
    try:
        host, port = parse_endpoint(text)
        return ViewConfig(host=host, port=port)
    except ParameterError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def port_arg(text: str) -> int:
    v = int(text)
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r} must be a TCP port in [0, 65535] (0: any free port)")
    return v


def add_commands(sub) -> None:
    p = sub.add_parser("view", help="serve the live stream to Foxglove (WebSocket): targets, range profiles, health",
                       description="Subscribes <prefix>/*/{targets,quantized,health} and serves them over the "
                       "Foxglove WebSocket protocol: targets as foxglove.PointCloud in the frame radar_<sensor>, "
                       "range profiles and health as JSON. Open it in Foxglove with 'Open connection' -> "
                       f"'Foxglove WebSocket', then load the layout {LAYOUT}.")
    p.add_argument("--host", default="127.0.0.1",
                   help="address the server binds (default 127.0.0.1: this host only; 0.0.0.0: every interface)")
    p.add_argument("--port", type=port_arg, default=8765, help="TCP port (default 8765; 0: any free port)")
    p.add_argument("--profile-rate", type=nonneg_float, default=2.0, metavar="HZ",
                   help="range profiles per second and sensor at most (default 2; 0: none)")
    p.add_argument("--queue", type=pos_int, default=256, help="bounded input queue (messages)")
    poses_option(p)
    p.add_argument("--duration", type=float, default=None, help="stop after S seconds (default: Ctrl-C)")
    intake_options(p)
    bus_options(p)
    p.set_defaults(func=cmd_view)


def poses_option(p) -> None:
    p.add_argument("--sensor-poses", type=Path, default=None, metavar="SENSORS.toml",
                   help="each sensor's pose in the world, a TOML table per sensor id with x_m, y_m and yaw_deg "
                   "(the frame radar_<id> is placed there; default: every sensor at the origin)")


def cmd_view(args) -> int:
    cfg = ViewConfig(host=args.host, port=args.port, profile_rate_hz=args.profile_rate, queue_size=args.queue,
                     poses=load_poses(args.sensor_poses) if args.sensor_poses is not None else {})
    view = FoxgloveView(bus_from_args(args), cfg, intake=intake_budget(args))
    install_sigterm("view")
    view.start()  # a busy port or an unknown host: ViewError, one line
    try:
        print(f"qradar view: Foxglove WebSocket server on {view.url}; in Foxglove: Open connection -> Foxglove "
              f"WebSocket -> {view.url}, then load the layout {LAYOUT}; Ctrl-C to stop", file=sys.stderr, flush=True)
        deadline = None if args.duration is None else time.monotonic() + args.duration
        while deadline is None or time.monotonic() < deadline:
            time.sleep(0.1)
            if view.errors:  # the worker died: say why and stop
                raise PipelineError(f"node view failed: {view.errors[0]!r}")
    except KeyboardInterrupt:
        pass
    finally:
        view.stop()
    print(json.dumps({"node": view.name, **view.summary(), **audit.finish()}), flush=True)
    return 0
