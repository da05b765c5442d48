"""The motor driver's logic (services/motors.py MotorDriver) without a router."""

import numpy as np
import pytest

import schemas
from flight.control.mixer import mix
from flight.motor_model import thrust_to_pwm
from flight.vehicle import load_vehicle
from services.motors import PARAMS, MotorDriver
from tests.unit.services.fake_io import FakeIO

X250 = load_vehicle("x250")
HOVER_N = X250.mass_kg * X250.gravity_m_s2


def planner(armed=True, mode="position"):
    return {"mode": mode, "armed": armed, "position_m": [0.0, 0.0, 1.0], "attitude_rad": [0.0, 0.0, 0.0],
            "item": 1, "phase": "hold", "measure": False, "mission_state": "running"}


def driver(**params):
    io = FakeIO("motors", PARAMS, params, rate_hz=400.0)
    io.tick_rate = 400.0
    return io, MotorDriver(io)


def test_a_fresh_command_is_mixed_into_pwm():
    io, d = driver()
    io.received(schemas.PLANNER_SETPOINT, "planner").push(1.0, planner())
    io.received(schemas.ATTITUDE_COMMAND, "attitude").push(1.0, {"thrust_n": HOVER_N, "torque_nm": [0.001, 0.0, 0.0],
                                                                  "imu_t_s": 0.999})
    d.step(1.0025)
    [(t, out)] = io.sent(schemas.MOTOR_PWM)
    forces, _ = mix(X250, HOVER_N, [0.001, 0.0, 0.0])
    assert t == 1.0025 and out["armed"] and not out["saturated"] and out["imu_t_s"] == 0.999
    np.testing.assert_allclose(out["pwm_us"], thrust_to_pwm(X250, forces))
    assert sum(out["thrust_n"]) == pytest.approx(HOVER_N)


def test_disarmed_is_idle_and_a_stale_command_is_never_mixed():
    io, d = driver()
    setpoints, commands = io.received(schemas.PLANNER_SETPOINT, "planner"), io.received(schemas.ATTITUDE_COMMAND, "attitude")
    setpoints.push(1.0, planner(armed=False))
    commands.push(1.0, {"thrust_n": HOVER_N, "torque_nm": [0.0, 0.0, 0.0], "imu_t_s": 1.0})
    d.step(1.0)
    assert io.sent(schemas.MOTOR_PWM)[-1][1]["pwm_us"] == [X250.pwm_min_us] * 4
    setpoints.push(2.0, planner(armed=True))
    commands.push(1.9, {"thrust_n": HOVER_N, "torque_nm": [0.0, 0.0, 0.0], "imu_t_s": 1.9})   # 0.1 s old
    d.step(2.0)
    _, out = io.sent(schemas.MOTOR_PWM)[-1]
    assert out["armed"] and out["thrust_n"] == [0.0] * 4   # armed, nothing to fly: idle
    assert io.rejected == {"stale_att_command": 1}


def test_the_attitude_level_gone_in_the_air_the_driver_descends_on_its_own():
    io, d = driver()
    setpoints, commands = io.received(schemas.PLANNER_SETPOINT, "planner"), io.received(schemas.ATTITUDE_COMMAND, "attitude")
    setpoints.push(1.0, planner())
    commands.push(1.0, {"thrust_n": HOVER_N, "torque_nm": [0.0, 0.0, 0.0], "imu_t_s": 1.0})
    d.step(1.0)
    imu = None
    for n in range(1, 41):   # 0.1 s with no command: the failsafe flies from the raw IMU
        t = 1.0 + n / 400
        d.step(t)
        if imu is None and ("imu", "sim") in io.inboxes:
            imu = io.received(schemas.IMU, "sim")   # subscribed when first needed
        if imu is not None:
            imu.push(t, {"gyro_rad_s": [0.0, 0.0, 0.0], "accel_m_s2": [0.0, 0.0, X250.gravity_m_s2]})
    assert imu is not None and io.rejected.get("failsafe_engaged") == 1
    _, out = io.sent(schemas.MOTOR_PWM)[-1]
    assert out["armed"] and 0.0 < sum(out["thrust_n"]) <= HOVER_N * 1.01
    commands.push(1.2, {"thrust_n": HOVER_N, "torque_nm": [0.0, 0.0, 0.0], "imu_t_s": 1.2})
    d.step(1.2)
    assert io.rejected.get("failsafe_recovered") == 1


@pytest.mark.parametrize("params, key", [({"command_timeout_s": 2.0}, "command_timeout_s"),
                                         ({"output": "can-bus"}, "output")])
def test_bad_parameters_are_refused_naming_the_key(params, key):
    with pytest.raises(ValueError, match=f"services.motors.params.*{key}"):
        driver(**params)


