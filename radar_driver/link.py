"""The serial link to a sensor: a pyserial URL opened by its kind, 8E1, with errors
that say what to check.

Any pyserial URL works (``/dev/ttyUSB0``, a pty path, ``socket://host:port``,
``rfc2217://host:port``). The URL's kind says whether the link can change the line
speed (:func:`link_kind`): a device path and ``rfc2217://`` can; a ``socket://`` link
(Ethernet, raw ser2net) cannot. ``rfc2217://`` gets pyserial's ``ign_set_control``,
which a ser2net or pty port needs. A device path is opened exclusively (flock), and a
second opener is told who holds it. :class:`SerialLink` knows bytes only; the
protocol spoken over it lives elsewhere.
"""

from __future__ import annotations

import errno
import os
import termios
from enum import Enum
from typing import Callable

import serial

from .devices import cmdline, device_identity, lock_holders, port_holders
from .errors import LinkError, PortBusy, PortDenied, WrongDevice


class LinkKind(str, Enum):
    """What a pyserial URL reaches, and whether the host can change its line speed."""

    DEVICE = "device"  # a local serial device or pty: yes
    RFC2217 = "rfc2217"  # a remote serial port over RFC 2217 (ser2net telnet(rfc2217)): yes
    SOCKET = "socket"  # raw TCP (the K-MD2's Ethernet port, a raw ser2net port): no
    OTHER = "other"  # loop://, spy://..., hwgrep://: as pyserial makes it

    @property
    def can_change_speed(self) -> bool:
        return self in (LinkKind.DEVICE, LinkKind.RFC2217, LinkKind.OTHER)


def link_kind(url: str) -> LinkKind:
    """The kind of a pyserial URL (``spy://`` is the kind of the URL it wraps)."""
    scheme, sep, rest = url.partition("://")
    if not sep:
        return LinkKind.DEVICE
    scheme = scheme.lower()
    if scheme == "spy":
        return link_kind(rest.split("?", 1)[0])
    return {"socket": LinkKind.SOCKET, "rfc2217": LinkKind.RFC2217}.get(scheme, LinkKind.OTHER)


def port_url(url: str) -> str:
    """The URL to open: ``rfc2217://`` gains ``ign_set_control`` (ser2net and ptys do
    not answer pyserial's control-line negotiation)."""
    if link_kind(url) is LinkKind.RFC2217 and url.lower().startswith("rfc2217://") and "ign_set_control" not in url:
        return url + ("&" if "?" in url else "?") + "ign_set_control"
    return url


def describe_device(ident: tuple) -> str:
    """``device_identity`` in words."""
    if ident[0] == "pty":
        return f"(a pty served by process {ident[1]})" if ident[1] else "(a pty whose other end is unknown)"
    return f"({', '.join(str(x) for x in ident[1:])})"


def busy_text(url: str) -> str:
    """Who holds ``url``: "process 1234 (python -m qradar drive ...)", or why unknown."""
    me = os.getpid()
    lockers = lock_holders(url)
    found = [(pid, cmdline(pid)) for pid in lockers] if lockers else port_holders(url)
    holders = [f"{'this process' if pid == me else 'process'} {pid} ({cmd})" for pid, cmd in found]
    return ", ".join(holders) if holders else "a process this user cannot see (`fuser -v` as root names it)"


def error_code(exc: BaseException) -> int | None:
    """The errno of an exception pyserial raised (it puts it first in ``args`` at times)."""
    code = getattr(exc, "errno", None)
    if code is None and exc.args and isinstance(exc.args[0], int):
        code = exc.args[0]
    return code


def is_busy(exc: BaseException) -> bool:
    """Whether an open failed because another program holds the port: its exclusive lock
    (pyserial's ``exclusive``: flock), or a device that says busy."""
    code = error_code(exc)
    return code in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EBUSY) or "exclusively lock" in str(exc)


