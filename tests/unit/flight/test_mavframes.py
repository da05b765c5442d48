"""ENU/FLU <-> NED/FRD: round trips and rotations whose answer is known."""

import math

import numpy as np
import pytest

from flight import mavframes as mf
from flight.quat import quat_from_euler, quat_to_rotation


def test_world_vectors_swap_and_round_trip():
    assert np.allclose(mf.enu_to_ned([1.0, 2.0, 3.0]), [2.0, 1.0, -3.0])  # 1 m east, 2 north, 3 up
    assert np.allclose(mf.ned_to_enu([2.0, 1.0, -3.0]), [1.0, 2.0, 3.0])
    v = np.random.default_rng(0).normal(size=3)
    assert np.allclose(mf.ned_to_enu(mf.enu_to_ned(v)), v)


def test_body_vectors_flip_y_and_z():
    assert np.allclose(mf.flu_to_frd([0.1, 0.2, 0.3]), [0.1, -0.2, -0.3])
    v = np.random.default_rng(1).normal(size=3)
    assert np.allclose(mf.frd_to_flu(mf.flu_to_frd(v)), v)
    # at rest an accelerometer reads +g on FLU z, -g on FRD z (MAVLink's convention)
    assert mf.flu_to_frd([0, 0, 9.81])[2] == pytest.approx(-9.81)


@pytest.mark.parametrize("yaw_enu, yaw_ned", [(math.pi / 2, 0.0), (0.0, math.pi / 2),
                                              (math.pi, -math.pi / 2), (-math.pi / 2, math.pi)])
def test_heading(yaw_enu, yaw_ned):
    """Nose north is yaw 90 deg in ENU and 0 in NED; nose east 0 in ENU and 90 deg in NED."""
    q = mf.quat_enu_flu_to_ned_frd(quat_from_euler(0.0, 0.0, yaw_enu))
    _, _, yaw = mf.euler_from_quat_ned(q)
    assert math.cos(yaw - yaw_ned) == pytest.approx(1.0)
    assert math.cos(mf.yaw_enu_to_ned(yaw_enu) - yaw_ned) == pytest.approx(1.0)


def test_nose_up_pitch_sign():
    """Nose up is a negative pitch about FLU y (left) and a positive one about FRD y (right)."""
    q_enu = quat_from_euler(0.0, -0.3, 0.0)  # rotation about +y(left) by -0.3: the nose rises
    nose_world = quat_to_rotation(q_enu) @ [1.0, 0.0, 0.0]
    assert nose_world[2] > 0  # ENU z up: nose points up
    roll, pitch, yaw = mf.euler_from_quat_ned(mf.quat_enu_flu_to_ned_frd(q_enu))
    assert pitch == pytest.approx(0.3) and roll == pytest.approx(0.0, abs=1e-12)
    assert mf.euler_enu_to_ned((0.0, -0.3, 0.0))[1] == pytest.approx(0.3)


def test_roll_right_sign():
    """Right wing down is a positive roll in both frames (x forward is shared)."""
    q_enu = quat_from_euler(0.2, 0.0, 0.0)
    left_world = quat_to_rotation(q_enu) @ [0.0, 1.0, 0.0]
    assert left_world[2] > 0  # left wing up = right wing down
    roll, _, _ = mf.euler_from_quat_ned(mf.quat_enu_flu_to_ned_frd(q_enu))
    assert roll == pytest.approx(0.2)


def test_quaternion_round_trip_and_agrees_with_vectors():
    rng = np.random.default_rng(2)
    for _ in range(50):
        rpy = rng.uniform([-1.5, -1.4, -3.1], [1.5, 1.4, 3.1])
        q = quat_from_euler(*rpy)
        q_ned = mf.quat_enu_flu_to_ned_frd(q)
        back = mf.quat_ned_frd_to_enu_flu(q_ned)
        assert np.allclose(back, q if q[0] >= 0 else -q)
        v_flu = rng.normal(size=3)
        # rotating in one frame pair equals rotating in the other
        assert np.allclose(quat_to_rotation(q_ned) @ mf.flu_to_frd(v_flu),
                           mf.enu_to_ned(quat_to_rotation(q) @ v_flu))
        # Euler conversion agrees with the quaternion conversion
        e_ned = mf.euler_enu_to_ned(rpy)
        assert np.allclose(quat_to_rotation(mf.quat_ned_from_euler(*e_ned)), quat_to_rotation(q_ned))
        assert np.allclose(mf.euler_ned_to_enu(e_ned), [rpy[0], rpy[1], math.remainder(rpy[2], 2 * math.pi)])


def test_body_rates_follow_body_vectors():
    """A yaw rate to the left (FLU +z) is a negative yaw rate in FRD."""
    assert mf.flu_to_frd([0.0, 0.0, 0.5])[2] == pytest.approx(-0.5)


def test_geodetic_offsets():
    lat, lon, alt = mf.ned_to_geodetic([111.32, 0.0, -10.0], 47.0, 8.0, 400.0)
    assert lat == pytest.approx(47.001, abs=1e-5) and lon == pytest.approx(8.0) and alt == pytest.approx(410.0)
    _, lon2, _ = mf.ned_to_geodetic([0.0, 100.0, 0.0], 47.0, 8.0, 400.0)
    assert lon2 > 8.0
    ned = [12.5, -30.25, -7.0]
    back = mf.geodetic_to_ned(*mf.ned_to_geodetic(ned, 47.0, 8.0, 400.0), 47.0, 8.0, 400.0)
    assert back == pytest.approx(ned, abs=1e-9)


def test_actuator_controls_normalise_in_frd():
    from flight.control.mixer import mix
    from flight.vehicle import load_vehicle
    v = load_vehicle("x250")
    hover = mf.actuator_controls(v.allocation, v.max_thrust_n, [v.hover_thrust_per_motor_n] * 4)
    assert hover[:3] == pytest.approx([0.0, 0.0, 0.0], abs=1e-12)
    assert hover[3] == pytest.approx(v.hover_thrust_per_motor_n / v.max_thrust_n) and len(hover) == 8
    forces, _ = mix(v, 4 * v.hover_thrust_per_motor_n, [0.01, 0.01, 0.001])  # roll right, nose down, yaw left
    c = mf.actuator_controls(v.allocation, v.max_thrust_n, forces)
    assert c[0] > 0 and c[1] < 0 and c[2] < 0  # FRD: pitch and yaw change sign
    full = mf.actuator_controls(v.allocation, v.max_thrust_n, [v.max_thrust_n] * 4)
    assert full[3] == 1.0
