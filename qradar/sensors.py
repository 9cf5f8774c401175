"""The real sensors of ``qradar run --sensor URL,id=NAME[,KEY=VALUE...]``: one spec each,
validated when it is read, with one-line errors that quote the spec.

A spec is a pyserial URL (a device path, ``socket://host:port``, ``rfc2217://host:port``)
or ``auto``, and then, separated by commas, the sensor's options, as ``qradar drive`` takes them:

- ``id``: the sensor's id in the zenoh keys (required; 1-16 of [A-Za-z0-9_-]);
- ``profile``: a packaged sensor profile or a TOML file (default kmd2-blocks);
- ``baud``: the line speed after INIT (default: 2 000 000 on a device path or
  ``rfc2217://``; a ``socket://`` link stays at the start-up 115200);
- ``ramps``: ramps per frame, M = 256 x ramps (default 2);
- ``chirp-select``: with several chirps per RADC, ``first`` or ``stride``.

The URL ``auto`` (``auto,id=kmd2-0[,profile=...]``) stands for the one K-MD2 that answers
on this host's serial adapters: :func:`resolve_auto` probes them (``INIT`` and ``GBYE``,
as ``qradar ports --probe`` does, :mod:`radar_driver.ports`) and puts that port in its
place, or fails in one line naming what it found.

Before a run starts anything, :func:`check_sensor_specs` refuses two sensors of one id or
one port, and :func:`probe_sensors` opens each port once and closes it (a device path
exclusively, as its driver will), so that a port that cannot be opened, or a device held
by another process, is one line naming the sensor (and the holder)."""

from __future__ import annotations

import logging
import math
import os
import typing
from dataclasses import dataclass, field, replace

from pipeline.errors import ParameterError, WireError
from pipeline.wire import check_sensor_id
from radar_driver import ports as serial_ports
from radar_driver.errors import ConfigError, DiscoveryError, LinkError, RadarError
from radar_driver.model import RadarConfig
from radar_driver.options import Option, OptionValueError, finite_float, like, option, options_of, read_text
from radar_driver.profile import CHIRP_SELECT, DEFAULT_PROFILE_NAME, resolve_profile
from radar_driver.session import LinkKind, SensorSession, SessionConfig, link_kind

log = logging.getLogger("qradar.sensors")

#: the URL of a spec that stands for the one K-MD2 found on this host's serial ports
AUTO = "auto"


