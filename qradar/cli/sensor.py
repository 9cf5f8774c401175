"""Sensor commands: ``sim`` (a simulated K-MD2 on a pty and/or TCP) and ``drive`` (read
a K-MD2, real or simulated, and publish its frames)."""

from __future__ import annotations

import json
import os
import select
import sys
import time
from pathlib import Path

import numpy as np

from pipeline.errors import ParameterError
from pipeline.nodes.stream import SourceNode
from pipeline.wire import check_sensor_id
from radar_driver.profile import CHIRP_SELECT, DEFAULT_PROFILE_NAME, packaged_profiles, resolve_profile
from radar_driver.scene import packaged_scenes, resolve_scene
from radar_driver.session import DEFAULT_FAST_BAUD, SensorSession, SessionConfig, save_frames_npz
from radar_driver.simulator import SimFaults, SimulatorServer
from replay.outputs import check_new_file

from .common import (
    force_option,
    bus_from_args,
    bus_options,
    edge_quantizer,
    edge_quantizer_options,
    install_sigterm,
    nonneg_float,
    nonneg_int,
    pos_float,
    pos_int,
    prob,
    watch_parent,
    load_calibration,
)


#: at most this long, ``drive --linger-stdin`` keeps its zenoh session open after the counters, s
LINGER_S = 10.0


def linger_until_stdin_closes(timeout_s: float) -> bool:
    """Read stdin until it ends (the parent closed it): True, or False after ``timeout_s``."""
    fd = sys.stdin.fileno()
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        ready, _, _ = select.select([fd], [], [], left)
        if ready and not os.read(fd, 4096):
            return True
    return False


def add_commands(sub) -> None:
    p = sub.add_parser("sim", help="serve a simulated K-MD2 on a pty and/or TCP until interrupted",
                       description="A simulated RFbeam K-MD2 speaking the serial protocol; ramps from "
                       "the paper's model of a TOML scene through its front end, with noise, 12-bit ADC and optional "
                       "faults.")
    p.add_argument("--scene", default="chamber",
                   help=f"TOML scene file, or the name of a packaged scene ({', '.join(packaged_scenes())})")
    p.add_argument("--empty", action="store_true",
                   help="the scene without its targets: the empty chamber, front end (DC, leakage) and noise only")
    p.add_argument("--link", type=Path, default=None, help="stable symlink path to the pty (e.g. /tmp/kmd2)")
    p.add_argument("--tcp", type=int, default=None, metavar="PORT", help="also serve socket://127.0.0.1:PORT")
    p.add_argument("--rate", type=nonneg_float, default=20.0, help="frames per second (0 = as fast as polled)")
    p.add_argument("--seed", type=nonneg_int, default=0, help="noise and fault seed")
    p.add_argument("--garbage", type=prob, default=0.0, metavar="P", help="garbage burst before a message")
    p.add_argument("--truncate", type=prob, default=0.0, metavar="P", help="RADC cut short")
    p.add_argument("--skip-done", type=prob, default=0.0, metavar="P", help="DONE counter jumps")
    p.add_argument("--disconnect-after", type=pos_int, default=None, metavar="N", help="drop the link after N frames")
    p.add_argument("--reconnect-after", type=nonneg_float, default=1.0, metavar="T", help="link back after T s")
    p.add_argument("--line-rate", action="store_true",
                   help="on the pty, take as long as a real serial line at the host's speed (8E1)")
    p.add_argument("--hold-clock-when-late", action="store_true",
                   help="when this process itself writes a reply late (a loaded host), stop the device clock for "
                   "as long, as a K-MD2 on its own clock would: the drops left are the driver's")
    profile_option(p)
    p.set_defaults(func=cmd_sim, parser=p)

    p = sub.add_parser("drive", help="read frames from a K-MD2 (real or simulated)",
                       description="Drive a K-MD2 on any pyserial URL (/dev/ttyUSB0, a pty path, "
                       "socket://host:port, rfc2217://host:port), 8E1, reconnecting on errors.")
    p.add_argument("--port", required=True, help="pyserial URL or device path")
    p.add_argument("--frames", type=pos_int, default=None, help="stop after N frames (default: until Ctrl-C)")
    p.add_argument("--baud", type=int, default=None,
                   help=f"rate after INIT (115200, 460800, 921600, 2000000, 3000000); default {DEFAULT_FAST_BAUD}, "
                   "except on socket:// (Ethernet, raw ser2net), which stays at the start-up 115200")
    p.add_argument("--ramps", type=pos_int, default=2, help="ramps per frame (M = 256 x ramps)")
    p.add_argument("--timeout", type=pos_float, default=0.5, help="seconds to wait for a GNFD answer")
    profile_option(p)
    p.add_argument("--outstanding", type=int, choices=(1, 2), default=1,
                   help="GNFD requests kept in flight: 2 lets the sensor hold one while the host is late "
                   "(assumes the K-MD2 queues a second GNFD; the simulator does)")
    p.add_argument("--chirp-select", choices=CHIRP_SELECT, default="first",
                   help="with several chirps per RADC: a frame takes the first --ramps chirps, or every k-th")
    p.add_argument("--out", type=Path, default=None, help="save frames to FILE.npz (frames, M, 2)")
    force_option(p, "the --out file")
    p.add_argument("--json", action="store_true",
                   help="end with one JSON object on stdout: the counters, or the error and exit code")
    p.add_argument("--quiet", action="store_true", help="no line per frame")
    p.add_argument("--sensor-id", default="kmd2", help="sensor id in the zenoh keys")
    p.add_argument("--no-publish", action="store_true", help="read frames without opening a zenoh session")
    edge_quantizer_options(p, "--quantize")
    p.add_argument("--linger-stdin", action="store_true",
                   help="after a stop, print the counters and keep the zenoh session open until stdin closes "
                   f"(at most {LINGER_S:g} s): a parent that reads the counters closes stdin once it has received "
                   "every frame they count (a put just before a session closes can be lost)")
    p.add_argument("--parent-pid", type=pos_int, default=None, metavar="PID",
                   help="stop (GBYE, counters) within a second once process PID is no longer this one's parent, "
                   "however it died (qradar run sets it for its drivers)")
    bus_options(p)
    p.set_defaults(func=cmd_drive)


