"""Zenoh sessions and key expressions.

Default: an embedded peer with multicast scouting off and no listener, so nothing
leaves the process and nothing comes in unless asked. ``connect`` / ``listen``
endpoints (e.g. ``tcp/127.0.0.1:7447``) join nodes in other processes or on other
hosts; a JSON5 config file can set anything else (the endpoints and mode given here are
applied on top of it). A session listens only on the endpoints given here or in the
file's ``listen/endpoints``: never on zenoh's implicit ``tcp/[::]:0`` (peer) or
``tcp/[::]:7447`` (router), which would open a port on every interface.

``secure`` (:class:`pipeline.bus.security.SecureConfig`) turns on mutual TLS and the
access-control policy, and refuses every endpoint that is not ``tls/`` (or a local
``unixsock-stream/``), also those of the config file.

Keys: ``<prefix>/<sensor>/{raw,quantized,targets,health}``; liveliness tokens at
``<prefix>/alive/<node>/<instance>``.
"""

from __future__ import annotations

import json
import re
import sys
import threading
import time
import uuid
import zlib
from dataclasses import dataclass
from typing import TextIO
from pathlib import Path

import zenoh

from radar_driver.limits import SENSOR_ID_CHARS
from radar_driver.options import option

from pipeline.bus import audit, router_check
from pipeline.errors import BusError, ParameterError
from pipeline.bus.security import SecureConfig, check_secure_endpoint
from pipeline.keys import TOPICS

_RUST_SOURCE = re.compile(r"\s+at\s+\S+\.rs:\d+\.?\s*$")


def zenoh_reason(exc: BaseException) -> str:
    """zenoh's message of ``exc`` on one line, without the Rust source path it ends in
    (`` at /root/.cargo/.../orchestrator.rs:447.``), which tells a user nothing."""
    return " ".join(_RUST_SOURCE.sub("", str(exc)).split())


_DEFAULT_ENDPOINTS = {key: zenoh.Config().get_json(key) for key in ("listen/endpoints", "connect/endpoints")}


def check_prefix(prefix: str, what: str = "key prefix") -> str:
    """``prefix``, a plain key expression (``radar``, ``lab/radar``: no wildcard, no leading or
    trailing ``/``, no empty chunk ``//``); a ParameterError naming ``what`` otherwise."""
    if not prefix or any(c in prefix for c in "*$?#@ ") or "" in prefix.split("/"):
        raise ParameterError(f"{what} {prefix!r} must be a plain key expression like 'radar' or 'lab/radar'")
    return prefix


