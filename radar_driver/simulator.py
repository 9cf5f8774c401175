"""A simulated K-MD2: the device's protocol logic (bytes in, bytes out, no I/O) and the
links that serve it on a pseudo-terminal or a TCP port.

The device answers ``INIT`` / ``GNFD`` / ``GBYE`` like the sensor: ``RESP`` first (with
an error code for an unknown command or a bad parameter), then for ``GNFD`` the
selected ``RADC`` and ``DONE`` with its frame counter. It speaks a sensor profile
(:mod:`.profile`): in the default one a ``RADC`` is one ramp and a frame takes
``ramps_per_frame`` of them; in a profile of many chirps per ``RADC`` (``kmd2-cube256``)
one ``RADC`` is one measurement. Chirps come from the scene through the paper's model
and the scene's receiver front end (DC offset, leakage, receiver and I/Q imbalance:
:mod:`.frontend`), with noise and the profile's ADC, at ``rate_hz`` frames per second
(0 = as fast as polled). The azimuth pair carries the scene; any other receiver (the
K-MD2's elevation one) sees receiver 1's signal, front end included, with its own noise. The azimuth noise of the first
``ramps_per_frame`` chirps of a ``RADC`` is drawn from the scene's noise stream, so
that frames built from them equal the in-process simulated sensor's with the same seed.
The device measures on its own clock: a host that polls late finds the counter
advanced, and the gap is what a real sensor shows for dropped frames.

The links (:mod:`.simlinks`) serve it on a pty or TCP. On a pty the device reads the host's line speed from the terminal settings and, like
a real UART, does not understand bytes sent at another speed than its own. With
``line_rate`` it also takes as long as a real serial line to send (11 bits a byte at
8E1: a 2 080-byte ``RADC`` takes 11 ms at 2 Mbaud, 199 ms at 115200); without it a pty
delivers at once.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import ConfigError, LinkDown
from .options import nonneg_float, option, pos_int, prob
from .profile import DEFAULT_PROFILE, SensorProfile
from .protocol import (
    Done,
    Gbye,
    Gnfd,
    Init,
    OtherMessage,
    Radc,
    Resp,
    RespCode,
    StreamDecoder,
    encode,
)
from .scene import SIM_RATE_HZ, SimScene, check_sim_rate, frame_ramp_times_s
from .simlinks import PtyLink, TcpLink

log = logging.getLogger("qradar.sim")


#: the radar fields a simulated K-MD2 takes from the sensor (its profile and the K-MD2's
#: RadarConfig defaults), which a scene's [radar] may not change: its frames carry that radar's
#: config id (samples a ramp, ramps and their spacing are checked against the profile apart)
SENSOR_RADAR_FIELDS = ("f0_hz", "bandwidth_hz", "c_m_s", "d_m")


@dataclass(frozen=True)
class SimFaults:
    """Fault injection. Probabilities are per message (garbage: a burst of 1 to
    ``garbage_max_bytes`` random bytes before a message; truncate: a RADC cut short;
    skip_done: the DONE counter jumps by 1 to 3). ``skip_frames_after``: once, after
    that many frames, the counter jumps over ``skip_frames`` whole frames (what a host
    that stalled that long finds). ``disconnect_after_frames``: drop the link once after
    that many frames and bring it back after ``reconnect_after_s``."""

    garbage_prob: float = option(0.0, "garbage burst before a message", flag="--garbage", metavar="P", parse=prob)
    garbage_max_bytes: int = 64
    truncate_prob: float = option(0.0, "RADC cut short", flag="--truncate", metavar="P", parse=prob)
    skip_done_prob: float = option(0.0, "DONE counter jumps", flag="--skip-done", metavar="P", parse=prob)
    skip_frames_after: int | None = None
    skip_frames: int = 1
    disconnect_after_frames: int | None = option(None, "drop the link after N frames", flag="--disconnect-after",
                                                 metavar="N", parse=pos_int)
    reconnect_after_s: float = option(1.0, "link back after T s", flag="--reconnect-after", metavar="T",
                                      parse=nonneg_float)

    def __post_init__(self) -> None:
        for name in ("garbage_prob", "truncate_prob", "skip_done_prob"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.0 <= v <= 1.0):
                raise ConfigError(f"SimFaults.{name}={v!r} must be a probability in [0, 1]")
        if not (isinstance(self.garbage_max_bytes, int) and self.garbage_max_bytes >= 1):
            raise ConfigError(f"SimFaults.garbage_max_bytes={self.garbage_max_bytes!r} must be an integer >= 1")
        for name in ("skip_frames_after", "disconnect_after_frames"):
            n = getattr(self, name)
            if n is not None and not (isinstance(n, int) and n >= 1):
                raise ConfigError(f"SimFaults.{name}={n!r} must be an integer >= 1")
        if not (isinstance(self.skip_frames, int) and self.skip_frames >= 1):
            raise ConfigError(f"SimFaults.skip_frames={self.skip_frames!r} must be an integer >= 1")
        if not (math.isfinite(self.reconnect_after_s) and self.reconnect_after_s >= 0):
            raise ConfigError(f"SimFaults.reconnect_after_s={self.reconnect_after_s!r} must be >= 0")


class RecentEvents:
    """The last ``maxlen`` events of a device, oldest first: a ring, so a long run keeps a
    bounded memory. Reads (iteration, indexing, slicing, ``in``) see a snapshot, safe
    while the device's thread appends."""

    def __init__(self, maxlen: int):
        self._ring: deque[tuple[str, float | None]] = deque(maxlen=maxlen)
        self._lock = threading.Lock()

    def append(self, event: tuple[str, float | None]) -> None:
        with self._lock:
            self._ring.append(event)

    def snapshot(self) -> list[tuple[str, float | None]]:
        with self._lock:
            return list(self._ring)

    @property
    def maxlen(self) -> int:
        return self._ring.maxlen

    def __len__(self) -> int:
        return len(self._ring)

    def __iter__(self):
        return iter(self.snapshot())

    def __getitem__(self, i):
        return self.snapshot()[i]

    def __contains__(self, event) -> bool:
        return event in self.snapshot()

    def __repr__(self) -> str:
        return f"RecentEvents({self.snapshot()!r}, maxlen={self.maxlen})"


