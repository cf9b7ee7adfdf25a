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
from tests.support import lanes, stand_ins

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


# The compute lane (tests/support/lanes.py, tests/README.md "Two lanes"): modules whose tests neither
# fly nor time anything (no sockets, threads, sleeps, clocks or tolerances in seconds: in-process
# maths, parsers, files), each checked to pass at nice 19 beside busy processes. Everything not
# listed is the flights lane's: a new module is a flight until it is shown to be pure.
COMPUTE_MODULES = frozenset({
    "tests/test_layout.py",  # the source's layout, statically
    "tests/core/test_config.py", "tests/core/test_doa.py", "tests/core/test_dynamics.py",
    "tests/core/test_guidance.py",  # its budget is counted in QP solves, not timed (a test shows it)
    "tests/core/test_information.py", "tests/core/test_intent.py", "tests/core/test_obstacles.py",
    "tests/core/test_planning.py", "tests/core/test_setpoint.py", "tests/core/test_tracking.py",
    "tests/sim/test_ceiling.py", "tests/sim/test_error_split.py", "tests/sim/test_latency_account.py",
    "tests/sim/test_sensors.py", "tests/sim/test_truth.py", "tests/sim/test_truth_kinds.py",
    "tests/sim/test_worlds.py", "tests/sim/test_evaluation.py",  # evaluations: CPU-bound trials
    "tests/gcs/test_export.py", "tests/gcs/test_locate.py",  # files written and read back
    "tests/app/test_kraken.py", "tests/app/test_datagram.py", "tests/app/test_fence.py",  # parsers, rules
    "tests/app/test_jerk_limit.py",  # the autopilot side's parameter handling, no link
})
# ... and the tests of those modules that stay flights: they wait on processes or sockets in seconds
# (the compute lane may be starved for minutes: its own tests have no timeout shorter than
# lanes.COMPUTE_TIMEOUT_S)
COMPUTE_MODULES_FLIGHTS = frozenset({
    "tests/sim/test_worlds.py::test_a_world_is_its_family_seed_and_index_in_any_process",
    "tests/sim/test_worlds.py::test_the_planner_bench_refuses_a_bad_scenario_in_one_line_and_times_several_in_one_run",
    "tests/sim/test_evaluation.py::test_docs_results_trial_0_reproduces_here",  # pmon eval, 240 s
    "tests/sim/test_evaluation.py::test_pmon_eval_writes_csv_table_figures_and_a_json_line",  # the same
    "tests/sim/test_evaluation.py::test_dask_cluster_gives_the_same_trials",  # a TCP cluster
    "tests/sim/test_evaluation.py::test_workers_load_the_avx2_kernels_where_the_cpu_has_them",
    "tests/sim/test_evaluation.py::test_a_sigterm_while_the_worker_pool_starts_stops_the_run_and_the_pool",
    "tests/sim/test_evaluation.py::test_pmon_eval_stopped_midway_stops_its_workers",
})


_LANE = pytest.StashKey[str]()
_COMPUTE = pytest.StashKey[lanes.ComputeLane]()


def pytest_configure(config):
    if os.environ.get(lanes.LANE_ENV) == "compute":
        lanes.become_compute()
        config.stash[_LANE] = "compute"
    elif lanes.split_wanted(config):
        config.stash[_LANE] = "flights"
        config.stash[_COMPUTE] = lanes.ComputeLane(config)


def pytest_report_header(config):
    if _COMPUTE in config.stash:
        lane = config.stash[_COMPUTE]
        return f"lanes: flights here; compute at nice {lanes.COMPUTE_NICE} in pid {lane.proc.pid} ({lane.log})"
    return None


def pytest_itemcollected(item):  # as each test is collected: before -m reads the marks
    """Every test of a real firmware carries the ``firmware`` marker: those marked ``ardupilot`` or
    ``px4`` and all of tests/firmware/ (the fast tier deselects them: -m 'not firmware and not slow');
    every test of the compute lane carries ``compute`` (-m compute selects it in one process)."""
    if (str(item.path).startswith(_FIRMWARE_DIR) or item.get_closest_marker("ardupilot")
            or item.get_closest_marker("px4")):
        item.add_marker(pytest.mark.firmware)
    if lanes.is_compute(item, COMPUTE_MODULES, COMPUTE_MODULES_FLIGHTS):
        flies = [m for m in lanes.FLIGHT_MARKERS if item.get_closest_marker(m)]
        if flies:
            raise pytest.UsageError(f"{item.nodeid} is marked {flies[0]} but tests/conftest.py lists it for "
                                    "the compute lane: list it in COMPUTE_MODULES_FLIGHTS")
        item.add_marker(pytest.mark.compute)


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    """A mock flight whose firmware version runs in this session is skipped (tests/support/stand_ins.py);
    each lane keeps its own tests (after -m and -k have chosen)."""
    for item, reason in stand_ins.stand_ins_covered(items):
        item.add_marker(pytest.mark.skip(reason=reason))
    lane = config.stash.get(_LANE, None)
    if lane is None:
        return
    keep = [i for i in items if (i.get_closest_marker("compute") is not None) == (lane == "compute")]
    if len(keep) < len(items):
        config.hook.pytest_deselected(items=[i for i in items if i not in set(keep)])
        items[:] = keep


def pytest_sessionfinish(session, exitstatus):
    lane = session.config.stash.get(_COMPUTE, None)
    if lane is None:
        return
    if exitstatus == pytest.ExitCode.INTERRUPTED:
        lane.stop()
        return
    session.config.get_terminal_writer().line(f"\nwaiting for the compute lane (pid {lane.proc.pid})")
    session.exitstatus = lanes.merged_exit(exitstatus, lane.wait())


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    lane = config.stash.get(_COMPUTE, None)
    if lane is None or lane.rc is None:
        return
    terminalreporter.section(f"compute lane: exit {lane.rc}, {lane.wall_s:.0f} s at nice {lanes.COMPUTE_NICE}")
    terminalreporter.write(lane.output())
    if lane.rc == 0:
        os.unlink(lane.log)
    else:
        terminalreporter.line(f"(its log: {lane.log})")


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
