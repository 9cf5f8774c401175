"""``qradar run``: the main job. Simulated K-MD2(s) on pseudo-terminals, or real sensors
on their pyserial URLs (``--sensor``, :mod:`qradar.sensors`), the serial driver of each
sensor in its own process (``qradar drive``, so that nothing here can stall its serial
line), the quantize-with-dither node, the localizer and the recorder, wired through one
embedded zenoh session; live targets beside the true positions (the simulated scene's,
or a ``--truth`` scene file's: the reflectors' measured positions), and a summary at the
end. It composes all three libraries, so it lives here.

The driver processes reach the run's session through a unix socket in the run's
temporary directory (zenoh client mode): no network port is opened."""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TextIO

from pipeline.dsp.calibration import Calibration
from pipeline.dsp.calibration import load as load_calibration
from pipeline.bus.session import BusConfig
from pipeline.wire.shared import DecodedOnce
from pipeline.wire import HealthMsg
from pipeline.dsp.decode import DEFAULT_ALGO, Algo, DecoderConfig
from pipeline.dsp.gate import RangeGate, gate_warning
from pipeline.errors import ParameterError, RunSetupError
from pipeline.dsp.localize import DEFAULT_PFA
from pipeline.nodes.stream import LocalizeNode, LocalizerConfig, QuantizeNode, SourceNode, run_nodes
from pipeline.dsp.track import TrackerConfig
from pipeline.dsp.quantize import QuantizerConfig
from radar_driver.model import RadarConfig
from radar_driver.scene import DEFAULT_SCENE, SIM_RATE_HZ, SimScene, check_sim_rate, load_truth, resolve_scene
from radar_driver.session import SensorSession
from radar_driver.simulator import SimulatorServer
from replay.errors import RecordingExists
from replay.outputs import check_file_kind, check_new_file
from radar_driver.options import option, pos_float, pos_int
from replay.recorder import OnWriteError, RecorderNode

from .drivers import MAX_RESTARTS, RESTART_BACKOFF_S, DriverProcess, SupervisedDriver, driver_bus
from .monitor import Monitor
from .summary import RunSummary, format_summary, print_json, simulator_lateness, summarize  # noqa: F401 (run's API)
from .rundir import remove_run_dirs, run_directory
from .sensors import SensorSpec, as_spec, check_sensor_specs, probe_sensors, resolve_auto
from .liveview import seen_from
from .view import FoxgloveView, ViewConfig
from .web import WebConfig, WebView

#: targets a frame of a real sensor holds when neither --K nor a --truth file says (the chamber's two reflectors)
REAL_SENSOR_K = 2


