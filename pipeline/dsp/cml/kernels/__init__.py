"""cml's compiled (numba) kernels: the likelihood of the codes (:mod:`.likelihood`), the model
and its Jacobian (:mod:`.model`), the linear solves (:mod:`.linalg`), the Levenberg--Marquardt
refinement (:mod:`.refine`), the search of the oversampled range grid (:mod:`.search`),
detection and the count test (:mod:`.detect`) and the stages a decode calls, one call a block
each (:mod:`.stages`); their arguments: :mod:`.layout`.

Compiled on first use and cached on disk (``cache=True``: ``__pycache__`` beside these files,
or ``NUMBA_CACHE_DIR``), so a later process loads them instead of compiling. The kernels of
these files call one another and read one another's constants, which numba's cache does not
follow across files (:mod:`pipeline.dsp.kernel_cache`): the files are one unit, whose cached
code is dropped when any of them changes."""

from __future__ import annotations

import os

from numba.core.dispatcher import Dispatcher

from pipeline.dsp.cml.kernels import detect, entry, layout, likelihood, linalg, model, refine, search, stages
from pipeline.dsp.kernel_cache import drop_stale

MODULES = (layout, likelihood, model, linalg, refine, search, detect, stages, entry)
#: every kernel of the package
KERNELS = tuple(v for m in MODULES for v in vars(m).values() if isinstance(v, Dispatcher)
                and v.py_func.__module__ == m.__name__)
#: whether importing the package dropped a stale cache (its files changed since it was written)
DROPPED = drop_stale(KERNELS, [m.__file__ for m in MODULES] + [os.path.abspath(__file__)], "cml-kernels")
