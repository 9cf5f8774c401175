"""The command's error contract: a failure prints one line naming what failed and where,
exits 2, and shows a traceback only under -v."""

import subprocess
import sys

import pytest


def qradar(*args, timeout_s=60):
    return subprocess.run([sys.executable, "-m", "qradar", *args], capture_output=True, text=True,
                          timeout=timeout_s, stdin=subprocess.DEVNULL)


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


def test_verbose_adds_the_traceback():
    proc = qradar("-v", "reprocess", "/nonexistent/rec.mcap")
    assert proc.returncode == 2 and "Traceback" in proc.stderr and "qradar reprocess: error:" in proc.stderr


def test_bad_option_values_are_usage_errors():
    proc = qradar("quantize", "--delta", "abc")
    assert proc.returncode == 2 and "--delta" in proc.stderr and "Traceback" not in proc.stderr
    proc = qradar("sim")
    assert proc.returncode == 2 and "--link" in proc.stderr


def test_a_busy_tcp_port_is_a_one_line_error(free_port):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", free_port))
        s.listen(1)
        proc = qradar("sim", "--tcp", str(free_port))
    assert proc.returncode == 2 and f"127.0.0.1:{free_port}" in proc.stderr and "Traceback" not in proc.stderr
