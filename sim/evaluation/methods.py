"""The methods an evaluation compares (``pmon eval --methods``), registered by name: a sensing mode
and, for a UAV, the planner the monitor's tick runs, its motion model and the autopilot parameters
a flown copter flies with. sim/evaluation/trials.py runs them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from onboard.config import override
from onboard.core.planner_choice import PLANNERS
from onboard.policy import POLICIES
from onboard.settings.sections import SETTINGS
from sim.evaluation.baselines import register_baselines
from sim.mock.multicopter import DEMO_VEHICLE_PARAMS, PX4_DEFAULTS

register_baselines()  # the methods below name them

# the ArduCopter parameters a vehicle method's copter flies with (sim.mock.multicopter.limits_from_params):
# ``NAME@LABEL`` in --methods picks one (default stock: 10 m/s, 2.5 m/s^2; demo: sim.mock.multicopter.DEMO_VEHICLE_PARAMS;
# px4: PX4 v1.16's stock MPC_* parameters, its controller and SIH airframe)
AUTOPILOTS: dict[str, dict[str, float]] = {"stock": {}, "demo": dict(DEMO_VEHICLE_PARAMS), "px4": dict(PX4_DEFAULTS)}

# the declared defaults fly (the flight methods); the paper's methods and the baselines start from
# the paper's (``--policy paper``) and change only what makes each what it is
FLIGHT = tuple(POLICIES["flight"].items())
PAPER = tuple(POLICIES["paper"].items())


@dataclass(frozen=True, eq=False)
class Method:
    """A sensing mode and, for a UAV, how it moves.

    sensing: ``uav`` (the UAV's DF: p_D, Poisson clutter), ``fixed`` (the paper's three
    ground DFs, no clutter, p_D = 1) or ``ceiling`` (bound only, no sensor and no filter run: the
    path is the clairvoyant ceiling's, ``sim.evaluation.ceiling_search.ceiling_path``, from the trial's
    truth, gains and start at the method's vehicle limits; only its PCRB and path are defined). clutter_rate: Lambda for both the simulated DF and the
    filter's likelihood (None: the scenario's). planner: the UAV planner the monitor's tick runs
    from the UAV position (``onboard.core.planner_choice.PLANNERS``: greedy, lookahead, and the baselines
    hover, orbit, random of sim/evaluation/baselines.py); None: the scenario's ``planning.planner``.
    settings: scenario settings that make this method what it is (``onboard.config.override``,
    over the run's own ``--set``, as sensing, clutter_rate, planner and motion are).
    motion: the UAV's motion model for this method, ``jump`` or ``vehicle``, with the scenario's
    ``planning.speed_max_mps`` / ``accel_max_mps2``; None: the scenario's ``planning.motion``.
    A UAV that the monitor's tick plans on the vehicle motion is *flown*: at each tick the app's
    setpoint (the plan's position, velocity and acceleration) is given to the vehicle model
    fitted to ArduCopter (sim.mock.guided.fly_plan), and the next scan is taken where it is a tick
    later, with the velocity it has then (not at the planned point).
    jump_twin: for a vehicle method, the method with the same planner and the jump model; when
    both run, the summary reports this method's RMSE over the twin's, paired, with its CI.
    scenario_overrides: scenario settings of this method only (``onboard.policy.POLICIES``), under
    the run's own ``--set`` (``onboard.config.override(..., beneath=True)``).
    autopilot: the ArduCopter parameter set (``AUTOPILOTS``) a flown method's copter flies with
    (None: stock). follows: ``ceiling``: the UAV flies the clairvoyant ceiling's path (at the method's
    limits, as the bound-only ``ceiling``), known in advance: no planning; the filter runs on its
    bearings (what the filter makes of the best path for the bound). autopilot_limits: the planner plans with the autopilot's WPNAV_SPEED,
    WPNAV_ACCEL and jerk (PSC_JERK_XY, capped as the firmware caps it) capped by the scenario's
    planning.speed_max_mps / accel_max_mps2 / jerk_max_mps3 (what the airframe flies;
    ``onboard.policy.vehicle_motion``), as the app does; else with the scenario's values.
    """

    name: str
    description: str
    sensing: str = "uav"
    clutter_rate: float | None = None
    planner: str | None = None
    settings: tuple[tuple[str, Any], ...] = ()
    motion: str | None = None
    jump_twin: str | None = None
    scenario_overrides: tuple[tuple[str, Any], ...] = ()
    autopilot: str | None = None
    autopilot_limits: bool = False
    follows: str | None = None

    def __post_init__(self):
        if self.sensing not in ("uav", "fixed", "ceiling"):
            raise ValueError(f"method {self.name}: sensing must be 'uav', 'fixed' or 'ceiling'")
        if (self.sensing == "ceiling" or self.follows is not None) and self.motion != "vehicle":
            raise ValueError(f"method {self.name}: a ceiling is a vehicle's (motion 'vehicle')")
        if self.follows not in (None, "ceiling") or (self.follows and self.sensing != "uav"):
            raise ValueError(f"method {self.name}: follows must be None or 'ceiling' (with sensing 'uav')")
        if self.planner is not None and self.planner not in PLANNERS:
            raise ValueError(f"method {self.name}: planner must be one of {', '.join(PLANNERS)}")
        if self.motion not in (None, "jump", "vehicle"):
            raise ValueError(f"method {self.name}: motion must be 'jump', 'vehicle' or None")
        if self.autopilot is not None and self.autopilot not in AUTOPILOTS:
            raise ValueError(f"method {self.name}: autopilot must be one of {', '.join(AUTOPILOTS)}")

    @property
    def bound_only(self) -> bool:
        """No filter run (RMSE and NEES undefined): the clairvoyant ceiling."""
        return self.sensing == "ceiling"


METHODS: dict[str, Method] = {}


def register_method(method: Method) -> Method:
    """Add (or replace) a method by name; ``pmon eval --methods`` can then name it."""
    METHODS[method.name] = method
    return method


for _m in (
    Method("greedy_l1", "single UAV, the paper's one-step greedy rule, Lambda = 1", planner="greedy",
           clutter_rate=1.0, scenario_overrides=PAPER),
    Method("lookahead", "single UAV, the non-myopic planner (docs/PLANNING.md), jump moves, Lambda = 1",
           planner="lookahead", clutter_rate=1.0, motion="jump", scenario_overrides=PAPER),
    Method("lookahead_vehicle", "single UAV, the non-myopic planner with vehicle limits (planning.speed_max_mps, "
           "accel_max_mps2: ArduCopter's 10 m/s, 2.5 m/s^2 in the paper scenario), Lambda = 1", planner="lookahead",
           clutter_rate=1.0, motion="vehicle", jump_twin="lookahead", scenario_overrides=PAPER),
    Method("greedy_vehicle", "single UAV, the paper's greedy rule with vehicle limits (as lookahead_vehicle), "
           "Lambda = 1", planner="greedy", clutter_rate=1.0, motion="vehicle", jump_twin="greedy_l1",
           scenario_overrides=PAPER),
    Method("flight", "single UAV, the flight default (the declared defaults, onboard/settings/sections.py: docs/PLANNING.md, "
           "'What flies'), planning with the autopilot's WPNAV_SPEED / WPNAV_ACCEL capped by what the airframe "
           "flies, Lambda = 1", clutter_rate=1.0, motion="vehicle",
           scenario_overrides=FLIGHT, autopilot_limits=True),
    Method("ceiling", "bound only: the path of a vehicle at the flight default's limits (its policy, the stock "
           "autopilot's WPNAV_SPEED / WPNAV_ACCEL capped by what the airframe flies) that minimises the PCRB "
           "knowing the true target trajectories (sim/evaluation/ceiling.py, docs/PLANNING.md 'The clairvoyant ceiling'); "
           "no filter run, Lambda = 1", sensing="ceiling", clutter_rate=1.0, motion="vehicle",
           scenario_overrides=FLIGHT, autopilot_limits=True),
    Method("ceiling_flown", "single UAV flying the ceiling's path (clairvoyant, not a planner: the path of "
           "'ceiling'), the flight default's filter on its bearings, Lambda = 1", clutter_rate=1.0, motion="vehicle",
           follows="ceiling", scenario_overrides=FLIGHT, autopilot_limits=True),
    Method("greedy_l8", "single UAV, greedy rule, Lambda = 8 (DF and filter)", planner="greedy", clutter_rate=8.0,
           scenario_overrides=PAPER),
    Method("fixed3", "three fixed DFs (150,200), (800,200), (500,900) m; no clutter, p_D = 1", sensing="fixed",
           scenario_overrides=PAPER),
    # the baselines move on the paper's grid S_(t+1) (the jump model): never flown
    Method("hover", "single UAV hovering at its start, Lambda = 1", planner="hover", motion="jump", clutter_rate=1.0,
           scenario_overrides=PAPER),
    Method("orbit", "single UAV on a circle around the targets' initial centroid, Lambda = 1", planner="orbit",
           motion="jump", clutter_rate=1.0, scenario_overrides=PAPER),
    Method("random", "single UAV, uniformly random admissible move, Lambda = 1", planner="random", motion="jump",
           clutter_rate=1.0, scenario_overrides=PAPER),
):
    register_method(_m)
DEFAULT_METHODS = ("greedy_l1", "greedy_l8", "fixed3", "hover", "orbit", "random")  # the paper's set


def method_scenario(sc, method: Method):
    """The scenario a method runs: the run's (with its ``--set``) under the method's policy
    (``scenario_overrides``, beneath the run's own settings), then the settings that make the
    method what it is (over them)."""
    sc = override(sc, dict(method.scenario_overrides), beneath=True)
    own = dict(method.settings)
    if method.sensing == "fixed":  # the baseline's sensors: no clutter, every target seen; the filter must know it
        own.update({"sensor.p_detect": 1.0, "sensor.clutter_rate": 0.0})
    elif method.clutter_rate is not None:
        own["sensor.clutter_rate"] = method.clutter_rate
    if method.planner is not None and method.planner in SETTINGS["planning.planner"].choices:
        own["planning.planner"] = method.planner  # (a baseline or a bench's planner is set on the setup: _setup_for)
    if method.motion is not None:
        own["planning.motion"] = method.motion
    return override(sc, own)
