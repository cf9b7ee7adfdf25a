"""Fixtures every test folder shares (the paper scenario, its motion model, a seeded Generator).
Shared helpers are modules in tests/support/ (imported as ``tests.support.NAME``); a test module
never imports another test module (tests/test_layout.py)."""
import os

import numpy as np
import pytest

from sim.autopilot import MockAutopilot  # noqa: F401  (sets MAVLINK20 before pymavlink is imported)

from onboard.config import load_scenario
from onboard.core.dynamics import MotionModel

# the pmon gcs programs the tests start keep normal priority (as before the program lowered itself):
# at idle priority beside a loaded machine's work their start can take longer than a test waits.
# The rig runs the operator's commands of a flight at idle by chrt (sim/procedure.py), and
# tests/app/test_realtime.py checks the program's own default with this variable unset.
os.environ.setdefault("PMON_GCS_NO_IDLE", "1")


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
