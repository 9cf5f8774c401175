"""The sensor side of qradar: radar configuration and the paper's signal model
(what the simulated K-MD2 emits)."""

from .errors import ConfigError, InputError, RadarError
from .model import (
    RadarConfig,
    Scene,
    Target,
    add_noise,
    angle_from_antennas_rad,
    antenna_phase_rad,
    polar_to_xy,
    sensing_matrix,
    simulate_frames,
    snap_to_range_grid,
)

__all__ = [
    "ConfigError",
    "InputError",
    "RadarConfig",
    "RadarError",
    "Scene",
    "Target",
    "add_noise",
    "angle_from_antennas_rad",
    "antenna_phase_rad",
    "polar_to_xy",
    "sensing_matrix",
    "simulate_frames",
    "snap_to_range_grid",
]