@dataclass(frozen=True)
class RunConfig:
    """What ``qradar run`` does. Its sensors are simulated (``scene``, ``sensors``,
    ``rate_hz``; None: chamber, 1, 20) unless ``sensor_specs`` names real ones (pyserial
    URLs with their ids and profiles, :class:`~qradar.sensors.SensorSpec` or spec strings),
    which the simulation's three do not go with. ``truth``: a scene file (or packaged
    name) whose targets are the reflectors' true positions, for the position errors;
    None: the simulated scene, or no error with real sensors."""

    scene: str | None = option(None, "the simulated sensors' scene: file or packaged name (default chamber)")
    empty: bool = option(False, "the scene without its targets: the empty chamber, front end (DC, leakage) and "
                         "noise only (simulated sensors; for `qradar calibrate --empty`)")
    sensors: int | None = option(None, "simulated sensors at once (default 1)", parse=pos_int)
    duration_s: float | None = option(
        15.0, "seconds (default 15); Ctrl-C or SIGTERM ends the run earlier, normally: the same summary (with "
        "\"interrupted\": true) and status 0; a second one while it stops exits at once with 130", flag="--duration",
        parse=pos_float)
    rate_hz: float | None = option(None, "frames per second per simulated sensor (default 20)", flag="--rate",
                                   parse=pos_float)
    quantizer: QuantizerConfig = field(default_factory=QuantizerConfig)
    k: int | None = None  # None = the scene's (or --truth's) count, else REAL_SENSOR_K; with auto_k the most a frame has
    algo: Algo = DEFAULT_ALGO
    bus: BusConfig = field(default_factory=BusConfig)
    baud: int = 2_000_000  # the simulated sensors' line speed after INIT (a real one's: its spec's baud)
    record: Path | None = None  # MCAP path, or None for no recording
    frames: int | None = option(None, "stop after N frames per sensor", parse=pos_int)
    auto_k: bool = False  # the localizer decides each frame's count (CFAR, false-alarm probability pfa)
    pfa: float = DEFAULT_PFA
    foxglove: ViewConfig | None = None  # serve the live stream to Foxglove (qradar.view) on its host and port
    web: WebConfig | None = None  # serve the live stream as a web page (qradar.web) on its host and port
    # each sensor's driver in its own process (False: a thread of this one)
    driver_process: bool = option(True, "run the serial drivers as threads of this process (default: a process "
                                  "each)", flag="--driver-in-process", negate=True)
    record_on_error: OnWriteError = option(
        OnWriteError.RESUME, "after a write error (a full disk, EFBIG, EIO, a removed folder) the file is closed up to "
        "its last flushed chunk; resume: keep running, count the messages that cannot be written (by topic) and go on "
        "in a new file (NAME_0001.mcap, ...) when space returns; stop: end the recording and go on without it (the "
        "pipeline keeps running; the summary says so). A file that cannot be created at the start is an error either "
        "way", flag="--on-write-error", choices=tuple(m.value for m in OnWriteError))
    record_retry_s: float = option(5.0, "while paused after a write error, look for space every S seconds",
                                   flag="--write-retry", metavar="S", parse=pos_float)
    record_split_mb: float | None = option(
        None, "record into a new file every MB megabytes (NAME_0001.mcap, ...): the MCAP writer keeps each chunk's "
        "index in memory until its file ends: at most 0.7 KB a chunk (one a second, or each MB) plus 70 B for each "
        "channel in it", flag="--split-size", metavar="MB", parse=pos_float)
    record_new_name_if_taken: bool = False  # record is a default name: -1, -2, ... if taken (else refused)
    record_overwrite: bool = False  # --force: an existing file at record (a name given) is replaced
    # GNFDs each driver keeps in flight: 2 lets the sensor hold a request while its driver is late (a busy
    # host; the simulator queues it, a K-MD2 is assumed to), 1 asks only after each answer. None: 2 with
    # simulated sensors, 1 (drive's default: no assumption) with real ones
    outstanding: int | None = option(
        None, "GNFD requests each driver keeps in flight: 2 lets the sensor hold one while its driver is late on a "
        "busy host (the simulator queues a second GNFD; a real K-MD2 is assumed to). Default 2 with simulated "
        "sensors, 1 with --sensor", choices=(1, 2), parse=int)
    sensor_specs: tuple[SensorSpec | str, ...] = option(
        (), "a real sensor instead of the simulated ones (repeatable, one each): a pyserial URL (a device path, "
        "socket://HOST:PORT, rfc2217://HOST:PORT) or auto (the one K-MD2 that answers on this host's serial adapters, "
        "probed with INIT and GBYE as `qradar ports --probe` does), then its id (required) and the driver's options: "
        "profile=NAME|FILE (default kmd2-blocks), baud=B (default 2000000; a socket:// link stays at 115200), ramps=R "
        "(default 2), chirp-select=first|stride; e.g. /dev/ttyUSB0,id=kmd2-0,profile=kmd2-blocks. Not with --scene, "
        "--sensors, --rate", flag="--sensor", metavar="URL,id=NAME[,KEY=VALUE]", many="append",
        parse=SensorSpec.parse, table=SensorSpec)
    truth: str | Path | None = option(
        None, "a scene file whose targets are the reflectors' true (measured) positions (a sensor with a pose in a lab "
        "file's [[sensor]] table sees them from where it stands): the live lines and the summary give the position "
        "errors against them (only the targets' ranges and angles count). Default: the simulated scene; with --sensor, no "
        "error", metavar="SCENE.toml", kinds=frozenset({"str"}))
    calibration: str | Path | None = None  # a `qradar calibrate` file, applied by the quantize node
    # the localizer's range gate, m (None: the radar's default, pipeline.dsp.gate.RangeGate.default)
    min_range_m: float | None = None
    max_range_m: float | None = None
    tracking: TrackerConfig | None = None  # tracks after the localizer (pipeline.dsp.track), None: none
    # a driver that dies is started again after driver_backoff_s, doubled each time it dies again soon;
    # its sensor is given up after driver_restarts such deaths in a row (qradar.drivers.SupervisedDriver)
    driver_backoff_s: float = RESTART_BACKOFF_S
    driver_restarts: int = MAX_RESTARTS

    def __post_init__(self) -> None:
        object.__setattr__(self, "algo", DecoderConfig(algo=self.algo, auto_k=self.auto_k, pfa=self.pfa).algo)
        specs = tuple(as_spec(s) for s in self.sensor_specs)
        object.__setattr__(self, "sensor_specs", specs)
        if specs:
            if self.sensors is not None:
                raise ParameterError(f"--sensors {self.sensors} starts simulated sensors; it does not go with "
                                     f"--sensor (real ones): give one --sensor per sensor")
            if self.scene is not None:
                raise ParameterError(f"--scene {self.scene} is the simulated sensors' scene; with --sensor (real "
                                     f"sensors) give the reflectors' measured positions as --truth SCENE.toml")
            if self.rate_hz is not None:
                raise ParameterError(f"--rate {self.rate_hz:g} is the simulated sensors' frame rate; a real sensor "
                                     f"(--sensor) measures at its own")
            if self.empty:
                raise ParameterError("--empty empties the simulated scene; with --sensor (real sensors) empty the "
                                     "chamber itself and record it")
            check_sensor_specs(specs)
        else:
            for name, default in (("scene", DEFAULT_SCENE), ("sensors", 1), ("rate_hz", SIM_RATE_HZ)):
                if getattr(self, name) is None:
                    object.__setattr__(self, name, default)
        if self.outstanding is None:
            object.__setattr__(self, "outstanding", 1 if specs else 2)
        if not specs and not (isinstance(self.sensors, int) and 1 <= self.sensors <= 256):
            raise ParameterError(f"sensors={self.sensors!r} must be an integer in [1, 256]")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ParameterError(f"duration={self.duration_s!r} must be > 0")
        if not specs:
            check_sim_rate(self.rate_hz, "rate", error=ParameterError)
        if self.record_on_error not in tuple(OnWriteError) or not self.record_retry_s > 0:
            raise ParameterError(f"record_on_error={self.record_on_error!r} must be one of "
                                 f"{[m.value for m in OnWriteError]} and record_retry_s={self.record_retry_s!r} > 0")
        object.__setattr__(self, "record_on_error", OnWriteError(self.record_on_error))
        if self.outstanding not in (1, 2):
            raise ParameterError(f"outstanding={self.outstanding!r} must be 1 or 2")
        if not (self.driver_backoff_s > 0 and isinstance(self.driver_restarts, int) and self.driver_restarts >= 0):
            raise ParameterError(f"driver_backoff_s={self.driver_backoff_s!r} must be > 0 and "
                                 f"driver_restarts={self.driver_restarts!r} an integer >= 0")

    @property
    def real(self) -> bool:
        """Real sensors (``sensor_specs``), not simulated ones."""
        return bool(self.sensor_specs)

    @property
    def n_sensors(self) -> int:
        return len(self.sensor_specs) or self.sensors


