"""Position-level EKF of document 000 (flight/estimation/position_ekf.py)."""
from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import pytest

from flight.estimation.position_ekf import (
    N_STATE,
    LaggedMotorInput,
    PositionEKF,
    PositionEKFError,
    PositionEKFParams,
    discretize,
    f,
    jacobian_f,
    rk4_step,
)
from flight.quat import quat_from_euler, quat_multiply, quat_to_euler, quat_to_rotation
from flight.vehicle import load_vehicle

VEH = load_vehicle("x250")
NO_DISTURBANCE = PositionEKFParams(q_disturbance_m2_s5=0.0, init_std_disturbance_m_s2=0.0)
DT = 0.01
DEG = math.pi / 180
ATT_STD = np.array([0.5 * DEG] * 3)
RATE_STD = np.array([0.02] * 3)
CAM_STD = 0.005
CAM_EVERY = 5          # 20 Hz at 100 Hz
NEES_LO, NEES_HI = 0.216, 9.35   # 95 % interval of chi-square, 3 dof


# --------------------------------------------------------------------------- model
def _random_state(rng):
    x = rng.normal(size=12)
    x[6:9] = rng.uniform([-1.0, -1.0, -math.pi], [1.0, 1.0, math.pi])
    x[9:12] = rng.normal(scale=2.0, size=3)
    return x


def _fd_jacobian(x, u, h=1e-6):
    J = np.zeros((12, 12))
    for i in range(12):
        e = np.zeros(12)
        e[i] = h
        J[:, i] = (f(x + e, u, VEH) - f(x - e, u, VEH)) / (2 * h)
    return J


def test_jacobian_matches_central_differences():
    rng = np.random.default_rng(1)
    for _ in range(50):
        x = _random_state(rng)
        u = np.array([rng.uniform(0.0, 10.0), *rng.normal(scale=0.05, size=3)])
        np.testing.assert_allclose(jacobian_f(x, u, VEH), _fd_jacobian(x, u), rtol=1e-6, atol=1e-7)


def test_jacobian_with_unequal_inertia():
    """The Euler-equation terms that vanish for Ixx = Iyy."""
    from dataclasses import replace
    veh = replace(VEH, inertia_kg_m2=(5e-3, 8e-3, 14e-3))
    rng = np.random.default_rng(2)
    for _ in range(10):
        x = _random_state(rng)
        u = np.array([4.0, 0.01, -0.02, 0.003])
        J = np.zeros((12, 12))
        for i in range(12):
            e = np.zeros(12)
            e[i] = 1e-6
            J[:, i] = (f(x + e, u, veh) - f(x - e, u, veh)) / 2e-6
        np.testing.assert_allclose(jacobian_f(x, u, veh), J, rtol=1e-6, atol=1e-7)


def test_model_matches_project_conventions():
    """Thrust along R e3 of flight.quat (ZYX, ENU/FLU); Euler rates are the ZYX kinematics of body rates."""
    rng = np.random.default_rng(3)
    m, g, c = VEH.mass_kg, VEH.gravity_m_s2, VEH.drag_n_per_m_s
    for _ in range(20):
        x = _random_state(rng)
        u = np.array([5.0, 0.0, 0.0, 0.0])
        xd = f(x, u, VEH)
        R = quat_to_rotation(quat_from_euler(*x[6:9]))
        np.testing.assert_allclose(xd[3:6], u[0] / m * R[:, 2] - c / m * x[3:6] - [0, 0, g], atol=1e-12)
        # Euler rates: derivative of quat_to_euler along q' = 1/2 q (x) [0, w]
        q = quat_from_euler(*x[6:9])
        h = 1e-7
        dq = 0.5 * quat_multiply(q, np.r_[0.0, x[9:12]])
        e_p = np.array(quat_to_euler(q + h * dq))
        e_m = np.array(quat_to_euler(q - h * dq))
        de = (e_p - e_m + math.pi) % (2 * math.pi) - math.pi
        np.testing.assert_allclose(xd[6:9], de / (2 * h), rtol=1e-5, atol=1e-6)
    # hover: u1 = m g, level, at rest -> no acceleration
    np.testing.assert_allclose(f(np.zeros(12), [m * g, 0, 0, 0], VEH), np.zeros(12), atol=1e-12)


def test_discretisation_transition_matches_rk4_sensitivity():
    rng = np.random.default_rng(4)
    x = _random_state(rng) * 0.3
    u = np.array([4.2, 0.01, -0.01, 0.002])
    _, F, Q = discretize(x, u, VEH, DT, np.ones(12))
    Fd = np.zeros((12, 12))
    for i in range(12):
        e = np.zeros(12)
        e[i] = 1e-6
        Fd[:, i] = (rk4_step(x + e, u, VEH, DT) - rk4_step(x - e, u, VEH, DT)) / 2e-6
    from scipy.linalg import expm
    np.testing.assert_allclose(F, expm(jacobian_f(x, u, VEH) * DT), atol=1e-5)
    # F is taken at the step's start: the state's motion over one step is an O(dt^2) difference
    np.testing.assert_allclose(F, Fd, atol=2e-3)
    x[9:12] = 0.0  # without rotation the linearisation point stays put: much closer
    u[1:] = 0.0
    _, F, _ = discretize(x, u, VEH, DT)
    for i in range(12):
        e = np.zeros(12)
        e[i] = 1e-6
        Fd[:, i] = (rk4_step(x + e, u, VEH, DT) - rk4_step(x - e, u, VEH, DT)) / 2e-6
    np.testing.assert_allclose(F, Fd, atol=2e-5)
    np.testing.assert_allclose(Q, np.eye(12) * DT)


def _rk4_full(xf, u, dt):
    """The filter's full step, from f itself: (1)-(2) with u1 times the thrust scale xf[12] and
    the disturbance xf[13:15] added to the horizontal acceleration (RK4, u held); s, d and the
    accelerometer's bias xf[15:17] stay."""
    ue = np.array(u, dtype=float)
    ue[0] *= xf[12]

    def rate(x12):
        r = f(x12, ue, VEH)
        r[3:5] += xf[13:15]
        return r
    x = xf[:12]
    k1 = rate(x)
    k2 = rate(x + 0.5 * dt * k1)
    k3 = rate(x + 0.5 * dt * k2)
    k4 = rate(x + dt * k3)
    return np.r_[x + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4), xf[12:]]


def test_filter_state_columns_match_finite_differences():
    """The thrust scale's column and the disturbance's two, against finite differences of f."""
    rng = np.random.default_rng(5)
    x = np.r_[_random_state(rng) * 0.3, 0.9, 0.3, -0.2, 0.02, -0.01]
    x[9:12] = 0.0
    u = np.array([4.2, 0.0, 0.0, 0.0])
    x_next, F, Q = discretize(x, u, VEH, DT, np.ones(N_STATE))
    np.testing.assert_allclose(x_next, _rk4_full(x, u, DT), atol=1e-12)
    Fd = np.zeros((N_STATE, N_STATE))
    for i in range(N_STATE):
        e = np.zeros(N_STATE)
        e[i] = 1e-6
        Fd[:, i] = (_rk4_full(x + e, u, DT) - _rk4_full(x - e, u, DT)) / 2e-6
    np.testing.assert_allclose(F, Fd, atol=2e-5)
    assert F[5, 12] == pytest.approx(DT * u[0] / VEH.mass_kg * math.cos(x[6]) * math.cos(x[7]), rel=5e-3)
    assert F[3, 13] == pytest.approx(DT, rel=1e-2) and F[4, 14] == pytest.approx(DT, rel=1e-2)
    np.testing.assert_allclose(Q, np.eye(N_STATE) * DT)


# --------------------------------------------------------------------------- params
def test_params_from_dict_and_validation():
    p = PositionEKFParams.from_dict({"q_velocity_m2_s3": 0.05, "gate_probability": 0.99})
    assert p.q_velocity_m2_s3 == 0.05 and p.gate_probability == 0.99
    assert PositionEKFParams.from_dict(p.to_dict()) == p
    with pytest.raises(PositionEKFError, match="unknown"):
        PositionEKFParams.from_dict({"q_velocity": 1.0})
    for bad in ({"gate_probability": 0.0}, {"gate_probability": 1.5}, {"q_rates_rad2_s3": -1.0},
                {"init_std_position_m": 0.0}, {"max_delay_s": -0.1}, {"q_position_m2_s": float("nan")},
                {"q_position_m2_s": True}):
        with pytest.raises(PositionEKFError):
            PositionEKFParams.from_dict(bad)
    d = PositionEKFParams()
    assert d.max_delay_s >= 0.3 and d.gate_probability == 0.999


