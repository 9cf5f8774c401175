"""Handing the C heap's free memory back to the system.

glibc keeps what a program frees in its heap arenas and returns to the system only the
free top of the main arena (beyond M_TRIM_THRESHOLD); memory freed inside an arena, or
in the arenas of other threads (zenoh's among them), stays in the process's RSS until
``malloc_trim`` is called. A node that forgets many sensors at once frees their state
(stats, histograms, zenoh publishers: ~12 KB a sensor) into the heap, so it calls
:func:`release_memory` after an expiry sweep (:meth:`pipeline.nodes.runtime.Node._expire`).
"""

from __future__ import annotations

import ctypes
import sys


def _find_malloc_trim():
    """glibc's ``malloc_trim``, or None (not Linux, or another C library)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        trim = ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


_MALLOC_TRIM = _find_malloc_trim()


def release_memory() -> bool:
    """Give the free pages of every heap arena back to the system (glibc's
    ``malloc_trim(0)``); True when some were, False when none were or there is no such call."""
    return _MALLOC_TRIM is not None and bool(_MALLOC_TRIM(0))
