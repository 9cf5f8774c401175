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
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TextIO

from pipeline.dsp.calibration import Calibration
from pipeline.dsp.calibration import load as load_calibration
from pipeline.bus.session import BusConfig
from pipeline.wire.shared import DecodedOnce
from pipeline.wire import HealthMsg
from pipeline.dsp.decode import DEFAULT_ALGO, Algo, DecoderConfig
from pipeline.errors import ParameterError, RunSetupError
from pipeline.dsp.localize import DEFAULT_PFA
from pipeline.nodes.stream import LocalizeNode, LocalizerConfig, QuantizeNode, SourceNode, run_nodes
from pipeline.dsp.track import TrackerConfig
from pipeline.dsp.quantize import QuantizerConfig
from radar_driver.errors import ConfigError
from radar_driver.model import RadarConfig
from radar_driver.scene import SimScene, resolve_scene, scene_from_dict
from radar_driver.session import SensorSession
from radar_driver.simulator import SimulatorServer
from replay.errors import RecordingExists
from replay.outputs import check_new_file
from replay.recorder import OnWriteError, RecorderNode

from .drivers import MAX_RESTARTS, RESTART_BACKOFF_S, DriverProcess, SupervisedDriver, driver_bus
from .monitor import Monitor
from .summary import RunSummary, format_summary, print_json, simulator_lateness, summarize  # noqa: F401 (run's API)
from .rundir import remove_run_dirs, run_directory
from .sensors import SensorSpec, as_spec, check_sensor_specs, probe_sensors, resolve_auto
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

    scene: str | None = None
    empty: bool = False  # the simulated scene without its targets (front end and noise only)
    sensors: int | None = None
    duration_s: float | None = 15.0
    rate_hz: float | None = None
    quantizer: QuantizerConfig = field(default_factory=QuantizerConfig)
    k: int | None = None  # None = the scene's (or --truth's) count, else REAL_SENSOR_K; with auto_k the most a frame has
    algo: Algo = DEFAULT_ALGO
    bus: BusConfig = field(default_factory=BusConfig)
    baud: int = 2_000_000  # the simulated sensors' line speed after INIT (a real one's: its spec's baud)
    record: Path | None = None  # MCAP path, or None for no recording
    frames: int | None = None  # stop after this many frames per sensor
    auto_k: bool = False  # the localizer decides each frame's count (CFAR, false-alarm probability pfa)
    pfa: float = DEFAULT_PFA
    foxglove: ViewConfig | None = None  # serve the live stream to Foxglove (qradar.view) on its host and port
    web: WebConfig | None = None  # serve the live stream as a web page (qradar.web) on its host and port
    driver_process: bool = True  # each sensor's driver in its own process (False: a thread of this one)
    record_on_error: OnWriteError = OnWriteError.RESUME  # the recorder after a write error: resume or stop
    record_retry_s: float = 5.0  # while the recording is paused, look for space this often, s
    record_split_mb: float | None = None  # a new file every that many MB (bounds the MCAP index in memory)
    record_new_name_if_taken: bool = False  # record is a default name: -1, -2, ... if taken (else refused)
    record_overwrite: bool = False  # --force: an existing file at record (a name given) is replaced
    # GNFDs each driver keeps in flight: 2 lets the sensor hold a request while its driver is late (a busy
    # host; the simulator queues it, a K-MD2 is assumed to), 1 asks only after each answer. None: 2 with
    # simulated sensors, 1 (drive's default: no assumption) with real ones
    outstanding: int | None = None
    sensor_specs: tuple[SensorSpec | str, ...] = ()  # real sensors: no simulator
    truth: str | Path | None = None  # scene file of the true positions
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
            for name, default in (("scene", "chamber"), ("sensors", 1), ("rate_hz", 20.0)):
                if getattr(self, name) is None:
                    object.__setattr__(self, name, default)
        if self.outstanding is None:
            object.__setattr__(self, "outstanding", 1 if specs else 2)
        if not specs and not (isinstance(self.sensors, int) and 1 <= self.sensors <= 256):
            raise ParameterError(f"sensors={self.sensors!r} must be an integer in [1, 256]")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ParameterError(f"duration={self.duration_s!r} must be > 0")
        if not specs and not self.rate_hz > 0:
            raise ParameterError(f"rate={self.rate_hz!r} must be > 0")
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


