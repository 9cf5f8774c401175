"""The packages import one way: radar_driver <- pipeline <- replay <- qradar.

Every import of every module (also the ones inside functions) is read from the source,
so a lazy import cannot hide a cycle. A module may import its own package and the
packages before it, never one after it; and no two modules may import each other,
directly or through others."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ORDER = ["radar_driver", "pipeline", "replay", "qradar"]


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
    assert not wrong, "imports against radar_driver <- pipeline <- replay <- qradar:\n" + "\n".join(wrong)


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
    p.write_text("def f():\n    from replay.mcapio import McapFile\nfrom .bus import BusConfig\n")
    known = {"replay.mcapio", "pipeline.bus", "pipeline.x"}
    assert imports_of("pipeline.x", p, known) == {"replay.mcapio", "pipeline.bus"}


@pytest.mark.parametrize("module, absent", [
    ("radar_driver.session", ["pipeline", "replay", "qradar", "zenoh", "mcap"]),
    ("pipeline.montecarlo", ["replay", "qradar", "zenoh", "serial", "mcap"]),
    ("replay.reprocess", ["qradar", "zenoh"]),
])
def test_offline_modules_do_not_pull_in_the_bus(module, absent):
    code = (f"import sys, {module}; bad = [m for m in {absent!r} if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert proc.returncode == 0, f"{module} imports {proc.stdout.strip()} {proc.stderr[-500:]}"


def test_python_m_qradar_works():
    proc = subprocess.run([sys.executable, "-m", "qradar", "--help"], capture_output=True, text=True, timeout=60,
                          cwd=ROOT)
    assert proc.returncode == 0 and "montecarlo" in proc.stdout and "reprocess" in proc.stdout