#: a run whose first REFUSED_AFTER raw frames (or more) were all refused, none decoded, ends
#: with a RunSetupError (the frames cannot be processed as set up)
REFUSED_AFTER = 10


@dataclass(frozen=True)
class Plan:
    """What a run knows before anything starts: its config (an ``auto`` sensor found), the
    simulated scene (None: real sensors), the truth (the simulated scene, a ``truth``
    file's positions, or None) and, per sensor with a pose, that truth seen from it, the
    radar configuration, the calibration and the localizer's config."""

    cfg: RunConfig
    scene: SimScene | None
    truth: SimScene | None
    truths: dict
    radar: RadarConfig
    calibration: Calibration | None
    localizer: LocalizerConfig


def localizer_of(cfg: RunConfig, scene: SimScene | None, truth: SimScene | None,
                 radar: RadarConfig) -> LocalizerConfig:
    """The localizer's config of a run on ``radar`` (checked: K, the range gate, the decoder),
    its K :func:`targets_a_frame`'s; a K the user did not give is named with where it came from."""
    k = targets_a_frame(cfg, scene, truth)
    try:
        return LocalizerConfig(k=k, algo=cfg.algo, radar=radar, fallback_pbp=cfg.quantizer.alpha == 0,
                               auto_k=cfg.auto_k, pfa=cfg.pfa, min_range_m=cfg.min_range_m,
                               max_range_m=cfg.max_range_m)
    except ParameterError as e:
        named = f"--max-targets={k}" if cfg.auto_k else f"K={k}"  # as LocalizerConfig names the K it refuses
        if cfg.k or named not in str(e):
            raise
        origin = ("the scene's targets" if scene is not None else "--truth's targets"
                  if truth is not None and truth.targets else "a real sensor's default without --truth")
        given = f"no --max-targets given: at most {k} targets a frame" if cfg.auto_k else f"no --K given: K={k}"
        raise ParameterError(f"{given}, {origin}; {e}") from None


