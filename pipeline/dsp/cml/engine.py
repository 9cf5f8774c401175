"""The one place that decides cml's engine: the compiled kernels (numba) or the numpy
reference they are tested against."""

from __future__ import annotations

import importlib.util

from pipeline.dsp.cml.options import ENGINES
from pipeline.errors import ParameterError

#: numba is installed: the compiled engine can run (imported on first use, so that importing
#: cml stays cheap)
HAVE_NUMBA = importlib.util.find_spec("numba") is not None
DEFAULT_ENGINE = "numba" if HAVE_NUMBA else "numpy"


def resolve(engine: str | None) -> str:
    """The engine to run for ``engine`` (None: :data:`DEFAULT_ENGINE`): "numba" or "numpy";
    a ParameterError for an unknown one or for "numba" without numba."""
    name = DEFAULT_ENGINE if engine is None else engine
    if name not in ENGINES or (name == "numba" and not HAVE_NUMBA):
        raise ParameterError(f"cml: engine={engine!r} is not available; available: "
                             f"{', '.join(e for e in ENGINES if e != 'numba' or HAVE_NUMBA)}")
    return name


def blocks(engine: str, config, options):
    """The block decoder of ``engine`` (resolved) for ``config`` (a RadarConfig) and
    ``options`` (:class:`~pipeline.dsp.cml.options.CmlOptions`): a
    :class:`pipeline.dsp.cml.compiled.CompiledBlocks` or a
    :class:`pipeline.dsp.cml.reference.ReferenceBlocks`, each imported here only."""
    if engine == "numba":
        from pipeline.dsp.cml.compiled import CompiledBlocks
        return CompiledBlocks(config, options)
    from pipeline.dsp.cml.reference import ReferenceBlocks
    return ReferenceBlocks(config, options)
