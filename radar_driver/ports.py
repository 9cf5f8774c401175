"""The serial adapters of this host and which of them answer as a K-MD2.

:func:`list_serial_ports` reads pyserial's ``serial.tools.list_ports`` (device, USB
VID:PID, serial number, description, manufacturer) and writes nothing to any port; it
leaves out the on-board UARTs the kernel knows of but found no hardware for (their
``/sys/class/tty/<name>/type`` is 0, ``PORT_UNKNOWN``: the ``/dev/ttyS0``-``S3`` of a
virtual machine).

:func:`probe_port` asks one port (a device path or any pyserial URL) whether a K-MD2 is
on it, with the session's own command exchange (:class:`~.connection.SensorConnection`):
the port opened as a session opens it (a device path exclusively, so a port held by
another program, e.g. a running driver, is reported busy and is neither configured nor
written), then ``INIT`` asking for the start-up speed (no line-speed switch) and ``GBYE``.
A sensor left at another speed by a host that died without ``GBYE`` gets ``GBYE`` at
those speeds and a second ``INIT``, as a session's connect does. ``GNFD`` is never
sent: no measurement starts, and the sensor is left at its start-up speed.
:func:`probe_ports` probes several at once (at most :data:`PROBE_WORKERS` at a time).

The K-MD2's answer to ``INIT`` is a ``RESP`` code and nothing else: the protocol gives
no serial number or firmware version among the commands qradar sends, so what names a
sensor is its adapter (VID:PID and serial number) or its URL.
"""

from __future__ import annotations

import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from enum import Enum
from typing import Callable

import serial

from .assembly import DriverCounters, FrameAssembler
from .connection import SensorConnection
from .errors import LinkError, PortBusy, PortDenied, RespCode, SensorResponseError, SensorTimeout
from .link import LinkKind, link_kind
from .profile import SensorProfile, resolve_profile

#: ports probed at once
PROBE_WORKERS = 8
#: a probe's wait for the RESP to INIT (and to the retry after a speed reset), s
PROBE_TIMEOUT_S = 0.5


@dataclass(frozen=True)
class PortInfo:
    """A serial adapter as pyserial lists it; None where the system does not say."""

    device: str
    vid: int | None = None
    pid: int | None = None
    serial_number: str | None = None
    description: str | None = None
    manufacturer: str | None = None
    product: str | None = None
    location: str | None = None
    hwid: str | None = None

    @property
    def vid_pid(self) -> str | None:
        """``"0403:6001"`` for a USB adapter, else None."""
        return f"{self.vid:04x}:{self.pid:04x}" if self.vid is not None and self.pid is not None else None

    def identity(self) -> str:
        """The adapter in a few words: VID:PID, manufacturer, description, serial number."""
        parts = [p for p in (self.vid_pid, self.manufacturer, self.description) if p]
        if self.serial_number:
            parts.append(f"serial {self.serial_number}")
        return ", ".join(parts)

    def to_dict(self) -> dict:
        return {"device": self.device, "vid_pid": self.vid_pid, "vid": self.vid, "pid": self.pid,
                "serial_number": self.serial_number, "description": self.description,
                "manufacturer": self.manufacturer, "product": self.product, "location": self.location,
                "hwid": self.hwid}


def _absent_uart(name: str) -> bool:
    """An on-board UART the kernel registered without finding its hardware (type 0)."""
    try:
        with open(f"/sys/class/tty/{name}/type") as f:
            return f.read().strip() == "0"
    except OSError:
        return False


def list_serial_ports() -> list[PortInfo]:
    """The serial adapters present, sorted by device (nothing is written to them)."""
    from serial.tools import list_ports

    out = []
    for p in list_ports.comports():
        if _absent_uart(p.name or os.path.basename(p.device)):
            continue
        known = [None if v in (None, "", "n/a") else v for v in
                 (p.serial_number, p.description, p.manufacturer, p.product, p.location, p.hwid)]
        out.append(PortInfo(p.device, p.vid, p.pid, *known))
    return sorted(out, key=lambda p: p.device)


def port_info(url: str, listed: list[PortInfo]) -> PortInfo | None:
    """The listed adapter a device path names (a ``/dev/serial/by-id/`` link too), or None."""
    if link_kind(url) is not LinkKind.DEVICE:
        return None
    real = os.path.realpath(url)
    return next((p for p in listed if os.path.realpath(p.device) == real), None)


class Answer(str, Enum):
    """What a probed port did."""

    KMD2 = "kmd2"  # answered INIT with a RESP: speaks the K-MD2's protocol
    OTHER = "other"  # answered, but no RESP: something else (an echo, text, other bytes)
    SILENT = "silent"  # no byte within the timeout
    BUSY = "busy"  # held by another program (not opened, nothing written)
    DENIED = "denied"  # this user may not open it
    ERROR = "error"  # cannot be opened or failed otherwise (no such device, refused, hung up)

    @property
    def words(self) -> str:
        return {"kmd2": "K-MD2", "other": "not a K-MD2", "silent": "silent", "busy": "busy",
                "denied": "permission denied", "error": "cannot open"}[self.value]


