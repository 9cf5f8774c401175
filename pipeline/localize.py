"""Projected back projection (PBP, paper eq. 5) and target extraction.

``X_hat = P_Theta_K(Phi^* Z / M)``: back-project the (quantized) measurements, keep the
K range bins with the largest joint energy ``(|U_n1|^2 + |U_n2|^2)^(1/2)``, then read
range from the bin and angle from the phase between the antennas.

Two back projections give the same ``Phi^* Z / M``:

* :func:`back_project_ramps` for frames of whole ramps: fold the ramps, one inverse
  FFT of length N per antenna, times ``exp(+i 4 pi f0 R_n / c)``: O(M + N log N).
* :func:`back_project_dense` for any set of frequencies (a subset, per frame or shared):
  an explicit ``Phi^H Z``: O(M N).

Shapes: Z is (B, M, 2); U and X_hat are (B, N, 2); supports and targets are (B, K),
ordered strongest first.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from radar_driver.model import (RadarConfig, angle_from_antennas_rad, carrier, polar_to_plane, polar_to_xy,
                                sensing_matrix)

from .errors import ParameterError


def _check_z(z: np.ndarray) -> np.ndarray:
    z = np.asarray(z)
    if z.ndim != 3 or z.shape[-1] != 2:
        raise ParameterError(f"Z must have shape (B, M, 2), got {z.shape}")
    return z


def back_project_ramps(z: np.ndarray, config: RadarConfig) -> np.ndarray:
    """``Phi^* Z / M`` for frames of whole ramps (fast path).

    z : (B, M, 2) with M a multiple of N (measurement m at frequency index m mod N).
    Returns U, (B, N, 2) complex.
    """
    z = _check_z(z)
    n = config.samples_per_ramp
    b, m, _ = z.shape
    if m == 0 or m % n:
        raise ParameterError(f"M={m} is not a whole number of ramps of N={n} samples")
    folded = z.reshape(b, m // n, n, 2).sum(axis=1)  # (B, N, 2)
    # sum_k folded_k exp(+i 2 pi k n / N) = N * ifft; the f0 term exp(+i 4 pi f0 R_n / c)
    spectrum = np.fft.ifft(folded, axis=1) * (n / m)
    return spectrum * np.conj(carrier(config))[None, :, None].astype(spectrum.dtype)


def back_project_dense(z: np.ndarray, config: RadarConfig, indices: np.ndarray | None = None) -> np.ndarray:
    """``Phi^* Z / M`` for any frequencies (dense path).

    z : (B, M, 2). indices : None (whole ramps), (M,) shared or (B, M) per-frame
    frequency indices in [0, N). Returns U, (B, N, 2) complex.
    """
    z = _check_z(z)
    if indices is None or np.ndim(indices) == 1:
        key = None if indices is None else np.asarray(indices, dtype=np.int64).tobytes()
        phi = _shared_adjoint(config, key)  # (M, N), cached: a live stream reuses one subset
    else:
        phi = sensing_matrix(config, indices)  # (B, M, N)
    if phi.shape[-2] != z.shape[1] or (phi.ndim == 3 and phi.shape[0] != z.shape[0]):
        raise ParameterError(f"Z {z.shape} does not match the frequencies {phi.shape[:-1]}")
    if phi.ndim == 2:
        u = np.einsum("mn,bmp->bnp", phi, z, optimize=True)
    else:
        u = np.einsum("bmn,bmp->bnp", np.conj(phi), z, optimize=True)
    return u / z.shape[1]


@lru_cache(maxsize=32)
def _shared_adjoint(config: RadarConfig, indices_key: bytes | None) -> np.ndarray:
    """conj(Phi) for whole ramps (key None) or one shared subset (int64 bytes); read-only."""
    indices = None if indices_key is None else np.frombuffer(indices_key, dtype=np.int64)
    phi = np.conj(sensing_matrix(config, indices))
    phi.flags.writeable = False
    return phi


def back_project(z: np.ndarray, config: RadarConfig, indices: np.ndarray | None = None) -> np.ndarray:
    """``Phi^* Z / M``: the FFT path for whole ramps (``indices=None``), dense otherwise."""
    if indices is None:
        return back_project_ramps(z, config)
    return back_project_dense(z, config, indices)


def joint_support(u: np.ndarray, k: int) -> np.ndarray:
    """Indices of the K bins with the largest ``(|U_n1|^2 + |U_n2|^2)^(1/2)``,
    strongest first: (B, N, 2) -> (B, K) int."""
    u = np.asarray(u)
    n = u.shape[1]
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= k <= n:
        raise ParameterError(f"K={k!r} must be an integer in [1, N={n}]")
    energy = (np.abs(u) ** 2).sum(axis=2)  # monotone in the joint norm
    top = np.argpartition(-energy, k - 1, axis=1)[:, :k]
    order = np.argsort(-np.take_along_axis(energy, top, axis=1), axis=1, kind="stable")
    return np.take_along_axis(top, order, axis=1)


def project_theta_k(u: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """P_Theta_K(U): zero all but the K strongest rows (joint support).

    Returns (X_hat (B, N, 2), support (B, K) strongest first).
    """
    support = joint_support(u, k)
    x = np.zeros_like(u)
    rows = np.take_along_axis(u, support[:, :, None], axis=1)
    np.put_along_axis(x, support[:, :, None], rows, axis=1)
    return x, support


def pbp(z: np.ndarray, config: RadarConfig, k: int, indices: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """PBP estimate ``P_Theta_K(Phi^* Z / M)``: (X_hat (B, N, 2), support (B, K))."""
    return project_theta_k(back_project(z, config, indices), k)


@dataclass(frozen=True)
class Detections:
    """Targets found in a batch of frames; every array is (B, K), strongest first.

    range_m (m), angle_deg (deg, positive = antenna 2 leads), x_m / y_m (m, x along
    boresight), amplitude (joint magnitude / sqrt(2), frame units), bin (range bin).
    """

    range_m: np.ndarray
    angle_deg: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    amplitude: np.ndarray
    bin: np.ndarray

    def frame(self, i: int) -> list[dict[str, float]]:
        """The targets of frame ``i`` as plain dicts (for JSON)."""
        return [
            {
                "range_m": float(self.range_m[i, j]),
                "angle_deg": float(self.angle_deg[i, j]),
                "x_m": float(self.x_m[i, j]),
                "y_m": float(self.y_m[i, j]),
                "amplitude": float(self.amplitude[i, j]),
                "bin": int(self.bin[i, j]),
            }
            for j in range(self.range_m.shape[1])
        ]


def detections_from_support(u: np.ndarray, support: np.ndarray, config: RadarConfig) -> Detections:
    """Range, angle and position of each support bin of U (B, N, 2); support (B, K)."""
    rows = np.take_along_axis(u, support[:, :, None], axis=1)  # (B, K, 2)
    angle = angle_from_antennas_rad(rows[..., 0], rows[..., 1], config)
    rng_m = config.range_grid_m()[support]
    x, y = polar_to_xy(rng_m, angle)
    amp = np.sqrt((np.abs(rows) ** 2).sum(axis=2) / 2.0)
    return Detections(rng_m, np.rad2deg(angle), x, y, amp, support)


def localize(z: np.ndarray, config: RadarConfig, k: int, indices: np.ndarray | None = None) -> Detections:
    """PBP targets of a batch of frames Z (B, M, 2) (quantized or not)."""
    u = back_project(z, config, indices)
    return detections_from_support(u, joint_support(u, k), config)


def localize_frame(z: np.ndarray, config: RadarConfig, k: int, indices: np.ndarray | None = None) -> list[dict[str, float]]:
    """PBP targets of one frame Z (M, 2), strongest first, as dicts."""
    z = np.asarray(z)
    if z.ndim != 2 or z.shape[-1] != 2:
        raise ParameterError(f"a single frame Z must have shape (M, 2), got {z.shape}")
    idx = None if indices is None else np.asarray(indices)
    return localize(z[None], config, k, idx).frame(0)


def nearest_estimates(
    true_range_m: np.ndarray, true_angle_deg: np.ndarray, est_range_m: np.ndarray, est_angle_deg: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """For each true target, the closest estimate in the plane: (error m (B, K),
    position x + i y of that estimate (B, K) complex, m).

    true_* : (B, K); est_* : (B, L); errors are ``min_k |R e^{i theta} - R_hat_k e^{i theta_hat_k}|``.
    """
    t = polar_to_plane(true_range_m, np.deg2rad(true_angle_deg))
    e = polar_to_plane(est_range_m, np.deg2rad(est_angle_deg))
    dist = np.abs(t[:, :, None] - e[:, None, :])  # (B, K, L)
    nearest = np.argmin(dist, axis=2)
    pos = np.take_along_axis(np.broadcast_to(e[:, None, :], dist.shape), nearest[:, :, None], axis=2)[..., 0]
    return np.take_along_axis(dist, nearest[:, :, None], axis=2)[..., 0], pos


def position_error_m(
    true_range_m: np.ndarray, true_angle_deg: np.ndarray, est_range_m: np.ndarray, est_angle_deg: np.ndarray
) -> np.ndarray:
    """Error of each true target: ``min_k |R e^{i theta} - R_hat_k e^{i theta_hat_k}|``, m.

    true_* : (B, K); est_* : (B, L). Returns (B, K).
    """
    return nearest_estimates(true_range_m, true_angle_deg, est_range_m, est_angle_deg)[0]
