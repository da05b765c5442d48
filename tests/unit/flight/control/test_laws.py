import numpy as np
import pytest

from flight.control.laws import altitude_law, attitude_from_thrust_vector, attitude_law, position_law
from flight.quat import quat_from_euler, quat_to_rotation, wrap_angle

G = 9.81


def test_thrust_vector_attitude_is_parallel():
    rng = np.random.default_rng(4)
    for _ in range(300):
        h = rng.normal(0, 5, 3)
        h[2] = abs(h[2]) + 0.1
        yaw = rng.uniform(-np.pi, np.pi)
        roll, pitch = attitude_from_thrust_vector(h, yaw)
        e3 = quat_to_rotation(quat_from_euler(roll, pitch, yaw))[:, 2]
        np.testing.assert_allclose(e3, h / np.linalg.norm(h), atol=1e-12)


def test_position_law_direction_and_hover():
    m = 0.4
    k = a = np.full(3, 4.0)
    r, p, t = position_law(m, G, [0, 0, 1], [0, 0, 0], [0, 0, 1], k, a, yaw=0.3)
    assert (r, p) == pytest.approx((0, 0)) and t == pytest.approx(m * G)
    # target ahead (+x) with yaw 0: pitch forward (positive pitch tilts thrust to +x)
    r, p, t = position_law(m, G, [0, 0, 1], [0, 0, 0], [0.1, 0, 1], k, a, yaw=0.0)
    assert p > 0 and r == pytest.approx(0)
    # target to the left (+y): negative roll tilts thrust to +y
    r, p, t = position_law(m, G, [0, 0, 1], [0, 0, 0], [0, 0.1, 1], k, a, yaw=0.0)
    assert r < 0 and p == pytest.approx(0)
    # unclamped: R e3 parallel to H, thrust = m |H|
    pos, vel, ref, yaw = np.array([0.2, -0.1, 1.0]), np.array([0.1, 0.05, -0.2]), np.array([0.0, 0.0, 1.1]), 1.0
    h = -(a + k) * vel - a * k * (pos - ref) + [0, 0, G]
    r, p, t = position_law(m, G, pos, vel, ref, k, a, yaw, max_tilt_rad=1.5)
    e3 = quat_to_rotation(quat_from_euler(r, p, yaw))[:, 2]
    np.testing.assert_allclose(e3 * t / m, h, atol=1e-12)


def test_position_law_clamps_tilt_and_never_inverts():
    k = a = np.full(3, 4.0)
    r, p, t = position_law(0.4, G, [0, 0, 1], [0, 0, 0], [100, 50, 1], k, a, yaw=0.0, max_tilt_rad=0.6)
    e3 = quat_to_rotation(quat_from_euler(r, p, 0.0))[:, 2]
    assert np.arccos(e3[2]) == pytest.approx(0.6)
    r, p, t = position_law(0.4, G, [0, 0, 100], [0, 0, 0], [0, 0, 0], k, a, yaw=0.0)
    assert t == pytest.approx(0.4 * 0.1 * G) and (r, p) == pytest.approx((0, 0))


def test_attitude_law_and_yaw_wrap():
    inertia = np.array([7.5e-3, 7.5e-3, 14.2e-3])
    k = a = np.full(3, 16.0)
    tau = attitude_law(inertia, [0.1, 0, 0], [0, 0.5, 0], [0, 0, 0], k, a)
    np.testing.assert_allclose(tau, inertia * np.array([-256 * 0.1, -32 * 0.5, 0]))
    # yaw 3.1 to ref -3.1: the short way is +0.083 rad, so torque is positive
    tau = attitude_law(inertia, [0, 0, 3.1], [0, 0, 0], [0, 0, -3.1], k, a)
    assert tau[2] == pytest.approx(-inertia[2] * 256 * wrap_angle(6.2))
    assert tau[2] > 0


def test_altitude_law_tilted_keeps_vertical_thrust():
    t = altitude_law(0.4, G, 1.0, 0.0, 1.0, 4.0, 4.0, roll=0.2, pitch=-0.1)
    assert t * np.cos(0.2) * np.cos(-0.1) == pytest.approx(0.4 * G)
    assert altitude_law(0.4, G, 1.0, 0.0, 1.5, 4.0, 4.0, 0.0, 0.0) > 0.4 * G


