"""``qradar up LAB.toml [--host NAME]``: the set-up of a lab file over several processes
(and hosts): this host's nodes, each a child process (``qradar COMMAND --config-json``),
supervised.

The lab file is ``qradar run``'s (docs/lab.md): what ``run`` does in one process, ``up``
splits into nodes, each given its own command's options from the file's tables (the
shared parts: ``[quantizer]`` is the quantize node's, ``[decoder]``, ``[gate]`` and
``[tracks]`` the localizer's, ``[recording]`` the recorder's, ``[views]`` the views',
``[zenoh]`` and ``[security]`` everyone's):

- ``router``: a zenoh router every other node joins as a client; it listens on ``[zenoh]
  listen``, else on a unix socket in ``up``'s private directory (nothing on the network);
  the nodes connect to ``[zenoh] connect``, else to the router's endpoints;
- ``driver <id>`` per ``[[sensor]]`` (``qradar drive``), or ``sources``: the simulated
  sensors (``qradar source``);
- ``quantize``, ``localize``, ``record`` (unless ``no-record``), ``view`` / ``web``
  (``[views] foxglove`` / ``web``).

``[hosts]`` (and a sensor's ``host``) place them; ``up --host NAME`` starts NAME's nodes
(without a ``[hosts]`` table every node is ``localhost``'s). Each child is started again
with backoff when it dies (:class:`~qradar.drivers.SupervisedDriver`), told ``up``'s pid
(it stops by itself once ``up`` is gone, however that died: SIGKILL too), and stopped
on Ctrl-C or SIGTERM, the sources first and the router last; then ``up`` prints one JSON
object: each node's restarts, exits and last summary."""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import zenoh

from pipeline.bus.session import BusConfig
from pipeline.dsp.decode import default_alpha
from pipeline.errors import ParameterError, PipelineError
from pipeline.nodes.runtime import run_nodes
from radar_driver.errors import RadarError
from radar_driver.options import nonneg_float, option
from radar_driver.scene import DEFAULT_SCENE, resolve_scene
from replay.errors import ReplayError
from replay.recorder import default_recording_path

from ..drivers import NodeProcess, SupervisedDriver
from radar_driver.scene import load_truth

from ..run import check_offline, setup_metadata, targets_a_frame
from ..sensors import check_sensor_specs
from ..rundir import remove_run_dirs, run_directory
from . import lab
from .common import StopOnSignals
from .lab import toml_value
from .parts import LOCALHOST
from .record import RECORD_PARTS
from .schema import Part, Schema, add_command
from .sensor import DRIVE_PARTS, drive_values
from .run_command import RUN_PARTS, run_config
from .stream import LOCALIZE_PARTS, QUANTIZE_PARTS, ROUTER_PARTS, SOURCE_PARTS
from .view import VIEW_PARTS
from ..view import parse_endpoint


#: how long up waits for its router to listen before it starts the other nodes, s
ROUTER_READY_S = 10.0
#: a wildcard address, to connect to
LOOPBACK = {"0.0.0.0": "127.0.0.1", "[::]": "::1"}


@dataclass(frozen=True)
class Up:
    """``qradar up``'s own options."""

    lab: Path = option(help="the lab file (docs/lab.md): what `qradar run LAB.toml` runs in one process",
                       positional=True, required=True, metavar="LAB.toml")
    host: str | None = option(None, "start the nodes [hosts] places on this host (default: [hosts] default, "
                              f"{LOCALHOST} unless the file says)", metavar="NAME")
    duration_s: float | None = option(None, "stop after S seconds (default: the lab file's duration if it gives one, "
                                      "else Ctrl-C)", flag="--duration", parse=nonneg_float)


def add_commands(sub) -> None:
    add_command(sub, "up", [Part(Up)], cmd_up,
                help="the set-up of a lab file as separate processes: this host's router, drivers, quantizer, "
                "localizer, recorder and views, supervised",
                description=__doc__.split("\n\n", 1)[0].replace("``", "`"))


#: the parts (the options) of each command up starts
NODE_PARTS = {"router": ROUTER_PARTS, "drive": DRIVE_PARTS, "source": SOURCE_PARTS, "quantize": QUANTIZE_PARTS,
              "localize": LOCALIZE_PARTS, "record": RECORD_PARTS, "view": VIEW_PARTS}


