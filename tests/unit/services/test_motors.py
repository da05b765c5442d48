"""The motor driver's logic (services/motors.py MotorDriver) without a router."""

import numpy as np
import pytest

import schemas
from flight.control.mixer import mix
from flight.motor_model import thrust_step, thrust_to_pwm
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
    io, d = driver(lag_compensation_tau_s=X250.motor_time_constant_s)   # no lead: the mixer's forces as they are
    io.received(schemas.PLANNER_SETPOINT, "planner").push(1.0, planner())
    io.received(schemas.ATTITUDE_COMMAND, "attitude").push(1.0, {"thrust_n": HOVER_N, "torque_nm": [0.001, 0.0, 0.0],
                                                                  "imu_t_s": 0.999})
    d.step(1.0025)
    [(t, out)] = io.sent(schemas.MOTOR_PWM)
    forces, _ = mix(X250, HOVER_N, [0.001, 0.0, 0.0])
    assert t == 1.0025 and out["armed"] and not out["saturated"] and out["imu_t_s"] == 0.999
    np.testing.assert_allclose(out["pwm_us"], thrust_to_pwm(X250, forces))
    assert sum(out["thrust_n"]) == pytest.approx(HOVER_N)


def fly_commands(d, io, torques, t0=1.0, dt=0.0025):
    """Each torque as a fresh hover command, one driver step apiece; the rotors' forces (the
    exact speed lag of what was sent) after each step, and the outputs."""
    setpoints, commands = io.received(schemas.PLANNER_SETPOINT, "planner"), io.received(schemas.ATTITUDE_COMMAND, "attitude")
    setpoints.push(t0, planner())
    rotors, after, outs = np.zeros(4), [], []
    for i, torque in enumerate(torques):
        t = t0 + i * dt
        commands.push(t, {"thrust_n": HOVER_N, "torque_nm": torque, "imu_t_s": t})
        d.step(t)
        out = io.sent(schemas.MOTOR_PWM)[-1][1]
        rotors = thrust_step(rotors, out["thrust_n"], dt, X250.motor_time_constant_s)
        after.append(rotors)
        outs.append(out)
    return after, outs


def test_the_lead_makes_the_rotors_follow_the_mixer_with_the_target_time_constant():
    """lag_compensation_tau_s: the rotors (the simulator's exact lag of what was sent) reach the
    mixer's forces with that time constant instead of their own 20 ms; once there the output
    is the mixer's; without it they lag by 20 ms."""
    target, h = 0.01, 0.0025
    small = [0.005, -0.003, 0.0]     # a torque that fits with the lead
    settle, step = [[0.0, 0.0, 0.0]] * 400, [small] * 8
    for tau_param, time_constant in ((target, target), (X250.motor_time_constant_s, X250.motor_time_constant_s)):
        io, d = driver(lag_compensation_tau_s=tau_param)
        after, outs = fly_commands(d, io, settle + step)
        hover, _ = mix(X250, HOVER_N, [0.0, 0.0, 0.0])
        np.testing.assert_allclose(after[399], hover, rtol=1e-9)
        np.testing.assert_allclose(outs[399]["thrust_n"], hover, rtol=1e-9)   # settled: no lead left
        desired, _ = mix(X250, HOVER_N, small)
        s_d, s = np.sqrt(desired), np.sqrt(after[399])
        for k in range(8):   # each step: s_d + (s - s_d) exp(-h / time constant)
            s = s_d + (s - s_d) * np.exp(-h / time_constant)
            np.testing.assert_allclose(np.sqrt(after[400 + k]), s, rtol=1e-9)


def test_a_lead_that_does_not_fit_is_scaled_back_and_still_helps():
    """A roll step near the rotors' range (the low rotors asked for 0.13 N from 0.98 N): the led
    commands stay in [min, max]; the rotors' roll torque rises faster than without the lead and
    their collective dips less (their speeds lag, their forces go with the speeds squared)."""
    big = [0.3, 0.0, 0.0]
    flown = {}
    for tau in (0.01, X250.motor_time_constant_s):
        io, d = driver(lag_compensation_tau_s=tau)
        after, outs = fly_commands(d, io, [[0.0, 0.0, 0.0]] * 400 + [big] * 12)
        for out in outs[400:]:
            f = np.array(out["thrust_n"])
            assert np.all(f >= X250.min_thrust_n) and np.all(f <= X250.max_thrust_n)
        flown[tau] = np.array([X250.allocation @ a for a in after[400:]])
    led, lagged = flown[0.01], flown[X250.motor_time_constant_s]
    assert np.all(led[:, 1] > lagged[:, 1])
    assert np.all(np.abs(led[:, 0] - HOVER_N) <= np.abs(lagged[:, 0] - HOVER_N) + 1e-12)


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
    # the rotors already spin at what the driver before sent: no lead from rest on this one
    np.testing.assert_allclose(out["thrust_n"], mix(X250, HOVER_N, [0.0, 0.0, 0.0])[0], rtol=1e-12)
    io2 = FakeIO("motors", PARAMS, {}, rate_hz=400.0, restarted=True)
    io2.tick_rate = 400.0
    d2 = MotorDriver(io2)
    io2.received(schemas.PLANNER_SETPOINT, "planner").push(1.0, planner(armed=False))
    d2.step(1.0)                      # told it is disarmed: idle, as always
    assert io2.sent(schemas.MOTOR_PWM)[-1][1]["pwm_us"] == [X250.pwm_min_us] * 4