@dataclass(frozen=True)
class SensorSpec:
    """One real sensor of a run: its URL, id and driver options (see the module), the
    options of ``qradar drive`` (:class:`~radar_driver.session.SessionConfig`: the same
    defaults and checks), and where it stands (``pose``, a lab file's key: the views
    place it there, and a ``--truth`` file's world positions are seen from it). The
    ``--sensor`` grammar and a lab file's ``[[sensor]]`` table read the same fields
    (:meth:`parse`, :func:`qradar.cli.schema.read_table`)."""

    url: str = option(help="a pyserial URL (a device path, socket://HOST:PORT, rfc2217://HOST:PORT) or auto (the one "
                      "K-MD2 that answers on this host's serial adapters)", required=True)
    sensor_id: str = like(SessionConfig, "sensor_id", flag="--id", required=True,
                          help="the sensor's id in the zenoh keys (1-16 of [A-Za-z0-9_-])")
    profile: str | None = like(SessionConfig, "profile")
    baud: int | None = like(SessionConfig, "baud")
    ramps: int = like(SessionConfig, "ramps_per_frame", flag="--ramps")
    chirp_select: str = like(SessionConfig, "chirp_select")
    pose: tuple[float, ...] | None = option(
        None, "where the sensor stands in the world: [x_m, y_m, yaw_deg] (yaw counter-clockwise; boresight along "
        "the world's x at 0); default: at the origin", cli=False, many=3, parse=finite_float, metavar="X_M Y_M YAW")
    host: str | None = option(None, "qradar up: the host whose `up --host` starts this sensor's driver (default: "
                              "[hosts] default)", cli=False)
    text: str = field(default="", compare=False)  # the spec as given, for messages

    def __post_init__(self) -> None:
        where = self.where
        try:
            check_sensor_id(self.sensor_id)
        except WireError as exc:
            raise ParameterError(f"{where}: id: {exc}") from None
        if self.chirp_select not in CHIRP_SELECT:
            raise ParameterError(f"{where}: chirp-select={self.chirp_select!r} must be one of {list(CHIRP_SELECT)}")
        if self.pose is not None:
            if len(self.pose) != 3 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in self.pose):
                raise ParameterError(f"{where}: pose={list(self.pose)!r} must be [x_m, y_m, yaw_deg], three numbers")
            object.__setattr__(self, "pose", tuple(float(v) for v in self.pose))
        try:
            self.session_config()  # the profile, the baud among its speeds, the ramps in its chirps
        except ConfigError as exc:
            raise ParameterError(f"{where}: {exc}") from None

    @property
    def profile_name(self) -> str:
        return self.profile or DEFAULT_PROFILE_NAME

    @property
    def is_auto(self) -> bool:
        """The URL is ``auto``: the port is found by :func:`resolve_auto`."""
        return self.url == AUTO

    @property
    def where(self) -> str:
        return f"--sensor {self.text or self.url!r}"

    def session_config(self, outstanding: int = 1) -> SessionConfig:
        return SessionConfig(self.url, baud=self.baud, ramps_per_frame=self.ramps, sensor_id=self.sensor_id,
                             profile=self.profile, chirp_select=self.chirp_select, outstanding=outstanding)

    def radar(self) -> RadarConfig:
        """The radar configuration its frames carry."""
        return self.session_config().radar()

    def port_key(self) -> str:
        """What names the port, for telling two specs of one port apart: a device path's
        real path, a network URL's scheme, host and port."""
        kind = link_kind(self.url)
        if kind is LinkKind.DEVICE and not self.is_auto:
            return os.path.realpath(self.url)
        return self.url.split("?", 1)[0].lower()

    @classmethod
    def spec_keys(cls) -> dict[str, tuple[str, Option]]:
        """The keys a spec may give after its URL: key -> (field, option)."""
        return {o.key(name): (name, o) for name, (_, o) in options_of(cls).items() if o.cli and name != "url"}

    @classmethod
    def parse(cls, text: str) -> "SensorSpec":
        """``URL,id=NAME[,KEY=VALUE...]``; ParameterError (one line, quoting ``text``) on
        an unknown, repeated or empty key, a missing id, a bad value or profile. Each value
        reads as the option of its field does (``qradar drive``'s)."""
        where = f"--sensor {text!r}"
        keys = cls.spec_keys()
        if not isinstance(text, str) or not text.strip():
            raise ParameterError(f"{where}: empty; expected {SPEC_FORM}")
        url, *fields = [f.strip() for f in text.split(",")]
        if not url:
            raise ParameterError(f"{where}: no URL before the first comma; expected {SPEC_FORM}")
        if url.partition("=")[0].strip() in keys:
            raise ParameterError(f"{where}: starts with the key {url!r}; the URL comes first: {SPEC_FORM}")
        kw: dict[str, object] = {}
        for f in fields:
            key, sep, value = (s.strip() for s in f.partition("="))
            if not sep:
                raise ParameterError(f"{where}: {f!r} is not KEY=VALUE; expected {SPEC_FORM}")
            if key not in keys:
                raise ParameterError(f"{where}: unknown key {key!r}; known: {', '.join(keys)}")
            name, opt = keys[key]
            if name in kw:
                raise ParameterError(f"{where}: {key} given twice")
            if not value:
                raise ParameterError(f"{where}: {key}= has no value")
            kw[name] = _read(opt, name, key, value, where)
        if "sensor_id" not in kw:
            raise ParameterError(f"{where}: missing id=NAME (the sensor's id in the zenoh keys, e.g. "
                                 f"{url},id=kmd2-0)")
        try:
            resolve_profile(kw.get("profile"))
        except RadarError as exc:
            raise ParameterError(f"{where}: profile: {exc}") from None
        return cls(url, text=text, **kw)


def _read(opt: Option, name: str, key: str, value: str, where: str):
    """A spec's value as its field's option reads it; ``key=value`` and why, if it does not."""
    try:
        return read_text(opt, typing.get_type_hints(SensorSpec)[name], value)
    except (OptionValueError, ConfigError, ValueError) as exc:
        shown = value if value.lstrip("-").replace(".", "", 1).isdigit() else repr(value)
        detail = str(exc) if isinstance(exc, OptionValueError) else f"is not valid: {exc}"
        raise ParameterError(f"{where}: {key}={shown} {detail}") from None


#: the form of a spec, for messages
SPEC_FORM = "URL,id=NAME[,profile=P][,baud=B][,ramps=R][,chirp-select=first|stride]"