@dataclass
class Reply:
    """Bytes to write at monotonic time ``due_s`` (None = now); ``disconnect`` asks the
    link to go down after writing."""

    data: bytes
    due_s: float | None = None
    disconnect: bool = False


@dataclass
class SimulatedKMD2:
    """The K-MD2's protocol logic. ``receive(bytes, host_baud)`` -> replies."""

    scene: SimScene
    rate_hz: float = SIM_RATE_HZ
    faults: SimFaults = field(default_factory=SimFaults)
    seed: int = 0
    profile: SensorProfile = DEFAULT_PROFILE

    #: lateness of the simulator's own writes that hold_clock lets pass (a scheduler tick)
    LATE_TOLERANCE_S = 0.002
    #: events kept in ``events`` (the most recent); ``event_counts`` counts all since start
    EVENTS_KEPT = 1024

    def __post_init__(self) -> None:
        check_sim_rate(self.rate_hz, zero="0 = as fast as polled")
        lay, radar = self.profile.radc, self.scene.radar
        if lay.samples != radar.samples_per_ramp:
            raise ConfigError(f"profile {self.profile.name} has {lay.samples} samples a chirp; "
                              f"the scene's radar {radar.samples_per_ramp}")
        rpf = radar.ramps_per_frame
        if lay.chirps > 1 and rpf > lay.chirps:
            raise ConfigError(f"a frame of {rpf} ramps does not fit the {lay.chirps} chirps of a "
                              f"{self.profile.name} RADC")
        if lay.chirps == 1 and not math.isclose(lay.chirp_interval_s, radar.ramp_interval_s, rel_tol=1e-9):
            raise ConfigError(f"the scene's ramps are {radar.ramp_interval_s:g} s apart ([radar] ramp_interval_s), "
                              f"profile {self.profile.name}'s chirps {lay.chirp_interval_s:g} s (chirp_interval_s): "
                              "the simulated sensor measures on its profile's, the decoder's velocities on the "
                              "scene's; make them agree")
        sensor = self.profile.radar(rpf)
        differ = [n for n in SENSOR_RADAR_FIELDS if not math.isclose(getattr(radar, n), getattr(sensor, n),
                                                                     rel_tol=1e-9)]
        if differ:  # its frames would carry the K-MD2's radar config id, their physics not
            said = {"d_m": "antenna_spacing_m"}
            scene_has = ", ".join(f"{said.get(n, n)} = {getattr(radar, n)!r}" for n in differ)
            raise ConfigError(f"the scene's [radar] {scene_has} is not what a simulated K-MD2 measures (profile "
                              f"{self.profile.name}: " + ", ".join(f"{said.get(n, n)} = {getattr(sensor, n)!r}"
                                                                   for n in differ) + "); leave it out of the scene")
        self.decoder = StreamDecoder(self.profile)
        self.baud = self.profile.startup_baud
        self.counter = -1  # frame counter of the last RADC sent
        self.radcs_sent = 0
        #: (kind, value) of the latest commands and faults, at most EVENTS_KEPT; counts of every
        #: kind since start in ``event_counts``, the RADCs the counter jumped over in ``skipped_radcs``
        self.events = RecentEvents(self.EVENTS_KEPT)
        self.event_counts: Counter[str] = Counter()
        self.skipped_radcs = 0
        self._skipped_once = False
        self._noise_rng = np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(0,)))
        self._fault_rng = np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(1,)))
        self._extra_rng = np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(2,)))
        self._t0: float | None = None
        self._disconnected_once = False
        #: RADCs a frame takes, and RADCs a second the sensor measures (0 = when polled)
        self.radcs_per_frame = rpf if lay.chirps == 1 else 1
        self.radc_rate_hz = self.rate_hz * self.radcs_per_frame
        self.late_writes = 0
        self.late_s = 0.0
        #: the frame being measured (device frame index) and the seconds its scene is later
        #: than its device time (``late_s`` when its first RADC was measured: hold_clock)
        self._scene_frame: int | None = None
        self._scene_late_s = 0.0

    def _event(self, kind: str, value: float | None) -> None:
        self.events.append((kind, value))
        self.event_counts[kind] += 1

    def hold_clock(self, late_s: float) -> None:
        """The process that plays the sensor wrote a reply ``late_s`` after it was due
        (it was not scheduled: a loaded host). A real K-MD2 measures on its own clock
        and would have sent it on time, so the device clock stands still for that long
        instead of counting the host's next GNFD late (a drop that is the simulator's,
        not the driver's). The scene does not stand still: the world went on meanwhile,
        so the frames measured after show it ``late_s`` later than their device time (a
        moving target is where it is when the host's clock stamps the frame, as with a
        real sensor; :meth:`measure`). Counted in ``late_writes`` / ``late_s``."""
        if late_s > self.LATE_TOLERANCE_S and self._t0 is not None:
            self._t0 += late_s
            self.late_writes += 1
            self.late_s += late_s
            self._event("LATE", round(late_s * 1e3, 2))

    # -- link events --------------------------------------------------------------------
    def link_reset(self, power_cycle: bool) -> None:
        """The link went down. ``power_cycle``: the sensor restarts at 115200 baud."""
        self.decoder.reset()
        if power_cycle:
            self.baud = self.profile.startup_baud
        self._event("LINK_RESET", self.baud)

    # -- bytes in, bytes out ---------------------------------------------------------------
    def receive(self, data: bytes, host_baud: int | None = None, now_s: float | None = None) -> list[Reply]:
        if host_baud is not None and host_baud != self.baud:
            self._event("BAUD_MISMATCH", host_baud)
            return []  # a UART at another speed sees noise, not bytes
        now = time.monotonic() if now_s is None else now_s
        replies: list[Reply] = []
        for msg in self.decoder.feed(data):
            replies.extend(self._handle(msg, host_baud, now))
        return replies

    def _handle(self, msg, host_baud: int | None, now: float) -> list[Reply]:
        if isinstance(msg, Init):
            self._event("INIT", host_baud)
            codes = self.profile.baud_codes
            if msg.baud_code not in codes:
                return [self._reply(Resp(RespCode.INVALID_PARAMETER))]
            reply = self._reply(Resp(RespCode.OK))
            self.baud = codes[msg.baud_code]
            self._event("SWITCH", self.baud)
            return [reply]
        if isinstance(msg, Gbye):
            self._event("GBYE", host_baud)
            reply = self._reply(Resp(RespCode.OK))
            self.baud = self.profile.startup_baud
            return [reply]
        if isinstance(msg, Gnfd):
            self._event("GNFD", host_baud)
            if msg.mask & ~self.profile.frame_mask or msg.mask == 0:
                return [self._reply(Resp(RespCode.INVALID_PARAMETER))]
            return [self._reply(Resp(RespCode.OK))] + self._ramp_replies(msg.mask, now)
        # a sensor-to-host message or an unknown frame sent to the sensor
        self._event("UNKNOWN", None)
        return [self._reply(Resp(RespCode.UNKNOWN_COMMAND))]

    def _ramp_replies(self, mask: int, now: float) -> list[Reply]:
        rng = self._fault_rng
        if self.radc_rate_hz > 0:
            if self._t0 is None:
                self._t0 = now
            measured = math.ceil((now - self._t0) * self.radc_rate_hz - 1e-9)
            index = max(self.counter + 1, measured)
            due = self._t0 + index / self.radc_rate_hz
        else:
            index, due = self.counter + 1, None
        n = self.faults.skip_frames_after
        if n is not None and not self._skipped_once and self.radcs_sent >= n * self.radcs_per_frame:
            self._skipped_once = True  # whole frames go by unpolled: the device clock ran on
            skip = self.faults.skip_frames * self.radcs_per_frame
            index += skip
            if self.radc_rate_hz > 0:
                self._t0 -= skip / self.radc_rate_hz
            self._event("SKIP_DONE", skip)
            self.skipped_radcs += skip
        measured_index = index
        if self.faults.skip_done_prob and rng.random() < self.faults.skip_done_prob:
            skip = int(rng.integers(1, 4))
            index += skip
            self._event("SKIP_DONE", skip)
            self.skipped_radcs += skip
        self.counter = index
        out = []
        bits = self.profile.gnfd_bits
        if mask & bits["RADC"]:
            radc = self._reply(Radc(self.measure(measured_index), self.profile.radc), due)
            if self.faults.truncate_prob and rng.random() < self.faults.truncate_prob:
                radc.data = radc.data[: int(rng.integers(1, len(radc.data)))]
                self._event("TRUNCATED", index)
            out.append(radc)
        for name, bit in bits.items():
            if name != "RADC" and mask & bit:
                out.append(self._reply(OtherMessage(name.encode()), due))
        out.append(self._reply(Done(index & 0xFFFFFFFF), due))
        self.radcs_sent += 1
        n = self.faults.disconnect_after_frames
        if n is not None and not self._disconnected_once and self.radcs_sent >= n * self.radcs_per_frame:
            self._disconnected_once = True
            out[-1].disconnect = True
            self._event("DISCONNECT", index)
        return out

    def measure(self, index: int) -> np.ndarray:
        """The ADC words (receivers, chirps, samples, 2) of RADC ``index``: the scene's
        chirps at their times through its front end, noise, the profile's ADC. Their times:
        the device clock's, plus the seconds it was held (:meth:`hold_clock`) when the
        frame's first RADC was measured (the world does not wait for a late simulator; a
        frame's ramps stay the profile's chirp interval apart)."""
        lay, scene = self.profile.radc, self.scene
        chirps = lay.chirps
        frame = index // self.radcs_per_frame
        if frame != self._scene_frame:
            self._scene_frame, self._scene_late_s = frame, self.late_s
        # the chirps' places in their frame, spaced by the profile's chirp interval
        start = (index % self.radcs_per_frame) * chirps
        t_s = frame_ramp_times_s(frame, start + np.arange(chirps), self.rate_hz,
                                 lay.chirp_interval_s) + self._scene_late_s
        clean = scene.clean_ramps(t_s)  # (chirps, N, 2)
        first = min(chirps, scene.radar.ramps_per_frame)
        azimuth = clean + np.concatenate([scene.noise(first, self._noise_rng),
                                          scene.noise(chirps - first, self._extra_rng)])
        z = np.empty((chirps, lay.samples, lay.receivers), complex)
        for rx in range(lay.receivers):
            if rx in lay.azimuth:
                z[..., rx] = azimuth[..., lay.azimuth.index(rx)]
            else:  # the elevation receiver, at elevation 0: antenna 1's signal, its own noise
                z[..., rx] = clean[..., 0] + scene.noise(chirps, self._extra_rng)[..., 0]
        return lay.from_complex(z)

    def _reply(self, msg, due: float | None = None) -> Reply:
        data = encode(msg)
        f = self.faults
        if f.garbage_prob and self._fault_rng.random() < f.garbage_prob:
            n = int(self._fault_rng.integers(1, f.garbage_max_bytes + 1))
            data = self._fault_rng.integers(0, 256, n, dtype=np.uint8).tobytes() + data
        return Reply(data, due)