def check_offline(cfg: RunConfig) -> None:
    """What :func:`plan` checks of the localizer without opening a port or a file (``--print-config``
    prints only a config that runs): against the simulated scene's radar; with real sensors,
    whose radar their profiles give once their ports open, the range gate's ends against
    each other."""
    if cfg.real:
        if cfg.min_range_m is not None and cfg.max_range_m is not None:
            RangeGate(cfg.min_range_m, cfg.max_range_m)
        return
    scene = resolve_scene(cfg.scene)
    localizer_of(cfg, scene, None, scene.radar)


def targets_a_frame(cfg: RunConfig, scene: SimScene | None, truth) -> int:
    """The run's K: ``--K`` (``cfg.k``: a RunConfig's, or up's parsed lab options'), else the
    simulated scene's targets, else the truth's, else REAL_SENSOR_K."""
    if scene is not None:
        return cfg.k or max(1, len(scene.targets))
    return cfg.k or (len(truth.targets) if truth is not None and truth.targets else REAL_SENSOR_K)


def plan(cfg: RunConfig) -> Plan:
    """Everything a run checks before it starts anything: the scene or the sensors' specs
    (each port opened once), the truth, the calibration against the sensors, the
    recording's file, the localizer's config; a wrong one is one line."""
    scene, truth, radar = world(cfg)
    calibration = check_calibration(cfg)
    check_record(cfg)
    localizer = localizer_of(cfg, scene, truth, radar)  # checked before anything starts
    # a truth file holds the world's positions: each sensor with a pose sees them from there
    truths = {s.sensor_id: seen_from(truth, s.pose, s.sensor_id) for s in cfg.sensor_specs
              if s.pose is not None and cfg.truth is not None}
    if cfg.real:
        cfg = replace(cfg, sensor_specs=resolve_auto(cfg.sensor_specs))  # --sensor auto: the one K-MD2 found
        probe_sensors(cfg.sensor_specs)  # each port opens (and is nobody else's), before anything starts
    return Plan(cfg, scene, truth, truths, radar, calibration, localizer)


def world(cfg: RunConfig) -> tuple[SimScene | None, SimScene | None, RadarConfig]:
    """A run's scene (None with real sensors; ``--empty``: without its targets), its truth
    (``--truth``'s, else the scene) and its radar (real sensors': from their profiles)."""
    scene = None if cfg.real else resolve_scene(cfg.scene)
    if cfg.empty and scene is not None:
        scene = scene.without_targets()
    truth = load_truth(cfg.truth) if cfg.truth is not None else scene
    return scene, truth, check_sensor_specs(cfg.sensor_specs) if cfg.real else scene.radar


def check_calibration(cfg: RunConfig) -> Calibration | None:
    """The run's calibration file (None: none), refused when it has no entry for one of its sensors."""
    if cfg.calibration is None:
        return None
    calibration = load_calibration(cfg.calibration)
    for sid in [s.sensor_id for s in cfg.sensor_specs] if cfg.real else [f"kmd2-{i}" for i in range(cfg.sensors)]:
        calibration.check_sensor(sid)
    return calibration


def check_record(cfg: RunConfig) -> None:
    """A recording's file given by name: refused if it exists (unless ``record_overwrite``)
    or its folder cannot be made (one level at most)."""
    if cfg.record is not None and not cfg.record_new_name_if_taken:
        check_file_kind(cfg.record, "recording")  # a folder or a link: said as such, --force or not
        if os.path.lexists(cfg.record) and not cfg.record_overwrite:
            raise RecordingExists.at(cfg.record)
        check_new_file(cfg.record, cfg.record_overwrite, "recording")