def open_failure(url: str, exc: BaseException) -> LinkError:
    """The LinkError for a port that would not open: :class:`PortBusy`, :class:`PortDenied`
    or a plain LinkError, with :func:`open_error`'s line."""
    code = error_code(exc)
    kind = PortBusy if is_busy(exc) else PortDenied if code in (errno.EACCES, errno.EPERM) else LinkError
    return kind(open_error(url, exc))


def address_problem(url: str) -> str | None:
    """What is wrong with the ``HOST:PORT`` of a ``socket://`` or ``rfc2217://`` URL (pyserial
    says it in its own words: "'debug|info|warning|error'" for a port that is not a number),
    or None."""
    scheme, sep, rest = url.partition("://")
    if not sep or scheme.lower() not in ("socket", "rfc2217"):
        return None
    host, colon, port = rest.split("?", 1)[0].rstrip("/").rpartition(":")
    if colon and port.isdigit() and 0 < int(port) < 65536:
        return None
    return (f"{scheme}:// takes HOST:PORT with PORT a number in 1-65535 (e.g. {scheme}://192.168.0.50:4001), "
            f"not {rest!r}")


def open_error(url: str, exc: BaseException) -> str:
    """One line for a port that would not open, with what to check."""
    problem = address_problem(url)
    if problem is not None:
        return f"cannot open {url}: {problem}"
    code = error_code(exc)
    if isinstance(exc, ConnectionRefusedError) or code == errno.ECONNREFUSED or "refused" in str(exc).lower():
        return f"cannot connect to {url}: connection refused (is the sensor, ser2net or `qradar sim --tcp` listening there?)"
    if code == errno.ENOENT:
        return (f"cannot open {url}: no such device (is the sensor plugged in? `ls /dev/ttyUSB* /dev/ttyACM*` "
                f"lists serial adapters)")
    if code == errno.EACCES or code == errno.EPERM:
        return (f"cannot open {url}: permission denied (add yourself to the dialout group: "
                f"`sudo usermod -aG dialout $USER`, then log in again)")
    if code in (errno.EAGAIN, errno.EWOULDBLOCK) or "exclusively lock" in str(exc):
        return f"cannot open {url}: the port is in use by {busy_text(url)}; a serial port has one owner"
    if code == errno.EBUSY:
        return f"cannot open {url}: the device is busy (another program has it open: `fuser {url}`)"
    if isinstance(exc, termios.error):
        reason = exc.args[1] if len(exc.args) > 1 else exc
        return f"cannot open {url}: the port refused the terminal settings (8E1 at its speed): {reason}"
    if isinstance(exc, (TimeoutError, serial.SerialTimeoutException)) or "timed out" in str(exc).lower():
        return f"cannot open {url}: timed out (is the host reachable and the port right?)"
    if "does not seem to support rfc2217" in str(exc).lower():
        return (f"cannot open {url}: the other end did not negotiate RFC 2217 (a raw TCP port rather than "
                f"telnet(rfc2217)? or ser2net could not open its device? see its log)")
    if code == errno.EPIPE or "broken pipe" in str(exc).lower() or "reset by peer" in str(exc).lower():
        return (f"cannot open {url}: the other end hung up during the set-up (ser2net could not open its "
                f"device? see its log, the device path in its YAML, its user's dialout group)")
    reason = getattr(exc, "strerror", None) or str(exc)
    # pyserial repeats itself: "[Errno 2] could not open port X: [Errno 2] ..."; keep the last clause
    reason = reason.rsplit("] ", 1)[-1] if reason.count("[Errno") else reason
    return f"cannot open {url}: {reason}"


#: what pyserial raises when opening a port fails
OPEN_ERRORS = (serial.SerialException, OSError, ValueError, termios.error)


