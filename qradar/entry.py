"""The ``qradar`` command's process entry (the console script and ``python -m qradar``):
what a process must set before numpy loads, then :func:`qradar.cli.main`."""

from __future__ import annotations

import json
import os
import sys

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
    """The ``qradar`` command (:func:`qradar.cli.main`) in a prepared process. Ctrl-C before
    the command handles it (while its modules load, its options are read): one line and
    status 130, with ``--json`` the error object on stdout, as after (no traceback)."""
    prepare_process()
    try:
        from qradar.cli import main as cli_main

        return cli_main()
    except KeyboardInterrupt:
        return interrupted(sys.argv[1:])


def interrupted(argv: list[str]) -> int:
    """What a command interrupted before it could say so itself prints (``argv``: its
    arguments); 130."""
    command = next((a for a in argv if not a.startswith("-")), "")
    print(f"qradar {command}: interrupted" if command else "qradar: interrupted", file=sys.stderr, flush=True)
    if "--json" in argv:
        print(json.dumps({"error": "interrupted", "exit_code": 130, "command": command}), flush=True)
    return 130
