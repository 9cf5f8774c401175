"""The driver processes of ``qradar run``: one ``qradar drive`` per sensor, joined to the
run's zenoh session through a unix socket in the run's directory."""

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


class DriverProcess:
    """One sensor's serial driver in its own process (``qradar drive``), publishing raw
    frames on ``bus`` (a zenoh client). :class:`~pipeline.nodes.runtime.Runnable` by :func:`run_nodes`: ``start``,
    ``stop``, ``errors``, ``done`` (the driver has finished: its counters came, or it
    exited). Stopped with SIGTERM, it says GBYE and prints its counters (JSON), which
    :meth:`stats` returns; its log lines go to ``log``.

    ``received()``: the raw frames of this sensor the run has received. With it the
    driver keeps its zenoh session open after its counters (``--linger-stdin``) until
    the run has received every frame they count (at most ``ack_timeout_s``), and only
    then is its stdin closed: zenoh can lose a put made just before its session
    closes, and the last frames of a stop are just that."""

    name = "driver"

    def __init__(self, url: str, sensor_id: str, baud: int | None, ramps: int, bus: BusConfig,
                 frames: int | None = None, log: TextIO | None = sys.stderr, profile: str | None = None,
                 received: Callable[[], int] | None = None, ack_timeout_s: float = 5.0, outstanding: int = 1,
                 chirp_select: str = "first"):
        self.sensor_id = sensor_id
        self.cmd = [sys.executable, "-m", "qradar", "drive", "--port", url, "--sensor-id", sensor_id,
                    "--ramps", str(ramps), "--json", "--quiet", "--mode", bus.mode, "--prefix", bus.prefix,
                    "--parent-pid", str(os.getpid())]  # it stops when this process dies, however
        self.cmd += [a for ep in bus.connect for a in ("--connect", ep)]
        if bus.config_file is not None:
            self.cmd += ["--zenoh-config", str(bus.config_file)]
        if baud is not None:
            self.cmd += ["--baud", str(baud)]
        if frames is not None:
            self.cmd += ["--frames", str(frames)]
        if outstanding != 1:
            self.cmd += ["--outstanding", str(outstanding)]
        if profile is not None:
            self.cmd += ["--profile", str(profile)]
        if chirp_select != "first":
            self.cmd += ["--chirp-select", chirp_select]
        if received is not None:
            self.cmd.append("--linger-stdin")
        self.received, self.ack_timeout_s = received, ack_timeout_s
        self.log = log
        self.errors: list[BaseException] = []
        self.done = threading.Event()
        self.counters: dict[str, int] = {}
        self._proc: subprocess.Popen | None = None
        self._stopping = False
        self._out: list[str] = []
        self._final: dict = {}  # the JSON object the driver ends with (counters or error)
        self._exited = threading.Event()
        self._threads: list[threading.Thread] = []

    def start(self) -> "DriverProcess":
        stdin = subprocess.DEVNULL if self.received is None else subprocess.PIPE
        self._proc = subprocess.Popen(self.cmd, stdin=stdin, stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, text=True, start_new_session=True)
        for target in (self._read_stdout, self._read_stderr, self._watch):
            t = threading.Thread(target=target, name=f"driver-{self.sensor_id}-{target.__name__}", daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def _read_stdout(self) -> None:
        for line in self._proc.stdout:
            self._out.append(line)
            del self._out[:-4]
            final = last_json_object([line])
            if final:
                self._final = final
                self.done.set()

    def _read_stderr(self) -> None:
        for line in self._proc.stderr:
            if self.log is not None and not line.startswith("qradar drive: error:"):  # the run says it itself
                self.log.write(f"[driver {self.sensor_id}] {line}")
                self.log.flush()

    def _watch(self) -> None:
        rc = self._proc.wait()
        for t in self._threads[:2]:
            t.join(5.0)
        last = last_json_object(self._out)
        if "error" in last:  # a wrong set-up (SetupError: not to be restarted) or another failure
            kind = SetupError if last.get("setup") else RadarError
            self.errors.append(kind(f"the driver of {self.sensor_id} failed: {last['error']}"))
        elif rc != 0 and not self._stopping:
            self.errors.append(RadarError(f"the driver of {self.sensor_id} exited with status {rc}"))
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
                self.log.write(f"[driver {self.sensor_id}] the run received {self.received()} of its {sent} frames "
                               f"within {self.ack_timeout_s:g} s\n")
        if self._proc.stdin is not None:
            try:
                self._proc.stdin.close()
            except OSError:
                pass

    def stop(self, timeout_s: float = 10.0) -> None:
        """SIGTERM (the driver says GBYE and prints its counters) unless it has finished;
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
            self.errors.append(RadarError(f"the driver of {self.sensor_id} did not stop in {timeout_s} s"))
        self._exited.wait(timeout_s)

    def stats(self) -> dict[str, dict[str, int]]:
        return {self.sensor_id: dict(self.counters)}
