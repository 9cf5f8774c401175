"""numba's on-disk cache of kernels that call kernels of other files.

What numba checks itself before it loads a cached kernel (``numba.core.caching``): the
defining file's stamp (its modification time and size up to numba 0.67, a hash of its content
from 0.68, numba PR #10659), the kernel's own bytecode and closure, the argument types, the
CPU and numba's version. What
it does not: the files of the kernels it calls and of the globals it reads, which it compiled
in as they were (numba issue #1833; measured: a merged decoder 1.7 times slower, with other
results, until its cache was dropped). :func:`drop_stale` covers that part alone: a stamp of
the content of the files a module's kernels import (not of their own file: numba checks
that), kept beside the cache; when it differs, the kernels' cached code is dropped and numba
compiles them again."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence


def drop_stale(kernels: Sequence, files: Sequence[str], name: str) -> bool:
    """Flush the on-disk cache of ``kernels`` (numba dispatchers of one file) when the content
    of ``files`` (the files whose kernels and constants they use) changed since the stamp
    ``name`` kept beside the cache; call it when the files are imported, before a kernel is
    first used. A read-only or absent cache is left alone (numba then compiles in memory).
    Returns whether the cache was flushed."""
    try:
        digest = hashlib.sha256()
        for path in sorted(files):
            with open(path, "rb") as fh:
                digest.update(os.path.basename(path).encode() + b"\0" + fh.read() + b"\0")
        stamp = digest.hexdigest()
        path = os.path.join(kernels[0]._cache._cache_path, f"{name}.deps")
        if os.path.exists(path):
            with open(path) as fh:
                if fh.read() == stamp:
                    return False
        for kernel in kernels:
            kernel._cache.flush()
        with open(path, "w") as fh:
            fh.write(stamp)
        return True
    except (OSError, AttributeError):
        return False
