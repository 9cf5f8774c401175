"""The driver against the simulated K-MD2 through a real pseudo-terminal (and TCP): the link,
the reader thread, polling and reconnect. Frame assembly and its counters alone:
tests/test_assembly.py."""

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.dsp.localize import localize
from radar_driver.model import RadarConfig, simulate_frames
from radar_driver.protocol import Done, Gbye, Gnfd, Init, OtherMessage, Radc, Resp, RespCode, StreamDecoder, encode
from radar_driver.scene import SimScene, SimTarget, resolve_scene
from radar_driver.session import (
    LinkError,
    SensorResponseError,
    SensorSession,
    SensorTimeout,
    SessionConfig,
)
from radar_driver.simulator import SimFaults, SimulatedKMD2, SimulatorServer
from radar_driver.source import RawFrame
from zenoh_helpers import QRADAR, wait_until

LSB = np.sqrt(2) * 0.5 / 2048 * 1.001  # half an ADC step on I and Q
SCENE = SimScene((SimTarget(12.0, 20.0, 0.5), SimTarget(4.8, -35.0, 0.1, phase_deg=40.0)))


def expected_frame(scene: SimScene) -> np.ndarray:
    r = np.array([[t.range_m for t in scene.targets]])
    a = np.array([[t.angle_deg for t in scene.targets]])
    x = np.array([[t.amplitude * np.exp(1j * np.deg2rad(t.phase_deg)) for t in scene.targets]])
    return simulate_frames(r, a, x, scene.radar)[0]


@pytest.fixture
def link(tmp_path) -> Path:
    return tmp_path / "kmd2"


def session(url, **kw) -> SensorSession:
    kw.setdefault("reconnect_timeout_s", 5.0)
    return SensorSession(SessionConfig(str(url), **kw))


def test_frames_equal_the_model_within_adc_quantization(link):
    with SimulatorServer(SCENE, link_path=link, rate_hz=0) as sim, session(link) as s:
        frames = list(s.frames(10))
    gamma = expected_frame(SCENE)
    assert len(frames) == 10
    for i, f in enumerate(frames):
        assert f.seq == i and f.data.shape == (512, 2) and f.data.dtype == np.complex64
        assert np.abs(f.data - gamma).max() <= LSB
        assert f.counters == (2 * i, 2 * i + 1)
    assert s.counters.frames == 10 and s.counters.dropped == 0 and s.counters.resyncs == 0
    assert s.counters.bytes == 20 * (12 + 2056 + 12) + 2 * 12  # RESP, RADC, DONE per ramp; INIT, GBYE RESPs
    assert not sim.errors


def test_init_baud_switch_gnfd_and_gbye_happen_in_order(link):
    with SimulatorServer(SCENE, link_path=link, rate_hz=0) as sim:
        with session(link, baud=921_600) as s:
            list(s.frames(2))
        s.close()  # idempotent
        s.close()
        events = [e for e in sim.devices[0].events]
    assert events[0] == ("INIT", 115_200)  # INIT at 115200 (the host's line speed)
    assert events[1] == ("SWITCH", 921_600)
    assert events[2:6] == [("GNFD", 921_600)] * 4  # the host switched too
    assert events[-1] == ("GBYE", 921_600)
    assert sim.devices[0].baud == 115_200  # GBYE returned the sensor to 115200