def test_stopping_rate_is_linear_near_zero_and_stoppable_beyond():
    from flight.control.laws import stopping_rate
    gain, accel = 8.0, 10.9
    edge = accel / gain ** 2
    small = np.linspace(-edge, edge, 21)
    np.testing.assert_allclose(stopping_rate(small, gain, accel), gain * small)
    # continuous in value and slope at the edge
    h = 1e-6
    assert stopping_rate(edge + h, gain, accel) == pytest.approx(gain * (edge + h), rel=1e-5)
    slope = (stopping_rate(edge + h, gain, accel) - stopping_rate(edge, gain, accel)) / h
    assert slope == pytest.approx(gain, rel=1e-3)
    # beyond: decelerating at accel from that rate stops before the reference
    big = np.array([0.2, 0.5, 1.0, 3.0])
    rate = stopping_rate(big, gain, accel)
    assert np.all(rate < gain * big)
    assert np.all(rate ** 2 / (2 * accel) <= big)
    np.testing.assert_allclose(stopping_rate(-big, gain, accel), -rate)
    np.testing.assert_allclose(stopping_rate(big, gain, np.inf), gain * big)


def test_attitude_law_with_stopping_limit():
    inertia = np.array([7.5e-3, 7.5e-3, 14.2e-3])
    k = a = np.full(3, 16.0)
    accel = np.array([20.0, 20.0, 5.0])
    # inside the linear range (|e| < 20 / 64 rad): law (8) exactly
    angles, rates = [0.1, -0.2, 0.05], [0.3, -0.1, 0.2]
    np.testing.assert_allclose(attitude_law(inertia, angles, rates, [0, 0, 0], k, a, accel),
                               attitude_law(inertia, angles, rates, [0, 0, 0], k, a), rtol=1e-12)
    # a large roll error asks for less torque than the linear law, same sign
    linear = attitude_law(inertia, [0.8, 0, 0], [0, 0, 0], [0, 0, 0], k, a)
    limited = attitude_law(inertia, [0.8, 0, 0], [0, 0, 0], [0, 0, 0], k, a, accel)
    assert linear[0] < limited[0] < 0
    # ... and brakes a rate it could not stop in time
    assert attitude_law(inertia, [0.8, 0, 0], [-6.0, 0, 0], [0, 0, 0], k, a, accel)[0] > 0


def test_vehicle_max_angular_accel():
    from flight.vehicle import load_vehicle
    v = load_vehicle("q820")
    # plus frame: roll from the two motors on the y axis, arm 0.15 m (the flip baseline's 21.8 rad/s^2)
    assert v.max_angular_accel_rad_s2[0] == pytest.approx(21.756, rel=1e-3)
    assert np.all(v.max_angular_accel_rad_s2 > 0)


def test_attitude_law_is_the_vectorised_formula():
    """attitude_law works per axis in floats; it is the array formula of its docstring (with
    stopping_rate) to the last bit, for gains and limits given as numbers or per axis."""
    from flight.control.laws import stopping_rate
    rng = np.random.default_rng(7)
    inertia = np.array([7.5e-3, 7.5e-3, 14.2e-3])
    for n in range(500):
        angles, ref = rng.uniform(-3.5, 3.5, 3), rng.uniform(-3.5, 3.5, 3)
        rates = rng.normal(0.0, 3.0, 3)
        k, a = (rng.uniform(1.0, 20.0, 3), rng.uniform(1.0, 20.0, 3)) if n % 2 else (16.0, 8.0)
        max_accel = [None, np.array([20.0, 20.0, 5.0]), 10.0, np.inf][n % 4]
        err = angles - ref
        err[2] = wrap_angle(err[2])
        k_, a_ = np.broadcast_to(k, 3), np.broadcast_to(a, 3)
        if max_accel is None:
            expected = inertia * (-(a_ + k_) * rates - a_ * k_ * err)
        else:
            expected = inertia * (a_ + k_) * (-stopping_rate(err, a_ * k_ / (a_ + k_), max_accel) - rates)
        got = attitude_law(np.diag(inertia) if n % 3 == 0 else list(inertia), list(angles), rates, tuple(ref),
                           k, a, max_accel)
        assert isinstance(got, np.ndarray) and got.shape == (3,)
        np.testing.assert_array_equal(got, expected)


