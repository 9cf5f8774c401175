"""Raw captures of a serial session: every byte each way, with its time, in one file.

The bring-up kit for a sensor whose wire layout is unknown: ``qradar capture`` records
what crosses the link while the driver (or a minimal raw poller) talks to the sensor,
and :mod:`.inspection` reads the file back offline. pyserial's ``spy://`` prints a hex
dump for a human; a capture is a file a program can replay and decode again with every
sensor profile.

File layout (all integers little-endian; docs/capture-format.md):

- magic ``\\x89QRCAP\\r\\n`` (8 bytes), uint16 format version (1), uint32 header length H,
  H bytes of a UTF-8 JSON object (at least ``url``, ``start_time_ns``, ``profile``);
- then records to the end of the file, each: uint8 kind (:class:`Kind`), uint64
  ``time_ns`` (host wall clock, ``time.time_ns()``), uint32 length L, L bytes.

A file cut short (a killed capture) reads up to its last whole record; the reader says
where and why it stopped instead of raising.

:class:`CapturingPort` wraps an open pyserial port and logs every read chunk, write,
line-speed change and close; :func:`capturing_factory` makes one for
:class:`~.session.SensorSession`'s ``port_factory``. :func:`run_capture` drives a
capture: the driver's session first and, if it decodes no frame (a wrong profile), a
raw poller (``INIT``, then a ``GNFD`` each time a ``DONE`` arrives, ``GBYE`` at the end)
that records the sensor's answers without decoding them.
"""

from __future__ import annotations

import json
import logging
import struct
import threading
import time
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

import serial

from .errors import CaptureError, ConfigError, LinkError, SensorError, SensorTimeout
from .options import like, option, pos_float, pos_int
from .profile import DEFAULT_PROFILE_NAME, SensorProfile, packaged_profiles, resolve_profile
from .protocol import BAUD_SWITCH_SETTLE_S, Gbye, Gnfd, Init, encode
from .session import DEFAULT_FAST_BAUD, SensorSession, SessionConfig, open_error, port_url

log = logging.getLogger("qradar.capture")

MAGIC = b"\x89QRCAP\r\n"
VERSION = 1
_PREAMBLE = struct.Struct("<8sHI")  # magic, version, header length
_RECORD = struct.Struct("<BQI")  # kind, time_ns, length
#: the largest header and record a reader accepts (checked before allocating)
MAX_HEADER_LEN = 1 << 20
MAX_RECORD_LEN = 64 << 20


class Kind(IntEnum):
    """What a record holds."""

    TX = 1  # bytes the host wrote to the sensor
    RX = 2  # bytes the host read from the sensor (one read call)
    BAUD = 3  # the host set the line speed: uint32 baud
    OPEN = 4  # the host opened the port: JSON {"url", "baudrate"}
    CLOSE = 5  # the host closed the port: no bytes


@dataclass(frozen=True)
class Record:
    """One record: its ``kind``, the host's ``time_ns`` and its bytes."""

    kind: Kind
    time_ns: int
    data: bytes = b""

    def encode(self) -> bytes:
        return _RECORD.pack(int(self.kind), self.time_ns, len(self.data)) + self.data

    @property
    def baud(self) -> int:
        """The line speed of a BAUD record."""
        return struct.unpack("<I", self.data)[0]


@dataclass(frozen=True)
class CaptureHeader:
    """The file's JSON header: the ``url`` captured, ``start_time_ns`` (wall clock), the
    ``profile`` the capture asked for, and anything else (``extra``: baud, ramps, tool)."""

    url: str
    start_time_ns: int
    profile: str
    extra: dict = field(default_factory=dict)

    def to_json(self) -> bytes:
        return json.dumps({"url": self.url, "start_time_ns": self.start_time_ns, "profile": self.profile,
                           **self.extra}, sort_keys=True).encode()

    @classmethod
    def from_json(cls, blob: bytes, where: str) -> "CaptureHeader":
        try:
            data = json.loads(blob.decode())
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise CaptureError(f"{where}: the capture header is not JSON: {exc}") from None
        if not isinstance(data, dict) or not {"url", "start_time_ns", "profile"} <= set(data):
            raise CaptureError(f"{where}: the capture header must be an object with url, start_time_ns and profile")
        rest = {k: v for k, v in data.items() if k not in ("url", "start_time_ns", "profile")}
        return cls(str(data["url"]), int(data["start_time_ns"]), str(data["profile"]), rest)


