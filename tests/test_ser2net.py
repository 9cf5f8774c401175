"""The driver through a real ser2net (4.x) in front of the simulated K-MD2's pty: raw TCP
(``socket://``) and RFC 2217 (``rfc2217://...?ign_set_control``), with the YAML of
docs/chamber.md (tests/ser2net_helpers.py). Skipped without ser2net unless
QRADAR_REQUIRE_SER2NET=1 (CI), where a missing ser2net fails.

The simulated K-MD2 reads the host's line speed from the pty's terminal settings, so
what ser2net does to the pty (and only that) decides whether a baud switch arrives."""

import re
import subprocess
import socket
import time
from pathlib import Path

import numpy as np
import pytest

import ser2net_helpers
from radar_driver.session import SensorSession, SessionConfig
from radar_driver.simulator import SimulatorServer
from ser2net_helpers import HOST, REQUIRE_ENV, listening_addresses, require_ser2net, ser2net_for, ser2net_yaml
from test_session import LSB, SCENE, expected_frame
from zenoh_helpers import QRADAR

ROOT = Path(__file__).resolve().parents[1]
#: every test here ends well within this (each takes about a second; a loaded host's bound, not a speed)
BOUND_S = 60.0


@pytest.fixture
def link(tmp_path) -> Path:
    """The simulated K-MD2's pty link; ser2net's YAML and log go beside it (kept by pytest
    for a failed test)."""
    return tmp_path / "kmd2"


def session(url: str, **kw) -> SensorSession:
    kw.setdefault("reconnect_timeout_s", 5.0)
    return SensorSession(SessionConfig(url, **kw))


def check_frames(frames, n: int) -> None:
    gamma = expected_frame(SCENE)
    assert len(frames) == n and [f.seq for f in frames] == list(range(n))
    for f in frames:
        assert f.data.shape == (512, 2) and np.abs(f.data - gamma).max() <= LSB
        assert f.counters[1] == f.counters[0] + 1


def test_raw_tcp_40_frames(link):
    t0 = time.monotonic()
    with SimulatorServer(SCENE, link_path=link, rate_hz=0) as sim, ser2net_for(link, "raw", workdir=link.parent) as s2n:
        assert s2n.url == f"socket://127.0.0.1:{s2n.port}"
        assert listening_addresses(s2n.port) == {HOST}  # nothing beyond the loopback
        with session(s2n.url) as s:  # the default options: a socket stays at 115200
            assert s.config.line_baud == 115_200
            frames = list(s.frames(40))
        assert not sim.errors
    check_frames(frames, 40)
    c = s.counters
    assert c.reconnects == 0 and c.dropped == 0 and c.resyncs == 0 and c.timeouts == 0
    events = sim.devices[0].events
    assert events[:2] == [("INIT", 115_200), ("SWITCH", 115_200)]
    assert events[2:-1] == [("GNFD", 115_200)] * 80
    assert events[-1] == ("GBYE", 115_200)
    assert time.monotonic() - t0 < BOUND_S


def test_rfc2217_switches_the_pty_to_2M_and_says_gbye_on_close(link):
    t0 = time.monotonic()
    with SimulatorServer(SCENE, link_path=link, rate_hz=0) as sim, ser2net_for(link, "rfc2217", workdir=link.parent) as s2n:
        assert s2n.url == f"rfc2217://127.0.0.1:{s2n.port}?ign_set_control"
        assert listening_addresses(s2n.port) == {HOST}
        bare = s2n.url.split("?")[0]  # the driver adds ign_set_control itself
        with session(bare) as s:  # the default rate, 2 000 000
            assert s.config.line_baud == 2_000_000
            # ser2net applied the client's SET-BAUDRATE to the pty's terminal settings
            assert sim.links[0].host_baud() == 2_000_000
            frames = list(s.frames(40))
        assert not sim.errors
    check_frames(frames, 40)
    assert s.counters.reconnects == 0 and s.counters.timeouts == 0
    dev = sim.devices[0]
    assert dev.events[:2] == [("INIT", 115_200), ("SWITCH", 2_000_000)]
    assert dev.events[2:-1] == [("GNFD", 2_000_000)] * 80  # the device saw the host at 2 M
    assert dev.events[-1] == ("GBYE", 2_000_000)
    assert dev.baud == 115_200  # GBYE took the sensor back to its power-up rate
    assert time.monotonic() - t0 < BOUND_S


