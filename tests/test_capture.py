"""The bring-up kit: capture files (format, port wrapper, raw poller) and the inspection
that finds the sensor profile of a capture, against the simulated K-MD2 on a real pty
with each shipped profile."""

import json
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from qradar.cli import main
from radar_driver.capture import (
    MAGIC,
    Capture,
    CaptureConfig,
    CaptureHeader,
    CaptureReader,
    CaptureWriter,
    Kind,
    Record,
    capturing_factory,
    run_capture,
)
from radar_driver.errors import CaptureError, ConfigError
from radar_driver.inspection import (
    MAX_ANGLE_SPREAD_DEG,
    MIN_PURITY_DB,
    Reflector,
    inspect_capture,
    score_frames,
    split_messages,
)
from radar_driver.model import RadarConfig, simulate_frames
from radar_driver.profile import RadcLayout, SensorProfile, packaged_profiles, resolve_profile
from radar_driver.protocol import Done, OtherMessage, Radc, Resp, encode
from radar_driver.scene import SimScene, SimTarget
from radar_driver.simulator import SimFaults, SimulatorServer
from zenoh_helpers import QRADAR, wait_until

ROOT = Path(__file__).resolve().parents[1]
#: one reflector off the range grid (bin 20.5), on antenna 2's side, with sensor noise
SCENE = SimScene((SimTarget(12.3, 20.0, 0.5),), noise_std=0.01, name="one-reflector")
SHIPPED = packaged_profiles()
#: a layout no shipped profile has: 3 receivers x 4 chirps x 256 samples, I/Q interleaved
ODD_TOML = """name = "odd"
[radc]
receivers = 3
azimuth = [0, 1]
chirps = 4
samples = 256
order = "interleaved"
"""


def header(**extra) -> CaptureHeader:
    return CaptureHeader("loop://", 1_700_000_000_000_000_000, "kmd2-blocks", extra)


def run_cli(capsys, *argv) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def capture_sim(tmp_path: Path, sim_profile: SensorProfile, *argv, rate_hz: float = 20.0) -> Path:
    """``qradar capture`` (in process) of the simulated K-MD2 speaking ``sim_profile`` on a
    pty, at most 60 s (a cap: the callers' captures end at their --frames): the file."""
    link, out = tmp_path / f"kmd2-{sim_profile.name}", tmp_path / f"{sim_profile.name}-{len(argv)}.bin"
    with SimulatorServer(SCENE, link_path=link, rate_hz=rate_hz, profile=sim_profile) as sim:
        rc = main(["capture", "--port", str(link), "-o", str(out), "--seconds", "60", *map(str, argv)])
    assert rc == 0 and not sim.errors
    return out


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> dict[str, Path]:
    """A capture of 6 frames of each shipped profile, asked with the right profile."""
    tmp = tmp_path_factory.mktemp("captures")
    return {name: capture_sim(tmp, resolve_profile(name), "--profile", name, "--frames", 6) for name in SHIPPED}


# -- the file format ------------------------------------------------------------------------------
def test_record_and_preamble_bytes_are_exact(tmp_path):
    assert Record(Kind.RX, 5, b"ab").encode() == b"\x02" + (5).to_bytes(8, "little") + (2).to_bytes(4, "little") + b"ab"
    path = tmp_path / "c.bin"
    h = header()
    with CaptureWriter(path, h):
        pass
    blob = h.to_json()
    assert path.read_bytes() == MAGIC + struct.pack("<HI", 1, len(blob)) + blob
    assert json.loads(blob) == {"url": "loop://", "start_time_ns": 1_700_000_000_000_000_000, "profile": "kmd2-blocks"}


def test_the_format_round_trips(tmp_path):
    path = tmp_path / "c.bin"
    records = [Record(Kind.OPEN, 1, b'{"url": "loop://"}'), Record(Kind.TX, 2, encode(Resp())),
               Record(Kind.RX, 3, bytes(range(256)) * 40), Record(Kind.BAUD, 4, struct.pack("<I", 2_000_000)),
               Record(Kind.RX, 5, b""), Record(Kind.CLOSE, 6)]
    h = header(baud=None, ramps_per_frame=2)
    with CaptureWriter(path, h) as w:
        for r in records:
            w.write(r.kind, r.data, r.time_ns)
    assert w.records == 6 and w.bytes[Kind.RX] == 10240 and w.bytes[Kind.TX] == 12
    cap = Capture.read(path)
    assert cap.header == h and cap.records == records and cap.truncated is None
    with CaptureReader(path) as reader:  # the same, one record at a time
        records_read = iter(reader)
        assert reader.header == h and next(records_read) == records[0] and list(records_read) == records[1:]
    assert cap.records[3].baud == 2_000_000 and cap.byte_count(Kind.RX) == 10240
    with pytest.raises(CaptureError, match="closed"):
        w.write(Kind.RX, b"x")


