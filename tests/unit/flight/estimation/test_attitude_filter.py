"""Attitude level of document 000 (flight/estimation/attitude_filter.py).

A synthetic vehicle: per axis the double integrator I w' = u of 000 (roll,
pitch, yaw independent, body rate = Euler rate), integrated exactly between
samples; the torque is piecewise constant over the 200 Hz control period
(optionally through a first-order actuator lag).  IMU at 400 Hz:
gyro = w + noise (variance 1e-5 per sample, the simulator's), accel =
R^T [0, 0, g] + noise (1e-4 m^2/s^4); magnetometer at 50 Hz: R^T (0, 20, -45)
uT + 0.5 uT noise.  The filter is called at 200 Hz with the samples that are
`delay_s` old or older, the torque applied since the last call, and t_now.
"""
import math
from collections import deque

import numpy as np
import pytest

from flight.control.laws import attitude_law
from flight.estimation.attitude_filter import (
    AF,
    FILTER_000,
    G_REF,
    NX,
    WF,
    A,
    AttitudeEstimate,
    AttitudeFilter,
    AttitudeFilterParams,
    B,
    W,
    accel_roll_pitch,
    continuous_model,
    discrete_model,
    mag_yaw,
    rotation_zyx,
)
from flight.quat import quat_from_euler, quat_to_rotation, wrap_angle

INERTIA = np.array([7.5e-3, 7.5e-3, 14.2e-3])   # the x250 of 000
G = 9.81
FIELD = np.array([0.0, 20.0, -45.0])
DT = 1.0 / 200.0
IMU_DT = 1.0 / 400.0
GAIN = 16.0


def simulate(filters, *, t_end, angles0=(0.0, 0.0, 0.0), ref=None, step_t=0.2, control="estimate",
             delay_s=0.0, seed=0, actuator_tau_s=0.0, gyro_var=1e-5, accel_var=1e-4, mag_std=0.5,
             gyro_bias=(0.0, 0.0, 0.0)):
    """Run the synthetic closed loop; law (8) on filters[0]'s estimate (or on the truth).

    ref: (3,) reference applied from step_t on (before it: angles0).
    Returns dict of arrays: t (control times), truth (n, 3), rates (n, 3), est[j] (n, 3), rate_est[j],
    and the last AttitudeEstimate of each filter.
    """
    rng = np.random.default_rng(seed)
    angle = np.array(angles0, dtype=float)
    w = np.zeros(3)
    torque_cmd = np.zeros(3)
    torque_act = np.zeros(3)
    pending = []          # IMU samples not yet given to the filters
    mag_pending = None
    n_ctrl = int(round(t_end / DT))
    out = {"t": [], "truth": [], "rates": [], "est": [[] for _ in filters], "rate_est": [[] for _ in filters],
           "last": [None] * len(filters)}
    sub = 5
    h = IMU_DT / sub
    k_imu = 0

    def sample(tt):
        r = quat_to_rotation(quat_from_euler(*angle))
        gyro = w + np.asarray(gyro_bias) + rng.normal(0.0, math.sqrt(gyro_var), 3)
        acc = r.T @ np.array([0.0, 0.0, G]) + rng.normal(0.0, math.sqrt(accel_var), 3)
        pending.append((tt, gyro, acc))
        if k_imu % 8 == 0:
            return (tt, r.T @ FIELD + rng.normal(0.0, mag_std, 3))
        return None

    mag_pending = sample(0.0)
    prev_torque = np.zeros(3)
    for c in range(n_ctrl + 1):
        t_now = c * DT
        ready = [s for s in pending if s[0] <= t_now - delay_s + 1e-9]
        pending[:] = [s for s in pending if s[0] > t_now - delay_s + 1e-9]
        mag = mag_pending if (mag_pending is not None and mag_pending[0] <= t_now - delay_s + 1e-9) else None
        if mag is not None:
            mag_pending = None
        ests = [f.update(list(ready), mag, prev_torque, t_now) for f in filters]
        r = np.asarray(ref if (ref is not None and t_now >= step_t) else angles0, dtype=float)
        if control == "none":
            torque_cmd = np.zeros(3)
        elif control == "truth":
            torque_cmd = attitude_law(INERTIA, angle, w, r, GAIN, GAIN)
        else:
            torque_cmd = attitude_law(INERTIA, ests[0].euler_rad, ests[0].rate_rad_s, r, GAIN, GAIN)
        out["t"].append(t_now)
        out["truth"].append(angle.copy())
        out["rates"].append(w.copy())
        for j, e in enumerate(ests):
            out["est"][j].append(e.euler_rad.copy())
            out["rate_est"][j].append(e.rate_rad_s.copy())
            out["last"][j] = e
        prev_torque = torque_cmd.copy()
        # plant over [t_now, t_now + DT): two IMU periods
        for _ in range(2):
            for _ in range(sub):
                if actuator_tau_s > 0:
                    torque_act = torque_act + (1.0 - math.exp(-h / actuator_tau_s)) * (torque_cmd - torque_act)
                else:
                    torque_act = torque_cmd
                u = torque_act / INERTIA
                angle = angle + w * h + 0.5 * u * h * h
                w = w + u * h
            k_imu += 1
            m = sample(round(k_imu * IMU_DT, 9))
            if m is not None:
                mag_pending = m
    for key in ("t", "truth", "rates"):
        out[key] = np.asarray(out[key])
    out["est"] = [np.asarray(e) for e in out["est"]]
    out["rate_est"] = [np.asarray(e) for e in out["rate_est"]]
    return out


def step_metrics(t, y, y0, y1, t_step):
    """Overshoot (fraction), 5 % settling time after t_step, and the largest reversal (fraction)."""
    sel = t >= t_step
    tt, yy = t[sel] - t_step, (y[sel] - y0) / (y1 - y0)
    overshoot = max(0.0, float(yy.max()) - 1.0)
    outside = np.nonzero(np.abs(yy - 1.0) > 0.05)[0]
    settle = float(tt[outside[-1] + 1]) if len(outside) else 0.0
    # monotone-ish: largest drop below the running maximum before reaching the target
    run_max = np.maximum.accumulate(yy)
    reversal = float(np.max(run_max - yy))
    return overshoot, settle, reversal


def rms_deg(a, b):
    return float(np.degrees(np.sqrt(np.mean(wrap_angle(np.asarray(a) - np.asarray(b)) ** 2))))