@dataclass
class Node:
    """A node of the set-up: its name, the command that runs it, that command's options
    (by dest; those the command does not have are left out), the host that runs it."""

    name: str
    command: str
    values: dict
    host: str

    def config(self, start: int = 0) -> dict:
        """The command's options as a lab file's mapping (what ``--config-json`` carries) for
        its ``start``-th start: a recorder started again records to a new file
        (``NAME-1.mcap``, ...), never over what it wrote before."""
        values = self.values
        if self.command == "record" and start:
            out = Path(values["output"])
            values = {**values, "output": out.with_name(f"{out.stem}-{start}{out.suffix}"), "force": False}
        return Schema(self.command, NODE_PARTS[self.command]).mapping(values)


def read_lab(path: Path):
    """``qradar run``'s parsed options of lab file ``path`` (every check of ``run``), and
    the keys the file gives (by dest)."""
    from . import build_parser, with_config  # (this module is one of the package's commands)

    explicit = lab.read_file(path, Schema("run", RUN_PARTS))
    parser = build_parser("run")
    argv = ["run", str(path)]
    args = with_config(parser, parser.parse_args(argv), argv)
    if not args.sensor_specs:  # simulated sensors: what run checks of its localizer (K, the gate, the decoder)
        check_offline(run_config(args))  # (with real ones on several hosts a port may repeat: run refuses that)
    return args, explicit


def hosts_of(args) -> dict[str, str]:
    """The host of each node kind, from ``[hosts]``."""
    default = args.host_default
    return {kind: getattr(args, f"host_{kind}") or default
            for kind in ("router", "sources", "quantize", "localize", "record", "view")}


def bus_values(args, connect: list[str]) -> dict:
    """A node's zenoh options: a client of the router, with the lab's prefix, config file and security."""
    return {"mode": "client", "connect": list(connect), "listen": [], "prefix": args.prefix,
            "config_file": args.config_file, "secure": args.secure, "identity": None}


def plan_nodes(args, tmp: Path) -> list[Node]:
    """Every node of the lab's set-up, in the order they start (router, recorder, views,
    localizer, quantizer, the sources), with its host."""
    hosts = hosts_of(args)
    listen = list(args.listen) or [f"unixsock-stream/{tmp / 'zenoh.sock'}"]
    connect = list(args.connect) or [ep.replace("/0.0.0.0:", "/127.0.0.1:") for ep in listen]
    base = {**bus_values(args, connect), "quiet": True, "parent_pid": os.getpid()}
    nodes = [Node("router", "router", {**base, "connect": [], "listen": listen}, hosts["router"])]
    if not args.no_record:
        nodes.append(Node("record", "record", {**base, **record_values(args)}, hosts["record"]))
    for name, kind, endpoint in (("view", "foxglove", args.foxglove), ("web", "web", args.web)):
        if endpoint is not None:
            nodes.append(Node(name, "view", {**base, **view_values(args, kind, endpoint, tmp)}, hosts["view"]))
    nodes.append(Node("localize", "localize", {**base, **copied(args, LOCALIZE_PARTS, ("algo", "max_targets", "pfa",
                      "min_range_m", "max_range_m", "track", "integrate_s")), "k": lab_k(args)}, hosts["localize"]))
    alpha = default_alpha(args.algo) if args.alpha is None else args.alpha
    nodes.append(Node("quantize", "quantize", {**base, **copied(args, QUANTIZE_PARTS, (
        "bits", "delta", "delta_margin", "dither_seed", "calibration")), "alpha": alpha}, hosts["quantize"]))
    return nodes + source_nodes(args, base, hosts)


def copied(args, parts: list, dests: tuple[str, ...]) -> dict:
    """The lab's values of ``dests``, which the node's command (``parts``) shares with ``run``."""
    known = Schema("node", parts).by_dest
    missing = [d for d in dests if d not in known]
    if missing:
        raise TypeError(f"no option {missing} in the node's command")
    return {d: getattr(args, d) for d in dests}


def lab_k(args) -> int | str:
    """The localizer's K, as ``run``'s (:func:`qradar.run.targets_a_frame`): the file's, else the
    simulated scene's count, else the truth's, else a real sensor's default."""
    scene = None if args.sensor_specs else resolve_scene(args.scene or DEFAULT_SCENE)
    truth = load_truth(args.truth) if args.truth is not None else None
    return targets_a_frame(args, scene, truth)