# --------------------------------------------------------------------------- simulation
def _ctrl(x, p_ref):
    """Laws (8)-(11) of 000 on the true state (tilt limited to 0.35 rad)."""
    m, g = VEH.mass_kg, VEH.gravity_m_s2
    ix, iy, iz = VEH.inertia_kg_m2
    h = -8.0 * x[3:6] - 16.0 * (x[0:3] - p_ref)
    h[2] = max(h[2] + g, 0.3 * g)
    lim = h[2] * math.tan(0.35)
    hor = math.hypot(h[0], h[1])
    if hor > lim:
        h[:2] *= lim / hor
    yaw = x[8]
    hx = math.cos(yaw) * h[0] + math.sin(yaw) * h[1]
    hy = -math.sin(yaw) * h[0] + math.cos(yaw) * h[1]
    ref = np.array([math.atan2(-hy, math.hypot(hx, h[2])), math.atan2(hx, h[2]), 0.0])
    err = x[6:9] - ref
    err[2] = (err[2] + math.pi) % (2 * math.pi) - math.pi
    tau = np.array([ix, iy, iz]) * (-32.0 * x[9:12] - 256.0 * err)
    return np.r_[m * np.linalg.norm(h), tau]


def _step_ref(t):
    return np.array([0.0, 0.0, 1.0]) if t < 2.0 else np.array([1.5, 0.8, 1.5])


@functools.lru_cache(maxsize=None)
def _truth(seed: int = 0, duration: float = 8.0, q_scale: float = 1.0, thrust_scale: float = 1.0,
           pull_m_s2=(0.0, 0.0)):
    """Truth at 100 Hz from the same model (RK4 at 2 ms), u held over each 10 ms, plus
    process noise (times q_scale) on velocity and rates: a calm indoor 0.005 m^2/s^3 on
    velocity, below the filter's default, which also covers the plant's unmodelled motor lag.
    thrust_scale: the plant makes this times the commanded collective (a payload); the
    recorded inputs are the commands. pull_m_s2: a steady horizontal acceleration on the plant
    (a wind's drag) that the model does not have."""
    rng = np.random.default_rng(seed)
    qc = PositionEKFParams(q_velocity_m2_s3=0.005).process_noise_density * q_scale
    n = int(round(duration / DT))
    xs = np.zeros((n + 1, 12))
    us = np.zeros((n, 4))
    x = np.zeros(12)
    x[0:3] = [0.0, 0.0, 1.0]
    xs[0] = x
    for k in range(n):
        u = _ctrl(x, _step_ref(k * DT))
        u_real = u * [thrust_scale, 1.0, 1.0, 1.0]
        for _ in range(5):
            x = rk4_step(x, u_real, VEH, DT / 5)
            x[0:2] += 0.5 * np.asarray(pull_m_s2) * (DT / 5) ** 2
            x[3:5] += np.asarray(pull_m_s2) * (DT / 5)
        x[3:6] += rng.normal(size=3) * np.sqrt(qc[3:6] * DT)
        x[9:12] += rng.normal(size=3) * np.sqrt(qc[9:12] * DT)
        us[k] = u
        xs[k + 1] = x
    return xs, us


def _run(xs, us, *, seed=0, delay_steps=5, naive=False, params=None, outage=None, outlier_at=None,
         trace=None):
    """Feed a filter: attitude at 100 Hz, camera at 20 Hz exposed at step k, delivered delay_steps later.

    naive: the camera fix is fused as if taken now. outage: (t0, t1) exposure times with no camera.
    outlier_at: exposure step whose fix is moved 1 m in x. Returns estimates, position covariances.
    """
    rng = np.random.default_rng(1000 + seed)
    n = len(us)
    ekf = PositionEKF(VEH, params or PositionEKFParams(), dt=DT)
    ekf.initialize(0.0, xs[0, 0:3] + rng.normal(scale=0.02, size=3), xs[0, 6:9])
    est = np.zeros((n + 1, N_STATE))
    pcov = np.zeros((n + 1, 3, 3))
    est[0], pcov[0] = ekf.x, ekf.position_cov
    cam_cov = np.eye(3) * CAM_STD ** 2
    pending = []
    for k in range(n):
        t = (k + 1) * DT
        ekf.predict(t, us[k])
        xt = xs[k + 1]
        ekf.update_attitude(t, xt[6:9] + rng.normal(size=3) * ATT_STD, xt[9:12] + rng.normal(size=3) * RATE_STD,
                                 ATT_STD ** 2, RATE_STD ** 2)
        if (k + 1) % CAM_EVERY == 0:
            z = xt[0:3] + rng.normal(scale=CAM_STD, size=3)
            if outlier_at is not None and k + 1 == outlier_at:
                z = z + [1.0, 0.0, 0.0]
            if outage is None or not outage[0] <= t < outage[1]:
                pending.append((k + 1 + delay_steps, t, z))
        while pending and pending[0][0] == k + 1:
            _, t_exp, z = pending.pop(0)
            res = ekf.update_position(t if naive else t_exp, z, cam_cov)
            if trace is not None:
                trace.append((t, t_exp, z, res))
        est[k + 1], pcov[k + 1] = ekf.x, ekf.position_cov
        if trace is not None:
            trace.append((t, None, None, (ekf.accepted("position"), np.trace(pcov[k + 1]))))
    return ekf, est, pcov


def test_a_steady_pull_is_learnt_and_the_fixes_stay_in_the_gate():
    """A wind's drag (0.5 m/s^2 on the x250 at 2 m/s) that the model lacks: the disturbance
    states learn it, the camera's fixes keep passing the gate and the estimate stays within
    a centimetre; through a 1 s camera outage the prediction carries the pull (without the
    states, their noise 0, it drifts more than three times as far)."""
    pull = (0.5, -0.3)
    xs, us = _truth(0, pull_m_s2=pull)
    t = np.arange(len(xs)) * DT
    ekf, est, pcov = _run(xs, us)
    rms, _ = _metrics(xs, est, pcov, t >= 3.0)
    assert rms < 0.01, rms
    np.testing.assert_allclose(est[t >= 4.0, 13:15].mean(axis=0), pull, atol=0.05)
    assert ekf.counters["position"]["gate"] == 0
    outage = (t >= 4.0) & (t <= 5.06)   # to the first fix after it
    drift = {}
    for name, params in (("learnt", None), ("blind", NO_DISTURBANCE)):
        _, est, _ = _run(xs, us, params=params, outage=(4.0, 5.0))
        drift[name] = float(np.max(np.linalg.norm(est[outage, 0:3] - xs[outage, 0:3], axis=1)))
    assert drift["learnt"] < drift["blind"] / 3.0, drift


def _hover_filter(drag=None, seconds=1.0, tilt=(0.0, 0.0)):
    """A level (or tilted) hover held 1 m up, no camera: each 10 ms step predicted, its
    attitude fused, and the accelerometer's body x and y `drag` fused (None: not)."""
    ekf = PositionEKF(VEH, PositionEKFParams(), dt=DT)
    ekf.initialize(0.0, [0.0, 0.0, 1.0], euler=(*tilt, 0.3))
    u = [VEH.mass_kg * VEH.gravity_m_s2, 0.0, 0.0, 0.0]
    for k in range(1, int(round(seconds / DT)) + 1):
        ekf.predict(k * DT, u)
        ekf.update_attitude(k * DT, [*tilt, 0.3], [0.0] * 3, ATT_STD ** 2, RATE_STD ** 2)
        if drag is not None:
            assert ekf.update_drag(k * DT, drag, (0.01, 0.01))[0]
    return ekf