#: bits on the line per byte at 8E1: start, 8 data, parity, stop
BITS_PER_BYTE = 11


class SimulatorServer:
    """Serves a simulated K-MD2 on a pty (``link_path``) and/or TCP (``tcp_port``, 0 =
    any free port) until :meth:`stop`. Each link has its own device state."""

    def __init__(
        self,
        scene: SimScene,
        link_path: str | Path | None = None,
        tcp_port: int | None = None,
        rate_hz: float = SIM_RATE_HZ,
        faults: SimFaults | None = None,
        seed: int = 0,
        profile: SensorProfile = DEFAULT_PROFILE,
        line_rate: bool = False,
        hold_clock_when_late: bool = False,
    ):
        if link_path is None and tcp_port is None:
            raise ConfigError("SimulatorServer needs a pty link path or a TCP port")
        self.links: list[PtyLink | TcpLink] = []
        if link_path is not None:
            self.links.append(PtyLink(link_path))
        if tcp_port is not None:
            self.links.append(TcpLink(tcp_port))
        self.devices = [SimulatedKMD2(scene, rate_hz, faults or SimFaults(), seed, profile) for _ in self.links]
        self.line_rate = line_rate
        self.hold_clock_when_late = hold_clock_when_late
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.errors: list[BaseException] = []

    @property
    def tcp_port(self) -> int | None:
        return next((lk.port for lk in self.links if isinstance(lk, TcpLink)), None)

    def start(self) -> "SimulatorServer":
        for link, dev in zip(self.links, self.devices):
            link.open()
            t = threading.Thread(target=self._serve, args=(link, dev), name=f"sim-{type(link).__name__}", daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout_s)
        for link in self.links:
            link.close()

    def __enter__(self) -> "SimulatorServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Block until stopped (True) or ``timeout_s`` passed (False)."""
        return self._stop.wait(timeout_s)

    def _serve(self, link, dev: SimulatedKMD2) -> None:
        line_free = 0.0  # monotonic s when the serial line is free again (line_rate)
        try:
            while not self._stop.is_set():
                try:
                    data = link.read(0.05)
                except LinkDown:
                    if isinstance(link, TcpLink) and link.server is not None:
                        dev.link_reset(power_cycle=False)
                        continue
                    raise
                if not data:
                    continue
                baud = link.host_baud()
                last_due = None  # when the last timed reply (DONE) of this answer was due
                for reply in dev.receive(data, baud):
                    due = reply.due_s
                    if self.line_rate and baud:  # the last byte arrives a line time after the line is free
                        start = max(due or 0.0, line_free, time.monotonic())
                        due = line_free = start + len(reply.data) * BITS_PER_BYTE / baud
                    if due is not None:
                        delay = due - time.monotonic()
                        if delay > 0 and self._stop.wait(delay):
                            return
                    if not link.write(reply.data):
                        log.warning("host is not reading: dropped %d bytes", len(reply.data))
                    elif due is not None:
                        last_due = due
                    if reply.disconnect:
                        self._disconnect(link, dev)
                        last_due = None
                        break
                if last_due is not None and self.hold_clock_when_late:
                    dev.hold_clock(time.monotonic() - last_due)
        except BaseException as exc:  # surfaced through .errors, never silent
            if not self._stop.is_set():
                log.exception("simulator link %s failed", link)
                self.errors.append(exc)

    def _disconnect(self, link, dev: SimulatedKMD2) -> None:
        log.info("fault: link down for %.2f s", dev.faults.reconnect_after_s)
        link.close()
        if self._stop.wait(dev.faults.reconnect_after_s):
            return
        link.open()
        dev.link_reset(power_cycle=True)
