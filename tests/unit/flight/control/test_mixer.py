import numpy as np
import pytest

from flight.control.mixer import mix
from flight.motor_model import pwm_to_thrust, thrust_to_pwm
from flight.vehicle import load_vehicle


@pytest.fixture(params=["x250", "q820"])
def veh(request):
    return load_vehicle(request.param)


def test_unsaturated_is_exact_inverse(veh):
    u = np.array([4 * veh.hover_thrust_per_motor_n, 0.01, -0.02, 0.005])
    f, sat = mix(veh, u[0], u[1:])
    assert not sat
    np.testing.assert_allclose(veh.allocation @ f, u, atol=1e-12)


def test_forces_always_in_range(veh):
    rng = np.random.default_rng(3)
    for _ in range(500):
        f, _ = mix(veh, rng.uniform(-5, 30), rng.normal(0, 1.0, 3))
        assert np.all(f >= veh.min_thrust_n - 1e-12) and np.all(f <= veh.max_thrust_n + 1e-12)


def test_thrust_gives_way_before_torque():
    v = load_vehicle("x250")
    torque = np.array([0.05, -0.03, 0.002])
    f, sat = mix(v, 4 * v.max_thrust_n, torque)  # full throttle + torque cannot both fit
    assert sat
    u = v.allocation @ f
    np.testing.assert_allclose(u[1:], torque, atol=1e-12)   # all torque kept
    assert u[0] < 4 * v.max_thrust_n                         # thrust reduced
    f, sat = mix(v, 0.0, torque)                             # zero throttle: thrust raised
    assert sat
    np.testing.assert_allclose((v.allocation @ f)[1:], torque, atol=1e-12)


def test_yaw_gives_way_before_roll_pitch():
    v = load_vehicle("x250")
    l = v.motor_positions_m[0][0]
    roll = 0.8 * v.max_thrust_n * 2 * l   # needs 80% of the range
    f, sat = mix(v, 4 * v.hover_thrust_per_motor_n, [roll, 0.0, 0.05])  # yaw needs far more
    assert sat
    u = v.allocation @ f
    assert u[1] == pytest.approx(roll, abs=1e-12)
    assert 0.0 < u[3] < 0.05                   # yaw scaled down, not dropped
    assert np.ptp(f) == pytest.approx(v.max_thrust_n - v.min_thrust_n, abs=1e-9)


def test_roll_pitch_scaled_when_alone_too_big():
    v = load_vehicle("x250")
    torque = np.array([1.0, 0.5, 0.01])
    f, sat = mix(v, 2.0, torque)
    assert sat
    u = v.allocation @ f
    assert u[3] == pytest.approx(0.0, abs=1e-12)                    # yaw dropped
    assert u[1] / u[2] == pytest.approx(torque[0] / torque[1])      # direction kept
    assert u[1] < torque[0]


def test_pwm_round_trip_and_clipping(veh):
    f = np.linspace(veh.min_thrust_n, veh.max_thrust_n, 4)
    pwm = thrust_to_pwm(veh, f)
    assert pwm[0] == veh.pwm_min_us and pwm[-1] == veh.pwm_max_us
    np.testing.assert_allclose(pwm_to_thrust(veh, pwm), f, atol=1e-12)
    assert np.all(thrust_to_pwm(veh, [-1, 1e6, 0, 0])[:2] == [veh.pwm_min_us, veh.pwm_max_us])
    np.testing.assert_allclose(pwm_to_thrust(veh, [500, 2500, 1000, 2000]),
                               [veh.min_thrust_n, veh.max_thrust_n, 0, veh.max_thrust_n])