def test_hold_integral_removes_a_steady_wind_offset_and_does_not_wind_up():
    """A point mass under laws (10) and a steady horizontal push: alone they hold it off by
    a / (alpha k); with the hold integral the offset goes to zero; the integral's acceleration
    never exceeds its limit, and ki = 0 is laws (10) exactly."""
    from flight.control.laws import hold_integral_update
    k = alpha = np.array([4.0, 4.0, 4.0])
    wind = np.array([1.0, -0.5])   # m/s^2 of push

    def settle(ki: float, seconds: float = 20.0, dt: float = 0.01) -> np.ndarray:
        p, v, integral, bias = np.zeros(2), np.zeros(2), np.zeros(2), None
        for _ in range(int(seconds / dt)):
            if ki > 0:
                integral, bias = hold_integral_update(integral, p, dt, ki, 2.0)
            h = -(alpha[:2] + k[:2]) * v - alpha[:2] * k[:2] * p + (bias if bias is not None else 0.0)
            v = v + (h + wind) * dt
            p = p + v * dt
        return p
    assert np.allclose(settle(0.0), wind / 16.0, atol=1e-3)    # the offset laws (10) leave
    assert np.linalg.norm(settle(16.0)) < 1e-3
    integral, bias = hold_integral_update(np.zeros(2), np.array([100.0, 0.0]), 1.0, 16.0, 2.0)
    assert np.isclose(np.linalg.norm(bias), 2.0) and np.allclose(-16.0 * integral, bias)
    integral, bias = hold_integral_update(np.ones(2), np.ones(2), 0.01, 0.0, 2.0)
    assert not integral.any() and not bias.any()
    args = (0.4, 9.81, [0.1, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], k, alpha, 0.0)
    assert position_law(*args) == position_law(*args, accel_bias_xy=None)
    assert abs(position_law(*args)[1]) > 0.1   # 0.1 m off: it tilts back
    # a bias that cancels the offset's pull levels it: the bias enters H as an acceleration
    assert np.allclose(position_law(*args, accel_bias_xy=np.array([1.6, 0.0]))[:2], 0.0, atol=1e-12)


def test_disturbance_observer_converges_to_a_constant_wind_and_the_law_holds_without_offset():
    # a point mass under laws (10) with the observer's feed-forward, in a steady wind: the
    # observer's estimate is the wind's drag k w (to 1 %), the position offset it leaves is
    # under 1 mm where laws (10) alone hold a_wind / (alpha k) = 31 mm off
    from flight.control.laws import DisturbanceObserver, thrust_accel_xy
    mass, drag, g, dt = 0.4, 0.1, 9.81, 0.01
    k_drag = drag / mass
    wind = np.array([2.0, -1.0])

    def fly(observer):
        p, v = np.zeros(3), np.zeros(3)
        for _ in range(1500):   # 15 s
            bias = None if observer is None else -np.asarray(observer.d)
            r, pt, thrust = position_law(mass, g, p, v, [0, 0, 0], 4.0, 4.0, 0.0, accel_bias_xy=bias)
            a_xy = np.array(thrust_accel_xy(thrust, mass, r, pt, 0.0))
            if observer is not None:
                observer.update(v[:2], a_xy, dt)
            acc = np.r_[a_xy - k_drag * (v[:2] - wind), 0.0]
            v = v + dt * acc
            p = p + dt * v
        return p
    offset = fly(None)
    assert np.linalg.norm(offset[:2]) == pytest.approx(k_drag * np.linalg.norm(wind) / 16, rel=0.05)
    obs = DisturbanceObserver(3.0, 3.0, k_drag)
    held = fly(obs)
    np.testing.assert_allclose(obs.d, k_drag * wind, rtol=0.01)
    assert np.linalg.norm(held[:2]) < 1e-3


def test_disturbance_observer_clamps_and_resumes_where_it_held():
    from flight.control.laws import DisturbanceObserver
    obs = DisturbanceObserver(2.0, 1.0, 0.0)
    for _ in range(2000):   # a 5 m/s^2 pull: the estimate stops at the limit, no wind-up past it
        obs.update([0.0, 0.0], [-5.0, 0.0], 0.01)
    assert obs.d == pytest.approx((1.0, 0.0))
    obs.hold()
    assert obs.update([3.0, 1.0], [-1.0, 0.0], 0.01) == pytest.approx((1.0, 0.0))   # restarted where it was
    obs.reset()
    assert obs.d == (0.0, 0.0)