def test_a_sensor_left_at_high_speed_is_recovered(link):
    with SimulatorServer(SCENE, link_path=link, rate_hz=0) as sim:
        # a host that dies without GBYE: a driver process killed with SIGKILL
        crashed = subprocess.Popen([*QRADAR, "drive", "--port", str(link), "--baud",
                                    "3000000", "--no-publish"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                   text=True)
        try:
            assert crashed.stdout.readline().startswith("frame")  # it runs
        finally:
            crashed.kill()
            crashed.wait(10)
        assert sim.devices[0].baud == 3_000_000
        with session(link) as s:
            assert len(list(s.frames(3))) == 3
    assert ("BAUD_MISMATCH", 115_200) in sim.devices[0].events


@pytest.mark.parametrize("transport", ["pty", "tcp"])
def test_device_disconnects_and_returns_and_the_driver_reconnects(link, transport):
    faults = SimFaults(disconnect_after_frames=5, reconnect_after_s=0.3)
    kw = {"link_path": link} if transport == "pty" else {"tcp_port": 0}
    with SimulatorServer(SCENE, rate_hz=0, faults=faults, **kw) as sim:
        url = link if transport == "pty" else f"socket://127.0.0.1:{sim.tcp_port}"
        t0 = time.monotonic()
        with session(url) as s:
            frames = list(s.frames(12))
        assert time.monotonic() - t0 < 20
    assert s.counters.reconnects == 1
    assert len(frames) == 12 and [f.seq for f in frames] == list(range(12))
    gamma = expected_frame(SCENE)
    assert all(np.abs(f.data - gamma).max() <= LSB for f in frames)
    counts = sim.devices[0].event_counts
    assert counts["INIT"] == 2 and counts["DISCONNECT"] == 1


def test_paced_at_the_frame_rate(link):
    with SimulatorServer(SCENE, link_path=link, rate_hz=20), session(link) as s:
        t0 = time.monotonic()
        list(s.frames(6))
        elapsed = time.monotonic() - t0
    # 6 frames at 20 frames/s are 0.25 s apart at the least: paced, never faster (a busy host may be slower,
    # so no upper bound)
    assert elapsed > 0.2


def test_typed_errors(tmp_path):
    with pytest.raises(LinkError, match="cannot open .*nowhere"):
        session(tmp_path / "nowhere").open()
    master, slave = os.openpty()  # a port where nothing answers
    try:
        with pytest.raises(SensorTimeout, match="no RESP to INIT .* within 0.10 s; saw no message"):
            session(os.ttyname(slave), timeout_s=0.1).open()
    finally:
        os.close(master)
        os.close(slave)
    s = session(tmp_path / "nowhere", reconnect_timeout_s=0.3)
    with pytest.raises(LinkError, match="could not reconnect .* within 0.3 s"):
        list(s.frames(1))


def test_device_answers_errors_like_the_sensor():
    dev = SimulatedKMD2(SCENE, rate_hz=0)
    d = StreamDecoder()
    assert d.feed(b"".join(r.data for r in dev.receive(encode(Init(9))))) == [Resp(RespCode.INVALID_PARAMETER)]
    assert d.feed(b"".join(r.data for r in dev.receive(encode(OtherMessage(b"PDAT"))))) == [
        Resp(RespCode.UNKNOWN_COMMAND)]
    assert d.feed(b"".join(r.data for r in dev.receive(encode(Gnfd(0x100))))) == [Resp(RespCode.INVALID_PARAMETER)]
    err = SensorResponseError("INIT", 2)
    assert "RESP 2 (INVALID_PARAMETER)" in str(err)


@pytest.mark.parametrize("garbage", [False, True])
def test_cli_sim_and_drive_in_two_processes(link, tmp_path, garbage):
    # the ideal chamber: this test's point is the two processes and the protocol, and that the frames carry
    # the scene's strong reflector (the front end's leakage would outshine it: tests/test_frontend.py)
    sim_cmd = [*QRADAR, "sim", "--scene", "chamber-ideal", "--link", str(link)]
    if garbage:
        sim_cmd += ["--garbage", "0.2"]
    sim = subprocess.Popen(sim_cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_until(link.exists, 20, f"{link} to appear")
        out = tmp_path / "frames.npz"
        drive = subprocess.run(
            [*QRADAR, "drive", "--port", str(link), "--frames", "40", "--json",
             "--out", str(out)], capture_output=True, text=True, timeout=120)
        assert drive.returncode == 0, drive.stderr
        counters = json.loads(drive.stdout.strip().splitlines()[-1])
        assert counters["frames"] == 40 and counters["reconnects"] == 0
        assert set(counters) >= {"frames", "bytes", "resyncs", "skipped_bytes", "dropped", "reconnects"}
        if garbage:
            assert counters["resyncs"] > 0 and counters["skipped_bytes"] > 0
        else:
            assert counters["resyncs"] == 0
        saved = np.load(out)
        frames = saved["frames"]
        assert frames.shape == (40, 512, 2)
        assert saved["seq"].tolist() == list(range(40))
        chamber = resolve_scene("chamber-ideal")  # radar_driver/scenes/chamber-ideal.toml
        radar = RadarConfig.from_dict(json.loads(str(saved["radar_config"])))
        assert radar == chamber.radar and radar.ramps_per_frame == 2
        # no clipping: no I or Q sample at either end of the 12-bit ADC (codes 0 and 4095)
        assert -1.0 < frames.real.min() and frames.real.max() < 2047 / 2048
        assert -1.0 < frames.imag.min() and frames.imag.max() < 2047 / 2048
        # the chamber scene's strong reflector dominates every frame: PBP's strongest detection
        # is it, within one range bin and a few degrees
        strong = max(chamber.targets, key=lambda t: t.amplitude)
        assert strong.amplitude > 2 * min(t.amplitude for t in chamber.targets)
        det = localize(frames, radar, k=len(chamber.targets))
        assert np.all(np.abs(det.range_m[:, 0] - strong.range_m) <= radar.range_resolution_m), det.range_m[:, 0]
        assert np.all(np.abs(det.angle_deg[:, 0] - strong.angle_deg) <= 3.0), det.angle_deg[:, 0]
    finally:
        sim.send_signal(signal.SIGINT)
        try:
            sim.wait(10)
        except subprocess.TimeoutExpired:
            sim.kill()
    assert sim.returncode == 0, sim.stderr.read()
    assert not link.exists()  # the symlink is removed on exit


def test_socket_links_stay_at_the_start_up_speed_with_the_default_options(caplog):
    """Ethernet or raw ser2net: no baud switch (INIT asks for 115200), said in the log;
    an explicit --baud is ignored with a warning; GBYE on close."""
    with SimulatorServer(SCENE, tcp_port=0, rate_hz=0) as sim:
        url = f"socket://127.0.0.1:{sim.tcp_port}"
        with caplog.at_level("INFO", logger="qradar.driver"), session(url) as s:
            frames = list(s.frames(4))
        assert len(frames) == 4 and s.counters.reconnects == 0
        assert "socket link: the line speed stays at 115200 baud" in caplog.text
        with caplog.at_level("WARNING", logger="qradar.driver"), session(url, baud=3_000_000) as s:
            assert len(list(s.frames(2))) == 2
        assert "cannot change the line speed: baud 3000000 ignored, staying at 115200" in caplog.text
        events = sim.devices[0].events
    assert ("SWITCH", 115_200) in events and not any(e == "SWITCH" and b != 115_200 for e, b in events)
    assert [e for e in events if e[0] == "GBYE"] == [("GBYE", None)] * 2  # one per session
    assert sim.devices[0].baud == 115_200


def test_the_cli_drives_a_tcp_sensor_with_the_default_options(tmp_path, free_port):
    sim = subprocess.Popen([*QRADAR, "sim", "--tcp", str(free_port), "--rate", "0"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert "socket://127.0.0.1" in sim.stdout.readline()
        drive = subprocess.run([*QRADAR, "drive", "--port", f"socket://127.0.0.1:{free_port}",
                                "--frames", "10", "--no-publish", "--json", "--quiet"],
                               capture_output=True, text=True, timeout=60)
        assert drive.returncode == 0, drive.stderr
        c = json.loads(drive.stdout.strip().splitlines()[-1])
        assert c["frames"] == 10 and c["reconnects"] == 0 and c["timeouts"] == 0
        assert "the line speed stays at 115200" in drive.stderr
    finally:
        sim.send_signal(signal.SIGINT)
        sim.wait(10)


@pytest.mark.parametrize("how", ["SIGTERM", "SIGINT"])
def test_a_signal_leaves_the_sensor_at_its_start_up_speed(link, how):
    with SimulatorServer(SCENE, link_path=link, rate_hz=20) as sim:
        drive = subprocess.Popen([*QRADAR, "drive", "--port", str(link), "--baud", "921600",
                                  "--no-publish"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert drive.stdout.readline().startswith("frame")
            assert sim.devices[0].baud == 921_600
            drive.send_signal(getattr(signal, how))
            out, err = drive.communicate(timeout=15)
        finally:
            drive.kill()
        assert drive.returncode == 0, err
        assert "counters: frames=" in out
        wait_until(lambda: sim.devices[0].events[-1][0] == "GBYE", 5, "GBYE")
        assert sim.devices[0].baud == 115_200


def test_an_error_without_reconnect_says_goodbye_first(link):
    """Every RADC cut short (the decoder refuses it at the DONE header inside it, so every
    answer lacks a whole RADC): the session ends with a timeout (reconnect off), and the
    sensor got a GBYE before the error reached the caller."""
    with SimulatorServer(SCENE, link_path=link, rate_hz=0, faults=SimFaults(truncate_prob=1.0)) as sim:
        s = session(link, reconnect=False, baud=921_600)
        with pytest.raises(SensorTimeout, match="GNFD answers in a row from .* lacked a whole RADC"):
            with s:
                list(s.frames(2))
        events = sim.devices[0].events
        assert events[-1] == ("GBYE", 921_600) and sim.devices[0].baud == 115_200


def test_a_warning_per_reconnect_attempt_with_the_time_since_the_last_frame(link, caplog):
    faults = SimFaults(disconnect_after_frames=3, reconnect_after_s=1.0)
    with SimulatorServer(SCENE, link_path=link, rate_hz=0, faults=faults):
        with caplog.at_level("WARNING", logger="qradar.driver"), session(link, backoff_s=0.1, max_backoff_s=0.2) as s:
            frames = list(s.frames(6))
    assert len(frames) == 6 and s.counters.reconnects == 1
    attempts = [r.getMessage() for r in caplog.records if "reconnect attempt" in r.getMessage()]
    assert 2 <= len(attempts) <= 15, attempts
    assert all(" s since the last frame" in a and str(link) in a for a in attempts)
    assert any("reconnected after" in r.getMessage() for r in caplog.records)


def test_a_link_that_stays_down_is_said_a_few_times_then_every_two_minutes(monkeypatch, caplog):
    """A sensor unplugged for an hour, its driver retrying every 2 s: a warning for each of the
    first 6 attempts (the last says what follows), then one every 120 s, not 1 800 lines."""
    import types

    import radar_driver.session as session_mod

    clock = [1000.0]
    monkeypatch.setattr(session_mod, "time", types.SimpleNamespace(monotonic=lambda: clock[0]))
    said = None
    with caplog.at_level("WARNING", logger="qradar.driver"):
        for attempt in range(1, 1801):
            said = session_mod.say_down("/dev/ttyUSB0", OSError("gone"), attempt, 990.0, 2.0, said)
            clock[0] += 2.0
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 6 + 29, len(lines)  # then one every 120 s of the hour's 3 588 s left
    assert "reconnect attempt 6, 20.0 s since the last frame; next in 2.00 s (then a line every 120 s" in lines[5]
    assert "reconnect attempt 7," not in "".join(lines) and "reconnect attempt 66, 140.0 s since" in lines[6]
    # a new error (the port back, another's: permission denied) is said at once
    caplog.clear()
    with caplog.at_level("WARNING", logger="qradar.driver"):
        said = session_mod.say_down("/dev/ttyUSB0", OSError("permission denied"), 1801, 990.0, 2.0, said)
    assert [r.getMessage() for r in caplog.records][0].startswith("/dev/ttyUSB0 is down (permission denied)")


def test_the_simulated_line_takes_as_long_as_a_real_one(link):
    """With line_rate, a 2 080-byte RADC takes 11 bits a byte at the host's speed: 199 ms
    at 115200 (so a 115200 line carries 2.5 frames/s, never the sensor's 20), 11 ms at
    2 Mbaud. These are lower bounds: the line cannot be faster."""
    radc_bytes = 8 + 2048 + 12 + 12  # RADC, DONE and RESP of one poll
    with SimulatorServer(SCENE, link_path=link, rate_hz=0, line_rate=True) as sim:
        with session(link, baud=115_200) as s:
            t0 = time.monotonic()
            list(s.frames(2))
            slow = time.monotonic() - t0
        with session(link, baud=2_000_000) as s:
            t0 = time.monotonic()
            list(s.frames(10))
            fast = time.monotonic() - t0
        assert not sim.errors
    assert slow >= 4 * radc_bytes * 11 / 115_200 * 0.99  # 4 ramps: 0.80 s
    assert fast >= 20 * radc_bytes * 11 / 2_000_000 * 0.99  # 20 ramps: 0.23 s


def test_sessions_one_after_another_at_115200_on_one_pty(link):
    """A Linux pty has no parity and refuses settings that change nothing else: the
    second session at 115200 8E1 on the same pty opens all the same."""
    with SimulatorServer(SCENE, link_path=link, rate_hz=0) as sim:
        for _ in range(3):
            with session(link, baud=115_200) as s:
                assert len(list(s.frames(1))) == 1
        assert not sim.errors


@pytest.mark.parametrize("outstanding", [1, 2])
def test_requests_in_flight_ask_for_exactly_the_frames_wanted(link, outstanding):
    """One or two GNFDs in flight: every frame intact, not a frame beyond those asked for,
    and every GNFD answered (a stop leaves none unanswered). A GNFD beyond the 16 ramps of
    the 8 frames goes out only for a counted loss: a host late by a RADC period (a loaded
    machine) finds the sensor's counter moved on; the partial frame that the gap broke is
    discarded (``discarded_ramps``) and its ramp asked for again."""
    with SimulatorServer(SCENE, link_path=link, rate_hz=20, hold_clock_when_late=True) as sim:
        with session(link, outstanding=outstanding) as s:
            frames = list(s.frames(6))
            more = list(s.frames(2))
        assert not sim.errors
        gnfds = sim.devices[0].event_counts["GNFD"]
    gamma = expected_frame(SCENE)
    c = s.counters
    assert [f.seq for f in frames + more] == list(range(8)) and c.frames == 8
    assert all(np.abs(f.data - gamma).max() <= LSB for f in frames + more)
    assert gnfds == c.ramps == 2 * 8 + c.discarded_ramps
    assert c.timeouts == 0 and c.incomplete == 0


@pytest.mark.parametrize("outstanding, drops", [(1, True), (2, False)])
def test_a_second_request_in_flight_rides_out_a_stall_of_the_host(link, outstanding, drops):
    """The reader stalls for 300 ms (1.2 RADC periods at 2 frames/s: the host not
    scheduled) just after a DONE arrived: with one GNFD in flight the next goes out later
    than the next RADC was due and the sensor's counter moves on (a drop, whatever else
    delays the host); with two, the next was already queued at the sensor, which answers
    on time as long as the host is less than two periods late: the stall leaves 200 ms for
    the machine's own delays (a loaded host's; at 10 frames/s it left 40 ms). Either way no
    more GNFDs go out than RADCs come back. (The simulator's own lateness, on a loaded host,
    does not count: hold_clock_when_late; a GNFD's answer may come two periods after it.)"""
    with SimulatorServer(SCENE, link_path=link, rate_hz=2, hold_clock_when_late=True) as sim:
        s = session(link, outstanding=outstanding, timeout_s=5.0)
        fill, stall_at = s._fill_inbox, {4, 8}

        def stalling_fill():
            fill()
            if s.counters.ramps in stall_at and any(isinstance(m, Done) for m in s._inbox):
                stall_at.discard(s.counters.ramps)
                time.sleep(0.3)  # a RADC period is 250 ms at 2 frames/s of 2 ramps

        s._fill_inbox = stalling_fill
        with s:
            frames = list(s.frames(6))
        wait_until(lambda: any(e == "GBYE" for e, _ in sim.devices[0].events), 2.0, "GBYE")
    assert not stall_at and [f.seq for f in frames] == list(range(6))
    assert (s.counters.dropped_radcs > 0) == drops
    assert sim.devices[0].event_counts["GNFD"] == s.counters.ramps
    assert s.counters.timeouts == 0 and not sim.errors


@pytest.mark.parametrize("hold", [False, True])
def test_a_simulator_late_by_its_own_fault_can_hold_its_clock(link, hold):
    """The simulator itself writes one RADC 350 ms after it was due (600 ms to measure it:
    its process not scheduled): on its own clock the host's next GNFD is then late and a
    RADC is counted lost, a drop that a real K-MD2 would not have; with
    hold_clock_when_late the device clock stands still for that long and nothing is lost.
    At 2 frames/s, where the host's every GNFD may be a RADC period (250 ms) late before
    it costs a RADC (at 20 frames/s, 25 ms: a loaded host's delay)."""
    with SimulatorServer(SCENE, link_path=link, rate_hz=2, hold_clock_when_late=hold) as sim:
        dev = sim.devices[0]
        measure = dev.measure

        def late_measure(index):
            if index == 6:
                time.sleep(0.6)  # asked for at RADC 5's DONE: 250 ms before it is due, 500 before RADC 7
            return measure(index)

        dev.measure = late_measure
        with session(link, timeout_s=5.0) as s:  # (the late RADC's answer takes 600 ms)
            frames = list(s.frames(5))
        assert not sim.errors
    assert len(frames) == 5
    assert (s.counters.dropped_radcs > 0) == (not hold)
    assert (dev.late_writes >= 1 and 0.3 < dev.late_s < 5.0) if hold else dev.late_writes == 0


def test_a_frame_completed_after_a_stop_is_still_handed_out(link):
    """A stop while the GNFD of a frame's second ramp is in flight (what SIGTERM does to a
    driver): the reader drains the answer, and the frame it completes comes out of
    frames() before the end, so that ``frames`` counts only frames handed on."""
    with SimulatorServer(SCENE, link_path=link, rate_hz=0) as sim:
        s = session(link)
        write = s._write

        def stop_after_asking_for_ramp_3(data):
            write(data)
            if s.counters.ramps == 3 and data == encode(Gnfd()):
                s.request_stop()

        s._write = stop_after_asking_for_ramp_3
        with s:
            handed = s.frames()
            first = next(handed)
            wait_until(lambda: not s._reader.is_alive(), 5, "the reader to end after its drain")
            rest = list(handed)
        assert not sim.errors
    assert [f.seq for f in [first, *rest]] == [0, 1] and rest[0].counters == (2, 3)
    assert s.counters.frames == 2 and s.counters.ramps == 4


def test_frames_asked_for_while_the_reader_queues_one_are_not_asked_twice(link):
    """frames() works out how many frames the reader is still to ask for from the frames
    produced and those queued; it must not read them while the reader has counted a frame
    it has not queued yet (here that moment lasts 0.3 s), or one frame more is asked for."""
    with SimulatorServer(SCENE, link_path=link, rate_hz=0) as sim:
        s = session(link)
        with s:
            put = s._queue.put

            def slow_put(item):
                if isinstance(item, RawFrame) and item.seq == 1:
                    time.sleep(0.3)
                put(item)

            s._queue.put = slow_put
            handed = s.frames(2)
            first = next(handed)
            time.sleep(0.1)  # the consumer is slow: the reader is inside the put of frame 1
            rest = list(handed)
        gnfds = sim.devices[0].event_counts["GNFD"]
    assert [f.seq for f in [first, *rest]] == [0, 1]
    assert s.counters.frames == 2 and gnfds == s.counters.ramps == 4


def test_a_gap_in_the_counter_is_time_that_went_by_on_the_device_clock():
    """The device skips 66 frames of 2 ramps (a host stalled that long): on its clock
    (20 frames/s) the answers stay on time. (The frames and counters of such a gap:
    tests/test_assembly.py.)"""
    dev = SimulatedKMD2(SCENE, rate_hz=20, faults=SimFaults(skip_frames_after=1, skip_frames=66))
    dec = StreamDecoder()
    seen = []
    for k in range(4):
        for reply in dev.receive(encode(Gnfd()), now_s=100.0 + k / 40):
            seen += [(m.frame_counter, reply.due_s) for m in dec.feed(reply.data) if isinstance(m, Done)]
    assert [n for n, _ in seen] == [0, 1, 134, 135]
    assert np.allclose([t for _, t in seen], [100.0, 100.025, 100.05, 100.075])


def test_the_simulated_sensor_keeps_recent_events_and_counts_all_of_them():
    """A long run (here 3 times the events kept) does not grow the device's event list;
    the counts since start stay exact."""
    dev = SimulatedKMD2(SCENE, rate_hz=0)
    n = 3 * dev.EVENTS_KEPT  # GNFDs with an empty mask (answered RESP 2) and 2 for a frame
    replies = dev.receive(encode(Init(0)) + encode(Gnfd(0)) * n + encode(Gnfd()) * 2 + encode(Gbye()))
    assert sum(r.data == encode(Resp(RespCode.INVALID_PARAMETER)) for r in replies) == n
    assert len(dev.events) == dev.EVENTS_KEPT == dev.events.maxlen
    assert dict(dev.event_counts) == {"INIT": 1, "SWITCH": 1, "GNFD": n + 2, "GBYE": 1}
    assert dev.radcs_sent == 2 and dev.counter == 1
    assert dev.events[-1] == ("GBYE", None) and dev.events[:-1] == [("GNFD", None)] * (dev.EVENTS_KEPT - 1)
    assert ("INIT", None) not in dev.events  # the oldest are gone, but counted


def test_a_serial_port_has_one_owner_and_a_second_opener_is_told_who(link):
    """A driver process holds the pty (flock); a second opener gets one line naming the
    port and the holder's pid and command, and the first keeps its frames."""
    with SimulatorServer(SCENE, link_path=link, rate_hz=20) as sim:
        first = subprocess.Popen([*QRADAR, "drive", "--port", str(link), "--no-publish"],
                                 stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        try:
            assert first.stdout.readline().startswith("frame")  # it holds the port
            second = subprocess.run([*QRADAR, "drive", "--port", str(link), "--no-publish",
                                     "--frames", "1"], capture_output=True, text=True, timeout=60)
            assert second.returncode != 0
            line = second.stderr.strip()
            assert "\n" not in line and str(link) in line and f"in use by process {first.pid}" in line, line
            assert "qradar drive" in line
            assert first.stdout.readline().startswith("frame") and first.poll() is None  # undisturbed
        finally:
            first.terminate()
            first.wait(10)
        assert sim.devices[0].event_counts["INIT"] == 1  # the second never spoke to the sensor


def test_a_reconnect_does_not_follow_the_path_to_another_device(link):
    """The sensor goes away and the link path comes back naming a pty that another
    program serves: the driver does not INIT it; it counts and says so, then gives up."""
    sim = SimulatorServer(SCENE, link_path=link, rate_hz=0).start()
    s = session(link, reconnect_timeout_s=2.0)
    other = None
    try:
        s.open()
        assert len(list(s.frames(2))) == 2
        sim.stop()  # the device is gone (its link too) ...
        other = subprocess.Popen([*QRADAR, "sim", "--link", str(link), "--rate", "0"],
                                 stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        assert "simulated K-MD2" in other.stdout.readline()  # ... and the path names another program's pty
        with pytest.raises(LinkError, match="another device"):
            list(s.frames(3))
        assert s.counters.wrong_device >= 1 and s.counters.reconnects == 0
    finally:
        s.close()
        sim.stop()
        if other is not None:
            other.terminate()
            other.wait(10)
