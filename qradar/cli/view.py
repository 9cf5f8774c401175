"""``qradar view``: the live stream in Foxglove (a Foxglove WebSocket server, qradar.view)
or, with ``--web``, in a web page (qradar.web), live or from a recording."""

from __future__ import annotations

import argparse
import json
import secrets
import sys
import time
from dataclasses import replace
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


def endpoint_arg(text: str) -> str:
    """``[HOST:]PORT``, checked; parsed again once the default host is known."""
    try:
        parse_endpoint(text)
    except ParameterError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def port_arg(text: str) -> int:
    v = int(text)
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r} must be a TCP port in [0, 65535] (0: any free port)")
    return v


def add_commands(sub) -> None:
    p = sub.add_parser("view", help="the live stream in Foxglove (WebSocket) or, with --web, in a web page: targets, "
                       "range profiles, health",
                       description="Subscribes <prefix>/*/{targets,tracks,quantized,health} and serves them over the "
                       "Foxglove WebSocket protocol: targets as foxglove.PointCloud in the frame radar_<sensor>, "
                       "range profiles and health as JSON. Open it in Foxglove with 'Open connection' -> "
                       f"'Foxglove WebSocket', then load the layout {LAYOUT}. With --web, serves a web page "
                       "instead (nothing to install: open its URL in a browser), of the live stream or of a "
                       "--recording with play, pause and seek.")
    p.add_argument("--host", default="127.0.0.1",
                   help="address the server binds (default 127.0.0.1: this host only; 0.0.0.0: every interface)")
    p.add_argument("--port", type=port_arg, default=8765, help="Foxglove's TCP port (default 8765; 0: any free port)")
    web_options(p)
    p.add_argument("--recording", type=Path, default=None, metavar="REC.mcap",
                   help="with --web: show this recording (play, pause and seek on the page) instead of the live "
                   "stream; no zenoh session is opened")
    p.add_argument("--truth", default=None, metavar="SCENE.toml",
                   help="with --web: the true positions to show beside the targets, a scene file or a packaged "
                   "scene's name (a recording's own truth is shown without it)")
    p.add_argument("--profile-rate", type=nonneg_float, default=None, metavar="HZ",
                   help="range profiles per second and sensor at most (default 2 for Foxglove, 20 for --web; 0: none)")
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


def web_options(p) -> None:
    """--web [HOST:]PORT and --web-token-file (view and run)."""
    p.add_argument("--web", type=endpoint_arg, default=None, metavar="[HOST:]PORT",
                   help="serve the live view as a web page on HOST:PORT (host default 127.0.0.1 on run, --host on "
                   "view; 0: any free port); nothing listens without it. Under --secure the page needs a token, "
                   "generated and printed in its URL unless --web-token-file gives it")
    p.add_argument("--web-token-file", type=Path, default=None, metavar="FILE",
                   help="the web page's token (16-256 characters of [A-Za-z0-9_~.-], the file's first line): the "
                   "page then needs ?token=... in its URL, with or without --secure")


def web_config(args, default_host: str = "127.0.0.1"):
    """The ``--web`` view's config from the parsed options (None without --web): its host
    and port, token (``--web-token-file``'s, else a new one under ``--secure``, else none),
    poses and profile rate."""
    if args.web is None:
        if getattr(args, "web_token_file", None) is not None:
            raise ParameterError("--web-token-file is the token of the --web page: give --web [HOST:]PORT too")
        return None
    from ..web import WebConfig

    host, port = parse_endpoint(args.web, default_host)
    token = None
    if args.web_token_file is not None:
        try:
            lines = args.web_token_file.read_text().splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            raise ParameterError(f"--web-token-file {args.web_token_file}: cannot read ({exc})") from None
        token = lines[0].strip() if lines else ""
    elif getattr(args, "secure", None) is not None:
        token = secrets.token_urlsafe(24)
    try:
        cfg = WebConfig(host=host, port=port, token=token,
                        poses=load_poses(args.sensor_poses) if args.sensor_poses is not None else {})
    except ParameterError as exc:
        where = f" (--web-token-file {args.web_token_file})" if args.web_token_file is not None else ""
        raise ParameterError(f"{exc}{where}") from None
    rate = getattr(args, "profile_rate", None)
    return cfg if rate is None else replace(cfg, profile_rate_hz=rate)


def cmd_view(args) -> int:
    if args.web is None:
        for option, value in (("--recording", args.recording), ("--truth", args.truth),
                              ("--web-token-file", args.web_token_file)):
            if value is not None:
                raise ParameterError(f"{option} is for the web page: give --web [HOST:]PORT too")
        cfg = ViewConfig(host=args.host, port=args.port, queue_size=args.queue,
                         poses=load_poses(args.sensor_poses) if args.sensor_poses is not None else {},
                         **({} if args.profile_rate is None else {"profile_rate_hz": args.profile_rate}))
        view = FoxgloveView(bus_from_args(args), cfg, intake=intake_budget(args))
        hint = (f"Foxglove WebSocket server on {{url}}; in Foxglove: Open connection -> Foxglove WebSocket -> "
                f"{{url}}, then load the layout {LAYOUT}")
    else:
        view = web_view(args)
        hint = "web page on {url} (open it in a browser)"
    install_sigterm("view")
    view.start()  # a busy port or an unknown host: ViewError, one line
    try:
        print(f"qradar view: {hint.format(url=view.url)}; Ctrl-C to stop", file=sys.stderr, flush=True)
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


def web_view(args):
    """``view --web``: of the live stream (its bus, the --truth scene), or of --recording."""
    from ..run import load_truth
    from ..web import WebView

    cfg = replace(web_config(args, args.host), queue_size=args.queue)
    truth = load_truth(args.truth) if args.truth is not None else None
    if args.recording is not None:
        view = WebView.of_recording(args.recording, cfg)
        view.truth = truth or view.truth
        return view
    return WebView(bus_from_args(args), cfg, truth=truth, intake=intake_budget(args))
