"""What :func:`pipeline.dsp.cml.cml` returns (:class:`CmlResult`), the same targets as
:class:`~pipeline.dsp.localize.Detections`, and the model's frames of given targets."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from radar_driver.model import RadarConfig, range_phase, velocity_from_phase_step

from pipeline.dsp.localize import Detections


@dataclass(frozen=True)
class CmlResult:
    """Targets found by :func:`pipeline.dsp.cml.cml`; per-target arrays strongest first.

    range_m : (B, K) ranges in [0, N dR), m (with a range gate: inside it), at the middle
        of the frame.
    amplitudes : (B, K, 2) complex amplitudes ``a_{t,p}`` of the model, frame units, at the
        middle of the frame (ramp r's: ``a exp(i (r - (R - 1) / 2) phi)``).
    statistic_db : (B, K) detection statistic, dB: the target's joint power
        ``|a1|^2 + |a2|^2`` over the mean joint power per range bin of the back
        projection of the final residual (``Z - xi - model``).
    sigma_eff : (B,) the last ``sigma_eff`` of the likelihood (std of each real part,
        frame units); for unquantized frames the RMS of the residual.
    present : (B, K) bool; with a count test (``pfa``) the targets past a frame's count
        are False (their other entries are meaningless), else all True.
    phase_step_rad : (B, K) each target's phase step from one ramp to the next, rad in
        (-pi, pi] (its radial velocity: :func:`radar_driver.model.velocity_from_phase_step`);
        NaN where the model is static (``CmlOptions(motion=False)``, frames of one ramp).
    """

    range_m: np.ndarray
    amplitudes: np.ndarray
    statistic_db: np.ndarray
    sigma_eff: np.ndarray
    present: np.ndarray
    phase_step_rad: np.ndarray

    def detections(self, config: RadarConfig) -> Detections:
        """The same targets as :class:`pipeline.dsp.localize.Detections`."""
        return cml_detections(self, config)

    @classmethod
    def empty(cls, k: int) -> "CmlResult":
        """The result of no frame, ``k`` targets a frame."""
        return cls(np.zeros((0, k)), np.zeros((0, k, 2), dtype=complex), np.zeros((0, k)), np.zeros(0),
                   np.zeros((0, k), dtype=bool), np.zeros((0, k)))

    @classmethod
    def concatenate(cls, parts: list["CmlResult"]) -> "CmlResult":
        """The results of consecutive blocks as one (a single one as it is)."""
        if len(parts) == 1:
            return parts[0]
        return cls(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(cls)))

    @classmethod
    def stack(cls, rows: list["CmlResult"]) -> "CmlResult":
        """The results of single frames (:meth:`row`) as one of a batch."""
        return cls(*(np.stack([getattr(r, f.name) for r in rows]) for f in fields(cls)))

    def row(self, j: int) -> "CmlResult":
        """Frame ``j``'s result (its arrays without the batch axis)."""
        return CmlResult(*(getattr(self, f.name)[j] for f in fields(self)))


def cml_detections(result: CmlResult, config: RadarConfig) -> Detections:
    """Range, angle (from the phase between the antennas), position, amplitude
    ``sqrt((|a1|^2 + |a2|^2) / 2)``, nearest range bin and radial velocity (from the phase
    step between ramps, in ``[-V/2, V/2)`` of the ambiguity V; NaN for the static model) of
    each target of ``result``: the operations of
    :func:`radar_driver.model.angle_from_antennas_rad` and :func:`~radar_driver.model.polar_to_xy`
    in their order (the same bits), fewer numpy calls."""
    a = result.amplitudes
    c, per_phase = config.c_m_s, 2.0 * np.pi * config.f0_hz * config.d_m
    dr, n = config.range_resolution_m, config.samples_per_ramp
    x = a[..., 1] * np.conj(a[..., 0])
    s = c * np.arctan2(x.imag, x.real) / per_phase  # np.angle, then the arcsin's argument
    angle = np.arcsin(np.minimum(np.maximum(s, -1.0), 1.0))  # np.clip's result, NaN kept
    r = result.range_m
    p = r * np.exp(1j * angle)
    power = np.abs(a)
    np.square(power, out=power)
    amp = np.sqrt((power[..., 0] + power[..., 1]) / 2.0)  # the sum over the 2 antennas
    bins = np.rint(np.where(np.isnan(r), 0.0, r) / dr).astype(np.int64) % n
    values = (r, np.rad2deg(angle), p.real, p.imag, amp)
    velocity = velocity_from_phase_step(result.phase_step_rad, config)
    velocity = np.minimum(velocity, 0.5 * config.velocity_ambiguity_mps * (1.0 - 1e-12))  # phi = -pi: in [-V/2, V/2)
    present = result.present
    if present.all():
        return Detections(*values, bins, result.statistic_db, None, radial_velocity_mps=velocity)
    present = present.astype(bool)  # a copy; then Detections.masked(present)'s, without the unmasked Detections
    return Detections(*(np.where(present, v, np.nan) for v in values), np.where(present, bins, -1),
                      np.where(present, result.statistic_db, np.nan), present,
                      radial_velocity_mps=np.where(present, velocity, np.nan))


def model_frames(range_m: np.ndarray, amplitudes: np.ndarray, config: RadarConfig, ramps: int,
                 phase_step_rad: np.ndarray | None = None) -> np.ndarray:
    """cml's model of ``ramps`` whole ramps: on ramp r, ``Gamma_{m,p} = sum_t a_{t,p}
    exp(i (r - (R - 1) / 2) phi_t) exp(-i 4 pi f_m r_t / c)``.

    range_m : (B, K), m; amplitudes : (B, K, 2) complex (at the middle of the frame);
    phase_step_rad : (B, K) or None (static: every ramp the same; NaN counts as 0).
    Returns (B, ramps N, 2) complex.
    """
    f = config.frequencies_hz(np.arange(config.samples_per_ramp))
    steer = range_phase(f[None, :, None], np.asarray(range_m, dtype=float)[:, None, :], config)  # (B, N, K)
    amp = np.asarray(amplitudes, dtype=complex)
    if phase_step_rad is None:
        ramp = np.einsum("bnk,bkp->bnp", steer, amp)
        return np.tile(ramp, (1, ramps, 1))
    phi = np.nan_to_num(np.asarray(phase_step_rad, dtype=float))
    c = np.arange(ramps) - (ramps - 1) / 2.0
    turn = np.exp(1j * c[None, :, None] * phi[:, None, :])  # (B, R, K)
    out = np.einsum("bnk,brk,bkp->brnp", steer, turn, amp)
    return out.reshape(out.shape[0], ramps * config.samples_per_ramp, 2)
