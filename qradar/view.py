"""``qradar view``: the live stream in Foxglove, over the Foxglove WebSocket protocol
(``foxglove-sdk``).

A node like the others (:class:`pipeline.nodes.intake.ProcessingNode`): it subscribes
``<prefix>/*/targets``, ``<prefix>/*/quantized`` and ``<prefix>/*/health``, zenoh's
callback copies a payload into a bounded queue (a full queue drops the newest and counts
it in ``drops``), and one worker thread decodes and logs to a Foxglove WebSocket server
that listens only where asked (default 127.0.0.1:8765). Per sensor ``s``:

* ``/<prefix>/s/targets``: ``foxglove.PointCloud`` (protobuf) in the frame ``radar_s``,
  one point per target, float32 fields x, y, z (m; x = R cos θ along boresight, y = R sin θ
  across it, from :func:`radar_driver.model.polar_to_xy`; z = 0), amplitude, range_m,
  angle_deg and statistic_db (NaN when the localizer gave none);
* ``/<prefix>/s/tracks``: ``foxglove.SceneUpdate`` (protobuf) in the frame ``radar_s``, one
  entity per track of the sensor's tracks messages (``--track``): a sphere at the track's
  position (diameter 2 sigma, at least 0.2 m; green while static, orange while moving) and
  a label with its id, speed and sigma; an entity lives 0.5 s unless the next message
  replaces it;
* ``/<prefix>/s/targets_json``: the targets message as on the wire (JSON,
  docs/wire-formats.md), for plots of ``targets[0].range_m`` and the like;
* ``/<prefix>/s/range_profile``: |Φ*Z/M| of a quantized frame against range, per antenna
  and joint, in dB (JSON, :func:`range_profile`), at most ``profile_rate_hz`` a second;
* ``/<prefix>/s/health/<node>``: each node's health JSON as on the wire (the view's own,
  node ``view``, among them);
* ``/tf``: ``foxglove.FrameTransform`` world → ``radar_s``, once a second: the sensor's pose
  from a sensors file (``--sensor-poses sensors.toml``: per sensor id its ``x_m``, ``y_m``
  and ``yaw_deg`` in the world; :func:`load_poses`), else the identity.

A malformed payload is counted (``decode_errors``), logged at most once a second, and
skipped; the view keeps running. The WebSocket server keeps at most 1 024 outgoing
messages per client (the SDK's backlog; the oldest data message is dropped beyond it).
"""

from __future__ import annotations

import json
import logging
import math
import re
import time
from dataclasses import dataclass, field, replace

import foxglove
import numpy as np
import zenoh
from foxglove.channels import FrameTransformChannel, PointCloudChannel, SceneUpdateChannel
from foxglove.messages import (
    Color,
    Duration,
    FrameTransform,
    PackedElementField,
    PackedElementFieldNumericType,
    PointCloud,
    Pose,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector3,
)

from pipeline.nodes.budget import IntakeBudget
from pipeline.bus.session import BusConfig
from pipeline.errors import ParameterError, PipelineError, WireError
from pipeline.nodes.intake import SEQ, SEQ_OFFSET, ProcessingNode, QueuedFrame
from pipeline.dsp.localize import back_project
from pipeline.dsp.quantize import dequantize
from pipeline.wire import (
    HEADER_LEN,
    MAGIC,
    QuantizedFrameMsg,
    TargetsMsg,
    TracksMsg,
    check_sensor_id,
    decode_health,
    decode_quantized,
    decode_targets,
    decode_tracks,
)
from radar_driver.errors import RadarError
from replay.mcapio import TARGETS_SCHEMA
from radar_driver.model import RadarConfig, polar_to_xy

log = logging.getLogger("qradar.view")

#: the root frame of the sensors' frames (``radar_<sensor>``)
WORLD_FRAME = "world"
#: the topic of the frame transforms
TF_TOPIC = "/tf"
#: profile values below this magnitude (full-scale units) are shown as it: -240 dB
PROFILE_FLOOR = 1e-12
#: the float32 fields of a target point, in order (4 bytes each)
POINT_FIELDS = ("x", "y", "z", "amplitude", "range_m", "angle_deg", "statistic_db")
POINT_DTYPE = np.dtype([(f, "<f4") for f in POINT_FIELDS])
#: names of nodes in health messages: they become topic names
NODE_NAME = re.compile(r"[A-Za-z0-9_-]{1,32}")
#: health channels per sensor at most (one per node)
MAX_NODES_PER_SENSOR = 16
#: the largest sensor timestamp a foxglove Timestamp holds (uint32 seconds), ns
MAX_TIMESTAMP_NS = (1 << 32) * 1_000_000_000 - 1