@dataclass(frozen=True)
class ProbeResult:
    """One probed port: its URL, what it did, one line why, the RESP code of a K-MD2,
    how long the probe took (s), and the adapter if listed."""

    url: str
    answer: Answer
    reason: str
    resp_code: int | None = None
    elapsed_s: float = 0.0
    port: PortInfo | None = None

    @property
    def is_kmd2(self) -> bool:
        return self.answer is Answer.KMD2

    @property
    def name(self) -> str:
        """The URL, and the adapter in parentheses if it is known."""
        ident = self.port.identity() if self.port is not None else ""
        return f"{self.url} ({ident})" if ident else self.url

    def line(self) -> str:
        """``/dev/ttyUSB0 (0403:6001, ...): K-MD2: RESP 0 ...``: the port, its answer and why."""
        return f"{self.name}: {self.answer.words}: {self.reason}"

    def to_dict(self) -> dict:
        return {"url": self.url, "answer": self.answer.value, "reason": self.reason, "resp_code": self.resp_code,
                "resp": RespCode(self.resp_code).name if self.resp_code in RespCode._value2member_map_ else None,
                "elapsed_s": round(self.elapsed_s, 4)}


@dataclass(frozen=True)
class _ProbeSettings:
    """A session's link settings for a probe: the start-up speed, no switch
    (:class:`~.connection.LinkSettings`)."""

    url: str
    profile: SensorProfile
    timeout_s: float

    @property
    def baud(self) -> int:
        return self.profile.startup_baud

    @property
    def kind(self) -> LinkKind:
        return link_kind(self.url)

    @property
    def line_baud(self) -> int:
        return self.profile.startup_baud

    @property
    def baud_code(self) -> int:
        return self.profile.baud_code(self.profile.startup_baud)


def probe_port(url: str, profile: SensorProfile | str | None = None, timeout_s: float = PROBE_TIMEOUT_S,
               port: PortInfo | None = None,
               port_factory: Callable[..., serial.SerialBase] = serial.serial_for_url) -> ProbeResult:
    """Whether a K-MD2 answers on ``url``: INIT at the start-up speed, then GBYE (see the
    module). Never raises for what the port does; the answer says it."""
    prof = resolve_profile(profile)
    counters = DriverCounters()
    assembler = FrameAssembler(prof, 2, "first", "probe", url, counters)
    conn = SensorConnection(_ProbeSettings(url, prof, timeout_s), assembler, counters, port_factory)
    conn.connected_log_level = logging.DEBUG  # a probe is no session: its result says what it found
    t0 = time.monotonic()

    def result(answer: Answer, reason: str, code: int | None = None) -> ProbeResult:
        return ProbeResult(url, answer, " ".join(reason.split()), code, time.monotonic() - t0, port)

    try:
        conn.connect()  # opens (a device path exclusively) and INITs at the start-up speed, or closes again
    except PortBusy as exc:
        return result(Answer.BUSY, str(exc))
    except PortDenied as exc:
        return result(Answer.DENIED, str(exc))
    except SensorResponseError as exc:  # a RESP, with an error code: the protocol is the K-MD2's
        return result(Answer.KMD2, f"{exc} (at {prof.startup_baud} baud)", exc.code)
    except SensorTimeout as exc:
        heard = bool(conn.link.first_bytes)
        return result(Answer.OTHER if heard else Answer.SILENT, str(exc))
    except LinkError as exc:
        return result(Answer.ERROR, str(exc))
    conn.goodbye()  # GBYE (its RESP awaited briefly) and close
    return result(Answer.KMD2, f"RESP 0 (OK) to INIT at {prof.startup_baud} baud; GBYE sent", int(RespCode.OK))


def probe_ports(urls: list[str], profile: SensorProfile | str | None = None, timeout_s: float = PROBE_TIMEOUT_S,
                listed: list[PortInfo] | None = None, workers: int = PROBE_WORKERS) -> list[ProbeResult]:
    """:func:`probe_port` of each URL, at most ``workers`` at a time, in the order given;
    ``listed``: the adapters to name device paths by (:func:`port_info`)."""
    prof = resolve_profile(profile)
    listed = listed or []
    if not urls:
        return []
    with ThreadPoolExecutor(max_workers=max(1, min(workers, len(urls))), thread_name_prefix="probe") as pool:
        futures = [pool.submit(probe_port, u, prof, timeout_s, port_info(u, listed)) for u in urls]
        return [f.result() for f in futures]