def record_values(args) -> dict:
    output = args.record or default_recording_path(args.folder)
    return {"output": output, "split_size_mb": args.record_split_mb, "record_on_error": args.record_on_error,
            "record_retry_s": args.record_retry_s, "force": args.force,
            "scene": args.scene or DEFAULT_SCENE if not args.sensor_specs and args.truth is None else None}


def setup_file(args, tmp: Path) -> Path:
    """The set-up's metadata for the recorder of this host (``record --setup``) in ``tmp``: what a
    run's recording says (:func:`qradar.run.setup_metadata`). Sensors of several hosts may share a
    port path (up checks the ports of each host, :func:`check_sensors`): run's config is made of
    one sensor of each port, and the metadata then names every sensor."""
    seen, specs = set(), []
    for s in args.sensor_specs:
        if s.port_key() not in seen:
            seen.add(s.port_key())
            specs.append(s)
    cfg = run_config(argparse.Namespace(**{**vars(args), "sensor_specs": tuple(specs)}))
    path = tmp / "setup.json"
    path.write_text(json.dumps(setup_metadata(cfg, args.sensor_specs)))
    return path


def view_values(args, kind: str, endpoint: str, tmp: Path) -> dict:
    """A view node: Foxglove's on ``[views] foxglove``, or the web page on ``[views] web``;
    the sensors' poses in a sensors file in ``up``'s directory."""
    poses = {s.sensor_id: s.pose for s in args.sensor_specs if s.pose is not None}
    sensor_poses = args.sensor_poses
    if poses:
        if sensor_poses is not None:
            raise ParameterError("give the sensors' poses in their [[sensor]] tables or in [views] sensor-poses, "
                                 "not both")
        sensor_poses = tmp / "poses.toml"
        sensor_poses.write_text("".join(f"[{sid}]\nx_m = {toml_value(p[0])}\ny_m = {toml_value(p[1])}\n"
                                        f"yaw_deg = {toml_value(p[2])}\n" for sid, p in poses.items()))
    if kind == "web":
        return {"web": endpoint, "web_token_file": args.web_token_file, "sensor_poses": sensor_poses}
    host, port = parse_endpoint(endpoint)
    return {"host": host, "port": port, "sensor_poses": sensor_poses}


def source_nodes(args, base: dict, hosts: dict) -> list[Node]:
    """A driver per ``[[sensor]]`` (on its host), or the simulated sensors (``qradar source``)."""
    if args.empty:
        raise ParameterError("qradar up: empty = true (the empty chamber) is for `qradar run`'s simulated K-MD2s; "
                             "up's simulated sensors (qradar source) hold the scene's targets")
    if args.sensor_specs:
        bus = BusConfig(mode="client", connect=tuple(base["connect"]), prefix=base["prefix"],
                        config_file=base["config_file"])
        return [Node(f"driver {s.sensor_id}", "drive", {
            **drive_values(s, bus, frames=args.frames, outstanding=args.outstanding or 1, parent_pid=os.getpid()),
            "secure": args.secure}, s.host or args.host_default) for s in args.sensor_specs]
    values = {**base, "scene": args.scene or DEFAULT_SCENE, "sensors": args.sensors or 1, "rate": args.rate_hz,
              "id_prefix": "kmd2-", "frames": args.frames}
    return [Node("sources", "source", values, hosts["sources"])]