# -- writing ------------------------------------------------------------------------------------
class CaptureWriter:
    """Writes a capture file; thread-safe (the session's reader thread and its owner both
    write). ``with CaptureWriter(path, header) as w: w.write(Kind.RX, data)``. Counts
    records and bytes per kind; flushes at least every ``flush_s`` seconds, so a killed
    capture loses at most that much."""

    def __init__(self, path: str | Path, header: CaptureHeader, flush_s: float = 0.5):
        self.path = Path(path)
        self.header = header
        self.records = 0
        self.bytes = {k: 0 for k in Kind}
        self._lock = threading.Lock()
        self._flush_s = flush_s
        self._last_flush = time.monotonic()
        blob = header.to_json()
        try:
            self._f: BinaryIO | None = open(self.path, "wb")
            self._f.write(_PREAMBLE.pack(MAGIC, VERSION, len(blob)) + blob)
        except OSError as exc:
            raise CaptureError(f"cannot write capture {self.path}: {exc.strerror or exc}") from None

    def write(self, kind: Kind, data: bytes = b"", time_ns: int | None = None) -> None:
        """Append one record (``time_ns`` default: now)."""
        rec = Record(kind, time.time_ns() if time_ns is None else time_ns, bytes(data))
        with self._lock:
            if self._f is None:
                raise CaptureError(f"capture {self.path} is closed")
            try:
                self._f.write(rec.encode())
                now = time.monotonic()
                if now - self._last_flush >= self._flush_s:
                    self._f.flush()
                    self._last_flush = now
            except OSError as exc:
                raise CaptureError(f"cannot write capture {self.path}: {exc.strerror or exc}") from None
            self.records += 1
            self.bytes[kind] += len(rec.data)

    def close(self) -> None:
        with self._lock:
            f, self._f = self._f, None
        if f is not None:
            try:
                f.close()
            except OSError as exc:
                raise CaptureError(f"cannot write capture {self.path}: {exc.strerror or exc}") from None

    def __enter__(self) -> "CaptureWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# -- reading ------------------------------------------------------------------------------------