@pytest.mark.parametrize("kind", ["raw", "rfc2217"])
def test_the_driver_reconnects_after_ser2net_restarts(link, kind):
    with SimulatorServer(SCENE, link_path=link, rate_hz=0) as sim, ser2net_for(link, kind, workdir=link.parent) as s2n:
        frames = []
        with session(s2n.url, reconnect_timeout_s=BOUND_S) as s:  # the default options
            for f in s.frames(12):
                frames.append(f)
                if len(frames) == 5:
                    s2n.restart()  # ser2net goes away and comes back on the same port
                    t_restart = time.monotonic()
                elif len(frames) == 6:
                    back_after_s = time.monotonic() - t_restart
        assert not sim.errors
    assert back_after_s < BOUND_S
    assert s.counters.reconnects == 1
    check_frames(frames, 12)
    names = [e for e, _ in sim.devices[0].events]
    assert sim.devices[0].event_counts["INIT"] == 2
    if kind == "rfc2217":
        # the sensor stayed at 2 M (no GBYE: the link dropped); the new INIT at 115200 was
        # not understood, and the driver's GBYE at every rate through RFC 2217 released it
        assert ("BAUD_MISMATCH", 115_200) in sim.devices[0].events
    else:
        # raw TCP cannot change the line: the sensor is asked for 115200 only, every time
        events = sim.devices[0].events
        assert all(b == 115_200 for e, b in events if e in ("INIT", "SWITCH")), events
        # ser2net sets the pty's termios as it closes and reopens it; the simulator reads
        # them when bytes arrive, so a request in flight at the restart may meet them
        # (seen once on a loaded host): at most the restart's, never a lasting mismatch
        assert names.count("BAUD_MISMATCH") <= 2 and names[-1] != "BAUD_MISMATCH", events


def test_a_stale_client_is_kicked_off(link):
    """kickolduser: a client that never left (a half-open connection, a hung driver)
    does not lock the sensor out."""
    with SimulatorServer(SCENE, link_path=link, rate_hz=0), ser2net_for(link, "raw", workdir=link.parent) as s2n:
        stale = socket.create_connection((HOST, s2n.port), timeout=2.0)
        try:
            with session(s2n.url) as s:
                frames = list(s.frames(3))
            assert stale.recv(1) == b""  # ser2net closed the old connection
        finally:
            stale.close()
    check_frames(frames, 3)


def test_raw_tcp_with_an_explicit_fast_baud_stays_at_115200(link, caplog):
    """A --baud that a socket cannot follow is ignored with a warning (no INIT to 2 M,
    which would leave the sensor unreachable behind ser2net's fixed 115200)."""
    with SimulatorServer(SCENE, link_path=link, rate_hz=0) as sim, \
            ser2net_for(link, "raw", workdir=link.parent) as s2n:
        with caplog.at_level("WARNING", logger="qradar.driver"), \
                session(s2n.url, baud=2_000_000, reconnect=False, timeout_s=5.0) as s:
            frames = list(s.frames(3))
    check_frames(frames, 3)
    assert "baud 2000000 ignored, staying at 115200" in caplog.text
    assert ("SWITCH", 2_000_000) not in sim.devices[0].events


def test_the_chamber_guide_shows_the_tested_yaml():
    """docs/chamber.md shows, verbatim, the YAML these tests run (for its device and port)."""
    text = (ROOT / "docs" / "chamber.md").read_text()
    blocks = re.findall(r"```yaml\n(.*?)```", text, re.S)
    shown = {}
    for block in blocks:
        m = re.search(r"accepter: (?:telnet\(rfc2217\),)?tcp\(nodelay\),([^,\s]+),(\d+)\n"
                      r"  connector: serialdev,(\S+?),", block)
        if m:
            kind = "rfc2217" if "telnet(rfc2217)" in block else "raw"
            shown[kind] = (block, ser2net_yaml(m.group(3), kind, int(m.group(2)), host=m.group(1)))
    assert set(shown) == {"raw", "rfc2217"}, "docs/chamber.md lost a ser2net YAML"
    for kind, (block, tested) in shown.items():
        assert block == tested, f"docs/chamber.md's {kind} YAML is not the tested one"


def test_a_missing_ser2net_skips_or_fails_in_ci(monkeypatch):
    monkeypatch.setattr(ser2net_helpers.shutil, "which", lambda name: None)
    monkeypatch.setattr(ser2net_helpers, "SBIN_PATHS", ())
    monkeypatch.delenv(REQUIRE_ENV, raising=False)
    with pytest.raises(pytest.skip.Exception, match="ser2net is not installed"):
        require_ser2net()
    monkeypatch.setenv(REQUIRE_ENV, "1")
    with pytest.raises(pytest.fail.Exception, match="QRADAR_REQUIRE_SER2NET=1 requires"):
        require_ser2net()


@pytest.mark.parametrize("kind", ["raw", "rfc2217"])
def test_ser2net_that_cannot_open_its_device_is_named(tmp_path, kind):
    # "the other end hung up during the set-up" (raw: with what ser2net said, when pyserial
    # passed it on) or, for RFC 2217 when the hang-up beats the negotiation, "did not
    # negotiate RFC 2217"; both name the likely cause
    says = "ser2net could not open its device?"
    with ser2net_for(tmp_path / "no-such-device", kind, workdir=tmp_path) as s2n:
        proc = subprocess.run([*QRADAR, "drive", "--port", s2n.url.split("?")[0],
                               "--no-publish", "--frames", "1"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and says in proc.stderr and "Traceback" not in proc.stderr, proc.stderr


def test_an_rfc2217_url_on_a_raw_port_says_so(link):
    with SimulatorServer(SCENE, link_path=link, rate_hz=0), ser2net_for(link, "raw", workdir=link.parent) as s2n:
        url = s2n.url.replace("socket://", "rfc2217://")
        proc = subprocess.run([*QRADAR, "drive", "--port", url, "--no-publish", "--frames", "1"],
                              capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert "did not negotiate RFC 2217 (a raw TCP port rather than telnet(rfc2217)?" in proc.stderr, proc.stderr
