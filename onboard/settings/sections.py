"""The scenario's settings, section by section: each field carries its ``Setting`` in its metadata
(onboard/settings/declare.py), and ``SETTINGS`` / ``PARAMS`` index them by dotted key and by PMON_*
parameter.

The objects hold each setting as the file states it, in the file's unit (so a scenario written
back and read again is the same object, bit for bit); what the code needs in SI units and
radians is a property (``Sensor.sigma_rad``, ``Box.yaw_rad``).

Pure Python (no YAML, no numpy).
"""
from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, field
from typing import Any, Callable

from onboard.settings.declare import (
    Setting,
    choice,
    default_text,
    flag,
    integer,
    location,
    names,
    number,
    records,
    section,
    text,
    value_text,
    vector,
    walk,
)

POS_M = 1e5  # |coordinate| of the ENU frame, m: a flat frame 100 km out is off by ~0.8 km (Earth's curvature)


@dataclass(frozen=True)
class Origin:
    lat_deg: float = number(MISSING, -90, 90, "deg", "geodetic latitude of the ENU frame's origin")
    lon_deg: float = number(MISSING, -180, 180, "deg", "geodetic longitude of the origin")
    alt_m: float = number(MISSING, -500, 9000, "m", "altitude of the origin above mean sea level")


@dataclass(frozen=True)
class Area:
    min_m: tuple[float, float, float] = vector(MISSING, 3, -POS_M, POS_M, "m",
                                               "lowest corner of the surveillance area E (ENU)")
    max_m: tuple[float, float, float] = vector(MISSING, 3, -POS_M, POS_M, "m",
                                               "highest corner; greater than min_m in every axis")

    def contains(self, points):
        """True where each point (..., 3) lies inside the closed box."""
        import numpy as np  # here: this module stays importable without numpy

        p = np.asarray(points, dtype=float)
        return np.all((p >= np.asarray(self.min_m)) & (p <= np.asarray(self.max_m)), axis=-1)


@dataclass(frozen=True)
class Dynamics:
    dt_s: float = number(1.0, 0.1, 10, "s", "time step of the targets' model and of the monitor's tick",
                         paper=True)
    friction: float = number(0.2, 0, 1, "", "epsilon: velocity lost to friction per step", paper=True,
                             experimental=True)
    mass_kg: float = number(1300.0, 1, 1e5, "kg", "a target's mass", paper=True, experimental=True)
    process_noise_diag: tuple[float, ...] = vector((30.0, 30.0, 1e-10, 3.0, 3.0, 1e-10), 6, 0, 1e6,
                                                   "m^2, (m/s)^2", "diagonal of Q (x, y, z, vx, vy, vz)",
                                                   paper=True, experimental=True)


@dataclass(frozen=True, kw_only=True)
class Target:
    name: str = text(MISSING, "the target's name")
    position_m: tuple[float, float, float] = vector(MISSING, 3, -POS_M, POS_M, "m",
                                                    "mu_0: its initial mean position, inside the area")
    velocity_mps: tuple[float, float, float] = vector((0.0, 0.0, 0.0), 3, -100, 100, "m/s",
                                                      "its initial mean velocity (ground targets)")
    goal: str | None = text(None, "the name of the goal region in goals it heads for (a prior, not a certainty: "
                            "docs/TRACKING.md 'Intent'); null or left out: not known", nullable=True)
    goals: tuple[str, ...] = names((), 16, "candidate goal regions it may head for (equally likely), besides "
                                   "its goal")
    stationary: bool = flag(False, "it is expected to stand still (a transmitter being hunted): with "
                            "tracking.intent, its stationary mode's prior is 0.8")

    @property
    def candidates(self) -> tuple[str, ...]:
        """Its goal, then its other candidate goals: every goal it may head for."""
        first = () if self.goal is None else (self.goal,)
        return first + tuple(g for g in self.goals if g != self.goal)

    @property
    def mean(self):
        import numpy as np

        return np.array(self.position_m + self.velocity_mps, dtype=float)