HEALTH_SCHEMA = {
    "type": "object", "title": "qradar.Health",
    "properties": {"node": {"type": "string"}, "sensor_id": {"type": "string"}, "timestamp_ns": {"type": "integer"},
                   "frames_in": {"type": "integer"}, "frames_out": {"type": "integer"}, "drops": {"type": "integer"},
                   "decode_errors": {"type": "integer"}, "latency_ms": {"type": "object"},
                   "bytes_in_per_s": {"type": "number"}, "bytes_out_per_s": {"type": "number"},
                   "extra": {"type": "object"}},
}
_DB_ARRAY = {"type": "array", "items": {"type": "number"}}
RANGE_PROFILE_SCHEMA = {
    "type": "object", "title": "qradar.RangeProfile",
    "properties": {"sensor_id": {"type": "string"}, "seq": {"type": "integer"}, "timestamp_ns": {"type": "integer"},
                   "config_id": {"type": "integer"}, "bits": {"type": "integer"}, "alpha": {"type": "number"},
                   "delta": {"type": "number"},
                   "range_m": {"type": "array", "items": {"type": "number"}, "description": "range bins, m"},
                   "profile_db": _DB_ARRAY | {"description": "20 log10 sqrt((|U1|^2 + |U2|^2) / 2), dB full scale"},
                   "antenna1_db": _DB_ARRAY | {"description": "20 log10 |U1|, dB full scale"},
                   "antenna2_db": _DB_ARRAY | {"description": "20 log10 |U2|, dB full scale"}},
}


class ViewError(PipelineError):
    """The Foxglove server could not start (a busy port, an unknown host)."""


@dataclass(frozen=True)
class ViewConfig:
    """host: the address the WebSocket server binds (127.0.0.1: this host only). port: its
    TCP port (0: any free one). profile_rate_hz: range profiles per second and sensor at
    most (0: none, and quantized frames are not subscribed). radar: the base radar
    configuration of the range profiles; frames of 1..max_ramps whole ramps are shown.
    queue_size: bounded input queue (messages). max_sensors: sensors shown at most."""

    host: str = "127.0.0.1"
    port: int = 8765
    profile_rate_hz: float = 2.0
    radar: RadarConfig = field(default_factory=RadarConfig)
    max_ramps: int = 16
    queue_size: int = 256
    max_sensors: int = 64
    name: str = "qradar"
    #: sensor id -> (x_m, y_m, yaw_deg) of the sensor in the world (:func:`load_poses`)
    poses: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not (isinstance(self.host, str) and self.host.strip()):
            raise ParameterError(f"foxglove host={self.host!r} must be a host name or address, e.g. 127.0.0.1")
        if isinstance(self.port, bool) or not (isinstance(self.port, int) and 0 <= self.port <= 65535):
            raise ParameterError(f"foxglove port={self.port!r} must be an integer in [0, 65535] (0: any free port)")
        if not (isinstance(self.profile_rate_hz, (int, float)) and math.isfinite(self.profile_rate_hz)
                and self.profile_rate_hz >= 0):
            raise ParameterError(f"profile_rate_hz={self.profile_rate_hz!r} must be a finite number >= 0")
        for name in ("max_ramps", "queue_size", "max_sensors"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, int) and v >= 1):
                raise ParameterError(f"ViewConfig.{name}={v!r} must be an integer >= 1")

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
        raise ParameterError(f"foxglove endpoint {text!r} must be [HOST:]PORT, e.g. 127.0.0.1:8765") from None
    if not host or not 0 <= value <= 65535:
        raise ParameterError(f"foxglove endpoint {text!r} must be [HOST:]PORT with PORT in [0, 65535]")
    return host, value