def as_spec(spec: SensorSpec | str) -> SensorSpec:
    return spec if isinstance(spec, SensorSpec) else SensorSpec.parse(spec)


def check_sensor_specs(specs: tuple[SensorSpec, ...]) -> RadarConfig:
    """Refuse two specs of one id or one port, and sensors whose frames a run's nodes
    could not all take (another radar configuration than the first's, the ramps apart);
    returns that configuration."""
    if not specs:
        raise ParameterError("no sensor given")
    ids: dict[str, SensorSpec] = {}
    ports: dict[str, SensorSpec] = {}
    autos = [s for s in specs if s.is_auto]
    if len(autos) > 1:
        raise ParameterError(f"{autos[1].where}: {AUTO} stands for the one K-MD2 found on this host, and "
                             f"{autos[0].where} takes it; give the other sensors their ports (`qradar ports "
                             f"--probe` lists them)")
    for s in specs:
        if s.sensor_id in ids:
            raise ParameterError(f"{s.where}: id {s.sensor_id!r} is taken by {ids[s.sensor_id].where}; each "
                                 f"sensor needs its own id")
        ids[s.sensor_id] = s
        key = s.port_key()
        if key in ports:
            raise ParameterError(f"{s.where}: {s.url} is the port of sensor {ports[key].sensor_id} too (a port "
                                 f"has one owner)")
        ports[key] = s
    base = replace(specs[0].radar(), ramps_per_frame=1)
    for s in specs[1:]:
        if replace(s.radar(), ramps_per_frame=1) != base:
            raise ParameterError(f"{s.where}: its profile {s.profile_name!r} makes frames of another radar "
                                 f"configuration than sensor {specs[0].sensor_id}'s ({specs[0].profile_name!r}); "
                                 f"one run processes one (its ramps per frame apart)")
    return replace(base, ramps_per_frame=specs[0].ramps)


def probe_sensors(specs: tuple[SensorSpec, ...]) -> None:
    """Open each sensor's port and close it at once, sending nothing: a LinkError naming
    the sensor for the first that cannot be opened (who holds a busy device, what to
    check). ``socket://`` and ``rfc2217://`` ports are connected to once."""
    for s in specs:
        try:
            SensorSession(s.session_config()).probe()
        except LinkError as exc:
            raise LinkError(f"sensor {s.sensor_id}: {exc}") from exc


def resolve_auto(specs: tuple[SensorSpec, ...],
                 timeout_s: float = serial_ports.PROBE_TIMEOUT_S) -> tuple[SensorSpec, ...]:
    """``specs`` with an ``auto`` spec's URL replaced by the port of the one K-MD2 that
    answers on this host's serial adapters (``radar_driver.ports.list_serial_ports``, less
    the ports the other specs name), said in one log line; a DiscoveryError (one line:
    what was found, and ``qradar ports --probe``) when none or several answer."""
    auto = next((s for s in specs if s.is_auto), None)
    if auto is None:
        return specs
    taken = {s.port_key() for s in specs if not s.is_auto}
    listed = serial_ports.list_serial_ports()  # the one place the candidates come from
    candidates = [p.device for p in listed if os.path.realpath(p.device) not in taken]
    if not candidates:
        others = f" besides {', '.join(sorted(taken))}" if taken else ""
        raise DiscoveryError(f"{auto.where}: no serial port found on this host{others} (is the sensor plugged in "
                             f"and its adapter's driver loaded? `qradar ports` lists them; docs/chamber.md)")
    results = serial_ports.probe_ports(candidates, profile=auto.profile, timeout_s=timeout_s, listed=listed)
    found = [r for r in results if r.is_kmd2]
    if len(found) == 1:
        log.info("%s: the K-MD2 on %s", auto.where, found[0].name)
        return tuple(replace(s, url=found[0].url) if s.is_auto else s for s in specs)
    if found:
        names = ", ".join(r.name for r in found)
        raise DiscoveryError(f"{auto.where}: {len(found)} K-MD2s answer: {names}; give one its port, e.g. "
                             f"--sensor {found[0].url},id={auto.sensor_id} (`qradar ports --probe` lists them)")
    seen = "; ".join(f"{r.url}: {r.answer.words}" for r in results)
    raise DiscoveryError(f"{auto.where}: no K-MD2 answered on the {len(results)} serial port(s) of this host "
                         f"({seen}); `qradar ports --probe` says why for each")