# ------------------------------------------------------------------ helpers and params
def test_accel_and_mag_helpers_match_the_frame_convention():
    for roll, pitch, yaw in [(0.1, -0.2, 0.5), (-0.4, 0.3, -2.5), (0.0, 0.0, 3.0), (0.6, 0.5, -3.1)]:
        r = quat_to_rotation(quat_from_euler(roll, pitch, yaw))
        rr, pp = accel_roll_pitch(r.T @ np.array([0.0, 0.0, G]))
        assert rr == pytest.approx(roll, abs=1e-12) and pp == pytest.approx(pitch, abs=1e-12)
        assert float(wrap_angle(mag_yaw(r.T @ FIELD, roll, pitch) - yaw)) == pytest.approx(0.0, abs=1e-12)
    # the brief's signs: nose-down pitch about +y reads ax = -g sin(theta); roll reads ay = g sin(phi)
    assert accel_roll_pitch([-G * math.sin(0.2), 0.0, G * math.cos(0.2)])[1] == pytest.approx(0.2)
    assert accel_roll_pitch([0.0, G * math.sin(0.3), G * math.cos(0.3)])[0] == pytest.approx(0.3)


def test_params_from_dict():
    p = AttitudeFilterParams.from_dict({"lpf_tau_s": 0.03, "angle_meas_var": [1e-3, 1e-3, 2e-3],
                                        "extrapolate": False})
    assert p.lpf_tau_s == 0.03 and p.angle_meas_var == (1e-3, 1e-3, 2e-3) and p.extrapolate is False
    assert AttitudeFilterParams.from_dict({}) == AttitudeFilterParams()
    assert AttitudeFilterParams.from_dict(p.to_dict()) == p
    with pytest.raises(ValueError, match="unknown"):
        AttitudeFilterParams.from_dict({"lpf_tau": 0.02})
    with pytest.raises(ValueError):
        AttitudeFilterParams.from_dict({"lpf_tau_s": -1.0})
    with pytest.raises(ValueError):
        AttitudeFilterParams.from_dict({"rate_meas_var": [1e-5, 1e-5]})
    with pytest.raises(ValueError):
        AttitudeFilterParams.from_dict({"model_filter_lag": 1})


# ------------------------------------------------------------------ (1) at rest, tilted
def test_converges_at_rest_tilted():
    angles = np.radians([5.0, -8.0, 30.0])
    f = AttitudeFilter(INERTIA)
    out = simulate([f], t_end=2.0, angles0=angles, control="none", seed=1)
    err = np.degrees(np.abs(wrap_angle(out["est"][0] - out["truth"])))
    late = out["t"] >= 1.0
    print("at rest: max |error| over the last second (deg):", err[late].max(axis=0))
    assert np.all(err[late] < 0.5)
    last = out["last"][0]
    assert isinstance(last, AttitudeEstimate)
    assert np.degrees(np.abs(wrap_angle(last.euler_rad - angles))).max() < 0.5
    assert np.allclose(last.quaternion_wxyz, quat_from_euler(*last.euler_rad))
    assert np.all(last.euler_var > 0) and np.all(last.rate_var > 0)
    assert np.abs(last.rate_rad_s).max() < 0.01


# ------------------------------------------------------------------ (2) closed loop on the estimate
@pytest.mark.parametrize("seed, actuator_tau_s", [(0, 0.0), (1, 0.0), (2, 0.02)])
def test_closed_loop_roll_step_on_estimate(seed, actuator_tau_s):
    """Law (8), k = alpha = 16, on the estimate; the last case adds a 20 ms actuator lag
    (the simulator's motor time constant) that the filter's model does not know."""
    f = AttitudeFilter(INERTIA)
    target = math.radians(10.0)
    out = simulate([f], t_end=1.2, ref=(target, 0.0, 0.0), step_t=0.2, seed=seed, actuator_tau_s=actuator_tau_s)
    overshoot, settle, reversal = step_metrics(out["t"], out["truth"][:, 0], 0.0, target, 0.2)
    # the same loop on the truth, for reference
    ref_out = simulate([AttitudeFilter(INERTIA)], t_end=1.2, ref=(target, 0.0, 0.0), step_t=0.2,
                       control="truth", seed=seed, actuator_tau_s=actuator_tau_s)
    o_t, s_t, _ = step_metrics(ref_out["t"], ref_out["truth"][:, 0], 0.0, target, 0.2)
    print(f"roll step on estimate (actuator lag {actuator_tau_s * 1e3:.0f} ms): overshoot {overshoot:.3%}, settle {settle:.3f} s, reversal {reversal:.3%}"
          f" (on truth: overshoot {o_t:.3%}, settle {s_t:.3f} s)")
    assert overshoot <= 0.05
    assert settle <= 0.35
    assert reversal <= 0.05
    # the other axes stay put
    assert np.degrees(np.abs(out["truth"][:, 1:])).max() < 0.5


# ------------------------------------------------------------------ (3) transport delay, extrapolator
def test_extrapolator_compensates_transport_delay():
    target = math.radians(10.0)
    fx = AttitudeFilter(INERTIA, AttitudeFilterParams(extrapolate=True))
    fn = AttitudeFilter(INERTIA, AttitudeFilterParams(extrapolate=False))
    out = simulate([fx, fn], t_end=1.0, ref=(target, 0.0, 0.0), step_t=0.2, control="truth",
                   delay_s=0.010, seed=3)
    sel = (out["t"] >= 0.2) & (out["t"] <= 0.7)
    e_x = rms_deg(out["est"][0][sel, 0], out["truth"][sel, 0])
    e_n = rms_deg(out["est"][1][sel, 0], out["truth"][sel, 0])
    r_x = float(np.degrees(np.sqrt(np.mean((out["rate_est"][0][sel, 0] - out["rates"][sel, 0]) ** 2))))
    r_n = float(np.degrees(np.sqrt(np.mean((out["rate_est"][1][sel, 0] - out["rates"][sel, 0]) ** 2))))
    print(f"10 ms delay: roll RMS error {e_x:.4f} deg with the extrapolator, {e_n:.4f} deg without;"
          f" rate RMS {r_x:.3f} vs {r_n:.3f} deg/s; delay_s {out['last'][0].delay_s:.4f}")
    assert out["last"][0].delay_s == pytest.approx(0.010, abs=1e-6)
    assert e_x < 0.5 * e_n
    assert r_x < 0.5 * r_n


# ------------------------------------------------------------------ (4) filter lag in the model
def lag_s(t, est, truth, max_lag=0.05, res=1e-4):
    """Shift (s) of est behind truth that minimises the RMS difference (linear interpolation)."""
    best = (float("inf"), 0.0)
    for lag in np.arange(-0.01, max_lag, res):
        shifted = np.interp(t - lag, t, truth)
        e = float(np.mean((est - shifted) ** 2))
        best = min(best, (e, lag))
    return best[1]