def run(cfg: RunConfig, live: TextIO | None = sys.stdout, stop: threading.Event | None = None) -> RunSummary:
    """Run the pipeline; returns its summary. A wrong set-up ends it with an error of the
    libraries' roots (one line): a calibration that does not fit a sensor's first frame
    (CalibrationError), frames that never assemble (the driver's SetupError), frames that
    arrive but are every one refused (RunSetupError)."""
    p = plan(cfg)
    if live is not None:
        print(run_header(p.cfg, p.scene, p.truth, p.localizer, p.calibration), file=live, flush=True)
    t_start = time.monotonic()
    stop = stop or threading.Event()
    with run_directory() as tmp:  # removed at the end; a SIGKILLed run's, by the next run's start
        sims = start_simulators(p, Path(tmp))
        try:
            nodes = RunNodes(p, Path(tmp), sims, live, stop)
            nodes.run()
        finally:
            for sim in sims:
                sim.stop()
    return nodes.summary(time.monotonic() - t_start, sims)


def start_simulators(p: Plan, tmp: Path) -> list[SimulatorServer]:
    """A simulated K-MD2 per simulated sensor, on a pty in the run's directory (none with
    real sensors). A simulator late by its own fault (a busy host) holds its device clock,
    as a K-MD2 on its own clock would, and counts it: the drops left are the driver's."""
    if p.cfg.real:
        return []
    sims = [SimulatorServer(p.scene, link_path=tmp / f"kmd2-{i}", rate_hz=p.cfg.rate_hz, seed=i,
                            hold_clock_when_late=True) for i in range(p.cfg.sensors)]
    for sim in sims:
        sim.start()
    return sims