# -- messages ----------------------------------------------------------------------------
def frame_id(sensor_id: str) -> str:
    """The Foxglove frame of a sensor: ``radar_<sensor>``."""
    return f"radar_{sensor_id}"


def sensor_topics(prefix: str, sensor_id: str) -> dict[str, str]:
    """A sensor's Foxglove topics by kind: ``targets`` (foxglove.PointCloud), ``targets_json``,
    ``range_profile``, ``tracks`` (foxglove.SceneUpdate); its health topics are :func:`health_topic`."""
    base = f"/{prefix}/{sensor_id}"
    return {"targets": f"{base}/targets", "targets_json": f"{base}/targets_json",
            "range_profile": f"{base}/range_profile", "tracks": f"{base}/tracks"}


def health_topic(prefix: str, sensor_id: str, node: str) -> str:
    """The Foxglove topic of one node's health for one sensor."""
    return f"/{prefix}/{sensor_id}/health/{node}"


def _timestamp(ns: int, what: str) -> Timestamp:
    if not 0 <= ns <= MAX_TIMESTAMP_NS:
        raise WireError(f"{what}: timestamp_ns={ns} outside what a Foxglove timestamp holds [0, {MAX_TIMESTAMP_NS}]")
    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def target_points(msg: TargetsMsg) -> np.ndarray:
    """The targets as packed points: (K,) of :data:`POINT_DTYPE` (float32 fields; x, y in m
    by :func:`~radar_driver.model.polar_to_xy` of range_m and angle_deg, z = 0;
    statistic_db NaN when absent)."""
    pts = np.zeros(len(msg.targets), dtype=POINT_DTYPE)
    if not msg.targets:
        return pts
    range_m = np.array([t["range_m"] for t in msg.targets])
    angle_deg = np.array([t["angle_deg"] for t in msg.targets])
    pts["x"], pts["y"] = polar_to_xy(range_m, np.radians(angle_deg))
    pts["amplitude"] = [t["amplitude"] for t in msg.targets]
    pts["range_m"], pts["angle_deg"] = range_m, angle_deg
    pts["statistic_db"] = [t.get("statistic_db", np.nan) for t in msg.targets]
    return pts


def targets_pointcloud(msg: TargetsMsg, source: str = "<targets>") -> PointCloud:
    """``foxglove.PointCloud`` of one targets message, in the frame ``radar_<sensor>``, stamped
    with the frame's sensor timestamp; fields :data:`POINT_FIELDS` (float32)."""
    return PointCloud(
        timestamp=_timestamp(msg.timestamp_ns, f"targets from {source}"), frame_id=frame_id(msg.sensor_id),
        pose=Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
        point_stride=POINT_DTYPE.itemsize,
        fields=[PackedElementField(name=f, offset=POINT_DTYPE.fields[f][1], type=PackedElementFieldNumericType.Float32)
                for f in POINT_FIELDS],
        data=target_points(msg).tobytes())


#: how long a track's entity stays without a newer message, ns
TRACK_LIFETIME_NS = 500_000_000
#: colours of a static and of a moving track (RGBA, 0..1)
STATIC_COLOR = (0.2, 0.8, 0.3, 0.9)
MOVING_COLOR = (1.0, 0.55, 0.1, 0.9)


def track_label(track: dict) -> str:
    """``#3 1.52 m/s σ 0.041 m`` (``static`` instead of the speed while static)."""
    speed = "static" if track["static"] else f"{math.hypot(track['vx_mps'], track['vy_mps']):.2f} m/s"
    return f"#{track['track_id']} {speed} σ {track['sigma_m']:.3f} m"