def run(cfg: RunConfig, live: TextIO | None = sys.stdout, stop: threading.Event | None = None) -> "RunSummary":
    """Run the pipeline; returns its summary. A wrong set-up ends it with an error of the
    libraries' roots (one line): a calibration that does not fit a sensor's first frame
    (CalibrationError), frames that never assemble (the driver's SetupError), frames that
    arrive but are every one refused (RunSetupError)."""
    scene = None if cfg.real else resolve_scene(cfg.scene)
    if cfg.empty and scene is not None:
        scene = scene.without_targets()
    truth = load_truth(cfg.truth) if cfg.truth is not None else scene
    radar = check_sensor_specs(cfg.sensor_specs) if cfg.real else scene.radar
    calibration = None
    if cfg.calibration is not None:  # a file for other sensors: refused before anything starts
        calibration = load_calibration(cfg.calibration)
        for sid in ([s.sensor_id for s in cfg.sensor_specs] if cfg.real else
                    [f"kmd2-{i}" for i in range(cfg.sensors)]):
            calibration.check_sensor(sid)
    if cfg.record is not None and not cfg.record_new_name_if_taken:  # before anything starts
        if os.path.lexists(cfg.record) and not cfg.record_overwrite:
            raise RecordingExists.at(cfg.record)
        check_new_file(cfg.record, cfg.record_overwrite, "recording")  # its folder, one level at most
    if scene is not None:
        k = cfg.k or max(1, len(scene.targets))
    else:
        k = cfg.k or (len(truth.targets) if truth is not None and truth.targets else REAL_SENSOR_K)
    localizer_cfg = LocalizerConfig(k=k, algo=cfg.algo, radar=radar, fallback_pbp=cfg.quantizer.alpha == 0,
                                    auto_k=cfg.auto_k, pfa=cfg.pfa, min_range_m=cfg.min_range_m,
                                    max_range_m=cfg.max_range_m)  # checked before anything starts
    if cfg.real:
        cfg = replace(cfg, sensor_specs=resolve_auto(cfg.sensor_specs))  # --sensor auto: the one K-MD2 found
        probe_sensors(cfg.sensor_specs)  # each port opens (and is nobody else's), before anything starts
    if live is not None:
        print(run_header(cfg, scene, truth, localizer_cfg, calibration), file=live, flush=True)
    t_start = time.monotonic()
    stop = stop or threading.Event()
    refused: list[RunSetupError] = []
    with run_directory() as tmp:  # removed at the end; a SIGKILLed run's, by the next run's start
        # a simulator late by its own fault (a busy host) holds its device clock, as a K-MD2 on its own
        # clock would, and counts it: the drops left are the driver's
        sims = [] if cfg.real else [
            SimulatorServer(scene, link_path=Path(tmp) / f"kmd2-{i}", rate_hz=cfg.rate_hz, seed=i,
                            hold_clock_when_late=True) for i in range(cfg.sensors)]
        for sim in sims:
            sim.start()
        # a simulated sensor is a simulator on a pty and a driver on that pty; a real one only the driver
        specs = cfg.sensor_specs or tuple(
            SensorSpec(str(sim.links[0].link_path), f"kmd2-{i}", baud=cfg.baud, ramps=scene.radar.ramps_per_frame)
            for i, sim in enumerate(sims))
        bus = driver_bus(cfg.bus, Path(tmp))
        listen = cfg.driver_process and bus.connect != cfg.bus.connect  # the unix socket, for driver processes only
        session = (replace(cfg.bus, listen=cfg.bus.listen + bus.connect) if listen else cfg.bus).open()
        try:
            decoded = DecodedOnce()  # each JSON message parsed once for the monitor, the recorder and the views
            monitor = Monitor(cfg.bus, session, truth, time.time_ns(), live, clock_per_sensor=not cfg.real,
                              calibration=None if calibration is None else calibration.source, decoded=decoded).start()
            localizer = LocalizeNode(cfg.bus, localizer_cfg, session=session, tracking=cfg.tracking)
            quantizer = QuantizeNode(cfg.bus, cfg.quantizer, session=session, radar=radar, calibration=calibration,
                                     calibration_required=True)  # a file that does not fit: refused at the first frame
            drivers = supervised_drivers(cfg, specs, bus, session, monitor, live, stop)
            if cfg.frames is not None:
                threading.Thread(target=lambda: ([d.done.wait() for d in drivers], stop.set()), daemon=True).start()
            ended = threading.Event()  # the run's nodes have stopped: the watch ends too
            threading.Thread(target=watch_refusals, args=(monitor, quantizer, localizer, stop, refused, ended),
                             name="refusals", daemon=True).start()
            recorder = []
            if cfg.record is not None:
                recorder = [RecorderNode(cfg.bus, cfg.record, session=session, radar=radar,
                                         metadata=run_metadata(cfg, scene, truth, radar, k, calibration,
                                                               localizer_cfg.gate),
                                         on_write_error=cfg.record_on_error, retry_s=cfg.record_retry_s,
                                         split_size_mb=cfg.record_split_mb,
                                         new_name_if_taken=cfg.record_new_name_if_taken,
                                         overwrite=cfg.record_overwrite, decoded=decoded)]
            view = web = None
            if cfg.foxglove is not None:  # started first and stopped last, so it shows every target
                view = FoxgloveView(cfg.bus, replace(cfg.foxglove, radar=radar), session=session,
                                    decoded=decoded).start()
                if live is not None:
                    print(f"foxglove: WebSocket server on {view.url}", file=live, flush=True)
            if cfg.web is not None:  # the truth's clock: each simulated sensor's first frame, as the monitor's
                try:
                    web = WebView(cfg.bus, replace(cfg.web, radar=radar), session=session, truth=truth,
                                  truth_t0_ns=time.time_ns() if cfg.real else None, decoded=decoded).start()
                except BaseException:  # a busy port: the Foxglove view ends too
                    if view is not None:
                        view.stop()
                    raise
                if live is not None:
                    print(f"web: page on {web.url}", file=live, flush=True)
            try:
                run_nodes([*recorder, localizer, quantizer, *drivers], cfg.duration_s, stop)
            finally:
                ended.set()
                monitor.stop()
                for v in (view, web):
                    if v is not None:
                        v.stop()
        finally:
            session.close()
            for sim in sims:
                sim.stop()
    if refused:
        raise refused[0]
    summary = summarize(cfg, scene, monitor, localizer, quantizer, drivers, time.monotonic() - t_start,
                        simulator=simulator_lateness(sims) if sims else None, truth=truth, calibration=calibration)
    if recorder:  # state, files, written, dropped (queue), lost (write errors, by topic), error
        summary.recording = recorder[0].summary()
    if view is not None:
        summary.foxglove = view.summary()
    if web is not None:
        summary.web = web.summary()
    return summary


