"""Uncertainty ellipses: the covariance of a target's (x, y) from that of its (R, θ), and
the 1-σ ellipse of a 2×2 covariance (pure numpy, a batch of K first). What the recordings'
scenes (pipeline.wire.foxglove) and the web page (qradar.web.events) draw.

An ellipse is ``[a_m, b_m, phi_rad]``: semi-axes a >= b (m) and the angle of a from the
frame's x axis, counter-clockwise, in (-π/2, π/2]."""

from __future__ import annotations

import math

import numpy as np

from radar_driver.model import polar_to_xy


def polar_covariance_to_xy(range_m: np.ndarray, angle_deg: np.ndarray, sigma_range_m: np.ndarray,
                           sigma_angle_deg: np.ndarray, cov_range_angle: np.ndarray) -> np.ndarray:
    """The covariance of (x, y) of K targets from that of (R, θ), to first order:
    Σ_xy = J Σ_Rθ Jᵀ, J the Jacobian of :func:`~radar_driver.model.polar_to_xy` at (R, θ)
    (columns u(θ) and R u(θ + π/2), u(θ) = polar_to_xy(1, θ); θ in rad). Inputs (K,), m
    and deg (the covariance in m·deg); -> (K, 2, 2), m²."""
    r = np.asarray(range_m, dtype=float)
    a = np.radians(np.asarray(angle_deg, dtype=float))
    ux, uy = polar_to_xy(np.ones_like(r), a)
    vx, vy = polar_to_xy(r, a + np.pi / 2)
    jac = np.stack([np.stack([ux, vx], axis=-1), np.stack([uy, vy], axis=-1)], axis=-2)  # (K, 2, 2)
    s_r = np.asarray(sigma_range_m, dtype=float)
    s_a = np.radians(np.asarray(sigma_angle_deg, dtype=float))
    c = np.radians(np.asarray(cov_range_angle, dtype=float))
    polar = np.stack([np.stack([s_r ** 2, c], axis=-1), np.stack([c, s_a ** 2], axis=-1)], axis=-2)
    return jac @ polar @ np.swapaxes(jac, -1, -2)


def rotate_covariance(cov: np.ndarray, yaw_deg: float) -> np.ndarray:
    """(K, 2, 2) covariances of a sensor's frame in the world (the sensor turned by yaw_deg)."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    rot = np.array([[c, -s], [s, c]])
    return rot @ cov @ rot.T


def ellipses(cov: np.ndarray) -> np.ndarray:
    """1-σ ellipses of (K, 2, 2) covariances: (K, 3) of semi-axes a >= b (m) and the angle
    of a from x (rad, in (-π/2, π/2])."""
    w, v = np.linalg.eigh(cov)  # ascending eigenvalues, eigenvectors in columns
    a, b = np.sqrt(np.maximum(w[:, 1], 0.0)), np.sqrt(np.maximum(w[:, 0], 0.0))
    phi = np.arctan2(v[:, 1, 1], v[:, 0, 1])
    phi = np.where(phi > np.pi / 2, phi - np.pi, np.where(phi <= -np.pi / 2, phi + np.pi, phi))
    return np.stack([a, b, phi], axis=-1)