@dataclass(frozen=True)
class BusConfig:
    """mode: "peer", "client" or "router". prefix: the first key chunk (default radar)."""

    mode: str = option("peer", "zenoh mode", choices=("peer", "client"))
    connect: tuple[str, ...] = option((), "e.g. tcp/127.0.0.1:7447 (with --secure: tls/HOST:PORT)", many="append",
                                      metavar="ENDPOINT")
    listen: tuple[str, ...] = option((), "e.g. tcp/127.0.0.1:7447; none by default (nothing listens unless asked, "
                                     "here or in --zenoh-config)", many="append", metavar="ENDPOINT")
    config_file: Path | None = option(None, "zenoh JSON5 config file", flag="--zenoh-config")
    prefix: str = option("radar", "key prefix (default radar)")
    multicast_scouting: bool = False
    secure: SecureConfig | None = None
    #: zenoh's shared-memory transport; off: with it (zenoh's default) each new publisher
    #: session left a 16 MB pool mapped in the router and every subscriber for as long as
    #: they ran (16-20 MB more a restart, tests/test_restarts.py). It overrides the config file.
    shared_memory: bool = False
    #: a stand-alone command's name: its session says so once on stderr if it reaches no
    #: other process within ALONE_AFTER_S (None: no such check, e.g. in-process sessions)
    alone_warning: str | None = None

    def __post_init__(self) -> None:
        if self.mode not in ("peer", "client", "router"):
            raise ParameterError(f"zenoh mode={self.mode!r} must be peer, client or router")
        check_prefix(self.prefix)
        for ep in self.connect + self.listen:
            if "/" not in ep:
                raise ParameterError(f"endpoint {ep!r} must look like tcp/127.0.0.1:7447")
        if self.mode == "client" and not self.connect:
            raise ParameterError("a zenoh client needs at least one --connect endpoint")
        if self.secure is not None:
            for what, eps in (("connect", self.connect), ("listen", self.listen)):
                for ep in eps:
                    check_secure_endpoint(ep, what)

    def _file_config(self) -> zenoh.Config:
        if self.config_file is None:
            return zenoh.Config()
        try:
            return zenoh.Config.from_file(str(self.config_file))
        except zenoh.ZError as exc:  # missing, unreadable or unparsable: the parser's message
            raise BusError(f"zenoh config file {self.config_file}: {zenoh_reason(exc)}") from None

    def _endpoints(self, conf: zenoh.Config, what: str) -> list[str]:
        """``what`` (listen or connect) endpoints of ``conf`` for this mode; zenoh's
        defaults count as none (a file that leaves them alone asks for nothing)."""
        raw = conf.get_json(f"{what}/endpoints")
        if raw == _DEFAULT_ENDPOINTS[f"{what}/endpoints"]:
            return []
        value = json.loads(raw)
        if isinstance(value, dict):  # per mode: {router: [...], peer: [...], client: [...]}
            value = value.get(self.mode, [])
        out = []
        for ep in value or []:  # an endpoint, or {"strategy": ..., "locators": [...]}
            out.extend(ep.get("locators", []) if isinstance(ep, dict) else [ep])
        return [str(ep) for ep in out]

    def listen_endpoints(self) -> list[str]:
        """Where a session of this config listens: ``listen``, else the config file's
        endpoints for this mode, else nowhere."""
        return list(self.listen) or self._endpoints(self._file_config(), "listen")

    def zenoh_config(self) -> zenoh.Config:
        conf = self._file_config()
        file_listen = self._endpoints(conf, "listen")
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        conf.insert_json5("transport/shared_memory/enabled", json.dumps(self.shared_memory))
        if self.connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        if self.listen or not file_listen:  # no implicit listener on every interface
            conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        if self.secure is not None:
            where = f"zenoh config file {self.config_file}" if self.config_file is not None else "zenoh config"
            for what in ("connect", "listen"):
                for ep in self._endpoints(conf, what):
                    check_secure_endpoint(ep, f"{where}: {what}")
            for key, value in self.secure.tls().items():
                conf.insert_json5(f"transport/link/tls/{key}", json.dumps(value))
            conf.insert_json5("access_control", json.dumps(self.secure.policy.access_control(self.prefix)))
        return conf

    def open(self) -> zenoh.Session:
        conf = self.zenoh_config()
        try:
            session = zenoh.open(conf)
        except zenoh.ZError as exc:
            who = "" if self.secure is None else f", secure as {self.secure.identity!r} from {self.secure.directory}"
            hint = ""
            if self.secure is not None and self.connect:
                hint = ("; under --secure only the router's own certificate, naming the host dialled, is accepted: "
                        "is the router running with its identity (`qradar router --secure DIR`) and its certificate "
                        "made for that host (`qradar security init --host HOST`)?")
            raise BusError(f"cannot open zenoh session (mode={self.mode}, connect={list(self.connect)}, "
                           f"listen={self.listen_endpoints()}{who}): {zenoh_reason(exc)}{hint}") from None
        if self.secure is not None:
            audit.attach(session)  # (nothing unless the command turned the audit on)
            router_check.install(session, self)  # the peers dialled are router identities (BusError, closed, if not)
        if self.alone_warning is not None:
            warn_if_alone(session, self)
        return session

    def alone_text(self, after_s: float) -> str:
        """The one line a session that has reached no other process says: where it
        looked and what to do."""
        where = f"mode {self.mode}, connect {list(self.connect)}, listen {self.listen_endpoints()}"
        head = f"{self.alone_warning}: no zenoh peer or router reached in {after_s:g} s ({where})"
        if self.connect:
            return (f"{head}: nothing answers at {', '.join(self.connect)}; is `qradar router --listen ...` (or "
                    f"the node listening there) running, and the address right?")
        if self.listen_endpoints():
            return f"{head}: no process has connected yet; give the others --connect {self.listen_endpoints()[0]}"
        return (f"{head}: this process is alone; separate processes meet through a router: start `qradar router "
                f"--listen tcp/127.0.0.1:7447` and give each command --mode client --connect tcp/127.0.0.1:7447")

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


