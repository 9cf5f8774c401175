"""The K-MD2 driver session: polls the sensor from a reader thread, hands frames to a
consumer, and reconnects.

Built as pyserial's ``ReaderThread`` is on its ``Protocol``: the link
(:mod:`.link`: the port opened by its URL's kind, and errors in words), the command
exchange over it (:mod:`.connection`: ``INIT`` and the line-speed switch, ``GBYE``) and
the frame assembler (:mod:`.assembly`: messages in, frames and counters out, no I/O)
are each testable alone; the session owns the thread, the polling and the reconnect.

A dedicated reader thread owns the port once the session is open. It keeps one
``GNFD`` outstanding: the next goes out as soon as a ``DONE`` arrives, before the frame
is assembled and handed on, so nothing the consumer does (or the GIL it holds) sits
between one answer and the next request. Frames wait in a bounded queue; when the
consumer falls that far behind the reader stops asking, and the sensor's counter
counts what is lost.

Errors are typed (:class:`SensorTimeout`, :class:`SensorResponseError`,
:class:`LinkError`) and their messages say what to check (permission: the ``dialout``
group; silence: the line speed or the device; an echo: not a K-MD2). With
``reconnect`` the reader reconnects with backoff and re-INITs on any of them, logging
one warning per attempt with the time since the last frame. ``GBYE`` on close and
before giving up a link, so that the next session finds the sensor at its start-up
speed; close is idempotent.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np
import serial

from .assembly import DriverCounters, FrameAssembler, Taken
from .connection import SensorConnection
from .errors import ConfigError, LinkError, RadarError, SensorError, SensorResponseError, SensorTimeout, SetupError
from .limits import check_sensor_id
from .link import LinkKind, SerialLink, busy_text, describe_device, link_kind, open_error, port_url
from .model import RadarConfig
from .options import option, pos_float, pos_int
from .profile import CHIRP_SELECT, DEFAULT_PROFILE_NAME, SensorProfile, packaged_profiles, resolve_profile
from .protocol import Done, Gnfd, Radc, encode
from .source import RawFrame

__all__ = [
    "DEFAULT_FAST_BAUD", "DriverCounters", "LinkError", "LinkKind", "SensorResponseError", "SensorSession",
    "SensorTimeout", "SessionConfig", "busy_text", "describe_device", "link_kind", "open_error", "port_url",
    "save_frames_npz", "Done", "Radc",
]

log = logging.getLogger("qradar.driver")

#: the rate after INIT on a link that can change speed, unless told otherwise
DEFAULT_FAST_BAUD = 2_000_000


#: a link that stays down: a warning for each of its first DOWN_LINES_FIRST failed reconnect
#: attempts, then one every DOWN_LINE_EVERY_S (a sensor unplugged for an hour: 35 lines, not 1 800)
DOWN_LINES_FIRST = 6
DOWN_LINE_EVERY_S = 120.0


def say_down(url: str, exc: Exception, attempt: int, last_frame_mono: float | None, delay_s: float,
             said: tuple[float, str] | None) -> tuple[float, str] | None:
    """The warning of failed reconnect ``attempt`` to ``url`` when due (the first
    DOWN_LINES_FIRST, then one every DOWN_LINE_EVERY_S or when the error changes); returns
    when one was last said and its error (monotonic s; ``said`` when none is now)."""
    now = time.monotonic()
    if (attempt > DOWN_LINES_FIRST and said is not None and now - said[0] < DOWN_LINE_EVERY_S
            and str(exc) == said[1]):
        return said
    since = "no frame yet" if last_frame_mono is None else f"{now - last_frame_mono:.1f} s since the last frame"
    then = f" (then a line every {DOWN_LINE_EVERY_S:g} s while it stays down)" if attempt == DOWN_LINES_FIRST else ""
    log.warning("%s is down (%s); reconnect attempt %d, %s; next in %.2f s%s", url, exc, attempt, since, delay_s, then)
    return now, str(exc)


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

    url: str = option(help="pyserial URL or device path", flag="--port", required=True)
    baud: int | None = option(None, "rate after INIT (115200, 460800, 921600, 2000000, 3000000); default "
                              f"{DEFAULT_FAST_BAUD}, except on socket:// (Ethernet, raw ser2net), which stays at the "
                              "start-up 115200")
    ramps_per_frame: int = option(2, "ramps per frame (M = 256 x ramps)", flag="--ramps", parse=pos_int)
    timeout_s: float = option(0.5, "seconds to wait for a GNFD answer", flag="--timeout", parse=pos_float)
    reconnect: bool = True
    backoff_s: float = 0.05
    max_backoff_s: float = 2.0
    reconnect_timeout_s: float | None = None
    sensor_id: str = option("kmd2", "sensor id in the zenoh keys", flag="--sensor-id")
    profile: SensorProfile | str | None = option(
        None, f"sensor profile (RADC layout, baud codes): {', '.join(packaged_profiles())} or a TOML file (default: "
        f"{DEFAULT_PROFILE_NAME})", kinds=frozenset({"str"}))
    chirp_select: str = option("first", "with several chirps per RADC: a frame takes the first --ramps chirps, or "
                               "every k-th", choices=CHIRP_SELECT)
    queue_frames: int = 256
    outstanding: int = option(1, "GNFD requests kept in flight: 2 lets the sensor hold one while the host is late "
                              "(assumes the K-MD2 queues a second GNFD; the simulator does)", choices=(1, 2), parse=int)
    #: connections in a row in which the sensor answered but no frame assembled, before a
    #: session that never had one gives up with a SetupError naming the profile (None: never)
    barren_connections: int | None = 5

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
        if self.barren_connections is not None and not (isinstance(self.barren_connections, int)
                                                        and self.barren_connections >= 1):
            raise ConfigError(f"barren_connections={self.barren_connections!r} must be an integer >= 1 or None")

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
        """The radar configuration of this session's frames (its profile's samples and ramp
        spacing, :meth:`~radar_driver.profile.SensorProfile.radar`)."""
        return self.profile.radar(self.ramps_per_frame, self.chirp_select)



class SensorSession:
    """``with SensorSession(SessionConfig(url)) as s: for frame in s.frames(): ...``

    A :class:`~radar_driver.source.FrameSource`: a K-MD2 (real or simulated) on a
    serial link. :meth:`open` connects in the caller (and raises on failure); the
    reader thread then owns the port until :meth:`close`."""

    READ_TIMEOUT_S = SerialLink.READ_TIMEOUT_S
    DRAIN_S = 0.3  # at stop, how long the reader waits for the answer to its outstanding GNFD

    def __init__(self, config: SessionConfig, port_factory: Callable[..., serial.SerialBase] = serial.serial_for_url):
        self.config = config
        self.profile: SensorProfile = config.profile
        self.counters = DriverCounters()
        self.assembler = FrameAssembler(self.profile, config.ramps_per_frame, config.chirp_select,
                                        config.sensor_id, config.url, self.counters)
        self._conn = SensorConnection(config, self.assembler, self.counters, port_factory)
        self._closed = False
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
        self._last_frame_mono: float | None = None
        self._barren = 0  # connections in a row that ended without a frame
        self._connected_at = 0  # counters.frames when the port last connected

    # -- life cycle -----------------------------------------------------------------------
    def __enter__(self) -> "SensorSession":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def is_open(self) -> bool:
        return self._conn.is_open

    def open(self) -> None:
        """Open the port and INIT the sensor (in the caller; raises a SensorError on
        failure), then start the reader thread."""
        self._closed = False
        self._stop.clear()
        if not self._conn.is_open:
            self._connect()
        self._start_reader()

    def probe(self) -> None:
        """Open the port as :meth:`open` would (a device path exclusively) and close it at
        once, sending nothing: a LinkError saying why it cannot be opened (and who holds a
        busy device), for a caller that checks its ports before it starts anything. Not on
        an open session."""
        if self._conn.is_open:
            raise LinkError(f"{self.config.url} is open in this session already")
        port = self._conn.link.open_port()
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
        self._conn.goodbye()

    def _connect(self) -> None:
        self._in_flight = 0
        self._retries = 0
        self._conn.connect()
        self._connected_at = self.counters.frames

    # -- I/O (one method each, so that a probe can watch them) ----------------------------------
    @property
    def _inbox(self):
        return self._conn.inbox

    def _write(self, data: bytes) -> None:
        self._conn.write(data)

    def _fill_inbox(self) -> None:
        """One read of the port (blocks at most READ_TIMEOUT_S) into the inbox."""
        self._conn.fill()

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
        coming = (self.assembler.held + self._in_flight) // self.config.radcs_per_frame
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
                    if not self._in_flight or not self._conn.is_open or now > drain_until:
                        return
                if not self._conn.is_open and not self._reconnect():  # LinkError once reconnect_timeout_s is spent
                    return
                frames_before = self.counters.frames
                try:
                    self._step()
                except SensorError as exc:
                    self._in_flight = 0
                    if not cfg.reconnect or self._stop.is_set():
                        self._conn.goodbye()
                        raise
                    self._conn.goodbye()
                    self._note_barren(exc, frames_before)
                    log.warning("%s; reconnecting", exc)
        except BaseException as exc:  # handed to the consumer, never silent
            self._queue.put(exc)
        finally:
            self._queue.put(None)  # the end of the stream

    def _step(self) -> None:
        """One read of the port and what it completes."""
        self._top_up()
        self._fill_inbox()
        inbox = self._inbox
        while inbox:
            self._handle(inbox.popleft())
        if self._in_flight and time.monotonic() >= self._deadline:
            self.counters.timeouts += 1
            self._retries += 1
            if self._retries >= 2 or self._stop.is_set():
                raise SensorTimeout(f"no complete RADC from {self.config.url} after 2 GNFD polls of "
                                    f"{self.config.timeout_s:.2f} s; {self.assembler.decoder.stats.skipped_bytes} "
                                    f"bytes skipped in all")
            self._in_flight = 0  # the answers are lost: ask once more
            self._top_up()

    def _note_barren(self, exc: SensorError, frames_before: int) -> None:
        """A connection lost after the sensor answered: count it if it brought no frame (the
        frames since the connect: ``_connected_at``); once ``barren_connections`` in a row
        have, and the session never had a frame, a SetupError: the sensor talks, but its
        frames do not assemble in this profile's layout."""
        if self.counters.frames > self._connected_at or self.counters.frames > frames_before:
            self._barren = 0
            return
        self._barren += 1
        limit = self.config.barren_connections
        if limit is None or self._barren < limit or self._last_frame_mono is not None:
            return
        p = self.profile
        stats = self.assembler.decoder.stats
        raise SetupError(
            f"no frame assembled from {self.config.url} in {self._barren} connections: the sensor answers, but "
            f"not in the layout of sensor profile {p.name!r} (RADC of {p.radc.payload_len} bytes; "
            f"{stats.skipped_bytes} bytes skipped, last: {exc}). The likely cause is the profile: give the "
            f"sensor's (run --sensor URL,id=NAME,profile=..., drive --profile; packaged: "
            f"{', '.join(packaged_profiles())}), or record the link with `qradar capture` and read it with "
            f"`qradar inspect` (docs/sensor.md)")

    def _handle(self, m) -> None:
        """One message: an answer (a DONE) lets the next GNFD out before its frame is built."""
        taken = self.assembler.take(m)
        if taken is Taken.NOTHING:
            return
        self._in_flight = max(0, self._in_flight - 1)
        self._retries = 0
        self._deadline = time.monotonic() + self.config.timeout_s
        self._top_up()  # the next request first, then the frame
        if taken is Taken.FRAME:
            frame = self.assembler.frame()
            self._last_frame_mono = time.monotonic()
            with self._lock:  # _produced and the queue change together: frames() reads both
                self._produced += 1
                self._queue.put(frame)

    def _reconnect(self) -> bool:
        """Connect again with backoff (warnings with the time since the last frame, :func:`say_down`;
        counted: link_losses, down_ms and, while it lasts, link_down). True once connected,
        False at a stop; LinkError once reconnect_timeout_s is spent."""
        cfg, c = self.config, self.counters
        delay, start, attempt, said = cfg.backoff_s, time.monotonic(), 0, None
        c.link_losses, c.link_down = c.link_losses + 1, 1
        try:
            while not self._stop.is_set():
                attempt += 1
                try:
                    self._connect()
                    c.link_down = 0
                    if attempt > 1:
                        log.warning("%s: reconnected after %d attempts, %.1f s without a link", cfg.url, attempt,
                                    time.monotonic() - start)
                    return True
                except SensorError as exc:
                    if cfg.reconnect_timeout_s is not None and time.monotonic() - start > cfg.reconnect_timeout_s:
                        raise LinkError(f"could not reconnect to {cfg.url} within {cfg.reconnect_timeout_s} s: "
                                        f"{exc}") from exc
                    said = say_down(cfg.url, exc, attempt, self._last_frame_mono, delay, said)
                    if self._stop.wait(delay):
                        break
                    delay = min(delay * 2, cfg.max_backoff_s)
            return False
        finally:
            c.down_ms += round((time.monotonic() - start) * 1e3)

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
