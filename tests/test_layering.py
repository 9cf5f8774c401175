"""The packages import one way: radar_driver <- pipeline <- replay <- experiments <- qradar, and inside
pipeline its jobs: the base (errors, defaults, keys) <- dsp <- wire <- bus <- nodes.

Every import of every module (also the ones inside functions) is read from the source,
so a lazy import cannot hide a cycle. A module may import its own package and the
packages before it, never one after it; and no two modules may import each other,
directly or through others."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest
from zenoh_helpers import QRADAR

ROOT = Path(__file__).resolve().parents[1]
ORDER = ["radar_driver", "pipeline", "replay", "experiments", "qradar"]


def modules() -> dict[str, Path]:
    out = {}
    for pkg in ORDER:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = path
    return out


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    """The qradar modules ``name`` imports (resolved to the longest known module name)."""
    tree = ast.parse(path.read_text(), str(path))
    is_pkg = path.name == "__init__.py"
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    found = set()
    for node in ast.walk(tree):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                head = base[: len(base) - node.level + 1]
                mod = ".".join(head + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            targets = [mod] + [f"{mod}.{a.name}" for a in node.names]
        for t in targets:
            parts = t.split(".")
            for i in range(len(parts), 0, -1):
                cand = ".".join(parts[:i])
                if cand in known:
                    if cand != name:
                        found.add(cand)
                    break
    return found


def graph() -> dict[str, set[str]]:
    mods = modules()
    known = set(mods)
    return {name: imports_of(name, path, known) for name, path in mods.items()}


def test_every_import_follows_the_package_order():
    rank = {pkg: i for i, pkg in enumerate(ORDER)}
    wrong = [f"{m} imports {d}" for m, deps in graph().items() for d in sorted(deps)
             if rank[d.split(".")[0]] > rank[m.split(".")[0]]]
    assert not wrong, "imports against " + " <- ".join(ORDER) + ":\n" + "\n".join(wrong)


def test_no_import_cycle():
    g = graph()
    # a package's __init__ re-exporting its own modules is not a cycle of the modules
    edges = {m: {d for d in deps if not (g.get(d) is not None and d == m.rsplit(".", 1)[0])}
             for m, deps in g.items()}
    state: dict[str, int] = {}
    cycles = []

    def visit(m, stack):
        state[m] = 1
        for d in sorted(edges[m]):
            if state.get(d) == 1:
                cycles.append(" -> ".join(stack[stack.index(d):] + [d]))
            elif d not in state:
                visit(d, stack + [d])
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m, [m])
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_the_checker_sees_lazy_and_relative_imports(tmp_path):
    p = tmp_path / "x.py"
    p.write_text("def f():\n    from replay.mcapio import McapFile\nfrom .session import BusConfig\n"
                 "from ..dsp import quantize\n")
    known = {"replay.mcapio", "pipeline.bus.session", "pipeline.bus.x", "pipeline.dsp.quantize", "pipeline.dsp"}
    assert imports_of("pipeline.bus.x", p, known) == {"replay.mcapio", "pipeline.bus.session", "pipeline.dsp",
                                                      "pipeline.dsp.quantize"}


@pytest.mark.parametrize("module, absent", [
    ("radar_driver.session", ["pipeline", "replay", "qradar", "zenoh", "mcap"]),
    ("experiments.montecarlo", ["qradar", "zenoh", "serial", "mcap", "pipeline.wire", "pipeline.bus", "pipeline.nodes"]),
    ("experiments.report", ["qradar", "zenoh", "serial", "mcap", "pipeline.wire", "pipeline.bus", "pipeline.nodes"]),
    ("replay.reprocess", ["qradar", "zenoh", "experiments"]),
    # every qradar process (each node, driver, router) imports the command line: numba (the
    # compiled kernels, ~0.25 s) and scipy (~0.12 s) load when a cml decoder or an uncertainty
    # is first asked for, not at its start
    ("qradar.cli", ["numba", "scipy", "pipeline.dsp.cml.decoder", "pipeline.dsp.cml.kernels"]),
])
def test_offline_modules_do_not_pull_in_the_bus(module, absent):
    code = (f"import sys, {module}; bad = [m for m in {absent!r} if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert proc.returncode == 0, f"{module} imports {proc.stdout.strip()} {proc.stderr[-500:]}"


def test_python_m_qradar_works():
    proc = subprocess.run([*QRADAR, "--help"], capture_output=True, text=True, timeout=60,
                          cwd=ROOT)
    assert proc.returncode == 0 and "montecarlo" in proc.stdout and "reprocess" in proc.stdout


#: inside pipeline the jobs import one way too: the base modules (errors, defaults, keys)
#: <- dsp (the maths) <- wire (the formats) <- bus (zenoh) <- nodes (the runtime and the nodes)
PIPELINE_ORDER = ["pipeline", "pipeline.dsp", "pipeline.wire", "pipeline.bus", "pipeline.nodes"]


def pipeline_layer(module: str) -> str | None:
    """The layer of a pipeline module (None outside pipeline): its subpackage, or the base."""
    parts = module.split(".")
    if parts[0] != "pipeline":
        return None
    sub = ".".join(parts[:2])
    return sub if sub in PIPELINE_ORDER else "pipeline"


def test_pipeline_imports_follow_its_jobs():
    rank = {layer: i for i, layer in enumerate(PIPELINE_ORDER)}
    wrong = [f"{m} imports {d}" for m, deps in graph().items() if pipeline_layer(m)
             for d in sorted(deps) if pipeline_layer(d) and rank[pipeline_layer(d)] > rank[pipeline_layer(m)]]
    assert not wrong, "imports against " + " <- ".join(PIPELINE_ORDER) + ":\n" + "\n".join(wrong)


def test_every_pipeline_module_sits_in_a_job():
    """A new module goes into the subpackage of its job, not beside them."""
    base = sorted(m for m in modules() if pipeline_layer(m) == "pipeline")
    assert base == ["pipeline", "pipeline.defaults", "pipeline.errors", "pipeline.keys"], base


def _loaded_after_import(modules_: list[str]) -> set[str]:
    code = ("import sys, importlib; [importlib.import_module(m) for m in sys.argv[1:]]; "
            "print(' '.join(sorted(sys.modules)))")
    proc = subprocess.run([sys.executable, "-c", code, *modules_], capture_output=True, text=True, timeout=120,
                          cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-800:]
    return set(proc.stdout.split())


def test_the_maths_import_no_io():
    """pipeline.dsp: numpy (scipy, numba) and the signal model; no bus, port or file format."""
    dsp = sorted(m for m in modules() if pipeline_layer(m) == "pipeline.dsp")
    loaded = _loaded_after_import(dsp)
    bad = sorted(m for m in loaded if m.split(".")[0] in ("zenoh", "serial", "mcap", "replay", "qradar")
                 or pipeline_layer(m) in ("pipeline.wire", "pipeline.bus", "pipeline.nodes"))
    assert not bad, f"importing pipeline.dsp loads {bad}"


def test_opening_a_bus_imports_no_maths():
    loaded = _loaded_after_import(["pipeline.bus.session", "pipeline.bus.security"])
    bad = sorted(m for m in loaded if pipeline_layer(m) in ("pipeline.dsp", "pipeline.wire", "pipeline.nodes"))
    assert not bad, f"opening a bus loads {bad}"


MAX_FILE_LINES = 600
MAX_CLASS_LINES = 300


def test_no_file_over_600_lines_and_no_class_over_300():
    long = []
    for name, path in modules().items():
        text = path.read_text()
        if len(text.splitlines()) > MAX_FILE_LINES:
            long.append(f"{path.relative_to(ROOT)}: {len(text.splitlines())} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > MAX_CLASS_LINES:
                long.append(f"{path.relative_to(ROOT)}: class {node.name} {node.end_lineno - node.lineno + 1} lines")
    assert not long, "\n".join(long)


#: the size of a function (issue 39): its lines, and its parameters (self and *args included)
MAX_FUNCTION_LINES = 80
MAX_FUNCTION_PARAMS = 12


def oversized_functions(prefixes: tuple[str, ...] = ()) -> list[str]:
    """The functions (kernels included) over MAX_FUNCTION_LINES lines or MAX_FUNCTION_PARAMS
    parameters in the library modules whose names start with one of ``prefixes`` (all: ())."""
    found = []
    for name, path in modules().items():
        if prefixes and not name.startswith(prefixes):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                params = (len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + (a.vararg is not None)
                          + (a.kwarg is not None))
                lines = node.end_lineno - node.lineno + 1
                if lines > MAX_FUNCTION_LINES or params > MAX_FUNCTION_PARAMS:
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}: {lines} lines, "
                                 f"{params} parameters")
    return found


def test_no_library_function_is_over_80_lines_or_12_parameters():
    long = oversized_functions()
    assert not long, "\n".join(long)


def test_the_size_checker_counts_lines_and_every_kind_of_parameter(tmp_path, monkeypatch):
    p = tmp_path / "x.py"
    body = "\n".join(f"    v{i} = {i}" for i in range(MAX_FUNCTION_LINES))
    p.write_text(f"def long():\n{body}\n\ndef wide(a, b, /, c, *d, e, f, g, h, i, j, k, l, **m):\n    return 0\n\n"
                 "def fine(a, b, c, d, e, f, g, h, i, j, k, l):\n    return 0\n")
    monkeypatch.setattr(sys.modules[__name__], "modules", lambda: {"pipeline.dsp.cml.x": p})
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    found = oversized_functions()
    assert [f.split(" ")[1] for f in found] == ["long:", "wide:"], found


def test_the_cml_package_imports_no_private_name_of_another_module():
    """Its stages share only public names; what a module keeps to itself starts with ``_``."""
    mods = {n: p for n, p in modules().items() if n.startswith("pipeline.dsp.cml")}
    bad = []
    for name, path in mods.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("pipeline.dsp.cml"):
                bad += [f"{name}: {node.module}.{a.name}" for a in node.names if a.name.startswith("_")]
    assert not bad, "\n".join(bad)


def test_one_module_of_cml_chooses_the_engine():
    """pipeline.dsp.cml.engine alone imports the compiled engine or the numpy reference (the
    tests compare the two), so the choice is made in one place."""
    g = graph()
    importers = sorted(m for m, deps in g.items() if deps & {"pipeline.dsp.cml.compiled", "pipeline.dsp.cml.reference"})
    assert importers == ["pipeline.dsp.cml.engine"], importers


# -- no hidden global state (issue 39): caches and registries belong to the object that uses them
#: methods that change a container or an event in place
MUTATORS = {"add", "append", "appendleft", "clear", "discard", "extend", "insert", "pop", "popitem", "remove",
            "setdefault", "update", "sort", "reverse", "set"}
#: module-level state a library module still changes after import, each with why it is the process's own
PROCESS_STATE = {
    "pipeline.bus.audit": "zenoh's log is the process's (zenoh.init_log_* takes effect once) and the audit holds "
                          "fd 2 to read it: one audit a process, started by the command",
    "pipeline.bus.router_check": "the checks of the process's zenoh sessions, looked up by zenoh id from a session's "
                                 "callbacks, dropped when their session closes",
    "qradar.rundir": "the process's run directories, for the exit at once of a second Ctrl-C (a signal handler)",
}


def state_mutations(path: Path) -> list[str]:
    """Where a module's functions change its module-level state: a ``global`` statement, a
    mutating method called on a module-level name, an item or attribute of one assigned or
    deleted. (A bounded ``functools.lru_cache`` of a pure function is a memo, not state.)"""
    tree = ast.parse(path.read_text())
    names = set()
    for node in tree.body:
        targets = (node.targets if isinstance(node, ast.Assign)
                   else [node.target] if isinstance(node, ast.AnnAssign) else [])
        names |= {t.id for t in targets if isinstance(t, ast.Name)}
    found = []
    for fn in ast.walk(tree):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        local = {a.arg for a in fn.args.args + fn.args.kwonlyargs + fn.args.posonlyargs}
        local |= {t.id for n in ast.walk(fn) if isinstance(n, (ast.Assign, ast.AnnAssign, ast.For, ast.With))
                  for t in ast.walk(n) if isinstance(t, ast.Name) and isinstance(t.ctx, ast.Store)}
        shared = names - local
        for n in ast.walk(fn):
            if isinstance(n, ast.Global):
                found.append(f"{n.lineno}: global {', '.join(n.names)}")
            elif (isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and isinstance(n.func.value, ast.Name)
                  and n.func.value.id in shared and n.func.attr in MUTATORS):
                found.append(f"{n.lineno}: {n.func.value.id}.{n.func.attr}()")
            elif isinstance(n, (ast.Assign, ast.AugAssign, ast.Delete)):
                for t in n.targets if isinstance(n, (ast.Assign, ast.Delete)) else [n.target]:
                    if isinstance(t, (ast.Subscript, ast.Attribute)) and isinstance(t.value, ast.Name) \
                            and t.value.id in shared:
                        found.append(f"{n.lineno}: {ast.unparse(t)} changed")
    return found


def test_no_library_module_mutates_module_level_state_after_import():
    bad = [f"{path.relative_to(ROOT)}:{line}" for name, path in modules().items() if name not in PROCESS_STATE
           for line in state_mutations(path)]
    assert not bad, "module-level state changed after import (own it in the object that uses it):\n" + "\n".join(bad)


def test_the_state_checker_sees_globals_methods_and_items(tmp_path):
    p = tmp_path / "x.py"
    p.write_text("_seen = set()\n_cache = {}\n_on = None\n\ndef a(x):\n    _seen.add(x)\n\n"
                 "def b(k):\n    _cache[k] = 1\n\ndef c():\n    global _on\n    _on = 1\n\n"
                 "def fine(_seen):\n    _seen.add(1)\n    local = {}\n    local[1] = 2\n    return len(_cache)\n")
    assert [f.split(": ", 1)[1] for f in state_mutations(p)] == ["_seen.add()", "_cache[k] changed", "global _on"]
