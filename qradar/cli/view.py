"""``qradar view``: the live stream in Foxglove (a Foxglove WebSocket server, qradar.view)
or, with ``--web``, in a web page (qradar.web), live or from a recording."""

from __future__ import annotations

import json
import secrets
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

from pipeline.bus import audit
from pipeline.errors import ParameterError, PipelineError
from radar_driver.lifetime import watch_parent
from radar_driver.options import nonneg_float, option

from ..view import FoxgloveView, ViewConfig, load_poses, parse_endpoint
from .common import bus_from_args, install_sigterm, intake_budget
from .parts import INTAKE, node_part, zenoh_parts
from .schema import Part, add_command

LAYOUT = "docs/foxglove-layout.json"


def endpoint(text: str) -> str:
    """``[HOST:]PORT``, checked; parsed again once the default host is known."""
    parse_endpoint(text)
    return text


@dataclass(frozen=True)
class Views:
    """The live views of a run (``[views]``) and what ``qradar view`` shares with them."""

    foxglove: str | None = option(None, "also serve the live stream to Foxglove (as `qradar view`) on HOST:PORT (host "
                                  "default 127.0.0.1)", metavar="[HOST:]PORT", parse=endpoint)
    web: str | None = option(None, "serve the live view as a web page on HOST:PORT (host default 127.0.0.1 on run, "
                             "--host on view; 0: any free port); nothing listens without it. Under --secure the page "
                             "needs a token, generated and printed in its URL unless --web-token-file gives it",
                             metavar="[HOST:]PORT", parse=endpoint)
    web_token_file: Path | None = option(None, "the web page's token (16-256 characters of [A-Za-z0-9_~.-], the "
                                         "file's first line): the page then needs ?token=... in its URL, with or "
                                         "without --secure", metavar="FILE")
    sensor_poses: Path | None = option(None, "each sensor's pose in the world, a TOML table per sensor id with x_m, "
                                       "y_m and yaw_deg (the frame radar_<id> is placed there; default: every sensor "
                                       "at the origin; a lab file's [[sensor]] pose does the same)",
                                       metavar="SENSORS.toml")


@dataclass(frozen=True)
class ViewOptions:
    """What only ``qradar view`` takes."""

    recording: Path | None = option(None, "with --web: show this recording (play, pause and seek on the page) instead "
                                    "of the live stream; no zenoh session is opened", metavar="REC.mcap")
    truth: str | None = option(None, "with --web: the true positions to show beside the targets, a scene file or a "
                               "packaged scene's name (a recording's own truth is shown without it)",
                               metavar="SCENE.toml")
    profile_rate: float | None = option(None, "range profiles per second and sensor at most (default 2 for Foxglove, "
                                        "20 for --web; 0: none)", metavar="HZ", parse=nonneg_float)


VIEWS = Part(Views, "views", only=("web", "web_token_file"))


VIEW_PARTS = [Part(ViewConfig, "view", only=("host", "port")), VIEWS, Part(ViewOptions, "view"),
              Part(ViewConfig, "view", only=("queue_size",)), Part(Views, "views", only=("sensor_poses",)),
              node_part("duration_s", "parent_pid"), INTAKE, *zenoh_parts()]


def add_commands(sub) -> None:
    add_command(
        sub, "view", VIEW_PARTS, cmd_view, config_json=True,
        help="the live stream in Foxglove (WebSocket) or, with --web, in a web page: targets, range profiles, health",
        description="Subscribes <prefix>/*/{targets,tracks,quantized,health} and serves them over the Foxglove "
        "WebSocket protocol: targets as foxglove.PointCloud in the frame radar_<sensor>, range profiles and health as "
        "JSON. Open it in Foxglove with 'Open connection' -> 'Foxglove WebSocket', then load the layout "
        f"{LAYOUT}. With --web, serves a web page instead (nothing to install: open its URL in a browser), of the "
        "live stream or of a --recording with play, pause and seek.")


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
        cfg = WebConfig(host=host, port=port, token=token, poses=poses_of(args, getattr(args, "sensor_specs", ())))
    except ParameterError as exc:
        where = f" (--web-token-file {args.web_token_file})" if args.web_token_file is not None else ""
        raise ParameterError(f"{exc}{where}") from None
    rate = getattr(args, "profile_rate", None)
    return cfg if rate is None else replace(cfg, profile_rate_hz=rate)


def poses_of(args, specs=()) -> dict:
    """Each sensor's pose: ``--sensor-poses``'s file, and a lab file's ``[[sensor]]`` pose
    (``specs``); one sensor in both is refused."""
    poses = load_poses(args.sensor_poses) if args.sensor_poses is not None else {}
    for s in specs:
        if s.pose is not None:
            if s.sensor_id in poses:
                raise ParameterError(f"sensor {s.sensor_id}: a pose in its [[sensor]] table and in --sensor-poses "
                                     f"{args.sensor_poses}: give one")
            poses[s.sensor_id] = s.pose
    return poses


def cmd_view(args) -> int:
    if args.web is None:
        for option, value in (("--recording", args.recording), ("--truth", args.truth),
                              ("--web-token-file", args.web_token_file)):
            if value is not None:
                raise ParameterError(f"{option} is for the web page: give --web [HOST:]PORT too")
        cfg = ViewConfig(host=args.host, port=args.port, queue_size=args.queue_size, poses=poses_of(args),
                         **({} if args.profile_rate is None else {"profile_rate_hz": args.profile_rate}))
        view = FoxgloveView(bus_from_args(args), cfg, intake=intake_budget(args))
        hint = (f"Foxglove WebSocket server on {{url}}; in Foxglove: Open connection -> Foxglove WebSocket -> "
                f"{{url}}, then load the layout {LAYOUT}")
    else:
        if args.port != ViewConfig.__dataclass_fields__["port"].default:
            raise ParameterError(f"--port {args.port} is Foxglove's port, and --web serves the web page instead of "
                                 "Foxglove's server: give one (both views: two `qradar view` commands)")
        view = web_view(args)
        hint = "web page on {url} (open it in a browser)"
    install_sigterm("view")
    if args.parent_pid is not None:
        watch_parent(args.parent_pid, "view")
    view.start()  # a busy port or an unknown host: ViewError, one line
    try:
        print(f"qradar view: {hint.format(url=view.url)}; Ctrl-C to stop", file=sys.stderr, flush=True)
        deadline = None if args.duration_s is None else time.monotonic() + args.duration_s
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
    from radar_driver.scene import load_truth
    from ..web import WebView

    cfg = replace(web_config(args, args.host), queue_size=args.queue_size)
    truth = load_truth(args.truth) if args.truth is not None else None
    if args.recording is not None:
        view = WebView.of_recording(args.recording, cfg)
        view.truth = truth or view.truth
        return view
    return WebView(bus_from_args(args), cfg, truth=truth, intake=intake_budget(args))
