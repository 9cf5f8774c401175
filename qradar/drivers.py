"""The child processes of ``qradar run`` and ``qradar up``: a node in a process of its own
(``qradar COMMAND --config-json``: the command's own options, serialized), a driver per
sensor (``qradar drive``, joined to the run's zenoh session through a unix socket in the
run's directory), each supervised: started again with backoff when it dies."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable, TextIO

from pipeline.bus.session import BusConfig
from radar_driver.errors import RadarError, SetupError


def driver_bus(bus: BusConfig, tmp: Path) -> BusConfig:
    """How a driver process joins the run's zenoh session: through a unix socket in the
    run's directory (nothing listens on the network), or, when the run is itself a zenoh
    client, through the same endpoints."""
    if bus.mode == "client":
        return replace(bus, listen=())
    return BusConfig(mode="client", connect=(f"unixsock-stream/{tmp / 'zenoh.sock'}",), prefix=bus.prefix)


def last_json_object(lines) -> dict:
    """The last line of ``lines`` that is a JSON object (what a ``--json`` command ends
    with), or {}."""
    for line in reversed(list(lines)):
        try:
            out = json.loads(line)
        except ValueError:
            continue
        if isinstance(out, dict):
            return out
    return {}


class NodeProcess:
    """One node in a process of its own: ``qradar COMMAND --config-json CONFIG`` (``config``:
    the command's options as a lab file's mapping, :mod:`qradar.cli.lab`), started in a
    session of its own (a terminal's Ctrl-C reaches only its parent, which stops it) and
    told its parent's pid, so that it stops once its parent is gone, however that died.
    :class:`~pipeline.nodes.runtime.Runnable` by :func:`run_nodes`: ``start``, ``stop``
    (SIGTERM, then SIGKILL after a timeout), ``errors``, ``done`` (it has finished: its
    JSON summary came, or it exited). Its stderr lines go to ``log``, prefixed with its
    name; the last JSON object on its stdout is :attr:`final`.

    ``received()``: what the parent has received of it; with it the child keeps its zenoh
    session open after its summary until the parent has received everything the summary
    counts (``frames``, at most ``ack_timeout_s``), and only then is its stdin closed:
    zenoh can lose a put made just before its session closes. ``on_start(node)``: told
    once it has started (its pid)."""

    def __init__(self, command: str, config: dict, name: str, log: TextIO | None = sys.stderr,
                 received: Callable[[], int] | None = None, ack_timeout_s: float = 5.0,
                 on_start: Callable[["NodeProcess"], None] | None = None):
        self.command, self.config, self.name, self.on_start = command, config, name, on_start
        self.cmd = [sys.executable, "-m", "qradar", command, "--config-json", json.dumps(config)]
        self.received, self.ack_timeout_s = received, ack_timeout_s
        self.log = log
        self.errors: list[BaseException] = []
        self.done = threading.Event()
        self.counters: dict[str, int] = {}
        self._proc: subprocess.Popen | None = None
        self._stopping = False
        self._out: list[str] = []
        self._final: dict = {}  # the JSON object the child ends with (its summary, or its error)
        self._error_line = ""  # the one line of its error, on its stderr
        self._exited = threading.Event()
        self._threads: list[threading.Thread] = []

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    @property
    def final(self) -> dict:
        return dict(self._final)

    @property
    def returncode(self) -> int | None:
        return None if self._proc is None else self._proc.poll()

    def start(self) -> "NodeProcess":
        stdin = subprocess.DEVNULL if self.received is None else subprocess.PIPE
        self._proc = subprocess.Popen(self.cmd, stdin=stdin, stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, text=True, start_new_session=True)
        for target in (self._read_stdout, self._read_stderr, self._watch):
            t = threading.Thread(target=target, name=f"{self.name}-{target.__name__}", daemon=True)
            t.start()
            self._threads.append(t)
        if self.on_start is not None:
            self.on_start(self)
        return self

    def _read_stdout(self) -> None:
        for line in self._proc.stdout:
            self._out.append(line)
            del self._out[:-4]
            final = last_json_object([line])
            if final:
                self._final = final
                if "error" not in final:  # an error: done once _watch has it in errors (a supervisor reads them)
                    self.done.set()

    def _read_stderr(self) -> None:
        prefix = f"qradar {self.command}: error: "
        for line in self._proc.stderr:
            if line.startswith(prefix):  # said by its parent, in the error of its exit
                self._error_line = line[len(prefix):].strip()
                continue
            if self.log is not None:
                try:
                    self.log.write(f"[{self.name}] {line}")
                    self.log.flush()
                except (OSError, ValueError):
                    pass

    def _watch(self) -> None:
        rc = self._proc.wait()
        for t in self._threads[:2]:
            t.join(5.0)
        last = last_json_object(self._out)
        if "error" in last:  # a wrong set-up (SetupError: not to be restarted) or another failure
            kind = SetupError if last.get("setup") else RadarError
            self.errors.append(kind(f"{self.what} failed: {last['error']}"))
        elif rc != 0 and not self._stopping:
            why = f": {self._error_line}" if self._error_line else ""
            self.errors.append(RadarError(f"{self.what} exited with status {rc}{why}"))
        else:
            self.counters = {k: v for k, v in last.items() if isinstance(v, int)}
        self._exited.set()
        self.done.set()

    def _acknowledge(self) -> None:
        """Once the run has received the frames the driver counted (or after
        ack_timeout_s, said in the log), close its stdin: it closes its zenoh session."""
        sent = self._final.get("frames")
        if self.received is not None and isinstance(sent, int) and self._proc.poll() is None:
            deadline = time.monotonic() + self.ack_timeout_s
            while self.received() < sent and time.monotonic() < deadline:
                time.sleep(0.01)
            if self.received() < sent and self.log is not None:
                self.log.write(f"[{self.name}] the run received {self.received()} of its {sent} frames "
                               f"within {self.ack_timeout_s:g} s\n")
        if self._proc.stdin is not None:
            try:
                self._proc.stdin.close()
            except OSError:
                pass

    @property
    def what(self) -> str:
        """The node, in messages."""
        return f"node {self.name}"

    def stop(self, timeout_s: float = 10.0) -> None:
        """SIGTERM (a driver says GBYE; every node prints its summary) unless it has finished;
        the acknowledgement of its last frames; SIGKILL after ``timeout_s``."""
        if self._proc is None:
            return
        self._stopping = True
        if self._proc.poll() is None and not self.done.is_set():
            self._proc.send_signal(signal.SIGTERM)
        if self.received is not None:
            self.done.wait(timeout_s)  # its counters, or its exit
        self._acknowledge()
        try:
            self._proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self.errors.append(RadarError(f"{self.what} did not stop in {timeout_s} s"))
        self._exited.wait(timeout_s)

    def stats(self) -> dict[str, dict[str, int]]:
        return {self.name: dict(self.counters)}


class DriverProcess(NodeProcess):
    """One sensor's serial driver in its own process (``qradar drive``), publishing raw
    frames on ``bus`` (a zenoh client), handed its configuration (the sensor's ``spec``,
    the bus, a frame limit, the requests in flight) as ``drive``'s own options
    (:func:`qradar.cli.sensor.drive_config`). Stopped with SIGTERM, it says GBYE and prints
    its counters (JSON), which :meth:`stats` returns."""

    def __init__(self, spec, bus: BusConfig, frames: int | None = None, log: TextIO | None = sys.stderr,
                 received: Callable[[], int] | None = None, ack_timeout_s: float = 5.0, outstanding: int = 1):
        from .cli.sensor import drive_config  # the drive command's schema: the one definition of its keys

        self.sensor_id = spec.sensor_id
        config = drive_config(spec, bus, frames=frames, outstanding=outstanding, parent_pid=os.getpid(),
                              linger=received is not None)
        super().__init__("drive", config, f"driver {spec.sensor_id}", log=log, received=received,
                         ack_timeout_s=ack_timeout_s)

    @property
    def what(self) -> str:
        return f"the driver of {self.sensor_id}"

    def stats(self) -> dict[str, dict[str, int]]:
        return {self.sensor_id: dict(self.counters)}


#: the driver counters that are a state (the current driver's), not a count (summed over its drivers)
STATES = ("link_down",)

#: a driver that dies is started again after RESTART_BACKOFF_S, doubled after each death
#: that came within HEALTHY_S of its start, up to MAX_BACKOFF_S; after MAX_RESTARTS such
#: deaths in a row its sensor is given up (gone)
RESTART_BACKOFF_S = 0.5
MAX_BACKOFF_S = 30.0
HEALTHY_S = 30.0
MAX_RESTARTS = 5


class SupervisedDriver:
    """One sensor's driver (a :class:`DriverProcess`, or any :class:`Runnable` with
    ``done`` and ``errors``), started again with backoff when it dies, while the others go
    on: :class:`~pipeline.nodes.runtime.Runnable` by :func:`run_nodes`, whose ``errors``
    stay empty (a dead driver ends nothing else) but for a driver that ended with a
    :class:`~radar_driver.errors.SetupError` (its sensor's frames never assemble): that is
    not restarted, and ends the run. ``make(frames_done)`` makes a new driver
    (``frames_done``: the frames its sensor's earlier drivers delivered, for a frame
    limit). ``on_event(sensor_id, state, detail)``, if given, hears of each death
    (``state`` "restarting" or "gone") and restart ("running"): the run reports them
    (health, live line). What the run may read: ``restarts``, ``exits`` (why each died),
    ``state``, ``gone`` (given up after ``max_restarts`` quick deaths in a row: ``done``
    is then set too). ``what``: the supervised node in the messages ("its driver")."""

    name = "driver"

    def __init__(self, sensor_id: str, make: Callable[[int], object], frames_done: Callable[[], int] = lambda: 0,
                 on_event: Callable[[str, str, str], None] | None = None, backoff_s: float = RESTART_BACKOFF_S,
                 max_restarts: int = MAX_RESTARTS, healthy_s: float = HEALTHY_S, what: str = "its driver"):
        self.sensor_id, self.what = sensor_id, what
        self.make, self.frames_done, self.on_event = make, frames_done, on_event
        self.backoff_s, self.max_restarts, self.healthy_s = backoff_s, max_restarts, healthy_s
        self.errors: list[BaseException] = []  # stays empty: a dead driver is restarted, not raised
        self.done = threading.Event()
        self.gone = threading.Event()
        self.restarts = 0
        self.exits: list[str] = []  # why each driver died, in order
        self.quick_deaths = 0  # deaths in a row, each within healthy_s of its start
        self.started_at = time.monotonic()  # the current driver's start
        self.state = "starting"
        self.current = None
        self._counters: dict[str, int] = {}  # counters of earlier drivers that ended with them
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    def start(self) -> "SupervisedDriver":
        self.current = self.make(0).start()
        self.state = "running"
        self._thread = threading.Thread(target=self._supervise, name=f"supervise-{self.sensor_id}", daemon=True)
        self._thread.start()
        return self

    def _supervise(self) -> None:
        quick_deaths, backoff, started = 0, self.backoff_s, time.monotonic()
        while not self._stop.is_set():
            driver = self.current
            while not (driver.done.wait(0.1) or self._stop.is_set()):
                pass
            if self._stop.is_set():
                return
            if not driver.errors:  # it finished (its frame limit): the sensor is done
                self.done.set()
                return
            if isinstance(driver.errors[0], SetupError):  # a wrong set-up, which no restart mends: it
                self.errors.append(driver.errors[0])  # ends the run, in one line (run_nodes raises it)
                self.state = "failed"
                self.done.set()
                return
            why = str(driver.errors[0])
            try:
                driver.stop()  # what is left of it (an in-process driver's threads)
            except Exception:
                pass
            self._keep_counters(driver)
            lived_s = time.monotonic() - started
            if lived_s >= self.healthy_s:
                quick_deaths, backoff = 0, self.backoff_s
            quick_deaths += 1
            self.quick_deaths = quick_deaths
            with self._lock:
                self.exits.append(why)
            if quick_deaths > self.max_restarts:
                self.state = "gone"
                self._tell("gone", f"{why}; given up after {self.max_restarts} restarts in a row")
                self.gone.set()
                self.done.set()
                return
            self.state = "restarting"
            self._tell("restarting", f"{why}; restarting in {backoff:g} s (restart {self.restarts + 1})")
            if self._stop.wait(backoff):
                return
            backoff = min(backoff * 2, MAX_BACKOFF_S)
            try:
                with self._lock:
                    if self._stop.is_set():
                        return
                    self.current = self.make(self.frames_done()).start()
                    self.restarts += 1
            except Exception as exc:  # could not even start: counts as one more death
                self.current = _Failed(exc)
                continue
            started = self.started_at = time.monotonic()
            self.state = "running"
            self._tell("running", f"{self.what} started again (restart {self.restarts})")

    @property
    def failing(self) -> bool:
        """Its node died and has not stayed up since: given up, waiting to start again, or
        started again less than ``healthy_s`` ago after a quick death (a sensor that never works
        is failing whenever it is asked)."""
        return self.quick_deaths > 0 and (self.state != "running"
                                          or time.monotonic() - self.started_at < self.healthy_s)

    def _tell(self, state: str, detail: str) -> None:
        if self.on_event is not None:
            try:
                self.on_event(self.sensor_id, state, detail)
            except Exception:  # a report that fails ends no supervision
                pass

    def _keep_counters(self, driver) -> None:
        for counters in _driver_stats(driver).values():
            for k, v in counters.items():
                if k not in STATES:
                    self._counters[k] = self._counters.get(k, 0) + v

    def stop(self) -> None:
        with self._lock:
            self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        if self.current is not None:
            self.current.stop()

    def stats(self) -> dict[str, dict[str, int]]:
        """The counters of every driver of the sensor (those that died without their
        counters count nothing), with ``restarts``."""
        out = dict(self._counters)
        for counters in _driver_stats(self.current).values():
            for k, v in counters.items():
                out[k] = v if k in STATES else out.get(k, 0) + v
        return {self.sensor_id: {**out, "restarts": self.restarts}}


def _driver_stats(driver) -> dict[str, dict[str, int]]:
    """A driver's counters by sensor: a DriverProcess's, or an in-process SourceNode's source's."""
    if driver is None or isinstance(driver, _Failed):
        return {}
    return getattr(driver, "source", driver).stats()


class _Failed:
    """A driver that could not start: done at once, with the reason."""

    def __init__(self, exc: BaseException):
        self.errors = [exc]
        self.done = threading.Event()
        self.done.set()

    def stop(self) -> None:
        pass

    def stats(self) -> dict:
        return {}
