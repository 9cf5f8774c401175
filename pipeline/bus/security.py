"""``--secure``: mutual TLS and an access-control policy for the zenoh sessions.

A security directory (made by ``qradar security init``, see :mod:`qradar.security`) holds

- ``ca.pem``: the certificate of the project's own certificate authority;
- ``<name>.pem`` / ``<name>.key``: the certificate and private key of an identity (the
  certificate's common name is ``<name>``);
- ``identities.json``: every identity's role and sensors (the policy);
- ``ca.key`` only on the machine that issues certificates.

A session opened with a :class:`SecureConfig` speaks TLS only (``tls/`` endpoints; a
``unixsock-stream/`` socket, which file permissions protect, is allowed for local
processes), requires a certificate of the same CA from every remote (mTLS), and filters
every message from and to a remote by its certificate's common name with zenoh's
``access_control`` (default deny). What each role may publish, under prefix P:

=========  =====================================================================
role       may publish (put), besides reading everything under P
=========  =====================================================================
router     everything under P (it forwards the others' messages)
sensor     P/<id>/raw, P/<id>/quantized, P/<id>/health for its own ids
quantizer  P/<s>/quantized, P/<s>/health for the sensors it serves (default all)
localizer  P/<s>/targets, P/<s>/health for the sensors it serves (default all)
recorder   P/*/health
viewer     P/*/health
=========  =====================================================================

Each role may also declare liveliness tokens at P/alive/<its node>/* only (source,
quantize, localize, record, view). A local unix-socket peer (the driver processes of
``qradar run``) gets the sensor rights for every sensor.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

from radar_driver.limits import check_sensor_id

from pipeline.errors import BusError, ParameterError

POLICY_FILE = "identities.json"
POLICY_FORMAT = "qradar-identities"
POLICY_VERSION = 1
CA_CERT = "ca.pem"
CA_KEY = "ca.key"

ROLES = ("router", "sensor", "quantizer", "localizer", "recorder", "viewer")
# the liveliness name (Node.name) of the node each role runs: the node class that declares
# that role (Node.role; tests/test_security.py checks the two agree). A table here, not a
# look-up of the classes: the router enforces it and imports none of them
ROLE_NODE = {"sensor": "source", "quantizer": "quantize", "localizer": "localize", "recorder": "record",
             "viewer": "view"}
# the data topics each role may publish for its sensors
ROLE_TOPICS = {"sensor": ("raw", "quantized"), "quantizer": ("quantized",), "localizer": ("targets", "tracks"),
               "recorder": (), "viewer": ()}
ALL_SENSORS = ("*",)
LOCAL_LINKS = ("unixsock-stream",)  # trusted as far as the socket file's permissions go
SECURE_LINKS = ("tls",)

_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


def check_name(name: str) -> str:
    """Identity names are certificate common names and file names: 1-64 of [A-Za-z0-9_.-]."""
    if not (isinstance(name, str) and _NAME.fullmatch(name)):
        raise ParameterError(f"identity name {name!r} must be 1-64 characters of [A-Za-z0-9_.-], "
                             "starting with a letter or digit")
    return name


@dataclass(frozen=True)
class Identity:
    """One certificate holder. ``sensors``: a sensor's own ids; the ids a quantizer or
    localizer serves (``("*",)``: all); empty for the other roles. ``hosts``: the DNS
    names and IP addresses in the certificate (needed where the identity listens)."""

    name: str
    role: str
    sensors: tuple[str, ...] = ()
    hosts: tuple[str, ...] = ()
    not_after: str = ""  # the certificate's expiry, as openssl prints it (information only)

    def __post_init__(self) -> None:
        if self.role not in ROLES:
            raise ParameterError(f"identity {self.name!r}: role={self.role!r} must be one of {', '.join(ROLES)}")
        object.__setattr__(self, "sensors", tuple(self.sensors))
        object.__setattr__(self, "hosts", tuple(self.hosts))
        if self.role == "sensor":
            if not self.sensors or self.sensors == ALL_SENSORS:
                raise ParameterError(f"identity {self.name!r}: a sensor identity needs its sensor ids")
            for sid in self.sensors:
                _check_sensor(sid, self.name)
        elif self.role in ("quantizer", "localizer"):
            if not self.sensors:
                object.__setattr__(self, "sensors", ALL_SENSORS)
            elif self.sensors != ALL_SENSORS:
                for sid in self.sensors:
                    _check_sensor(sid, self.name)
        elif self.sensors:
            raise ParameterError(f"identity {self.name!r}: a {self.role} identity serves no particular sensors")
        check_name(self.name)

    def to_dict(self) -> dict:
        return {"name": self.name, "role": self.role, "sensors": list(self.sensors), "hosts": list(self.hosts),
                "not_after": self.not_after}

    def publishes(self, prefix: str) -> list[str]:
        """The key expressions this identity may put on (a router: all of ``prefix/**``)."""
        if self.role == "router":
            return [f"{prefix}/**"]
        sensors = self.sensors or ALL_SENSORS
        return [f"{prefix}/{s}/{t}" for s in sensors for t in (*ROLE_TOPICS[self.role], "health")]

    def may_publish(self, prefix: str, sensor_id: str, topic: str) -> bool:
        """Whether the policy lets this identity put on ``prefix/sensor_id/topic`` (what
        :meth:`publishes` lists, for one key of a sensor id)."""
        if self.role == "router":
            return True
        sensors = self.sensors or ALL_SENSORS
        return topic in (*ROLE_TOPICS[self.role], "health") and (sensors == ALL_SENSORS or sensor_id in sensors)

    def liveliness(self, prefix: str) -> list[str]:
        if self.role == "router":
            return [f"{prefix}/alive/**"]
        return [f"{prefix}/alive/{ROLE_NODE[self.role]}/*"]


def _check_sensor(sid: str, name: str) -> None:
    try:
        check_sensor_id(sid, ParameterError)
    except ParameterError as exc:
        raise ParameterError(f"identity {name!r}: {exc}") from None


@dataclass(frozen=True)
class Policy:
    """The identities of one CA (``identities.json``)."""

    identities: tuple[Identity, ...] = ()

    def __post_init__(self) -> None:
        names = [i.name for i in self.identities]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ParameterError(f"identities {dup} appear more than once")

    def get(self, name: str) -> Identity | None:
        return next((i for i in self.identities if i.name == name), None)

    def with_identity(self, ident: Identity) -> "Policy":
        if self.get(ident.name) is not None:
            raise ParameterError(f"identity {ident.name!r} exists already")
        return Policy(self.identities + (ident,))

    def without(self, name: str) -> "Policy":
        if self.get(name) is None:
            raise ParameterError(f"no identity {name!r} (known: {', '.join(i.name for i in self.identities)})")
        return Policy(tuple(i for i in self.identities if i.name != name))

    @classmethod
    def load(cls, directory: Path) -> "Policy":
        path = Path(directory) / POLICY_FILE
        try:
            obj = json.loads(path.read_text())
        except FileNotFoundError:
            raise BusError(f"{path} does not exist: is {directory} a directory made by `qradar security init`?") \
                from None
        except (OSError, ValueError) as exc:
            raise BusError(f"{path}: {exc}") from None
        if not isinstance(obj, dict) or obj.get("format") != POLICY_FORMAT or obj.get("version") != POLICY_VERSION:
            raise BusError(f"{path} is not a {POLICY_FORMAT} file of version {POLICY_VERSION}")
        try:
            return cls(tuple(Identity(i["name"], i["role"], tuple(i.get("sensors", ())), tuple(i.get("hosts", ())),
                                      str(i.get("not_after", ""))) for i in obj.get("identities", [])))
        except (KeyError, TypeError) as exc:
            raise BusError(f"{path}: an identity lacks {exc}") from None
        except ParameterError as exc:
            raise BusError(f"{path}: {exc}") from None

    def save(self, directory: Path) -> Path:
        path = Path(directory) / POLICY_FILE
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"format": POLICY_FORMAT, "version": POLICY_VERSION,
                                   "identities": [i.to_dict() for i in self.identities]}, indent=1) + "\n")
        tmp.replace(path)
        return path

    def access_control(self, prefix: str) -> dict:
        """zenoh's ``access_control`` block: default deny; every identity (by certificate
        common name) may read everything under ``prefix`` and publish what its role allows;
        a local unix-socket peer gets a sensor's rights for every sensor. (The ids of rules
        and subjects made from identity names all start with cn-, publish-, alive-,
        forward- or policy-: they cannot collide with the fixed ones.)"""
        everything = [f"{prefix}/**"]
        rules = [
            {"id": "read", "permission": "allow", "flows": ["ingress", "egress"], "key_exprs": everything,
             "messages": ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]},
            {"id": "receive", "permission": "allow", "flows": ["egress"], "key_exprs": everything,
             "messages": ["put", "delete", "liveliness_token"]},
        ]
        subjects, policies = [], []
        for ident in self.identities:
            sid = f"cn-{ident.name}"
            subjects.append({"id": sid, "cert_common_names": [ident.name]})
            rules.append({"id": f"publish-{ident.name}", "permission": "allow", "flows": ["ingress"],
                          "key_exprs": ident.publishes(prefix), "messages": ["put", "delete"]})
            rules.append({"id": f"alive-{ident.name}", "permission": "allow", "flows": ["ingress"],
                          "key_exprs": ident.liveliness(prefix), "messages": ["liveliness_token"]})
            names = ["read", "receive", f"publish-{ident.name}", f"alive-{ident.name}"]
            if ident.role == "router":  # it forwards every message of the others, in both directions
                rules.append({"id": f"forward-{ident.name}", "permission": "allow", "flows": ["ingress", "egress"],
                              "key_exprs": everything, "messages": list(ALL_MESSAGES)})
                names.append(f"forward-{ident.name}")
            policies.append({"id": f"policy-{ident.name}", "subjects": [sid], "rules": names})
        subjects.append({"id": "unixsock", "link_protocols": list(LOCAL_LINKS)})
        rules.append({"id": "unixsock-publish", "permission": "allow", "flows": ["ingress"],
                      "key_exprs": [f"{prefix}/*/raw", f"{prefix}/*/quantized", f"{prefix}/*/health"],
                      "messages": ["put", "delete"]})
        rules.append({"id": "unixsock-alive", "permission": "allow", "flows": ["ingress"],
                      "key_exprs": [f"{prefix}/alive/{ROLE_NODE['sensor']}/*"], "messages": ["liveliness_token"]})
        policies.append({"id": "unixsock-policy", "subjects": ["unixsock"],
                         "rules": ["read", "receive", "unixsock-publish", "unixsock-alive"]})
        return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
                "policies": policies}