@dataclass(frozen=True)
class Box:
    """A cuboid given by centre, extents (before yaw) and yaw about +z (CCW from +x)."""

    name: str = text(MISSING, "its name")
    center_m: tuple[float, float, float] = vector(MISSING, 3, -POS_M, POS_M, "m", "its centre")
    size_m: tuple[float, float, float] = vector(MISSING, 3, 0, 1e4, "m",
                                                "its x, y, z extents before yaw (an obstacle's > 0)")
    yaw_deg: float = number(0.0, -360, 360, "deg", "its rotation about +z, counterclockwise from +x")

    @property
    def yaw_rad(self) -> float:
        return math.radians(self.yaw_deg)


@dataclass(frozen=True)
class Guidance:
    """Problem P1: each target's plan to its goal (docs/GUIDANCE.md)."""

    horizon: int = integer(50, 2, 200, "steps", "T: steps each target's guidance plans ahead",
                           param="PMON_HORIZON", paper=True)
    u_max_n: float = number(6000.0, 0, 1e6, "N", "|u_x|, |u_y| bound of a target's control input",
                            lo_open=True, paper=True, experimental=True)
    speed_max_mps: float = number(16.0, 0, 100, "m/s", "a target's ground speed bound (inscribed polygon)",
                                  lo_open=True, paper=True, experimental=True)
    speed_polygon_sides: int = integer(16, 4, 64, "", "sides of the polygon that keeps the speed bound",
                                       experimental=True)
    terminal_weight: float = number(1.0, 0, 1e6, "1/m^2", "weight of ||mu_pos(t+T) - G_o||^2",
                                    paper=True, experimental=True)
    stage_weight: float = number(1.0, 0, 1e6, "1/m^2", "weight of ||mu_pos(t+tau) - G_o||^2 for tau < T "
                                 "(ours; not both 0)", experimental=True)
    smooth_weight: float = number(1000.0, 0, 1e6, "1/kN^2", "weight of ||u_tau - u_(tau-1)||^2", experimental=True)
    obstacle_margin_m: float = number(5.0, 0, 1000, "m", "obstacles are inflated by this for the targets' plans",
                                      experimental=True)
    max_qp_solves: int = integer(80, 1, 1000, "", "QP solves per target and tick; then the best plan found",
                                 experimental=True)
    max_solve_time_s: float | None = number(None, 0, 10, "s", "solve time per target and tick; null: no limit "
                                            "(results independent of the machine's speed)",
                                            lo_open=True, nullable=True, experimental=True)


@dataclass(frozen=True)
class Sensor:
    """The direction finder."""

    sigma_deg: float = number(1.0, 0.05, 30, "deg", "bearing noise, 1 sigma", param="PMON_SIGMA_DEG", paper=True)
    p_detect: float = number(0.95, 0.01, 1, "", "p_D: probability that a scan holds a target's bearing",
                             param="PMON_PD", paper=True)
    clutter_rate: float = number(1.0, 0, 50, "1/scan", "Lambda: Poisson mean of false bearings per scan, "
                                 "uniform on (-pi, pi]", param="PMON_CLUTTER", paper=True)

    @property
    def sigma_rad(self) -> float:
        return math.radians(self.sigma_deg)


@dataclass(frozen=True, kw_only=True)
class Uav:
    start_m: tuple[float, float, float] = vector(MISSING, 3, -POS_M, POS_M, "m",
                                                 "the UAV's start (x, y; it flies at altitude_m)")
    altitude_m: float = number(40.0, 2, 1000, "m", "h: flight altitude above the mission origin",
                               param="PMON_ALT", paper=True)
    step_m: float = number(5.0, 0.5, 100, "m", "Delta_r: radial step of the candidate grid",
                           param="PMON_DR", paper=True)
    n_radial: int = integer(4, 0, 20, "", "N_r: radial steps of the candidate grid", param="PMON_NR", paper=True)
    n_heading: int = integer(15, 1, 72, "", "N_theta: headings of the candidate grid", param="PMON_NTH",
                             paper=True)
    obstacle_margin_m: float = number(10.0, 0, 1000, "m", "clearance the UAV keeps from obstacles it cannot overfly")