def test_filter_lag_in_model_removes_the_lowpass_lag():
    target = math.radians(10.0)
    tau = AttitudeFilterParams().lpf_tau_s
    f_lag = AttitudeFilter(INERTIA, AttitudeFilterParams(model_filter_lag=True))
    f_cas = AttitudeFilter(INERTIA, AttitudeFilterParams(model_filter_lag=False))
    out = simulate([f_lag, f_cas], t_end=1.0, ref=(target, 0.0, 0.0), step_t=0.2, control="truth", seed=4)
    sel = (out["t"] >= 0.2) & (out["t"] <= 0.7)
    t = out["t"][sel]
    lag_model = lag_s(t, out["est"][0][sel, 0], out["truth"][sel, 0])
    lag_casc = lag_s(t, out["est"][1][sel, 0], out["truth"][sel, 0])
    rlag_model = lag_s(t, out["rate_est"][0][sel, 0], out["rates"][sel, 0])
    rlag_casc = lag_s(t, out["rate_est"][1][sel, 0], out["rates"][sel, 0])
    e_model = rms_deg(out["est"][0][sel, 0], out["truth"][sel, 0])
    e_casc = rms_deg(out["est"][1][sel, 0], out["truth"][sel, 0])
    print(f"lag of the roll estimate: {lag_model * 1e3:.1f} ms with the filter lag in the model, "
          f"{lag_casc * 1e3:.1f} ms without (tau {tau * 1e3:.0f} ms); rate lag {rlag_model * 1e3:.1f} vs "
          f"{rlag_casc * 1e3:.1f} ms; RMS {e_model:.4f} vs {e_casc:.4f} deg")
    assert abs(lag_model) < 0.25 * tau
    assert lag_casc > 0.5 * tau
    assert lag_model < lag_casc
    assert abs(rlag_model) < rlag_casc
    assert e_model < e_casc


# ------------------------------------------------------------------ (5) yaw from the magnetometer
@pytest.mark.parametrize("yaw_deg", [-179.0, -120.0, -45.0, 0.0, 60.0, 135.0, 179.5])
def test_yaw_from_magnetometer(yaw_deg):
    angles = np.array([math.radians(4.0), math.radians(-6.0), math.radians(yaw_deg)])
    f = AttitudeFilter(INERTIA)
    out = simulate([f], t_end=1.5, angles0=angles, control="none", seed=5)
    err = np.degrees(np.abs(wrap_angle(out["est"][0][:, 2] - out["truth"][:, 2])))
    late = out["t"] >= 0.5
    print(f"yaw {yaw_deg}: max |error| after 0.5 s {err[late].max():.3f} deg")
    assert err[late].max() < 1.0
    assert -math.pi <= out["est"][0][:, 2].min() and out["est"][0][:, 2].max() < math.pi


def test_yaw_tracks_a_turn_through_180():
    """A yaw step across +-180 deg: the estimate follows the short way and stays wrapped."""
    f = AttitudeFilter(INERTIA)
    out = simulate([f], t_end=1.5, angles0=(0.0, 0.0, math.radians(170.0)),
                   ref=(0.0, 0.0, math.radians(-170.0)), step_t=0.2, seed=6)
    err = np.degrees(np.abs(wrap_angle(out["est"][0][:, 2] - out["truth"][:, 2])))
    print(f"yaw turn 170 -> -170 deg: max |error| {err[out['t'] >= 0.2].max():.3f} deg from t = 0.2 s")
    assert err[out["t"] >= 0.2].max() < 1.0
    assert abs(float(wrap_angle(out["truth"][-1, 2] - math.radians(-170.0)))) < math.radians(0.5)


# ------------------------------------------------------------------ (6) no NaN, predict only
def test_no_nan_without_imu_samples():
    f = AttitudeFilter(INERTIA)
    e = f.update([], None, np.zeros(3), 0.0)
    assert not f.initialized
    assert np.all(np.isfinite(e.euler_rad)) and np.all(np.isfinite(e.quaternion_wxyz))
    assert np.all(np.isfinite(e.euler_var)) and np.all(np.isfinite(e.rate_var))
    # initialise from accel/mag, then calls with no IMU samples: predict (extrapolate) only
    r = quat_to_rotation(quat_from_euler(0.1, -0.05, 1.0))
    f.update([(0.0, np.zeros(3), r.T @ [0, 0, G])], (0.0, r.T @ FIELD), np.zeros(3), 0.005)
    assert f.initialized and f.last_sample_t == 0.0
    torque = np.array([1e-3, -1e-3, 0.0])
    for k in range(2, 200):
        e = f.update([], None, torque, k * DT)
        for v in (e.euler_rad, e.rate_rad_s, e.quaternion_wxyz, e.euler_var, e.rate_var):
            assert np.all(np.isfinite(v))
        assert np.all(e.euler_rad >= -math.pi) and np.all(e.euler_rad < math.pi)
    assert e.delay_s == pytest.approx(199 * DT)
    # extrapolation is capped at max_delay_steps: the variances stay bounded
    assert np.all(e.euler_var < 1.0)
    assert np.all(e.euler_var == f.update([], None, torque, 10.0).euler_var)
    # garbage in: non-finite samples are dropped, never propagated
    e = f.update([(1.0, np.array([np.nan, 0, 0]), np.array([0, 0, G]))], (1.0, [np.inf, 0, 0]),
                 np.array([np.nan, 0, 0]), 1.0)
    assert np.all(np.isfinite(e.euler_rad)) and np.all(np.isfinite(e.rate_rad_s))
    # after a long IMU gap the filter re-initialises from the next sample
    e = f.update([(5.0, np.zeros(3), r.T @ [0, 0, G])], None, np.zeros(3), 5.0)
    assert np.degrees(np.abs(wrap_angle(e.euler_rad[:2] - [0.1, -0.05]))).max() < 0.01


def test_reset_and_free_fall():
    f = AttitudeFilter(INERTIA)
    f.update([(0.0, np.zeros(3), np.array([0.0, 0.0, G]))], None, np.zeros(3), 0.0)
    assert f.initialized
    f.reset()
    assert not f.initialized and f.last_sample_t is None
    # free fall (no specific force): rates still estimated, angles carried by the gyro
    f.update([(0.0, np.zeros(3), np.array([0.0, 0.0, G]))], None, np.zeros(3), 0.0)
    t = 0.0
    for k in range(1, 81):
        samples = [(t + IMU_DT, np.array([0.5, 0.0, 0.0]), np.zeros(3)),
                   (t + 2 * IMU_DT, np.array([0.5, 0.0, 0.0]), np.zeros(3))]
        t += DT
        e = f.update(samples, None, np.zeros(3), t)
    assert np.all(np.isfinite(e.euler_rad))
    assert e.rate_rad_s[0] == pytest.approx(0.5, abs=0.02)
    assert e.euler_rad[0] == pytest.approx(0.5 * t, abs=0.03)


