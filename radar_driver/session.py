"""The K-MD2 driver session: owns the serial port, speaks the protocol through the
codec, and assembles ramps into frames.

Any pyserial URL works (``/dev/ttyUSB0``, a pty path, ``socket://host:port``,
``rfc2217://host:port``), always 8E1. ``INIT`` goes out at 115200 baud; after its
``RESP`` the host waits :data:`~.protocol.BAUD_SWITCH_SETTLE_S` and switches to the
requested rate. Every ramp is one ``GNFD`` poll answered by ``RESP``, ``RADC``, ``DONE``.
``ramps_per_frame`` consecutive ramps (by the ``DONE`` counter) make a frame of
M = ramps x 256 measurements; a counter gap counts as dropped sensor frames and the
partial frame is discarded.

Errors are typed (:class:`SensorTimeout`, :class:`SensorResponseError`,
:class:`LinkError`); :meth:`SensorSession.frames` reconnects with backoff and re-INITs
on any of them (an unplug, a timeout, a RESP error) and yields every complete frame.
``GBYE`` on close, so that the next session finds the sensor at 115200; close is
idempotent.

Timestamps: K-MD2 frames carry no clock, so a frame's ``timestamp_ns`` is the host's
``time.time_ns()`` when the ``DONE`` of its first ramp arrived.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import asdict, dataclass
from typing import Callable, Iterator

import numpy as np
import serial

from .errors import ConfigError, LinkError, RadarError, SensorError, SensorResponseError, SensorTimeout
from .model import RadarConfig
from .source import RawFrame
from .protocol import (
    BAUD_CODES,
    BAUD_SWITCH_SETTLE_S,
    DEFAULT_BAUD,
    FRAME_BITS,
    RADC_LAYOUT,
    Done,
    Gbye,
    Gnfd,
    Init,
    Radc,
    Resp,
    RespCode,
    StreamDecoder,
    adc_to_complex,
    encode,
)

log = logging.getLogger("qradar.driver")


@dataclass
class DriverCounters:
    """What a session has seen. ``dropped`` counts sensor frames (DONE counter gaps);
    ``incomplete`` ramps whose RADC never arrived; ``discarded_ramps`` ramps thrown away
    with a partial frame."""

    frames: int = 0
    ramps: int = 0
    bytes: int = 0
    resyncs: int = 0
    skipped_bytes: int = 0
    dropped: int = 0
    reconnects: int = 0
    incomplete: int = 0
    discarded_ramps: int = 0
    timeouts: int = 0
    resp_errors: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


@dataclass(frozen=True)
class SessionConfig:
    """url: any pyserial URL. baud: rate after INIT (one of BAUD_CODES). timeout_s: wait
    for a GNFD answer before one retry (then SensorTimeout). reconnect: in
    :meth:`SensorSession.frames`, reconnect on errors with backoff from
    ``backoff_s`` to ``max_backoff_s``; give up after ``reconnect_timeout_s`` (None = never).
    sensor_id: the id its frames carry (the sensor's chunk of the zenoh keys)."""

    url: str
    baud: int = 2_000_000
    ramps_per_frame: int = 2
    timeout_s: float = 0.5
    reconnect: bool = True
    backoff_s: float = 0.05
    max_backoff_s: float = 2.0
    reconnect_timeout_s: float | None = None
    sensor_id: str = "kmd2"

    def __post_init__(self) -> None:
        if not isinstance(self.url, str) or not self.url:
            raise ConfigError(f"url={self.url!r} must be a non-empty string")
        if not isinstance(self.sensor_id, str) or not self.sensor_id:
            raise ConfigError(f"sensor_id={self.sensor_id!r} must be a non-empty string")
        if self.baud not in BAUD_CODES.values():
            raise ConfigError(f"baud={self.baud!r} must be one of {sorted(BAUD_CODES.values())}")
        if not (isinstance(self.ramps_per_frame, int) and self.ramps_per_frame >= 1):
            raise ConfigError(f"ramps_per_frame={self.ramps_per_frame!r} must be an integer >= 1")
        for name in ("timeout_s", "backoff_s", "max_backoff_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be > 0")

    @property
    def baud_code(self) -> int:
        return next(code for code, b in BAUD_CODES.items() if b == self.baud)

    def radar(self) -> RadarConfig:
        return RadarConfig(ramps_per_frame=self.ramps_per_frame)


class SensorSession:
    """``with SensorSession(SessionConfig(url)) as s: for frame in s.frames(): ...``

    A :class:`~radar_driver.source.FrameSource`: a K-MD2 (real or simulated) on a
    serial link."""

    READ_TIMEOUT_S = 0.02  # port read granularity; bounds how late a deadline is noticed

    def __init__(self, config: SessionConfig, port_factory: Callable[..., serial.SerialBase] = serial.serial_for_url):
        self.config = config
        self.counters = DriverCounters()
        self._port_factory = port_factory
        self._port: serial.SerialBase | None = None
        self._decoder = StreamDecoder()
        self._pending_radc: Radc | None = None
        self._last_counter: int | None = None
        self._ramps: list[tuple[int, int, np.ndarray]] = []  # (counter, t_ns, words)
        self._inbox: deque = deque()
        self._seq = 0
        self._closed = False
        self._ever_connected = False
        self._config_id = config.radar().config_id()

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
        """Open the port and INIT the sensor; raises a SensorError on failure."""
        self._closed = False
        self._connect()

    def request_stop(self) -> None:
        """Ask :meth:`frames` to end at the next frame, without touching the port (safe
        from another thread); the owner then closes."""
        self._closed = True

    def close(self) -> None:
        """GBYE (best effort) and close the port. Safe to call any number of times."""
        self._closed = True
        if self._port is None:
            return
        try:
            self._command(Gbye(), "GBYE", timeout_s=0.3)
        except SensorError as exc:
            log.debug("GBYE on close failed: %s", exc)
        finally:
            self._drop_port()

    def _connect(self) -> None:
        cfg = self.config
        try:
            port = self._port_factory(cfg.url, baudrate=DEFAULT_BAUD, bytesize=serial.EIGHTBITS,
                                      parity=serial.PARITY_EVEN, stopbits=serial.STOPBITS_ONE,
                                      timeout=self.READ_TIMEOUT_S)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LinkError(f"cannot open {cfg.url}: {exc}") from exc
        self._port = port
        self._decoder.reset()
        self._inbox.clear()
        self._pending_radc = None
        self._reset_assembly()
        try:
            port.reset_input_buffer()
            try:
                self._command(Init(cfg.baud_code), "INIT", timeout_s=cfg.timeout_s)
            except SensorTimeout:
                # the sensor may still run at a rate a previous session left it at
                self._release_stuck_sensor()
                self._command(Init(cfg.baud_code), "INIT", timeout_s=cfg.timeout_s)
            time.sleep(BAUD_SWITCH_SETTLE_S)
            port.baudrate = cfg.baud
        except (serial.SerialException, OSError) as exc:
            self._drop_port()
            raise LinkError(f"{cfg.url} failed during INIT: {exc}") from exc
        except BaseException:
            self._drop_port()
            raise
        if self._ever_connected:
            self.counters.reconnects += 1
        self._ever_connected = True
        log.info("connected to %s at %d baud", cfg.url, cfg.baud)

    def _release_stuck_sensor(self) -> None:
        port = self._port
        for baud in sorted(set(BAUD_CODES.values()) - {DEFAULT_BAUD}):
            port.baudrate = baud
            port.write(encode(Gbye()))
            port.flush()
            time.sleep(0.02)
        port.baudrate = DEFAULT_BAUD
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
        except (serial.SerialException, OSError) as exc:
            raise LinkError(f"write to {self.config.url} failed: {exc}") from exc

    def _fill_inbox(self) -> None:
        """One read of the port (blocks at most READ_TIMEOUT_S) into the inbox."""
        port = self._port
        if port is None:
            raise LinkError(f"{self.config.url} is not open")
        try:
            waiting = port.in_waiting
            data = port.read(max(self._decoder.wanted(), waiting))
        except (serial.SerialException, OSError) as exc:
            raise LinkError(f"read from {self.config.url} failed: {exc}") from exc
        if not data:
            return
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
        """Send a command and wait for its RESP (OK, or SensorResponseError)."""
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
        raise SensorTimeout(
            f"no RESP to {name} from {self.config.url} within {timeout_s:.2f} s; "
            f"saw {seen or 'no message'} and {self._decoder.stats.skipped_bytes} skipped bytes in all"
        )

    # -- ramps and frames -------------------------------------------------------------------------
    MAX_INCOMPLETE_IN_A_ROW = 8

    def read_ramp(self) -> tuple[int, int, np.ndarray]:
        """Poll one ramp: (DONE counter, host time ns, ADC words (2, 2, 256)).

        A GNFD answer whose RADC was lost (garbled, truncated) is counted as incomplete
        and polled again; no answer within timeout_s gets one more GNFD, then
        SensorTimeout."""
        timeouts = incomplete = 0
        while True:
            self._write(encode(Gnfd(FRAME_BITS["RADC"])))
            deadline = time.monotonic() + self.config.timeout_s
            seen: list[str] = []
            while (m := self._next_message(deadline)) is not None:
                seen.append(type(m).__name__)
                if isinstance(m, Radc):
                    if self._pending_radc is not None:
                        self.counters.incomplete += 1
                    self._pending_radc = m
                elif isinstance(m, Done):
                    radc, self._pending_radc = self._pending_radc, None
                    self._note_counter(m.frame_counter)
                    if radc is not None:
                        self.counters.ramps += 1
                        return m.frame_counter, time.time_ns(), radc.words
                    self.counters.incomplete += 1
                    self._reset_assembly()
                    break
                elif isinstance(m, Resp) and m.code != RespCode.OK:
                    self.counters.resp_errors += 1
                    raise SensorResponseError("GNFD", m.code)
            else:
                timeouts += 1
                self.counters.timeouts += 1
                if timeouts >= 2:
                    raise SensorTimeout(
                        f"no complete ramp from {self.config.url} after 2 GNFD polls of "
                        f"{self.config.timeout_s:.2f} s; saw {seen or 'no message'}"
                    )
                continue
            incomplete += 1
            if incomplete >= self.MAX_INCOMPLETE_IN_A_ROW:
                raise SensorTimeout(f"{incomplete} GNFD answers in a row from {self.config.url} lacked a RADC")

    def _note_counter(self, counter: int) -> None:
        last = self._last_counter
        if last is not None:
            gap = (counter - last - 1) & 0xFFFFFFFF
            if 0 < gap < 0x80000000:
                self.counters.dropped += gap
                self._reset_assembly()
        self._last_counter = counter

    def _reset_assembly(self) -> None:
        self.counters.discarded_ramps += len(self._ramps)
        self._ramps = []

    def read_frame(self) -> RawFrame:
        """Read ramps until ``ramps_per_frame`` consecutive ones make a frame."""
        rpf = self.config.ramps_per_frame
        while True:
            counter, t_ns, words = self.read_ramp()
            self._ramps.append((counter, t_ns, words))
            if len(self._ramps) < rpf:
                continue
            ramps, self._ramps = self._ramps, []
            data = adc_to_complex(np.stack([w for _, _, w in ramps]))  # (R, 256, 2)
            frame = RawFrame(
                sensor_id=self.config.sensor_id,
                seq=self._seq,
                timestamp_ns=ramps[0][1],
                data=data.reshape(rpf * RADC_LAYOUT.samples, RADC_LAYOUT.receivers).astype(np.complex64),
                counters=tuple(c for c, _, _ in ramps),
                config_id=self._config_id,
            )
            self._seq += 1
            self.counters.frames += 1
            return frame

    def frames(self, limit: int | None = None) -> Iterator[RawFrame]:
        """Frames until ``limit`` (None = forever) or close(). With ``reconnect``, errors
        lead to a reconnect with backoff (counted) instead of ending the stream."""
        n = 0
        while limit is None or n < limit:
            if self._closed:
                return
            if self._port is None:
                self._reconnect()  # raises LinkError once reconnect_timeout_s is spent
                continue
            try:
                frame = self.read_frame()
            except SensorError as exc:
                if not self.config.reconnect or self._closed:
                    raise
                log.warning("%s; reconnecting", exc)
                self._drop_port()
                continue
            yield frame
            n += 1

    def __iter__(self) -> Iterator[RawFrame]:
        return self.frames()

    def stats(self) -> dict[str, dict[str, int]]:
        """The driver counters of this sensor, keyed by its id."""
        return {self.config.sensor_id: self.counters.as_dict()}

    def _reconnect(self) -> None:
        cfg = self.config
        delay = cfg.backoff_s
        start = time.monotonic()
        while not self._closed:
            try:
                self._connect()
                return
            except SensorError as exc:
                if cfg.reconnect_timeout_s is not None and time.monotonic() - start > cfg.reconnect_timeout_s:
                    raise LinkError(f"could not reconnect to {cfg.url} within {cfg.reconnect_timeout_s} s: {exc}") from exc
                log.debug("reconnect to %s failed (%s); next try in %.2f s", cfg.url, exc, delay)
                time.sleep(delay)
                delay = min(delay * 2, cfg.max_backoff_s)


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