def tracks_scene(msg: TracksMsg, source: str = "<tracks>") -> SceneUpdate:
    """``foxglove.SceneUpdate`` of one tracks message, in the frame ``radar_<sensor>``,
    stamped with the frame's sensor timestamp: an entity ``track-<id>`` per track, a sphere
    at its position (diameter 2 sigma, at least 0.2 m) and a label (:func:`track_label`)."""
    stamp = _timestamp(msg.timestamp_ns, f"tracks from {source}")
    identity = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
    entities = []
    for t in msg.tracks:
        size = max(2.0 * t["sigma_m"], 0.2)
        r, g, b, a = STATIC_COLOR if t["static"] else MOVING_COLOR
        entities.append(SceneEntity(
            timestamp=stamp, frame_id=frame_id(msg.sensor_id), id=f"track-{t['track_id']}",
            lifetime=Duration(sec=0, nsec=TRACK_LIFETIME_NS), frame_locked=True,
            spheres=[SpherePrimitive(pose=Pose(position=Vector3(x=t["x_m"], y=t["y_m"], z=0.0), orientation=identity),
                                     size=Vector3(x=size, y=size, z=size), color=Color(r=r, g=g, b=b, a=a))],
            texts=[TextPrimitive(pose=Pose(position=Vector3(x=t["x_m"], y=t["y_m"], z=0.5), orientation=identity),
                                 billboard=True, font_size=14.0, scale_invariant=True,
                                 color=Color(r=1.0, g=1.0, b=1.0, a=1.0), text=track_label(t))]))
    return SceneUpdate(entities=entities)


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


def sensor_transform(sensor: str, pose: tuple[float, float, float] | None, stamp: Timestamp) -> FrameTransform:
    """world -> ``radar_<sensor>`` at ``pose`` (x_m, y_m, yaw_deg; None: the identity)."""
    x, y, yaw = pose or (0.0, 0.0, 0.0)
    half = math.radians(yaw) / 2.0
    return FrameTransform(timestamp=stamp, parent_frame_id=WORLD_FRAME, child_frame_id=frame_id(sensor),
                          translation=Vector3(x=x, y=y, z=0.0),
                          rotation=Quaternion(x=0.0, y=0.0, z=math.sin(half), w=math.cos(half)))


def _db(magnitude: np.ndarray) -> list[float]:
    return np.round(20.0 * np.log10(np.maximum(magnitude, PROFILE_FLOOR)), 2).tolist()


def range_profile(msg: QuantizedFrameMsg, radar: RadarConfig) -> dict:
    """The range profile of one quantized frame: U = Φ*Z/M (what PBP thresholds; Z the
    dequantized codes, the dither not removed), (N, 2), as JSON-ready arrays of N values:
    ``range_m`` (the bins, m), ``antenna1_db`` and ``antenna2_db`` (20 log10 |U|, dB of
    full scale, floored at -240 dB) and ``profile_db`` (the joint magnitude
    sqrt((|U1|² + |U2|²) / 2), the scale of a target's ``amplitude``)."""
    if msg.codes.shape[0] != radar.n_measurements:
        raise WireError(f"quantized frame {msg.seq} of {msg.sensor_id}: M={msg.codes.shape[0]} but its radar "
                        f"config has M={radar.n_measurements}")
    u = back_project(dequantize(msg.codes[None], msg.delta, msg.bits), radar)[0]
    mag = np.abs(u)
    joint = np.sqrt((mag ** 2).sum(axis=1) / 2.0)
    return {"sensor_id": msg.sensor_id, "seq": msg.seq, "timestamp_ns": msg.timestamp_ns,
            "config_id": msg.config_id, "bits": msg.bits, "alpha": msg.alpha, "delta": msg.delta,
            "range_m": np.round(radar.range_grid_m(), 4).tolist(),
            "profile_db": _db(joint), "antenna1_db": _db(mag[:, 0]), "antenna2_db": _db(mag[:, 1])}


# -- the node ----------------------------------------------------------------------------
@dataclass
class _SensorChannels:
    points: PointCloudChannel
    targets: foxglove.Channel
    profile: foxglove.Channel
    tracks: SceneUpdateChannel
    health: dict[str, foxglove.Channel] = field(default_factory=dict)


