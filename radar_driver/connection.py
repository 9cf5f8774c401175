"""The command exchange with a K-MD2 over a :class:`~.link.SerialLink`: ``INIT`` (and the
line-speed switch after it), ``GBYE``, and the inbox of decoded messages.

``INIT`` goes out at the profile's start-up speed (115200); on a link that can change
speed the host waits :data:`~.protocol.BAUD_SWITCH_SETTLE_S` after its ``RESP`` and
switches to the requested rate; a ``socket://`` link cannot, so the connection stays
at the start-up speed and says so. A sensor left at another speed by a host that died
without ``GBYE`` is sent ``GBYE`` at each other speed before a second ``INIT``. A
command left unanswered raises a :class:`~.errors.SensorTimeout` saying what was seen
instead (our own echo: not a K-MD2; bytes that are no message: a baud mismatch).
"""

from __future__ import annotations

import logging
import termios
import time
from collections import deque
from typing import Callable, Protocol

import serial

from .assembly import DriverCounters, FrameAssembler
from .errors import LinkError, SensorError, SensorResponseError, SensorTimeout, WrongDevice
from .link import LinkKind, SerialLink
from .profile import SensorProfile
from .protocol import BAUD_SWITCH_SETTLE_S, Gbye, Init, Message, Resp, RespCode, encode

log = logging.getLogger("qradar.driver")


def silence_text(url: str, startup_baud: int, name: str, timeout_s: float, seen: list[str], sent: str,
                 skipped: int) -> str:
    """One line for a command ``name`` left without an answer, with the likely cause;
    ``seen``: the kinds of message that came instead; ``skipped``: bytes that were none."""
    if sent in seen:
        return (f"no RESP to {name} from {url} within {timeout_s:.2f} s, but our own {name} came back: "
                f"the link echoes (a loopback, a modem or a console), not a K-MD2")
    if seen:
        kinds = ", ".join(sorted(set(seen)))
        return f"no RESP to {name} from {url} within {timeout_s:.2f} s; saw {kinds} instead"
    what = f"saw {skipped} bytes that were no message" if skipped else "saw no message"
    if name == "INIT":
        return (f"no RESP to INIT from {url} within {timeout_s:.2f} s; {what} (check that it is a K-MD2, "
                f"powered, and that the line runs at {startup_baud} baud 8E1: a ser2net port must be set to "
                f"{startup_baud}e81; bytes that are no message mean a baud mismatch)")
    return f"no RESP to {name} from {url} within {timeout_s:.2f} s; {what}"


class LinkSettings(Protocol):
    """What a connection reads of its configuration (a :class:`~.session.SessionConfig`)."""

    url: str
    baud: int | None
    timeout_s: float
    profile: SensorProfile

    @property
    def kind(self) -> LinkKind: ...

    @property
    def line_baud(self) -> int: ...

    @property
    def baud_code(self) -> int: ...


