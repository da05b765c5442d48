"""The service side of the flip (issue 5): plan execution, the plan message, the flip item."""

import math

import numpy as np
import pytest

import schemas
from flight.control.flip_runner import loop_rate_hz
from flight.control.mission import MissionError, MissionPlanner, MissionRunner
from flight.control.plan import RotorPlan, body_state
from flight.quat import quat_from_euler, quat_integrate, quat_to_euler
from services.stack import load_mission


def _plan_msg(h=3, n=17, t0=1.0, dt=0.1):
    rng = np.random.default_rng(0)
    return {"method": "ilqr-project", "phase": "flip", "t0_s": t0, "dt_s": dt, "horizon": h, "state_dim": n,
            "states": rng.normal(size=(h + 1) * n).tolist(), "controls_rad_s": [1000.0] * (4 * h),
            "gains": rng.normal(size=4 * h * n).tolist(), "roll_rad": 0.0, "target_roll_rad": [0.0] * h,
            "solve_ms": 2.0, "iterations": 3, "cost": 1.0, "converged": True, "solves": 1,
            "failed_solves": 0, "overrun_solves": 0}


def test_plan_message_checks_its_sizes():
    msg = _plan_msg()
    doc = schemas.PLANNER_PLAN.decode(schemas.PLANNER_PLAN.encode(1.0, 0, "planner", msg))
    assert RotorPlan.from_message(doc).gains.shape == (3, 4, 17)
    bad = dict(msg, gains=msg["gains"][:-1])
    with pytest.raises(schemas.SchemaError) as exc:
        schemas.PLANNER_PLAN.encode(1.0, 0, "planner", bad)
    assert exc.value.reason == "wrong_length"


def test_rotor_plan_feedback_and_validity():
    plan = RotorPlan.from_message(_plan_msg())
    assert plan.valid_at(1.0) and plan.valid_at(1.29) and not plan.valid_at(1.3) and not plan.valid_at(0.9)
    # on the plan: the plan's control; off it: + K dx, clipped
    x = 0.5 * plan.states[1] + 0.5 * plan.states[2]
    assert np.allclose(plan.control(1.15, x, 1e9), plan.controls[1])
    dx = np.zeros(17)
    dx[0] = 0.01
    assert np.allclose(plan.control(1.15, x + dx, 1e9), plan.controls[1] + plan.gains[1] @ dx)
    assert np.all(plan.control(1.15, x + 1e3, 2100.0) <= 2100.0)


def test_body_state_carries_the_estimates_to_now():
    q = quat_from_euler(0.2, 0.0, 0.0)
    att = {"header": {"t_s": 1.0}, "quaternion_wxyz": list(q), "rate_rad_s": [10.0, 0.0, 0.0]}
    pos = {"header": {"t_s": 0.99}, "position_m": [1.0, 2.0, 5.0], "velocity_m_s": [1.0, 0.0, -1.0]}
    x = body_state(1.005, att, pos)
    assert np.allclose(x[0:3], [1.015, 2.0, 4.985])
    assert quat_to_euler(x[6:10])[0] == pytest.approx(0.25)
    assert np.allclose(quat_integrate(q, [0.0, 0.0, 0.0], 1.0), q)


def test_body_state_carries_the_translation_by_the_model():
    """With the vehicle and the rotor forces flown, velocity and position are carried with
    the model's acceleration: matches the plant integrated over the same age (inverted,
    collective 2 g: the body falls at 3 g; at constant velocity it would be 3 cm/s off
    per ms of age)."""
    from flight.control.plan import thrust_acceleration
    from flight.vehicle import load_vehicle
    from simulator.plant import Plant
    vehicle = load_vehicle("q820")
    q = quat_from_euler(math.pi, 0.0, 0.0)  # upside down
    forces = np.full(4, vehicle.mass_kg * 9.81 * 2.0 / 4.0)
    v0 = np.array([0.5, 0.0, 0.0])
    accel = thrust_acceleration(vehicle, q, forces, v0)
    assert np.allclose(accel, [-0.1 * 0.5 / vehicle.mass_kg, 0.0, -3.0 * 9.81], atol=1e-6)
    att = {"header": {"t_s": 1.0}, "quaternion_wxyz": list(q), "rate_rad_s": [0.0, 0.0, 0.0]}
    pos = {"header": {"t_s": 0.99}, "position_m": [0.0, 0.0, 5.0], "velocity_m_s": list(v0)}
    x = body_state(1.0, att, pos, vehicle, forces)
    plant = Plant(vehicle, position_m=(0.0, 0.0, 5.0), velocity_m_s=v0, motor_thrust_n=forces)
    plant.x[6:10] = q
    for _ in range(50):
        plant.step(0.0002, forces, np.zeros(3))
    assert np.allclose(x[3:6], plant.x[3:6], atol=2e-3)
    assert np.allclose(x[0:3], plant.x[0:3], atol=1e-5)
    assert np.allclose(body_state(1.0, att, pos)[3:6], v0)  # without the model: constant velocity