def test_reinitialise_restarts_the_filter_at_a_given_attitude():
    filt = AttitudeFilter(INERTIA)
    filt.update([(0.0, np.zeros(3), np.array([0.0, 0.0, 9.81]))], None, np.zeros(3), 0.0)
    filt.reinitialise([0.3, -0.2, 1.0], [0.5, 0.0, -0.1])
    euler, rate = filt.sample_state()
    assert euler == pytest.approx([0.3, -0.2, 1.0]) and rate == pytest.approx([0.5, 0.0, -0.1])


# ------------------------------------------------------------------ gyro bias state
def test_bias_state_converges_to_a_constant_gyro_bias():
    """A constant gyro bias (the simulator draws one, sigma ~0.18 deg/s per axis): the bias
    state [w, wf, a, af, b] learns it from the accelerometer/magnetometer angles, and the angles
    lose the offset b * (their correction time) that the 000 filter without it keeps."""
    bias = np.array([3e-3, -4e-3, 2.5e-3])   # rad/s, ~0.2 deg/s
    angles = np.radians([5.0, -8.0, 30.0])
    with_b, without_b = AttitudeFilter(INERTIA, AttitudeFilterParams()), AttitudeFilter(
        INERTIA, AttitudeFilterParams(init_bias_var=0.0, bias_process_var=1e-30))
    out = simulate([with_b, without_b], t_end=20.0, angles0=angles, control="none", seed=3, gyro_bias=bias)
    late = out["t"] >= 15.0
    err_b = np.degrees(np.abs(wrap_angle(out["est"][0] - out["truth"])))[late]
    err_0 = np.degrees(np.abs(wrap_angle(out["est"][1] - out["truth"])))[late]
    print("gyro bias: estimated", with_b.gyro_bias, "true", bias,
          "| late mean |angle error| (deg) with", err_b.mean(axis=0), "without", err_0.mean(axis=0))
    assert with_b.gyro_bias == pytest.approx(bias, abs=1e-3)
    assert np.abs(without_b.gyro_bias).max() < 1e-12
    assert np.all(err_b.mean(axis=0) < 0.5 * err_0.mean(axis=0))
    # the published rate is the body rate (here 0), the bias removed
    assert np.abs(out["rate_est"][0][late].mean(axis=0)).max() < 1e-3
    assert np.abs(out["rate_est"][1][late].mean(axis=0) - bias).max() < 1e-3
    # the bias is the sensor's: a re-initialisation keeps it
    kept = with_b.gyro_bias.copy()
    with_b.reinitialise([0.0, 0.0, 0.0], bias)
    assert with_b.gyro_bias == pytest.approx(kept)
    assert with_b.sample_state()[1] == pytest.approx(bias - kept, abs=1e-12)


# ------------------------------------------------------------------ Euler kinematics
def test_euler_rate_excess_matches_the_quaternion_kinematics():
    from flight.estimation.attitude_filter import euler_rate_excess
    from flight.quat import quat_integrate, quat_to_euler
    rng = np.random.default_rng(0)
    for _ in range(20):
        e0 = rng.uniform([-0.8, -0.8, -3.0], [0.8, 0.8, 3.0])
        w = rng.normal(0.0, 1.0, 3)
        h = 1e-6
        q = quat_integrate(quat_from_euler(*e0), w, h)
        euler_rate = wrap_angle(np.array(quat_to_euler(q)) - e0) / h
        assert w + euler_rate_excess(e0[0], e0[1], w) == pytest.approx(euler_rate, abs=1e-4)
    assert euler_rate_excess(0.0, 0.0, [1.0, -2.0, 3.0]) == pytest.approx(np.zeros(3))


def _banked_turn_samples(roll, yaw_rate, t_end, seed=0):
    """IMU and magnetometer of a vehicle held at `roll` (pitch 0) turning at `yaw_rate`, level flight."""
    rng = np.random.default_rng(seed)
    gyro_body = np.array([0.0, math.sin(roll) * yaw_rate, math.cos(roll) * yaw_rate])
    calls = []
    for c in range(int(round(t_end / DT)) + 1):
        t_now = c * DT
        imu, mag = [], None
        for k in (1, 0):
            t = round(t_now - k * IMU_DT, 9)
            if t < 0:
                continue
            r = quat_to_rotation(quat_from_euler(roll, 0.0, yaw_rate * t))
            imu.append((t, gyro_body + rng.normal(0.0, math.sqrt(1e-5), 3),
                        r.T @ np.array([0.0, 0.0, G]) + rng.normal(0.0, 1e-2, 3)))
            if round(t / IMU_DT) % 8 == 0:
                mag = (t, r.T @ FIELD + rng.normal(0.0, 0.5, 3))
        calls.append((t_now, imu, mag))
    return calls


def test_euler_kinematics_keep_a_banked_turn():
    """Held at 20 deg of roll while turning at 1 rad/s, the body pitch rate is sin(20 deg) rad/s
    although the pitch stays 0: the 000 filter (body rate as Euler rate) integrates it and
    the accelerometer must pull the pitch back all the time (degrees of error); with the ZYX
    kinematics the angles stay on the truth."""
    roll, yaw_rate = math.radians(20.0), 1.0
    calls = _banked_turn_samples(roll, yaw_rate, 3.0)
    errs = {}
    for kin in (True, False):
        f = AttitudeFilter(INERTIA, AttitudeFilterParams(euler_kinematics=kin))
        worst = np.zeros(3)
        for t_now, imu, mag in calls:
            e = f.update(imu, mag, np.zeros(3), t_now)
            if t_now >= 1.0:
                truth = np.array([roll, 0.0, yaw_rate * t_now])
                worst = np.maximum(worst, np.degrees(np.abs(wrap_angle(e.euler_rad - truth))))
        errs[kin] = worst
    print("banked turn: max |error| (deg) with kinematics", errs[True], "000 as printed", errs[False])
    assert np.all(errs[True][:2] < 0.5)
    assert errs[False][:2].max() > 3.0