class RunNodes:
    """The nodes of a run in one zenoh session (opened here, closed by :meth:`run`): the
    monitor, the localizer, the quantizer, a supervised driver per sensor (a simulated one
    is a simulator on a pty and a driver on that pty), the recorder and the views."""

    def __init__(self, p: Plan, tmp: Path, sims: list[SimulatorServer], live: TextIO | None,
                 stop: threading.Event):
        self.p, self.live, self.stop = p, live, stop
        cfg = p.cfg
        self.refused: list[RunSetupError] = []
        self.ended = threading.Event()  # the run's nodes have stopped: the watches end too
        self.recorder: list[RecorderNode] = []
        self.view = self.web = None
        self.decoded = DecodedOnce()  # each JSON message parsed once for the monitor, the recorder and the views
        self.drivers_bus = driver_bus(cfg.bus, tmp)
        listen = cfg.driver_process and self.drivers_bus.connect != cfg.bus.connect  # the unix socket, for drivers
        self.session = (replace(cfg.bus, listen=cfg.bus.listen + self.drivers_bus.connect) if listen
                        else cfg.bus).open()
        try:
            specs = cfg.sensor_specs or tuple(
                SensorSpec(str(sim.links[0].link_path), f"kmd2-{i}", baud=cfg.baud,
                           ramps=p.scene.radar.ramps_per_frame) for i, sim in enumerate(sims))
            self._build(specs)
            self._start_views()
        except BaseException:
            self.session.close()
            raise

    def _build(self, specs) -> None:
        p, cfg, session = self.p, self.p.cfg, self.session
        # the truth's clock: real sensors' starts now, for the monitor, the web page and the recording alike
        # (each simulated sensor's: its first frame)
        self.truth_t0_ns = time.time_ns() if cfg.real else None
        self.monitor = Monitor(cfg.bus, session, p.truth, self.truth_t0_ns or time.time_ns(), self.live,
                               clock_per_sensor=not cfg.real,
                               calibration=None if p.calibration is None else p.calibration.source,
                               truths=p.truths, decoded=self.decoded).start()
        self.localizer = LocalizeNode(cfg.bus, p.localizer, session=session, tracking=cfg.tracking,
                                      bits=None if p.localizer.source == "raw" else cfg.quantizer.bits)
        self.quantizer = QuantizeNode(cfg.bus, cfg.quantizer, session=session, radar=p.radar,
                                      calibration=p.calibration,
                                      calibration_required=True)  # a file that does not fit: refused at the first frame
        self.drivers = supervised_drivers(cfg, specs, self.drivers_bus, session, self.monitor, self.live, self.stop)
        if cfg.frames is not None:
            threading.Thread(target=lambda: ([d.done.wait() for d in self.drivers], self.stop.set()),
                             daemon=True).start()
        threading.Thread(target=watch_refusals, args=(self.monitor, self.quantizer, self.localizer, self.stop,
                                                      self.refused, self.ended), name="refusals", daemon=True).start()
        if cfg.record is not None:
            self.recorder = [RecorderNode(
                cfg.bus, cfg.record, session=session, radar=p.radar, on_write_error=cfg.record_on_error,
                metadata=run_metadata(cfg, p.scene, p.truth, p.radar, p.localizer.k, p.calibration,
                                      p.localizer.gate, self.truth_t0_ns),
                retry_s=cfg.record_retry_s, split_size_mb=cfg.record_split_mb,
                new_name_if_taken=cfg.record_new_name_if_taken, overwrite=cfg.record_overwrite, decoded=self.decoded)]

    def _start_views(self) -> None:
        """The Foxglove view and the web page, started first and stopped last, so they show
        every target; a view that cannot start (a busy port) stops the other."""
        p, cfg = self.p, self.p.cfg
        if cfg.foxglove is not None:
            self.view = FoxgloveView(cfg.bus, replace(cfg.foxglove, radar=p.radar), session=self.session,
                                     decoded=self.decoded).start()
            self._say(f"foxglove: WebSocket server on {self.view.url}")
        if cfg.web is not None:  # the truth's clock: the monitor's (_build)
            try:
                self.web = WebView(cfg.bus, replace(cfg.web, radar=p.radar), session=self.session, truth=p.truth,
                                   truth_t0_ns=self.truth_t0_ns, decoded=self.decoded).start()
            except BaseException:
                if self.view is not None:
                    self.view.stop()
                raise
            self._say(f"web: page on {self.web.url}")

    def _say(self, line: str) -> None:
        if self.live is not None:
            print(line, file=self.live, flush=True)

    def run(self) -> None:
        """Until the duration, ``stop`` or the frames; then every node stopped and the
        session closed. A wrong set-up seen meanwhile is raised (RunSetupError)."""
        try:
            try:
                run_nodes([*self.recorder, self.localizer, self.quantizer, *self.drivers], self.p.cfg.duration_s,
                          self.stop)
            finally:
                self.ended.set()
                self.monitor.stop()
                for v in (self.view, self.web):
                    if v is not None:
                        v.stop()
        finally:
            self.session.close()
        # else a short run (fewer frames than REFUSED_AFTER) whose every frame was refused
        error = self.refused[0] if self.refused else refusal(self.monitor, self.quantizer, self.localizer, 1)
        if error is not None:
            raise error

    def summary(self, seconds: float, sims: list[SimulatorServer]) -> RunSummary:
        p = self.p
        summary = summarize(p.cfg, p.scene, self.monitor, self.localizer, self.quantizer, self.drivers, seconds,
                            simulator=simulator_lateness(sims) if sims else None, truth=p.truth,
                            calibration=p.calibration)
        if self.recorder:  # state, files, written, dropped (queue), lost (write errors, by topic), error
            summary.recording = self.recorder[0].summary()
        if self.view is not None:
            summary.foxglove = self.view.summary()
        if self.web is not None:
            summary.web = self.web.summary()
        return summary


def watch_refusals(monitor: Monitor, quantizer, localizer, stop: threading.Event, out: list,
                   ended: threading.Event) -> None:
    """Until ``stop`` or ``ended``: once REFUSED_AFTER raw frames (or more) have arrived and every
    one was refused (none reached the targets), a RunSetupError into ``out`` and ``stop`` set."""
    while not (stop.is_set() or ended.wait(0.5)):
        error = refusal(monitor, quantizer, localizer, REFUSED_AFTER)
        if error is not None:
            out.append(error)
            stop.set()
            return


