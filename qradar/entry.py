"""The ``qradar`` command's process entry (the console script and ``python -m qradar``):
what a process must set before numpy loads, then :func:`qradar.cli.main`."""

from __future__ import annotations

import os

#: BLAS threads a qradar process runs with unless the environment says otherwise
#: (``OPENBLAS_NUM_THREADS``): one. qradar scales by processes (nodes, zenoh shards), and its
#: products are small; OpenBLAS's own threads, on a 2-core host shared by a driver, a
#: quantizer and a localizer, mostly spin waiting for each other: ``make test`` took 589 s of
#: CPU with them and 498 s without (378 -> 346 s; 2026-11-28, 2-core host)
BLAS_THREADS = 1


def prepare_process() -> None:
    """One BLAS thread (:data:`BLAS_THREADS`) unless ``OPENBLAS_NUM_THREADS`` is set; before
    numpy loads (it reads it once), so only a process's entry calls it."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", str(BLAS_THREADS))


def main() -> int:
    """The ``qradar`` command (:func:`qradar.cli.main`) in a prepared process."""
    prepare_process()
    from qradar.cli import main as cli_main

    return cli_main()