# ------------------------------------------------------------------ acceleration reference
def _accelerating_calls(roll, t_end, seed=0, t_tilt=1.0, ramp_s=0.2):
    """Level at rest, then from t_tilt rolled to `roll` over ramp_s and held, the thrust tilted
    so that the altitude is kept: the vehicle accelerates at g tan(roll(t)) sideways and the
    accelerometer reads g / cos(roll) along body z only ('level!').  Returns the calls and the
    mean world acceleration over a window, as the position level's velocity slope gives it."""
    rng = np.random.default_rng(seed)
    rate = roll / ramp_s

    def phi(t):
        return roll * min(max((t - t_tilt) / ramp_s, 0.0), 1.0)

    def mean_accel(t0, t1):
        tt = np.linspace(t0, t1, 201)
        return np.array([0.0, -G * float(np.mean([math.tan(phi(t)) for t in tt])), 0.0])

    calls = []
    for c in range(int(round(t_end / DT)) + 1):
        t_now = c * DT
        imu = []
        for k in (1, 0):
            t = round(t_now - k * IMU_DT, 9)
            if t < 0:
                continue
            p_rate = rate if t_tilt < t <= t_tilt + ramp_s else 0.0
            imu.append((t, np.array([p_rate, 0.0, 0.0]) + rng.normal(0.0, math.sqrt(1e-5), 3),
                        np.array([0.0, 0.0, G / math.cos(phi(t))]) + rng.normal(0.0, 1e-2, 3)))
        r = quat_to_rotation(quat_from_euler(phi(t_now), 0.0, 0.0))
        mag = (t_now, r.T @ FIELD) if c % 4 == 0 else None
        calls.append((t_now, imu, mag))
    return calls, mean_accel


def test_acceleration_reference_gives_the_tilt_of_an_accelerating_vehicle():
    """The accelerometer of a multirotor reads 'level' while it tilts to accelerate; a mean
    acceleration over a past window (the position level's velocity slope, 10 ms old) gives
    the tilt back: the window's mean of R f + g at the filter's own attitude is compared with it."""
    roll = math.radians(10.0)
    calls, mean_accel = _accelerating_calls(roll, 4.0)
    plain, aided = AttitudeFilter(INERTIA, gravity_m_s2=G), AttitudeFilter(INERTIA, gravity_m_s2=G)
    worst = 0.0
    for t_now, imu, mag in calls:
        e0 = plain.update(imu, mag, np.zeros(3), t_now)
        ref = (t_now - 0.11, t_now - 0.01, mean_accel(t_now - 0.11, t_now - 0.01)) if t_now > 0.2 else None
        e1 = aided.update(imu, mag, np.zeros(3), t_now, accel_ref=ref)
        if t_now > 1.2:
            worst = max(worst, abs(e1.euler_rad[0] - roll))
    print("accelerating at 10 deg: roll without reference", math.degrees(e0.euler_rad[0]),
          "with", math.degrees(e1.euler_rad[0]), "worst error after the tilt", math.degrees(worst))
    assert abs(e0.euler_rad[0]) < math.radians(2.0)          # 000 as printed: pulled to level
    assert worst < math.radians(0.3)
    assert abs(e1.euler_rad[1]) < math.radians(0.2)


def test_acceleration_reference_is_bounded_and_expires():
    calls, _ = _accelerating_calls(0.0, 2.0)   # at rest, level
    p = AttitudeFilterParams()
    f = AttitudeFilter(INERTIA, p, gravity_m_s2=G)
    for t_now, imu, mag in calls[:200]:
        f.update(imu, mag, np.zeros(3), t_now, accel_ref=(t_now - 0.11, t_now - 0.01, np.zeros(3)))
    assert np.degrees(np.abs(f.sample_state()[0][:2])).max() < 0.2
    # a wild reference (100 m/s^2 sideways) pulls at most as hard as aid_max_correction_m_s2 does
    wild = AttitudeFilter(INERTIA, p, gravity_m_s2=G)
    for t_now, imu, mag in calls[:300]:
        a = np.zeros(3) if t_now < 1.0 else np.array([0.0, 100.0, 0.0])
        e_w = wild.update(imu, mag, np.zeros(3), t_now, accel_ref=(t_now - 0.11, t_now - 0.01, a))
        assert wild._aid_c is None or np.linalg.norm(wild._aid_c) <= p.aid_max_correction_m_s2 + 1e-9
    assert math.radians(-30.0) < e_w.euler_rad[0] < 0.0   # 3 m/s^2: ~17 deg; 100 m/s^2 would be ~84
    # a reference that stops (its window ends longer than aid_max_age_s ago) is dropped: the
    # raw accelerometer angles take over, exactly as with no reference
    import copy
    t_stop = calls[300][0]
    stale = (t_stop - 0.11, t_stop - 0.01, np.array([0.0, 100.0, 0.0]))
    plain = None
    for t_now, imu, mag in calls[300:]:
        if plain is None and t_now > stale[1] + p.aid_max_age_s + DT:
            plain = copy.deepcopy(wild)
        e = wild.update(imu, mag, np.zeros(3), t_now, accel_ref=stale)
        if plain is not None:
            e_plain = plain.update(imu, mag, np.zeros(3), t_now)
    assert e.euler_rad == pytest.approx(e_plain.euler_rad, abs=1e-12)


# ------------------------------------------------------------------ against the per-axis filterpy filter
def _van_loan(lpf_tau_s, h):
    """F, B and the unit process noises on w', a', b' of (13) from matrix exponentials (scipy)."""
    from scipy.linalg import expm
    a, b = continuous_model(lpf_tau_s)
    n, nu = NX, b.shape[1]
    m = np.zeros((n + nu, n + nu))
    m[:n, :n], m[:n, n:] = a, b
    e = expm(m * h)
    qs = []
    for idx in (W, A, B):
        vl = np.zeros((2 * n, 2 * n))
        vl[:n, :n], vl[n:, n:] = -a, a.T
        vl[idx, n + idx] = 1.0
        ev = expm(vl * h)
        qd = ev[n:, n:].T @ ev[:n, n:]
        qs.append(0.5 * (qd + qd.T))
    return (e[:n, :n], e[:n, n:], *qs)


@pytest.mark.parametrize("tau", [0.005, 0.02, 0.1])
def test_closed_form_discretisation_is_the_matrix_exponential(tau):
    """F, B, Q in closed form (power series where the closed form's differences cancel) against
    scipy's expm: to the exponential's own accuracy (~1e-11 of the largest entry at k h = 100),
    and entry by entry, the smallest ones too, where that is ~1e-10 (short steps)."""
    for h in (0.0, 1e-4, 3e-4, 2.5e-3, 5e-3, 0.0123, 0.05, 0.1, 0.5):
        for got, ref in zip(discrete_model(tau, h), _van_loan(tau, h)):
            np.testing.assert_allclose(got, ref, rtol=1e-8 if h <= 0.01 else 1e-11,
                                       atol=1e-11 * np.abs(ref).max(), err_msg=f"tau {tau}, h {h}")


