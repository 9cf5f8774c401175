"""pipeline.dsp.kernel_cache: a cached numba kernel that calls another file's kernel is
recompiled when that file changes (numba alone would keep the stale callee), in fresh
processes sharing one cache directory."""

import os
import subprocess
import sys
import textwrap

CALLER = textwrap.dedent("""
    from numba import njit
    from callee import value
    from pipeline.dsp.kernel_cache import drop_stale

    @njit(cache=True)
    def caller():
        return value() + 1

    drop_stale(__file__, (caller,), ("callee.py",))
""")


def run(tmp_path) -> int:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"), PYTHONPATH=os.pathsep.join(
        [str(tmp_path), os.getcwd()]))
    out = subprocess.run([sys.executable, "-c", "import caller; print(caller.caller())"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return int(out.stdout.strip())


def test_a_changed_callee_is_not_served_from_the_cache(tmp_path):
    (tmp_path / "caller.py").write_text(CALLER)
    callee = tmp_path / "callee.py"
    callee.write_text("from numba import njit\n\n@njit(cache=True)\ndef value():\n    return 1\n")
    assert run(tmp_path) == 2
    assert run(tmp_path) == 2  # from the cache
    callee.write_text("from numba import njit\n\n@njit(cache=True)\ndef value():\n    return 10\n")
    assert run(tmp_path) == 11


def test_without_the_guard_numba_serves_the_stale_callee(tmp_path):
    """Why the guard exists: the same files without it keep the first callee."""
    (tmp_path / "caller.py").write_text(CALLER.replace('drop_stale(__file__, (caller,), ("callee.py",))', ""))
    callee = tmp_path / "callee.py"
    callee.write_text("from numba import njit\n\n@njit(cache=True)\ndef value():\n    return 1\n")
    assert run(tmp_path) == 2
    callee.write_text("from numba import njit\n\n@njit(cache=True)\ndef value():\n    return 10\n")
    assert run(tmp_path) == 2
