"""The ``qradar`` command's processes run one BLAS thread unless the environment says
otherwise (qradar.entry): OpenBLAS's threads on a shared 2-core host spin waiting."""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: a child that prepares itself as the command's process does, then asks numpy's OpenBLAS
PROBE = "from qradar.entry import prepare_process; prepare_process(); from test_entry import openblas_threads; " \
        "print(openblas_threads())"


def openblas_threads() -> int:
    """The threads numpy's OpenBLAS runs in this process."""
    import ctypes
    import glob

    import numpy

    lib, = glob.glob(os.path.join(os.path.dirname(numpy.__path__[0]), "numpy.libs", "libscipy_openblas*.so"))
    return ctypes.CDLL(lib).scipy_openblas_get_num_threads64_()


def blas_threads(env_value: str | None) -> int:
    """:func:`openblas_threads` of a prepared child whose environment sets
    ``OPENBLAS_NUM_THREADS`` to ``env_value`` (None: unset)."""
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "tests"), env.get("PYTHONPATH", "")])
    if env_value is not None:
        env["OPENBLAS_NUM_THREADS"] = env_value
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    return int(out.stdout)


def test_a_qradar_process_runs_one_blas_thread_unless_told():
    assert blas_threads(None) == 1
    assert blas_threads("2") == 2  # the user's choice stands


def test_both_ways_of_starting_qradar_go_through_the_entry():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts == {"qradar": "qradar.entry:main"}
    assert "from .entry import main" in (ROOT / "qradar" / "__main__.py").read_text()


def test_the_tests_run_as_a_qradar_process_does():
    """tests/conftest.py prepares the test processes before numpy loads."""
    assert openblas_threads() == int(os.environ["OPENBLAS_NUM_THREADS"])


#: a child whose command is interrupted (a real SIGINT) before it installs its own handling, as
#: Ctrl-C in the first half second of `qradar run` is (its modules still loading)
EARLY_SIGINT = """
import os, signal, sys, time, types
signal.signal(signal.SIGINT, signal.default_int_handler)  # as from a terminal (a test worker's children ignore it)
cli = types.ModuleType("qradar.cli")
def main():
    os.kill(os.getpid(), signal.SIGINT)
    time.sleep(10)
cli.main = main
sys.modules["qradar.cli"] = cli
sys.argv = ["qradar", *sys.argv[1:]]
from qradar.entry import main as entry
sys.exit(entry())
"""


def test_ctrl_c_while_the_command_loads_is_one_line_not_a_traceback():
    for argv, out in ((["run", "--duration", "10"], ""),
                      (["run", "--json"], '{"error": "interrupted", "exit_code": 130, "command": "run"}\n')):
        proc = subprocess.run([sys.executable, "-c", EARLY_SIGINT, *argv], capture_output=True, text=True,
                              timeout=60, cwd=ROOT)
        assert proc.returncode == 130 and proc.stderr == "qradar run: interrupted\n", proc.stderr
        assert proc.stdout == out
