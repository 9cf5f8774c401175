"""The receiver front end of a real sensor: what stands between the paper's signal model
(eq. 2, :mod:`.model`) and the ADC words. The default :class:`FrontEnd` is the ideal
sensor (it changes nothing); a scene's ``[frontend]`` table (:mod:`.scene`) sets the
impairments a K-MD2 in a chamber shows (docs/design.md, "A real front end is not the paper's
model").

The chain, per receiver p (1, 2) and measurement m, all in full-scale units of the ADC::

    s_p[m]  = Gamma_p[m] + L[m]                        targets (eq. 2) + TX-to-RX leakage
    r_p[m]  = h_p s_p[m]                               receiver gain and phase
    y_p[m]  = mu r_p[m] + nu conj(r_p[m])              I/Q imbalance
    y'_p[m] = y_p[m] + (I_p + i Q_p)                   DC offset

then the sensor noise and the 12-bit ADC (:class:`.scene.SimScene`, :mod:`.simulator`).

* **Leakage** ``L[m] = a_L exp(i phi_L) exp(-i 4 pi f_m R_L / c)``: a beat tone at the
  leakage's range ``R_L`` (``leakage_range_m``), like a target there but with the same
  phase on both receivers (no angle term), amplitude ``a_L`` (``leakage_amplitude``) and
  phase ``phi_L`` (``leakage_phase_deg``). It enters at the receivers' inputs, so it goes
  through the same chain as the targets (the chain is linear over the reals: adding it
  before or after gives the same frame).
* **Receivers** ``h_1 = 1``, ``h_2 = 10^(rx2_gain_db / 20) exp(i rx2_phase_deg)``:
  receiver 2 relative to receiver 1. A positive phase makes antenna 2 lead, so the angle
  estimate (model.py's convention) reads ``sin(theta_hat) = sin(theta) + c phi_2 /
  (2 pi f0 d)``: 20 deg of phase at d = lambda / 2 is 6.4 deg of angle at boresight.
* **I/Q imbalance**, the Q path relative to the I path, the same on both receivers
  (gain ``g = 10^(iq_gain_db / 20)``, phase ``phi = iq_phase_deg``; one mixer design, one
  LO splitter)::

      I' = I
      Q' = g (Q cos(phi) - I sin(phi))

  i.e. ``y = mu r + nu conj(r)`` with ``mu = (1 + g e^{-i phi}) / 2`` and
  ``nu = (1 - g e^{+i phi}) / 2`` (the widely linear form of the same model). A target's
  tone at range bin n, ``exp(-i 2 pi n k / N)``, leaves a mirror ("ghost") ``nu conj(.)``
  at bin ``N - n`` (the negative beat frequency), ``20 log10(|mu| / |nu|)`` dB weaker:
  that ratio is the image rejection ratio (IRR, :attr:`FrontEnd.image_rejection_db`);
  0.5 dB and 3 deg give 28.2 dB. The ghost's phase between the receivers is the
  target's negated (``conj``), so it also sits at the mirrored angle.
* **DC offset** ``(I_p, Q_p)`` per receiver, full-scale units (``dc_offset``): ADC
  mid-code error and mixer self-mixing; it lands in range bin 0.

This is the model of a homodyne I/Q receiver used to calibrate radar front ends (e.g.
the ghost-peak calibration of US patent 10 527 713 B2, "Radar I-Q mismatching measurement
and calibration"); MATLAB's ``iqimbal`` splits the same imbalance half on I, half on Q,
which differs from this one only by a complex gain.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np

from .errors import ConfigError, InputError
from .model import RadarConfig, range_phase


def _number(value: Any, where: str, lo: float | None = None, hi: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{where}: {value!r} is not a finite number")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        bounds = f"[{lo}, {hi}]" if hi is not None else f"[{lo}, inf)"
        raise ConfigError(f"{where}: {value!r} is outside {bounds}")
    return float(value)


def _dc_pairs(value: Any, where: str) -> tuple[tuple[float, float], tuple[float, float]]:
    shape_ok = (isinstance(value, (list, tuple)) and len(value) == 2
                and all(isinstance(p, (list, tuple)) and len(p) == 2 for p in value))
    if not shape_ok:
        raise ConfigError(f"{where}: {value!r} must be [[I1, Q1], [I2, Q2]] (full-scale units, per receiver)")
    return tuple(tuple(_number(v, f"{where}[{i}][{j}]", -1.0, 1.0) for j, v in enumerate(p))
                 for i, p in enumerate(value))  # type: ignore[return-value]


@dataclass(frozen=True)
class FrontEnd:
    """The receiver impairments of a sensor (module docstring: the chain and its units).
    Every default is the ideal sensor.

    Attributes
    ----------
    dc_offset : ((I1, Q1), (I2, Q2)), full-scale units, per receiver; each in [-1, 1].
    leakage_amplitude : TX-to-RX leakage at the ADC, full-scale units, in [0, 1].
    leakage_range_m : its range, m, >= 0 (electrical length of the coupling path, radome).
    leakage_phase_deg : its phase, deg (the same on both receivers).
    rx2_gain_db, rx2_phase_deg : receiver 2 relative to receiver 1, dB in [-40, 40], deg.
    iq_gain_db, iq_phase_deg : the Q path relative to the I path (both receivers), dB in
        [-20, 20], deg in [-45, 45].
    """

    dc_offset: tuple[tuple[float, float], tuple[float, float]] = ((0.0, 0.0), (0.0, 0.0))
    leakage_amplitude: float = 0.0
    leakage_range_m: float = 0.0
    leakage_phase_deg: float = 0.0
    rx2_gain_db: float = 0.0
    rx2_phase_deg: float = 0.0
    iq_gain_db: float = 0.0
    iq_phase_deg: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "dc_offset", _dc_pairs(self.dc_offset, "FrontEnd.dc_offset"))
        limits = {"leakage_amplitude": (0.0, 1.0), "leakage_range_m": (0.0, None), "leakage_phase_deg": (None, None),
                  "rx2_gain_db": (-40.0, 40.0), "rx2_phase_deg": (None, None), "iq_gain_db": (-20.0, 20.0),
                  "iq_phase_deg": (-45.0, 45.0)}
        for name, (lo, hi) in limits.items():
            object.__setattr__(self, name, _number(getattr(self, name), f"FrontEnd.{name}", lo, hi))

    # -- the chain's coefficients ---------------------------------------------------------
    @property
    def ideal(self) -> bool:
        """True when the front end changes nothing (the paper's sensor)."""
        return self == FrontEnd()

    @property
    def rx_gain(self) -> np.ndarray:
        """(h_1, h_2) = (1, 10^(rx2_gain_db/20) e^{i rx2_phase}), complex (2,)."""
        return np.array([1.0, 10 ** (self.rx2_gain_db / 20) * np.exp(1j * np.deg2rad(self.rx2_phase_deg))])

    @property
    def iq_coefficients(self) -> tuple[complex, complex]:
        """(mu, nu) of ``y = mu r + nu conj(r)``: ``mu = (1 + g e^{-i phi}) / 2``,
        ``nu = (1 - g e^{+i phi}) / 2``."""
        g, phi = 10 ** (self.iq_gain_db / 20), math.radians(self.iq_phase_deg)
        return (1 + g * np.exp(-1j * phi)) / 2, (1 - g * np.exp(1j * phi)) / 2

    @property
    def image_rejection_db(self) -> float:
        """Image rejection ratio ``20 log10(|mu| / |nu|)``, dB (inf without imbalance): how
        much weaker a target's mirror at bin N - n is than the target."""
        mu, nu = self.iq_coefficients
        return math.inf if abs(nu) == 0 else 20 * math.log10(abs(mu) / abs(nu))

    @property
    def dc(self) -> np.ndarray:
        """DC offset per receiver as complex numbers ``I_p + i Q_p``, (2,)."""
        return np.array([complex(i, q) for i, q in self.dc_offset])

    def leakage(self, config: RadarConfig, indices: np.ndarray | None = None, m: int | None = None) -> np.ndarray:
        """The leakage tone ``L[m]`` (full-scale units) at the measured frequencies: for a
        frame of ``m`` measurements of whole ramps (``indices`` None; m a multiple of N),
        shape (M,); for frequency indices of shape (M,) or (B, M), that shape."""
        if indices is None:
            n = config.samples_per_ramp
            if m is None or m % n:
                raise InputError(f"a frame of whole ramps has a multiple of {n} measurements, got {m}")
            f = config.frequencies_hz(np.arange(m) % n)
        else:
            f = config.frequencies_hz(indices)
        a = self.leakage_amplitude * np.exp(1j * np.deg2rad(self.leakage_phase_deg))
        return a * range_phase(f, self.leakage_range_m, config)

    # -- the chain -------------------------------------------------------------------------
    def apply(self, frames: np.ndarray, config: RadarConfig, indices: np.ndarray | None = None) -> np.ndarray:
        """The noiseless frames at the ADC's input: the targets' frames through this front
        end (leakage, receiver gain and phase, I/Q imbalance, DC; module docstring).

        Parameters
        ----------
        frames : (B, M, 2) or (M, 2) complex, full-scale units: Gamma of the targets
            (measurement, receiver), as :func:`~.model.simulate_frames` makes it.
        config : the radar (frequencies of the leakage tone).
        indices : None for frames of whole ramps (M a multiple of N), or the frequency
            indices (M,) / (B, M) of a subset, as for :func:`~.model.simulate_frames`.

        Returns
        -------
        A new complex128 array of the shape of ``frames``.
        """
        z = np.asarray(frames)
        if z.ndim not in (2, 3) or z.shape[-1] != 2:
            raise InputError(f"frames must have shape (B, M, 2) or (M, 2), got {z.shape}")
        z = z.astype(complex)  # a copy: the input is never changed
        if self.ideal:
            return z
        if self.leakage_amplitude:
            leak = self.leakage(config, indices, z.shape[-2])
            if leak.shape[-1] != z.shape[-2] or (leak.ndim == 2 and (z.ndim != 3 or leak.shape[0] != z.shape[0])):
                raise InputError(f"indices of shape {np.shape(indices)} do not match frames of shape {z.shape}")
            z += leak[..., None]  # the same on both receivers
        z *= self.rx_gain
        mu, nu = self.iq_coefficients
        if nu != 0:
            z = mu * z + nu * np.conj(z)
        z += self.dc
        return z

    # -- scene files -----------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["dc_offset"] = [list(p) for p in self.dc_offset]
        return d

    @classmethod
    def from_dict(cls, data: Any, where: str = "[frontend]") -> "FrontEnd":
        """Build from a scene's ``[frontend]`` table; unknown keys and bad values are a
        ConfigError that starts with ``where`` (the file and the table) and names the key."""
        if not isinstance(data, dict):
            raise ConfigError(f"{where}: must be a table")
        unknown = sorted(set(data) - set(FRONTEND_KEYS))
        if unknown:
            raise ConfigError(f"{where}: unknown keys {unknown}; known: {list(FRONTEND_KEYS)}")
        try:
            return cls(**data)
        except ConfigError as exc:
            raise ConfigError(f"{where}: {str(exc).removeprefix('FrontEnd.')}") from None


#: the keys of a scene's [frontend] table
FRONTEND_KEYS = tuple(f.name for f in fields(FrontEnd))