def refusal(monitor: Monitor, quantizer, localizer, at_least: int) -> RunSetupError | None:
    """The RunSetupError of a run whose ``at_least`` (>= 1) raw frames or more have arrived and were
    every one refused by its nodes (none reached the targets); None otherwise."""
    raw, targets = monitor.count["raw"], monitor.count["targets"]
    if raw < at_least or targets:
        return None
    q, lo = quantizer.totals(), localizer.totals()
    kinds = ("invalid_frames", "decode_errors", "processing_errors")
    n_q, n_l = sum(q[k] for k in kinds), sum(lo[k] for k in kinds)
    if n_q + n_l < raw:
        return None
    node = quantizer if n_q else localizer
    why = next((node.last_reason[k] for k in kinds if k in node.last_reason), "no reason logged")
    return RunSetupError(f"{raw} raw frames arrived and every one was refused, none decoded (quantize "
                         f"refused {n_q}, localize {n_l}); the last reason: {why}")


def run_header(cfg: RunConfig, scene: SimScene | None, truth: SimScene | None, localizer: LocalizerConfig,
               calibration: Calibration | None) -> str:
    """The run's first lines: what runs, against which truth, and whether its frames are calibrated."""
    where = (", ".join(f"{s.sensor_id} on {s.url}" for s in cfg.sensor_specs) if cfg.real else
             f"scene {scene.name}{' (empty)' if cfg.empty else ''}, {cfg.sensors} simulated sensor(s) at "
             f"{cfg.rate_hz:g} frames/s")
    gate = localizer.gate
    k = f"K auto (at most {localizer.k})" if cfg.auto_k else f"K = {localizer.k}"
    q = cfg.quantizer
    lines = [f"qradar run: {where}; {cfg.algo} {k} in {gate.min_range_m:g}-{gate.max_range_m:g} m, {q.bits}-bit "
             f"alpha {q.alpha}; truth: " + ("none (no position error)" if truth is None else
                                            "the simulated scene" if truth is scene else str(cfg.truth))]
    outside = gate_warning(truth, gate)
    if outside is not None:
        lines.append(f"  warning: {outside}")
    if calibration is not None:
        made = calibration.meta.get("created_utc", "at an unknown time")
        lines.append(f"  calibration {calibration.source} (made {made}, for {', '.join(sorted(calibration.sensors))}); "
                     "each sensor's first frame is checked against it")
    elif scene is not None and not scene.front_end.ideal:
        lines.append(f"  calibration none: the frames are uncalibrated, and the simulated scene {scene.name} has a "
                     "front end (DC offset, TX leakage, receiver mismatch): expect the warning below (a calibrated "
                     "run: --calibration recordings/chamber-cal.json)")
    else:
        lines.append("  calibration none: the frames are uncalibrated (a warning follows if the localizer sees a "
                     "front end's leakage)")
    return "\n".join(lines)


def supervised_drivers(cfg: RunConfig, specs, bus: BusConfig, session, monitor: Monitor, live: TextIO | None,
                       stop: threading.Event) -> list[SupervisedDriver]:
    """A driver per sensor (a process of its own, or a thread of this one), each
    restarted with backoff when it dies while the others go on (:class:`SupervisedDriver`):
    a death and a restart are said on the live stream and in the sensor's health (node
    ``run``, ``extra.driver``: state, restarts, why); once every sensor is given up,
    ``stop`` is set (the run ends with its summary)."""
    drivers: list[SupervisedDriver] = []

    def report(sensor_id: str, state: str, detail: str) -> None:
        sup = next(d for d in drivers if d.sensor_id == sensor_id)
        if live is not None:
            print(f"{sensor_id}: {detail}", file=live, flush=True)
        health = HealthMsg("run", sensor_id, time.time_ns(), extra={"driver": {
            "state": state, "restarts": sup.restarts, "exits": len(sup.exits), "last_exit": detail}})
        try:
            session.put(cfg.bus.key(sensor_id, "health"), health.to_json())
        except Exception:  # a closing session: the live line and the summary say it
            pass
        if state == "gone" and all(d.gone.is_set() or d is sup for d in drivers):
            stop.set()

    def maker(s: SensorSpec):
        def make(frames_done: int):
            frames = None if cfg.frames is None else max(cfg.frames - frames_done, 1)
            if not cfg.driver_process:
                return SourceNode(cfg.bus, SensorSession(s.session_config(cfg.outstanding)), session=session,
                                  frames=frames)
            base = monitor.raw_by_sensor.get(s.sensor_id, 0)  # this driver's frames are those after
            return DriverProcess(s, bus, frames=frames, outstanding=cfg.outstanding,
                                 log=sys.stderr if live is not None else None,
                                 received=lambda: monitor.raw_by_sensor.get(s.sensor_id, 0) - base)
        return make

    for s in specs:
        drivers.append(SupervisedDriver(s.sensor_id, maker(s), lambda sid=s.sensor_id: monitor.raw_by_sensor.get(
            sid, 0), on_event=report, backoff_s=cfg.driver_backoff_s, max_restarts=cfg.driver_restarts))
    return drivers



