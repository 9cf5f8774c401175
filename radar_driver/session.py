"""The K-MD2 driver session: owns the serial port, speaks the protocol through the
codec, and assembles RADCs into frames.

Any pyserial URL works (``/dev/ttyUSB0``, a pty path, ``socket://host:port``,
``rfc2217://host:port``), always 8E1. The URL's kind says whether the link can change
the line speed (:func:`link_kind`): a device path and ``rfc2217://`` can, so ``INIT``
goes out at the profile's start-up speed (115200) and, after its ``RESP``, the host
waits :data:`~.protocol.BAUD_SWITCH_SETTLE_S` and switches to the requested rate; a
``socket://`` link (Ethernet, raw ser2net) cannot, so the session stays at the
start-up speed and says so. ``rfc2217://`` gets pyserial's ``ign_set_control``, which
a ser2net or pty port needs.

A dedicated reader thread owns the port once the session is open. It keeps one
``GNFD`` outstanding: the next goes out as soon as a ``DONE`` arrives, before the frame
is assembled and handed on, so nothing the consumer does (or the GIL it holds) sits
between one answer and the next request. Each ``GNFD`` is answered by ``RESP``, the
selected ``RADC`` and ``DONE``. In the default profile a ``RADC`` is one ramp and
``ramps_per_frame`` consecutive ones (by the ``DONE`` counter) make a frame of
M = ramps x 256; in a profile of many chirps per ``RADC`` one ``RADC`` makes a frame
of ``ramps_per_frame`` of its chirps (``chirp_select``). A counter gap counts the
sensor frames lost (``dropped``) and discards the partial frame. Frames wait in a
bounded queue; when the consumer falls that far behind the reader stops asking, and
the sensor's counter counts what is lost.

Errors are typed (:class:`SensorTimeout`, :class:`SensorResponseError`,
:class:`LinkError`) and their messages say what to check (permission: the ``dialout``
group; silence: the line speed or the device; an echo: not a K-MD2). With
``reconnect`` the reader reconnects with backoff and re-INITs on any of them, logging
one warning per attempt with the time since the last frame. ``GBYE`` on close and
before giving up a link, so that the next session finds the sensor at its start-up
speed; close is idempotent.

Timestamps: K-MD2 frames carry no clock, so a frame's ``timestamp_ns`` is the host's
``time.time_ns()`` when the ``DONE`` of its first RADC arrived.
"""

from __future__ import annotations

import errno
import logging
import os
import queue
import termios
import threading
import time
from collections import deque
from dataclasses import asdict, dataclass
from enum import Enum
from typing import Callable, Iterator

import numpy as np
import serial

from .devices import cmdline, device_identity, lock_holders, port_holders
from .errors import ConfigError, LinkError, RadarError, SensorError, SensorResponseError, SensorTimeout
from .limits import check_sensor_id
from .model import RadarConfig
from .profile import CHIRP_SELECT, SensorProfile, resolve_profile
from .protocol import (
    BAUD_SWITCH_SETTLE_S,
    Done,
    Gbye,
    Gnfd,
    Init,
    Radc,
    Resp,
    RespCode,
    StreamDecoder,
    encode,
)
from .source import RawFrame

log = logging.getLogger("qradar.driver")

#: the rate after INIT on a link that can change speed, unless told otherwise
DEFAULT_FAST_BAUD = 2_000_000


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


@dataclass
class DriverCounters:
    """What a session has seen. ``dropped``: sensor frames lost (the DONE counter's gaps
    and the partial frames they broke, in frames); ``dropped_radcs``: the gaps in RADCs
    (ramps in the default profile); ``incomplete``: RADCs that never arrived whole;
    ``discarded_ramps``: RADCs thrown away with a partial frame; ``timeouts``: GNFDs sent
    again after ``timeout_s`` of silence; ``repeated``: answers with the last counter
    again (not a new measurement: skipped); ``wrong_device``: reconnect attempts refused
    because the port's path now names another device than the one first opened."""

    frames: int = 0
    ramps: int = 0
    bytes: int = 0
    resyncs: int = 0
    skipped_bytes: int = 0
    dropped: int = 0
    dropped_radcs: int = 0
    reconnects: int = 0
    incomplete: int = 0
    discarded_ramps: int = 0
    timeouts: int = 0
    resp_errors: int = 0
    repeated: int = 0
    wrong_device: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


