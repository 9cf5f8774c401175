"""``qradar view``: the live stream in Foxglove, over the Foxglove WebSocket protocol
(``foxglove-sdk``).

A live view (:class:`qradar.liveview.LiveView`, which it shares with the web page of
:mod:`qradar.web`): it subscribes ``<prefix>/*/{targets,tracks,quantized,health}``, zenoh's
callback copies a payload into a bounded queue (a full queue drops the newest and counts
it in ``drops``), and one worker thread decodes and logs to a Foxglove WebSocket server
that listens only where asked (default 127.0.0.1:8765). Per sensor ``s``:

* ``/<prefix>/s/targets``: ``foxglove.PointCloud`` (protobuf) in the frame ``radar_s``,
  one point per target, float32 fields x, y, z (m; x = R cos θ along boresight, y = R sin θ
  across it, from :func:`radar_driver.model.polar_to_xy`; z = 0), then every number of a
  target (range_m, angle_deg, amplitude, statistic_db: NaN when the localizer gave none),
  the points of :func:`pipeline.wire.foxglove.target_points`, as recordings hold them;
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
import time
from dataclasses import dataclass, field

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

from pipeline.bus.session import BusConfig
from pipeline.errors import WireError
from pipeline.nodes.budget import IntakeBudget
from pipeline.wire import HealthMsg, QuantizedFrameMsg, TargetsMsg, TracksMsg
from radar_driver.model import RadarConfig, polar_to_xy
from pipeline.wire.fields import HEALTH, PROFILE, json_schema
from pipeline.wire.shared import DecodedOnce
from pipeline.wire.foxglove import (  # noqa: F401 (POINT_FIELDS, target_points: the view's names)
    ENTITY_LIFETIME_NS, MOVING_COLOR, POINT_FIELDS, STATIC_COLOR, point_dtype, target_points, track_label)
from replay.mcapio import TARGETS_SCHEMA

# the views' shared parts, imported from here by older callers
from .liveview import (  # noqa: F401
    MAX_NODES_PER_SENSOR,
    NODE_NAME,
    PROFILE_FLOOR,
    LiveView,
    ViewConfig,
    ViewError,
    load_poses,
    parse_endpoint,
    range_profile,
)

log = logging.getLogger("qradar.view")

#: the root frame of the sensors' frames (``radar_<sensor>``)
WORLD_FRAME = "world"
#: the topic of the frame transforms
TF_TOPIC = "/tf"
#: the float32 fields of a target point, in order (4 bytes each): pipeline.wire.foxglove's
POINT_DTYPE = point_dtype()
#: the largest sensor timestamp a foxglove Timestamp holds (uint32 seconds), ns
MAX_TIMESTAMP_NS = (1 << 32) * 1_000_000_000 - 1
#: the JSON topics' schemas, from the one definition of the formats' fields (pipeline.wire.fields)
HEALTH_SCHEMA = json_schema(HEALTH)
RANGE_PROFILE_SCHEMA = json_schema(PROFILE)


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
TRACK_LIFETIME_NS = ENTITY_LIFETIME_NS


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


def sensor_transform(sensor: str, pose: tuple[float, float, float] | None, stamp: Timestamp) -> FrameTransform:
    """world -> ``radar_<sensor>`` at ``pose`` (x_m, y_m, yaw_deg; None: the identity)."""
    x, y, yaw = pose or (0.0, 0.0, 0.0)
    half = math.radians(yaw) / 2.0
    return FrameTransform(timestamp=stamp, parent_frame_id=WORLD_FRAME, child_frame_id=frame_id(sensor),
                          translation=Vector3(x=x, y=y, z=0.0),
                          rotation=Quaternion(x=0.0, y=0.0, z=math.sin(half), w=math.cos(half)))


# -- the node ----------------------------------------------------------------------------
@dataclass
class _SensorChannels:
    points: PointCloudChannel
    targets: foxglove.Channel
    profile: foxglove.Channel
    tracks: SceneUpdateChannel
    health: dict[str, foxglove.Channel] = field(default_factory=dict)


class FoxgloveView(LiveView):
    """zenoh ``<prefix>/*/{targets,quantized,health}`` -> a Foxglove WebSocket server (see
    the module docstring for the topics). ``session=None`` opens one from ``bus``. The
    server starts with :meth:`start` (``url`` and ``port`` then tell where it listens) and
    stops with :meth:`stop`."""

    def __init__(self, bus: BusConfig, config: ViewConfig = ViewConfig(), session: zenoh.Session | None = None,
                 health_period_s: float = 1.0, intake: IntakeBudget | None = None, decoded: DecodedOnce | None = None):
        super().__init__(bus, config, session, health_period_s=health_period_s, intake=intake, decoded=decoded)
        self._context = foxglove.Context()  # channels and server of this view only
        self._server = None
        self._sensors: dict[str, _SensorChannels] = {}
        self._tf: FrameTransformChannel | None = None
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

    def stop(self, timeout_s: float = 5.0) -> None:
        super().stop(timeout_s)
        if self._server is not None:
            self._server.stop()
            self._server = None

    # -- the worker ------------------------------------------------------------------------------
    def show_sensor(self, sensor: str) -> None:
        topics = sensor_topics(self.bus.prefix, sensor)
        self._sensors[sensor] = _SensorChannels(
            points=PointCloudChannel(topics["targets"], context=self._context),
            targets=foxglove.Channel(topics["targets_json"], schema=TARGETS_SCHEMA, context=self._context),
            profile=foxglove.Channel(topics["range_profile"], schema=RANGE_PROFILE_SCHEMA, context=self._context),
            tracks=SceneUpdateChannel(topics["tracks"], context=self._context))
        self._log_transform(sensor)

    def show_targets(self, sensor: str, msg: TargetsMsg, payload: bytes) -> None:
        cloud = targets_pointcloud(msg, self.bus.key(sensor, "targets"))
        ch = self._sensors[sensor]
        ch.points.log(cloud, log_time=msg.timestamp_ns)
        ch.targets.log(payload, log_time=msg.timestamp_ns)
        self._count_out(sensor, 2, len(payload), (time.time_ns() - msg.timestamp_ns) / 1e6)

    def show_tracks(self, sensor: str, msg: TracksMsg, payload: bytes) -> None:
        scene = tracks_scene(msg, self.bus.key(sensor, "tracks"))
        self._sensors[sensor].tracks.log(scene, log_time=msg.timestamp_ns)
        self._count_out(sensor, 1, len(payload))

    def show_profile(self, sensor: str, msg: QuantizedFrameMsg, radar: RadarConfig) -> None:
        _timestamp(msg.timestamp_ns, f"quantized frame from {self.bus.key(sensor, 'quantized')}")
        profile = json.dumps(range_profile(msg, radar), separators=(",", ":")).encode()
        self._sensors[sensor].profile.log(profile, log_time=msg.timestamp_ns)
        self._count_out(sensor, 1, len(profile))

    def show_health(self, sensor: str, msg: HealthMsg, payload: bytes) -> None:
        ch = self._sensors[sensor]
        channel = ch.health.get(msg.node)
        if channel is None:
            channel = foxglove.Channel(health_topic(self.bus.prefix, sensor, msg.node), schema=HEALTH_SCHEMA,
                                       context=self._context)
            ch.health[msg.node] = channel
        channel.log(payload, log_time=max(0, msg.timestamp_ns))
        self._count_out(sensor, 1, len(payload))

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

    def summary(self) -> dict:
        """The view's totals: where it listened, counters, sensors shown."""
        return {"url": self.url, **super().summary()}