def test_drag_fusion_learns_the_pull_from_the_accelerometer_alone():
    """A wind's pull, read by the accelerometer as the air's force on the airframe in body
    axes (yaw 0.3 rad here), is learnt in a second without a camera fix, as a world-frame
    disturbance; the update leaves the vertical, the attitude and the thrust scale exactly
    where the same filter without it puts them (the thrust is along body z: a drag reading
    says nothing of it)."""
    pull = np.array([0.5, -0.2])
    yaw = 0.3
    body = [math.cos(yaw) * pull[0] + math.sin(yaw) * pull[1], -math.sin(yaw) * pull[0] + math.cos(yaw) * pull[1]]
    fused, plain = _hover_filter(drag=body), _hover_filter()
    k = VEH.drag_n_per_m_s / VEH.mass_kg
    # the reading is d less the drag of the velocity the pull has built meanwhile, plus the bias;
    # without a camera the two split it by their priors (d's 0.5 m/s^2 against b's 0.1): most is d
    c, s_ = math.cos(yaw), math.sin(yaw)
    b_world = np.array([c * fused.x[15] - s_ * fused.x[16], s_ * fused.x[15] + c * fused.x[16]])
    np.testing.assert_allclose(np.array(fused.x[13:15]) - k * np.array(fused.x[3:5]) + b_world, pull, atol=0.02)
    np.testing.assert_allclose(np.array(fused.x[13:15]) - k * np.array(fused.x[3:5]), pull, rtol=0.15)
    assert np.linalg.norm(fused.x[3:5]) > 0.2          # ... and the pull moves the vehicle's estimate
    for i in (2, 5, 6, 7, 8, 9, 10, 11, 12):
        assert fused.x[i] == plain.x[i], i
    assert fused.counters["drag"]["accepted"] == 100


def test_drag_fusion_tells_the_accelerometers_bias_from_a_wind_by_the_camera():
    """Still air, an accelerometer biased (0.01, -0.026) m/s^2 on body x and y (seed 1's draw):
    the camera's fixes say the vehicle does not accelerate, so the reading is learnt as the bias,
    not as a pull the position law would feed forward."""
    bias = (0.01, -0.026)
    ekf = PositionEKF(VEH, PositionEKFParams(), dt=DT)
    ekf.initialize(0.0, [0.0, 0.0, 1.0])
    u = [VEH.mass_kg * VEH.gravity_m_s2, 0.0, 0.0, 0.0]
    rng = np.random.default_rng(2)
    for k in range(1, 1001):
        ekf.predict(k * DT, u)
        ekf.update_attitude(k * DT, [0.0] * 3, [0.0] * 3, ATT_STD ** 2, RATE_STD ** 2)
        ekf.update_drag(k * DT, np.add(bias, rng.normal(0.0, 0.005, 2)), (0.01, 0.01))
        if k % CAM_EVERY == 0:
            ekf.update_position(k * DT, [0.0, 0.0, 1.0] + rng.normal(0.0, CAM_STD, 3), np.eye(3) * CAM_STD ** 2)
    np.testing.assert_allclose(ekf.x[15:17], bias, atol=0.005)
    assert np.max(np.abs(ekf.x[13:15])) < 0.01


def test_drag_fusion_refuses_bad_input_and_gates_an_outlier():
    ekf = _hover_filter(drag=(0.0, 0.0), seconds=0.5)
    assert ekf.update_drag(ekf.t, (math.nan, 0.0), (0.01, 0.01)) == (False, pytest.approx(math.nan, nan_ok=True))
    assert ekf.counters["drag"]["invalid"] == 1
    with pytest.raises(PositionEKFError, match="drag variances"):
        ekf.update_drag(ekf.t, (0.0, 0.0), (0.0, 0.01))
    accepted, nis = ekf.update_drag(ekf.t, (30.0, 0.0), (0.01, 0.01))   # a knock, not the air
    assert not accepted and nis > 100.0 and ekf.counters["drag"]["gate"] == 1
    assert ekf.update_drag(ekf.t + 0.1, (0.0, 0.0), (0.01, 0.01))[0] is False   # ahead of the filter
    assert ekf.counters["drag"]["future"] == 1


def test_drag_readings_are_replayed_under_a_late_camera_fix():
    """A camera fix 60 ms old is fused at its node and the predictions after it re-run with the
    drag readings stored there: the result is the one fusing everything in time order."""
    late, ordered = (_hover_filter(drag=(0.3, 0.0), seconds=0.5) for _ in range(2))
    u = [VEH.mass_kg * VEH.gravity_m_s2, 0.0, 0.0, 0.0]
    fix = ([0.01, -0.02, 1.0], np.eye(3) * 1e-4)
    # ordered: the fix at 0.51 fused when 0.51 is now, after that step's drag reading (a node's
    # measurements are applied in the order they came)
    for ekf, in_time in ((late, False), (ordered, True)):
        for k in range(51, 58):
            ekf.predict(k * DT, u)
            ekf.update_drag(k * DT, (0.3, 0.0), (0.01, 0.01))
            if in_time and k == 51:
                ekf.update_position(0.51, *fix)
        if not in_time:
            ekf.update_position(0.51, *fix)
    np.testing.assert_allclose(late.x, ordered.x, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(late.P, ordered.P, rtol=1e-10, atol=1e-18)


def _metrics(xs, est, pcov, mask):
    e = est[mask, 0:3] - xs[mask, 0:3]
    rms = float(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))
    nees = np.einsum("ki,kij,kj->k", e, np.linalg.inv(pcov[mask]), e)
    return rms, float(np.mean(nees))


