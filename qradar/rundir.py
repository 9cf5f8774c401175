"""The private directory of a ``qradar run`` (its simulated sensors' pty links and the
zenoh unix socket its drivers join): made in the system's temporary folder, removed
when the run ends in any way it can (its end, an error, a second Ctrl-C:
:func:`remove_run_dirs`), and, for the one way it cannot (SIGKILL, a power cut), by the
next ``qradar run`` that starts (:func:`remove_stale_run_dirs`).

A run holds an exclusive ``flock`` on the file ``owner.lock`` in its directory for as
long as it lives; the kernel lets go of it however the process ends, and no child holds
it (the descriptor is not inherited). So a directory whose lock can be taken belongs to
no live run, whatever became of its process id. Only the current user's directories of
that name that hold such a lock file are ever removed: one made before the lock existed,
or by another user, is left alone.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

RUN_DIR_PREFIX = "qradar-run-"
OWNER_LOCK = "owner.lock"

#: the directories of the runs in progress in this process
_RUN_DIRS: set[str] = set()


def remove_run_dirs() -> None:
    """For an exit at once (a second Ctrl-C while a run stops, no time to stop in order):
    the runs' temporary directories removed, pty links and zenoh socket (their driver
    processes stop by themselves). Quick, and raises nothing."""
    for path in list(_RUN_DIRS):
        shutil.rmtree(path, ignore_errors=True)


def remove_stale_run_dirs(base: str | Path | None = None) -> list[str]:
    """Remove the run directories in ``base`` (the temporary folder) whose run is gone
    (see the module's docstring); the paths removed."""
    base = Path(base or tempfile.gettempdir())
    removed = []
    try:
        entries = list(os.scandir(base))
    except OSError:
        return removed
    for entry in entries:
        try:
            if (not entry.name.startswith(RUN_DIR_PREFIX) or not entry.is_dir(follow_symlinks=False)
                    or entry.stat(follow_symlinks=False).st_uid != os.getuid()):
                continue
            fd = os.open(os.path.join(entry.path, OWNER_LOCK), os.O_RDONLY | os.O_CLOEXEC | os.O_NOFOLLOW)
        except OSError:  # no lock file (not one of ours to judge), or gone meanwhile
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # its run is alive
            os.close(fd)
            continue
        try:
            shutil.rmtree(entry.path, ignore_errors=True)
            removed.append(entry.path)
        finally:
            os.close(fd)
    return removed


@contextmanager
def run_directory() -> Iterator[str]:
    """A new run directory, held (``owner.lock``) while the block runs and removed after
    it; the stale ones of runs gone first."""
    remove_stale_run_dirs()
    with tempfile.TemporaryDirectory(prefix=RUN_DIR_PREFIX) as tmp:
        fd = os.open(os.path.join(tmp, OWNER_LOCK), os.O_CREAT | os.O_RDWR | os.O_CLOEXEC, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            os.write(fd, f"{os.getpid()}\n".encode())
            _RUN_DIRS.add(tmp)
            yield tmp
        finally:
            _RUN_DIRS.discard(tmp)
            os.close(fd)