class CaptureReader:
    """Reads a capture: ``header`` at once, then ``for record in reader``. A record cut
    short or malformed ends the iteration and sets ``truncated`` to one line saying
    where and why; a file that is not a capture raises CaptureError naming it."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.truncated: str | None = None
        try:
            self._f: BinaryIO = open(self.path, "rb")
        except OSError as exc:
            raise CaptureError(f"cannot read capture {self.path}: {exc.strerror or exc}") from None
        try:
            self.header = self._read_header()
        except BaseException:
            self._f.close()
            raise

    def _read_header(self) -> CaptureHeader:
        pre = self._f.read(_PREAMBLE.size)
        if len(pre) < 8 or pre[:8] != MAGIC:
            raise CaptureError(f"{self.path} is not a qradar capture: it starts with {pre[:8]!r} where a capture "
                               f"starts with {MAGIC!r}")
        if len(pre) < _PREAMBLE.size:
            raise CaptureError(f"{self.path}: the capture is cut short inside its preamble ({len(pre)} bytes)")
        _, version, hlen = _PREAMBLE.unpack(pre)
        if version != VERSION:
            raise CaptureError(f"{self.path}: capture format version {version}; this reader knows {VERSION}")
        if hlen > MAX_HEADER_LEN:
            raise CaptureError(f"{self.path}: a capture header of {hlen} bytes is beyond {MAX_HEADER_LEN}")
        blob = self._f.read(hlen)
        if len(blob) < hlen:
            raise CaptureError(f"{self.path}: the capture is cut short inside its header ({len(blob)} of {hlen} bytes)")
        self._offset = _PREAMBLE.size + hlen
        self.header = CaptureHeader.from_json(blob, str(self.path))
        return self.header

    def __iter__(self) -> Iterator[Record]:
        index = 0
        f = self._f
        while True:
            at = self._offset
            head = f.read(_RECORD.size)
            if not head:
                return
            if len(head) < _RECORD.size:
                self.truncated = f"record {index} at byte {at} is cut short inside its {_RECORD.size}-byte prefix"
                return
            kind, t_ns, length = _RECORD.unpack(head)
            if kind not in Kind._value2member_map_:
                self.truncated = f"record {index} at byte {at} has unknown kind {kind}: the rest is unreadable"
                return
            if length > MAX_RECORD_LEN:
                self.truncated = (f"record {index} at byte {at} declares {length} bytes, beyond {MAX_RECORD_LEN}: "
                                  f"the rest is unreadable")
                return
            data = f.read(length)
            if len(data) < length:
                self.truncated = f"record {index} at byte {at} is cut short: {len(data)} of {length} bytes"
                return
            self._offset = at + _RECORD.size + length
            index += 1
            yield Record(Kind(kind), t_ns, data)

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> "CaptureReader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class Capture:
    """A capture read whole: its header, its records in order, and ``truncated`` (None,
    or where and why the records end early)."""

    path: Path
    header: CaptureHeader
    records: list[Record]
    truncated: str | None = None

    @classmethod
    def read(cls, path: str | Path) -> "Capture":
        with CaptureReader(path) as r:
            records = list(r)
            return cls(Path(path), r.header, records, r.truncated)

    def byte_count(self, kind: Kind) -> int:
        return sum(len(r.data) for r in self.records if r.kind == kind)

    @property
    def duration_s(self) -> float:
        """From the header's start to the last record, s."""
        if not self.records:
            return 0.0
        return (self.records[-1].time_ns - self.header.start_time_ns) / 1e9


# -- the port wrapper ----------------------------------------------------------------------------
class CapturingPort:
    """A pyserial port that logs to a :class:`CaptureWriter` every chunk read (RX), every
    write (TX), every line-speed change (BAUD) and its close (CLOSE); everything else
    is delegated. ``reset_input_buffer`` first reads what is waiting, so that the
    capture holds the bytes the host throws away too."""

    def __init__(self, port: serial.SerialBase, writer: CaptureWriter):
        self._port = port
        self._writer = writer

    def read(self, size: int = 1) -> bytes:
        data = self._port.read(size)
        if data:
            self._writer.write(Kind.RX, data)
        return data

    def write(self, data: bytes) -> int | None:
        t_ns = time.time_ns()
        n = self._port.write(data)
        self._writer.write(Kind.TX, bytes(data), t_ns)
        return n

    @property
    def in_waiting(self) -> int:
        return self._port.in_waiting

    @property
    def baudrate(self) -> int:
        return self._port.baudrate

    @baudrate.setter
    def baudrate(self, baud: int) -> None:
        self._port.baudrate = baud
        self._writer.write(Kind.BAUD, struct.pack("<I", baud))

    def reset_input_buffer(self) -> None:
        waiting = self._port.in_waiting
        if waiting:
            self.read(waiting)
        self._port.reset_input_buffer()

    def flush(self) -> None:
        self._port.flush()

    def close(self) -> None:
        was_open = getattr(self._port, "is_open", True)
        self._port.close()
        if was_open:
            self._writer.write(Kind.CLOSE)

    def __getattr__(self, name: str):  # only for what this class does not define
        if name == "_port":
            raise AttributeError(name)
        return getattr(self._port, name)

    def __enter__(self) -> "CapturingPort":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def capturing_factory(writer: CaptureWriter,
                      factory: Callable[..., serial.SerialBase] = serial.serial_for_url) -> Callable[..., CapturingPort]:
    """A ``port_factory`` for :class:`~.session.SensorSession`: opens the port with
    ``factory`` (pyserial's ``serial_for_url``), logs an OPEN record and wraps it."""

    def open_port(url: str, **kwargs) -> CapturingPort:
        port = factory(url, **kwargs)
        writer.write(Kind.OPEN, json.dumps({"url": url, "baudrate": kwargs.get("baudrate")}).encode())
        return CapturingPort(port, writer)

    return open_port


