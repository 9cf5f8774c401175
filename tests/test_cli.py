"""The command's error contract: a failure prints one line naming what failed and where,
exits 2, and shows a traceback only under -v."""

import json
import os
from pathlib import Path

import pytest
from zenoh_helpers import qradar


@pytest.mark.parametrize("args, where", [
    (["sim", "--link", "/nonexistent/dir/kmd2"], "/nonexistent/dir/kmd2"),
    (["drive", "--port", "/dev/qradar-no-such-port", "--no-publish"], "/dev/qradar-no-such-port"),
    (["record", "-o", "/proc/qradar/x.mcap", "--duration", "1"], "/proc/qradar/x.mcap"),
    (["montecarlo", "--out", "/proc/qradar", "--runs", "10", "--K", "1"], "/proc/qradar"),
    (["reprocess", "/nonexistent/rec.mcap"], "/nonexistent/rec.mcap"),
    (["run", "--scene", "/nonexistent/scene.toml", "--no-record"], "/nonexistent/scene.toml"),
    (["replay", "pyproject.toml", "--fast"], "pyproject.toml"),
    (["drive", "--port", "/dev/qradar-no-such-port", "--frames", "1"], "/dev/qradar-no-such-port"),  # via the node
    (["drive", "--port", "/dev/null", "--sensor-id", "a/b"], "'a/b'"),
    (["source", "--recording", "/nonexistent/rec.mcap", "--duration", "5"], "/nonexistent/rec.mcap"),
    (["source", "--recording", "pyproject.toml", "--duration", "5"], "pyproject.toml"),
    (["sim", "--tcp", "99999"], "99999"),
])
def test_errors_are_one_line_naming_the_place(args, where):
    proc = qradar(*args)
    assert proc.returncode == 2, proc.stderr
    errors = [ln for ln in proc.stderr.splitlines() if ": error: " in ln]
    assert len(errors) == 1 and errors[0].startswith(f"qradar {args[0]}: error: ") and where in errors[0], proc.stderr
    assert "Traceback" not in proc.stderr
    message = errors[0].split(": error: ", 1)[1]
    assert sum(message in ln for ln in proc.stderr.splitlines()) == 1, proc.stderr  # said once


@pytest.mark.parametrize("port, hint", [
    ("/dev/qradar-no-such-port", "no such device (is the sensor plugged in?"),
    ("loop://", "our own INIT came back: the link echoes (a loopback, a modem or a console), not a K-MD2"),
    ("socket://127.0.0.1:1", "connection refused (is the sensor, ser2net or `qradar sim --tcp` listening there?)"),
])
def test_drive_errors_say_what_to_check_once_and_as_json(port, hint):
    proc = qradar("drive", "--port", port, "--no-publish", "--timeout", "0.2", "--json")
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and proc.stderr.count(hint) == 1, proc.stderr
    assert "[Errno" not in proc.stderr  # pyserial's repeated errno text is not passed on
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["exit_code"] == 2 and out["command"] == "drive" and hint in out["error"]
    proc = qradar("drive", "--port", port, "--no-publish", "--timeout", "0.2", "-v")
    assert "Traceback" in proc.stderr  # -v after the command too


def test_a_silent_port_suggests_the_line_speed_or_another_device():
    master, slave = os.openpty()  # a port where nothing answers
    try:
        proc = qradar("drive", "--port", os.ttyname(slave), "--no-publish", "--timeout", "0.2")
    finally:
        os.close(master)
        os.close(slave)
    assert proc.returncode == 2
    assert "saw no message (check that it is a K-MD2, powered, and that the line runs at 115200 baud 8E1" in proc.stderr


def test_permission_denied_names_the_dialout_group():
    import errno

    import serial

    from radar_driver.session import open_error

    # what pyserial raises for a device the user may not open (as root the real one cannot be made)
    exc = serial.SerialException(errno.EACCES, "could not open port /dev/ttyUSB0: [Errno 13] Permission denied: "
                                 "'/dev/ttyUSB0'")
    msg = open_error("/dev/ttyUSB0", exc)
    assert msg == ("cannot open /dev/ttyUSB0: permission denied (add yourself to the dialout group: "
                   "`sudo usermod -aG dialout $USER`, then log in again)")


@pytest.mark.parametrize("url, address", [("socket://127.0.0.1:notaport", "'127.0.0.1:notaport'"),
                                          ("socket://127.0.0.1:99999", "'127.0.0.1:99999'"),
                                          ("rfc2217://sensor-host", "'sensor-host'")])
