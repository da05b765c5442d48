"""The planner's commands (from the MAVLink bridge): idle without a mission, commands replace the plan."""

import pytest

from flight.control.mission import MissionError, MissionPlanner
from services.stack import load_mission


def fly(planner, t0, t1, z_of_t, dt=0.02):
    """Feed the planner a vehicle that follows its reference exactly."""
    t = t0
    sp = planner.sp
    while t < t1:
        sp = planner.update(t, [0.0, 0.0, z_of_t(sp)], [0.0, 0.0, 0.0])
        t += dt
    return sp


def test_no_mission_waits_idle_until_commanded():
    p = MissionPlanner(None)
    sp = p.update(0.0, [0, 0, 0], [0, 0, 0])
    assert (sp.mode, sp.armed, sp.phase, sp.mission_state) == ("idle", False, "waiting", "waiting")
    p.command("arm")
    sp = fly(p, 0.0, 1.0, lambda sp: 0.0)
    assert sp.armed and sp.mode == "idle" and sp.phase == "arm"
    p.command("takeoff", altitude_m=2.0)
    sp = fly(p, 1.0, 8.0, lambda sp: sp.position_m[2])
    assert sp.armed and sp.mode == "position" and sp.position_m[2] == 2.0 and sp.phase == "hold"
    p.command("goto", position_m=[1.0, 0.0, 2.0], yaw_rad=0.5)
    sp = fly(p, 8.0, 9.0, lambda sp: 2.0)
    assert sp.position_m == [1.0, 0.0, 2.0] and sp.attitude_rad[2] == pytest.approx(0.5)
    p.command("hold")
    sp = fly(p, 9.0, 10.0, lambda sp: 2.0)
    assert sp.phase == "hold" and sp.attitude_rad[2] == pytest.approx(0.5)  # yaw kept
    p.command("land")
    sp = fly(p, 10.0, 20.0, lambda sp: max(0.0, sp.position_m[2]))
    assert sp.phase == "landed" and not sp.armed and sp.mission_state == "completed"


def test_disarm_and_refused_commands():
    p = MissionPlanner(load_mission("hover"))
    p.update(0.0, [0, 0, 0], [0, 0, 0])
    p.command("disarm")
    sp = p.update(0.1, [0, 0, 0], [0, 0, 0])
    assert not sp.armed and sp.mode == "idle" and sp.phase == "disarmed"
    with pytest.raises(MissionError):
        p.command("takeoff", altitude_m=0.0)


def test_uploaded_mission_flies_waypoints_by_acceptance_then_lands():
    from flight.control.mission import mission_items
    msg = {"types": ["takeoff", "goto", "goto", "land"],
           "position_m": [0, 0, 2.0, 1.0, 0, 2.0, 1.0, 1.0, 2.0, 0, 0, 0], "yaw_rad": [0.0, 0.0, 0.5, 0.0],
           "hold_s": [0.0, 1.0, 0.0, 0.0], "acceptance_m": [0.3] * 4, "origin": "test"}
    p = MissionPlanner(None)
    p.command("arm")
    fly(p, 0.0, 0.5, lambda sp: 0.0)
    p.fly(mission_items(msg))
    pos = [0.0, 0.0, 0.0]
    items_seen, t = [], 0.5
    while t < 40.0 and p.sp.mission_state != "completed":
        # a vehicle that moves towards its reference at 1 m/s
        ref = p.sp.position_m
        pos = [x + max(-0.02, min(0.02, r - x)) for x, r in zip(pos, ref)]
        pos[2] = max(pos[2], 0.0)
        sp = p.update(t, pos, [0.0, 0.0, 0.0])
        if not items_seen or items_seen[-1] != sp.item:
            items_seen.append(sp.item)
        t += 0.02
    assert items_seen == [0, 1, 2, 3]
    assert p.sp.phase == "landed" and not p.sp.armed and p.sp.mission_state == "completed"
    with pytest.raises(MissionError):
        p.fly([{"type": "flip"}])   # no flip controller
    with pytest.raises(MissionError):
        p.fly([])
