"""cml's compiled (numba) kernels: the likelihood of the codes (:mod:`.likelihood`), the model
and its Jacobian (:mod:`.model`), the linear solves (:mod:`.linalg`), the Levenberg--Marquardt
refinement (:mod:`.refine`), the search over the phase step between ramps (:mod:`.doppler`)
and of the oversampled range grid (:mod:`.search`),
detection and the count test (:mod:`.detect`), the stages a decode calls, one call a block
each (:mod:`.stages`), and the kernels Python calls (:mod:`.entry`); their arguments:
:mod:`.layout`.

Compiled on first use and cached on disk (``cache=True``: ``__pycache__`` beside these files,
or ``NUMBA_CACHE_DIR``), so a later process loads them instead of compiling. numba checks a
cached kernel against its own file; these kernels also call the kernels and read the
constants of the modules they import, which numba does not follow
(:mod:`pipeline.dsp.kernel_cache`): a module's cached kernels are dropped when a module it
imports, directly or not, changes (:data:`DEPENDS`, read from the import statements)."""

from __future__ import annotations

import re
from pathlib import Path

from numba.core.dispatcher import Dispatcher

from pipeline.dsp.cml.kernels import detect, doppler, entry, layout, likelihood, linalg, model, refine, search, stages
from pipeline.dsp.kernel_cache import drop_stale

MODULES = (layout, likelihood, model, linalg, refine, doppler, search, detect, stages, entry)
#: every kernel of the package
KERNELS = tuple(v for m in MODULES for v in vars(m).values() if isinstance(v, Dispatcher)
                and v.py_func.__module__ == m.__name__)


#: a ``from X import a, b as c`` statement (its names in parentheses over lines, or to the line's end)
_FROM_IMPORT = re.compile(r"^[ \t]*from[ \t]+([\w.]+)[ \t]+import[ \t]+(\([^)]*\)|[^\n]*)", re.M)


def _imported(module) -> set[str]:
    """The modules of the package ``module`` imports (its ``from ... import`` statements; read
    as text, not parsed: every cml process imports this package, and parsing its ten files
    cost 50 ms of each one's start)."""
    names = {m.__name__ for m in MODULES}
    found = set()
    for m in _FROM_IMPORT.finditer(Path(module.__file__).read_text()):
        words = m.group(2).split("#")[0] if not m.group(2).startswith("(") else re.sub(r"#[^\n]*", "", m.group(2))
        found |= {m.group(1)} | {f"{m.group(1)}.{w.split()[0]}" for w in words.strip("()").split(",") if w.strip()}
    return found & names


def _depends() -> dict[str, tuple[str, ...]]:
    """Each module's name -> the modules it imports, directly or through others (itself not)."""
    direct = {m.__name__: _imported(m) for m in MODULES}
    closure = {}
    for name in direct:
        seen, todo = set(), list(direct[name])
        while todo:
            dep = todo.pop()
            if dep not in seen and dep != name:
                seen.add(dep)
                todo += direct[dep]
        closure[name] = tuple(sorted(seen))
    return closure


#: each module -> the modules whose change drops its cached kernels (its own change numba sees)
DEPENDS = _depends()
_FILES = {m.__name__: m.__file__ for m in MODULES}
_OWN = {m.__name__: [k for k in KERNELS if k.py_func.__module__ == m.__name__] for m in MODULES}
#: the modules whose cached kernels importing the package dropped (a module they import changed)
DROPPED = tuple(name for name, own in _OWN.items() if own and DEPENDS[name] and drop_stale(
    own, [_FILES[d] for d in DEPENDS[name]], name.rsplit(".", 1)[1]))