# -- the raw poller ---------------------------------------------------------------------------------
#: what ends a GNFD answer whatever the RADC layout: a DONE header with its 4-byte length
DONE_PREFIX = b"DONE\x04\x00\x00\x00"
RESP_HEADER = b"RESP"


@dataclass
class RawPollStats:
    """What the raw poller saw: GNFD ``polls`` sent, ``answers`` (DONEs) received,
    ``timeouts`` (polls sent again after ``timeout_s`` without a DONE)."""

    polls: int = 0
    answers: int = 0
    timeouts: int = 0


class RawPoller:
    """The sensor's protocol at its most basic, for a sensor whose RADC layout is unknown:
    ``INIT`` (and the switch to ``line_baud`` on a link that can change speed), a
    ``GNFD`` for the RADC bit, the next one as soon as the ``DONE`` of the previous
    answer arrives (so it runs at the sensor's rate) or after ``timeout_s`` without one,
    and ``GBYE`` at the end. It looks for the RESP and DONE headers in the bytes and
    decodes nothing else; the capturing port records everything."""

    READ_TIMEOUT_S = 0.02

    def __init__(self, port, profile: SensorProfile, url: str, line_baud: int, can_change_speed: bool,
                 timeout_s: float = 0.5):
        self.port, self.profile, self.url = port, profile, url
        self.line_baud, self.can_change_speed, self.timeout_s = line_baud, can_change_speed, timeout_s
        self.stats = RawPollStats()
        self._tail = b""

    def _wait_for(self, pattern: bytes, deadline: float) -> bool:
        """Read until ``pattern`` appears in the bytes since the last match, or
        ``deadline`` (monotonic s) passes; keeps only a short tail in memory."""
        while True:
            try:
                data = self.port.read(max(1, self.port.in_waiting))
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                raise LinkError(f"read from {self.url} failed: {getattr(exc, 'strerror', None) or exc}") from exc
            if data:
                buf = self._tail + data
                i = buf.find(pattern)
                if i >= 0:
                    self._tail = buf[i + len(pattern):][-(len(pattern) - 1):]
                    return True
                self._tail = buf[-(len(pattern) - 1):]
            elif time.monotonic() >= deadline:
                return False

    def _send(self, msg) -> None:
        try:
            self.port.write(encode(msg))
        except (serial.SerialException, OSError) as exc:
            raise LinkError(f"write to {self.url} failed: {getattr(exc, 'strerror', None) or exc}") from exc

    def start(self) -> None:
        """INIT and the line-speed switch; SensorTimeout if the sensor does not answer."""
        self.port.reset_input_buffer()
        self._send(Init(self.profile.baud_code(self.line_baud)))
        if not self._wait_for(RESP_HEADER, time.monotonic() + self.timeout_s):
            raise SensorTimeout(f"no RESP to INIT from {self.url} within {self.timeout_s:.2f} s "
                                f"(raw poller, {self.profile.startup_baud} baud 8E1)")
        if self.can_change_speed and self.line_baud != self.profile.startup_baud:
            time.sleep(BAUD_SWITCH_SETTLE_S)
            self.port.baudrate = self.line_baud

    def poll(self, answers: int | None, deadline: float, stop: threading.Event | None = None) -> RawPollStats:
        """GNFD polls until ``answers`` DONEs (None = no limit), ``deadline`` (monotonic s)
        or ``stop``."""
        mask = self.profile.gnfd_bits["RADC"]
        st = self.stats
        while (answers is None or st.answers < answers) and time.monotonic() < deadline:
            if stop is not None and stop.is_set():
                break
            self._send(Gnfd(mask))
            st.polls += 1
            if self._wait_for(DONE_PREFIX, min(deadline, time.monotonic() + self.timeout_s)):
                st.answers += 1
            elif time.monotonic() < deadline:
                st.timeouts += 1
        return st

    def goodbye(self) -> None:
        """GBYE; waits for its RESP behind the rest of an answer (at most 1 s), best effort."""
        try:
            self._send(Gbye())
            self._wait_for(RESP_HEADER, time.monotonic() + max(1.0, self.timeout_s))
        except SensorError as exc:
            log.debug("GBYE to %s failed: %s", self.url, exc)