def cmd_sim(args) -> int:
    if args.link is None and args.tcp is None:
        args.parser.error("give --link PATH and/or --tcp PORT")
    scene = resolve_scene(args.scene)
    if args.empty:
        scene = scene.without_targets()
    faults = SimFaults(garbage_prob=args.garbage, truncate_prob=args.truncate, skip_done_prob=args.skip_done,
                       disconnect_after_frames=args.disconnect_after, reconnect_after_s=args.reconnect_after)
    install_sigterm("sim")
    profile = resolve_profile(args.profile)
    server = SimulatorServer(scene, link_path=args.link, tcp_port=args.tcp, rate_hz=args.rate,
                             faults=faults, seed=args.seed, profile=profile, line_rate=args.line_rate,
                             hold_clock_when_late=args.hold_clock_when_late)
    t0 = time.monotonic()
    with server:
        where = [str(args.link)] if args.link else []
        if args.tcp is not None:
            where.append(f"socket://127.0.0.1:{server.tcp_port}")
        front = ("ideal front end" if scene.front_end.ideal else
                 "front end: DC offset, TX leakage, receiver mismatch (calibrate: docs/chamber.md, section 7)")
        print(f"simulated K-MD2 ({scene.name}, {len(scene.targets)} targets, {front}, {args.rate:g} frames/s, "
              f"profile {profile.name}) on "
              f"{' and '.join(where)}; Ctrl-C to stop", flush=True)
        try:
            while not server.wait(0.5):
                if server.errors:
                    raise server.errors[0]
        except KeyboardInterrupt:
            pass
    print(sim_summary(server, time.monotonic() - t0), flush=True)
    return 0


