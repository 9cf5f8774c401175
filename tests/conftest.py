import numpy as np
import pytest

from radar_driver.model import RadarConfig


@pytest.fixture
def cfg() -> RadarConfig:
    return RadarConfig()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261121)
