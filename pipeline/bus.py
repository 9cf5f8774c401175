"""Zenoh sessions and key expressions.

Default: an embedded peer with multicast scouting off, so nothing leaves the process
unless asked. ``connect`` / ``listen`` endpoints (e.g. ``tcp/127.0.0.1:7447``) join
nodes in other processes or on other hosts; a JSON5 config file can set anything else
(the endpoints and mode given here are applied on top of it).

Keys: ``<prefix>/<sensor>/{raw,quantized,targets,health}``; liveliness tokens at
``<prefix>/alive/<node>/<instance>``.
"""

from __future__ import annotations

import json
import uuid
from dataclasses import dataclass
from pathlib import Path

import zenoh

from .errors import BusError, ParameterError
from .wire import TOPICS


@dataclass(frozen=True)
class BusConfig:
    """mode: "peer", "client" or "router". prefix: the first key chunk (default radar)."""

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: Path | None = None
    prefix: str = "radar"
    multicast_scouting: bool = False

    def __post_init__(self) -> None:
        if self.mode not in ("peer", "client", "router"):
            raise ParameterError(f"zenoh mode={self.mode!r} must be peer, client or router")
        if not self.prefix or any(c in self.prefix for c in "*$?#@ ") or self.prefix.startswith("/") \
                or self.prefix.endswith("/"):
            raise ParameterError(f"key prefix {self.prefix!r} must be a plain key expression like 'radar' or 'lab/radar'")
        for ep in self.connect + self.listen:
            if "/" not in ep:
                raise ParameterError(f"endpoint {ep!r} must look like tcp/127.0.0.1:7447")
        if self.mode == "client" and not self.connect:
            raise ParameterError("a zenoh client needs at least one --connect endpoint")

    def zenoh_config(self) -> zenoh.Config:
        if self.config_file is not None:
            try:
                conf = zenoh.Config.from_file(str(self.config_file))
            except zenoh.ZError as exc:  # missing, unreadable or unparsable: the parser's message
                raise BusError(f"zenoh config file {self.config_file}: {exc}") from None
        else:
            conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        if self.connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        if self.listen:
            conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        elif self.config_file is None and self.mode == "peer" and not self.connect:
            # an isolated embedded peer: no listener needed
            conf.insert_json5("listen/endpoints", "[]")
        return conf

    def open(self) -> zenoh.Session:
        try:
            return zenoh.open(self.zenoh_config())
        except zenoh.ZError as exc:
            raise BusError(f"cannot open zenoh session (mode={self.mode}, connect={list(self.connect)}, "
                           f"listen={list(self.listen)}): {exc}") from None

    # -- keys ------------------------------------------------------------------------------
    def key(self, sensor_id: str, topic: str) -> str:
        if topic not in TOPICS:
            raise ParameterError(f"topic {topic!r} is not one of {TOPICS}")
        return f"{self.prefix}/{sensor_id}/{topic}"

    def wildcard(self, topic: str) -> str:
        return self.key("*", topic)

    def sensor_of(self, key: str) -> str | None:
        """The sensor chunk of ``<prefix>/<sensor>/<topic>``, or None if the key is not one."""
        head = self.prefix + "/"
        if not key.startswith(head):
            return None
        rest = key[len(head):].split("/")
        return rest[0] if len(rest) == 2 and rest[1] in TOPICS else None

    def liveliness_key(self, node: str) -> str:
        return f"{self.prefix}/alive/{node}/{uuid.uuid4().hex[:12]}"
