"""The attitude level's float rewrites against their zenpilot 6b2add1 versions
(bench/support/attitude_filter_reference.py, bench/support/attitude_parts_reference.py): the
same numbers bit for bit, not to rounding (the lockstep flight log must not change)."""
import math

import numpy as np
import pytest

import bench.support.attitude_filter_reference as ref_filter
import flight.estimation.attitude_filter as new_filter
from bench.support import attitude_parts_reference as ref_parts
from flight.control.laws import attitude_law, attitude_law_floats
from flight.estimation.attitude_filter import FILTER_000, AttitudeFilter, AttitudeFilterParams
from flight.estimation.camera_level import CameraLevel, CameraLevelParams
from flight.estimation.gyro_carrier import GyroCarrier
from flight.quat import quat_from_euler, quat_from_euler_floats, quat_tilt
from tests.unit.flight.estimation.test_attitude_filter import INERTIA, _manoeuvring_calls

FIELDS = ("euler_rad", "rate_rad_s", "quaternion_wxyz", "euler_var", "rate_var")


@pytest.mark.parametrize("overrides, mag_first", [
    ({}, True), ({}, False), ({"model_filter_lag": False}, False), ({"euler_kinematics": False}, True),
    ({"extrapolate": False}, True), (FILTER_000, False),
    ({"angle_meas_var": (1e-3, 2e-3, 5e-3)}, True),          # roll and pitch differ: no shared gain
    ({"rate_process_var": (50.0, 40.0, 20.0)}, False)])
def test_filter_is_6b2add1s_bit_for_bit(overrides, mag_first, monkeypatch):
    """update() and update_floats() against the former filter on a manoeuvring flight (jittered
    IMU, a gap and re-initialisation, the magnetometer late or early, acceleration references,
    tilt measurements, extrapolation): every estimate, state and covariance equal."""
    if mag_first:   # move the a_model integral's origin at every sample, in both
        monkeypatch.setattr(new_filter, "_AMODEL_REBASE", 0.0)
        monkeypatch.setattr(ref_filter, "_AMODEL_REBASE", 0.0)
    params = AttitudeFilterParams.from_dict(overrides)
    new, twin = AttitudeFilter(INERTIA, params, gravity_m_s2=9.8), AttitudeFilter(INERTIA, params, gravity_m_s2=9.8)
    old = ref_filter.AttitudeFilter(INERTIA, ref_filter.AttitudeFilterParams.from_dict(overrides), gravity_m_s2=9.8)
    shared = 0
    for imu, mag, torque, t_now, accel_ref, reinit in _manoeuvring_calls(seed=7, mag_first=mag_first):
        if reinit is not None:
            for f in (new, twin, old):
                f.reinitialise(*reinit)
        e_new, e_old = new.update(imu, mag, torque, t_now, accel_ref=accel_ref), old.update(imu, mag, torque, t_now,
                                                                                              accel_ref=accel_ref)
        floats = twin.update_floats(imu, mag, torque, t_now, accel_ref=accel_ref)
        for i, name in enumerate(FIELDS):
            np.testing.assert_array_equal(getattr(e_new, name), getattr(e_old, name), err_msg=f"{name} at {t_now}")
            assert list(floats[i]) == getattr(e_old, name).tolist(), (name, t_now)
        assert e_new.delay_s == e_old.delay_s == floats[5]
        np.testing.assert_array_equal(new.x, old.x)
        np.testing.assert_array_equal(new.P, old.P)
        assert new._aid_c == old._aid_c
        shared += new._ps[1] is new._ps[0]
        sample_euler, sample_rate = new.sample_state()
        assert new.sample_state_floats() == (sample_euler.tolist(), sample_rate.tolist())
    roll_pitch_alike = all(v[0] == v[1] for v in (params.rate_meas_var, params.angle_meas_var,
                                                  params.rate_process_var, params.angle_process_var))
    assert (shared > 300) == (roll_pitch_alike and params.model_filter_lag)   # the shared gain was used


def test_kf_axis_is_predict_update_rewrap():
    """The fused step of one axis against the three functions it writes out, on random states."""
    rng = np.random.default_rng(3)
    disc = new_filter._Discretiser(0.02, (50.0, 50.0, 20.0), (3e-6, 3e-6, 1e-5), (1e-9, 1e-9, 1e-9))
    for k in range(2000):
        coef, qs = disc(int(rng.integers(1, 60)))
        x = tuple((rng.normal(0.0, 1.0, 5) * [1, 1, 4, 4, 0.01]).tolist())
        m = rng.normal(0.0, 0.1, (5, 5))
        p = m @ m.T + np.eye(5) * 1e-4
        tri = tuple(float(p[i, j]) for i, j in new_filter._TRI)
        z_rate, z_angle = float(rng.normal()), (None if k % 3 == 0 else float(rng.normal(0.0, 3.0)))
        want_x, want_p = new_filter._update(x, new_filter._predict_p(tri, coef, qs[0]), z_rate, z_angle, 1e-5, 1e-3,
                                            True)
        got_x, got_p, gain = new_filter._kf_axis(x, tri, coef, qs[0], z_rate, z_angle, 1e-5, 1e-3)
        assert got_x == new_filter._rewrap(want_x) and got_p == want_p
        assert new_filter._kf_state(x, gain, z_rate, z_angle) == got_x