def cmd_up(args) -> int:
    run_args, explicit = read_lab(args.lab)  # every check of `qradar run LAB.toml`
    host = args.host or run_args.host_default
    duration = args.duration_s if args.duration_s is not None else explicit.get("duration_s")
    stop = threading.Event()
    signals = StopOnSignals(stop, "up", on_force=remove_run_dirs)
    with run_directory() as tmp:
        nodes = plan_nodes(run_args, Path(tmp))
        mine = [n for n in nodes if n.host == host]
        if not mine:
            places = sorted({n.host for n in nodes})
            raise ParameterError(f"qradar up: no node of {args.lab} runs on host {host!r}; its hosts: "
                                 f"{', '.join(places)} ([hosts] in docs/lab.md)")
        check_reachable(run_args, nodes, host)
        check_sensors(run_args)
        for n in mine:
            if n.command == "record":  # this host records: its files say the set-up
                try:
                    n.values["setup"] = setup_file(run_args, Path(tmp))
                except (PipelineError, RadarError, ReplayError) as exc:  # e.g. the calibration file is elsewhere
                    say("record", "setup", f"its files will not say the set-up's quantizer, decoder and calibration: "
                                           f"{exc}")
        router = next(n for n in nodes if n.name == "router")
        if router.host == host:
            check_free(router.values["listen"])
        connect = tuple(next(n for n in nodes if n is not router).values["connect"])
        ready = Readiness(None if run_args.secure is not None or router.host != host else BusConfig(
            mode="client", connect=connect, prefix=run_args.prefix))
        supervised = [supervise(n, ready) for n in mine]
        sources = [s for s, n in zip(supervised, mine) if n.command in ("drive", "source")]
        if run_args.frames is not None and sources:  # as run: the set-up ends once its sensors' frames are sent
            threading.Thread(target=lambda: ([s.done.wait() for s in sources], stop.set()), daemon=True).start()
        try:
            run_nodes(supervised, duration, stop)
        except KeyboardInterrupt:
            pass
        finally:
            ready.close()
    print(json.dumps({"up": {"host": host, "nodes": {s.sensor_id: report(s) for s in supervised}}}), flush=True)
    # as run: a set-up whose node ended failing (given up, or dying again at each start) is no success
    failed = [s for s in supervised if s.failing]
    if failed and signals.interrupted is None:
        why = "; ".join(f"{s.sensor_id} (died {len(s.exits)} time(s), {s.state}): {s.exits[-1]}" for s in failed)
        print(f"qradar up: error: {why} (check the sensor, its url and profile in the lab file, and the lines "
              "above)", file=sys.stderr, flush=True)
        return 1
    return 0


def check_sensors(args) -> None:
    """Each sensor's id is its own; on each host, each port has one sensor and the sensors
    make frames of one radar configuration (:func:`~qradar.sensors.check_sensor_specs`)."""
    ids: dict[str, str] = {}
    for s in args.sensor_specs:
        if s.sensor_id in ids:
            raise ParameterError(f"[[sensor]] id {s.sensor_id!r} is given twice; each sensor needs its own id")
        ids[s.sensor_id] = s.host or args.host_default
    for host in sorted(set(ids.values())):
        check_sensor_specs(tuple(s for s in args.sensor_specs if (s.host or args.host_default) == host))


def check_reachable(args, nodes: list[Node], host: str) -> None:
    """A node here whose router runs elsewhere needs ``[zenoh] connect`` (the router's address)."""
    router = next(n for n in nodes if n.name == "router")
    if router.host != host and not args.connect:
        raise ParameterError(f"qradar up: the router runs on host {router.host!r}: give [zenoh] connect, where this "
                             f"host's nodes reach it (e.g. [\"tcp/{router.host}:7447\"], with [zenoh] listen "
                             "[\"tcp/0.0.0.0:7447\"] for the router)")


def say(name: str, state: str, detail: str) -> None:
    print(f"qradar up: {name}: {detail}", file=sys.stderr, flush=True)


def supervise(node: Node, ready: "Readiness") -> SupervisedDriver:
    """``node`` as a child process, started again with backoff when it dies. Its start
    waits (a bounded time) until it can take what the next ones send: the router until it
    listens, a node until its liveliness token is seen (it subscribes as it declares it),
    so that the sensors, started last, lose no frame to a node still loading."""
    starts = []

    def make(_frames_done: int) -> NodeProcess:
        starts.append(ready.count(node.command))
        return NodeProcess(node.command, node.config(len(starts) - 1), node.name, on_start=started)

    def started(proc: NodeProcess) -> None:
        say(node.name, "started", f"started (pid {proc.pid}) on {node.host}")
        if node.command == "router":
            wait_listening(node.values["listen"], proc)
            ready.open()
        elif not ready.wait(node.command, starts[-1], proc):
            say(node.name, "started", f"not seen alive within {NODE_READY_S:g} s; going on")

    return SupervisedDriver(node.name, make, on_event=say, what="it")


#: a node's liveliness token, by command (pipeline.nodes.runtime.Node.name)
TOKEN = {"quantize": "quantize", "localize": "localize", "record": "record", "view": "view", "source": "source",
         "drive": "source"}
#: how long up waits for a node to be alive before it starts the next, s
NODE_READY_S = 30.0


#: the liveliness tokens ``up`` holds at most (a lab's nodes have a few; others on the network
#: may declare any number)
MAX_TOKENS = 4096


