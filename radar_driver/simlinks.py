"""The links a simulated K-MD2 is served on: a pseudo-terminal behind a stable symlink
(:class:`PtyLink`, which reads the host's line speed from the terminal settings) and a
TCP port for ``socket://`` (:class:`TcpLink`). Bytes only; the device logic is
:class:`~.simulator.SimulatedKMD2`. ``read`` returns what arrived within a timeout and
raises :class:`~.errors.LinkDown` once the link is gone; ``write`` says whether the host
took the bytes in time.
"""

from __future__ import annotations

import errno
import logging
import os
import select
import socket
import termios
import time
import tty
from pathlib import Path

from .devices import cmdline, pty_master_pid
from .errors import ConfigError, LinkDown

log = logging.getLogger("qradar.sim")

_SPEED_TO_BAUD = {getattr(termios, f"B{b}"): b for b in (9600, 19200, 38400, 57600, 115200, 230400, 460800,
                                                        921600, 1000000, 1500000, 2000000, 3000000)
                  if hasattr(termios, f"B{b}")}


class PtyLink:
    """A pseudo-terminal whose slave end is reachable at a stable symlink ``link_path``.

    The link replaces nothing that is not its own: a path that does not exist is
    created (exclusively); an existing path is replaced only if it is a stale link of a
    simulator: a symlink to a ``/dev/pts/N`` that no longer exists or whose master no
    process holds (left by a killed ``qradar sim``). Anything else (a file, a folder, a
    link elsewhere, a live simulator's link) is a ConfigError naming it. On close the
    link is removed only if it still points to this pty."""

    def __init__(self, link_path: str | Path):
        self.link_path = Path(link_path)
        self.master: int | None = None
        self.slave: int | None = None
        self._target: str | None = None

    def check_free(self) -> None:
        """ConfigError unless ``link_path`` is free or a stale simulator link."""
        path = self.link_path
        if not os.path.lexists(path):
            return
        if not path.is_symlink():
            kind = "folder" if path.is_dir() else "file"
            raise ConfigError(f"refusing to replace {path}: it is a {kind}, not a simulator's pty link; "
                              f"give --link a new path")
        target = os.readlink(path)
        index = target.removeprefix("/dev/pts/")
        if not (target.startswith("/dev/pts/") and index.isdigit()):
            raise ConfigError(f"refusing to replace {path}: it links to {target}, not to a pty; give --link a new path")
        holder = pty_master_pid(int(index)) if os.path.exists(target) else None
        if holder is not None:
            raise ConfigError(f"refusing to replace {path}: its pty {target} is served by process {holder} "
                              f"({cmdline(holder)}); stop that simulator or give --link a new path")

    def open(self) -> None:
        self.check_free()
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line editing, before any host opens it
        os.set_blocking(master, False)
        self.master, self.slave = master, slave
        self._target = os.ttyname(slave)
        try:
            if os.path.lexists(self.link_path):  # a stale link (check_free): replaced atomically
                tmp = self.link_path.with_name(f".{self.link_path.name}.{os.getpid()}.tmp")
                os.symlink(self._target, tmp)  # exclusive: fails if something is there
                os.replace(tmp, self.link_path)
            else:
                os.symlink(self._target, self.link_path)  # exclusive: a path made meanwhile is not replaced
        except OSError as exc:
            self.close()
            raise ConfigError(f"cannot make the pty link {self.link_path}: {exc.strerror or exc}") from None
        log.info("simulated K-MD2 on %s -> %s", self.link_path, self._target)

    def close(self) -> None:
        try:
            if self._target is not None and os.readlink(self.link_path) == self._target:
                self.link_path.unlink()
        except OSError:  # gone, or not a link: not ours to remove
            pass
        for fd in (self.master, self.slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = None

    def host_baud(self) -> int | None:
        if self.slave is None:
            return None
        speed = termios.tcgetattr(self.slave)[4]
        return _SPEED_TO_BAUD.get(speed)

    def read(self, timeout_s: float) -> bytes:
        if self.master is None:
            raise LinkDown("pty closed")
        ready, _, _ = select.select([self.master], [], [], timeout_s)
        if not ready:
            return b""
        try:
            return os.read(self.master, 65536)
        except BlockingIOError:
            return b""
        except OSError as exc:
            if exc.errno == errno.EIO:
                return b""
            raise

    def write(self, data: bytes, timeout_s: float = 1.0) -> bool:
        """Write all of ``data``; False (and the host's unread input flushed) if the host
        has not read it within ``timeout_s``."""
        view = memoryview(data)
        deadline = time.monotonic() + timeout_s
        while view:
            if self.master is None:
                raise LinkDown("pty closed")
            _, ready, _ = select.select([], [self.master], [], max(0.0, deadline - time.monotonic()))
            if not ready:
                termios.tcflush(self.slave, termios.TCIFLUSH)
                return False
            try:
                n = os.write(self.master, view)
            except BlockingIOError:
                continue
            view = view[n:]
        return True


class TcpLink:
    """A TCP server on ``host:port`` for ``socket://host:port``; one client at a time."""

    def __init__(self, port: int, host: str = "127.0.0.1"):
        self.host, self.port = host, port
        self.server: socket.socket | None = None
        self.client: socket.socket | None = None

    def open(self) -> None:
        srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            srv.bind((self.host, self.port))
            srv.listen(1)
        except (OSError, OverflowError) as exc:
            srv.close()
            raise ConfigError(f"cannot serve on {self.host}:{self.port}: {getattr(exc, 'strerror', None) or exc}") from None
        self.port = srv.getsockname()[1]
        self.server = srv
        log.info("simulated K-MD2 on socket://%s:%d", self.host, self.port)

    def close(self) -> None:
        for s in (self.client, self.server):
            if s is not None:
                try:
                    s.close()
                except OSError:
                    pass
        self.client = self.server = None

    def host_baud(self) -> int | None:
        return None

    def read(self, timeout_s: float) -> bytes:
        if self.server is None:
            raise LinkDown("tcp link closed")
        if self.client is None:
            ready, _, _ = select.select([self.server], [], [], timeout_s)
            if ready:
                self.client, _ = self.server.accept()
                self.client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            return b""
        ready, _, _ = select.select([self.client], [], [], timeout_s)
        if not ready:
            return b""
        try:
            data = self.client.recv(65536)
        except OSError:
            data = b""
        if not data:
            self.client.close()
            self.client = None
            raise LinkDown("tcp client left")
        return data

    def write(self, data: bytes, timeout_s: float = 1.0) -> bool:
        if self.client is None:
            return False
        try:
            self.client.settimeout(timeout_s)
            self.client.sendall(data)
            return True
        except OSError:
            return False
