import numpy as np
import pytest

from onboard.config import load_scenario
from onboard.core.dynamics import MotionModel


@pytest.fixture(scope="session")
def paper():
    return load_scenario("paper")


@pytest.fixture(scope="session")
def model(paper):
    d = paper.dynamics
    return MotionModel.create(d.dt_s, d.friction, d.mass_kg, d.process_noise_diag)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