class _PerAxisReference:
    """The attitude filter as it was written before the stacked floats: three filterpy
    KalmanFilters (one per axis, dim_x 5, dim_z 2), F, B, Q from scipy's matrix exponentials
    (Van Loan) for each piece of each step, the a_model mean by np.interp over the history,
    the extrapolator per axis and piece.  The numerics of that code, compacted; only the
    reference for test_stacked_filter_equals_the_per_axis_filterpy_filter."""

    def __init__(self, inertia, params, gravity_m_s2):
        from filterpy.kalman import KalmanFilter
        self._kalman = KalmanFilter
        self.inertia, self.gravity, self.params, self.dt = np.asarray(inertia, float), gravity_m_s2, params, DT
        self._cache = {}
        p = params
        if p.model_filter_lag:
            self._h = np.array([[0.0, 1.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0, 0.0]])
        else:
            self._h = np.array([[1.0, 0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 1.0, 0.0, 0.0]])
        self._h_rate_only = self._h.copy()
        self._h_rate_only[1, :] = 0.0
        self._angle_meas_idx = AF if p.model_filter_lag else A
        self._r = [np.diag([p.rate_meas_var[i], p.angle_meas_var[i]]) for i in range(3)]
        self.kfs = []
        for i in range(3):
            kf = self._kalman(dim_x=NX, dim_z=2, dim_u=2)
            kf.x, kf.P = np.zeros((NX, 1)), self._p0(0.0)
            self.kfs.append(kf)
        self.kfs[2].P[A, A] = self.kfs[2].P[AF, AF] = math.pi ** 2
        self._t_kf = self._t_prev_call = None
        self._bias_started = self._yaw_seen = False
        self._segs = []
        self._wf, self._af, self._g_prev, self._a_prev = np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3)
        self._yaw_hold, self._yaw_hold_t, self._pending_mag = None, 0.0, None
        self._amodel, self._aid_ref = deque(), None
        self._drop_aid_history()

    def _disc(self, h):
        key = int(round(h * 1e4))
        if key not in self._cache:
            self._cache[key] = _van_loan(self.params.lpf_tau_s, key * 1e-4)
        return self._cache[key]

    def _q(self, i, qw, qa, qb):
        p = self.params
        return p.rate_process_var[i] * qw + p.angle_process_var[i] * qa + p.bias_process_var[i] * qb

    def _p0(self, bias_var):
        p = self.params
        return np.diag([p.init_rate_var, p.init_rate_var, p.init_angle_var, p.init_angle_var,
                        p.init_bias_var if bias_var is None else bias_var])

    def _excess(self, xs):
        if not self.params.euler_kinematics:
            return np.zeros(3)
        roll, pitch = float(xs[0][A, 0]), float(xs[1][A, 0])
        p, q, r = (float(x[W, 0]) for x in xs)
        sr, cr, cp = math.sin(roll), math.cos(roll), math.cos(pitch)
        cp = math.copysign(max(abs(cp), 0.2), cp)
        return np.array([(sr * q + cr * r) * (math.sin(pitch) / cp), (cr - 1.0) * q - sr * r,
                         (sr * q + cr * r) / cp - r])

    def _add_torque(self, torque_nm, t_now):
        u = np.asarray(torque_nm, dtype=np.float64).reshape(-1)
        if u.shape != (3,) or not np.all(np.isfinite(u)):
            u = np.zeros(3)
        u = u / self.inertia
        t0 = self._t_prev_call if self._t_prev_call is not None else t_now - self.dt
        if self._segs:
            t0 = max(t0, self._segs[-1][1])
        if t_now > t0:
            self._segs.append((t0, t_now, u))
        if self._t_kf is not None:
            while self._segs and self._segs[0][1] < self._t_kf - 1.0:
                self._segs.pop(0)

    def _pieces(self, t0, t1):
        out, t, u_last = [], t0, np.zeros(3)
        for s0, s1, u in self._segs:
            if t >= t1:
                break
            if s1 <= t:
                u_last = u
                continue
            if s0 >= t1:
                break
            if s0 > t:
                out.append((s0 - t, u_last))
                t = s0
            e = min(s1, t1)
            out.append((e - t, u))
            t, u_last = e, u
        if t < t1:
            out.append((t1 - t, u_last))
        return [(h, u) for h, u in out if h > 1e-9]

    @staticmethod
    def _rewrap(x):
        a = float(x[A, 0])
        s = float(wrap_angle(a)) - a
        if s != 0.0:
            x[A, 0] += s
            x[AF, 0] += s
        x[AF, 0] = x[A, 0] + float(wrap_angle(float(x[AF, 0] - x[A, 0])))

    def _predict(self, t0, t1):
        for h, u in self._pieces(t0, t1):
            f, bd, qw, qa, qb = self._disc(h)
            e = self._excess([kf.x for kf in self.kfs])
            for i, kf in enumerate(self.kfs):
                kf.predict(u=np.array([[u[i]], [e[i]]]), B=bd, F=f, Q=self._q(i, qw, qa, qb))

    def _mag_yaw(self, field, roll, pitch):
        field = np.asarray(field, dtype=np.float64).reshape(-1)
        if field.shape != (3,) or not np.all(np.isfinite(field)):
            return None
        yaw = mag_yaw(field, roll, pitch, self.params.mag_field_world_ut)
        return yaw if math.isfinite(yaw) else None

    def _set_yaw_from_mag(self, yaw):
        kf = self.kfs[2]
        kf.x[A, 0] = kf.x[AF, 0] = yaw
        kf.P[[A, AF], :] = 0.0
        kf.P[:, [A, AF]] = 0.0
        kf.P[A, A] = kf.P[AF, AF] = self.params.init_angle_var
        self._af[2] = self._a_prev[2] = yaw
        self._yaw_seen = True

    def _accel_angles(self, accel):
        n = float(np.linalg.norm(accel))
        if not math.isfinite(n) or n < self.params.min_accel_g * G_REF or n == 0.0:
            return None
        return accel_roll_pitch(accel)

    def _initialise(self, t, gyro, accel):
        rp = self._accel_angles(accel)
        roll, pitch = rp if rp is not None else (0.0, 0.0)
        yaw = 0.0
        if self._pending_mag is not None:
            y = self._mag_yaw(self._pending_mag[1], roll, pitch)
            if y is not None:
                yaw = self._yaw_hold = y
                self._yaw_hold_t = t
        angles = np.array([roll, pitch, yaw])
        self._wf, self._g_prev, self._af, self._a_prev = gyro.copy(), gyro.copy(), angles.copy(), angles.copy()
        for i, kf in enumerate(self.kfs):
            bias, bias_var = float(kf.x[B, 0]), float(kf.P[B, B])
            if not self._bias_started:
                bias, bias_var = 0.0, None
            rate = gyro[i] - bias
            kf.x = np.array([[rate], [rate], [angles[i]], [angles[i]], [bias]])
            kf.P = self._p0(bias_var)
        self._bias_started = True
        self._yaw_seen = self._yaw_hold is not None
        if not self._yaw_seen:
            self.kfs[2].P[A, A] = self.kfs[2].P[AF, AF] = math.pi ** 2
        self._drop_aid_history()
        self._t_kf = t

    def _process_mag(self, t_m, field):
        if self._t_kf is None:
            self._pending_mag = (t_m, field)
            return
        yaw = self._mag_yaw(field, float(self.kfs[0].x[A, 0]), float(self.kfs[1].x[A, 0]))
        if yaw is None:
            return
        if not self._yaw_seen:
            self._set_yaw_from_mag(yaw)
        self._yaw_hold, self._yaw_hold_t = yaw, t_m

    def _process_imu(self, t, gyro, accel, tilt=None):
        if self._t_kf is None:
            self._initialise(t, gyro, accel)
            return
        h = t - self._t_kf
        if not h > 0:
            return
        if h > self.params.max_gap_s:
            yaw_keep, seen = float(self.kfs[2].x[A, 0]), self._yaw_seen
            self._t_kf = None
            self._initialise(t, gyro, accel)
            if seen and self._yaw_hold is None:
                self._set_yaw_from_mag(yaw_keep)
            return
        c = 1.0 - math.exp(-h / self.params.lpf_tau_s)
        self._wf += c * (0.5 * (self._g_prev + gyro) - self._wf)
        self._g_prev = gyro.copy()
        self._predict(self._t_kf, t)
        aid = self._aid_correction(t) if tilt is None else None
        if aid is not None:
            r = rotation_zyx(*(float(kf.x[A, 0]) for kf in self.kfs))
            rp = accel_roll_pitch(r.T @ (np.array([0.0, 0.0, self.gravity]) - aid))
        else:
            rp = self._accel_angles(accel) if tilt is None else tilt
        angle_ok = [rp is not None, rp is not None, False]
        if rp is not None:
            for i in range(2):
                mid = self._a_prev[i] + 0.5 * float(wrap_angle(rp[i] - self._a_prev[i]))
                self._af[i] = float(wrap_angle(self._af[i] + c * float(wrap_angle(mid - self._af[i]))))
                self._a_prev[i] = rp[i]
        if self._yaw_hold is not None:
            dt_hold = t - max(self._yaw_hold_t, t - h)
            if dt_hold > 0:
                self._yaw_hold = float(wrap_angle(self._yaw_hold + float(gyro[2]) * dt_hold))
                self._yaw_hold_t = t
            mid = self._a_prev[2] + 0.5 * float(wrap_angle(self._yaw_hold - self._a_prev[2]))
            self._af[2] = float(wrap_angle(self._af[2] + c * float(wrap_angle(mid - self._af[2]))))
            self._a_prev[2] = self._yaw_hold
            angle_ok[2] = self._yaw_seen
        for i, kf in enumerate(self.kfs):
            if angle_ok[i]:
                pred = float(kf.x[self._angle_meas_idx, 0])
                kf.update(np.array([[self._wf[i]], [pred + float(wrap_angle(self._af[i] - pred))]]), R=self._r[i], H=self._h)
            else:
                kf.update(np.array([[self._wf[i]], [0.0]]), R=self._r[i], H=self._h_rate_only)
            self._rewrap(kf.x)
            kf.P = 0.5 * (kf.P + kf.P.T)
        self._t_kf = t
        a = rotation_zyx(*(float(kf.x[A, 0]) for kf in self.kfs)) @ accel
        a[2] -= self.gravity
        self._amodel.append((t, a))
        while self._amodel and self._amodel[0][0] < t - 1.0:
            self._amodel.popleft()

    def _drop_aid_history(self):
        self._amodel.clear()
        self._aid_c = self._aid_done = None
        self._aid_t1 = -math.inf

    def _amodel_mean(self, t0, t1):
        if not self._amodel or not t1 > t0:
            return None
        if self._amodel[0][0] > t0 + 1e-6 or self._amodel[-1][0] < t1 - 1e-6:
            return None
        ts = np.array([e[0] for e in self._amodel])
        vals = np.array([e[1] for e in self._amodel])
        grid = np.concatenate(([t0], ts[(ts > t0) & (ts < t1)], [t1]))
        on_grid = np.stack([np.interp(grid, ts, vals[:, i]) for i in range(3)], axis=1)
        mean = np.sum(0.5 * (on_grid[1:] + on_grid[:-1]) * np.diff(grid)[:, None], axis=0) / (t1 - t0)
        return mean if np.all(np.isfinite(mean)) else None

    def _aid_correction(self, t):
        if self._aid_ref is None:
            return None
        t0, t1, a_ref = self._aid_ref
        if self._aid_done != (t0, t1):
            mean = self._amodel_mean(t0, t1)
            if mean is not None:
                corr = a_ref - mean
                n, cap = float(np.linalg.norm(corr)), self.params.aid_max_correction_m_s2
                self._aid_c = corr * (cap / n) if n > cap else corr
                self._aid_done, self._aid_t1 = (t0, t1), t1
        if self._aid_c is None or t - self._aid_t1 > self.params.aid_max_age_s:
            return None
        return self._aid_c

    def reinitialise(self, euler, rate):
        if self._t_kf is None:
            return
        euler, rate = wrap_angle(np.asarray(euler, dtype=np.float64)), np.asarray(rate, dtype=np.float64)
        for i, kf in enumerate(self.kfs):
            kf.x[W, 0] = kf.x[WF, 0] = rate[i] - kf.x[B, 0]
            kf.x[A, 0] = kf.x[AF, 0] = euler[i]
        self._wf, self._g_prev, self._af, self._a_prev = rate.copy(), rate.copy(), euler.copy(), euler.copy()
        if self._yaw_hold is not None:
            self._yaw_hold = float(euler[2])
        self._drop_aid_history()

    def update(self, imu_samples, mag, torque_nm, t_now, accel_ref=None):
        self._aid_ref = None
        if accel_ref is not None:
            self._aid_ref = (float(accel_ref[0]), float(accel_ref[1]), np.asarray(accel_ref[2], dtype=np.float64))
        self._add_torque(torque_nm, t_now)
        self._t_prev_call = t_now
        samples = []
        for s in imu_samples:
            g, a = np.asarray(s[1], dtype=np.float64), np.asarray(s[2], dtype=np.float64)
            samples.append((float(s[0]), g, a, s[3] if len(s) > 3 else None))
        samples.sort(key=lambda s: s[0])
        mag_item = (float(mag[0]), mag[1]) if mag is not None else None
        for t, g, a, tilt in samples:
            if mag_item is not None and mag_item[0] <= t:
                self._process_mag(*mag_item)
                mag_item = None
            self._process_imu(t, g, a, tilt)
        if mag_item is not None:
            self._process_mag(*mag_item)
        return self._estimate(t_now)

    def _estimate(self, t_now):
        if self._t_kf is None:
            return AttitudeEstimate(np.zeros(3), np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]),
                                    np.array([kf.P[A, A] for kf in self.kfs]),
                                    np.array([kf.P[W, W] for kf in self.kfs]), 0.0)
        delay = max(0.0, t_now - self._t_kf)
        xs, ps = [kf.x.copy() for kf in self.kfs], [kf.P.copy() for kf in self.kfs]
        if self.params.extrapolate and delay > 0.0:
            for h, u in self._pieces(self._t_kf, self._t_kf + min(delay, self.params.max_delay_steps * self.dt)):
                f, bd, qw, qa, qb = self._disc(h)
                e = self._excess(xs)
                for i in range(3):
                    xs[i] = f @ xs[i] + bd @ np.array([[u[i]], [e[i]]])
                    ps[i] = f @ ps[i] @ f.T + self._q(i, qw, qa, qb)
        euler = wrap_angle(np.array([x[A, 0] for x in xs]))
        return AttitudeEstimate(euler, np.array([x[W, 0] for x in xs]), quat_from_euler(*euler),
                                np.array([pp[A, A] for pp in ps]), np.array([pp[W, W] for pp in ps]), float(delay))