# -- a capture run -------------------------------------------------------------------------------------
MODES = ("auto", "session", "raw")


@dataclass(frozen=True)
class CaptureConfig:
    """url: any pyserial URL. profile: the layout to try (name, TOML path or profile;
    None = the default). frames: stop after that many frames (None = no limit).
    seconds: stop after that long, s. baud, ramps_per_frame, timeout_s: as
    :class:`~.session.SessionConfig`. mode: ``session`` (the driver only), ``raw`` (the
    raw poller only) or ``auto`` (the driver; if it stops without a frame, e.g. because
    the profile's RADC layout is wrong, the raw poller for the rest of the time). In the
    raw poller a frame counts ``ramps_per_frame`` GNFD answers, enough for any layout."""

    url: str = like(SessionConfig, "url")
    profile: SensorProfile | str | None = option(
        None, f"sensor profile for the driver: a packaged name ({', '.join(packaged_profiles())}) or a TOML file "
        f"(default {DEFAULT_PROFILE_NAME}); its baud codes and GNFD bits also serve the raw poller",
        kinds=frozenset({"str"}))
    frames: int | None = option(None, "stop after N frames (the raw poller: N x --ramps GNFD answers)", parse=pos_int)
    seconds: float = option(10.0, "stop after S seconds", parse=pos_float)
    baud: int | None = option(None, f"rate after INIT (default {DEFAULT_FAST_BAUD} on a link that can change speed)")
    ramps_per_frame: int = like(SessionConfig, "ramps_per_frame")
    timeout_s: float = like(SessionConfig, "timeout_s")
    mode: str = option("auto", "auto: the driver, then the raw poller if it decodes no frame; session: the driver "
                       "only; raw: the raw poller only", choices=MODES)

    def __post_init__(self) -> None:
        object.__setattr__(self, "profile", resolve_profile(self.profile))
        if self.frames is not None and not (isinstance(self.frames, int) and self.frames >= 1):
            raise ConfigError(f"frames={self.frames!r} must be an integer >= 1 or None")
        if not self.seconds > 0:
            raise ConfigError(f"seconds={self.seconds!r} must be > 0")
        if self.mode not in MODES:
            raise ConfigError(f"mode={self.mode!r} must be one of {list(MODES)}")

    def session_config(self) -> SessionConfig:
        """The driver's configuration (no reconnect: an error ends the session part)."""
        return SessionConfig(self.url, baud=self.baud, ramps_per_frame=self.ramps_per_frame,
                             timeout_s=self.timeout_s, reconnect=False, profile=self.profile)


@dataclass
class CaptureSummary:
    """What a capture did: ``frames`` the driver decoded with the profile, the raw
    poller's ``raw`` stats (None if it did not run), why the driver stopped early
    (``session_error``), records and bytes each way, and the seconds it took."""

    path: str
    profile: str
    mode: str
    frames: int = 0
    raw: RawPollStats | None = None
    session_error: str = ""
    records: int = 0
    bytes_rx: int = 0
    bytes_tx: int = 0
    seconds: float = 0.0

    def line(self) -> str:
        """One line for a person."""
        parts = []
        if self.mode != "raw":
            parts.append(f"{self.frames} frames decoded with {self.profile}"
                         + (f" (the driver stopped: {self.session_error})" if self.session_error else ""))
        if self.raw is not None:
            r = self.raw
            parts.append(f"raw poller: {r.answers} GNFD answers, {r.timeouts} polls without one")
        return (f"captured {self.bytes_rx} bytes from the sensor and {self.bytes_tx} to it in {self.records} records "
                f"over {self.seconds:.2f} s to {self.path}: " + "; ".join(parts))

    def to_dict(self) -> dict:
        d = {k: v for k, v in vars(self).items() if k != "raw"}
        d["raw"] = None if self.raw is None else vars(self.raw).copy()
        return d