def test_hover_and_step_accuracy_and_consistency():
    xs, us = _truth(0)
    ekf, est, pcov = _run(xs, us)
    assert np.all(np.isfinite(est)) and np.all(np.isfinite(pcov))
    t = np.arange(len(xs)) * DT
    mask = t >= 1.0
    rms, nees = _metrics(xs, est, pcov, mask)
    print(f"hover/step: position RMS {rms * 1e3:.2f} mm, mean NEES {nees:.2f}")
    assert rms < 0.01
    assert NEES_LO <= nees <= NEES_HI
    # the vehicle really moved, and the velocity is estimated too
    assert np.ptp(xs[:, 0]) > 1.0
    assert float(np.sqrt(np.mean(np.sum((est[mask, 3:6] - xs[mask, 3:6]) ** 2, axis=1)))) < 0.1
    c = ekf.counters
    assert c["position"]["accepted"] == (len(us) // CAM_EVERY) - 1  # the last fix is still in flight
    # the 0.999 gate refuses ~0.1 % of good attitude samples (6 dof), no good camera fix here
    assert c["position"]["gate"] == 0 and c["attitude"]["gate"] <= 0.01 * len(us)
    assert c["attitude"]["accepted"] + c["attitude"]["gate"] == len(us)
    # consistency over several seeds: mean NEES inside the 3-dof interval for each
    for seed in (1, 2):
        xs2, us2 = _truth(seed)
        _, est2, pcov2 = _run(xs2, us2, seed=seed)
        rms2, nees2 = _metrics(xs2, est2, pcov2, mask)
        print(f"seed {seed}: RMS {rms2 * 1e3:.2f} mm, mean NEES {nees2:.2f}")
        assert rms2 < 0.01 and NEES_LO <= nees2 <= NEES_HI


def test_thrust_scale_learns_a_heavier_vehicle():
    """The plant gives 10 % less collective than commanded (10 % heavier): the thrust
    scale converges to 1/1.1 and the position stays accurate and consistent."""
    xs, us = _truth(0, duration=8.0, thrust_scale=1 / 1.1)
    ekf, est, pcov = _run(xs, us)
    t = np.arange(len(xs)) * DT
    scale = est[:, 12]
    print(f"thrust scale at 1/2/4/8 s: {scale[[100, 200, 400, 800]]}")
    assert abs(scale[-1] - 1 / 1.1) < 0.01
    assert np.all(np.abs(scale[t >= 3.0] - 1 / 1.1) < 0.02)
    rms, nees = _metrics(xs, est, pcov, t >= 3.0)
    assert rms < 0.01
    assert NEES_LO <= nees <= NEES_HI
    # the nominal vehicle keeps its scale
    _, est_nominal, _ = _run(*_truth(0))
    assert np.all(np.abs(est_nominal[t >= 3.0, 12] - 1.0) < 0.02)


def test_delayed_fusion_beats_fusing_as_current():
    xs, us = _truth(0)
    nogate = PositionEKFParams(gate_probability=1.0)
    _, est_d, pcov_d = _run(xs, us, delay_steps=15, params=nogate)
    _, est_n, pcov_n = _run(xs, us, delay_steps=15, params=nogate, naive=True)
    moving = np.linalg.norm(xs[:, 3:6], axis=1) > 0.3
    assert moving.sum() > 100
    rms_d, nees_d = _metrics(xs, est_d, pcov_d, moving)
    rms_n, nees_n = _metrics(xs, est_n, pcov_n, moving)
    print(f"150 ms delay, moving: delayed fusion RMS {rms_d * 1e3:.1f} mm (NEES {nees_d:.1f}), "
          f"as-if-current RMS {rms_n * 1e3:.1f} mm (NEES {nees_n:.1f})")
    assert rms_d < 0.5 * rms_n
    assert rms_d < 0.02
    assert NEES_LO <= nees_d <= NEES_HI and nees_n > NEES_HI  # and only the delayed fusion is consistent
    # with the default gate the as-if-current fixes are mostly refused while moving
    ekf_g, _, _ = _run(xs, us, delay_steps=15, naive=True)
    assert ekf_g.rejected("position", "gate") > 0


def test_camera_outage_covariance_grows_and_fusion_resumes():
    xs, us = _truth(0)
    trace = []
    t0, t1 = 3.0, 5.0  # during the step's moving part
    ekf, est, pcov = _run(xs, us, outage=(t0, t1), trace=trace)
    t = np.arange(len(xs)) * DT
    # last fix before the outage is exposed just before t0 and delivered 50 ms later
    during = (t >= t0 + 0.06) & (t < t1 + 0.05)
    tr = np.trace(pcov[during], axis1=1, axis2=2)
    assert np.all(np.diff(tr) > 0), "position covariance must grow during the outage"
    assert tr[-1] > 20 * tr[0]
    err = np.linalg.norm(est[during, 0:3] - xs[during, 0:3], axis=1)
    print(f"outage: max error {err.max() * 1e3:.1f} mm, sqrt(trace) at end {math.sqrt(tr[-1]) * 1e3:.1f} mm")
    assert err.max() < 0.5
    acc = np.array([a for _, te, _, (a, _) in trace if te is None])  # accepted count after each step
    k_end = int(round((t1 + 0.04) / DT)) - 1  # the first fix after it is delivered at t1 + 0.05
    assert acc[-1] > acc[k_end] + 20  # fusion resumed
    assert acc[k_end] == acc[int(round((t0 + 0.06) / DT)) - 1]  # and nothing fused during the outage
    fixes = [res for _, te, _, res in trace if te is not None]
    assert all(ok for ok, _ in fixes)  # nothing refused after the outage either
    after = t >= t1 + 1.0
    rms_after, _ = _metrics(xs, est, pcov, after)
    assert rms_after < 0.01
    assert np.all(np.isfinite(est))


def test_outlier_rejected_and_counted():
    xs, us = _truth(0)
    _, est_ref, _ = _run(xs, us, seed=5, outage=(4.0, 4.005))  # the same run without that fix
    ekf, est, _ = _run(xs, us, seed=5, outlier_at=400)  # 1 m jump in the fix exposed at 4.0 s
    c = ekf.counters["position"]
    assert c["gate"] == 1
    assert c["accepted"] == (len(us) // CAM_EVERY) - 2
    assert ekf.last_nis["position"] < ekf._gate[3]
    np.testing.assert_allclose(est, est_ref, atol=1e-12)  # a refused fix leaves no trace


def test_too_old_future_and_invalid_refused():
    ekf = PositionEKF(VEH, dt=DT)
    with pytest.raises(RuntimeError):
        ekf.predict(0.01, [4, 0, 0, 0])
    ekf.initialize(0.0, [0, 0, 1])
    hover = [VEH.mass_kg * VEH.gravity_m_s2, 0, 0, 0]
    for k in range(1, 51):
        ekf.predict(k * DT, hover)
    cov = np.eye(3) * 1e-4
    ok, nis = ekf.update_position(0.5 - 0.31, [0, 0, 1], cov)
    assert not ok and math.isnan(nis) and ekf.rejected("position", "too_old") == 1
    ok, _ = ekf.update_position(0.6, [0, 0, 1], cov)
    assert not ok and ekf.rejected("position", "future") == 1
    ok, _ = ekf.update_position(0.45, [0, float("nan"), 1], cov)
    assert not ok and ekf.rejected("position", "invalid") == 1
    assert not ekf.update_attitude(0.7, [0, 0, 0], [0, 0, 0], [1e-4] * 3, [1e-4] * 3)
    assert ekf.rejected("attitude", "future") == 1
    ok, nis = ekf.update_position(0.5 - 0.29, [0.001, 0, 1.0], cov)  # within the history
    assert ok and nis >= 0 and ekf.accepted("position") == 1
    assert ekf.history_span_s <= 0.3 + 1e-9
    with pytest.raises(PositionEKFError):
        ekf.predict(0.5, hover)  # time must advance
    with pytest.raises(PositionEKFError):
        ekf.update_position(0.5, [0, 0], cov)
    assert np.all(np.isfinite(ekf.x)) and np.all(np.isfinite(ekf.P))


def test_yaw_innovation_wrapped():
    ekf = PositionEKF(VEH, dt=DT)
    ekf.initialize(0.0, [0, 0, 1], euler=(0.0, 0.0, math.pi - 0.01))
    ekf.predict(DT, [VEH.mass_kg * VEH.gravity_m_s2, 0, 0, 0])
    ok = ekf.update_attitude(DT, [0, 0, -math.pi + 0.01], [0, 0, 0], [1e-4] * 3, [1e-4] * 3)
    assert ok
    yaw = ekf.euler[2]
    assert abs(abs(yaw) - math.pi) < 0.011  # moved across the cut, not through zero
    assert -math.pi <= yaw < math.pi


def test_out_of_order_fixes_replay_consistently():
    """An older fix arriving after a newer one is fused at its time and the newer one re-applied."""
    xs, us = _truth(0)
    cov = np.eye(3) * CAM_STD ** 2
    rng = np.random.default_rng(9)
    fixes = {k: xs[k, 0:3] + rng.normal(scale=CAM_STD, size=3) for k in (300, 305)}

    def run(order):
        ekf = PositionEKF(VEH, dt=DT)
        ekf.initialize(0.0, xs[0, 0:3], xs[0, 6:9])
        for k in range(320):
            t = (k + 1) * DT
            ekf.predict(t, us[k])
            ekf.update_attitude(t, xs[k + 1, 6:9], xs[k + 1, 9:12], ATT_STD ** 2, RATE_STD ** 2)
            if (k + 1) % CAM_EVERY == 0 and k + 1 < 300:
                assert ekf.update_position(t, xs[k + 1, 0:3], cov)[0]
            if k + 1 == 315:
                for j in order:
                    assert ekf.update_position(j * DT, fixes[j], cov)[0]
        return ekf

    a, b = run((300, 305)), run((305, 300))
    # linear in the measurement up to re-linearisation: the two orders agree closely
    np.testing.assert_allclose(a.x[0:6], b.x[0:6], atol=1e-4)
    np.testing.assert_allclose(a.position_cov, b.position_cov, rtol=1e-3)


# --------------------------------------------------------------------------- the flip
def test_attitude_innovation_is_wrapped_through_inversion():
    ekf = PositionEKF(VEH, dt=DT)
    ekf.initialize(0.0, [0.0, 0.0, 5.0], euler=(math.pi - 0.01, 0.0, 0.0))
    # the attitude level reports -179.4 deg: 1.2 deg away, not 358.8
    assert ekf.update_attitude(0.0, [-math.pi + 0.01, 0.0, 0.0], np.zeros(3), [1e-4] * 3, [1e-3] * 3)
    assert abs(abs(ekf.euler[0]) - math.pi) < 0.02


def test_pinned_attitude_drives_the_prediction_and_survives_a_delayed_fix():
    ekf = PositionEKF(VEH, dt=DT)
    ekf.initialize(0.0, [0.0, 0.0, 5.0])
    hover = np.array([VEH.mass_kg * VEH.gravity_m_s2, 0.0, 0.0, 0.0])
    t = 0.0
    assert ekf.pin_attitude(t, [math.pi, 0.0, 0.0], [0.0, 0.0, 0.0])
    for k in range(10):   # inverted, hover thrust: the thrust points down, 2 g down
        t = (k + 1) * DT
        ekf.predict(t, hover)
        assert ekf.pin_attitude(t, [math.pi, 0.0, 0.0], [0.0, 0.0, 0.0])
    assert ekf.euler == pytest.approx([-math.pi, 0.0, 0.0], abs=1e-9)
    assert ekf.velocity[2] == pytest.approx(-2 * VEH.gravity_m_s2 * 0.1, rel=0.03)
    assert ekf.accepted("pin") == 11 and ekf.accepted("attitude") == 0
    # a camera fix from 50 ms ago replays the predictions; the pins are re-applied there
    ok, _ = ekf.update_position(t - 0.05, ekf.position, np.eye(3) * 1e-4)
    assert ok and ekf.euler == pytest.approx([-math.pi, 0.0, 0.0], abs=1e-9)


# --------------------------------------------------------------------------- motor input
def test_lagged_motor_input_is_the_mean_of_the_plants_lag_over_every_command():
    """The mean force over a 10 ms step equals the plant's motor lag integrated finely
    under the same 400 Hz commands, each held from its stamp; a command stamped at the
    step's end waits for the next step; the old way (latest command only) is far off."""
    tau, tick = 0.02, 0.0025
    rng = np.random.default_rng(3)
    commands = [(k * tick, rng.uniform(0.0, 6.5, 4)) for k in range(41)]  # 0 .. 100 ms
    lag = LaggedMotorInput(tau)
    lag.add(*commands[0])
    fine, force, sub = [], commands[0][1].copy(), 400
    for t0, c in commands[:-1]:  # the plant: Euler on a fine grid, each command held a tick
        for _ in range(sub):  # the rotor speed lags (sqrt(f) ~ speed, flight/motor_model.py)
            root = np.sqrt(force)
            root = root + (np.sqrt(c) - root) * (tick / sub) / tau
            force = root * root
            fine.append(force.copy())
    fine = np.array(fine)
    per_step = 4 * sub
    for step in range(10):
        t_end = (step + 1) * 0.01
        for t_cmd, c in commands:
            if step * 0.01 < t_cmd <= t_end:
                lag.add(t_cmd, c)
        mean = lag.mean_to(t_end)
        expected = fine[step * per_step:(step + 1) * per_step].mean(axis=0)
        np.testing.assert_allclose(mean, expected, atol=2e-3)
        np.testing.assert_allclose(lag.forces, fine[(step + 1) * per_step - 1], atol=2e-3)
    # the latest command lagged over the whole step (the former input) misses by ~0.5 N
    latest = commands[4][1]
    old = commands[0][1] + (latest - commands[0][1]) * (1 - math.exp(-0.01 / tau))
    assert np.max(np.abs(old - fine[:per_step].mean(axis=0))) > 0.3


def test_lagged_motor_input_late_and_degenerate():
    lag = LaggedMotorInput(0.02)
    np.testing.assert_array_equal(lag.mean_to(1.0), np.zeros(4))  # nothing sent: nothing flown
    lag.add(1.0, [2.0] * 4)
    np.testing.assert_allclose(lag.mean_to(1.01), [2.0] * 4)      # steady: the command itself
    lag.add(1.005, [4.0] * 4)  # older than the forces integrated: holds from now on
    mean = lag.mean_to(1.02)
    assert 2.0 < mean[0] < 4.0 and lag.t == 1.02
    np.testing.assert_array_equal(lag.mean_to(1.02), lag.forces)  # no time: the forces now
    with pytest.raises(PositionEKFError, match="time_constant_s"):
        LaggedMotorInput(0.0)


# --------------------------------------------------------------------------- the plain-float rewrite
# The filter before its arithmetic went to plain floats and fewer numpy calls (a2ef311),
# kept as the reference the rewrite must reproduce: the same equations, so the same
# numbers to rounding (here bit for bit; 1e-9 is the bound held).
def _ref_f(x, u, vehicle):
    _, _, _, vx, vy, vz, r, p, y, wx, wy, wz = list(x)
    u1, u2, u3, u4 = list(u)
    m, c = vehicle.mass_kg, vehicle.drag_n_per_m_s
    ixx, iyy, izz = vehicle.inertia_kg_m2
    sr, cr, sp, cp, sy, cy = math.sin(r), math.cos(r), math.sin(p), math.cos(p), math.sin(y), math.cos(y)
    a, k, tp = u1 / m, c / m, sp / cp
    q = sr * wy + cr * wz
    return np.array([vx, vy, vz,
                     a * (sy * sr + cy * cr * sp) - k * vx,
                     a * (-cy * sr + sy * cr * sp) - k * vy,
                     a * (cr * cp) - k * vz - vehicle.gravity_m_s2,
                     wx + tp * q, cr * wy - sr * wz, q / cp,
                     (u2 - (izz - iyy) * wy * wz) / ixx,
                     (u3 - (ixx - izz) * wz * wx) / iyy,
                     (u4 - (iyy - ixx) * wx * wy) / izz])


def _ref_jacobian(x, u, vehicle):
    _, _, _, _, _, _, r, p, y, wx, wy, wz = list(x)
    m = vehicle.mass_kg
    k = vehicle.drag_n_per_m_s / m
    ixx, iyy, izz = vehicle.inertia_kg_m2
    sr, cr, sp, cp, sy, cy = math.sin(r), math.cos(r), math.sin(p), math.cos(p), math.sin(y), math.cos(y)
    a, tp = float(u[0]) / m, sp / cp
    q, qd = sr * wy + cr * wz, cr * wy - sr * wz
    J = np.zeros((12, 12))
    J[0, 3] = J[1, 4] = J[2, 5] = 1.0
    J[3, 3] = J[4, 4] = J[5, 5] = -k
    J[3, 6], J[3, 7], J[3, 8] = a * (sy * cr - cy * sr * sp), a * (cy * cr * cp), a * (cy * sr - sy * cr * sp)
    J[4, 6], J[4, 7], J[4, 8] = a * (-cy * cr - sy * sr * sp), a * (sy * cr * cp), a * (sy * sr + cy * cr * sp)
    J[5, 6], J[5, 7] = -a * sr * cp, -a * cr * sp
    J[6, 6], J[6, 7], J[6, 9], J[6, 10], J[6, 11] = tp * qd, q / (cp * cp), 1.0, sr * tp, cr * tp
    J[7, 6], J[7, 10], J[7, 11] = -q, cr, -sr
    J[8, 6], J[8, 7], J[8, 10], J[8, 11] = qd / cp, q * sp / (cp * cp), sr / cp, cr / cp
    J[9, 10], J[9, 11] = -(izz - iyy) * wz / ixx, -(izz - iyy) * wy / ixx
    J[10, 9], J[10, 11] = -(ixx - izz) * wz / iyy, -(ixx - izz) * wx / iyy
    J[11, 9], J[11, 10] = -(iyy - ixx) * wy / izz, -(iyy - ixx) * wx / izz
    return J


def _ref_rk4(x, u, vehicle, dt):
    x, u = np.asarray(x, dtype=float), np.asarray(u, dtype=float)
    k1 = _ref_f(x, u, vehicle)
    k2 = _ref_f(x + 0.5 * dt * k1, u, vehicle)
    k3 = _ref_f(x + 0.5 * dt * k2, u, vehicle)
    k4 = _ref_f(x + dt * k3, u, vehicle)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def _ref_discretize(x, u, vehicle, dt, q_density=None):
    x, u = np.asarray(x, dtype=float), np.asarray(u, dtype=float)
    if x.shape[0] == 12:
        x_next, A = _ref_rk4(x, u, vehicle, dt), _ref_jacobian(x, u, vehicle) * dt
    else:
        u_real = u.copy()
        u_real[0] *= x[12]
        x_next = x.copy()
        x_next[:12] = _ref_rk4(x[:12], u_real, vehicle, dt)
        J = np.zeros((13, 13))
        J[:12, :12] = _ref_jacobian(x[:12], u_real, vehicle)
        r, p, y = x[6:9]
        sr, cr, sp, cp, sy, cy = math.sin(r), math.cos(r), math.sin(p), math.cos(p), math.sin(y), math.cos(y)
        J[3:6, 12] = (u[0] / vehicle.mass_kg) * np.array([sy * sr + cy * cr * sp, -cy * sr + sy * cr * sp, cr * cp])
        A = J * dt
    F = np.eye(x.shape[0]) + A + 0.5 * (A @ A)
    Q = None if q_density is None else np.diag(np.asarray(q_density, dtype=float) * dt)
    return x_next, F, Q


def _ref_wrap(v):
    return (v + math.pi) % (2 * math.pi) - math.pi


class _RefEKF:
    """PositionEKF as it was (predict, the three measurement kinds, replay), numpy throughout."""

    def __init__(self, vehicle, params=None, dt=DT):
        from scipy.stats import chi2
        self.vehicle, self.params, self.dt = vehicle, params or PositionEKFParams(), dt
        self._qc = self.params.process_noise_density[:13]   # without the disturbance's states
        p = self.params.gate_probability
        self._gate = {n: (math.inf if p >= 1.0 else float(chi2.ppf(p, n))) for n in (2, 3, 6)}
        self._eps = 1e-6 * dt
        self.counts = {k: {"accepted": 0, "gate": 0, "too_old": 0, "future": 0, "invalid": 0}
                       for k in ("attitude", "position", "pin", "drag")}
        self.last_nis = {}

    def initialize(self, t, position, euler):
        x = np.zeros(13)
        x[0:3], x[6:9], x[12] = position, euler, 1.0
        x[6], x[8] = _ref_wrap(x[6]), _ref_wrap(x[8])
        P = self.params.initial_covariance[:13, :13]
        self.t, self.x, self.P = float(t), x, 0.5 * (P + P.T)
        self.hist = [[self.t, None, x.copy(), self.P.copy(), []]]  # t, u, prior x, prior P, measurements

    def predict(self, t, u):
        u = np.array(u, dtype=float)
        self.x, self.P = self._propagate(self.x, self.P, u, float(t) - self.t)
        self.t = float(t)
        self.hist.append([self.t, u, self.x.copy(), self.P.copy(), []])
        horizon = self.t - self.params.max_delay_s + self._eps
        drop = 0
        while drop + 1 < len(self.hist) and self.hist[drop + 1][0] <= horizon:
            drop += 1
        del self.hist[:drop]

    def update_attitude(self, t, euler, rates, euler_var, rate_var):
        return self._fuse("attitude", float(t), np.r_[euler, rates], np.diag(np.r_[euler_var, rate_var]))[0]

    def pin_attitude(self, t, euler, rates):
        return self._fuse("pin", float(t), np.r_[euler, rates], None)[0]

    def update_position(self, t, position, cov):
        R = np.array(cov, dtype=float)
        return self._fuse("position", float(t), np.array(position, dtype=float), 0.5 * (R + R.T))

    def _propagate(self, x, P, u, h):
        n = max(1, math.ceil(h / self.dt - 1e-6))
        for _ in range(n):
            x, F, Q = _ref_discretize(x, u, self.vehicle, h / n, self._qc)
            P = F @ P @ F.T + Q
        P = 0.5 * (P + P.T)
        x[6], x[8] = _ref_wrap(x[6]), _ref_wrap(x[8])
        if x[2] <= 0.0:
            x[2], x[5] = 0.0, max(x[5], 0.0)
            if u[0] * x[12] < self.vehicle.mass_kg * self.vehicle.gravity_m_s2:
                x[3:6] = 0.0
        return x, P

    @staticmethod
    def _innovate(kind, x, P, z, R, offset):
        if kind == "position":
            H = np.zeros((3, 13))
            H[:, 0:3] = np.eye(3)
            if offset:
                H[:, 3:6] = offset * np.eye(3)
            y = z - (x[0:3] + offset * x[3:6])
        else:
            H = np.zeros((6, 13))
            H[:, 6:12] = np.eye(6)
            y = z - x[6:12]
            y[0:3] = _ref_wrap(y[0:3])
        return y, H, H @ P @ H.T + R

    @staticmethod
    def _correct(x, P, y, H, S_inv, R):
        K = P @ H.T @ S_inv
        x = x + K @ y
        IKH = np.eye(13) - K @ H
        P = IKH @ P @ IKH.T + K @ R @ K.T
        x[6], x[8] = _ref_wrap(x[6]), _ref_wrap(x[8])
        x[12] = min(max(x[12], 0.5), 2.0)
        return x, 0.5 * (P + P.T)

    def _apply(self, x, P, meas):
        kind, z, R, offset = meas
        if kind == "pin":
            x = x.copy()
            x[6:12] = z
            x[6], x[8] = _ref_wrap(x[6]), _ref_wrap(x[8])
            return x, P
        y, H, S = self._innovate(kind, x, P, z, R, offset)
        return self._correct(x, P, y, H, np.linalg.inv(S), R)

    def _reject(self, kind, reason, nis=math.nan):
        self.counts[kind][reason] += 1
        self.last_nis[kind] = nis
        return False, nis

    def _fuse(self, kind, t, z, R):
        if not (math.isfinite(t) and np.all(np.isfinite(z)) and (R is None or np.all(np.isfinite(R)))):
            return self._reject(kind, "invalid")
        if t > self.t + self._eps:
            return self._reject(kind, "future")
        if t < self.t - self.params.max_delay_s - self._eps or t < self.hist[0][0] - self._eps:
            return self._reject(kind, "too_old")
        j = len(self.hist) - 1
        while self.hist[j][0] > t + self._eps:
            j -= 1
        node = self.hist[j]
        offset = t - node[0] if t - node[0] > self._eps else 0.0
        if j == len(self.hist) - 1:
            x, P = self.x, self.P
        else:
            x, P = node[2].copy(), node[3].copy()
            for meas in node[4]:
                x, P = self._apply(x, P, meas)
        if kind == "pin":
            nis = math.nan
            x, P = self._apply(x, P, (kind, z, None, offset))
        else:
            y, H, S = self._innovate(kind, x, P, z, R, offset)
            S_inv = np.linalg.inv(S)
            nis = float(y @ S_inv @ y)
            if nis > self._gate[len(z)]:
                return self._reject(kind, "gate", nis)
            x, P = self._correct(x, P, y, H, S_inv, R)
        node[4].append((kind, z.copy(), None if R is None else R.copy(), offset))
        for k in range(j + 1, len(self.hist)):
            nk = self.hist[k]
            x, P = self._propagate(x, P, nk[1], nk[0] - self.hist[k - 1][0])
            nk[2], nk[3] = x.copy(), P.copy()
            for meas in nk[4]:
                x, P = self._apply(x, P, meas)
        self.x, self.P = x, P
        self.counts[kind]["accepted"] += 1
        self.last_nis[kind] = nis
        return True, nis


class _RefLaggedMotorInput:
    """LaggedMotorInput as it was (numpy 4-vectors), its lag on the rotor speed (issue 26)."""

    def __init__(self, tau):
        self.tau, self.forces, self.command, self.t, self.pending = tau, np.zeros(4), np.zeros(4), None, []

    def add(self, t_s, command_n):
        c = np.asarray(command_n, dtype=float).reshape(4)
        if self.t is None:
            self.t, self.forces, self.command = float(t_s), c.copy(), c
        elif t_s <= self.t:
            self.command = c
        else:
            self.pending.append((float(t_s), c))

    def mean_to(self, t_s):
        if self.t is None or t_s <= self.t:
            return self.forces.copy()
        self.pending.sort(key=lambda e: e[0])
        total, start = np.zeros(4), self.t
        while True:
            end = self.pending[0][0] if self.pending and self.pending[0][0] < t_s else t_s
            h = end - self.t
            if h > 0.0:
                decay = math.exp(-h / self.tau)
                sc = np.sqrt(np.maximum(self.command, 0.0))
                e = np.sqrt(np.maximum(self.forces, 0.0)) - sc
                w1 = self.tau / h * (1.0 - decay)
                w2 = 0.5 * self.tau / h * (1.0 - decay * decay)
                total += h * (sc * sc + 2.0 * sc * e * w1 + e * e * w2)
                self.forces = (sc + e * decay) ** 2
                self.t = end
            if end >= t_s:
                break
            self.command = self.pending.pop(0)[1]
        return total / (t_s - start)


def _assert_same(new, ref, what):
    new, ref = np.asarray(new, dtype=float), np.asarray(ref, dtype=float)
    scale = max(1.0, float(np.max(np.abs(ref))))
    np.testing.assert_allclose(new, ref, rtol=1e-9, atol=1e-12 * scale, err_msg=what)


def test_model_step_equals_the_reference():
    """rk4_step and discretize (12 states, and the filter's with the thrust scale, the
    disturbance and the accelerometer's bias 0) as before the rewrite (the reference's 13 states:
    the 14th to 17th, the disturbance and the bias, are what it does not have)."""
    rng = np.random.default_rng(11)
    veh_unequal = dataclasses.replace(VEH, inertia_kg_m2=(5e-3, 8e-3, 14e-3))
    for veh in (VEH, veh_unequal):
        for _ in range(30):
            x = _random_state(rng)
            u = np.array([rng.uniform(0.0, 10.0), *rng.normal(scale=0.05, size=3)])
            dt = float(rng.uniform(1e-3, 2e-2))
            _assert_same(rk4_step(x, u, veh, dt), _ref_rk4(x, u, veh, dt), "rk4_step")
            for xx in (x, np.r_[x, rng.uniform(0.6, 1.5)]):
                n = xx.shape[0]
                q = rng.uniform(0.0, 1.0, n)
                full = np.r_[xx, 0.0, 0.0, 0.0, 0.0] if n > 12 else xx
                for new, ref, name in zip(discretize(full, u, veh, dt, np.r_[q, 0.0, 0.0, 0.0, 0.0] if n > 12 else q),
                                          _ref_discretize(xx, u, veh, dt, q), ("x_next", "F", "Q")):
                    new = new[:n] if new.ndim == 1 else new[:n, :n]
                    _assert_same(new, ref, f"discretize {name} ({n} states)")
            np.testing.assert_array_equal(f(x, u, veh), _ref_f(x, u, veh))
            np.testing.assert_array_equal(jacobian_f(x, u, veh), _ref_jacobian(x, u, veh))


def _equivalence_flight(new, ref):
    """Fly both filters through the same 8 s: the step manoeuvre, attitude at 100 Hz (jittered
    time stamps, one 20 ms gap: two substeps), pinned attitude for 0.1 s, an attitude sample
    fused 20 ms late, camera fixes 50 ms late, two out of order, one between two nodes, one
    outlier, one too old, one from the future; compares state, covariance and answers at every step."""
    xs, us = _truth(0)
    rng = np.random.default_rng(21)
    for e in (new, ref):
        e.initialize(0.0, xs[0, 0:3] + [0.01, -0.02, 0.005], xs[0, 6:9])
    cam_cov = np.eye(3) * CAM_STD ** 2 + 1e-7
    pending, late_att = [], None
    for k in range(len(us)):
        if k == 300:
            continue  # no step at 3.01 s: the next predict covers 20 ms
        t = (k + 1) * DT + (5e-9 * rng.uniform() if k % 3 else 0.0)  # time-stamp jitter, < 1e-6 dt
        xt = xs[k + 1]
        for e in (new, ref):
            e.predict(t, us[k])
        euler = xt[6:9] + rng.normal(size=3) * ATT_STD
        rates = xt[9:12] + rng.normal(size=3) * RATE_STD
        if 500 <= k < 510:
            answers = [e.pin_attitude(t, euler, rates) for e in (new, ref)]
        elif k == 600:
            late_att = (t, euler, rates)
            answers = []
        else:
            answers = [e.update_attitude(t, euler, rates, ATT_STD ** 2, RATE_STD ** 2) for e in (new, ref)]
            if k == 602:
                answers += [e.update_attitude(late_att[0], late_att[1], late_att[2], ATT_STD ** 2, RATE_STD ** 2)
                            for e in (new, ref)]
        assert answers[0::2] == answers[1::2], k
        if (k + 1) % CAM_EVERY == 0:
            z = xt[0:3] + rng.normal(scale=CAM_STD, size=3)
            if k + 1 == 450:
                z = z + [0.5, 0.0, 0.0]  # gated out
            t_exp = t + 0.004 if k + 1 == 350 else t  # between two nodes: h = p + d v
            pending.append((k + 1 + (12 if k + 1 == 700 else 5), t_exp, z))
        if k + 1 == 250:
            pending.append((k + 1, t - 0.5, xt[0:3]))  # too old
            pending.append((k + 1, t + 0.05, xt[0:3]))  # not taken yet
        for item in sorted((p for p in pending if p[0] <= k + 1), key=lambda p: p[1]):
            pending.remove(item)
            (ok_n, nis_n), (ok_r, nis_r) = (e.update_position(item[1], item[2], cam_cov) for e in (new, ref))
            assert ok_n == ok_r, (k, item[1])
            if not math.isnan(nis_r):
                assert nis_n == pytest.approx(nis_r, rel=1e-9), k
        _assert_same(new.x[:13], ref.x, f"x at step {k}")
        _assert_same(new.P[:13, :13], ref.P, f"P at step {k}")
        assert new.x[13:].tolist() == [0.0] * 4   # no disturbance, no bias: they stay none
    return new, ref


def test_filter_equals_the_reference_through_a_flight():
    new, ref = _equivalence_flight(PositionEKF(VEH, NO_DISTURBANCE, dt=DT), _RefEKF(VEH, dt=DT))
    assert new._gate == pytest.approx(ref._gate, rel=1e-12)
    assert new.counters == ref.counts
    assert new.counters["position"]["gate"] == 1 and new.counters["position"]["too_old"] == 1
    assert new.counters["position"]["future"] == 1 and new.counters["pin"]["accepted"] == 10
    assert new.counters["position"]["accepted"] > 140 and new.counters["attitude"]["accepted"] > 700
    for kind in ("attitude", "position"):
        assert new.last_nis[kind] == pytest.approx(ref.last_nis[kind], rel=1e-9)


def test_gate_thresholds_equal_scipys_chi_square_quantiles():
    from scipy.stats import chi2

    from flight.estimation.position_ekf import _chi2_ppf
    for dof in range(1, 9):
        for p in (0.5, 0.9, 0.95, 0.99, 0.999, 0.9999, 1 - 1e-7):
            assert _chi2_ppf(p, dof) == pytest.approx(float(chi2.ppf(p, dof)), rel=1e-12), (dof, p)
    for p in (0.99, 0.999):
        assert PositionEKF(VEH, PositionEKFParams(gate_probability=p))._gate == pytest.approx(
            {n: float(chi2.ppf(p, n)) for n in (2, 3, 6)}, rel=1e-12)
    assert PositionEKF(VEH, PositionEKFParams(gate_probability=1.0))._gate == {2: math.inf, 3: math.inf, 6: math.inf}


def test_filter_module_does_not_import_scipy_stats():
    import subprocess
    import sys
    code = "import sys, flight.estimation.position_ekf; sys.exit('scipy.stats' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_lagged_motor_input_equals_the_reference():
    rng = np.random.default_rng(31)
    new, ref = LaggedMotorInput(0.02), _RefLaggedMotorInput(0.02)
    for step in range(60):
        for j in range(int(rng.integers(0, 6))):
            t_cmd = step * 0.01 + float(rng.uniform(-0.004, 0.012))
            c = rng.uniform(0.0, 6.5, 4)
            new.add(t_cmd, c.tolist() if j % 2 else c)
            ref.add(t_cmd, c)
        t = (step + 1) * 0.01
        _assert_same(new.mean_to(t), ref.mean_to(t), f"mean at step {step}")
        _assert_same(new.forces, ref.forces, f"forces at step {step}")
        assert new.t == ref.t


def test_quat_tilt():
    from flight.quat import quat_tilt, quat_to_rotation
    rng = np.random.default_rng(41)
    for _ in range(200):
        q = rng.normal(size=4)
        q = q / np.linalg.norm(q)
        assert quat_tilt(q.tolist()) == quat_tilt(q)
        assert quat_tilt(q) == pytest.approx(math.acos(np.clip(quat_to_rotation(q)[2, 2], -1, 1)), abs=1e-7)
    assert quat_tilt([1.0, 0.0, 0.0, 0.0]) == 0.0 and quat_tilt([0.0, 1.0, 0.0, 0.0]) == pytest.approx(math.pi)


def _former_pair(params=None):
    """This filter without the disturbance states' noise (they stay 0) and the filter as of
    6b2add1 (bench/support/position_ekf_reference.py: every prediction run when asked for,
    every delayed measurement re-running the ones after it; no disturbance states)."""
    from bench.support.position_ekf_reference import PositionEKF as FormerEKF
    from bench.support.position_ekf_reference import PositionEKFParams as FormerParams
    params = dataclasses.replace(params or PositionEKFParams(), q_disturbance_m2_s5=0.0,
                                 init_std_disturbance_m_s2=0.0)
    former = {k: v for k, v in dataclasses.asdict(params).items() if k in FormerParams.__dataclass_fields__}
    return PositionEKF(VEH, params, dt=DT), FormerEKF(VEH, FormerParams(**former), dt=DT)


def _assert_identical(new, old, what):
    """The former filter's 13 states and their covariance, to the last bits (the products of
    15 x 15 matrices, whose added terms are exact zeros, sum in another order), and the
    disturbance none."""
    np.testing.assert_allclose(new.x[:13], old.x, rtol=1e-12, atol=1e-14, err_msg=what)
    np.testing.assert_allclose(new.P[:13, :13], old.P, rtol=1e-10, atol=1e-18, err_msg=what)
    assert new.x[13:].tolist() == [0.0] * 4, what
    np.testing.assert_allclose(new.position_cov, old.position_cov, rtol=1e-10, atol=1e-18, err_msg=what)
    counters = {k: v for k, v in new.counters.items() if k != "drag"}   # a kind the former filter lacks
    last_nis = {k: v for k, v in new.last_nis.items() if k != "drag"}
    assert counters == old.counters and last_nis == pytest.approx(old.last_nis, nan_ok=True, rel=0), what


def test_filter_equals_the_former_filter_to_rounding():
    """The predictions re-run only when the state is read (_current) and the rest of the
    rewrite give the former filter's numbers exactly: in the flight's pattern (each attitude
    state 5 ms old, so fused a node back; camera fixes 60 ms old), with the state read only
    every few steps, attitude states at the newest node, a pin, fixes gated out or fused at
    stale nodes, two fixes in one step, a 20 ms step (two substeps) and a reset."""
    xs, us = _truth(0, duration=4.0)
    rng = np.random.default_rng(5)
    new, old = _former_pair()
    for e in (new, old):
        e.initialize(0.0, xs[0, 0:3] + [0.01, -0.02, 0.005], xs[0, 6:9])
    cam_cov = np.eye(3) * CAM_STD ** 2 + 1e-7
    fixes = []
    for k in range(len(us)):
        if k == 150:
            continue  # a 20 ms step
        t = (k + 1) * DT
        xt = xs[k + 1]
        for e in (new, old):
            e.predict(t, us[k])
        euler = (xt[6:9] + rng.normal(size=3) * ATT_STD).tolist()
        rates = (xt[9:12] + rng.normal(size=3) * RATE_STD).tolist()
        t_att = t - 0.005   # the attitude state of t - 5 ms: nearest node not after it is the one before
        if 250 <= k < 260:
            t_att = t   # at the newest node, not yet run
        if 200 <= k < 205:
            answers = [e.pin_attitude(t_att, euler, rates) for e in (new, old)]
        else:
            answers = [e.update_attitude(t_att, euler, rates, (ATT_STD ** 2).tolist(), (RATE_STD ** 2).tolist())
                       for e in (new, old)]
        assert answers[0] == answers[1], k
        if (k + 1) % CAM_EVERY == 0:
            z = xt[0:3] + rng.normal(scale=CAM_STD, size=3)
            if k + 1 in (100, 260):
                z = z + [0.5, 0.0, 0.0]   # gated out (at a stale node: the state was not read since)
            fixes.append((k + 7 + (k == 299) * 5, t, z))   # 60 ms old; one 110 ms old, arriving with the next
        for due, t_exp, z in [f for f in fixes if f[0] <= k + 1]:
            fixes.remove((due, t_exp, z))
            answers = [e.update_position(t_exp, z, cam_cov) for e in (new, old)]
            assert answers[0][0] == answers[1][0] and answers[0][1] == pytest.approx(answers[1][1], rel=0, nan_ok=True)
        if k == 320:
            for e in (new, old):
                e.reset_position(xt[0:3], cam_cov)
        if k % 3 == 0 or k > 380:   # the state read only now and then
            _assert_identical(new, old, f"step {k}")
    _assert_identical(new, old, "end")
    assert new.counters["position"]["gate"] == 2 and new.counters["pin"]["accepted"] == 5
    assert new.counters["attitude"]["accepted"] > 300


def test_short_history_keeps_the_former_filters_numbers():
    """max_delay_s shorter than a step: each prediction drops the node before it at once, so
    it is run then, not left for later (the history never holds a stale node alone)."""
    xs, us = _truth(0, duration=0.5)
    new, old = _former_pair(PositionEKFParams(max_delay_s=0.0))
    for e in (new, old):
        e.initialize(0.0, xs[0, 0:3], xs[0, 6:9])
    for k in range(len(us)):
        t = (k + 1) * DT
        for e in (new, old):
            e.predict(t, us[k])
        assert len(new._hist) == len(old._hist) == 1
        assert [e.update_attitude(t, xs[k + 1, 6:9], xs[k + 1, 9:12], ATT_STD ** 2, RATE_STD ** 2)
                for e in (new, old)] == [True, True]
        _assert_identical(new, old, f"step {k}")


def test_lagged_motor_input_equals_the_former_one_bit_for_bit():
    from bench.support.position_ekf_reference import LaggedMotorInput as FormerLaggedMotorInput
    rng = np.random.default_rng(32)
    new, old = LaggedMotorInput(0.02), FormerLaggedMotorInput(0.02)
    for step in range(300):
        for j in range(int(rng.integers(0, 6))):
            t_cmd = step * 0.01 + float(rng.choice([0.0, 0.0025, 0.005, 0.0075, rng.uniform(-0.004, 0.012)]))
            c = rng.uniform(-0.5, 6.5, 4)   # some below zero: the root of a negative command is 0
            for e in (new, old):
                e.add(t_cmd, c.tolist())
        t = (step + 1) * 0.01
        assert new.mean_to(t).tolist() == old.mean_to(t).tolist(), step
        assert new.forces.tolist() == old.forces.tolist() and new.command.tolist() == old.command.tolist()
        assert new.t == old.t


def test_a_new_vehicle_applies_from_the_next_prediction():
    """Predictions left to run later (stale nodes) run with the vehicle they were made with:
    the same numbers as the former filter, which ran them at once."""
    heavy = dataclasses.replace(VEH, mass_kg=VEH.mass_kg * 1.2)
    xs, us = _truth(0, duration=0.3)
    new, old = _former_pair()
    for e in (new, old):
        e.initialize(0.0, xs[0, 0:3], xs[0, 6:9])
    for k in range(len(us)):
        t = (k + 1) * DT
        for e in (new, old):
            e.predict(t, us[k])
            if k == 20:
                e.vehicle = heavy
        _assert_identical(new, old, f"step {k}")


def test_a_reset_at_an_old_fix_leaves_room_for_the_way_moved_since():
    """reset_position at a fix age_s old: the position's variance is the camera's plus
    (velocity_std x age_s)^2, the velocity's velocity_std^2, no cross terms; the attitude kept."""
    ekf = PositionEKF(VEH, dt=DT)
    ekf.initialize(0.0, [0.0, 0.0, 1.0], [0.05, -0.02, 0.3])
    for k in range(1, 21):
        ekf.predict(k * DT, [VEH.mass_kg * VEH.gravity_m_s2, 0.0, 0.0, 0.0])
    cam = np.eye(3) * 1e-4
    ekf.reset_position([1.0, 2.0, 1.5], cam, velocity_std_m_s=1.0, age_s=0.12)
    P = ekf.P
    np.testing.assert_allclose(P[:3, :3], cam + np.eye(3) * 0.12 ** 2)
    np.testing.assert_allclose(P[3:6, 3:6], np.eye(3))
    assert not np.any(P[:6, 6:]) and not np.any(P[6:, :6])
    assert ekf.position.tolist() == [1.0, 2.0, 1.5]
    np.testing.assert_allclose(ekf.euler, [0.05, -0.02, 0.3], atol=1e-3)
    ekf.reset_position([1.0, 2.0, 1.5], cam)   # a fix of now: the camera's variance alone
    np.testing.assert_allclose(ekf.P[:3, :3], cam)
