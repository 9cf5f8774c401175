"""What every live view of the stream shares: the Foxglove server (:mod:`qradar.view`) and
the web page (:mod:`qradar.web`).

:class:`LiveView` is a node like the others (:class:`pipeline.nodes.intake.ProcessingNode`):
it subscribes ``<prefix>/*/targets``, ``<prefix>/*/tracks``, ``<prefix>/*/health`` and,
when range profiles are wanted, ``<prefix>/*/quantized``; zenoh's callback copies a payload
into a bounded queue (a full queue drops and counts it in ``drops``; a sensor's quantized
frames beyond ``profile_rate_hz`` are skipped before the copy), and one worker thread
decodes each message once, checks its sensor id against its key and hands it to the
view's ``show_*`` methods. A malformed payload is counted (``decode_errors``), logged at
most once a second, and skipped; the view keeps running.

Also here: the views' configuration (:class:`ViewConfig`), the range profile of a
quantized frame (:func:`range_profile`) and the sensors' poses in the world
(:func:`load_poses`, :func:`to_world`)."""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass, field, replace

import numpy as np
import zenoh

from pipeline.bus.session import BusConfig
from pipeline.dsp import profile as dsp_profile
from pipeline.dsp.profile import PROFILE_FLOOR, to_db  # noqa: F401 (the views' names)
from pipeline.dsp.quantize import dequantize
from pipeline.errors import ParameterError, PipelineError, WireError
from pipeline.nodes.budget import IntakeBudget
from pipeline.nodes.counters import UNKNOWN_SENSOR
from pipeline.nodes.intake import ProcessingNode, QueueConfig, QueuedFrame
from pipeline.nodes.transport import Transport
from pipeline.wire import (
    HEADER_LEN,
    HealthMsg,
    QuantizedFrameMsg,
    TargetsMsg,
    TracksMsg,
    check_sensor_id,
    decode_quantized,
    peek_seq,
)
from pipeline.wire.shared import DecodedOnce, decoder
from radar_driver.errors import RadarError
from radar_driver.model import RadarConfig, polar_to_xy
from radar_driver.options import OptionValueError, option, pos_int
from radar_driver.scene import SimScene

#: names of nodes in health messages: they become topic names and keys of the views' state
NODE_NAME = re.compile(r"[A-Za-z0-9_-]{1,32}")
#: nodes per sensor at most (one health channel or table row each)
MAX_NODES_PER_SENSOR = 16


class ViewError(PipelineError):
    """A view's server could not start (a busy port, an unknown host)."""


def tcp_port(text: str) -> int:
    """A TCP port to listen on: 0 (any free one) to 65535."""
    try:
        v = int(text)
    except ValueError:
        raise OptionValueError("is not an integer") from None
    if not 0 <= v <= 65535:
        raise OptionValueError("must be a TCP port in [0, 65535] (0: any free port)")
    return v


@dataclass(frozen=True)
class ViewConfig:
    """host: the address the view's server binds (127.0.0.1: this host only). port: its
    TCP port (0: any free one). profile_rate_hz: range profiles per second and sensor at
    most (0: none, and quantized frames are not subscribed). radar: the base radar
    configuration of the range profiles; frames of 1..max_ramps whole ramps are shown.
    queue_size: bounded input queue (messages). max_sensors: sensors shown at most."""

    host: str = option("127.0.0.1", "address the server binds (default 127.0.0.1: this host only; 0.0.0.0: every "
                       "interface)")
    port: int = option(8765, "Foxglove's TCP port (default 8765; 0: any free port)", parse=tcp_port)
    profile_rate_hz: float = 2.0
    radar: RadarConfig = field(default_factory=RadarConfig)
    max_ramps: int = 16
    queue_size: int = option(256, "bounded input queue (messages)", flag="--queue", parse=pos_int)
    max_sensors: int = 64
    name: str = "qradar"
    #: sensor id -> (x_m, y_m, yaw_deg) of the sensor in the world (:func:`load_poses`)
    poses: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not (isinstance(self.host, str) and self.host.strip()):
            raise ParameterError(f"view host={self.host!r} must be a host name or address, e.g. 127.0.0.1")
        if isinstance(self.port, bool) or not (isinstance(self.port, int) and 0 <= self.port <= 65535):
            raise ParameterError(f"view port={self.port!r} must be an integer in [0, 65535] (0: any free port)")
        if not (isinstance(self.profile_rate_hz, (int, float)) and math.isfinite(self.profile_rate_hz)
                and self.profile_rate_hz >= 0):
            raise ParameterError(f"profile_rate_hz={self.profile_rate_hz!r} must be a finite number >= 0")
        for name in ("max_ramps", "queue_size", "max_sensors"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, int) and v >= 1):
                raise ParameterError(f"{type(self).__name__}.{name}={v!r} must be an integer >= 1")

    def known_configs(self) -> dict[int, RadarConfig]:
        """Radar configs by config id: ``radar`` with 1..max_ramps ramps per frame."""
        return {c.config_id(): c for c in (replace(self.radar, ramps_per_frame=r)
                                           for r in range(1, self.max_ramps + 1))}


