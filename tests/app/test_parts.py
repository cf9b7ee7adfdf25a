"""The part contract (onboard/app/part.py): the app runs its parts' jobs in one fixed order (a
job's place is its timing), clocked jobs wait for the autopilot's clock, and the router hands
each message to the parts that registered its type, only from whom it may be obeyed."""
from __future__ import annotations

from types import SimpleNamespace

import pytest

from onboard.app.app import OnboardApp
from onboard.app.app_config import AppConfig
from onboard.app.autopilot.clock import ManualClock
from onboard.app.counters import Counters
from onboard.app.gcs.dispatch import Router
from onboard.app.part import Part
from onboard.config import load_scenario
from onboard.policy import with_policy

JOBS = ["periodic heartbeat", "periodic telemetry", "periodic signing", "periodic link", "periodic clock",
        "periodic DF input", "periodic mode", "periodic launch", "tick schedule", "setpoint stream"]
CLOCKED = {"periodic mode", "periodic launch", "setpoint stream"}


@pytest.fixture
def app():
    a = OnboardApp(AppConfig("udpin:127.0.0.1:0", sensor_port=0), with_policy(load_scenario("paper"), "paper"),
                   clock=ManualClock(None))
    yield a
    a.stop()


@pytest.mark.timeout(30)
def test_the_jobs_run_in_their_order_and_clocked_ones_wait_for_the_clock(app):
    assert [j.where for j in app.jobs] == JOBS
    assert {j.where for j in app.jobs if j.clocked} == CLOCKED
    ran = []
    for part in app.parts:
        for name in ("beat", "periodic_requests", "periodic_signing", "periodic_link", "periodic_clock", "report",
                     "periodic_mode", "periodic_launch", "run", "stream"):
            if hasattr(part, name):
                setattr(part, name, lambda *a, _n=name: ran.append(_n))
    app.machine.may_stream = lambda: True
    app._periodic()  # no clock sample yet
    assert ran == ["beat", "periodic_requests", "periodic_signing", "periodic_link", "periodic_clock", "report"]
    before = app.schedule.ran_local
    ran.clear()
    app.clock.t = 10.0
    app._periodic()
    assert ran == ["beat", "periodic_requests", "periodic_signing", "periodic_link", "periodic_clock", "report",
                   "periodic_mode", "periodic_launch", "run", "stream"]
    assert app.schedule.ran_local >= before


@pytest.mark.timeout(30)
def test_a_job_that_raises_costs_itself_under_its_name(app):
    app.clock.t = 10.0
    app.autopilot.periodic_signing = lambda local: [][0]
    streamed = []
    app.machine.may_stream = lambda: True
    app.stream.stream = lambda now: streamed.append(now)
    app._periodic()
    assert app.errors.counts == {"periodic signing: IndexError": 1}
    assert streamed == [10.0]


class _Msg:
    def __init__(self, mtype, src=(1, 1), **fields):
        self.mtype, self.src = mtype, src
        self.__dict__.update(fields)

    def get_type(self):
        return self.mtype

    def get_srcSystem(self):
        return self.src[0]

    def get_srcComponent(self):
        return self.src[1]


class _Recorder(Part):
    def __init__(self, name, types, got):
        self.name, self.types, self.got = name, types, got

    def handlers(self):
        return {t: (lambda msg, _t=t: self.got.append((self.name, _t))) for t in self.types}


def _router(*parts):
    said = []
    seen = []
    autopilot = SimpleNamespace(vehicle=SimpleNamespace(sysid=1, compid=1), observe_time=seen.append)
    ctx = SimpleNamespace(cfg=SimpleNamespace(gcs_sysids=(255,)), counters=Counters(),
                          say=lambda text, *a, **k: said.append(text))
    return Router(ctx, autopilot, list(parts)), said, seen


def test_each_message_goes_to_the_parts_that_registered_its_type_in_their_order():
    got = []
    router, said, seen = _router(_Recorder("a", ("SYS_STATUS", "HEARTBEAT"), got), _Recorder("b", ("SYS_STATUS",), got))
    router.handle(_Msg("SYS_STATUS"))
    router.handle(_Msg("HEARTBEAT", src=(7, 1)))  # from anyone
    router.handle(_Msg("ATTITUDE"))  # nobody's: dropped, still a clock sample
    assert got == [("a", "SYS_STATUS"), ("b", "SYS_STATUS"), ("a", "HEARTBEAT")]
    assert len(seen) == 2


def test_who_may_be_obeyed_is_the_routers():
    got = []
    router, said, seen = _router(_Recorder("p", ("PARAM_REQUEST_READ", "PARAM_SET", "SYS_STATUS"), got))
    router.handle(_Msg("SYS_STATUS", src=(255, 190)))  # an autopilot message from a stranger
    router.handle(_Msg("PARAM_REQUEST_READ", src=(1, 1), target_system=1, target_component=191))  # from the autopilot
    router.handle(_Msg("PARAM_SET", src=(9, 190), target_system=1, target_component=191))  # not a GCS
    assert got == [] and router.counters["rejected_sysid"] == 1 and len(said) == 1
    router.handle(_Msg("PARAM_REQUEST_READ", src=(9, 190), target_system=0, target_component=0))  # reads: anyone
    router.handle(_Msg("PARAM_SET", src=(255, 190), target_system=1, target_component=191))
    assert got == [("p", "PARAM_REQUEST_READ"), ("p", "PARAM_SET")]
    router.handle(_Msg("BAD_DATA"))
    assert router.counters["mavlink_bad_data"] == 1