def _manoeuvring_calls(seed, n=400, mag_first=True):
    """Calls of the attitude service over a random manoeuvre: IMU samples with a jittered period
    and a transport delay, in any order within a call (the first call with 50 ms of them, older
    than any torque; now and then one sent again; a tilt measurement with some), the magnetometer
    (mag_first: one sample before the first IMU sample), an acceleration reference (some wild
    enough to be capped), the commanded torque, a 0.7 s IMU gap and a re-initialisation."""
    rng = np.random.default_rng(seed)
    angle, w = np.array([0.1, -0.2, 3.0]), np.zeros(3)
    t_imu, t_off, calls, last = 0.0, 0.05, [], None
    for c in range(n):
        if c == n // 2:       # the IMU falls silent for 0.7 s (the filter re-initialises)
            t_imu += 0.7
            t_off += 0.7
        t_now = DT * c + t_off + rng.uniform(0.0, 4e-4)
        imu = [last] if (c % 50 == 49 and last is not None) else []
        while t_imu < t_now - 0.003:
            t_imu += IMU_DT + rng.uniform(-2e-4, 2e-4)
            w = w + rng.normal(0.0, 0.3, 3)
            angle = angle + w * IMU_DT
            r = quat_to_rotation(quat_from_euler(*angle))
            s = (t_imu, w + 3e-3 + rng.normal(0.0, 3e-3, 3),
                 r.T @ [0.3 * math.sin(t_imu), 0.2, G] + rng.normal(0.0, 0.05, 3))
            imu.append(s + (tuple(angle[:2] + rng.normal(0.0, 0.01, 2)),) if 100 <= c < 130 else s)
        last = imu[-1] if imu else last
        rng.shuffle(imu)
        field = quat_to_rotation(quat_from_euler(*angle)).T @ FIELD + rng.normal(0.0, 0.5, 3)
        mag = (0.0, field) if (c == 0 and mag_first) else ((imu[0][0], field) if imu and c % 4 == 1 else None)
        ref = None
        if c > 40 and c % 3:
            ref = (t_now - 0.12, t_now - 0.02, rng.normal(0.0, 8.0 if c % 7 == 0 else 0.5, 3))
        reinit = ([0.1, 0.2, -1.0], [0.3, 0.0, 0.1]) if c == 3 * n // 4 else None
        calls.append((imu, mag, rng.normal(0.0, 0.02, 3), t_now, ref, reinit))
    return calls