class FoxgloveView(ProcessingNode):
    """zenoh ``<prefix>/*/{targets,quantized,health}`` -> a Foxglove WebSocket server (see
    the module docstring for the topics). ``session=None`` opens one from ``bus``. The
    server starts with :meth:`start` (``url`` and ``port`` then tell where it listens) and
    stops with :meth:`stop`."""

    name = "view"
    role = "viewer"

    def __init__(self, bus: BusConfig, config: ViewConfig = ViewConfig(), session: zenoh.Session | None = None,
                 health_period_s: float = 1.0, intake: IntakeBudget | None = None):
        super().__init__(bus, session, queue_size=config.queue_size, batch_max=64, health_period_s=health_period_s,
                         intake=intake)
        self.config = config
        self._configs = config.known_configs()
        self._context = foxglove.Context()  # channels and server of this view only
        self._server = None
        self._subscribers: list = []
        self._sensors: dict[str, _SensorChannels] = {}
        self._tf: FrameTransformChannel | None = None
        self._profile_period_s = 1.0 / config.profile_rate_hz if config.profile_rate_hz > 0 else math.inf
        self._last_profile: dict[str, float] = {}
        self._profiles_skipped: dict[str, int] = {}
        self.port: int | None = None

    @property
    def url(self) -> str | None:
        """``ws://host:port`` of the running server, else None."""
        if self.port is None:
            return None
        host = f"[{self.config.host}]" if ":" in self.config.host else self.config.host
        return f"ws://{host}:{self.port}"

    # -- life cycle -------------------------------------------------------------------------
    def start(self) -> "FoxgloveView":
        try:
            self._server = foxglove.start_server(name=self.config.name, host=self.config.host, port=self.config.port,
                                                 context=self._context)
        except RuntimeError as exc:  # FoxgloveError: the SDK's message names the cause
            raise ViewError(f"cannot start the Foxglove WebSocket server on {self.config.host}:{self.config.port}: "
                            f"{exc}") from None
        self.port = self._server.port
        self._tf = FrameTransformChannel(TF_TOPIC, context=self._context)
        try:
            super().start()
        except BaseException:
            self._server.stop()
            raise
        log.info("Foxglove WebSocket server on %s", self.url)
        return self

    def _start(self) -> None:
        topics = ["targets", "tracks", "health"] + (["quantized"] if self.config.profile_rate_hz > 0 else [])
        self._subscribers = [self.transport.declare_subscriber(self.bus.wildcard(t), self._on_sample) for t in topics]
        self._spawn_supervised(self._work_loop, "worker")

    def _stopping(self) -> None:
        for sub in self._subscribers:
            sub.undeclare()
        self._subscribers = []

    def stop(self, timeout_s: float = 5.0) -> None:
        super().stop(timeout_s)
        if self._server is not None:
            self._server.stop()
            self._server = None

    # -- zenoh's thread -----------------------------------------------------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        """Range profiles are rate-limited here, before the payload is copied."""
        key = str(sample.key_expr)
        if key.endswith("/quantized"):
            sensor = self.bus.sensor_of(key) or "_unknown"
            now = time.monotonic()
            with self._lock:
                last = self._last_profile.get(sensor)
                if last is not None and now - last < self._profile_period_s:
                    self._profiles_skipped[sensor] = self._profiles_skipped.get(sensor, 0) + 1
                    st = self.stats.get(sensor)
                    if st is not None:  # skipped on purpose is not missing: its seq moves the count on
                        head = sample.payload.to_bytes()[:HEADER_LEN]
                        if len(head) == HEADER_LEN and head[:4] == MAGIC:
                            st.note_seq("quantized", SEQ.unpack_from(head, SEQ_OFFSET)[0], now, self.intake.rate_hz)
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
                    self._targets(sensor, key, payload)
                elif topic == "tracks":
                    self._tracks(sensor, key, payload)
                elif topic == "quantized":
                    self._profile(sensor, key, payload)
                elif topic == "health":  # queued under no sensor when the view has none of its state yet
                    self._health(self.bus.sensor_of(key), key, payload)
            except (PipelineError, RadarError) as exc:
                self.count_error(sensor, exc)

    def _channels(self, sensor: str, key: str) -> _SensorChannels:
        ch = self._sensors.get(sensor)
        if ch is not None:
            return ch
        if len(self._sensors) >= self.config.max_sensors:
            raise WireError(f"{key}: a sensor beyond the first {self.config.max_sensors} the view shows "
                            "(ViewConfig.max_sensors)")
        check_sensor_id(sensor)
        topics = sensor_topics(self.bus.prefix, sensor)
        ch = _SensorChannels(
            points=PointCloudChannel(topics["targets"], context=self._context),
            targets=foxglove.Channel(topics["targets_json"], schema=TARGETS_SCHEMA, context=self._context),
            profile=foxglove.Channel(topics["range_profile"], schema=RANGE_PROFILE_SCHEMA, context=self._context),
            tracks=SceneUpdateChannel(topics["tracks"], context=self._context))
        self._sensors[sensor] = ch
        self._log_transform(sensor)
        return ch

    def _check_sensor(self, got: str, sensor: str, key: str, what: str) -> None:
        if got != sensor:
            raise WireError(f"{what} from {key}: sensor id {got!r} does not match the key")

    def _targets(self, sensor: str, key: str, payload: bytes) -> None:
        msg = decode_targets(payload, key)
        self._check_sensor(msg.sensor_id, sensor, key, "targets")
        cloud = targets_pointcloud(msg, key)
        ch = self._channels(sensor, key)
        ch.points.log(cloud, log_time=msg.timestamp_ns)
        ch.targets.log(payload, log_time=msg.timestamp_ns)
        self._count_out(sensor, 2, len(payload), (time.time_ns() - msg.timestamp_ns) / 1e6)

    def _tracks(self, sensor: str, key: str, payload: bytes) -> None:
        msg = decode_tracks(payload, key)
        self._check_sensor(msg.sensor_id, sensor, key, "tracks")
        scene = tracks_scene(msg, key)
        self._channels(sensor, key).tracks.log(scene, log_time=msg.timestamp_ns)
        self._count_out(sensor, 1, len(payload))

    def _profile(self, sensor: str, key: str, payload: bytes) -> None:
        msg = decode_quantized(payload, key)
        self._check_sensor(msg.sensor_id, sensor, key, "quantized frame")
        radar = self._configs.get(msg.config_id)
        if radar is None:
            raise WireError(f"quantized frame from {key}: unknown radar config id {msg.config_id:#010x}")
        _timestamp(msg.timestamp_ns, f"quantized frame from {key}")
        profile = json.dumps(range_profile(msg, radar), separators=(",", ":")).encode()
        self._channels(sensor, key).profile.log(profile, log_time=msg.timestamp_ns)
        self._count_out(sensor, 1, len(profile))

    def _health(self, sensor: str, key: str, payload: bytes) -> None:
        msg = decode_health(payload, key)
        self._check_sensor(msg.sensor_id, sensor, key, "health")
        if not NODE_NAME.fullmatch(msg.node):
            raise WireError(f"health from {key}: node name {msg.node!r} must be 1-32 characters of [A-Za-z0-9_-]")
        ch = self._channels(sensor, key)
        channel = ch.health.get(msg.node)
        if channel is None:
            if len(ch.health) >= MAX_NODES_PER_SENSOR:
                raise WireError(f"health from {key}: more than {MAX_NODES_PER_SENSOR} nodes for one sensor")
            channel = foxglove.Channel(health_topic(self.bus.prefix, sensor, msg.node), schema=HEALTH_SCHEMA,
                                       context=self._context)
            ch.health[msg.node] = channel
        channel.log(payload, log_time=max(0, msg.timestamp_ns))
        self._count_out(sensor, 1, len(payload))

    def _count_out(self, sensor: str, messages: int, size: int, latency_ms: float | None = None) -> None:
        with self._lock:
            st = self.sensor_stats(sensor)
            st.frames_out += messages
            st.bytes_out += size
            if latency_ms is not None:
                st.latency.add(latency_ms)

    def _log_transform(self, sensor: str) -> None:
        if self._tf is not None:
            self._tf.log(sensor_transform(sensor, self.config.poses.get(sensor), Timestamp.from_epoch_secs(time.time())))

    # -- health ---------------------------------------------------------------------------------
    def _publish_health(self, part: int | None = None) -> None:
        super()._publish_health(part)
        if part not in (None, 0):
            return
        for sensor in list(self._sensors):  # late clients get the transforms within a second
            self._log_transform(sensor)

    def health_extra(self, sensor_id: str) -> dict:
        with self._lock:
            return {"profiles_skipped": self._profiles_skipped.get(sensor_id, 0)}

    def summary(self) -> dict:
        """The view's totals: where it listened, counters, sensors shown."""
        with self._lock:
            skipped = sum(self._profiles_skipped.values())
        return {"url": self.url, **self.totals(), "profiles_skipped": skipped, "sensors": sorted(self._sensors)}
