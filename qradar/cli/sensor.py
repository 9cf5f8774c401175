"""Sensor commands: ``sim`` (a simulated K-MD2 on a pty and/or TCP) and ``drive`` (read
a K-MD2, real or simulated, and publish its frames)."""

from __future__ import annotations

import json
import os
import select
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import ParameterError
from pipeline.nodes.stream import SourceNode
from pipeline.wire import check_sensor_id
from radar_driver.lifetime import watch_parent
from radar_driver.options import like, nonneg_float, nonneg_int, option, pos_int
from radar_driver.scene import DEFAULT_SCENE, SIM_RATE_HZ, packaged_scenes, resolve_scene
from radar_driver.session import SensorSession, SessionConfig, save_frames_npz
from radar_driver.simulator import SimFaults, SimulatorServer
from radar_driver.profile import resolve_profile
from replay.outputs import check_new_file

from .common import bus_from_args, install_sigterm, load_calibration
from .parts import edge_parts, edge_quantizer, force_help, node_part, switches, zenoh_parts
from .schema import Part, Schema, add_command


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


@dataclass(frozen=True)
class Sim:
    """A simulated K-MD2 (``qradar sim``): its scene, links, rate and seed."""

    scene: str = option(DEFAULT_SCENE, f"TOML scene file, or the name of a packaged scene "
                        f"({', '.join(packaged_scenes())})")
    empty: bool = option(False, "the scene without its targets: the empty chamber, front end (DC, leakage) and noise "
                         "only")
    link: Path | None = option(None, "stable symlink path to the pty (e.g. /tmp/kmd2)")
    tcp: int | None = option(None, "also serve socket://127.0.0.1:PORT", metavar="PORT", parse=int)
    rate: float = option(SIM_RATE_HZ, "frames per second (0 = as fast as polled)", parse=nonneg_float)
    seed: int = option(0, "noise and fault seed", parse=nonneg_int)
    line_rate: bool = option(False, "on the pty, take as long as a real serial line at the host's speed (8E1)")
    hold_clock_when_late: bool = option(False, "when this process itself writes a reply late (a loaded host), stop "
                                        "the device clock for as long, as a K-MD2 on its own clock would: the drops "
                                        "left are the driver's (the scene goes on: a moving target is where "
                                        "it is when the frame is stamped)")
    profile: str | None = like(SessionConfig, "profile")


@dataclass(frozen=True)
class Drive:
    """What ``qradar drive`` does with the frames besides publishing them."""

    frames: int | None = option(None, "stop after N frames (default: until Ctrl-C)", parse=pos_int)
    out: Path | None = option(None, "save frames to FILE.npz (frames, M, 2)")
    no_publish: bool = option(False, "read frames without opening a zenoh session")
    linger_stdin: bool = option(False, "after a stop, print the counters and keep the zenoh session open until stdin "
                                f"closes (at most {LINGER_S:g} s): a parent that reads the counters closes stdin once "
                                "it has received every frame they count (a put just before a session closes can be "
                                "lost)")


SIM_PARTS = [Part(Sim, only=("scene", "empty", "link", "tcp", "rate", "seed")), Part(SimFaults, "faults"),
             Part(Sim, only=("line_rate", "hold_clock_when_late", "profile"))]
DRIVE_PARTS = [
    Part(SessionConfig, only=("url",)), Part(Drive, only=("frames",)),
    Part(SessionConfig, only=("baud", "ramps_per_frame", "timeout_s", "profile", "outstanding", "chirp_select")),
    Part(Drive, only=("out",)), switches(force=force_help("the --out file"), json="end with one JSON object on "
                                        "stdout: the counters, or the error and exit code"),
    node_part("quiet", quiet="no line per frame"), Part(SessionConfig, only=("sensor_id",)),
    Part(Drive, only=("no_publish",)), *edge_parts("--quantize"), Part(Drive, only=("linger_stdin",)),
    node_part("parent_pid", parent_pid="stop (GBYE, counters) within a second once process PID is no longer this "
              "one's parent, however it died (qradar run sets it for its drivers)"), *zenoh_parts()]


def add_commands(sub) -> None:
    p = add_command(sub, "sim", SIM_PARTS, cmd_sim, help="serve a simulated K-MD2 on a pty and/or TCP until "
                    "interrupted", description="A simulated RFbeam K-MD2 speaking the serial protocol; ramps from "
                    "the paper's model of a TOML scene through its front end, with noise, 12-bit ADC and optional "
                    "faults.")
    p.set_defaults(parser=p)
    add_command(sub, "drive", DRIVE_PARTS, cmd_drive, config_json=True,
                help="read frames from a K-MD2 (real or simulated)",
                description="Drive a K-MD2 on any pyserial URL (/dev/ttyUSB0, a pty path, socket://host:port, "
                "rfc2217://host:port), 8E1, reconnecting on errors.")


def drive_values(spec, bus, frames: int | None = None, outstanding: int = 1, parent_pid: int | None = None,
                 linger: bool = False) -> dict:
    """``qradar drive``'s options (by dest) for a sensor's driver (``spec``: a
    :class:`~qradar.sensors.SensorSpec`) publishing on ``bus``, with ``--json --quiet``."""
    return {"url": spec.url, "sensor_id": spec.sensor_id, "baud": spec.baud, "ramps_per_frame": spec.ramps,
            "profile": spec.profile, "chirp_select": spec.chirp_select, "outstanding": outstanding,
            "frames": frames, "json": True, "quiet": True, "parent_pid": parent_pid, "linger_stdin": linger,
            "mode": bus.mode, "connect": list(bus.connect), "prefix": bus.prefix, "config_file": bus.config_file}


def drive_config(spec, bus, **kw) -> dict:
    """:func:`drive_values` as a lab file's mapping: what a run hands its driver process
    (``--config-json``)."""
    return Schema("drive", DRIVE_PARTS).mapping(drive_values(spec, bus, **kw))


def cmd_sim(args) -> int:
    if args.link is None and args.tcp is None:
        args.parser.error("give --link PATH and/or --tcp PORT")
    scene = resolve_scene(args.scene)
    if args.empty:
        scene = scene.without_targets()
    faults = args.schema.build(SimFaults, args)
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
        try:  # a Ctrl-C as soon as it says it is up ends it with its summary too
            print(f"simulated K-MD2 ({scene.name}, {len(scene.targets)} targets, {front}, {args.rate:g} frames/s, "
                  f"profile {profile.name}) on "
                  f"{' and '.join(where)}; Ctrl-C to stop", flush=True)
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


def cmd_drive(args) -> int:
    check_sensor_id(args.sensor_id)
    cfg = args.schema.build(SessionConfig, args)
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