class SerialLink:
    """One pyserial port at a time on ``url``, 8E1, opened at ``startup_baud``.

    ``open`` raises a :class:`~.errors.LinkError` saying what to check; ``read`` and
    ``write`` raise one naming the URL. On a device path the first open records the
    device, and a later open refuses another device behind the same path
    (:class:`WrongDevice`). ``port`` is the pyserial port itself, for the speed switch."""

    READ_TIMEOUT_S = 0.02  # port read granularity; bounds how late a deadline is noticed
    FIRST_BYTES = 256  # what is kept of the first bytes after an open (for error messages)

    def __init__(self, url: str, startup_baud: int, other_baud: int,
                 port_factory: Callable[..., serial.SerialBase] = serial.serial_for_url):
        self.url = url
        self.kind = link_kind(url)
        self.startup_baud = startup_baud
        self.other_baud = other_baud  # a speed to open at when a pty refuses the start-up one
        self.port: serial.SerialBase | None = None
        self.first_bytes = bytearray()
        self._factory = port_factory
        self._device: tuple | None = None  # device_identity of the first open (device paths)

    @property
    def is_open(self) -> bool:
        return self.port is not None

    def open(self) -> None:
        """Open the port (a LinkError saying why not)."""
        ident = device_identity(self.url) if self.kind is LinkKind.DEVICE else None
        if self._device is not None and ident is not None and ident != self._device:
            raise WrongDevice(f"{self.url} now names another device {describe_device(ident)} than the "
                              f"{describe_device(self._device)} first opened: not reconnecting to it")
        self.port = self.open_port()
        if self._device is None:
            self._device = ident
        self.first_bytes.clear()

    def open_port(self) -> serial.SerialBase:
        """A new port at the start-up speed, 8E1 (a LinkError saying why not). A Linux pty
        has no parity and refuses (EINVAL) terminal settings that change nothing else,
        e.g. a second session at the speed the first left: then it opens at another
        speed and switches."""
        try:
            return self._open(port_url(self.url))
        except OPEN_ERRORS as exc:
            raise open_failure(self.url, exc) from exc

    def _open(self, url: str) -> serial.SerialBase:
        kw = dict(bytesize=serial.EIGHTBITS, parity=serial.PARITY_EVEN, stopbits=serial.STOPBITS_ONE,
                  timeout=self.READ_TIMEOUT_S)
        if self.kind is LinkKind.DEVICE:
            kw["exclusive"] = True  # flock: a second opener is refused (open_error names the holder)
        try:
            return self._factory(url, baudrate=self.startup_baud, **kw)
        except termios.error as exc:
            if not exc.args or exc.args[0] != errno.EINVAL:
                raise
        port = self._factory(url, baudrate=self.other_baud, **kw)
        try:
            port.baudrate = self.startup_baud
        except BaseException:
            port.close()
            raise
        return port

    def close(self) -> None:
        """Close the port (best effort); idempotent."""
        port, self.port = self.port, None
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass

    def write(self, data: bytes) -> None:
        try:
            self.port.write(data)
        except (serial.SerialException, OSError, AttributeError) as exc:
            raise LinkError(f"write to {self.url} failed: {getattr(exc, 'strerror', None) or exc}") from exc

    def read(self, wanted: int) -> bytes:
        """What arrived, at least ``wanted`` bytes if they come within READ_TIMEOUT_S."""
        port = self.port
        if port is None:
            raise LinkError(f"{self.url} is not open")
        try:
            waiting = port.in_waiting
            data = port.read(max(wanted, waiting))
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            # pyserial raises TypeError/AttributeError when the port is closed under it
            raise LinkError(f"read from {self.url} failed: {getattr(exc, 'strerror', None) or exc}") from exc
        if data and len(self.first_bytes) < self.FIRST_BYTES:
            self.first_bytes += data[: self.FIRST_BYTES - len(self.first_bytes)]
        return data

    def peer_text(self) -> str:
        """The first bytes received since the open, if they read as a line of text."""
        raw = bytes(self.first_bytes).strip(b"\r\n\x00 ")
        if len(raw) < 4 or sum(32 <= b < 127 or b in (9, 10, 13) for b in raw) < 0.9 * len(raw):
            return ""
        return " ".join(raw.decode("ascii", "replace").split())[:120]
