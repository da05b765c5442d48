import dataclasses

import numpy as np
import pytest

from flight.quat import quat_from_euler
from flight.vehicle import load_vehicle
from simulator.plant import Plant


def test_free_fall_matches_g():
    v = dataclasses.replace(load_vehicle("x250"), drag_n_per_m_s=0.0)
    p = Plant(v, position_m=(0, 0, 100.0))
    dt, n = 0.0005, 2000
    for _ in range(n):
        p.step(dt, np.zeros(4), np.zeros(3))
    t = dt * n
    assert p.position_m[2] == pytest.approx(100.0 - 0.5 * 9.81 * t * t, abs=1e-9)
    assert p.velocity_m_s[2] == pytest.approx(-9.81 * t, abs=1e-9)


def test_free_fall_with_drag_matches_analytic():
    v = load_vehicle("x250")
    p = Plant(v, position_m=(0, 0, 100.0))
    for _ in range(2000):
        p.step(0.0005, np.zeros(4), np.zeros(3))
    c_m = v.drag_n_per_m_s / v.mass_kg
    assert p.velocity_m_s[2] == pytest.approx(-9.81 / c_m * (1 - np.exp(-c_m * 1.0)), rel=1e-9)


def test_rk4_conserves_rotational_energy_and_quaternion_norm():
    v = dataclasses.replace(load_vehicle("x250"), inertia_kg_m2=(5e-3, 7.5e-3, 14.2e-3))
    p = Plant(v, position_m=(0, 0, 1000.0), rate_rad_s=(3.0, 0.5, 1.0))
    inertia = np.array(v.inertia_kg_m2)

    def energy_and_momentum():
        w = p.rate_rad_s
        r = p.rotation
        return 0.5 * w @ (inertia * w), r @ (inertia * w)  # momentum in world frame

    e0, h0 = energy_and_momentum()
    for _ in range(4000):  # 2 s at 2 kHz
        p.step(0.0005, np.zeros(4), np.zeros(3))
    e1, h1 = energy_and_momentum()
    assert e1 == pytest.approx(e0, rel=1e-8)
    np.testing.assert_allclose(h1, h0, atol=1e-9)
    assert np.linalg.norm(p.quaternion) == pytest.approx(1.0, abs=1e-12)


def test_motor_first_order_lag():
    """The lag is on the rotor speed (flight/motor_model.py): after one time constant from
    rest the speed is (1 - 1/e) of the commanded sqrt(c / kf), the thrust that squared."""
    v = load_vehicle("x250")
    p = Plant(v, position_m=(0, 0, 10.0))
    for _ in range(40):  # 0.02 s = one time constant
        p.step(0.0005, np.full(4, 2.0), np.zeros(3))
    np.testing.assert_allclose(p.rotor_speed_rad_s, np.sqrt(2.0 / v.thrust_coefficient_kf) * (1 - np.exp(-1)),
                               rtol=1e-12)
    np.testing.assert_allclose(p.motor_thrust_n, 2.0 * (1 - np.exp(-1)) ** 2, rtol=1e-12)


def test_ground_rest_and_landing():
    v = load_vehicle("x250")
    p = Plant(v, position_m=(0, 0, 0.3))
    p.x[6:10] = quat_from_euler(0.3, -0.2, 1.0)  # tilted while falling
    zs = []
    for _ in range(1000):
        p.step(0.0005, np.zeros(4), np.zeros(3))
        zs.append(p.position_m[2])
    assert min(zs) >= 0.0 and p.landed
    np.testing.assert_allclose(p.velocity_m_s, 0.0)
    np.testing.assert_allclose(p.quaternion, quat_from_euler(0, 0, 1.0), atol=1e-12)
    # enough thrust lifts it off
    for _ in range(400):
        p.step(0.0005, np.full(4, 2.0), np.zeros(3))
    assert not p.landed and p.position_m[2] > 0.0