def test_a_file_cut_short_reads_up_to_its_last_whole_record(tmp_path):
    path = tmp_path / "c.bin"
    with CaptureWriter(path, header()) as w:
        for i in range(5):
            w.write(Kind.RX, bytes([i]) * 100, i)
    data = path.read_bytes()
    last = len(data) - (13 + 100)
    cut = tmp_path / "cut.bin"
    for end, why in [(last + 1, "inside its 13-byte prefix"), (last + 13, "cut short: 0 of 100 bytes"),
                     (last + 60, "cut short: 47 of 100 bytes"), (len(data) - 1, "99 of 100")]:
        cut.write_bytes(data[:end])
        cap = Capture.read(cut)
        assert len(cap.records) == 4 and f"record 4 at byte {last}" in cap.truncated and why in cap.truncated
    for pos, value, why in [(last, 9, "unknown kind 9"), (last + 12, 0x7F, "beyond")]:
        b = bytearray(data)
        b[pos] = value
        cut.write_bytes(bytes(b))
        cap = Capture.read(cut)
        assert len(cap.records) == 4 and why in cap.truncated
    cut.write_bytes(data[:20])
    with pytest.raises(CaptureError, match=f"{cut}.*cut short inside its header"):
        Capture.read(cut)


def test_inspect_warns_about_a_cut_file_and_still_reports(tmp_path, capsys, captures):
    data = captures["kmd2-blocks"].read_bytes()
    cut = tmp_path / "cut.bin"
    cut.write_bytes(data[:len(data) - 1000])
    rc, out, err = run_cli(capsys, "inspect", cut, "--json")
    report = json.loads(out)
    assert rc == 0 and report["best"] == "kmd2-blocks" and "cut short" in report["truncated"]
    assert "ends early" in err


@pytest.mark.parametrize("content", [b"", b"hello, this is not a capture", MAGIC[:5],
                                     MAGIC + struct.pack("<HI", 7, 2) + b"{}", MAGIC + struct.pack("<HI", 1, 3) + b"{]}",
                                     MAGIC + struct.pack("<HI", 1, 2) + b"{}"])
def test_a_file_that_is_no_capture_gives_one_line_naming_it(tmp_path, capsys, content):
    path = tmp_path / "junk.bin"
    path.write_bytes(content)
    rc, out, err = run_cli(capsys, "inspect", path)
    assert rc == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("qradar inspect: error: ") and str(path) in err


def test_a_missing_or_unwritable_file_is_one_line(tmp_path, capsys):
    rc, _, err = run_cli(capsys, "inspect", tmp_path / "nope.bin")
    assert rc == 2 and "cannot read capture" in err and "nope.bin" in err
    with pytest.raises(CaptureError, match="cannot write capture .*nodir"):
        CaptureWriter(tmp_path / "nodir" / "c.bin", header())


def test_capturing_port_logs_reads_writes_speed_and_close(tmp_path):
    path = tmp_path / "c.bin"
    with CaptureWriter(path, header()) as w:
        port = capturing_factory(w)("loop://", baudrate=115_200, timeout=0.05)
        assert port.write(b"GNFD") == 4 and port.read(4) == b"GNFD"
        port.baudrate = 921_600
        assert port.baudrate == 921_600
        port.write(b"left over")
        wait_until(lambda: port.in_waiting == 9, 5, "the bytes looped back")
        port.reset_input_buffer()  # the bytes thrown away are captured too
        assert port.in_waiting == 0 and port.is_open  # delegated
        port.close()
    kinds = [(r.kind, r.data) for r in Capture.read(path).records]
    assert kinds == [(Kind.OPEN, b'{"url": "loop://", "baudrate": 115200}'), (Kind.TX, b"GNFD"), (Kind.RX, b"GNFD"),
                     (Kind.BAUD, struct.pack("<I", 921_600)), (Kind.TX, b"left over"), (Kind.RX, b"left over"),
                     (Kind.CLOSE, b"")]