def setup_metadata(cfg: RunConfig, specs: tuple[SensorSpec, ...] = ()) -> dict[str, dict[str, str]]:
    """:func:`run_metadata` of ``cfg`` from the config alone, no port opened (the radar of
    real sensors from their profiles), each value as text: what ``qradar up`` hands its
    recorder, so its files say the set-up as a run's do. ``specs``: every sensor of the set-up
    when ``cfg`` holds some of them (up's hosts may share a port path)."""
    scene, truth, radar = world(cfg)
    localizer = localizer_of(cfg, scene, truth, radar)
    meta = run_metadata(cfg, scene, truth, radar, localizer.k, check_calibration(cfg), localizer.gate)
    if specs:
        meta["qradar.sensors"] = sensors_metadata(specs)
        if "sensors" in meta.get("qradar.scene", {}):
            meta["qradar.scene"]["sensors"] = str(len(specs))
    return {name: {k: v if isinstance(v, str) else json.dumps(v) for k, v in record.items()}
            for name, record in meta.items()}


def sensors_metadata(specs: tuple[SensorSpec, ...]) -> dict[str, str]:
    """A recording's ``qradar.sensors`` record: each sensor's URL, profile and link settings (JSON)."""
    return {s.sensor_id: json.dumps({"url": s.url, "profile": s.profile_name, "baud": s.baud, "ramps": s.ramps,
                                     "chirp_select": s.chirp_select}) for s in specs}


def run_metadata(cfg: RunConfig, scene: SimScene | None, truth: SimScene | None, radar: RadarConfig,
                 k: int, calibration: Calibration | None = None, gate=None,
                 truth_t0_ns: int | None = None) -> dict[str, dict]:
    """MCAP metadata of a run: radar config, node configs (the localizer's range
    ``gate``), the sensors and the true
    positions (``qradar.scene``, which ``qradar reprocess`` takes for its truth): the
    simulated scene, or the ``--truth`` file's (with real sensors: ``simulated`` false, and
    ``truth_t0_ns``, when the truth's time began: the run's start)."""
    from dataclasses import asdict

    meta = {
        "qradar.radar": radar.to_dict() | {"config_id": radar.config_id()},
        "qradar.quantizer": asdict(cfg.quantizer),
        "qradar.localizer": {"algo": str(cfg.algo), "K": k, "K_auto": cfg.auto_k, "source": "quantized",
                             **({} if gate is None else gate.to_dict())},
    }
    if cfg.real:
        meta["qradar.sensors"] = sensors_metadata(cfg.sensor_specs)
    if calibration is not None:  # what the quantize node removed: a recording can be calibrated again later
        meta["qradar.calibration"] = {"file": calibration.source, "summary": json.dumps(calibration.summary())}
    if scene is not None and truth is scene:
        meta["qradar.scene"] = {"scene": json.dumps(scene.to_dict()), "simulated": "true",
                                "sensors": str(cfg.sensors), "rate_hz": str(cfg.rate_hz)}
    elif truth is not None:  # measured positions (a real sensor), or a truth other than the simulated scene
        meta["qradar.scene"] = {"scene": json.dumps(truth.to_dict()), "simulated": "false",
                                "truth_file": str(cfg.truth), "sensors": str(cfg.n_sensors)}
        if truth_t0_ns is not None:  # when the truth's time began (real sensors: the run's start, host clock ns)
            meta["qradar.scene"]["truth_t0_ns"] = str(truth_t0_ns)
        if scene is not None:
            meta["qradar.simulated_scene"] = {"scene": json.dumps(scene.to_dict()), "rate_hz": str(cfg.rate_hz)}
    return meta