@dataclass(frozen=True)
class Tracking:
    """The particle filters (docs/TRACKING.md)."""

    particles: int = integer(2000, 100, 20000, "", "particles per target", param="PMON_PARTICLES")
    resample_ess_fraction: float = number(0.5, 0, 1, "", "resample when the effective sample size falls "
                                          "below this fraction", experimental=True)
    control_mix: float = number(0.1, 0, 1, "", "share of particles predicted with a random control, the "
                                "rest with the plan's", hi_open=True, experimental=True)
    regularise_bandwidth: float = number(0.2, 0, 1, "", "h of the regularised resampling, jitter N(0, h^2 C); "
                                         "0: plain resampling", experimental=True)
    plan_steering: bool = flag(True, "particles steer by the affine law of the nearest reference plan "
                               "while the plan is constrained (false, the paper's: the free steering "
                               "alone, and the plan_* settings below unused)", experimental=True)
    plan_references: int = integer(2, 0, 8, "", "reference plans besides the mean's (pairs either side)", even=True,
                                   experimental=True)
    plan_spread_sigma: float = number(1.5, 0, 5, "sigma", "the references' spread along the cloud's major axis",
                                      lo_open=True, experimental=True)
    plan_steered_share: float = number(0.7, 0, 1, "", "share of the particles a reference plan steers "
                                       "(the rest keep its control)", experimental=True)
    plan_trust_sigma: float = number(2.0, 0, 10, "sigma", "only particles this close (Mahalanobis) to a "
                                     "reference are steered", lo_open=True, experimental=True)
    plan_max_qp_solves: int = integer(80, 1, 1000, "", "QP budget of each reference plan", experimental=True)
    plan_sides: bool = flag(True, "with plan_steering: a side of each obstacle per particle, reference "
                            "plans per side present (the side-aware filter; false, the paper's: one)",
                            experimental=True)
    plan_side_temperature: float = number(0.05, 0, 10, "", "a side costing P1 d more (relative) gets "
                                          "1/(1+exp(d/this)) of the particles", lo_open=True, experimental=True)
    recovery_prior: float = number(0.01, 0, 0.5, "", "probability per tick that a target left the motion "
                                   "model's prediction (tracking.Recovery: found again along the bearings); 0 "
                                   "(the paper's): off", experimental=True)
    recovery_share: float = number(0.02, 0, 1, "", "with recovery_prior: share of the particles drawn along "
                                   "the bearings each tick", experimental=True)
    recovery_sigma_m: float = number(50.0, 1, 5000, "m", "with recovery_prior: a target that left the "
                                     "prediction is N(its mean, its covariance + this^2 I) in the plane",
                                     experimental=True)
    intent: bool = flag(True, "a motion mode per particle: heading for each candidate goal, stationary, or "
                        "free; their probabilities estimated from the bearings, and a target whose bearings "
                        "no mode explains re-seeded along them (docs/TRACKING.md 'Intent'; false, the "
                        "paper's: each target heads for its goal)", experimental=True)
    intent_stationary_prior: float = number(0.3, 0, 1, "", "with intent: prior that a target with a goal "
                                            "stands still", experimental=True)
    intent_free_prior: float = number(0.1, 0, 1, "", "with intent: prior that a target with a goal moves "
                                      "freely instead (heads somewhere not named, wanders)", experimental=True)
    intent_switch_prob: float = number(0.02, 0, 0.5, "1/tick", "with intent: probability per tick that a "
                                       "particle's mode is redrawn from the prior (stops, turns, goes)",
                                       experimental=True)
    intent_free_accel_mps2: float = number(1.0, 0, 20, "m/s^2", "with intent: a free target's random "
                                           "acceleration, per axis", lo_open=True, experimental=True)
    intent_recovery_prior: float = number(0.05, 0, 0.5, "", "with intent and recovery_prior: the recovery's "
                                          "prior raised by this times the weight of a target's free and aimed "
                                          "modes (motion no goal predicts)", experimental=True)
    intent_recovery_sigma_m: float = number(150.0, 0, 5000, "m", "with intent and recovery_prior: the "
                                            "recovery's width raised by this times that weight", experimental=True)
    intent_start_speed_mps: float = number(3.0, 0, 20, "m/s", "with intent: a particle switching out of the "
                                           "stationary mode starts with a velocity N(0, this^2) per axis "
                                           "(0: at rest)", experimental=True)
    intent_goal_switch_share: float = number(0.1, 0, 1, "", "with intent: a particle heading for one "
                                             "candidate goal whose mode is redrawn takes another candidate "
                                             "goal at this share of its prior, else keeps its goal (a target "
                                             "rarely changes destination)", experimental=True)


