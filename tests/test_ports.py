"""``qradar ports`` and ``--sensor auto`` on real ports: the simulated K-MD2 on a real pty (a
SimulatorServer of this process, as ``qradar sim --link`` serves it) and over TCP (``qradar
sim --tcp`` in its own process, probed as ``socket://127.0.0.1:PORT``); ptys with something
else on them (a silent peer, an echo, a peer that speaks text); a port a running driver
holds. The probe writes INIT and GBYE only (every byte the peer received is decoded), leaves
the sensor at 115200 and serving the next session, and says busy without touching a held
port; without --probe nothing is written.

pyserial's list of adapters cannot list a pty, so where the host's adapters matter (the
listing, ``--sensor auto``) the ptys are handed in at the one place the list comes from,
``radar_driver.ports.list_serial_ports``; the probing behind it is real."""

from __future__ import annotations

import json
import os
import select
import subprocess
import threading
import time
import tty
from pathlib import Path

import pytest

from pipeline.errors import ParameterError
from qradar.cli import main
from qradar.run import RunConfig, run
from qradar.sensors import SensorSpec, check_sensor_specs, resolve_auto
from radar_driver import ports
from radar_driver.errors import DiscoveryError
from radar_driver.ports import Answer, PortInfo, probe_port, probe_ports
from radar_driver.protocol import Gbye, Init, StreamDecoder
from radar_driver.scene import SimScene, SimTarget, resolve_scene
from radar_driver.session import SensorSession, SessionConfig
from radar_driver.simulator import SimulatorServer
from zenoh_helpers import QRADAR, qradar

SCENE = SimScene((SimTarget(12.0, 20.0, 0.5),))
#: the probes' wait for a RESP here, s (a silent pty waits twice: INIT, then INIT again after the speed reset),
#: where a peer that never answers is probed too: the simulator of this process (its thread, on a loaded host)
#: answers INIT within it, and the echoing pty's thread echoes it (at 0.2 s, a host late by that made the K-MD2 silent)
TIMEOUT_S = 1.0
#: the probes' wait for a RESP where only simulated K-MD2s are probed: a probe ends at their RESP, so a bound
#: that says the answer is lost, not how fast it comes, costs nothing
ANSWER_TIMEOUT_S = 30.0
#: what a probe of a silent port may take at most: two waits, the GBYEs at the other speeds, slack for a busy
#: host (a probe without a bound would wait for ever)
SILENT_BOUND_S = 2 * TIMEOUT_S + 10.0


class Peer:
    """Something else than a K-MD2 on a real pty: ``silent`` reads and never answers,
    ``echo`` sends every byte back, ``text`` answers each read with a line of text. Keeps
    every byte it received (``received``). ``path``: the pty's slave, for the host."""

    def __init__(self, behaviour: str):
        self.behaviour = behaviour
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.received = bytearray()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)

    def __enter__(self) -> "Peer":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(5)
        os.close(self.master)
        os.close(self.slave)

    def _serve(self) -> None:
        while not self._stop.is_set():  # bounded by the test's own deadline: __exit__ stops it
            if not select.select([self.master], [], [], 0.02)[0]:
                continue
            try:
                data = os.read(self.master, 4096)
            except OSError:
                continue
            self.received += data
            if self.behaviour == "echo":
                os.write(self.master, data)
            elif self.behaviour == "text":
                os.write(self.master, b"ERROR: unknown command\r\n")


def messages(data: bytes) -> list[str]:
    """The kinds of message in bytes a host sent."""
    return [type(m).__name__ for m in StreamDecoder().feed(bytes(data))]


def nothing_arrives(fd: int, within_s: float = 0.3) -> bool:
    """No byte on ``fd`` (a pty's master) within ``within_s``: what a host wrote to the
    slave is readable at the master within that."""
    return not select.select([fd], [], [], within_s)[0]


@pytest.fixture
def link(tmp_path) -> Path:
    return tmp_path / "kmd2"