def test_a_network_url_without_a_port_number_says_so_not_pyserials_words(url, address):
    """pyserial says "'debug|info|warning|error'" for socket://HOST:notaport (its URL
    options' parser); the line says what the URL needs."""
    import serial

    from radar_driver.session import open_error

    scheme = url.split("://")[0]
    exc = serial.SerialException("expected a number, logging level, timeout, 'debug|info|warning|error'")
    assert open_error(url, exc) == (f"cannot open {url}: {scheme}:// takes HOST:PORT with PORT a number in 1-65535 "
                                    f"(e.g. {scheme}://192.168.0.50:4001), not {address}")
    assert "connection refused" in open_error("socket://127.0.0.1:1", ConnectionRefusedError())


@pytest.mark.parametrize("command, defaults", [
    ("drive", ["--ramps RAMPS         ramps per frame (M = 256 x ramps) (default: 2)", "default 2000000",
               "(default: 0.5)", "(default: kmd2-blocks)", "(default: kmd2)"]),
    ("sim", ["(default: chamber)", "(default: 20.0)", "(default: kmd2-blocks)"]),
])
def test_help_shows_the_defaults(command, defaults, cli):
    code, out, _ = cli(command, "--help")
    text = " ".join(out.split())
    assert code == 0
    for d in defaults:
        assert " ".join(d.split()) in text, (d, out)


def test_verbose_adds_the_traceback():
    proc = qradar("-v", "reprocess", "/nonexistent/rec.mcap")
    assert proc.returncode == 2 and "Traceback" in proc.stderr and "qradar reprocess: error:" in proc.stderr


def test_bad_option_values_are_usage_errors(cli):
    code, _, err = cli("quantize", "--delta", "abc")
    assert code == 2 and "--delta" in err and "Traceback" not in err
    code, _, err = cli("sim")
    assert code == 2 and "--link" in err


def test_a_busy_tcp_port_is_a_one_line_error(free_port):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", free_port))
        s.listen(1)
        proc = qradar("sim", "--tcp", str(free_port))
    assert proc.returncode == 2 and f"127.0.0.1:{free_port}" in proc.stderr and "Traceback" not in proc.stderr


def test_a_simulated_rate_beyond_any_sensor_is_refused_in_one_line(cli):
    """``--rate 1e9`` made a run count 12 billion frames dropped and end with status 0; a
    simulated sensor's rate is at most MAX_SIM_RATE_HZ, said with what a K-MD2 makes."""
    from radar_driver.scene import MAX_SIM_RATE_HZ

    for argv in (["run", "--rate", "1e9", "--frames", "5", "--no-record"], ["sim", "--rate", "5000", "--link", "x"]):
        code, _, err = cli(*argv)
        assert code == 2 and len(err.strip().splitlines()) == 1, err
        assert f", {MAX_SIM_RATE_HZ:g}] frames/s" in err and "a K-MD2 makes about 20 a second" in err, err


def test_sensor_poses_without_a_view_is_refused_not_ignored(cli, tmp_path):
    """``--sensor-poses`` places the sensors in the views; a run with none ignored the file,
    even a missing one, with status 0: now one line says it would do nothing."""
    code, _, err = cli("run", "--sensor-poses", tmp_path / "nope.toml", "--frames", "5", "--no-record")
    assert code == 2 and err.strip().splitlines() == [
        f"qradar run: error: --sensor-poses {tmp_path / 'nope.toml'} places each sensor in a view (--web, --foxglove); "
        "this run has none, so it would do nothing: give a view or leave it out"], err


def test_an_option_the_command_would_ignore_is_refused_in_one_line(cli, tmp_path):
    """``view --web P --port Q`` dropped Foxglove's port, ``calibrate --angle-deg`` without a
    reflector dropped the angle; each with status 0 before."""
    chamber = Path(__file__).resolve().parents[1] / "recordings" / "chamber.mcap"
    for argv, words in ((["view", "--web", "0", "--port", "18084"], "--port 18084 is Foxglove's port, and --web "
                         "serves the web page instead of Foxglove's server"),
                        (["calibrate", "--empty", chamber, "--angle-deg", "100", "--out", tmp_path / "c.json"],
                         "--angle-deg 100 is the reflector's angle: give --reflector REF.mcap and --range-m too")):
        code, _, err = cli(*argv)
        assert code == 2 and len(err.strip().splitlines()) == 1 and words in err, err
    assert not (tmp_path / "c.json").exists()