@dataclass(frozen=True)
class Lookahead:
    """The lookahead planner's routes (docs/PLANNING.md argues each value)."""

    ranges_m: tuple[float, ...] = vector((30.0, 80.0, 160.0, 320.0), None, 0, 5000, "m",
                                         "waypoints on a polar grid around the UAV at these ranges",
                                         max_items=16, lo_open=True, experimental=True)
    n_headings: int = integer(16, 1, 360, "", "... and this many headings (plus the targets' predicted positions)",
                              experimental=True)
    loiter_radius_m: float = number(40.0, 0, 1000, "m", "after its waypoint a route circles through it with "
                                    "this radius", lo_open=True, experimental=True)
    corner_clearance_m: float = number(3.0, 0, 100, "m", "routes round the UAV's inflated obstacles this much wider",
                                       experimental=True)
    spacing_m: float = number(2.0, 0.1, 50, "m", "arc-length resolution of the sampled routes", experimental=True)


@dataclass(frozen=True)
class Planning:
    """Where the UAV flies next (docs/PLANNING.md)."""

    objective: str = choice("trace", ("trace", "position_trace"), "what the greedy rule minimises: tr(Sigma) "
                            "of all six states, or of the position only", paper=True, experimental=True)
    planner: str = choice("lookahead", ("greedy", "lookahead"),
                          "routes scored over lookahead_steps, or greedy, the paper's one-step rule (the "
                          "evaluation's baselines hover, orbit, random are its methods: sim/evaluation/baselines.py)")
    lookahead_steps: int = integer(50, 1, 200, "ticks", "ticks the lookahead planner scores "
                                   "(<= guidance.horizon)", experimental=True)
    motion: str = choice("vehicle", ("jump", "vehicle"), "vehicle: within speed and acceleration limits; "
                         "jump, the paper's: any grid point each tick", experimental=True)
    speed_max_mps: float = number(9.0, 0, 30, "m/s", "vehicle motion: speed limit, what the airframe flies "
                                  "(the app plans with the smaller of this and the autopilot's WPNAV_SPEED, "
                                  "read at connection; the paper policy's 10: ArduCopter's WPNAV_SPEED "
                                  "default)", lo_open=True)
    accel_max_mps2: float = number(2.5, 0, 20, "m/s^2", "vehicle motion: acceleration limit (ArduCopter's "
                                   "WPNAV_ACCEL default)", lo_open=True)
    jerk_max_mps3: float = number(5.0, 0, 100, "m/s^3", "vehicle motion: 0, the acceleration steps at "
                                  "each tick; > 0, it is continuous, changing linearly over each tick by "
                                  "at most this times the tick (what ArduCopter's jerk-limited GUIDED "
                                  "follows). The app plans with the smaller of this and the autopilot's "
                                  "own, read at connection (ArduPilot: PSC_JERK_XY, 5 by default, capped "
                                  "by its attitude loop as AC_PosControl caps it; PX4's OFFBOARD shapes "
                                  "none: this); 0 stays 0")
    lookahead: Lookahead = section(Lookahead, "the lookahead planner's routes")


@dataclass(frozen=True)
class Mission:
    duration_s: float = number(100.0, 0, 86400, "s", "length of a simulated mission", lo_open=True)


@dataclass(frozen=True)
class App:
    """The onboard app's own settings (``pmon run``); the simulator and the evaluation do not use them."""

    reach_m: float | None = number(None, 1, 500, "m", "largest move asked per tick, farther candidates "
                                   "excluded; null: the grid's outer ring N_r Delta_r (at least 1 m)",
                                   nullable=True, param="PMON_REACH")
    setpoint_hz: float = number(10.0, 5, 50, "Hz", "setpoint re-send rate, of autopilot time", param="PMON_SP_HZ")
    scan_wait_s: float = number(0.3, 0, 0.9, "s", "after a scan's time, wait this long for missing channels "
                                "before ticking", param="PMON_SCAN_WAIT")
    tick_budget_s: float = number(0.9, 0.1, 1.0, "s", "after a scan's time, its setpoint must be sent by this "
                                  "or the tick is missed", param="PMON_BUDGET")
    guidance_s: float = number(0.3, 0, 0.9, "s", "autopilot time the targets' guidance may take per tick, then "
                               "the best plan found or the fallback; 0: fallback only (fault drill)",
                               param="PMON_GUID_S")
    fence_min_m: float | None = number(None, 0, 1000, "m", "geofence floor above the mission origin; null: "
                                       "min(10 m, uav.altitude_m)", nullable=True, param="PMON_ALT_MIN")
    fence_max_m: float | None = number(None, 2, 1000, "m", "geofence ceiling above the mission origin; null: "
                                       "max(120 m, uav.altitude_m)", nullable=True, param="PMON_ALT_MAX")
    rt_priority: int = integer(0, 0, 98, "", "SCHED_FIFO priority of the app's io thread (MAVLink, setpoints), "
                               "the tick worker's one below, memory locked (pmon run --rt-priority; "
                               "docs/DEPLOY.md); 0: normal scheduling")


