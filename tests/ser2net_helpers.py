"""ser2net (4.x) in front of a serial device, for the tests and benchmarks/bench_ser2net.py.

``with ser2net_for(link, "raw") as s2n: SessionConfig(s2n.url, ...)`` writes the YAML of
docs/chamber.md for ``link`` (a simulated K-MD2's pty) to a temporary directory, starts
ser2net in the foreground on a free 127.0.0.1 port, waits (bounded) until that port
listens, and stops ser2net on exit. ``kind`` is

- ``"raw"``: raw TCP, ``tcp(nodelay)``; the device stays at 115200 8E1 (a socket cannot
  change the line speed); URL ``socket://127.0.0.1:PORT``;
- ``"rfc2217"``: telnet with RFC 2217, ``telnet(rfc2217),tcp(nodelay)``; the client sets
  the line speed; URL ``rfc2217://127.0.0.1:PORT?ign_set_control`` (without
  ``ign_set_control`` pyserial's open waits for an answer to SET_CONTROL that ser2net
  never sends for a pty, whose modem lines it cannot read: "timeout while waiting for
  option 'control'").

ser2net missing: the test is skipped, unless ``QRADAR_REQUIRE_SER2NET=1`` (CI), where it
fails. Waiting is never done by probing the port with a connection (a connection makes
ser2net open the device): the listening socket is looked up in /proc/net/tcp.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import pytest

from zenoh_helpers import free_port

REQUIRE_ENV = "QRADAR_REQUIRE_SER2NET"
HOST = "127.0.0.1"
#: how long ser2net may take to listen after it starts, s (a bound on an event: the wait ends when it listens)
START_TIMEOUT_S = 30.0
#: how long ser2net may take to exit after SIGTERM before it gets SIGKILL, s
STOP_TIMEOUT_S = 3.0
#: ports tried when the one picked was taken in the meantime
PORT_ATTEMPTS = 3
POLL_S = 0.02

KINDS = ("raw", "rfc2217")
#: where ser2net lives when /usr/sbin is not on the PATH (a non-root user on Debian)
SBIN_PATHS = ("/usr/sbin/ser2net", "/usr/local/sbin/ser2net")


def ser2net_yaml(device: str | Path, kind: str, port: int, host: str = HOST, nodelay: bool = True,
                 chardelay: bool | None = None) -> str:
    """The ser2net 4 YAML for one K-MD2 on ``device``: 115200 8E1 (the sensor's rate at
    power-up), modem lines ignored (``local``), break cleared at open (``nobreak``), one
    client at a time, a new client takes over from a stale one (``kickolduser``).
    ``chardelay``: None leaves ser2net's default (on: it waits at least 1 ms after bytes
    from the device before sending them on, to send fewer packets)."""
    if kind not in KINDS:
        raise ValueError(f"kind={kind!r} must be one of {KINDS}")
    tcp = "tcp(nodelay)" if nodelay else "tcp"
    accepter = f"{tcp},{host},{port}" if kind == "raw" else f"telnet(rfc2217),{tcp},{host},{port}"
    return (
        "%YAML 1.1\n"
        "---\n"
        f"connection: &kmd2\n"
        f"  accepter: {accepter}\n"
        f"  connector: serialdev,{device},115200e81,local,nobreak\n"
        "  options:\n"
        "    kickolduser: true\n"
        "    max-connections: 1\n"
        + ("" if chardelay is None else f"    chardelay: {'true' if chardelay else 'false'}\n")
    )


def url_for(kind: str, port: int, host: str = HOST) -> str:
    return f"socket://{host}:{port}" if kind == "raw" else f"rfc2217://{host}:{port}?ign_set_control"


def require_ser2net() -> str:
    """The ser2net executable; skips the test when there is none (fails with
    QRADAR_REQUIRE_SER2NET=1)."""
    exe = shutil.which("ser2net") or next((p for p in SBIN_PATHS if os.access(p, os.X_OK)), None)
    if exe:
        return exe
    why = ("ser2net is not installed (Debian/Ubuntu: apt-get install ser2net); "
           "the ser2net tests need it")
    if os.environ.get(REQUIRE_ENV) == "1":
        pytest.fail(f"{why}, and {REQUIRE_ENV}=1 requires them", pytrace=False)
    pytest.skip(why)


def _die_with_parent() -> None:
    """In the child before exec: SIGKILL when the process that started it dies (Linux), so
    a killed test run leaves no ser2net behind."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def listening_addresses(port: int) -> set[str]:
    """Local addresses of the TCP sockets listening on ``port`` (IPv4 and IPv6), from
    /proc/net/tcp{,6}: ``{"127.0.0.1"}``, ``{"0.0.0.0", "::"}``, ..."""
    found = set()
    for name, family in (("tcp", socket.AF_INET), ("tcp6", socket.AF_INET6)):
        try:
            lines = Path(f"/proc/net/{name}").read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            addr_hex, port_hex = fields[1].split(":")
            if fields[3] != "0A" or int(port_hex, 16) != port:  # 0A = LISTEN
                continue
            raw = bytes.fromhex(addr_hex)
            if sys.byteorder == "little":  # the kernel prints each 32-bit word in host order
                raw = b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))
            found.add(socket.inet_ntop(family, raw))
    return found