def test_capture_config_is_validated():
    with pytest.raises(ConfigError, match="mode='fast'"):
        CaptureConfig("loop://", mode="fast")
    with pytest.raises(ConfigError, match="seconds=0"):
        CaptureConfig("loop://", seconds=0)
    with pytest.raises(ConfigError, match="packaged"):
        CaptureConfig("loop://", profile="kmd3")


# -- inspection, pure ---------------------------------------------------------------------------------
def test_split_without_a_profile_counts_headers_lengths_garbage_and_a_cut_end():
    radc = encode(Radc(np.full((2, 1, 256, 2), 2048), resolve_profile("kmd2-blocks").radc))
    stream = (encode(Resp()) + b"\xff\x01garbage" + radc + encode(Done(7)) + encode(OtherMessage(b"XYZ1", b"12345"))
              + encode(Done(8)) + b"QQQQ\xff\xff\xff\xff" + encode(Resp()) + radc[:100])
    chunks = [(i, stream[i * 50:(i + 1) * 50]) for i in range(len(stream) // 50 + 1)]
    split = split_messages([chunks])
    assert {h: (s.count, dict(s.lengths)) for h, s in split.headers.items()} == {
        "RESP": (2, {1: 2}), "RADC": (1, {2048: 1}), "DONE": (2, {4: 2}), "XYZ1": (1, {5: 1})}
    assert split.garbage_bytes == 9 + 8 and split.resyncs == 2 and split.cut == [("RADC", 2048)]
    assert split.bytes == len(stream)
    # a RADC cut short: the next message starts inside its declared length, so it is garbage
    stream = encode(Resp()) + radc[:500] + encode(Done(1)) + radc + encode(Done(2))
    split = split_messages([[(0, stream)]])
    assert {h: s.count for h, s in split.headers.items()} == {"RESP": 1, "DONE": 2, "RADC": 1}
    assert split.garbage_bytes == 500 and split.resyncs == 1 and split.cut == []
    # an unknown header must be followed by a message: here it is not, so it is garbage
    split = split_messages([[(0, encode(OtherMessage(b"XYZ1", b"1234")) + b"\x00\x01\x02" * 5)]])
    assert "XYZ1" not in split.headers and split.garbage_bytes == 8 + 4 + 15


def test_score_frames_of_a_known_reflector():
    radar = RadarConfig()
    rng = np.random.default_rng(3)
    gamma = simulate_frames(np.array([[12.3]]), np.array([[20.0]]), np.array([[0.5]]), radar)[0]  # (512, 2)
    frames = np.stack([gamma.reshape(2, 256, 2)] * 5) + 0.01 * (rng.standard_normal((5, 2, 256, 2))
                                                                + 1j * rng.standard_normal((5, 2, 256, 2)))
    fs = score_frames(frames, radar)
    assert fs.peak_bin in (20, 21) and fs.sharpness_db > 40 and fs.purity_db > 25
    np.testing.assert_allclose(np.rad2deg(fs.angles_rad), 20.0, atol=0.5)
    noise = score_frames(frames - gamma.reshape(2, 256, 2), radar)
    assert noise.sharpness_db < 15 and noise.purity_db < 3
    assert np.rad2deg(noise.angles_rad).std() > 10


# -- capture + inspect on the simulated sensor, each shipped profile ---------------------------------------------
@pytest.mark.parametrize("name", SHIPPED)
def test_capture_and_inspect_identify_each_shipped_profile(captures, capsys, name):
    rc, out, _ = run_cli(capsys, "inspect", captures[name], "--json")
    r = json.loads(out)
    assert rc == 0 and r["best"] == name and r["ambiguous"] == []
    assert r["header"]["profile"] == name and r["segments"] == 1 and r["truncated"] is None
    scores = {s["name"]: s for s in r["profiles"]}
    right = scores[name]
    assert right["fits"] and right["frames"] == 6 and right["peak_bin"] in (20, 21)
    assert abs(right["angle_deg"] - 20.0) < 1.0 and right["angle_spread_deg"] < MAX_ANGLE_SPREAD_DEG
    for other in set(SHIPPED) - {name}:
        assert not scores[other]["fits"] and scores[other]["radcs"] == 0 and "no RADC decodes" in scores[other]["why"]
    radc_len = resolve_profile(name).radc.payload_len
    assert r["sensor"]["headers"]["RADC"]["lengths"] == {str(radc_len): right["radcs"]}
    assert r["sensor"]["garbage_bytes"] == 0 and set(r["host"]["headers"]) == {"INIT", "GNFD", "GBYE"}
    rc, out, _ = run_cli(capsys, "inspect", captures[name])
    assert rc == 0 and f"verdict: {name} fits: one sharp range peak" in out


@pytest.mark.parametrize("sim_name", SHIPPED)
def test_a_capture_with_the_wrong_profile_still_records_and_inspect_finds_the_right_one(tmp_path, capsys, sim_name):
    asked = next(n for n in SHIPPED if n != sim_name)
    t0 = time.monotonic()
    path = capture_sim(tmp_path, resolve_profile(sim_name), "--profile", asked, "--frames", 6)
    out = capsys.readouterr().out
    assert time.monotonic() - t0 < 60  # ended by its frames, not by its seconds
    assert f"0 frames decoded with {asked} (the driver stopped:" in out and "raw poller: 12 GNFD answers" in out
    cap = Capture.read(path)
    assert cap.header.profile == asked and sum(r.kind == Kind.OPEN for r in cap.records) == 2
    report = inspect_capture(cap)
    assert report.best == sim_name
    assert next(s for s in report.scores if s.name == sim_name).frames >= 6
    assert not next(s for s in report.scores if s.name == asked).fits


def test_a_layout_no_profile_has_is_named_and_a_profile_file_then_fits(tmp_path, capsys):
    toml = tmp_path / "odd.toml"
    toml.write_text(ODD_TOML)
    odd = resolve_profile(toml)
    assert odd.radc.payload_len == 12288
    path = capture_sim(tmp_path, odd, "--frames", 4, "--mode", "raw")
    assert "raw poller: 8 GNFD answers" in capsys.readouterr().out
    rc, out, _ = run_cli(capsys, "inspect", path)
    assert rc == 1
    assert ("verdict: no shipped profile fits: RADC payloads of 12 288 bytes; kmd2-blocks expects 2 048, "
            "kmd2-cube256 expects 786 432.") in out
    rc, out, _ = run_cli(capsys, "inspect", path, "--profile", toml, "--json")
    assert rc == 0 and json.loads(out)["best"] == "odd"


def test_layouts_of_the_same_length_are_told_apart_by_images_and_the_known_angle(captures):
    cap = Capture.read(captures["kmd2-blocks"])
    decoys = [SensorProfile("interleaved", RadcLayout(order="interleaved")),
              SensorProfile("swapped", RadcLayout(azimuth=(1, 0)))]
    report = inspect_capture(cap, ["kmd2-blocks"] + decoys)
    by = {s.name: s for s in report.scores}
    assert report.best == "kmd2-blocks" and report.ambiguous == ["swapped"]
    # the same RADCs read in another order (6 frames of 2: 12, and 14 once when a GNFD was sent again on a
    # loaded host and answered twice)
    assert by["interleaved"].radcs == by["kmd2-blocks"].radcs >= 12 and not by["interleaved"].fits
    assert by["interleaved"].purity_db < MIN_PURITY_DB and "images" in by["interleaved"].why
    assert by["swapped"].fits and by["swapped"].angle_deg == pytest.approx(-by["kmd2-blocks"].angle_deg)
    assert "--angle-deg" in report.verdict
    report = inspect_capture(cap, ["kmd2-blocks"] + decoys, reflector=Reflector(12.3, 20.0))
    assert report.best == "kmd2-blocks" and report.ambiguous == []
    assert "not +20 deg" in {s.name: s for s in report.scores}["swapped"].why
    # only the swapped pair: the verdict names the swap, not the payload's size
    report = inspect_capture(cap, [decoys[1]], reflector=Reflector(12.3, 20.0))
    assert report.best is None and "the sign flipped" in report.scores[0].why
    assert report.verdict.startswith("no profile tried fits, but swapped reads the reflector with the angle's "
                                     "sign flipped (the reflector comes out at -20."), report.verdict
    assert "azimuth pair are swapped" in report.verdict and "expects" not in report.verdict


def test_a_capture_with_garbage_and_cut_messages_is_still_identified(tmp_path):
    link, out = tmp_path / "kmd2", tmp_path / "faults.bin"
    faults = SimFaults(garbage_prob=0.1, truncate_prob=0.1)
    with SimulatorServer(SCENE, link_path=link, rate_hz=0, faults=faults, seed=4) as sim:
        summary = run_capture(CaptureConfig(str(link), frames=20, seconds=8), out)
    assert not sim.errors and summary.frames == 20
    truncated = sim.devices[0].event_counts["TRUNCATED"]
    report = inspect_capture(Capture.read(out))
    assert truncated >= 1 and report.sensor.garbage_bytes > 0 and report.sensor.resyncs >= truncated
    heads = report.sensor.headers
    # every RADC cut short is lost (a cut one may also swallow the DONE behind it, or a
    # timeout's second GNFD may bring a whole one): between DONEs - cut and DONEs
    assert heads["DONE"].count - truncated <= heads["RADC"].count <= heads["DONE"].count
    assert heads["RADC"].lengths == {2048: heads["RADC"].count}
    assert report.best == "kmd2-blocks"


# -- the command as a process -------------------------------------------------------------------------------
def test_capture_as_a_process_ends_cleanly_on_sigint(tmp_path):
    link, out = tmp_path / "kmd2", tmp_path / "s.bin"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with SimulatorServer(SCENE, link_path=link, rate_hz=20) as sim:
        proc = subprocess.Popen([*QRADAR, "capture", "--port", str(link), "-o", str(out),
                                 "--seconds", "120", "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, cwd=ROOT, env=env)
        try:
            wait_until(lambda: (out.exists() and out.stat().st_size >= 20_000) or proc.poll() is not None, 60,
                       "20 kB captured")
            proc.send_signal(signal.SIGINT)
            stdout, stderr = proc.communicate(timeout=30)
        finally:
            proc.kill()
        assert not sim.errors
        assert sim.devices[0].events[-1][0] == "GBYE"
    assert proc.returncode == 0, stderr
    summary = json.loads(stdout)
    # ended by the signal, before its --seconds
    assert summary["frames"] >= 1 and summary["seconds"] < 120 and summary["session_error"] == ""
    cap = Capture.read(out)
    assert cap.truncated is None and cap.byte_count(Kind.RX) == summary["bytes_rx"]
    assert cap.records[-1].kind == Kind.CLOSE
    proc = subprocess.run([*QRADAR, "inspect", str(out)], capture_output=True, text=True,
                          cwd=ROOT, env=env, timeout=60)
    assert proc.returncode == 0 and "verdict: kmd2-blocks fits" in proc.stdout


def test_a_capture_of_no_sensor_is_a_one_line_error_and_a_whole_file(tmp_path, capsys):
    out = tmp_path / "s.bin"
    rc, _, err = run_cli(capsys, "capture", "--port", tmp_path / "nothing", "-o", out)
    assert rc == 2 and "cannot open" in err and err.count("\n") == 1
    assert Capture.read(out).records == []


def test_the_raw_poller_polls_again_until_its_seconds_are_spent(tmp_path):
    """A sensor that refuses every GNFD (its RADC bit is not the profile's): no DONE ever
    comes; the raw poller asks again after each timeout until the seconds are spent (2 s of
    0.2-s timeouts: a host stalled for most of them still times out, and asks again, once)."""
    link = tmp_path / "kmd2"
    wrong_bit = SensorProfile("bit4", gnfd_bits={"RADC": 0x10})
    with SimulatorServer(SCENE, link_path=link, rate_hz=0) as sim:
        t0 = time.monotonic()
        summary = run_capture(CaptureConfig(str(link), profile=wrong_bit, seconds=2.0, mode="raw", timeout_s=0.2),
                              tmp_path / "c.bin")
        took = time.monotonic() - t0
    assert not sim.errors and 2.0 <= took < 30.0  # its seconds spent, then it stopped
    # each poll timed out and was sent again, but the last, which the end may cut short
    assert summary.raw.answers == 0 and summary.raw.timeouts >= 1 and summary.raw.polls >= 2
    assert summary.raw.polls - summary.raw.timeouts in (0, 1), summary.raw
    split = inspect_capture(Capture.read(tmp_path / "c.bin")).sensor
    assert split.headers["RESP"].count == summary.raw.polls + 2  # INIT, the GNFDs (refused), GBYE
