"""The sensor side of qradar: radar configuration and the paper's signal model (what the
simulated K-MD2 emits), scenes, the K-MD2 protocol codec, the serial session, the
simulator, and the frame-source interface (:mod:`radar_driver.source`). It imports
nothing of the other qradar packages."""

from .errors import ConfigError, InputError, RadarError
from .model import (
    RadarConfig,
    add_noise,
    angle_from_antennas_rad,
    antenna_phase_rad,
    polar_to_xy,
    sensing_matrix,
    simulate_frames,
    snap_to_range_grid,
)
from .scene import SimScene, SimTarget

__all__ = [
    "ConfigError",
    "InputError",
    "RadarConfig",
    "RadarError",
    "SimScene",
    "SimTarget",
    "add_noise",
    "angle_from_antennas_rad",
    "antenna_phase_rad",
    "polar_to_xy",
    "sensing_matrix",
    "simulate_frames",
    "snap_to_range_grid",
]