def sim_summary(server: SimulatorServer, seconds: float) -> str:
    """What a simulated K-MD2 did: its RADCs (and frames) sent, the hosts' INITs, its faults
    and its own lateness."""
    parts = []
    for d in server.devices:
        faults = {k: v for k, v in d.event_counts.items() if k not in ("INIT", "GNFD", "GBYE", "SWITCH", "LATE")}
        parts.append(f"{d.radcs_sent} RADCs sent ({d.radcs_sent // d.radcs_per_frame} frames of "
                     f"{d.radcs_per_frame}), {d.event_counts.get('INIT', 0)} INIT(s), {d.event_counts.get('GBYE', 0)} "
                     f"GBYE(s)" + (f", faults: {', '.join(f'{k} {v}' for k, v in sorted(faults.items()))}" if faults
                                   else "")
                     + (f", {d.late_writes} late writes, {d.late_s * 1e3:.1f} ms in all (device clock held)"
                        if d.late_writes else ""))
    return f"simulator: {seconds:.1f} s; " + "; ".join(parts)


def profile_option(p) -> None:
    p.add_argument("--profile", default=DEFAULT_PROFILE_NAME,
                   help=f"sensor profile (RADC layout, baud codes): {', '.join(packaged_profiles())} or a TOML file")


def cmd_drive(args) -> int:
    cfg = SessionConfig(url=args.port, baud=args.baud, ramps_per_frame=args.ramps, timeout_s=args.timeout,
                        sensor_id=check_sensor_id(args.sensor_id), profile=args.profile,
                        chirp_select=args.chirp_select, outstanding=args.outstanding)
    quantizer, raw_every = edge_quantizer(args)
    load_calibration(args.calibration, [cfg.sensor_id])  # a file for another sensor: refused before the port opens
    if args.out is not None:
        if args.out.suffix != ".npz":  # numpy would add it, and write another file than the one checked
            raise ParameterError(f"--out {args.out}: the frames file must end in .npz")
        check_new_file(args.out, args.force, "--out")
    if quantizer is not None and args.no_publish:
        raise ParameterError("--quantize publishes quantized frames; it cannot go with --no-publish")
    lines = sys.stderr if args.json else sys.stdout
    frames = []

    def show(frame) -> None:
        if args.out is not None:
            frames.append(frame)
        if args.quiet:
            return
        peak = np.abs(frame.data).max()
        print(f"frame {frame.seq:6d}  counters {frame.counters}  t {frame.timestamp_ns}  "
              f"peak {peak:.3f} FS", file=lines, flush=True)

    install_sigterm("drive")
    if args.parent_pid is not None:
        watch_parent(args.parent_pid, "drive")
    session = SensorSession(cfg)
    bus_session = None  # the zenoh session, closed last: after the counters (and the parent's ack)
    try:
        session.open()  # in this thread, so that a port that does not open says so once
        if args.no_publish:
            with session:
                for frame in session.frames(args.frames):
                    show(frame)
        else:
            bus = bus_from_args(args)
            bus_session = bus.open()
            node = SourceNode(bus, session, session=bus_session, frames=args.frames, on_frame=show,
                              quantizer=quantizer, raw_every=raw_every,
                              calibration=load_calibration(args.calibration, [cfg.sensor_id]))
            try:
                node.start()
                while not node.done.wait(0.2):
                    if node.errors:
                        break
            finally:
                node.stop()  # publishes the frames the driver still had, then undeclares
            if node.errors:
                raise node.errors[0]
    except KeyboardInterrupt:
        pass
    except BaseException:
        if bus_session is not None:
            bus_session.close()
        raise
    finally:
        session.close()  # GBYE: also on an error and on SIGTERM
    if args.out is not None:
        save_frames_npz(args.out, frames, cfg)
    c = session.counters.as_dict()
    if args.json:
        print(json.dumps(c), flush=True)
    else:
        print("counters: " + ", ".join(f"{k}={v}" for k, v in c.items()), flush=True)
    if bus_session is not None:
        if args.linger_stdin:
            try:
                if not linger_until_stdin_closes(LINGER_S):
                    print(f"qradar drive: stdin still open after {LINGER_S:g} s; closing the zenoh session",
                          file=sys.stderr, flush=True)
            except KeyboardInterrupt:
                pass
        bus_session.close()
    return 0