@dataclass(frozen=True)
class SessionConfig:
    """url: any pyserial URL. baud: rate after INIT (one of the profile's baud codes);
    None = 2 000 000 on a link that can change speed, the start-up speed on one that
    cannot (socket://); a socket:// link always stays at the start-up speed.
    timeout_s: wait for a GNFD answer before one retry (then SensorTimeout). reconnect:
    reconnect on errors with backoff from ``backoff_s`` to ``max_backoff_s``; give up
    after ``reconnect_timeout_s`` (None = never). sensor_id: the id its frames carry
    (the sensor's chunk of the zenoh keys). profile: a SensorProfile, a packaged
    profile's name or a TOML path (None = the default, kmd2-blocks). chirp_select:
    with several chirps per RADC, a frame takes the first ``ramps_per_frame`` of them or
    every (chirps // ramps_per_frame)-th. queue_frames: frames the reader may hold for
    a slow consumer before it stops asking the sensor. outstanding: GNFDs kept in flight;
    1 (the next goes out when a DONE arrives) or 2 (the sensor then holds a request
    while the host is late by up to a measurement period; that a real K-MD2 queues a
    second GNFD is an assumption)."""

    url: str
    baud: int | None = None
    ramps_per_frame: int = 2
    timeout_s: float = 0.5
    reconnect: bool = True
    backoff_s: float = 0.05
    max_backoff_s: float = 2.0
    reconnect_timeout_s: float | None = None
    sensor_id: str = "kmd2"
    profile: SensorProfile | str | None = None
    chirp_select: str = "first"
    queue_frames: int = 256
    outstanding: int = 1

    def __post_init__(self) -> None:
        if not isinstance(self.url, str) or not self.url:
            raise ConfigError(f"url={self.url!r} must be a non-empty string")
        check_sensor_id(self.sensor_id)  # a ConfigError naming the rule (radar_driver.limits)
        object.__setattr__(self, "profile", resolve_profile(self.profile))
        if self.baud is not None:
            self.profile.baud_code(self.baud)  # ConfigError naming the profile's speeds
        if not (isinstance(self.ramps_per_frame, int) and self.ramps_per_frame >= 1):
            raise ConfigError(f"ramps_per_frame={self.ramps_per_frame!r} must be an integer >= 1")
        for name in ("timeout_s", "backoff_s", "max_backoff_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be > 0")
        if self.chirp_select not in CHIRP_SELECT:
            raise ConfigError(f"chirp_select={self.chirp_select!r} must be one of {list(CHIRP_SELECT)}")
        if self.profile.radc.chirps > 1:
            self.profile.radc.chirp_indices(self.ramps_per_frame, self.chirp_select)  # fits?
        if not (isinstance(self.queue_frames, int) and self.queue_frames >= 1):
            raise ConfigError(f"queue_frames={self.queue_frames!r} must be an integer >= 1")
        if self.outstanding not in (1, 2):
            raise ConfigError(f"outstanding={self.outstanding!r} must be 1 or 2")

    @property
    def kind(self) -> LinkKind:
        return link_kind(self.url)

    @property
    def line_baud(self) -> int:
        """The line speed after INIT: the start-up speed on a link that cannot change it."""
        if not self.kind.can_change_speed:
            return self.profile.startup_baud
        return DEFAULT_FAST_BAUD if self.baud is None else self.baud

    @property
    def baud_code(self) -> int:
        return self.profile.baud_code(self.line_baud)

    @property
    def radcs_per_frame(self) -> int:
        return self.ramps_per_frame if self.profile.radc.chirps == 1 else 1

    def radar(self) -> RadarConfig:
        return RadarConfig(samples_per_ramp=self.profile.radc.samples, ramps_per_frame=self.ramps_per_frame)


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