class SensorConnection:
    """The link, the codec (through ``assembler``) and the commands of a session's set-up
    and end. ``fill`` reads the port once into ``inbox``. ``connected_log_level``: the level
    of the "connected to ..." line (a probe's is DEBUG)."""

    connected_log_level = logging.INFO

    def __init__(self, config: LinkSettings, assembler: FrameAssembler, counters: DriverCounters,
                 port_factory: Callable[..., serial.SerialBase] = serial.serial_for_url):
        self.config = config
        self.profile = config.profile
        self.assembler = assembler
        self.counters = counters
        start = self.profile.startup_baud
        other = next(b for b in sorted(self.profile.baud_codes.values()) if b != start)
        self.link = SerialLink(config.url, start, other, port_factory)
        self.inbox: deque[Message] = deque()
        self.ever_connected = False

    @property
    def is_open(self) -> bool:
        return self.link.is_open

    def write(self, data: bytes) -> None:
        self.link.write(data)

    def fill(self) -> None:
        """One read of the port (blocks at most READ_TIMEOUT_S) into the inbox."""
        data = self.link.read(self.assembler.decoder.wanted())
        if data:
            self.inbox.extend(self.assembler.decode(data))

    def next_message(self, deadline: float) -> Message | None:
        """The next decoded message, or None once ``deadline`` (monotonic s) has passed."""
        while not self.inbox:
            if time.monotonic() >= deadline:
                return None
            self.fill()
        return self.inbox.popleft()

    def command(self, msg: Message, name: str, timeout_s: float) -> None:
        """Send a command and wait for its RESP (OK, or SensorResponseError). Only while
        no reader thread reads the port (connect, close)."""
        self.inbox.clear()
        self.write(encode(msg))
        deadline = time.monotonic() + timeout_s
        seen: list[str] = []
        while (m := self.next_message(deadline)) is not None:
            if isinstance(m, Resp):
                if m.code != RespCode.OK:
                    self.counters.resp_errors += 1
                    raise SensorResponseError(name, m.code)
                return
            seen.append(type(m).__name__)
        self.counters.timeouts += 1
        raise SensorTimeout(silence_text(self.config.url, self.profile.startup_baud, name, timeout_s, seen,
                                         type(msg).__name__, self.assembler.decoder.stats.skipped_bytes))

    def connect(self) -> None:
        """Open the link, INIT the sensor and switch the line speed; a SensorError saying
        what to check on failure (the port closed again)."""
        cfg, link = self.config, self.link
        try:
            link.open()
        except WrongDevice:
            self.counters.wrong_device += 1
            raise
        self.inbox.clear()
        self.assembler.restart()
        if cfg.baud is not None and cfg.baud != cfg.line_baud and not self.ever_connected:
            log.warning("%s is a %s link, which cannot change the line speed: baud %d ignored, staying at %d",
                        cfg.url, cfg.kind.value, cfg.baud, cfg.line_baud)
        try:
            self._init()
        except (serial.SerialException, OSError, termios.error) as exc:
            link.close()
            raise LinkError(f"{cfg.url} failed during INIT: {getattr(exc, 'strerror', None) or exc}") from exc
        except SensorError as exc:
            text = link.peer_text()  # e.g. ser2net's "Device open failure: ..." before it hangs up
            link.close()
            said = f", saying {text!r}" if text else ""
            if isinstance(exc, LinkError):
                raise LinkError(f"{exc}: the other end hung up during the set-up{said} (ser2net could not open "
                                f"its device? see its log, the device path in its YAML, its user's dialout "
                                f"group)") from exc
            if text:
                raise type(exc)(f"{exc}; the other end said {text!r}: not a K-MD2") from exc
            raise
        except BaseException:
            link.close()
            raise
        if self.ever_connected:
            self.counters.reconnects += 1
        self.ever_connected = True
        if cfg.kind.can_change_speed:
            log.log(self.connected_log_level, "connected to %s at %d baud (profile %s)", cfg.url, cfg.line_baud,
                    self.profile.name)
        else:
            log.log(self.connected_log_level, "connected to %s (%s link: the line speed stays at %d baud; profile %s)",
                    cfg.url, cfg.kind.value, cfg.line_baud, self.profile.name)

    def _init(self) -> None:
        cfg, port = self.config, self.link.port
        port.reset_input_buffer()
        try:
            self.command(Init(cfg.baud_code), "INIT", timeout_s=cfg.timeout_s)
        except SensorTimeout:
            if not cfg.kind.can_change_speed:
                raise
            # the sensor may still run at a rate a previous session left it at
            self._release_stuck_sensor()
            self.command(Init(cfg.baud_code), "INIT", timeout_s=cfg.timeout_s)
        if cfg.kind.can_change_speed and cfg.line_baud != self.profile.startup_baud:
            time.sleep(BAUD_SWITCH_SETTLE_S)
            port.baudrate = cfg.line_baud

    def _release_stuck_sensor(self) -> None:
        port = self.link.port
        start = self.profile.startup_baud
        for baud in sorted(set(self.profile.baud_codes.values()) - {start}):
            port.baudrate = baud
            port.write(encode(Gbye()))
            port.flush()
            time.sleep(0.02)
        port.baudrate = start
        time.sleep(BAUD_SWITCH_SETTLE_S)
        port.reset_input_buffer()
        self.assembler.decoder.reset()
        self.inbox.clear()

    def goodbye(self) -> None:
        """GBYE and close the port, so that the sensor goes back to its start-up speed."""
        if not self.link.is_open:
            return
        try:
            self.command(Gbye(), "GBYE", timeout_s=0.3)
        except SensorError as exc:
            log.debug("GBYE to %s failed: %s", self.config.url, exc)
        finally:
            self.link.close()