def test_loop_rate_is_a_multiple_of_every_solve_rate():
    assert loop_rate_hz(50.0, 400.0, [100.0]) == 100.0
    assert loop_rate_hz(50.0, 400.0, [20.0]) == 80.0
    assert loop_rate_hz(50.0, 400.0, [20.0, 100.0]) == 100.0
    assert loop_rate_hz(50.0, 400.0, [200.0]) == 200.0


def test_flip_mission_item_and_hook():
    mission = load_mission("flip")
    flip = [i for i in mission.items if i["type"] == "flip"]
    assert mission.vehicle == "q820" and flip[0]["method"] == "ilqr-project" and flip[0]["altitude_m"] >= 5.0
    calls = []

    def hook(item, t, starting):
        calls.append(starting)
        return ("recovery", len(calls) >= 3, False, np.array([0.0, 0.1, 5.0]))

    runner = MissionRunner(mission, hook)
    runner.index = mission.items.index(flip[0])
    runner.ref = np.array([0.0, 0.0, 5.0])
    for k in range(3):
        sp = runner.update(10.0 + 0.01 * k, [0.0, 0.0, 5.0], [0.0, 0.0, 0.0])
        assert sp.phase == "flip-recovery" and sp.mode == ("plan" if k < 2 else "position")
    assert calls == [True, False, False]
    assert runner.index == mission.items.index(flip[0]) + 1 and list(runner.ref) == [0.0, 0.1, 5.0]
    # no flip controller: the mission fails on the flip item, a flip command is refused
    bare = MissionRunner(mission)
    bare.index = runner.index - 1
    assert bare.update(0.0, [0, 0, 5], [0, 0, 0]).mission_state == "failed"
    with pytest.raises(MissionError):
        MissionPlanner(None).command("flip")


def test_flip_item_refuses_a_low_altitude_and_unknown_method(tmp_path):
    for body, what in (('altitude_m = 3.0', "altitude_m >= 5"), ('method = "loop"', "method")):
        path = tmp_path / "m.toml"
        path.write_text(f'[mission]\nname = "m"\nvehicle = "q820"\n[[items]]\ntype = "flip"\n{body}\n')
        with pytest.raises(MissionError, match=what):
            load_mission(str(path))


def test_scale_collective_keeps_torques_and_inverts():
    from flight.control.plan import scale_collective
    from flight.vehicle import load_vehicle
    veh = load_vehicle("q820")
    forces = np.array([4.0, 5.0, 6.0, 4.5])
    sent = scale_collective(veh.allocation, forces, 1 / 0.9)
    w, w_sent = veh.allocation @ forces, veh.allocation @ sent
    assert w_sent[0] == pytest.approx(w[0] / 0.9)
    np.testing.assert_allclose(w_sent[1:], w[1:], atol=1e-12)
    np.testing.assert_allclose(scale_collective(veh.allocation, sent, 0.9), forces, atol=1e-12)


def test_body_state_floats_match_numpy_to_rounding():
    """body_state runs in Python floats; its numpy definition (_body_state_arrays) gives the
    same numbers to the last bits (numpy's SIMD kernels round differently on some CPUs), with and without the model's carry, fresh and aged messages, at rest and turning."""
    from flight.control.plan import _body_state_arrays, _body_state_floats
    from flight.vehicle import load_vehicle
    vehicle = load_vehicle("q820")
    rng = np.random.default_rng(3)
    for i in range(5000):
        att = {"header": {"t_s": 10.0 - rng.uniform(0, 0.01) * (i % 5 != 0)},
               "quaternion_wxyz": (rng.normal(size=4) / 2).tolist(),
               "rate_rad_s": [0.0, 0.0, 0.0] if i % 7 == 0 else (rng.normal(size=3) * 10 ** rng.uniform(-3, 1.5)).tolist()}
        pos = {"header": {"t_s": 10.0 - rng.uniform(0, 0.02) * (i % 4 != 0)},
               "position_m": rng.normal(size=3).tolist(), "velocity_m_s": rng.normal(size=3).tolist()}
        forces = rng.uniform(0, 8, 4) if i % 3 else None
        a_age, p_age = 10.0 - att["header"]["t_s"], 10.0 - pos["header"]["t_s"]
        for v in (vehicle, None):
            expected = _body_state_arrays(a_age, p_age, att, pos, v, forces)
            np.testing.assert_allclose(_body_state_floats(a_age, p_age, att, pos, v, forces), expected,
                                       rtol=1e-14, atol=1e-15)
    att["quaternion_wxyz"] = [0.0, 0.0, 0.0, 0.0]   # numpy's way decides: its error, not ZeroDivisionError
    with pytest.raises(ValueError, match="zero or non-finite"):
        body_state(10.0, att, pos, vehicle, np.full(4, 5.0))
