"""Fixtures every test folder shares (the paper scenario, its motion model, a seeded Generator).
Shared helpers are modules in tests/support/ (imported as ``tests.support.NAME``); a test module
never imports another test module (tests/test_layout.py)."""
import os

import numpy as np
import pytest

from sim.mock.autopilot import MockAutopilot  # noqa: F401  (sets MAVLINK20 before pymavlink is imported)

from onboard.config import load_scenario
from onboard.core.dynamics import MotionModel
from onboard.policy import with_policy

# the pmon gcs programs the tests start keep normal priority (as before the program lowered itself):
# at idle priority beside a loaded machine's work their start can take longer than a test waits.
# The rig runs the operator's commands of a flight at idle by chrt (sim/stack/procedure.py), and
# tests/app/test_realtime.py checks the program's own default with this variable unset.
os.environ.setdefault("PMON_GCS_NO_IDLE", "1")

# The suite's flights run at normal scheduling (PMON_SIM_RT_PRIORITY unset, sim/firmware/priority.py):
# with the whole suite's flights at FIFO (40/41) the rehearsals of 2026-12-02 failed the
# observers' races (the conformance boot's pre-fix positions, a PX4 flight's ticks; docs/LOG.md).
# tests/firmware/test_under_load.py sets it for its own flights; PMON_SIM_RT_PRIORITY=40 in the
# environment flies every flight that way.

_FIRMWARE_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "firmware") + os.sep


def pytest_itemcollected(item):  # as each test is collected: before -m reads the marks
    """Every test of a real firmware carries the ``firmware`` marker: those marked ``ardupilot`` or
    ``px4`` and all of tests/firmware/ (the fast tier deselects them: -m 'not firmware and not slow')."""
    if (str(item.path).startswith(_FIRMWARE_DIR) or item.get_closest_marker("ardupilot")
            or item.get_closest_marker("px4")):
        item.add_marker(pytest.mark.firmware)


@pytest.fixture(scope="session")
def paper():
    """The paper's scenario under the paper's method (``--policy paper``: the greedy rule on the
    jump model, the paper's filter); a test of what flies loads the scenario as declared."""
    return with_policy(load_scenario("paper"), "paper")


@pytest.fixture(scope="session")
def model(paper):
    d = paper.dynamics
    return MotionModel.create(d.dt_s, d.friction, d.mass_kg, d.process_noise_diag)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