ALL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "reply", "declare_queryable", "liveliness_token",
                "declare_liveliness_subscriber", "liveliness_query")


@dataclass(frozen=True)
class SecureConfig:
    """A session's security: the directory of :mod:`qradar.security` and the identity
    (certificate common name) it speaks as. Checks on construction that the CA, the
    identity's certificate and key and the policy are there."""

    directory: Path
    identity: str
    policy: Policy = field(init=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "directory", Path(self.directory))
        check_name(self.identity)
        if not self.directory.is_dir():
            raise BusError(f"--secure {self.directory}: no such directory (make one with `qradar security init`)")
        policy = Policy.load(self.directory)
        if policy.get(self.identity) is None:
            known = ", ".join(i.name for i in policy.identities) or "none"
            raise BusError(f"--secure {self.directory}: no identity {self.identity!r} in {POLICY_FILE} "
                           f"(known: {known}); choose one with --identity or issue it with `qradar security add`")
        for path in (self.ca_cert, self.cert, self.key):
            if not path.is_file():
                raise BusError(f"--secure {self.directory}: {path.name} is missing (identity {self.identity!r})")
        object.__setattr__(self, "policy", policy)

    @property
    def ca_cert(self) -> Path:
        return self.directory / CA_CERT

    @property
    def cert(self) -> Path:
        return self.directory / f"{self.identity}.pem"

    @property
    def key(self) -> Path:
        return self.directory / f"{self.identity}.key"

    def tls(self) -> dict:
        """zenoh's ``transport/link/tls`` settings: this identity on both sides of a link,
        the project CA as the only root, client certificates required."""
        return {"root_ca_certificate": str(self.ca_cert.resolve()),
                "listen_certificate": str(self.cert.resolve()), "listen_private_key": str(self.key.resolve()),
                "connect_certificate": str(self.cert.resolve()), "connect_private_key": str(self.key.resolve()),
                "enable_mtls": True, "verify_name_on_connect": True, "close_link_on_expiration": True}


def check_secure_endpoint(endpoint: str, where: str) -> None:
    """In secure mode only TLS (and local unix sockets) may carry the bus."""
    proto = endpoint.split("/", 1)[0]
    if proto not in SECURE_LINKS + LOCAL_LINKS:
        raise ParameterError(f"--secure: {where} endpoint {endpoint!r} is not encrypted; use tls/HOST:PORT "
                             f"(a {proto}/ endpoint would let anyone on the network in)")
