"""Scenes for the simulated K-MD2, loaded from TOML.

```toml
name = "chamber"
noise_std = 0.02          # complex white noise, std of each of I and Q, full-scale units

[radar]                   # optional RadarConfig overrides (a simulated K-MD2 refuses those
ramps_per_frame = 2       # it does not measure: f0, bandwidth, antenna spacing are its own)

[[target]]
range_m = 4.8
angle_deg = -25.0         # positive = antenna 2 leads
amplitude = 0.06          # full-scale units at the ADC
phase_deg = 0.0           # optional
velocity_m_s = 0.0        # optional radial velocity, + = moving away

[frontend]                # optional: the receiver's impairments (radar_driver/frontend.py);
dc_offset = [[0.03, -0.02], [-0.025, 0.035]]   # [[I1, Q1], [I2, Q2]], full-scale units
leakage_amplitude = 0.3   # TX-to-RX leakage, full-scale units, same phase on both receivers
leakage_range_m = 0.15
leakage_phase_deg = 40.0
rx2_gain_db = 1.0         # receiver 2 relative to receiver 1
rx2_phase_deg = 30.0
iq_gain_db = 0.5          # the Q path relative to the I path, both receivers
iq_phase_deg = 3.0
```

Every ``[frontend]`` key defaults to the ideal sensor. Amplitudes are in units of the
ADC's full scale (see ``profile.RadcLayout``); the sum of the amplitudes (targets,
leakage, DC) plus a few noise stds should stay below 1 to avoid clipping.

A scene's ramps are the targets through the paper's model (eq. 2,
:meth:`SimScene.target_ramps`), then the front end (:meth:`SimScene.clean_ramps`), then
the sensor noise (:meth:`SimScene.noise`); the simulated K-MD2 and the in-process
simulated sensors put them through the 12-bit ADC.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ConfigError
from .frontend import FrontEnd
from .model import RadarConfig, polar_to_xy, simulate_frames


@dataclass(frozen=True)
class SimTarget:
    """One point reflector: range (m), angle (deg, positive = antenna 2 leads),
    amplitude at the ADC (full-scale units), phase (deg), radial velocity (m/s, + = away)."""

    range_m: float
    angle_deg: float
    amplitude: float
    phase_deg: float = 0.0
    velocity_m_s: float = 0.0

    def __post_init__(self) -> None:
        _number(self.range_m, "SimTarget.range_m", 0.0)
        _number(self.angle_deg, "SimTarget.angle_deg", -90.0, 90.0)
        _number(self.amplitude, "SimTarget.amplitude", 0.0)
        _number(self.phase_deg, "SimTarget.phase_deg")
        _number(self.velocity_m_s, "SimTarget.velocity_m_s")

    def range_at(self, t_s: np.ndarray | float) -> np.ndarray:
        """Range (m) at time ``t_s`` (s) since the start, never below 0."""
        return np.maximum(self.range_m + self.velocity_m_s * np.asarray(t_s, dtype=float), 0.0)


@dataclass(frozen=True)
class SimScene:
    """Targets, sensor noise, radar configuration and receiver front end of a simulated
    K-MD2 (``front_end``: the ideal sensor unless the scene has a ``[frontend]`` table)."""

    targets: tuple[SimTarget, ...]
    noise_std: float = 0.0
    radar: RadarConfig = field(default_factory=RadarConfig)
    name: str = "scene"
    front_end: FrontEnd = field(default_factory=FrontEnd)

    def target_ramps(self, t_s) -> np.ndarray:
        """The targets' ramps (R, N, 2), full-scale units, at times ``t_s`` (R,) s: the
        paper's model (eq. 2) for the targets where they are at each time, before the
        front end."""
        if not self.targets:
            return np.zeros((np.size(t_s), self.radar.samples_per_ramp, 2), complex)
        return simulate_frames(*self.arrays(t_s), self.radar, ramps=1)

    def clean_ramps(self, t_s) -> np.ndarray:
        """Noiseless ramps (R, N, 2) at the ADC's input, full-scale units, at times ``t_s``
        (R,) s: :meth:`target_ramps` through the front end (leakage, receiver gain and
        phase, I/Q imbalance, DC: :meth:`.frontend.FrontEnd.apply`). With the ideal front
        end, the paper's model."""
        return self.front_end.apply(self.target_ramps(t_s), self.radar)

    def clean_ramp(self, t_s: float) -> np.ndarray:
        """One noiseless ramp (N, 2) at time ``t_s`` (s)."""
        return self.clean_ramps([t_s])[0]

    def without_targets(self) -> "SimScene":
        """The same sensor in the same room with nothing in it (``--empty``): front end
        (leakage, DC, ...) and noise only; named ``<name>-empty``."""
        return replace(self, targets=(), name=f"{self.name}-empty")

    def noise(self, n_ramps: int, rng: np.random.Generator | None) -> np.ndarray:
        """Complex white noise of ``noise_std`` per I and Q for ``n_ramps`` ramps: (R, N, 2).
        Ramp by ramp, the real parts are drawn before the imaginary ones, so R ramps at
        once draw the same numbers as R calls for one. Nothing is drawn without noise."""
        shape = (n_ramps, self.radar.samples_per_ramp, 2)
        if self.noise_std == 0:
            return np.zeros(shape, complex)
        if rng is None:
            raise ConfigError("SimScene.noise: noise_std > 0 needs an rng")
        g = rng.standard_normal((n_ramps, 2) + shape[1:])
        return self.noise_std * (g[:, 0] + 1j * g[:, 1])

    def ramps(self, t_s, rng: np.random.Generator | None = None) -> np.ndarray:
        """:meth:`clean_ramps` plus :meth:`noise`: what the sensor's receivers see, (R, N, 2)."""
        clean = self.clean_ramps(t_s)
        return clean + self.noise(clean.shape[0], rng)

    def ramp(self, t_s: float, rng: np.random.Generator | None = None) -> np.ndarray:
        """One noisy ramp (N, 2) at time ``t_s`` (s)."""
        return self.ramps([t_s], rng)[0]

    def truth(self, t_s: float = 0.0) -> list[dict[str, float]]:
        """Ground truth at ``t_s``: range_m, angle_deg, x_m, y_m, amplitude and radial
        velocity (``radial_velocity_mps``, + = away) per target (the front end's leakage and
        I/Q ghosts are not targets)."""
        out = []
        for tg in self.targets:
            r = float(tg.range_at(t_s))
            x, y = polar_to_xy(r, math.radians(tg.angle_deg))
            v = tg.velocity_m_s if r > 0.0 or tg.velocity_m_s > 0 else 0.0  # stopped at the sensor
            out.append({"range_m": r, "angle_deg": tg.angle_deg, "x_m": float(x), "y_m": float(y),
                        "amplitude": tg.amplitude, "radial_velocity_mps": v})
        return out

    def arrays(self, t_s=0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(range_m, angle_deg, complex amplitude), each (T, K), at the times ``t_s`` (s; a
        number: T = 1; (T,), e.g. a recording's ``t_s``): the scene as the batch arrays
        :func:`~.model.simulate_frames` takes."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        if t.ndim != 1 or not np.all(np.isfinite(t)):
            raise ConfigError(f"SimScene.arrays: t_s must be a number or (T,) finite seconds, got shape {t.shape}")
        k = len(self.targets)
        ranges = np.stack([tg.range_at(t) for tg in self.targets], axis=1) if k else np.zeros((t.size, 0))
        return (ranges,
                np.tile(np.array([tg.angle_deg for tg in self.targets], dtype=float), (t.size, 1)),
                np.tile(np.array([tg.amplitude * np.exp(1j * np.deg2rad(tg.phase_deg)) for tg in self.targets],
                                 dtype=complex), (t.size, 1)))

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "noise_std": self.noise_std,
            "radar": self.radar.to_dict(),
            "target": [vars(t).copy() for t in self.targets],
            "frontend": self.front_end.to_dict(),
        }


_TARGET_KEYS = {"range_m", "angle_deg", "amplitude", "phase_deg", "velocity_m_s"}
_TOP_KEYS = {"name", "noise_std", "radar", "target", "frontend"}


def _number(value: Any, where: str, lo: float | None = None, hi: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{where}: {value!r} is not a finite number")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise ConfigError(f"{where}: {value!r} is outside [{lo}, {hi}]")
    return float(value)


def scene_from_dict(data: dict[str, Any], source: str = "<scene>") -> SimScene:
    """Validate a parsed scene; errors name ``source`` and the offending key."""
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise ConfigError(f"{source}: unknown keys {unknown}; known: {sorted(_TOP_KEYS)}")
    if not data:  # an empty room is a scene without [[target]] tables, its noise given (noise_std = 0.0 for none)
        raise ConfigError(f"{source}: holds no scene (no key of {sorted(_TOP_KEYS)}): an empty file, or the wrong one")
    radar_data = data.get("radar", {})
    if not isinstance(radar_data, dict):
        raise ConfigError(f"{source}: [radar] must be a table")
    try:
        radar = RadarConfig.from_dict(radar_data)
    except ConfigError as exc:
        raise ConfigError(f"{source}: [radar]: {exc}") from None
    noise = _number(data.get("noise_std", 0.0), f"{source}: noise_std", 0.0, 1.0)
    raw_targets = data.get("target", [])
    if not isinstance(raw_targets, list):
        raise ConfigError(f"{source}: targets must be given as [[target]] tables")
    targets = []
    for i, t in enumerate(raw_targets):
        where = f"{source}: target {i + 1}"
        if not isinstance(t, dict):
            raise ConfigError(f"{where}: must be a table")
        extra = sorted(set(t) - _TARGET_KEYS)
        if extra:
            raise ConfigError(f"{where}: unknown keys {extra}; known: {sorted(_TARGET_KEYS)}")
        for key in ("range_m", "angle_deg", "amplitude"):
            if key not in t:
                raise ConfigError(f"{where}: missing {key}")
        targets.append(SimTarget(
            range_m=_number(t["range_m"], f"{where}: range_m", 0.0, radar.max_range_m),
            angle_deg=_number(t["angle_deg"], f"{where}: angle_deg", -90.0, 90.0),
            amplitude=_number(t["amplitude"], f"{where}: amplitude", 0.0, 1.0),
            phase_deg=_number(t.get("phase_deg", 0.0), f"{where}: phase_deg"),
            velocity_m_s=_number(t.get("velocity_m_s", 0.0), f"{where}: velocity_m_s", -1000.0, 1000.0),
        ))
    same = [(i + 1, j + 1) for j, b in enumerate(targets) for i, a in enumerate(targets[:j])
            if (a.range_m, a.angle_deg, a.velocity_m_s) == (b.range_m, b.angle_deg, b.velocity_m_s)]
    if same:  # one reflector of their amplitudes summed, which no localizer reports as two
        raise ConfigError(f"{source}: targets {same[0][0]} and {same[0][1]} stand at the same range and angle "
                          "(one reflector to the radar): give one, with their amplitudes summed")
    front_end = FrontEnd.from_dict(data.get("frontend", {}), f"{source}: [frontend]")
    if front_end.leakage_range_m >= radar.max_range_m:
        raise ConfigError(f"{source}: [frontend]: leakage_range_m: {front_end.leakage_range_m!r} is outside "
                          f"[0, {radar.max_range_m}) (the radar's range)")
    name = data.get("name", Path(source).stem)
    if not isinstance(name, str):
        raise ConfigError(f"{source}: name must be a string")
    return SimScene(tuple(targets), noise, radar, name, front_end)


def load_scene(path: str | Path) -> SimScene:
    """Load and validate a TOML scene file."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read scene file {path}: {exc.strerror or exc}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    return scene_from_dict(data, str(path))


def load_truth(name_or_path: str | Path) -> SimScene:
    """The true positions of ``--truth``: a scene file as :mod:`radar_driver.scene` reads
    (or a packaged scene's name), of which only the targets' ranges and angles (and a
    velocity, from the run's start) count, so a target's ``amplitude`` may be left out.
    ConfigError naming ``--truth`` and the file, also for a file without a target."""
    path = Path(name_or_path)
    try:
        if not path.exists() and path.suffix == "" and len(path.parts) == 1:
            scene = resolve_scene(path.name)  # a packaged scene
        else:
            try:
                data = tomllib.loads(path.read_text())
            except OSError as exc:
                raise ConfigError(f"cannot read {path}: {exc.strerror or exc}") from None
            except tomllib.TOMLDecodeError as exc:
                raise ConfigError(f"{path}: not valid TOML: {exc}") from None
            targets = data.get("target")
            if isinstance(targets, list):
                data["target"] = [{"amplitude": 1.0, **t} if isinstance(t, dict) else t for t in targets]
            scene = scene_from_dict(data, str(path))
    except ConfigError as exc:
        raise ConfigError(f"--truth: {exc}") from None
    if not scene.targets:
        raise ConfigError(f"--truth: {name_or_path} has no [[target]] (range_m, angle_deg): no position to "
                          "compare with")
    return scene


#: time base of the ramps (ramps/s) of a sensor that is polled as fast as it answers
NOMINAL_RAMP_RATE_HZ = 40.0
#: the scene of a simulated sensor unless told (a packaged scene's name)
DEFAULT_SCENE = "chamber"
#: a simulated K-MD2's frames per second unless told (a K-MD2 makes about 20 measurements a second)
SIM_RATE_HZ = 20.0
#: a simulated sensor's frames per second at most: fifty times a K-MD2's, beyond what one
#: localizer decodes (a frame rate of 1e9 made a run count 12 billion frames dropped)
MAX_SIM_RATE_HZ = 1000.0


def check_sim_rate(rate_hz: float, what: str = "rate_hz", zero: str | None = None,
                   error: type[Exception] = ConfigError) -> None:
    """An ``error`` unless ``rate_hz`` is a number in (0, MAX_SIM_RATE_HZ] frames/s, or 0
    when ``zero`` says what 0 means."""
    low_ok = rate_hz >= 0 if zero else rate_hz > 0
    if isinstance(rate_hz, bool) or not (isinstance(rate_hz, (int, float)) and low_ok and rate_hz <= MAX_SIM_RATE_HZ):
        raise error(f"{what}={rate_hz!r} must be a number in {'[0' if zero else '(0'}, {MAX_SIM_RATE_HZ:g}] "
                          f"frames/s{f' ({zero})' if zero else ''}: a K-MD2 makes about 20 a second")


#: time base of the frames (frames/s) of a sensor that is polled as fast as it answers
NOMINAL_FRAME_RATE_HZ = 20.0


def ramp_time_s(ramp_index, ramp_rate_hz: float) -> np.ndarray:
    """Time (s) of ramp ``ramp_index`` (int or array) of a sensor measuring ``ramp_rate_hz``
    ramps a second, evenly (0: free-running, on the nominal time base)."""
    return np.asarray(ramp_index, dtype=float) / (ramp_rate_hz or NOMINAL_RAMP_RATE_HZ)


def frame_ramp_times_s(frame_index, ramps, frame_rate_hz: float, ramp_interval_s: float) -> np.ndarray:
    """Times (s) of ramps ``ramps`` (int or array, from 0) of frame ``frame_index`` of a sensor
    measuring ``frame_rate_hz`` frames a second (0: free-running, on the nominal time base),
    its ramps ``ramp_interval_s`` apart from the frame's start (the radar's
    :attr:`~radar_driver.model.RadarConfig.ramp_interval_s`, the profile's chirp spacing):
    ``k / rate + r dt``. At 20 frames a second and two ramps 25 ms apart, the ramps are
    evenly spaced, as :func:`ramp_time_s` at 40 ramps a second."""
    return (float(frame_index) / (frame_rate_hz or NOMINAL_FRAME_RATE_HZ)
            + np.asarray(ramps, dtype=float) * ramp_interval_s)


SCENES_DIR = Path(__file__).with_name("scenes")


def packaged_scenes() -> list[str]:
    """Names of the scenes shipped in radar_driver/scenes/."""
    return sorted(p.stem for p in SCENES_DIR.glob("*.toml"))


def resolve_scene(name_or_path: str | Path) -> SimScene:
    """Load a scene file, or a packaged scene by name (``chamber``, ``single``, ...)."""
    path = Path(name_or_path)
    if not path.exists() and path.suffix == "" and len(path.parts) == 1:
        packaged = SCENES_DIR / f"{path.name}.toml"
        if not packaged.exists():
            raise ConfigError(f"no scene file {str(path)!r} and no packaged scene of that name; "
                              f"packaged: {packaged_scenes()}")
        path = packaged
    return load_scene(path)
