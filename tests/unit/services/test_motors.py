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