def watch_refusals(monitor: Monitor, quantizer, localizer, stop: threading.Event, out: list,
                   ended: threading.Event) -> None:
    """Until ``stop`` or ``ended``: once REFUSED_AFTER raw frames (or more) have arrived and every
    one was refused (none reached the targets), a RunSetupError into ``out`` and ``stop`` set."""
    while not (stop.is_set() or ended.wait(0.5)):
        raw, targets = monitor.count["raw"], monitor.count["targets"]
        if raw < REFUSED_AFTER or targets:
            continue
        q, lo = quantizer.totals(), localizer.totals()
        kinds = ("invalid_frames", "decode_errors", "processing_errors")
        n_q, n_l = sum(q[k] for k in kinds), sum(lo[k] for k in kinds)
        if n_q + n_l < raw:
            continue
        node = quantizer if n_q else localizer
        why = next((node.last_reason[k] for k in kinds if k in node.last_reason), "no reason logged")
        out.append(RunSetupError(f"{raw} raw frames arrived and every one was refused, none decoded (quantize "
                                 f"refused {n_q}, localize {n_l}); the last reason: {why}"))
        stop.set()
        return


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
            return DriverProcess(s.url, s.sensor_id, s.baud, s.ramps, bus, frames=frames,
                                 outstanding=cfg.outstanding, log=sys.stderr if live is not None else None,
                                 profile=s.profile, chirp_select=s.chirp_select,
                                 received=lambda: monitor.raw_by_sensor.get(s.sensor_id, 0) - base)
        return make

    for s in specs:
        drivers.append(SupervisedDriver(s.sensor_id, maker(s), lambda sid=s.sensor_id: monitor.raw_by_sensor.get(
            sid, 0), on_event=report, backoff_s=cfg.driver_backoff_s, max_restarts=cfg.driver_restarts))
    return drivers


