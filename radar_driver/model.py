"""The radar's physics: configuration, measured frequencies, range grid, and the
paper's signal model (eq. 2), batched over scenes.

Conventions held here and nowhere else:

* **Angle sign** (docs/design.md): antenna 2 sees ``G = exp(+i 2 pi f0 d sin(theta) / c)``
  relative to antenna 1, so a positive angle means the phase on antenna 2 *leads*
  antenna 1, and ``theta_hat = arcsin(c * angle(x2 * conj(x1)) / (2 pi f0 d))``.
  See :func:`antenna_phase_rad` and :func:`angle_from_antennas_rad`.
* **Cartesian axes**: ``x_m = R cos(theta)`` along boresight, ``y_m = R sin(theta)``
  across it (positive towards antenna 2's side); ``R e^{i theta} = x + i y``.
  See :func:`polar_to_xy`.
* **Frequencies**: measurement ``m`` of a frame of whole ramps is at
  ``f_m = f0 + B (m mod N) / N``; a subset is given as frequency indices in ``[0, N)``.
* **Motion**: the ramps of a frame are ``ramp_interval_s`` (dt) apart; a target of radial
  velocity v (m/s, + = moving away) is at ``R + v t`` at ramp time t, so its phase turns by
  ``phi = -4 pi f_c v dt / c`` from one ramp to the next at the sweep's middle frequency
  f_c (:func:`phase_step_rad`, :func:`velocity_from_phase_step`); a phase step is known
  modulo 2 pi, a velocity modulo ``c / (2 f_c dt)`` (:attr:`RadarConfig.velocity_ambiguity_mps`).

Arrays put the batch axis first: a scene batch has shape ``(B, K)``, a frame batch
``(B, M, 2)`` (measurement, antenna).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from .errors import ConfigError, InputError

SPEED_OF_LIGHT_M_S = 3e8
#: the ramp spacing of the simulated K-MD2 (and of the default sensor profile): two ramps a
#: frame at 20 frames a second, back to back, s
DEFAULT_RAMP_INTERVAL_S = 0.025


@dataclass(frozen=True)
class RadarConfig:
    """FMCW radar configuration; defaults are the paper's (Sec. 5) and the K-MD2's.

    Attributes
    ----------
    f0_hz : start (carrier) frequency f0, Hz.
    bandwidth_hz : sweep bandwidth B, Hz.
    samples_per_ramp : N, samples per saw-tooth ramp (= number of range bins).
    ramps_per_frame : whole ramps in a frame; M = ramps_per_frame * N.
    c_m_s : propagation speed c, m/s.
    antenna_spacing_m : d, m; ``None`` means half a wavelength, c / (2 f0).
    ramp_interval_s : dt, s, from one ramp's start to the next one's in a frame (the
        simulated K-MD2's: two ramps a frame, 20 frames a second, back to back; a real
        sensor's from its profile, :meth:`radar_driver.profile.SensorProfile.radar`).
        At its default it is left out of :meth:`config_id`, so the ids of configurations
        made before it existed stand.
    """

    f0_hz: float = 24e9
    bandwidth_hz: float = 250e6
    samples_per_ramp: int = 256
    ramps_per_frame: int = 2
    c_m_s: float = SPEED_OF_LIGHT_M_S
    antenna_spacing_m: float | None = None
    ramp_interval_s: float = DEFAULT_RAMP_INTERVAL_S

    def __post_init__(self) -> None:
        for name in ("f0_hz", "bandwidth_hz", "c_m_s", "ramp_interval_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ConfigError(f"RadarConfig.{name}={value!r} must be a finite number > 0")
        for name in ("samples_per_ramp", "ramps_per_frame"):
            value = getattr(self, name)
            if not (isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= 1):
                raise ConfigError(f"RadarConfig.{name}={value!r} must be an integer >= 1")
        if self.bandwidth_hz >= self.f0_hz:
            raise ConfigError(
                f"RadarConfig.bandwidth_hz={self.bandwidth_hz!r} must be below "
                f"f0_hz={self.f0_hz!r} (the model assumes B << f0)"
            )
        d = self.antenna_spacing_m
        if d is not None and not (isinstance(d, (int, float)) and np.isfinite(d) and d > 0):
            raise ConfigError(f"RadarConfig.antenna_spacing_m={d!r} must be a finite number > 0 or None")

    # -- derived quantities -------------------------------------------------------
    @property
    def d_m(self) -> float:
        """Antenna spacing d, m (half a wavelength unless set)."""
        if self.antenna_spacing_m is None:
            return self.c_m_s / (2.0 * self.f0_hz)
        return float(self.antenna_spacing_m)

    @property
    def center_frequency_hz(self) -> float:
        """f_c = f0 + B (N - 1) / (2 N), Hz: the frequency of the sweep's middle sample, where
        cml refers its amplitudes and its phase steps."""
        n = self.samples_per_ramp
        return self.f0_hz + self.bandwidth_hz * (n - 1) / (2.0 * n)

    @property
    def velocity_ambiguity_mps(self) -> float:
        """The interval of radial velocities a phase step between ramps tells apart,
        ``c / (2 f_c dt)`` = lambda_c / (2 dt), m/s (0.249 m/s for the defaults): velocities
        are known modulo it, in [-it / 2, it / 2)."""
        return self.c_m_s / (2.0 * self.center_frequency_hz * self.ramp_interval_s)

    @property
    def n_measurements(self) -> int:
        """M for a frame of whole ramps."""
        return self.samples_per_ramp * self.ramps_per_frame

    @property
    def range_resolution_m(self) -> float:
        """Range bin width dR = c / (2 B), m."""
        return self.c_m_s / (2.0 * self.bandwidth_hz)

    @property
    def max_range_m(self) -> float:
        """R_max = N dR, m."""
        return self.samples_per_ramp * self.range_resolution_m

    def range_grid_m(self) -> np.ndarray:
        """Range bins R_n = n dR, shape (N,), m."""
        return np.arange(self.samples_per_ramp) * self.range_resolution_m

    def frequencies_hz(self, indices: np.ndarray | None = None) -> np.ndarray:
        """Measured frequencies, Hz.

        ``indices=None``: the whole-ramp frame, shape (M,), ``f_m = f0 + B (m mod N) / N``.
        ``indices``: frequency indices in ``[0, N)`` of an explicit subset, any shape
        (e.g. ``(B, M)`` for one subset per scene); the result has the same shape.
        """
        n = self.samples_per_ramp
        if indices is None:
            k = np.arange(self.n_measurements) % n
        else:
            k = np.asarray(indices)
            if not np.issubdtype(k.dtype, np.integer):
                raise InputError(f"frequency indices must be integers, got dtype {k.dtype}")
            if k.size and (k.min() < 0 or k.max() >= n):
                raise InputError(
                    f"frequency indices must lie in [0, {n}), got min {k.min()} max {k.max()}"
                )
        return self.f0_hz + self.bandwidth_hz * k / n

    def config_id(self) -> int:
        """Stable 32-bit identifier of this configuration (first 4 bytes of the SHA-256
        of its sorted JSON), carried by every message made with it."""
        return _config_id(self)

    def to_dict(self) -> dict[str, Any]:
        """The fields as a mapping; ``ramp_interval_s`` only where it is not its default (the
        configurations written before it was a field stand as they were)."""
        data = asdict(self)
        if data["ramp_interval_s"] == DEFAULT_RAMP_INTERVAL_S:
            del data["ramp_interval_s"]
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "RadarConfig":
        """Build from a mapping, rejecting unknown keys by name."""
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"RadarConfig: unknown keys {unknown}; known keys are {sorted(known)}")
        return cls(**data)


# -- the angle convention -----------------------------------------------------------
def antenna_phase_rad(angle_rad: np.ndarray, config: RadarConfig) -> np.ndarray:
    """Phase of antenna 2 relative to antenna 1 for a target at ``angle_rad``:
    ``2 pi f0 d sin(theta) / c``, rad. Same shape as ``angle_rad``."""
    return 2.0 * np.pi * config.f0_hz * config.d_m * np.sin(angle_rad) / config.c_m_s


def angle_from_antennas_rad(x1: np.ndarray, x2: np.ndarray, config: RadarConfig) -> np.ndarray:
    """Angle estimate ``arcsin(c angle(x2 conj(x1)) / (2 pi f0 d))``, rad.

    ``x1``, ``x2``: complex range-profile values on antennas 1 and 2, same shape.
    The arcsin argument is clipped to [-1, 1] (with d = lambda/2 it always is).
    """
    phase = np.angle(x2 * np.conj(x1))
    s = config.c_m_s * phase / (2.0 * np.pi * config.f0_hz * config.d_m)
    return np.arcsin(np.clip(s, -1.0, 1.0))


def polar_to_plane(range_m: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """Positions x + i y = R e^{i theta} (m) of polar points: x along boresight, y across
    (positive angle = antenna 2 side). Same shape as the inputs."""
    return np.asarray(range_m) * np.exp(1j * np.asarray(angle_rad))


def polar_to_xy(range_m: np.ndarray, angle_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x_m, y_m) = (R cos theta, R sin theta): :func:`polar_to_plane` as two real arrays."""
    p = polar_to_plane(range_m, angle_rad)
    return p.real, p.imag


# -- the signal model (eq. 2) ---------------------------------------------------------
def range_phase(freqs_hz: np.ndarray, range_m: np.ndarray, config: RadarConfig) -> np.ndarray:
    """Range term ``exp(-i 4 pi f R / c)``; broadcasts ``freqs_hz`` against ``range_m``."""
    return np.exp(-1j * (4.0 * np.pi / config.c_m_s) * freqs_hz * range_m)


def carrier(config: RadarConfig) -> np.ndarray:
    """The f0 term of Phi on the range grid, ``exp(-i 4 pi f0 R_n / c)``, (N,); 1 for the
    paper's numbers (f0 / B integer), not in general."""
    return range_phase(config.f0_hz, config.range_grid_m(), config)


def phase_step_rad(velocity_mps: np.ndarray, config: RadarConfig) -> np.ndarray:
    """The phase step between consecutive ramps of a target of radial velocity
    ``velocity_mps`` (+ = away) at the sweep's middle frequency, ``-4 pi f_c v dt / c``, rad
    (not wrapped); same shape."""
    return -4.0 * np.pi * config.center_frequency_hz * config.ramp_interval_s / config.c_m_s * np.asarray(
        velocity_mps, dtype=float)


def velocity_from_phase_step(phase_step_rad: np.ndarray, config: RadarConfig) -> np.ndarray:
    """The radial velocity (m/s, + = away) of a phase step between ramps (rad): the inverse
    of :func:`phase_step_rad`; a step in (-pi, pi] gives the velocity in
    ``[-V/2, V/2)``, V = :attr:`RadarConfig.velocity_ambiguity_mps`. Same shape."""
    return -np.asarray(phase_step_rad, dtype=float) * config.c_m_s / (
        4.0 * np.pi * config.center_frequency_hz * config.ramp_interval_s)


def fold(x: np.ndarray, period: float) -> np.ndarray:
    """``x`` folded into ``[-period/2, period/2)``: its value modulo ``period`` nearest 0."""
    return (np.asarray(x, dtype=float) + period / 2.0) % period - period / 2.0


def wrap_velocity(velocity_mps: np.ndarray, config: RadarConfig) -> np.ndarray:
    """Velocities (m/s) folded into ``[-V/2, V/2)``, V the ambiguity interval
    (:attr:`RadarConfig.velocity_ambiguity_mps`): what a phase step between ramps can tell
    of them. Same shape."""
    return fold(velocity_mps, config.velocity_ambiguity_mps)


def sensing_matrix(config: RadarConfig, indices: np.ndarray | None = None) -> np.ndarray:
    """Range measurement matrix Phi, ``Phi_mn = exp(-i 4 pi f_m R_n / c)``.

    Shape (M, N) for ``indices=None`` or 1-D indices; (B, M, N) for (B, M) indices.
    """
    f = config.frequencies_hz(indices)
    return range_phase(f[..., :, None], config.range_grid_m(), config)


def simulate_frames(
    range_m: np.ndarray,
    angle_deg: np.ndarray,
    amplitude: np.ndarray,
    config: RadarConfig,
    indices: np.ndarray | None = None,
    ramps: int | None = None,
    velocity_mps: np.ndarray | None = None,
) -> np.ndarray:
    """Noiseless measurements Gamma = Phi [x, G x] of a batch of scenes (eq. 2).

    Parameters
    ----------
    range_m, angle_deg : (B, K) target ranges (m, on or off the range grid) and
        angles (deg, positive = antenna 2 leads); with velocities, the ranges at the
        middle of the frame.
    amplitude : (B, K) complex amplitudes x; 0 marks an absent target (with velocities,
        at the middle of the frame).
    indices : None for whole ramps, or (M,) / (B, M) frequency indices of a subset.
    ramps : whole ramps when ``indices`` is None (default ``config.ramps_per_frame``).
    velocity_mps : None (static), or (B, K) radial velocities (m/s, + = away), whole
        ramps only: ramp r, at ``t_r = (r - (R - 1) / 2) dt`` from the middle of the frame
        (dt = ``config.ramp_interval_s``), sees each target at ``R + v t_r``: its phase
        turns by ``4 pi f_m v dt / c`` from ramp to ramp at each frequency and its range
        moves by ``v dt`` (range migration). Each ramp's samples are taken at the ramp's
        time (the motion within a ramp is left out, as the simulated sensor leaves it).

    Returns
    -------
    (B, M, 2) complex128: Gamma, measurement x antenna.
    """
    range_m, angle_deg, amplitude = _check_scene(range_m, angle_deg, amplitude)
    gain2 = np.exp(1j * antenna_phase_rad(np.deg2rad(angle_deg), config))  # (B, K)
    per_target = np.stack([amplitude, amplitude * gain2], axis=-1)  # (B, K, 2)
    if velocity_mps is not None and indices is not None:
        raise InputError("velocity_mps needs whole ramps (indices=None)")
    if indices is None:
        f = config.frequencies_hz(np.arange(config.samples_per_ramp))
        reps = config.ramps_per_frame if ramps is None else ramps
        if isinstance(reps, bool) or not isinstance(reps, (int, np.integer)) or reps < 1:
            raise InputError(f"ramps={ramps!r} must be an integer >= 1")
        if velocity_mps is None:
            # one ramp, then tiled: every ramp sees the same N frequencies
            ramp = _project(f, range_m, per_target, config)  # (B, N, 2)
            return np.tile(ramp, (1, reps, 1))
        v = np.asarray(velocity_mps, dtype=float).reshape(range_m.shape)
        if not np.all(np.isfinite(v)):
            raise InputError("velocity_mps must be finite")
        t = (np.arange(reps) - (reps - 1) / 2.0) * config.ramp_interval_s  # (R,) from the frame's middle
        r_at = range_m[:, None, :] + v[:, None, :] * t[None, :, None]  # (B, R, K)
        if np.any(r_at < 0):
            raise InputError("a moving target's range falls below 0 within the frame")
        out = np.empty((range_m.shape[0], reps * config.samples_per_ramp, 2), complex)
        n = config.samples_per_ramp
        for r in range(reps):
            out[:, r * n:(r + 1) * n] = _project(f, r_at[:, r], per_target, config)
        return out
    f = config.frequencies_hz(indices)
    if f.ndim == 2 and f.shape[0] != range_m.shape[0]:
        raise InputError(f"indices batch {f.shape[0]} does not match scene batch {range_m.shape[0]}")
    return _project(f, range_m, per_target, config)


def _project(f: np.ndarray, range_m: np.ndarray, per_target: np.ndarray, config: RadarConfig) -> np.ndarray:
    """sum_k exp(-i 4 pi f_m R_k / c) * per_target[k, p] -> (B, M, 2)."""
    fm = f[None, :, None] if f.ndim == 1 else f[:, :, None]  # (B|1, M, 1)
    steer = range_phase(fm, range_m[:, None, :], config)  # (B, M, K)
    return np.einsum("bmk,bkp->bmp", steer, per_target)


def add_noise(
    frames: np.ndarray,
    snr_db: float,
    rng: np.random.Generator,
    reference_power: float | np.ndarray | None = None,
) -> np.ndarray:
    """Add circular complex white Gaussian noise at ``snr_db``.

    ``frames``: (B, M, 2). The signal power is ``reference_power`` if given (scalar or
    (B,)), else the mean |Gamma|^2 of each frame. Returns a new array.
    """
    frames = np.asarray(frames)
    if frames.ndim != 3 or frames.shape[-1] != 2:
        raise InputError(f"frames must have shape (B, M, 2), got {frames.shape}")
    if not np.isfinite(snr_db):
        raise InputError(f"snr_db={snr_db!r} must be finite")
    if reference_power is None:
        power = np.mean(np.abs(frames) ** 2, axis=(1, 2))
    else:
        power = np.broadcast_to(np.asarray(reference_power, dtype=float), frames.shape[:1])
    sigma = np.sqrt(power / 10 ** (snr_db / 10) / 2.0)[:, None, None]
    noise = rng.standard_normal(frames.shape) + 1j * rng.standard_normal(frames.shape)
    return frames + sigma * noise


def _check_scene(range_m, angle_deg, amplitude):
    range_m = np.asarray(range_m, dtype=float)
    angle_deg = np.asarray(angle_deg, dtype=float)
    amplitude = np.asarray(amplitude, dtype=complex)
    if range_m.ndim == 1:
        range_m, angle_deg, amplitude = range_m[None], np.atleast_2d(angle_deg), np.atleast_2d(amplitude)
    if not (range_m.shape == angle_deg.shape == amplitude.shape) or range_m.ndim != 2:
        raise InputError(
            "scene arrays must share one (B, K) shape: "
            f"range_m {range_m.shape}, angle_deg {angle_deg.shape}, amplitude {amplitude.shape}"
        )
    if np.any(range_m < 0) or not np.all(np.isfinite(range_m)):
        raise InputError("range_m must be finite and >= 0")
    if np.any(np.abs(angle_deg) > 90) or not np.all(np.isfinite(angle_deg)):
        raise InputError("angle_deg must be finite and within [-90, 90]")
    return range_m, angle_deg, amplitude


def snap_to_range_grid(range_m: np.ndarray, config: RadarConfig) -> np.ndarray:
    """Nearest range bin centre n dR (n in [0, N)) of each range, m; same shape."""
    dr = config.range_resolution_m
    n = np.clip(np.rint(np.asarray(range_m, dtype=float) / dr), 0, config.samples_per_ramp - 1)
    return n * dr


@lru_cache(maxsize=1024)
def _config_id(config: RadarConfig) -> int:
    """:meth:`RadarConfig.config_id`, computed once per configuration (the ramp spacing left
    out at its default: the ids from before it was a field)."""
    data = config.to_dict()
    blob = json.dumps(data, sort_keys=True).encode()
    return int.from_bytes(hashlib.sha256(blob).digest()[:4], "little")
