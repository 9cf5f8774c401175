"""pipeline.dsp.kernel_cache: a cached numba kernel that calls another file's kernel is
recompiled when that file changes (numba alone would keep the stale callee), in fresh
processes sharing one cache directory; and cml's kernels are guarded as one unit."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

CALLER = textwrap.dedent("""
    import os
    from numba import njit
    from callee import value
    from pipeline.dsp.kernel_cache import drop_stale

    @njit(cache=True)
    def caller():
        return value() + 1

    GUARD = drop_stale((caller,), [os.path.join(os.path.dirname(__file__), "callee.py")], "caller")
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
    (tmp_path / "caller.py").write_text(CALLER.split("GUARD =")[0])
    callee = tmp_path / "callee.py"
    callee.write_text("from numba import njit\n\n@njit(cache=True)\ndef value():\n    return 1\n")
    assert run(tmp_path) == 2
    callee.write_text("from numba import njit\n\n@njit(cache=True)\ndef value():\n    return 10\n")
    assert run(tmp_path) == 2


def test_cml_kernels_are_guarded_by_what_they_import():
    """Each kernel module of cml is guarded by the modules it imports, directly or not (read
    from its import statements), and every kernel of the package by its module."""
    import pipeline.dsp.cml.kernels as kernels
    from numba.core.dispatcher import Dispatcher

    files = {p.name for p in Path(kernels.__file__).parent.glob("*.py")}
    assert {Path(m.__file__).name for m in kernels.MODULES} | {"__init__.py"} == files
    dispatchers = {v for m in kernels.MODULES for v in vars(m).values() if isinstance(v, Dispatcher)}
    assert dispatchers <= set(kernels.KERNELS) and len(kernels.KERNELS) > 50
    short = {k.rsplit(".", 1)[1]: {d.rsplit(".", 1)[1] for d in v} for k, v in kernels.DEPENDS.items()}
    assert short["likelihood"] == {"layout"} and short["layout"] == set()
    assert short["refine"] == {"layout", "likelihood", "linalg", "model"}
    assert short["stages"] == {"layout", "likelihood", "linalg", "model", "refine", "search", "detect", "doppler"}
    assert short["entry"] == short["stages"] | {"stages"}
