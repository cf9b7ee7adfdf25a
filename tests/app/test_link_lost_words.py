"""What the app says when the autopilot link is lost, by state: "setpoints stopped" only where
setpoints were flowing (monitoring), "launch aborted" only where a launch ran; advisory, idle
and paused keep estimating and say so without claiming to stop what never flowed."""
from types import SimpleNamespace

import pytest

from onboard.app.contract import State
from onboard.app.state_machine import StateMachine


def _machine(state: State, launching: bool = False):
    said = []
    publisher = SimpleNamespace(say=lambda text, *a, **k: said.append(text), heartbeat=lambda: None)
    vehicle = SimpleNamespace(profile=SimpleNamespace(release_mode=None), in_mission_mode=lambda: True)
    autopilot = SimpleNamespace(vehicle=vehicle, link_lost=True)
    ctx = SimpleNamespace(link=None, clock=SimpleNamespace(now=lambda: 0.0), params=None,
                          cfg=SimpleNamespace(auto_launch=False, advise=False))
    sm = StateMachine(ctx, autopilot, publisher, SimpleNamespace(clear=lambda: None), None, None)
    sm.state = state
    sm.launch = object() if launching else None
    return sm, said


@pytest.mark.parametrize("state, launching, words, to", [
    (State.MONITORING, False, "autopilot link lost: setpoints stopped, estimating", State.FAULT),
    (State.PAUSED, False, "autopilot link lost, estimating", State.FAULT),
    (State.ADVISORY, False, "autopilot link lost, estimating", State.ADVISORY),
    (State.IDLE, False, "autopilot link lost, estimating", State.IDLE),
    (State.IDLE, True, "autopilot link lost: launch aborted, estimating", State.IDLE),
])
def test_link_lost_says_only_what_stopped(state, launching, words, to):
    sm, said = _machine(state, launching)
    sm.on_link_lost()
    assert said == [words]
    assert sm.state == to and sm.launch is None