@pytest.fixture
def adapters(monkeypatch):
    """``adapters(paths)``: the host's serial adapters are these (ptys stand for USB
    adapters, each with its own made-up serial number)."""
    def set_adapters(paths):
        listed = [PortInfo(str(p), 0x0403, 0x6001, f"PTY{i}", "FT232R USB UART", "FTDI") for i, p in enumerate(paths)]
        monkeypatch.setattr(ports, "list_serial_ports", lambda: listed)
        return listed
    return set_adapters


# -- the probe on real ports -----------------------------------------------------------------------

def test_the_simulated_kmd2_on_a_pty_answers_and_then_serves_a_normal_session(link):
    """`qradar ports --probe LINK`: a K-MD2 (RESP 0 to INIT); the device saw INIT at 115200
    (no switch) and GBYE, no GNFD, and is at 115200; a session at 921600 then gets frames."""
    with SimulatorServer(SCENE, link_path=link, rate_hz=0) as sim:
        proc = qradar("ports", "--probe", str(link), "--json", "--timeout", ANSWER_TIMEOUT_S)
        assert proc.returncode == 0, proc.stderr
        out = json.loads(proc.stdout)
        assert out["kmd2"] == [str(link)]
        (entry,) = out["ports"]
        assert entry["probe"]["answer"] == "kmd2" and entry["probe"]["resp_code"] == 0
        assert entry["probe"]["resp"] == "OK" and entry["probe"]["elapsed_s"] < ANSWER_TIMEOUT_S
        dev = sim.devices[0]
        assert list(dev.events) == [("INIT", 115_200), ("SWITCH", 115_200), ("GBYE", 115_200)]
        assert dev.baud == 115_200 and "GNFD" not in dev.event_counts
        with SensorSession(SessionConfig(str(link), baud=921_600, reconnect=False)) as s:
            frames = list(s.frames(3))
        assert [f.seq for f in frames] == [0, 1, 2] and s.counters.reconnects == 0
        assert dev.baud == 115_200 and not sim.errors


