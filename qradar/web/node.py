"""The web view's node: the live stream (or a recording) to the pages of
:mod:`qradar.web.server`, as the events of :mod:`qradar.web.events`."""

from __future__ import annotations

import json
import logging
import re
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import zenoh

from pipeline.bus.session import BusConfig
from pipeline.errors import ParameterError
from pipeline.nodes.budget import IntakeBudget
from pipeline.nodes.transport import MemoryTransport, Transport
from pipeline.wire import HealthMsg, QuantizedFrameMsg, TargetsMsg, TracksMsg
from pipeline.wire.shared import DecodedOnce
from radar_driver.model import RadarConfig
from radar_driver.scene import SimScene

from ..liveview import LiveView, ViewConfig, profile_magnitude
from .events import TARGET_SIGMA_FIELDS, health_event, profile_event, targets_event, tracks_event
from .hub import CLIENT_BYTES, CLIENT_EVENTS, MAX_CLIENTS, EventHub
from .recording import RecordingPlayer
from .server import WebServer

log = logging.getLogger("qradar.web")

#: what a token may hold (it travels in a URL): 16 to 256 URL-safe characters
TOKEN = re.compile(r"[A-Za-z0-9_~.-]{16,256}")


@dataclass(frozen=True)
class WebConfig(ViewConfig):
    """:class:`~qradar.liveview.ViewConfig` of the web page (default port 8080; range
    profiles of every frame of a 20 Hz sensor). token: None, or what ``?token=`` must
    say (16-256 characters of ``[A-Za-z0-9_~.-]``). client_events, client_bytes: each
    page's queue (the oldest events dropped beyond, counted). max_clients: pages at once."""

    port: int = 8080
    profile_rate_hz: float = 20.0
    token: str | None = None
    client_events: int = CLIENT_EVENTS
    client_bytes: int = CLIENT_BYTES
    max_clients: int = MAX_CLIENTS

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.token is not None and not (isinstance(self.token, str) and TOKEN.fullmatch(self.token)):
            raise ParameterError("the web view's token must be 16 to 256 characters of [A-Za-z0-9_~.-] (it travels "
                                 "in the page's URL)")
        for name in ("client_events", "client_bytes", "max_clients"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, int) and v >= 1):
                raise ParameterError(f"WebConfig.{name}={v!r} must be an integer >= 1")


