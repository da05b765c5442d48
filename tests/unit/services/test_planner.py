"""The planner's logic (services/planner.py PlannerLoop) without a router: missions and
commands (the flip's controllers are tested in tests/unit/test_flip*.py)."""

import pytest

import schemas
from services.planner import PARAMS, PlannerLoop
from tests.unit.services.fake_io import FakeIO


def state(pos=(0.0, 0.0, 0.0)):
    return {"position_m": list(pos), "velocity_m_s": [0.0, 0.0, 0.0], "position_ref_m": list(pos),
            "position_cov_m2": [0.0] * 9, "acceleration_m_s2": [0.0, 0.0, 0.0], "thrust_scale": 1.0,
            "state_source": "truth"}


def command(name, altitude_m=0.0):
    return {"command": name, "altitude_m": altitude_m, "position_m": [0.0, 0.0, 0.0], "yaw_rad": 0.0,
            "origin": "test"}


def loop_for(mission, **params):
    io = FakeIO("planner", PARAMS, params, rate_hz=50.0)
    io.tick_rate = 400.0
    return io, PlannerLoop(io, mission)


def test_waits_for_a_state_then_flies_the_mission():
    io, loop = loop_for("hover")
    loop.step(0.0)
    [(_, sp)] = io.sent(schemas.PLANNER_SETPOINT)
    assert not sp["armed"] and sp["mission_state"] == "waiting"
    states = io.received(schemas.POSITION_STATE, "position")
    for n in range(1, 100):   # 2 s on the ground: armed, then taking off
        states.push(n / 50, state())
        loop.step(n / 50)
    _, sp = io.sent(schemas.PLANNER_SETPOINT)[-1]
    assert sp["armed"] and sp["mission_state"] == "running" and sp["position_m"][2] > 0.0


def test_commands_replace_the_mission_and_a_bad_one_is_refused_and_counted():
    io, loop = loop_for("none")
    states, commands = io.received(schemas.POSITION_STATE, "position"), io.received(schemas.PLANNER_COMMAND, "mavlink")
    states.push(0.0, state())
    commands.push(0.0, command("takeoff", altitude_m=500.0))   # outside (0, 100] m
    commands.push(0.0, command("flip"))                         # no flip controller without a flip item
    loop.step(0.0)
    assert io.rejected == {"command_refused": 2} and "refused" in io.problems[-1]
    commands.push(0.02, command("arm"))
    commands.push(0.02, command("takeoff", altitude_m=2.0))
    for n in range(1, 50):
        states.push(n / 50, state())
        loop.step(n / 50)
    _, sp = io.sent(schemas.PLANNER_SETPOINT)[-1]
    assert sp["armed"] and sp["position_m"][2] > 0.0
    commands.push(1.0, command("disarm"))
    loop.step(1.0)
    assert not io.sent(schemas.PLANNER_SETPOINT)[-1][1]["armed"]


def test_an_unknown_mission_or_flip_method_is_refused_at_start():
    with pytest.raises(ValueError, match="nonesuch"):
        loop_for("nonesuch")
    with pytest.raises(ValueError, match="services.planner.params.*flip_method"):
        loop_for("flip", flip_method="cartwheel")