def test_the_simulated_kmd2_over_tcp_answers_and_then_serves_a_normal_session(free_port):
    """`qradar sim --tcp PORT` in its own process, `qradar ports --probe socket://...`: a
    K-MD2, in the table; a session over the same URL then gets frames."""
    sim = subprocess.Popen([*QRADAR, "sim", "--tcp", str(free_port), "--rate", "0"], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    url = f"socket://127.0.0.1:{free_port}"
    try:
        assert url in sim.stdout.readline()
        proc = qradar("ports", "--probe", url, "--timeout", ANSWER_TIMEOUT_S)
        assert proc.returncode == 0, proc.stderr
        header, row, summary = proc.stdout.strip().splitlines()
        assert header.split() == ["PORT", "VID:PID", "SERIAL", "ANSWER", "WHY"]
        assert row.startswith(url) and " K-MD2 " in row and "RESP 0 (OK) to INIT at 115200 baud" in row
        assert summary.startswith(f"one K-MD2: {url}; use it with --sensor {url},id=NAME")
        assert proc.stderr == ""  # a probe is no session: no "connected to" line
        with SensorSession(SessionConfig(url, reconnect=False)) as s:
            assert len(list(s.frames(3))) == 3
    finally:
        sim.terminate()
        sim.wait(10)


@pytest.mark.parametrize("behaviour, answer, why", [
    ("silent", Answer.SILENT, "no RESP to INIT .* saw no message"),
    ("echo", Answer.OTHER, "our own INIT came back: the link echoes"),
    ("text", Answer.OTHER, "the other end said 'ERROR: unknown command.*': not a K-MD2"),
])
def test_something_else_on_a_pty_is_not_a_kmd2_within_the_timeout(behaviour, answer, why):
    """The peer got INIT and GBYE only (GBYE at the other speeds, for a sensor left there,
    and INIT once more), never a GNFD, and the answer came within two timeouts."""
    import re

    with Peer(behaviour) as peer:
        r = probe_port(peer.path, timeout_s=TIMEOUT_S)
    assert r.answer is answer and re.search(why, r.reason), r.line()
    assert r.elapsed_s < SILENT_BOUND_S and r.resp_code is None
    assert "\n" not in r.line()
    sent = messages(peer.received)
    assert sent[0] == "Init" and set(sent) == {"Init", "Gbye"}, sent
    assert sent.count("Init") <= 2


def test_a_port_held_by_a_running_driver_is_busy_and_left_alone(link):
    """A `qradar drive` process holds the pty (its lock): the probe says busy, naming the
    process, without configuring or writing the port; the driver's frames go on and the
    sensor saw no second INIT."""
    with SimulatorServer(SCENE, link_path=link, rate_hz=20) as sim:
        drive = subprocess.Popen([*QRADAR, "drive", "--port", str(link), "--no-publish"], stdout=subprocess.PIPE,
                                 stderr=subprocess.DEVNULL, text=True)
        try:
            assert drive.stdout.readline().startswith("frame")  # it holds the port
            speed = sim.links[0].host_baud()
            (r,) = probe_ports([str(link)], timeout_s=TIMEOUT_S)
            assert r.answer is Answer.BUSY, r.line()
            assert f"in use by process {drive.pid}" in r.reason and "qradar drive" in r.reason
            assert sim.links[0].host_baud() == speed == 2_000_000  # the line speed untouched
            for _ in range(3):
                assert drive.stdout.readline().startswith("frame")
            assert drive.poll() is None
        finally:
            drive.terminate()
            drive.wait(10)
        assert sim.devices[0].event_counts["INIT"] == 1 and not sim.errors


def test_ports_are_probed_at_once_and_reported_in_the_order_given(link, tmp_path):
    """Two silent ptys, a simulated K-MD2 and a missing device at once: each answer in its
    place, in about one silent probe's time rather than two."""
    with Peer("silent") as a, Peer("silent") as b, SimulatorServer(SCENE, link_path=link, rate_hz=0):
        missing = str(tmp_path / "ttyUSB9")
        t0 = time.monotonic()
        results = probe_ports([a.path, str(link), b.path, missing], timeout_s=TIMEOUT_S)
        wall_s = time.monotonic() - t0
    assert [r.answer for r in results] == [Answer.SILENT, Answer.KMD2, Answer.SILENT, Answer.ERROR]
    assert "no such device" in results[3].reason
    assert max(r.elapsed_s for r in results) < SILENT_BOUND_S
    assert wall_s < results[0].elapsed_s + results[2].elapsed_s  # one after the other would take the sum


# -- the listing writes nothing ----------------------------------------------------------------------

def test_without_probe_nothing_is_written(adapters, capsys):
    """`qradar ports` (table and --json) lists the adapters and writes no byte to them: the
    pty's master side receives nothing; with --probe the same port gets INIT."""
    with Peer("silent") as peer:
        adapters([peer.path])
        assert main(["ports"]) == 0
        table = capsys.readouterr().out
        assert peer.path in table and "0403:6001" in table and "PTY0" in table and "nothing was written" in table
        assert main(["ports", "--json"]) == 0
        (entry,) = json.loads(capsys.readouterr().out)["ports"]
        assert entry["device"] == peer.path and entry["vid_pid"] == "0403:6001" and entry["manufacturer"] == "FTDI"
        assert nothing_arrives(peer.master) and not peer.received
        assert main(["ports", "--probe", "--timeout", str(TIMEOUT_S)]) == 1  # every listed port, and none answers
        assert "silent" in capsys.readouterr().out
    assert messages(peer.received)[0] == "Init"


def test_the_hosts_own_list_is_pyserials(capsys):
    """Without a stand-in: `qradar ports --json` is pyserial's list (less absent UARTs), as dicts."""
    assert main(["ports", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["ports"] == [p.to_dict() for p in ports.list_serial_ports()]


# -- --sensor auto ---------------------------------------------------------------------------------

def test_auto_keeps_the_specs_other_keys():
    spec = SensorSpec.parse("auto,id=lab1,profile=kmd2-blocks,baud=921600")
    assert spec.is_auto and spec.sensor_id == "lab1" and spec.profile == "kmd2-blocks" and spec.baud == 921_600
    with pytest.raises(ParameterError, match="auto stands for the one K-MD2 found on this host"):
        check_sensor_specs((spec, SensorSpec.parse("auto,id=lab2")))


def test_auto_takes_the_one_kmd2_among_the_hosts_adapters(adapters, tmp_path, caplog):
    """A silent adapter and a K-MD2: auto is the K-MD2's port, said in one line; the other
    keys stay; the silent one got INIT, the K-MD2 was left at 115200."""
    with Peer("silent") as peer, SimulatorServer(SCENE, link_path=tmp_path / "kmd2", rate_hz=0) as sim:
        adapters([peer.path, tmp_path / "kmd2"])
        with caplog.at_level("INFO", logger="qradar.sensors"):
            (spec,) = resolve_auto((SensorSpec.parse("auto,id=lab1,ramps=2"),), timeout_s=TIMEOUT_S)
        assert spec.url == str(tmp_path / "kmd2") and spec.sensor_id == "lab1" and spec.ramps == 2
        (line,) = [r.getMessage() for r in caplog.records if r.name == "qradar.sensors"]
        assert line == f"--sensor 'auto,id=lab1,ramps=2': the K-MD2 on {tmp_path / 'kmd2'} (0403:6001, FTDI, " \
                       f"FT232R USB UART, serial PTY1)"
        assert sim.devices[0].baud == 115_200 and "GNFD" not in sim.devices[0].event_counts
        assert messages(peer.received)[0] == "Init"


def test_auto_skips_the_ports_other_sensors_name(adapters, tmp_path):
    with SimulatorServer(SCENE, link_path=tmp_path / "a", rate_hz=0) as a, \
            SimulatorServer(SCENE, link_path=tmp_path / "b", rate_hz=0) as b:
        adapters([tmp_path / "a", tmp_path / "b"])
        specs = resolve_auto((SensorSpec.parse(f"{tmp_path / 'a'},id=one"), SensorSpec.parse("auto,id=two")),
                             timeout_s=ANSWER_TIMEOUT_S)
        assert [s.url for s in specs] == [str(tmp_path / "a"), str(tmp_path / "b")]
        assert b.devices[0].event_counts["INIT"] == 1 and a.devices[0].event_counts["INIT"] == 0


def test_auto_without_a_kmd2_or_with_several_says_what_it_found(adapters, tmp_path):
    spec = (SensorSpec.parse("auto,id=lab1"),)
    adapters([])
    with pytest.raises(DiscoveryError, match=r"no serial port found on this host .*`qradar ports`"):
        resolve_auto(spec)
    with Peer("silent") as silent, Peer("echo") as echo:
        adapters([silent.path, echo.path])
        with pytest.raises(DiscoveryError) as exc:
            resolve_auto(spec, timeout_s=TIMEOUT_S)
        assert str(exc.value) == (f"--sensor 'auto,id=lab1': no K-MD2 answered on the 2 serial port(s) of this host "
                                  f"({silent.path}: silent; {echo.path}: not a K-MD2); `qradar ports --probe` says "
                                  f"why for each")
    with SimulatorServer(SCENE, link_path=tmp_path / "a", rate_hz=0), \
            SimulatorServer(SCENE, link_path=tmp_path / "b", rate_hz=0):
        adapters([tmp_path / "a", tmp_path / "b"])
        with pytest.raises(DiscoveryError, match=r"2 K-MD2s answer: .*/a \(0403:6001.*serial PTY0\), .*/b .*; give "
                                                 r"one its port, e.g. --sensor .*/a,id=lab1 \(`qradar ports --probe`"):
            resolve_auto(spec, timeout_s=ANSWER_TIMEOUT_S)


def test_run_with_sensor_auto_runs_on_the_kmd2_found(adapters, tmp_path):
    """`run` resolves auto before anything starts: its frames come from the K-MD2 found,
    and the summary names its port."""
    with SimulatorServer(resolve_scene("chamber-ideal"), link_path=tmp_path / "kmd2", rate_hz=20.0, seed=0,
                         hold_clock_when_late=True):
        adapters([tmp_path / "kmd2"])
        summary = run(RunConfig(sensor_specs=("auto,id=lab1",), frames=5, record=None, driver_process=False,
                                duration_s=30), live=None)
    assert summary["sensor_urls"] == {"lab1": str(tmp_path / "kmd2")}
    assert summary["driver"]["lab1"]["frames"] == 5 and summary["frames_targets"] == 5
