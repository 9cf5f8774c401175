"""What a local device path names, and who holds it: from /proc and sysfs (Linux), for
the driver's one-owner rule and reconnects, and the simulator's pty links."""

from __future__ import annotations

import os
import stat

#: majors of Unix 98 pty slaves (/dev/pts/N)
PTY_SLAVE_MAJORS = range(136, 144)


def device_identity(path: str) -> tuple | None:
    """The device a local path names now, as a reconnect compares it with the first
    open's, or None if it names no character device:

    - a pty slave (``/dev/pts/N``): ("pty", pid of the process holding its master), since
      the kernel hands a freed pty number to the next program, and the program on the
      other end is the device (a simulator that re-opens its link stays the same);
    - another device: ("device", its hardware's sysfs path: e.g. the USB interface an
      adapter sits in, which stays when it comes back as another ttyUSB number), or its
      real path and number when sysfs has no hardware behind it."""
    try:
        real = os.path.realpath(path)
        st = os.stat(real)
    except OSError:
        return None
    if not stat.S_ISCHR(st.st_mode):
        return None
    major, minor = os.major(st.st_rdev), os.minor(st.st_rdev)
    if major in PTY_SLAVE_MAJORS:
        return "pty", pty_master_pid(minor)
    hw = os.path.realpath(f"/sys/dev/char/{major}:{minor}/device")
    if os.path.exists(hw):
        return "device", os.path.dirname(hw) if os.path.basename(hw).startswith("tty") else hw
    return "device", real, st.st_rdev


def open_fds():
    """(pid, path of the fd in /proc) of every open file descriptor this user may see."""
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            fds = os.listdir(f"/proc/{entry}/fd")
        except OSError:
            continue
        for fd in fds:
            yield int(entry), f"/proc/{entry}/fd/{fd}"


def pty_master_pid(index: int) -> int | None:
    """The pid of a process holding the master of pty ``index`` open (its ``tty-index``
    in /proc/PID/fdinfo), or None if none this user may see."""
    for pid, fd_path in open_fds():
        try:
            if os.readlink(fd_path) != "/dev/ptmx":
                continue
            with open(fd_path.replace("/fd/", "/fdinfo/")) as f:
                if f"tty-index:\t{index}\n" in f.read():
                    return pid
        except OSError:
            continue
    return None


def port_holders(path: str, limit: int = 4) -> list[tuple[int, str]]:
    """(pid, command line) of the processes that hold the character device ``path`` open
    (from /proc: those this user may read), at most ``limit``."""
    try:
        st = os.stat(path)
    except OSError:
        return []
    if not stat.S_ISCHR(st.st_mode):
        return []
    pids: list[int] = []
    for pid, fd_path in open_fds():
        if len(pids) >= limit:
            break
        try:
            held = os.stat(fd_path)
        except OSError:
            continue
        if pid not in pids and stat.S_ISCHR(held.st_mode) and held.st_rdev == st.st_rdev:
            pids.append(pid)
    return [(pid, cmdline(pid)) for pid in pids]


def lock_holders(path: str) -> list[int]:
    """Pids holding a ``flock`` on ``path`` (from /proc/locks), e.g. another driver."""
    try:
        st = os.stat(path)
        with open("/proc/locks") as f:
            lines = f.read().splitlines()
    except OSError:
        return []
    where = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    return [int(p[4]) for p in (line.split() for line in lines) if len(p) > 5 and p[1] == "FLOCK" and p[5] == where]


def cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace").strip()[:120]
    except OSError:
        return "?"