class WebView(LiveView):
    """zenoh ``<prefix>/*/{targets,tracks,quantized,health}`` -> the pages of a web server
    on ``config.host:config.port`` (:meth:`start`; ``url`` then says where). ``truth``:
    the true targets to show beside the estimates (a scene), its time 0 at ``truth_t0_ns``
    (ns; a dict: each sensor's, a recording's; None, or a sensor the dict does not name: its
    first frame). ``recording``: a :class:`RecordingPlayer` whose
    transport is this view's (see :meth:`of_recording`)."""

    def __init__(self, bus: BusConfig, config: WebConfig = WebConfig(),
                 session: zenoh.Session | Transport | None = None, truth: SimScene | None = None,
                 truth_t0_ns: int | dict[str, int] | None = None, recording: RecordingPlayer | None = None,
                 health_period_s: float = 1.0, intake: IntakeBudget | None = None, decoded: DecodedOnce | None = None):
        super().__init__(bus, config, session, health_period_s=health_period_s, intake=intake, decoded=decoded)
        self.hub = EventHub(config.max_clients, config.client_events, config.client_bytes)
        self.truth, self.truth_t0_ns = truth, truth_t0_ns
        self._t0_by_sensor: dict[str, int] = {}
        self.player = recording
        self.server: WebServer | None = None
        self._serving: threading.Thread | None = None
        self.port: int | None = None
        self._refused = {"refused_token": 0, "refused_host": 0}  # requests refused, kept after the server stops

    @classmethod
    def of_recording(cls, path: str | Path, config: WebConfig = WebConfig(), bus: BusConfig = BusConfig(),
                     health_period_s: float = 1.0) -> "WebView":
        """A view of a recording (no bus: an in-memory transport), its radar configuration
        and truth from the file; the player starts with the view, playing."""
        transport = MemoryTransport()
        view: WebView | None = None

        def state(s: dict) -> None:
            view.hub.publish("replay", s, key=("replay",))

        player = RecordingPlayer(path, transport, bus, on_state=state, on_seek=lambda s: view.hub.reset(s))
        view = cls(bus, replace(config, radar=player.radar), session=transport, truth=player.truth,
                   truth_t0_ns=player.truth_t0_ns, recording=player, health_period_s=health_period_s)
        return view

    @property
    def url(self) -> str | None:
        """``http://host:port/`` of the running server (with ``?token=`` when it needs one), else None."""
        if self.port is None:
            return None
        host = f"[{self.config.host}]" if ":" in self.config.host else self.config.host
        return f"http://{host}:{self.port}/" + (f"?token={self.config.token}" if self.config.token else "")

    # -- life cycle -------------------------------------------------------------------------
    def start(self) -> "WebView":
        cfg = self.config
        self.hub.set_hello({"mode": "live" if self.player is None else "recording", "prefix": self.bus.prefix,
                            "poses": {s: list(p) for s, p in cfg.poses.items()}, "profile_rate_hz": cfg.profile_rate_hz,
                            "truth": self.truth is not None,
                            "recording": None if self.player is None else self.player.state()})
        self.server = WebServer(cfg.host, cfg.port, self.hub, cfg.token,
                                control=None if self.player is None else self.player.control)
        self.port = self.server.port
        self._serving = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.2},
                                         name="web-server", daemon=True)
        self._serving.start()
        try:
            super().start()
        except BaseException:
            self._stop_server()
            raise
        if self.player is not None:
            self.player.start()
        log.debug("web view on %s", self.url)
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        if self.player is not None:
            self.player.stop(timeout_s)
        super().stop(timeout_s)
        self._stop_server()
        if isinstance(self.transport, MemoryTransport):
            self.transport.close()

    def _stop_server(self) -> None:
        if self.server is not None:
            self.server.stop()
            self._serving.join(5.0)
            self._refused = {"refused_token": self.server.refused_token, "refused_host": self.server.refused_host}
            self.server = None

    # -- the worker ------------------------------------------------------------------------------
    def _truth_at(self, sensor: str, timestamp_ns: int) -> list[dict] | None:
        if self.truth is None:
            return None
        t0 = self.truth_t0_ns
        if isinstance(t0, dict):  # a recording's: each sensor's
            t0 = t0.get(sensor)
        if t0 is None:
            with self._lock:
                t0 = self._t0_by_sensor.setdefault(sensor, timestamp_ns)
        return self.truth.truth(max(0.0, (timestamp_ns - t0) / 1e9))

    def _latency_ms(self, timestamp_ns: int) -> float | None:
        """Sensor time to the pages' queues (a recording's frames are old: none)."""
        return None if self.player is not None else (time.time_ns() - timestamp_ns) / 1e6

    def show_targets(self, sensor: str, msg: TargetsMsg, payload: bytes) -> None:
        raw = None
        if b'"sigma_' in payload and not any(f in t for t in msg.targets for f in TARGET_SIGMA_FIELDS):
            raw = json.loads(payload).get("targets")  # fields the wire decoder does not keep (yet)
        event = targets_event(msg, self.config.poses.get(sensor), self._truth_at(sensor, msg.timestamp_ns), raw)
        size = self.hub.publish("targets", event, key=("targets", sensor))
        self._count_out(sensor, 1, size, self._latency_ms(msg.timestamp_ns))

    def show_tracks(self, sensor: str, msg: TracksMsg, payload: bytes) -> None:
        size = self.hub.publish("tracks", tracks_event(msg, self.config.poses.get(sensor)), key=("tracks", sensor))
        self._count_out(sensor, 1, size)

    def show_profile(self, sensor: str, msg: QuantizedFrameMsg, radar: RadarConfig) -> None:
        event = profile_event(sensor, msg.seq, msg.timestamp_ns, profile_magnitude(msg, radar), radar)
        self._count_out(sensor, 1, self.hub.publish("profile", event, key=("profile", sensor)))

    def show_health(self, sensor: str, msg: HealthMsg, payload: bytes) -> None:
        size = self.hub.publish("health", health_event(sensor, msg), key=("health", sensor, msg.node))
        self._count_out(sensor, 1, size)

    # -- health ---------------------------------------------------------------------------------
    def health_extra(self, sensor_id: str) -> dict:
        return {**super().health_extra(sensor_id), "web": self.hub.totals()}

    def summary(self) -> dict:
        """The view's totals: where it listened (without its token), counters, sensors
        shown, pages and the events dropped for slow ones, requests refused."""
        url = None if self.url is None else self.url.split("?", 1)[0]
        srv = self.server
        refused = self._refused if srv is None else {"refused_token": srv.refused_token,
                                                      "refused_host": srv.refused_host}
        out = {"url": url, **super().summary(), **self.hub.totals(), **refused}
        if self.player is not None:
            out["recording"] = self.player.state()
        return out