def test_restarted_mid_flight_it_says_nothing_until_it_has_heard_the_planner_and_a_command():
    io = FakeIO("motors", PARAMS, {}, rate_hz=400.0, restarted=True)
    io.tick_rate = 400.0
    d = MotorDriver(io)
    setpoints, commands = io.received(schemas.PLANNER_SETPOINT, "planner"), io.received(schemas.ATTITUDE_COMMAND, "attitude")
    d.step(1.0)                       # nothing heard: an idle output would cut a vehicle in the air
    setpoints.push(1.0, planner())    # armed, flying: still nothing until a command
    d.step(1.0025)
    assert io.sent(schemas.MOTOR_PWM) == []
    commands.push(1.004, {"thrust_n": HOVER_N, "torque_nm": [0.0, 0.0, 0.0], "imu_t_s": 1.004})
    d.step(1.005)
    [(_, out)] = io.sent(schemas.MOTOR_PWM)
    assert out["armed"] and sum(out["thrust_n"]) == pytest.approx(HOVER_N)
    io2 = FakeIO("motors", PARAMS, {}, rate_hz=400.0, restarted=True)
    io2.tick_rate = 400.0
    d2 = MotorDriver(io2)
    io2.received(schemas.PLANNER_SETPOINT, "planner").push(1.0, planner(armed=False))
    d2.step(1.0)                      # told it is disarmed: idle, as always
    assert io2.sent(schemas.MOTOR_PWM)[-1][1]["pwm_us"] == [X250.pwm_min_us] * 4


# ---------------------------------------------------------------- plans (the flip of 001)
def _plan(t0_s, speed_rad_s, horizon=4, dt_s=0.025):
    """A plan of constant rotor speeds, zero gains, the hover state throughout."""
    x = [0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    return {"method": "ilqr-project", "phase": "flip", "t0_s": t0_s, "dt_s": dt_s, "horizon": horizon,
            "state_dim": 13, "states": x * (horizon + 1), "controls_rad_s": [speed_rad_s] * 4 * horizon,
            "gains": [0.0] * 4 * 13 * horizon, "roll_rad": 0.0, "target_roll_rad": [0.0] * horizon,
            "solve_ms": 1.0, "iterations": 1, "cost": 1.0, "converged": True, "solves": 1, "failed_solves": 0,
            "overrun_solves": 0}


def _flying_plans():
    from tests.unit.services.test_attitude import pos_state
    from tests.unit.services.test_planner import attitude
    io, d = driver()
    io.received(schemas.PLANNER_SETPOINT, "planner").push(1.0, planner(mode="plan"))
    io.received(schemas.ATTITUDE_STATE, "attitude").push(1.0, attitude())
    io.received(schemas.POSITION_STATE, "position").push(1.0, pos_state())
    commands = io.received(schemas.ATTITUDE_COMMAND, "attitude")
    return io, d, io.received(schemas.PLANNER_PLAN, "planner"), commands


def _flown_speed(io, d, commands, t):
    commands.push(t, {"thrust_n": HOVER_N, "torque_nm": [0.0, 0.0, 0.0], "imu_t_s": t})
    d.step(t)
    thrust = io.sent(schemas.MOTOR_PWM)[-1][1]["thrust_n"]
    return float(np.sqrt(np.mean(thrust) / X250.thrust_coefficient_kf))


def test_a_plan_that_starts_later_waits_while_the_one_flying_goes_on():
    """A planner across a link sends its plans ahead (planner.plan_lead_s): the driver keeps
    flying the plan that has started, takes each later one at its start, and counts no fallback."""
    io, d, plans, commands = _flying_plans()
    plans.push(1.0, _plan(1.0, 1000.0))
    for k in range(1, 5):   # four plans made before they start, 10 ms apart, each 40 ms ahead
        plans.push(1.0 + 0.01 * k, _plan(1.04 + 0.01 * k, 1000.0 + 100.0 * k))
    assert _flown_speed(io, d, commands, 1.045) == pytest.approx(1000.0, rel=0.02)
    assert _flown_speed(io, d, commands, 1.0525) == pytest.approx(1100.0, rel=0.02)
    assert _flown_speed(io, d, commands, 1.085) == pytest.approx(1400.0, rel=0.02)
    assert io.rejected == {}


def test_with_the_newest_plan_over_an_older_one_flies_and_then_the_hover_laws():
    io, d, plans, commands = _flying_plans()
    plans.push(1.0, _plan(1.0, 1000.0, horizon=8))
    plans.push(1.01, _plan(1.01, 1200.0, horizon=2))   # the newest ends at 1.06, the older at 1.20
    assert _flown_speed(io, d, commands, 1.05) == pytest.approx(1200.0, rel=0.02)
    assert _flown_speed(io, d, commands, 1.10) == pytest.approx(1000.0, rel=0.02)
    assert io.rejected == {"plan_fallback_previous": 1}
    _flown_speed(io, d, commands, 1.25)   # every plan over: the attitude command is mixed
    assert io.rejected == {"plan_fallback_previous": 1, "plan_fallback_hover": 1}