def open_error(url: str, exc: BaseException) -> str:
    """One line for a port that would not open, with what to check."""
    code = getattr(exc, "errno", None)
    if code is None and exc.args and isinstance(exc.args[0], int):
        code = exc.args[0]
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


class SensorSession:
    """``with SensorSession(SessionConfig(url)) as s: for frame in s.frames(): ...``

    A :class:`~radar_driver.source.FrameSource`: a K-MD2 (real or simulated) on a
    serial link. :meth:`open` connects in the caller (and raises on failure); the
    reader thread then owns the port until :meth:`close`."""

    READ_TIMEOUT_S = 0.02  # port read granularity; bounds how late a deadline is noticed
    MAX_INCOMPLETE_IN_A_ROW = 8
    DRAIN_S = 0.3  # at stop, how long the reader waits for the answer to its outstanding GNFD

    def __init__(self, config: SessionConfig, port_factory: Callable[..., serial.SerialBase] = serial.serial_for_url):
        self.config = config
        self.profile: SensorProfile = config.profile
        self.counters = DriverCounters()
        self._port_factory = port_factory
        self._port: serial.SerialBase | None = None
        self._decoder = StreamDecoder(self.profile)
        self._inbox: deque = deque()
        self._first_bytes = bytearray()  # what arrived first after connecting (for error messages)
        self._pending_radc: Radc | None = None
        self._last_counter: int | None = None
        self._radcs: list[tuple[int, int, np.ndarray]] = []  # (counter, t_ns, words) of a partial frame
        self._lost_radcs = 0  # lost RADCs not yet a whole frame in ``dropped``
        self._seq = 0
        self._closed = False
        self._ever_connected = False
        self._device: tuple | None = None  # device_identity of the first open (device paths)
        self._config_id = config.radar().config_id()
        self._chirps = (self.profile.radc.chirp_indices(config.ramps_per_frame, config.chirp_select)
                        if self.profile.radc.chirps > 1 else None)
        # the reader thread and what it shares with the consumer
        self._queue: queue.Queue = queue.Queue()
        self._reader: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._produced = 0  # frames the reader queued
        self._target: int | None = 0  # frames the consumer asked for in all (None = no end)
        self._in_flight = 0  # GNFDs sent and not yet answered by a DONE
        self._deadline = 0.0  # when the next answer is late (monotonic s)
        self._retries = 0  # timeouts since the last DONE
        self._incomplete_in_a_row = 0
        self._last_frame_mono: float | None = None

    # -- life cycle -----------------------------------------------------------------------
    def __enter__(self) -> "SensorSession":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def is_open(self) -> bool:
        return self._port is not None

    def open(self) -> None:
        """Open the port and INIT the sensor (in the caller; raises a SensorError on
        failure), then start the reader thread."""
        self._closed = False
        self._stop.clear()
        if self._port is None:
            self._connect()
        self._start_reader()

    def probe(self) -> None:
        """Open the port as :meth:`open` would (a device path exclusively) and close it at
        once, sending nothing: a LinkError saying why it cannot be opened (and who holds a
        busy device), for a caller that checks its ports before it starts anything. Not on
        an open session."""
        if self._port is not None:
            raise LinkError(f"{self.config.url} is open in this session already")
        try:
            port = self._open_port(port_url(self.config.url))
        except (serial.SerialException, OSError, ValueError, termios.error) as exc:
            raise LinkError(open_error(self.config.url, exc)) from exc
        try:
            port.close()
        except (serial.SerialException, OSError):
            pass

    def request_stop(self) -> None:
        """Ask :meth:`frames` to end, without touching the port (safe from another
        thread); the owner then closes. The reader stops asking at once; the frames it
        already assembled, and one that the answers to its outstanding GNFDs complete
        (within DRAIN_S), still come out of :meth:`frames` before its end, so that
        ``frames`` counts only frames handed on."""
        self._closed = True
        self._stop.set()

    def close(self) -> None:
        """Stop the reader, GBYE (best effort) and close the port. Safe to call any
        number of times, from the thread that uses the session."""
        self.request_stop()
        reader, self._reader = self._reader, None
        if reader is not None and reader is not threading.current_thread():
            reader.join(self.DRAIN_S + 5 * self.READ_TIMEOUT_S + 2.0)
        self._goodbye()

    def _goodbye(self) -> None:
        """GBYE and close the port, so that the sensor goes back to its start-up speed."""
        if self._port is None:
            return
        try:
            self._command(Gbye(), "GBYE", timeout_s=0.3)
        except SensorError as exc:
            log.debug("GBYE to %s failed: %s", self.config.url, exc)
        finally:
            self._drop_port()

    def _connect(self) -> None:
        cfg = self.config
        url = port_url(cfg.url)
        ident = device_identity(cfg.url) if cfg.kind is LinkKind.DEVICE else None
        if self._device is not None and ident is not None and ident != self._device:
            self.counters.wrong_device += 1
            raise LinkError(f"{cfg.url} now names another device {describe_device(ident)} than the "
                            f"{describe_device(self._device)} first opened: not reconnecting to it")
        try:
            port = self._open_port(url)
        except (serial.SerialException, OSError, ValueError, termios.error) as exc:
            raise LinkError(open_error(cfg.url, exc)) from exc
        if self._device is None:
            self._device = ident
        self._port = port
        self._decoder.reset()
        self._inbox.clear()
        self._first_bytes.clear()
        self._pending_radc = None
        self._in_flight = 0
        self._retries = 0
        self._reset_assembly()
        if cfg.baud is not None and cfg.baud != cfg.line_baud and not self._ever_connected:
            log.warning("%s is a %s link, which cannot change the line speed: baud %d ignored, staying at %d",
                        cfg.url, cfg.kind.value, cfg.baud, cfg.line_baud)
        try:
            port.reset_input_buffer()
            try:
                self._command(Init(cfg.baud_code), "INIT", timeout_s=cfg.timeout_s)
            except SensorTimeout:
                if not cfg.kind.can_change_speed:
                    raise
                # the sensor may still run at a rate a previous session left it at
                self._release_stuck_sensor()
                self._command(Init(cfg.baud_code), "INIT", timeout_s=cfg.timeout_s)
            if cfg.kind.can_change_speed and cfg.line_baud != self.profile.startup_baud:
                time.sleep(BAUD_SWITCH_SETTLE_S)
                port.baudrate = cfg.line_baud
        except (serial.SerialException, OSError, termios.error) as exc:
            self._drop_port()
            raise LinkError(f"{cfg.url} failed during INIT: {getattr(exc, 'strerror', None) or exc}") from exc
        except SensorError as exc:
            self._drop_port()
            text = self._peer_text()  # e.g. ser2net's "Device open failure: ..." before it hangs up
            said = f", saying {text!r}" if text else ""
            if isinstance(exc, LinkError):
                raise LinkError(f"{exc}: the other end hung up during the set-up{said} (ser2net could not open "
                                f"its device? see its log, the device path in its YAML, its user's dialout "
                                f"group)") from exc
            if text:
                raise type(exc)(f"{exc}; the other end said {text!r}: not a K-MD2") from exc
            raise
        except BaseException:
            self._drop_port()
            raise
        if self._ever_connected:
            self.counters.reconnects += 1
        self._ever_connected = True
        if cfg.kind.can_change_speed:
            log.info("connected to %s at %d baud (profile %s)", cfg.url, cfg.line_baud, self.profile.name)
        else:
            log.info("connected to %s (%s link: the line speed stays at %d baud; profile %s)", cfg.url,
                     cfg.kind.value, cfg.line_baud, self.profile.name)

    def _open_port(self, url: str) -> serial.SerialBase:
        """The port at the start-up speed, 8E1. A Linux pty has no parity and refuses
        (EINVAL) terminal settings that change nothing else, e.g. a second session at the
        speed the first left: then it opens at another speed and switches."""
        kw = dict(bytesize=serial.EIGHTBITS, parity=serial.PARITY_EVEN, stopbits=serial.STOPBITS_ONE,
                  timeout=self.READ_TIMEOUT_S)
        if self.config.kind is LinkKind.DEVICE:
            kw["exclusive"] = True  # flock: a second opener is refused (open_error names the holder)
        start = self.profile.startup_baud
        try:
            return self._port_factory(url, baudrate=start, **kw)
        except termios.error as exc:
            if not exc.args or exc.args[0] != errno.EINVAL:
                raise
        other = next(b for b in sorted(self.profile.baud_codes.values()) if b != start)
        port = self._port_factory(url, baudrate=other, **kw)
        try:
            port.baudrate = start
        except BaseException:
            port.close()
            raise
        return port

    def _peer_text(self) -> str:
        """The first bytes received since connecting, if they read as a line of text."""
        raw = bytes(self._first_bytes).strip(b"\r\n\x00 ")
        if len(raw) < 4 or sum(32 <= b < 127 or b in (9, 10, 13) for b in raw) < 0.9 * len(raw):
            return ""
        return " ".join(raw.decode("ascii", "replace").split())[:120]

    def _release_stuck_sensor(self) -> None:
        port = self._port
        start = self.profile.startup_baud
        for baud in sorted(set(self.profile.baud_codes.values()) - {start}):
            port.baudrate = baud
            port.write(encode(Gbye()))
            port.flush()
            time.sleep(0.02)
        port.baudrate = start
        time.sleep(BAUD_SWITCH_SETTLE_S)
        port.reset_input_buffer()
        self._decoder.reset()
        self._inbox.clear()

    def _drop_port(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass

    # -- I/O ----------------------------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        try:
            self._port.write(data)
        except (serial.SerialException, OSError, AttributeError) as exc:
            raise LinkError(f"write to {self.config.url} failed: {getattr(exc, 'strerror', None) or exc}") from exc

    def _fill_inbox(self) -> None:
        """One read of the port (blocks at most READ_TIMEOUT_S) into the inbox."""
        port = self._port
        if port is None:
            raise LinkError(f"{self.config.url} is not open")
        try:
            waiting = port.in_waiting
            data = port.read(max(self._decoder.wanted(), waiting))
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            # pyserial raises TypeError/AttributeError when the port is closed under it
            raise LinkError(f"read from {self.config.url} failed: {getattr(exc, 'strerror', None) or exc}") from exc
        if not data:
            return
        if len(self._first_bytes) < 256:
            self._first_bytes += data[: 256 - len(self._first_bytes)]
        st = self._decoder.stats
        before = (st.resyncs, st.skipped_bytes)
        self._inbox.extend(self._decoder.feed(data))
        self.counters.bytes += len(data)
        self.counters.resyncs += st.resyncs - before[0]
        self.counters.skipped_bytes += st.skipped_bytes - before[1]

    def _next_message(self, deadline: float):
        """The next decoded message, or None once ``deadline`` (monotonic s) has passed."""
        while not self._inbox:
            if time.monotonic() >= deadline:
                return None
            self._fill_inbox()
        return self._inbox.popleft()

    def _command(self, msg, name: str, timeout_s: float) -> None:
        """Send a command and wait for its RESP (OK, or SensorResponseError). Only while
        the reader thread is not running (connect, close)."""
        self._inbox.clear()
        self._write(encode(msg))
        deadline = time.monotonic() + timeout_s
        seen: list[str] = []
        while (m := self._next_message(deadline)) is not None:
            if isinstance(m, Resp):
                if m.code != RespCode.OK:
                    self.counters.resp_errors += 1
                    raise SensorResponseError(name, m.code)
                return
            seen.append(type(m).__name__)
        self.counters.timeouts += 1
        raise SensorTimeout(self._silence(name, timeout_s, seen, type(msg)))

    def _silence(self, name: str, timeout_s: float, seen: list[str], sent: type) -> str:
        """One line for a command left without an answer, with the likely cause."""
        url, start = self.config.url, self.profile.startup_baud
        if sent.__name__ in seen:
            return (f"no RESP to {name} from {url} within {timeout_s:.2f} s, but our own {name} came back: "
                    f"the link echoes (a loopback, a modem or a console), not a K-MD2")
        if seen:
            kinds = ", ".join(sorted(set(seen)))
            return f"no RESP to {name} from {url} within {timeout_s:.2f} s; saw {kinds} instead"
        skipped = self._decoder.stats.skipped_bytes
        what = f"saw {skipped} bytes that were no message" if skipped else "saw no message"
        if name == "INIT":
            return (f"no RESP to INIT from {url} within {timeout_s:.2f} s; {what} (check that it is a K-MD2, "
                    f"powered, and that the line runs at {start} baud 8E1: a ser2net port must be set to "
                    f"{start}e81; bytes that are no message mean a baud mismatch)")
        return f"no RESP to {name} from {url} within {timeout_s:.2f} s; {what}"

    # -- the reader thread -----------------------------------------------------------------------
    def _start_reader(self) -> None:
        if self._reader is not None and self._reader.is_alive():
            return
        self._stop.clear()
        old, self._queue = self._queue, queue.Queue()
        while True:  # keep the frames a previous reader left, not its end or its error
            try:
                item = old.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, RawFrame):
                self._queue.put(item)
        self._reader = threading.Thread(target=self._read_loop, name=f"kmd2-reader-{self.config.sensor_id}",
                                        daemon=True)
        self._reader.start()

    def _may_poll(self) -> bool:
        """May the reader ask for another RADC? Not at a stop, not beyond the frames asked
        for, not beyond the queue's bound (counting the RADCs in hand and in flight)."""
        if self._stop.is_set():
            return False
        coming = (len(self._radcs) + self._in_flight) // self.config.radcs_per_frame
        if self._target is not None and self._produced + coming >= self._target:
            return False
        return self._queue.qsize() + coming < self.config.queue_frames

    def _top_up(self) -> None:
        """Keep ``outstanding`` GNFDs in flight (fewer when fewer frames are wanted)."""
        while self._in_flight < self.config.outstanding and self._may_poll():
            self._write(encode(Gnfd(self.profile.gnfd_bits["RADC"])))
            if self._in_flight == 0:
                self._deadline = time.monotonic() + self.config.timeout_s
            self._in_flight += 1

    def _read_loop(self) -> None:
        """The reader thread: poll, read, assemble, queue; reconnect on errors. At a stop
        it waits up to DRAIN_S for the answers to its outstanding GNFDs, so that the GBYE
        of close() finds a quiet line."""
        cfg = self.config
        drain_until = None
        try:
            while True:
                if self._stop.is_set():
                    now = time.monotonic()
                    drain_until = drain_until or now + self.DRAIN_S
                    if not self._in_flight or self._port is None or now > drain_until:
                        return
                if self._port is None and not self._reconnect():  # LinkError once reconnect_timeout_s is spent
                    return
                try:
                    self._step()
                except SensorError as exc:
                    self._in_flight = 0
                    if not cfg.reconnect or self._stop.is_set():
                        self._goodbye()
                        raise
                    log.warning("%s; reconnecting", exc)
                    self._goodbye()
        except BaseException as exc:  # handed to the consumer, never silent
            self._queue.put(exc)
        finally:
            self._queue.put(None)  # the end of the stream

    def _step(self) -> None:
        """One read of the port and what it completes."""
        self._top_up()
        self._fill_inbox()
        while self._inbox:
            self._handle(self._inbox.popleft())
        if self._in_flight and time.monotonic() >= self._deadline:
            self.counters.timeouts += 1
            self._retries += 1
            if self._retries >= 2 or self._stop.is_set():
                raise SensorTimeout(f"no complete RADC from {self.config.url} after 2 GNFD polls of "
                                    f"{self.config.timeout_s:.2f} s; {self._decoder.stats.skipped_bytes} bytes "
                                    f"skipped in all")
            self._in_flight = 0  # the answers are lost: ask once more
            self._top_up()

    def _handle(self, m) -> None:
        if isinstance(m, Radc):
            if self._pending_radc is not None:
                self.counters.incomplete += 1
            self._pending_radc = m
        elif isinstance(m, Done):
            self._in_flight = max(0, self._in_flight - 1)
            self._retries = 0
            self._deadline = time.monotonic() + self.config.timeout_s
            radc, self._pending_radc = self._pending_radc, None
            if m.frame_counter == self._last_counter:  # the same RADC again (a sensor that answers
                self.counters.repeated += 1           # a queued GNFD at once): not a new measurement
                self._top_up()
                return
            self._note_counter(m.frame_counter)
            t_ns = time.time_ns()
            if radc is None:
                self.counters.incomplete += 1
                self._reset_assembly()
                self._incomplete_in_a_row += 1
                if self._incomplete_in_a_row >= self.MAX_INCOMPLETE_IN_A_ROW:
                    self._incomplete_in_a_row = 0
                    raise SensorTimeout(f"{self.MAX_INCOMPLETE_IN_A_ROW} GNFD answers in a row from "
                                        f"{self.config.url} lacked a whole RADC")
                self._top_up()
                return
            self._incomplete_in_a_row = 0
            self.counters.ramps += 1
            self._radcs.append((m.frame_counter, t_ns, radc.words))
            self._top_up()  # the next request first, then the frame
            if len(self._radcs) >= self.config.radcs_per_frame:
                self._queue_frame()
        elif isinstance(m, Resp) and m.code != RespCode.OK:
            self.counters.resp_errors += 1
            self._in_flight = 0
            raise SensorResponseError("GNFD", m.code)

    def _queue_frame(self) -> None:
        radcs, self._radcs = self._radcs, []
        lay, cfg = self.profile.radc, self.config
        az = list(lay.azimuth)
        if self._chirps is None:  # one chirp per RADC: R RADCs
            words = np.stack([w[az, 0] for _, _, w in radcs])  # (R, 2, N, 2)
            data = lay.to_complex(words[:, :, None])[:, 0]  # (R, N, 2)
        else:  # R of one RADC's chirps
            data = lay.to_complex(radcs[0][2][az][:, self._chirps])  # (R, N, 2)
        frame = RawFrame(
            sensor_id=cfg.sensor_id,
            seq=self._seq,
            timestamp_ns=radcs[0][1],
            data=data.reshape(cfg.ramps_per_frame * lay.samples, 2).astype(np.complex64),
            counters=tuple(c for c, _, _ in radcs),
            config_id=self._config_id,
        )
        self._seq += 1
        self.counters.frames += 1
        self._last_frame_mono = time.monotonic()
        with self._lock:  # _produced and the queue change together: frames() reads both
            self._produced += 1
            self._queue.put(frame)

    def _note_counter(self, counter: int) -> None:
        last = self._last_counter
        if last is not None:
            gap = (counter - last - 1) & 0xFFFFFFFF
            if 0 < gap < 0x80000000:
                self.counters.dropped_radcs += gap
                self._lost_radcs += gap
                self._reset_assembly()
        self._last_counter = counter

    def _reset_assembly(self) -> None:
        n = len(self._radcs)
        self.counters.discarded_ramps += n
        self._lost_radcs += n
        self._radcs = []
        per = self.config.radcs_per_frame
        whole, self._lost_radcs = divmod(self._lost_radcs, per)
        self.counters.dropped += whole

    def _reconnect(self) -> bool:
        """Connect again with backoff; one warning per attempt with the time since the
        last frame. True once connected, False at a stop; LinkError once
        reconnect_timeout_s is spent."""
        cfg = self.config
        delay = cfg.backoff_s
        start = time.monotonic()
        attempt = 0
        while True:
            if self._stop.is_set():
                return False
            attempt += 1
            try:
                self._connect()
                if attempt > 1:
                    log.warning("%s: reconnected after %d attempts", cfg.url, attempt)
                return True
            except SensorError as exc:
                if cfg.reconnect_timeout_s is not None and time.monotonic() - start > cfg.reconnect_timeout_s:
                    raise LinkError(f"could not reconnect to {cfg.url} within {cfg.reconnect_timeout_s} s: {exc}") from exc
                since = ("no frame yet" if self._last_frame_mono is None
                         else f"{time.monotonic() - self._last_frame_mono:.1f} s since the last frame")
                log.warning("%s is down (%s); reconnect attempt %d, %s; next in %.2f s", cfg.url, exc, attempt,
                            since, delay)
                if self._stop.wait(delay):
                    return False
                delay = min(delay * 2, cfg.max_backoff_s)

    # -- the consumer side ------------------------------------------------------------------------
    def frames(self, limit: int | None = None) -> Iterator[RawFrame]:
        """Frames until ``limit`` (None = forever) or :meth:`request_stop` (then the frames
        the reader still had). The reader asks the sensor for exactly the frames wanted. With ``reconnect``, errors lead to
        a reconnect with backoff (counted) instead of ending the stream; without it (or
        once ``reconnect_timeout_s`` is spent) the error is raised here."""
        n = 0
        if self._closed:
            return
        self._start_reader()
        while limit is None or n < limit:
            with self._lock:
                self._target = None if limit is None else self._produced + max(0, limit - n - self._queue.qsize())
            item = self._get()
            if item is None:
                return
            if isinstance(item, BaseException):
                if self._stop.is_set():  # an error of the drain after a stop (counted): the end
                    log.debug("%s: after the stop: %s", self.config.url, item)
                    return
                raise item
            yield item
            n += 1

    def _get(self):
        """The next item of the reader's queue, or None at the stream's end (after a stop:
        once the reader has queued what it had and ended)."""
        while True:
            try:
                item = self._queue.get(timeout=0.05)
            except queue.Empty:
                if self._reader is None or not self._reader.is_alive():
                    try:
                        return self._queue.get_nowait()
                    except queue.Empty:
                        return None
                continue
            return item

    def __iter__(self) -> Iterator[RawFrame]:
        return self.frames()

    def stats(self) -> dict[str, dict[str, int]]:
        """The driver counters of this sensor, keyed by its id."""
        return {self.config.sensor_id: self.counters.as_dict()}


def save_frames_npz(path, frames: list[RawFrame], config: SessionConfig) -> None:
    """Save frames to an ``.npz``: frames (F, M, 2) complex64, seq (F,), timestamp_ns (F,),
    counters (F, ramps_per_frame) and the radar configuration as JSON."""
    import json

    radar = config.radar()
    try:
        np.savez_compressed(
            path,
            frames=np.stack([f.data for f in frames]) if frames else np.zeros((0, radar.n_measurements, 2), np.complex64),
            seq=np.array([f.seq for f in frames], dtype=np.int64),
            timestamp_ns=np.array([f.timestamp_ns for f in frames], dtype=np.int64),
            counters=np.array([f.counters for f in frames], dtype=np.int64).reshape(len(frames), config.ramps_per_frame),
            radar_config=json.dumps(radar.to_dict()),
        )
    except OSError as exc:
        raise RadarError(f"cannot write frames to {path}: {exc.strerror or exc}") from None