def parse_endpoint(text: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """``[HOST:]PORT`` -> (host, port); ``[::1]:8765`` for an IPv6 address."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]") if sep else default_host
    try:
        value = int(port)
    except ValueError:
        raise ParameterError(f"endpoint {text!r} must be [HOST:]PORT, e.g. 127.0.0.1:8765") from None
    if not host or not 0 <= value <= 65535:
        raise ParameterError(f"endpoint {text!r} must be [HOST:]PORT with PORT in [0, 65535]")
    return host, value


# -- range profiles and poses ---------------------------------------------------------------
def profile_magnitude(msg: QuantizedFrameMsg, radar: RadarConfig) -> np.ndarray:
    """|U| of one quantized frame, U = Φ*Z/M (what PBP thresholds; Z the dequantized
    codes, the dither not removed): (N, 2), full-scale units, one column per receiver
    (:func:`pipeline.dsp.profile.profile_magnitude`)."""
    if msg.codes.shape[0] != radar.n_measurements:
        raise WireError(f"quantized frame {msg.seq} of {msg.sensor_id}: M={msg.codes.shape[0]} but its radar "
                        f"config has M={radar.n_measurements}")
    return dsp_profile.profile_magnitude(dequantize(msg.codes[None], msg.delta, msg.bits), radar)[0]


def range_profile(msg: QuantizedFrameMsg, radar: RadarConfig, bins: int | None = None, digits: int = 2) -> dict:
    """The range profile of one quantized frame (:func:`profile_magnitude`) as the fields of
    a profile message (pipeline.wire.fields.PROFILE, JSON-ready): ``range_m`` (the bins, m),
    ``antenna1_db`` and ``antenna2_db`` (20 log10 |U|, dB of full scale, floored at -240 dB)
    and ``profile_db`` (the joint magnitude sqrt((|U1|² + |U2|²) / 2), the scale of a
    target's ``amplitude``); ``bins``: values kept (:func:`pipeline.dsp.profile.profile_db`)."""
    db = np.round(dsp_profile.profile_db(profile_magnitude(msg, radar)[None], bins)[0], digits)
    return {"version": 1, "type": "profile", "sensor_id": msg.sensor_id, "seq": msg.seq,
            "timestamp_ns": msg.timestamp_ns, "config_id": msg.config_id, "bits": msg.bits, "alpha": msg.alpha,
            "delta": msg.delta, "range_m": np.round(dsp_profile.profile_ranges(radar, bins), 4).tolist(),
            "profile_db": db[:, 0].tolist(), "antenna1_db": db[:, 1].tolist(), "antenna2_db": db[:, 2].tolist()}


def load_poses(path) -> dict[str, tuple[float, float, float]]:
    """A sensors file: a TOML table per sensor id with its pose in the world, ``x_m``,
    ``y_m`` (m) and ``yaw_deg`` (deg, counter-clockwise; boresight along the world's x at
    0), each optional (0). -> {sensor id: (x_m, y_m, yaw_deg)}; a mistake is one
    ParameterError naming the file and the entry."""
    import tomllib

    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except OSError as exc:
        raise ParameterError(f"sensors file {path}: cannot read ({exc.strerror or exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ParameterError(f"sensors file {path}: not TOML ({exc})") from None
    poses = {}
    for sid, entry in data.items():
        try:
            check_sensor_id(sid)
        except WireError as exc:
            raise ParameterError(f"sensors file {path}: {exc}") from None
        if not isinstance(entry, dict):
            raise ParameterError(f"sensors file {path}: [{sid}] must be a table of x_m, y_m, yaw_deg")
        unknown = sorted(set(entry) - {"x_m", "y_m", "yaw_deg"})
        if unknown:
            raise ParameterError(f"sensors file {path}: [{sid}] has unknown keys {unknown}; known: x_m, y_m, yaw_deg")
        pose = []
        for key in ("x_m", "y_m", "yaw_deg"):
            v = entry.get(key, 0.0)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ParameterError(f"sensors file {path}: [{sid}] {key}={v!r} must be a finite number")
            pose.append(float(v))
        poses[sid] = tuple(pose)
    return poses


def to_world(x_m: np.ndarray, y_m: np.ndarray, pose: tuple[float, float, float] | None
             ) -> tuple[np.ndarray, np.ndarray]:
    """Points (..., in m) of a sensor's frame (x along boresight, y towards antenna 2) in
    the world, the sensor standing at ``pose`` (x_m, y_m, yaw_deg counter-clockwise; None:
    the identity), as Foxglove's transform world -> ``radar_<sensor>`` places them."""
    if pose is None:
        return np.asarray(x_m, dtype=float), np.asarray(y_m, dtype=float)
    px, py, yaw = pose
    c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    return px + c * np.asarray(x_m) - s * np.asarray(y_m), py + s * np.asarray(x_m) + c * np.asarray(y_m)


def seen_from(truth: SimScene, pose: tuple[float, float, float] | None, sensor_id: str = "") -> SimScene:
    """The true positions of ``truth`` (ranges and angles in the world's frame: as seen
    from its origin along its x) as a sensor standing at ``pose`` sees them: the inverse of
    :func:`to_world`. A moving target, or one behind the sensor, is a ParameterError."""
    if pose is None or tuple(pose) == (0.0, 0.0, 0.0):
        return truth
    px, py, yaw = pose
    c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    targets = []
    for i, t in enumerate(truth.targets):
        if t.velocity_m_s:
            raise ParameterError(f"sensor {sensor_id}: the truth's target {i + 1} moves; a truth seen from a sensor's "
                                 "pose holds static targets only")
        x, y = polar_to_xy(t.range_m, math.radians(t.angle_deg))
        dx, dy = x - px, y - py
        xs, ys = c * dx + s * dy, -s * dx + c * dy
        if xs <= 0:
            raise ParameterError(f"sensor {sensor_id}: the truth's target {i + 1} ({t.range_m:g} m, "
                                 f"{t.angle_deg:+g} deg) is behind it, seen from its pose {list(pose)}")
        targets.append(replace(t, range_m=float(math.hypot(xs, ys)), angle_deg=math.degrees(math.atan2(ys, xs))))
    return replace(truth, targets=tuple(targets))


# -- the node ------------------------------------------------------------------------------
class LiveView(ProcessingNode):
    """zenoh ``<prefix>/*/{targets,tracks,quantized,health}`` -> the view's ``show_*``
    methods (in the worker thread), each message decoded and checked once. ``session=None``
    opens one from ``bus``. A subclass starts its server in :meth:`start` before calling
    this one's, and stops it after :meth:`stop`."""

    name = "view"
    role = "viewer"

    def __init__(self, bus: BusConfig, config: ViewConfig, session: zenoh.Session | Transport | None = None,
                 health_period_s: float = 1.0, intake: IntakeBudget | None = None, decoded: DecodedOnce | None = None):
        super().__init__(bus, session, queue=QueueConfig(queue_size=config.queue_size), batch_max=64,
                         health_period_s=health_period_s, intake=intake)
        self._decode = decoder(decoded)  # the process's JSON messages decoded once (pipeline.wire.shared)
        self.config = config
        self._configs = config.known_configs()
        self._subscribers: list = []
        self._shown: dict[str, set[str]] = {}  # sensor -> the nodes whose health it showed
        self._profile_period_s = 1.0 / config.profile_rate_hz if config.profile_rate_hz > 0 else math.inf
        self._last_profile: dict[str, float] = {}
        self._profiles_skipped: dict[str, int] = {}

    # -- what a view shows (the worker thread) -------------------------------------------------
    def show_sensor(self, sensor: str) -> None:
        """A sensor seen for the first time (its id checked)."""

    def show_targets(self, sensor: str, msg: TargetsMsg, payload: bytes) -> None:
        raise NotImplementedError

    def show_tracks(self, sensor: str, msg: TracksMsg, payload: bytes) -> None:
        raise NotImplementedError

    def show_profile(self, sensor: str, msg: QuantizedFrameMsg, radar: RadarConfig) -> None:
        raise NotImplementedError

    def show_health(self, sensor: str, msg: HealthMsg, payload: bytes) -> None:
        raise NotImplementedError

    # -- life cycle -------------------------------------------------------------------------
    def _start(self) -> None:
        topics = ["targets", "tracks", "health"] + (["quantized"] if self.config.profile_rate_hz > 0 else [])
        self._subscribers = [self.transport.declare_subscriber(self.bus.wildcard(t), self._on_sample) for t in topics]
        self._spawn_supervised(self._work_loop, "worker")

    def _stopping(self) -> None:
        for sub in self._subscribers:
            sub.undeclare()
        self._subscribers = []

    # -- zenoh's thread -----------------------------------------------------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        """Range profiles are rate-limited here, before the payload is copied."""
        key = str(sample.key_expr)
        if key.endswith("/quantized"):
            sensor = self.bus.sensor_of(key) or UNKNOWN_SENSOR
            now = time.monotonic()
            with self._lock:
                last = self._last_profile.get(sensor)
                if last is not None and now - last < self._profile_period_s:
                    self._profiles_skipped[sensor] = self._profiles_skipped.get(sensor, 0) + 1
                    st = self.stats.get(sensor)
                    if st is not None:  # skipped on purpose is not missing: its seq moves the count on
                        seq = peek_seq(sample.payload.to_bytes()[:HEADER_LEN])
                        if seq is not None:
                            st.note_seq("quantized", seq, now, self.intake.rate_hz)
                    return
                if len(self._last_profile) >= 4 * self.config.max_sensors:  # keys of garbage: bounded
                    self._last_profile.clear()
                self._last_profile[sensor] = now
        super()._on_sample(sample)

    # -- the worker ------------------------------------------------------------------------------
    def process(self, batch: list[QueuedFrame]) -> None:
        for item in batch:
            sensor, key, payload = item.sensor, item.key, item.payload
            topic = key.rsplit("/", 1)[-1]
            try:
                if topic == "targets":
                    msg = self._decode("targets", payload, key)
                    self._admit(msg.sensor_id, sensor, key, "targets")
                    self.show_targets(sensor, msg, payload)
                elif topic == "tracks":
                    msg = self._decode("tracks", payload, key)
                    self._admit(msg.sensor_id, sensor, key, "tracks")
                    self.show_tracks(sensor, msg, payload)
                elif topic == "quantized":
                    msg = decode_quantized(payload, key)
                    self._admit(msg.sensor_id, sensor, key, "quantized frame")
                    radar = self._configs.get(msg.config_id)
                    if radar is None:
                        raise WireError(f"quantized frame from {key}: unknown radar config id {msg.config_id:#010x}")
                    self.show_profile(sensor, msg, radar)
                elif topic == "health":  # queued under no sensor when the view has none of its state yet
                    msg = self._decode("health", payload, key)
                    of_key = self.bus.sensor_of(key)
                    self._admit(msg.sensor_id, of_key, key, "health", node=msg.node)
                    self.show_health(of_key, msg, payload)
            except (PipelineError, RadarError) as exc:
                self.count_error(sensor, exc)

    def _admit(self, got: str, sensor: str, key: str, what: str, node: str | None = None) -> None:
        """The message's sensor id is its key's, the sensor one the view may show (at most
        max_sensors), a health message's node a valid name (at most MAX_NODES_PER_SENSOR)."""
        if got != sensor:
            raise WireError(f"{what} from {key}: sensor id {got!r} does not match the key")
        nodes = self._shown.get(sensor)
        if nodes is None:
            if len(self._shown) >= self.config.max_sensors:
                raise WireError(f"{key}: a sensor beyond the first {self.config.max_sensors} the view shows "
                                f"({type(self.config).__name__}.max_sensors)")
            check_sensor_id(sensor)
            nodes = self._shown[sensor] = set()
            self.show_sensor(sensor)
        if node is not None and node not in nodes:
            if not NODE_NAME.fullmatch(node):
                raise WireError(f"health from {key}: node name {node!r} must be 1-32 characters of [A-Za-z0-9_-]")
            if len(nodes) >= MAX_NODES_PER_SENSOR:
                raise WireError(f"health from {key}: more than {MAX_NODES_PER_SENSOR} nodes for one sensor")
            nodes.add(node)

    def _count_out(self, sensor: str, messages: int, size: int, latency_ms: float | None = None) -> None:
        with self._lock:
            st = self.sensor_stats(sensor)
            st.frames_out += messages
            st.bytes_out += size
            if latency_ms is not None:
                st.latency.add(latency_ms)

    # -- health ---------------------------------------------------------------------------------
    def health_extra(self, sensor_id: str) -> dict:
        with self._lock:
            return {"profiles_skipped": self._profiles_skipped.get(sensor_id, 0)}

    def summary(self) -> dict:
        """The view's totals: counters, profiles skipped, sensors shown (the nodes' health of
        senders they could not put on a sensor yet, UNKNOWN_SENSOR, is shown as health, not
        listed as a sensor: on a busy host a sensor's first health can reach a node before its
        frames do)."""
        with self._lock:
            skipped = sum(self._profiles_skipped.values())
        return {**self.totals(), "profiles_skipped": skipped,
                "sensors": sorted(s for s in self._shown if s != UNKNOWN_SENSOR)}