class Readiness:
    """``up``'s own zenoh session, a client of its router (none under ``--secure``, where
    ``up`` has no identity of its own, nor on a host without the router): the liveliness
    tokens of its nodes, counted by kind as a liveliness subscriber sees them come and go
    (an event each, not a poll: a loop of liveliness queries took half a core from ``up``
    and a fifth from its router while a node loaded)."""

    def __init__(self, bus: BusConfig | None):
        self.bus, self.session, self._subscriber = bus, None, None
        self._alive: set[str] = set()
        self._changed = threading.Condition()

    def open(self) -> None:
        if self.bus is not None and self.session is None:
            self.session = self.bus.open()
            self._subscriber = self.session.liveliness().declare_subscriber(
                f"{self.bus.prefix}/alive/**", self._on_token, history=True)

    def _on_token(self, sample) -> None:
        key = str(sample.key_expr)
        with self._changed:
            if sample.kind == zenoh.SampleKind.PUT:
                if len(self._alive) < MAX_TOKENS:  # a peer declaring tokens without end takes no more
                    self._alive.add(key)
            else:
                self._alive.discard(key)
            self._changed.notify_all()

    def count(self, command: str) -> int:
        if self.session is None or command not in TOKEN:
            return 0
        kind = f"{self.bus.prefix}/alive/{TOKEN[command]}/"
        with self._changed:
            return sum(k.startswith(kind) for k in self._alive)

    def wait(self, command: str, before: int, proc: NodeProcess, timeout_s: float = NODE_READY_S) -> bool:
        """Until a token of ``command``'s kind more than ``before`` is seen (True), ``proc``
        ends or ``timeout_s`` (False); at once without a session."""
        if self.session is None or command not in TOKEN:
            return True
        deadline = time.monotonic() + timeout_s
        while proc.returncode is None:
            if self.count(command) > before:
                return True
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            with self._changed:  # a token, or a look at whether proc ended
                self._changed.wait(min(left, 0.5))
        return False

    def close(self) -> None:
        if self._subscriber is not None:
            self._subscriber.undeclare()
            self._subscriber = None
        if self.session is not None:
            self.session.close()
            self.session = None


def listening(ep: str) -> bool | None:
    """Whether something takes a connection at the endpoint ``ep`` (a unix socket's path
    exists, a TCP port accepts); None: no way to look."""
    kind, _, where = ep.partition("/")
    if kind == "unixsock-stream":  # a socket file left by a killed router takes no connection
        with socket.socket(socket.AF_UNIX) as s:
            try:
                s.connect(where)
                return True
            except OSError:
                return False
    if kind not in ("tcp", "tls"):
        return None
    host, _, port = where.rpartition(":")
    try:
        with socket.create_connection((LOOPBACK.get(host, host.strip("[]")), int(port)), 0.2):
            return True
    except (OSError, ValueError):
        return False


def check_free(endpoints: list[str]) -> None:
    """A ParameterError when one of the router's ``endpoints`` has a listener already (another
    set-up's router): its nodes would join that one and mix their sensors into it."""
    for ep in endpoints:
        if listening(ep):
            raise ParameterError(f"{ep} already has a listener (another `qradar up` or router?): this "
                                 "set-up's router cannot listen there, and its nodes would join the other set-up; "
                                 "stop that one, or give [zenoh] listen another endpoint")


def wait_listening(endpoints: list[str], proc: NodeProcess, timeout_s: float = ROUTER_READY_S) -> bool:
    """Until each of ``endpoints`` (a unix socket's path, a TCP port) takes a connection,
    ``proc`` ends, or ``timeout_s``; whether they all do."""
    deadline = time.monotonic() + timeout_s
    for ep in endpoints:
        while time.monotonic() < deadline and proc.returncode is None:
            up = listening(ep)
            if up or up is None:  # None: no way to look (the nodes retry)
                break
            time.sleep(0.05)
        else:
            return False
    return True


def report(s: SupervisedDriver) -> dict:
    """What ``up`` says of a node at its end: restarts, why it died, its last summary."""
    current = s.current
    final = current.final if isinstance(current, NodeProcess) else {}
    return {"restarts": s.restarts, "exits": list(s.exits), "state": s.state, "summary": final,
            "exit_code": current.returncode if isinstance(current, NodeProcess) else None}