@pytest.mark.parametrize("overrides, mag_first", [({}, True), ({}, False), ({"model_filter_lag": False}, False),
                                                  ({"euler_kinematics": False}, True), ({"extrapolate": False}, True),
                                                  (FILTER_000, False)])
def test_stacked_filter_equals_the_per_axis_filterpy_filter(overrides, mag_first, monkeypatch):
    """The filter (floats, closed-form discretisation) against the per-axis filterpy code it
    replaced: the same estimate, states and covariances to rounding on a manoeuvring flight.
    Half the cases move the a_model integral's origin at every sample (a long flight's case)."""
    import flight.estimation.attitude_filter
    if mag_first:
        monkeypatch.setattr(flight.estimation.attitude_filter, "_AMODEL_REBASE", 0.0)
    params = AttitudeFilterParams.from_dict(overrides)
    new, ref = AttitudeFilter(INERTIA, params, gravity_m_s2=9.8), _PerAxisReference(INERTIA, params, 9.8)
    aided = capped = 0
    for imu, mag, torque, t_now, accel_ref, reinit in _manoeuvring_calls(seed=7, mag_first=mag_first):
        if reinit is not None:
            new.reinitialise(*reinit)
            ref.reinitialise(*reinit)
        e_new = new.update(imu, mag, torque, t_now, accel_ref=accel_ref)
        e_ref = ref.update(imu, mag, torque, t_now, accel_ref=accel_ref)
        for name in ("euler_rad", "rate_rad_s", "quaternion_wxyz", "euler_var", "rate_var"):
            np.testing.assert_allclose(getattr(e_new, name), getattr(e_ref, name), rtol=1e-9, atol=1e-12,
                                       err_msg=f"{name} at t = {t_now}")
        assert e_new.delay_s == pytest.approx(e_ref.delay_s, abs=1e-12)
        np.testing.assert_allclose(new.x, np.array([kf.x[:, 0] for kf in ref.kfs]), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(new.P, np.array([kf.P for kf in ref.kfs]), rtol=1e-9, atol=1e-15)
        if ref._aid_c is not None:
            aided += 1
            capped += bool(np.linalg.norm(ref._aid_c) >= params.aid_max_correction_m_s2 - 1e-12)
            np.testing.assert_allclose(new._aid_c, ref._aid_c, rtol=1e-9, atol=1e-12)
    assert aided > 100 and capped > 0      # the acceleration reference was used, and capped
    np.testing.assert_allclose(new.gyro_bias, [kf.x[B, 0] for kf in ref.kfs], rtol=1e-9, atol=1e-15)


def test_no_filterpy_or_scipy_on_import():
    """The flight code imports neither (filterpy pulls scipy.stats: half a second at start-up)."""
    import subprocess
    import sys
    code = ("import sys, flight.estimation.attitude_filter, services.attitude; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('filterpy', 'scipy')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
