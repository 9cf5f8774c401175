"""numba's on-disk cache of kernels that call another module's kernels.

numba keys a cached kernel on the file that defines it alone, so a kernel compiled with a
callee from another file keeps a stale copy of that callee after the callee's file changes
(measured: the merged decoder 1.7 times slower, with other results, until its cache was
dropped). :func:`drop_stale` keeps a stamp (mtime and size) of the callees' files beside the
cache and drops the callers' cached code when it differs."""

from __future__ import annotations

import os


def drop_stale(module_file: str, kernels: tuple, deps: tuple[str, ...]) -> None:
    """Flush the on-disk cache of ``kernels`` (numba dispatchers defined in ``module_file``)
    when a file of ``deps`` (names beside ``module_file``) changed since the stamp kept for
    them; call it when the module is imported, before the kernels are first used. A
    read-only or absent cache is left alone (numba then compiles in memory)."""
    here = os.path.dirname(os.path.abspath(module_file))
    mine = os.path.basename(module_file)
    try:
        stamp = ";".join(f"{f}:{s.st_mtime_ns}:{s.st_size}" for f in sorted(deps)
                         for s in [os.stat(os.path.join(here, f))])
        path = os.path.join(kernels[0]._cache._cache_path, mine + ".deps")
        if os.path.exists(path):
            with open(path) as fh:
                if fh.read() == stamp:
                    return
        for kernel in kernels:
            kernel._cache.flush()
        with open(path, "w") as fh:
            fh.write(stamp)
    except (OSError, AttributeError):
        pass