@dataclass(frozen=True)
class KrakenVfo:
    """One VFO of a KrakenSDR: the frequency it is tuned to, and whose emitter that is."""

    target: str = text(MISSING, "a target's name: this VFO's bearings are its channel")
    freq_hz: float = number(MISSING, 1e6, 1e11, "Hz", "the VFO's frequency, as KrakenSDR writes it in each line")


@dataclass(frozen=True)
class Kraken:
    """A KrakenSDR's DoA output as the DF (``pmon run --kraken``; onboard/app/kraken/source.py;
    docs/KRAKENSDR.md argues each value)."""

    vfos: tuple[KrakenVfo, ...] = records(KrakenVfo, 0, 64, "each target's emitter: a VFO of KrakenSDR tuned "
                                          "to it (needed by pmon run --kraken)", required=False)
    url: str = location("http://127.0.0.1:8081/DOA_value.html", "its DoA output (the 'Kraken App' CSV) over "
                   "HTTP, or the file it writes; pmon run --kraken URL overrides it")
    status_url: str | None = location("auto", "its status.json (ADC overdrive, DAQ sync) for the overdrive gate; "
                                 "auto: beside url; null: none", words=("auto",), nullable=True)
    freq_tol_hz: float = number(2000.0, 0, 1e6, "Hz", "a line within this of a VFO's frequency is that VFO's",
                                lo_open=True, experimental=True)
    mount_offset_deg: float = number(0.0, -360, 360, "deg", "KrakenSDR's 0 (antenna 0), clockwise from the "
                                     "vehicle's nose")
    convention: str = choice("auto", ("auto", "unit_circle", "compass"), "the main DoA's angle convention; auto: "
                             "read off each line's spectrum", experimental=True)
    measurements: str = choice("peaks", ("peaks", "main"), "the measurement set: the spectrum's peaks, or the "
                               "main DoA alone", experimental=True)
    peak_floor_db: float = number(6.0, 0, 100, "dB", "peaks within this of the spectrum's highest",
                                  lo_open=True, experimental=True)
    peak_prominence_db: float = number(3.0, 0, 100, "dB", "... standing this far above their valleys",
                                       experimental=True)
    max_peaks: int = integer(8, 1, 64, "", "at most this many peaks per line (the highest)", experimental=True)
    min_confidence: float = number(0.0, 0, 1000, "", "gate: a line below this confidence is an empty set",
                                   experimental=True)
    min_power_db: float = number(-100.0, -300, 100, "dB", "gate: a line below this power is an empty set "
                                 "(KrakenSDR floors it at -100)", experimental=True)
    reject_overdrive: bool = flag(True, "gate: frames its status.json flags (ADC overdrive, DAQ not in sync) "
                                  "are empty sets", experimental=True)
    clutter: str = choice("fixed", ("fixed", "adaptive"), "the clutter rate of a KrakenSDR scan: fixed "
                          "(sensor.clutter_rate) or adaptive (what its peaks show)", experimental=True)
    clutter_min: float | None = number(None, 0, 1000, "1/scan", "adaptive clutter: its floor; null: the "
                                       "filter's own rate (sensor.clutter_rate, PMON_CLUTTER)", nullable=True,
                                       experimental=True)
    clutter_max: float = number(10.0, 0, 1000, "1/scan", "adaptive clutter: its ceiling (>= clutter_min)",
                                experimental=True)
    clutter_window: int = integer(20, 1, 10_000, "scans", "adaptive clutter: averaged over this many scans "
                                  "per target", experimental=True)
    time_source: str = choice("autopilot", ("autopilot", "host"), "its Unix stamps to autopilot time through "
                              "the autopilot's UTC (SYSTEM_TIME) or this computer's clock")
    poll_s: float = number(0.05, 0.005, 10, "s", "wall time between reads of url", experimental=True)

    @property
    def mount_offset_rad(self) -> float:
        return math.radians(self.mount_offset_deg)


