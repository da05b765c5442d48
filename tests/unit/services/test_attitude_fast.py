"""The attitude service's loop (services/attitude.py AttitudeLoop, floats from the filter to the
messages) against its zenpilot 6b2add1 version (bench/support/attitude_reference.py): the same
messages, byte for byte, over a flight with every input, a fast roll (the gyro carrier takes
over and hands back), a setpoint gap (the failsafe descent) and camera frames."""
import math

import numpy as np
import pytest

import schemas
from bench.support import attitude_reference
from flight.quat import quat_from_euler, quat_to_rotation
from flight.vehicle import load_vehicle
from services import attitude
from tests.unit.services.fake_io import FakeIO

X250 = load_vehicle("x250")
HOVER_N = X250.mass_kg * X250.gravity_m_s2
FIELD = np.array([0.0, 20.0, -45.0])


def inputs(seed: int, runs: int = 1000):
    """Per 200 Hz run: (t, [(message, upstream, t_s, values)]) of a synthetic manoeuvre."""
    rng = np.random.default_rng(seed)
    angle, w = np.array([0.02, -0.01, 0.5]), np.zeros(3)
    vel = np.zeros(3)
    out = []
    for k in range(1, runs + 1):
        t = 0.005 * k
        batch = []
        for ts in (t - 0.0025, t):
            flip = 2.0 <= ts < 2.6           # a fast roll: 11 rad/s, then back to level
            w = np.array([11.0 if flip else -angle[0] * 8.0, 0.0, 0.0]) + rng.normal(0.0, 0.05, 3)
            angle = angle + w * 0.0025
            r = quat_to_rotation(quat_from_euler(*angle))
            acc = r.T @ [0.3 * math.sin(ts), 0.1, X250.gravity_m_s2] + rng.normal(0.0, 0.01, 3)
            batch.append((schemas.IMU, "sim", ts, {"gyro_rad_s": (w + 2e-3).tolist(), "accel_m_s2": acc.tolist()}))
            if round(ts * 400) % 8 == 0:
                field = r.T @ FIELD + rng.normal(0.0, 0.5, 3)
                batch.append((schemas.MAG, "sim", ts, {"field_ut": field.tolist()}))
            thrust = (HOVER_N / 4 + rng.normal(0.0, 0.05, 4)).tolist()
            batch.append((schemas.MOTOR_PWM, "motors", ts, {"pwm_us": [1400.0] * 4, "thrust_n": thrust, "armed": True,
                                                            "saturated": False, "imu_t_s": ts - 0.0025}))
        if k % 2 == 0:
            vel = vel + rng.normal(0.0, 0.01, 3)
            batch.append((schemas.POSITION_STATE, "position", t, {
                "position_m": [0.0, 0.0, 1.0], "velocity_m_s": vel.tolist(), "position_ref_m": [0.0, 0.0, 1.0],
                "position_cov_m2": [1e-5, 0.0, 0.0, 0.0, 1e-5, 0.0, 0.0, 0.0, 1e-5],
                "acceleration_m_s2": rng.normal(0.0, 0.2, 3).tolist(), "thrust_scale": 1.0,
                "state_source": "estimate"}))
            if not 3.5 <= t < 3.9:           # the position level goes quiet: the failsafe descends
                batch.append((schemas.POSITION_SETPOINT, "position", t, {
                    "attitude_ref_rad": [0.03 * math.sin(t), -0.02, 0.5], "thrust_n": HOVER_N}))
        if k % 10 == 0 and t > 0.2:
            exp = t - 0.05
            q = quat_from_euler(*(angle + rng.normal(0.0, 0.002, 3) + [0.003, -0.002, 0.0]))
            batch.append((schemas.VISION_POSE, "vision", exp, {
                "position_m": [0.0, 0.0, 1.0], "quaternion_wxyz": q.tolist(), "position_cov_m2": [1e-6] * 9,
                "attitude_var_rad2": [1e-6] * 3, "reprojection_rms_px": 0.3, "markers": 5}))
        out.append((t, batch))
    return out


@pytest.mark.parametrize("params", [{}, {"acceleration_compensation": "slope"}, {"camera_level": False}])
def test_loop_sends_6b2add1s_messages_byte_for_byte(params):
    ios = [FakeIO("attitude", attitude.PARAMS, dict(params)), FakeIO("attitude", attitude_reference.PARAMS,
                                                                     dict(params))]
    loops = [attitude.AttitudeLoop(ios[0]), attitude_reference.AttitudeLoop(ios[1])]
    for t, batch in inputs(seed=4):
        for io, loop in zip(ios, loops):
            for message, upstream, ts, values in batch:
                io.inboxes.setdefault((message.name, upstream), io.inbox(message, upstream)).push(ts, values)
            loop.step(t)
    for message in (schemas.ATTITUDE_COMMAND, schemas.ATTITUDE_STATE):
        sent = [[message.encode(t, i, "attitude", v) for i, (t, v) in enumerate(io.sent(message))] for io in ios]
        assert len(sent[0]) > 900 and sent[0] == sent[1], message.name
    assert ios[0].rejected == ios[1].rejected and ios[0].problems == ios[1].problems
    assert ios[0].rejected.get("failsafe_engaged") == 1 and loops[0].carrier.activations == 1
    if loops[0].level is not None:
        assert loops[0].level.fused > 20