def capture_header(cfg: CaptureConfig) -> CaptureHeader:
    p = cfg.profile
    return CaptureHeader(cfg.url, time.time_ns(), p.name,
                         {"tool": "qradar capture", "mode": cfg.mode, "baud": cfg.baud,
                          "ramps_per_frame": cfg.ramps_per_frame, "profile_source": p.source})


def run_capture(cfg: CaptureConfig, path: str | Path, stop: threading.Event | None = None,
                factory: Callable[..., serial.SerialBase] = serial.serial_for_url) -> CaptureSummary:
    """Capture a session with the sensor at ``cfg.url`` into ``path`` (see
    :class:`CaptureConfig`); ``stop`` ends it early. Errors opening the link or at
    INIT are raised (the file is still closed whole); an error of the driver after that
    hands over to the raw poller in ``auto`` mode."""
    t0 = time.monotonic()
    deadline = t0 + cfg.seconds
    stop = stop or threading.Event()
    summary = CaptureSummary(str(path), cfg.profile.name, cfg.mode)
    with CaptureWriter(path, capture_header(cfg)) as writer:
        try:
            open_port = capturing_factory(writer, factory)
            if cfg.mode in ("auto", "session"):
                summary.frames, summary.session_error = _capture_session(cfg, open_port, deadline, stop)
                if summary.session_error and cfg.mode == "session":
                    raise SensorError(summary.session_error)
            wanted = None if cfg.frames is None else (cfg.frames - summary.frames) * cfg.ramps_per_frame
            if cfg.mode == "raw" or (summary.session_error and (wanted is None or wanted > 0)
                                     and time.monotonic() < deadline and not stop.is_set()):
                if summary.session_error:
                    log.warning("the driver stopped (%s); capturing on with the raw poller", summary.session_error)
                summary.raw = _capture_raw(cfg, open_port, wanted, deadline, stop)
        finally:
            summary.seconds = time.monotonic() - t0
            summary.records = writer.records
            summary.bytes_rx, summary.bytes_tx = writer.bytes[Kind.RX], writer.bytes[Kind.TX]
    return summary


def _capture_session(cfg: CaptureConfig, open_port, deadline: float, stop: threading.Event) -> tuple[int, str]:
    """Frames through the driver until cfg.frames, the deadline or a stop: (frames, the
    driver's error after it opened, or "")."""
    session = SensorSession(cfg.session_config(), port_factory=open_port)
    session.open()  # a link or INIT error is raised: the raw poller would not do better
    done = threading.Event()

    def watchdog() -> None:  # ends the frames below at the deadline or a stop
        while not done.wait(min(0.05, max(0.0, deadline - time.monotonic()))):
            if stop.is_set() or time.monotonic() >= deadline:
                session.request_stop()
                return

    threading.Thread(target=watchdog, name="capture-deadline", daemon=True).start()
    frames = 0
    try:
        for _ in session.frames(cfg.frames):
            frames += 1
    except SensorError as exc:
        return frames, str(exc)
    finally:
        done.set()
        session.close()
    return frames, ""


def _capture_raw(cfg: CaptureConfig, open_port, answers: int | None, deadline: float,
                 stop: threading.Event) -> RawPollStats:
    scfg = cfg.session_config()
    try:
        port = open_port(port_url(cfg.url), baudrate=cfg.profile.startup_baud, bytesize=serial.EIGHTBITS,
                         parity=serial.PARITY_EVEN, stopbits=serial.STOPBITS_ONE, timeout=RawPoller.READ_TIMEOUT_S)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise LinkError(open_error(cfg.url, exc)) from exc
    poller = RawPoller(port, cfg.profile, cfg.url, scfg.line_baud, scfg.kind.can_change_speed, cfg.timeout_s)
    try:
        poller.start()
        poller.poll(answers, deadline, stop)
    finally:
        poller.goodbye()
        try:
            port.close()
        except (serial.SerialException, OSError):
            pass
    return poller.stats