class Ser2net:
    """One ser2net process serving ``device`` as ``kind`` on 127.0.0.1; ``url`` is what
    the driver opens. ``restart()`` stops it (clients see the connection drop) and starts
    it again on the same port."""

    def __init__(self, device: str | Path, kind: str, workdir: str | Path, nodelay: bool = True,
                 chardelay: bool | None = None, exe: str | None = None):
        if kind not in KINDS:
            raise ValueError(f"kind={kind!r} must be one of {KINDS}")
        self.device, self.kind, self.nodelay, self.chardelay = str(device), kind, nodelay, chardelay
        self.workdir = Path(workdir)
        self.exe = exe or require_ser2net()
        self.port: int | None = None
        self.proc: subprocess.Popen | None = None
        tag = f"{kind}{'' if nodelay else '-nagle'}{'' if chardelay is None else f'-chardelay-{chardelay}'}"
        self.config = self.workdir / f"ser2net-{tag}.yaml"
        self.log = self.workdir / f"ser2net-{tag}.log"

    @property
    def url(self) -> str:
        if self.port is None:
            raise RuntimeError("ser2net has not been started")
        return url_for(self.kind, self.port)

    def output(self) -> str:
        try:
            return self.log.read_text(errors="replace")
        except OSError:
            return ""

    def start(self, timeout_s: float = START_TIMEOUT_S) -> "Ser2net":
        """Start ser2net and return once its port listens. A port taken in the meantime
        is replaced by another (at most PORT_ATTEMPTS); anything else fails the test with
        ser2net's own output."""
        ports = [self.port] if self.port is not None else [free_port() for _ in range(PORT_ATTEMPTS)]
        last, port = "", ports[0]
        for port in ports:
            self.config.write_text(ser2net_yaml(self.device, self.kind, port, nodelay=self.nodelay,
                                                chardelay=self.chardelay))
            with open(self.log, "ab") as log:
                # -n: stay in the foreground; -d: and log to stdout; -u: no UUCP lock file in
                # /var/lock (a killed ser2net would leave one behind)
                self.proc = subprocess.Popen([self.exe, "-n", "-d", "-u", "-c", str(self.config)],
                                             stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                             preexec_fn=_die_with_parent)
            deadline = time.monotonic() + timeout_s
            for _ in range(int(timeout_s / POLL_S) + 1):
                if HOST in listening_addresses(port):
                    self.port = port
                    return self
                if self.proc.poll() is not None or "Unable to startup network port" in self.output():
                    break
                if time.monotonic() >= deadline:
                    break
                time.sleep(POLL_S)
            last = self.output()
            self._kill()
            if "Address already in use" not in last:
                break
        pytest.fail(f"ser2net ({self.config}) did not listen on {HOST}:{port} within {timeout_s} s; "
                    f"its output:\n{last}", pytrace=False)

    def _kill(self) -> None:
        proc, self.proc = self.proc, None
        if proc is None or proc.poll() is not None:
            return
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:  # a ser2net whose accepter failed ignores SIGTERM
            proc.kill()
            proc.wait(STOP_TIMEOUT_S)

    def stop(self) -> None:
        """Stop ser2net (SIGTERM, then SIGKILL after STOP_TIMEOUT_S) and wait until its
        port no longer listens. Safe to call more than once."""
        self._kill()
        if self.port is not None:
            deadline = time.monotonic() + STOP_TIMEOUT_S
            while HOST in listening_addresses(self.port) and time.monotonic() < deadline:
                time.sleep(POLL_S)

    def restart(self) -> None:
        self.stop()
        self.start()

    def __enter__(self) -> "Ser2net":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


@contextmanager
def ser2net_for(link_path: str | Path, kind: str, nodelay: bool = True, chardelay: bool | None = None,
                workdir: str | Path | None = None) -> Iterator[Ser2net]:
    """ser2net serving the device at ``link_path`` as ``kind`` ("raw" or "rfc2217"); yields
    the running :class:`Ser2net` (``.url`` for the driver, ``.restart()``). The YAML and
    ser2net's log go to ``workdir`` (default: a temporary directory removed on exit)."""
    exe = require_ser2net()
    with tempfile.TemporaryDirectory(prefix="qradar-ser2net-") as tmp:
        s2n = Ser2net(link_path, kind, workdir or tmp, nodelay=nodelay, chardelay=chardelay, exe=exe)
        with s2n:
            yield s2n