def test_camera_level_is_6b2add1s_to_rounding():
    """record / fuse / apply against the numpy version, with frames of every rejection reason."""
    rng = np.random.default_rng(5)
    params = CameraLevelParams(gate_rad=0.02)
    new, old = CameraLevel(params), ref_parts.CameraLevel(params)
    for k in range(3000):
        t = 0.005 * k
        euler = [0.02 * math.sin(t) + 0.004, -0.01 + 0.6 * (k % 500 == 0), 0.3 * t]
        rate = [float(v) for v in rng.normal(0.0, 0.3 if k % 200 else 3.0, 3)]
        new.record(t, euler, rate)
        old.record(t, np.array(euler), np.array(rate))
        if k % 10 == 5:
            t_exp = t - rng.uniform(0.0, 0.6)
            q = quat_from_euler(euler[0] - 0.003 + rng.normal(0.0, 0.01), euler[1] + 0.002, euler[2])
            q = q * rng.uniform(0.8, 1.2) if k % 7 else (q * 0.1 if k % 14 else q * np.nan)
            assert new.fuse(t_exp, q.tolist()) == old.fuse(t_exp, q)
            assert new.rejected == old.rejected
        out = new.apply_floats(euler)
        assert out == new.apply(euler).tolist()
        # numpy's SIMD kernels round differently on some CPUs (AVX-512): the last bits may differ
        np.testing.assert_allclose(out, old.apply(np.array(euler)), rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(new.offset_rad, old.offset_rad, rtol=1e-13, atol=1e-15)
    assert new.fused > 50 and len(new.rejected) >= 4


def test_gyro_carrier_follow_euler_is_follow_of_the_quaternion():
    rng = np.random.default_rng(9)
    for k in range(300):
        euler = [float(v) for v in rng.normal(0.0, 1.0, 3)]
        gyro = [float(v) for v in rng.normal(0.0, 2.0, 3)]
        new, old = GyroCarrier(), ref_parts.GyroCarrier()
        new.follow_euler(0.1 * k, euler, gyro)
        old.follow(0.1 * k, quat_from_euler(*np.array(euler)), gyro)
        assert new.t == old.t
        np.testing.assert_array_equal(new.q, old.q)
        np.testing.assert_array_equal(new.gyro, old.gyro)
        q = quat_from_euler_floats(*euler)
        assert new.check_enter(q, gyro) == old.check_enter(np.array(q), np.array(gyro))
        for c in (new, old):
            c.propagate(0.1 * k + 0.0025, np.array(gyro) * 1.01)
        np.testing.assert_array_equal(new.q, old.q)
        np.testing.assert_array_equal(new.estimate(0.1 * k + 0.01, 0.025)[0], old.estimate(0.1 * k + 0.01, 0.025)[0])


def test_law_and_quaternion_helpers_are_6b2add1s():
    rng = np.random.default_rng(2)
    for k in range(3000):
        angles, rates, ref = (rng.normal(0.0, s, 3) for s in (0.5, 2.0, 0.5))
        gains, alpha = rng.uniform(1.0, 30.0, 3), rng.uniform(1.0, 30.0, 3)
        max_accel = None if k % 4 == 0 else rng.uniform(1.0, 80.0, 3)
        inertia = (7.5e-3, 7.6e-3, 14.2e-3)
        want = ref_parts.attitude_law(inertia, angles, rates, ref, gains, alpha, max_accel)
        np.testing.assert_array_equal(attitude_law(inertia, angles, rates, ref, gains, alpha, max_accel), want)
        got = attitude_law_floats(inertia, angles.tolist(), rates.tolist(), ref.tolist(), tuple(gains.tolist()),
                                  tuple(alpha.tolist()), None if max_accel is None else tuple(max_accel.tolist()))
        assert list(got) == want.tolist()
        e = angles.tolist()
        q = quat_from_euler_floats(*e)
        assert list(q) == ref_parts.quat_from_euler(*e).tolist() == quat_from_euler(*e).tolist()
        assert quat_tilt(q) == ref_parts.quat_tilt(np.array(q)) == quat_tilt(list(q))
