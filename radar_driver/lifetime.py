"""A child process's life tied to its parent's: :func:`watch_parent` (the nodes a command
starts, the Monte Carlo's worker processes)."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time


#: how often a child process looks whether its parent is still there, s
PARENT_POLL_S = 0.2
#: after its parent's death, how long a child may take to stop cleanly before it exits anyway, s
PARENT_GONE_GRACE_S = 3.0


def watch_parent(parent_pid: int, name: str) -> threading.Thread:
    """End this process when ``parent_pid`` is no longer its parent (it died, however:
    SIGKILL, the OOM killer, a crash), within PARENT_POLL_S: SIGTERM to itself, so the
    command stops as on a SIGTERM (a driver says GBYE), and, should that not end it within
    PARENT_GONE_GRACE_S, ``os._exit(1)``. A poll, not Linux's ``PR_SET_PDEATHSIG``:
    that fires when the *thread* that started the child ends, which may be long before
    its process does."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_POLL_S)
        try:  # stderr may be a pipe to the parent that died
            print(f"qradar {name}: its parent process {parent_pid} is gone; stopping", file=sys.stderr, flush=True)
        except (OSError, ValueError):
            pass
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(PARENT_GONE_GRACE_S)
        os._exit(1)

    t = threading.Thread(target=watch, name="parent-watch", daemon=True)
    t.start()
    return t