#: a stand-alone command whose session reaches no other process within this says so, s
ALONE_AFTER_S = 3.0


def reaches_anyone(session: zenoh.Session) -> bool:
    """The session has an open transport to another zenoh process (a router, a peer, or
    a client connected to it)."""
    info = session.info
    if hasattr(info, "transports"):  # zenoh-python >= 1.6: clients connected to this one count too
        return bool(info.transports())
    return bool(info.routers_zid() or info.peers_zid())


def warn_if_alone(session: zenoh.Session, bus: BusConfig, after_s: float = ALONE_AFTER_S,
                  stream: TextIO | None = None) -> threading.Thread:
    """After ``after_s``, once: if ``session`` reaches no other process, write
    :meth:`BusConfig.alone_text` to ``stream`` (stderr). A daemon thread; a session closed
    meanwhile says nothing."""

    def check() -> None:
        time.sleep(after_s)
        try:
            if session.is_closed() or reaches_anyone(session):
                return
            print(bus.alone_text(after_s), file=stream or sys.stderr, flush=True)
        except (zenoh.ZError, OSError, ValueError):  # closed under us, or stderr gone
            pass

    t = threading.Thread(target=check, name="zenoh-alone-check", daemon=True)
    t.start()
    return t


def check_sensor_pattern(pattern: str) -> str:
    """A key chunk naming sensors: characters of a sensor id and ``*`` wildcards (``*`` =
    every sensor, ``b1*`` = the ids starting with b1); anything else is a ParameterError."""
    ok = isinstance(pattern, str) and 1 <= len(pattern) <= 64 and all(
        c in SENSOR_ID_CHARS or c == "*" for c in pattern) and "**" not in pattern
    if not ok:
        raise ParameterError(f"sensor pattern {pattern!r} must be one key chunk of [A-Za-z0-9_-] and * wildcards "
                             "(e.g. '*' or 'b1*')")
    return pattern


def pattern_chunk(pattern: str) -> str:
    """The zenoh key chunk of a sensor pattern: ``*`` stays, a ``*`` inside a chunk
    becomes zenoh's sub-chunk wildcard ``$*`` (``b1*`` -> ``b1$*``)."""
    return pattern if pattern == "*" else check_sensor_pattern(pattern).replace("*", "$*")


@dataclass(frozen=True)
class Shard:
    """Shard ``index`` of ``count``: the sensors whose stable hash ``crc32(sensor id) mod
    count`` is ``index``. Processes with shards 0/n .. n-1/n serve every sensor exactly once,
    whichever host they run on and in whatever order they start."""

    index: int
    count: int

    def __post_init__(self) -> None:
        if not (isinstance(self.count, int) and isinstance(self.index, int) and 0 <= self.index < self.count):
            raise ParameterError(f"shard {self.index!r}/{self.count!r} must be i/n with 0 <= i < n")

    @classmethod
    def parse(cls, text: str) -> "Shard":
        """``"i/n"``, e.g. ``"0/2"``."""
        try:
            i, n = (int(x) for x in text.split("/"))
        except ValueError:
            raise ParameterError(f"shard {text!r} must be i/n, e.g. 0/2") from None
        return cls(i, n)

    def serves(self, sensor_id: str) -> bool:
        return zlib.crc32(sensor_id.encode()) % self.count == self.index

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"