def load_truth(name_or_path: str | Path) -> SimScene:
    """The true positions of ``--truth``: a scene file as :mod:`radar_driver.scene` reads
    (or a packaged scene's name), of which only the targets' ranges and angles (and a
    velocity, from the run's start) count, so a target's ``amplitude`` may be left out.
    ConfigError naming ``--truth`` and the file, also for a file without a target."""
    path = Path(name_or_path)
    try:
        if not path.exists() and path.suffix == "" and len(path.parts) == 1:
            scene = resolve_scene(path.name)  # a packaged scene
        else:
            try:
                data = tomllib.loads(path.read_text())
            except OSError as exc:
                raise ConfigError(f"cannot read {path}: {exc.strerror or exc}") from None
            except tomllib.TOMLDecodeError as exc:
                raise ConfigError(f"{path}: not valid TOML: {exc}") from None
            targets = data.get("target")
            if isinstance(targets, list):
                data["target"] = [{"amplitude": 1.0, **t} if isinstance(t, dict) else t for t in targets]
            scene = scene_from_dict(data, str(path))
    except ConfigError as exc:
        raise ConfigError(f"--truth: {exc}") from None
    if not scene.targets:
        raise ConfigError(f"--truth: {name_or_path} has no [[target]] (range_m, angle_deg): no position to compare with")
    return scene


def run_metadata(cfg: RunConfig, scene: SimScene | None, truth: SimScene | None, radar: RadarConfig,
                 k: int, calibration: Calibration | None = None, gate=None) -> dict[str, dict]:
    """MCAP metadata of a run: radar config, node configs (the localizer's range
    ``gate``), the sensors and the true
    positions (``qradar.scene``, which ``qradar reprocess`` takes for its truth): the
    simulated scene, or the ``--truth`` file's (with real sensors: ``simulated`` false)."""
    from dataclasses import asdict

    meta = {
        "qradar.radar": radar.to_dict() | {"config_id": radar.config_id()},
        "qradar.quantizer": asdict(cfg.quantizer),
        "qradar.localizer": {"algo": str(cfg.algo), "K": k, "K_auto": cfg.auto_k, "source": "quantized",
                             **({} if gate is None else gate.to_dict())},
    }
    if cfg.real:
        meta["qradar.sensors"] = {s.sensor_id: json.dumps({"url": s.url, "profile": s.profile_name, "baud": s.baud,
                                                           "ramps": s.ramps, "chirp_select": s.chirp_select})
                                  for s in cfg.sensor_specs}
    if calibration is not None:  # what the quantize node removed: a recording can be calibrated again later
        meta["qradar.calibration"] = {"file": calibration.source, "summary": json.dumps(calibration.summary())}
    if scene is not None and truth is scene:
        meta["qradar.scene"] = {"scene": json.dumps(scene.to_dict()), "simulated": "true",
                                "sensors": str(cfg.sensors), "rate_hz": str(cfg.rate_hz)}
    elif truth is not None:  # measured positions (a real sensor), or a truth other than the simulated scene
        meta["qradar.scene"] = {"scene": json.dumps(truth.to_dict()), "simulated": "false",
                                "truth_file": str(cfg.truth), "sensors": str(cfg.n_sensors)}
        if scene is not None:
            meta["qradar.simulated_scene"] = {"scene": json.dumps(scene.to_dict()), "rate_hz": str(cfg.rate_hz)}
    return meta