@dataclass(frozen=True, kw_only=True)
class Scenario:
    name: str = text(MISSING, "the scenario's name")
    origin: Origin = section(Origin, "geodetic origin of the ENU mission frame", required=True)
    area: Area = section(Area, "the surveillance environment E", required=True)
    dynamics: Dynamics = section(Dynamics, "the targets' motion model (eq. target_dynamics)")
    initial_cov_diag: tuple[float, ...] = vector((200.0, 200.0, 1e-10, 20.0, 20.0, 1e-10), 6, 0, 1e6,
                                                 "m^2, (m/s)^2", "diagonal of Sigma_0, every target's "
                                                 "initial covariance", paper=True, experimental=True)
    targets: tuple[Target, ...] = records(Target, 1, 64, "the targets (their initial means)")
    goals: tuple[Box, ...] = records(Box, 1, 64, "goal regions on the ground; guidance steers to a centroid")
    obstacles: tuple[Box, ...] = records(Box, 0, 256, "cuboids the targets go around", required=False)
    guidance: Guidance = section(Guidance, "Problem P1: the targets' guidance")
    sensor: Sensor = section(Sensor, "the direction finder")
    uav: Uav = section(Uav, "the UAV and its candidate grid", required=True)
    tracking: Tracking = section(Tracking, "the particle filters")
    planning: Planning = section(Planning, "where the UAV flies next")
    mission: Mission = section(Mission, "the simulated mission")
    app: App = section(App, "the onboard app (pmon run)")
    kraken: Kraken = section(Kraken, "a KrakenSDR as the DF (pmon run --kraken)")
    source: str = field(default="<memory>", compare=False)  # where it was read from, for messages
    overrides: tuple[tuple[str, Any], ...] = field(default=(), compare=False)  # KEY=VALUE applied, in order

    def goal_of(self, target: Target) -> Box | None:
        """Its goal region; None when its goal is not known."""
        return next((g for g in self.goals if g.name == target.goal), None)

    def goal_point(self, target: Target) -> tuple[float, float, float]:
        """Where one goal-directed model of the target steers it: its goal's centroid, or, its goal
        unknown, its initial mean position (it stays: the paper's filter needs one goal)."""
        g = self.goal_of(target)
        return target.position_m if g is None else g.center_m

    def goal_named(self, name: str) -> Box:
        return next(g for g in self.goals if g.name == name)

    @property
    def initial_cov(self):
        import numpy as np

        return np.diag(self.initial_cov_diag)


# null settings whose value is derived from others (the PMON_* parameter carries the number)
DERIVED: dict[str, Callable[[Scenario], float]] = {
    "app.reach_m": lambda sc: max(sc.uav.n_radial * sc.uav.step_m, 1.0),
    "app.fence_min_m": lambda sc: min(10.0, sc.uav.altitude_m),
    "app.fence_max_m": lambda sc: max(120.0, sc.uav.altitude_m),
}


# --------------------------------------------------------------------------- by key


SETTINGS: dict[str, Setting] = {key: s for key, _, s in walk(Scenario)}
PARAMS: dict[str, str] = {s.param: key for key, s in SETTINGS.items() if s.param}  # PMON name -> key


def value_of(sc: Scenario, key: str) -> Any:
    """The value of a dotted key (no records), a null derived one resolved (``DERIVED``)."""
    obj: Any = sc
    for part in key.split("."):
        obj = getattr(obj, part)
    if obj is None and key in DERIVED:
        return DERIVED[key](sc)
    return obj


def experimental_changes(sc: Scenario) -> list[tuple[str, str, str]]:
    """(key, value, default) of each experimental setting ``sc`` holds at other than its declared
    default (a field of a list's items: the items' values that differ), in declaration order."""
    out = []
    for key, f, s in walk(Scenario):
        if not s.experimental:
            continue
        head, sep, name = key.rpartition("[].")
        values = [getattr(item, name) for item in value_of(sc, head)] if sep else [value_of(sc, key)]
        changed = [v for v in values if v != f.default]
        if changed:
            out.append((key, ", ".join(value_text(v) for v in changed), default_text(f)))
    return out
