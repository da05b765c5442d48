"""The camera delay's online estimate (flight/estimation/camera_delay.py), on synthetic fixes.

The synthetic filter: a Kalman filter per axis on [position, velocity] at 100 Hz, predicted with
the truth's own increments (the model's timing is right, as the EKF's attitude and thrust are), fed at
20 Hz with camera positions taken `offset` earlier than the time they are fused at (a stamp that
does not show the camera's real delay). It follows those late fixes as the EKF does, so its
innovations have the shape the estimator must see through (zero-mean at a constant velocity).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from flight.estimation.camera_delay import STD_CAP_S, CameraDelayError, CameraDelayEstimator, CameraDelayParams

DT = 0.01
CAM_EVERY = 5   # 20 Hz
CAM_STD = 0.003


MOVE_S, EVERY_S = 1.2, 3.0   # a 1 m minimum-jerk move every 3 s, x, y, z in turn, as a mission's steps


def _truth(t, moving):
    """Position, velocity, acceleration (3,) at t of a vehicle flying 1 m moves (or at rest)."""
    p, v, a = np.zeros(3), np.zeros(3), np.zeros(3)
    if not moving:
        return p, v, a
    k = int(t // EVERY_S)
    for j in range(k + 1):   # the moves done (a 1 m step each, back and forth) and the one under way
        axis, sign = j % 3, (1.0 if (j // 3) % 2 == 0 else -1.0)
        s = min(max((t - j * EVERY_S) / MOVE_S, 0.0), 1.0)
        p[axis] += sign * (10 * s**3 - 15 * s**4 + 6 * s**5)
        if 0.0 < s < 1.0:
            v[axis] += sign * (30 * s**2 - 60 * s**3 + 30 * s**4) / MOVE_S
            a[axis] += sign * (60 * s - 180 * s**2 + 120 * s**3) / MOVE_S**2
    return p, v, a


def fly(offset_s, seconds=30.0, moving=True, seed=0, params=None):
    """Run the synthetic filter. offset_s: a number, or a function of time. The fix fused at t was
    taken at t - (offset - correction): the correction, as the position level applies it, moves
    the fusion back towards the real time. Returns the estimator, the correction after each fix,
    the times of the detections, and what a regression of the innovations on the bare velocity
    (-v d, no sensitivity) would read."""
    offset = offset_s if callable(offset_s) else (lambda t: offset_s)
    est = CameraDelayEstimator(params)
    rng = np.random.default_rng(seed)
    x = np.zeros((3, 2))          # per axis [p, v]
    P = np.tile(np.diag([1e-4, 1e-2]), (3, 1, 1))
    F = np.array([[1.0, DT], [0.0, 1.0]])
    Q = np.diag([1e-6 * DT, 0.02 * DT])
    corrections, detections, naive = [], [], [0.0, 0.0]
    p0, v0, _ = _truth(0.0, moving)
    x[:, 0], x[:, 1] = p0, v0
    for n in range(1, int(round(seconds / DT)) + 1):
        t = n * DT
        # the model's input is exact: what the truth moved over the step beyond p' = v (the
        # EKF's attitude and thrust have the right timing; only the camera's is in question)
        (pa, va, _), (pb, vb, _) = _truth(t - DT, moving), _truth(t, moving)
        x = x @ F.T + np.stack([pb - pa - va * DT, vb - va], axis=1)
        P = F @ P @ F.T + Q
        if n % CAM_EVERY:
            continue
        z = _truth(t - (offset(t) - est.correction_s), moving)[0] + rng.normal(0.0, CAM_STD, 3)
        y = z - x[:, 0]
        K = P[:, :, 0] / (P[:, 0, 0] + CAM_STD ** 2)[:, None]   # per axis, [p, v]
        v = x[:, 1].copy()
        x = x + K * y[:, None]
        P = P - np.einsum("ai,aj->aij", K, P[:, 0, :])
        gain = np.zeros((6, 3))   # the EKF's K, rows of the position and the velocity
        gain[[0, 1, 2], [0, 1, 2]] = K[:, 0]
        gain[[3, 4, 5], [0, 1, 2]] = K[:, 1]
        if est.innovation(t, y, v, gain):
            detections.append(t)
        corrections.append(est.correction_s)
        naive[0] += float(v @ v)
        naive[1] -= float(v @ y)
    return est, corrections, detections, naive[1] / naive[0] if naive[0] else 0.0


@pytest.mark.parametrize("offset_s", [0.07, 0.04, -0.05])
def test_a_known_offset_is_recovered_through_a_filter_that_follows_the_late_fixes(offset_s):
    # 34.5 s: just after a move (a hold forgets what the moves taught, at forget_s)
    est, corrections, detections, naive = fly(offset_s, seconds=34.5, params=CameraDelayParams(correct=False))
    assert est.confident
    assert est.offset_s == pytest.approx(offset_s, abs=max(0.01, 3 * est.offset_std_s))
    assert len(detections) == est.detections == 1 and set(corrections) == {0.0}   # correct=False
    # why the sensitivity: the filter follows the late fixes, so its innovations are far smaller
    # than -v d, and a regression on the bare velocity reads a fraction of the offset
    assert abs(naive) < 0.5 * abs(offset_s)


@pytest.mark.parametrize("seed", range(4))
def test_no_false_detection_without_an_offset(seed):
    est, corrections, detections, _ = fly(0.0, seconds=61.5, seed=seed)
    assert detections == [] and set(corrections) == {0.0}
    assert abs(est.offset_s) < 0.01 and est.confident


def test_at_rest_nothing_is_learnt_nor_detected():
    est, corrections, detections, _ = fly(0.07, moving=False)
    assert not est.confident and est.offset_std_s == STD_CAP_S and detections == []
    assert set(corrections) == {0.0}


def test_the_correction_follows_rate_limited_and_bounded():
    params = CameraDelayParams(slew_s_s=0.1)
    est, corrections, detections, _ = fly(0.07, seconds=34.5, params=params)
    steps = np.abs(np.diff(corrections))
    assert steps.max() <= params.slew_s_s * CAM_EVERY * DT + 1e-12
    assert corrections[-1] == pytest.approx(0.07, abs=0.01)   # the fixes now fused at their real time
    # the fit sees the whole offset however much is corrected: it stays, and nothing more is detected
    assert est.offset_s == pytest.approx(0.07, abs=0.01) and len(detections) == 1
    _, corrections, _, _ = fly(0.12, params=CameraDelayParams(max_correction_s=0.08))
    assert max(corrections) == 0.08


def test_a_step_of_the_offset_is_detected_within_two_seconds_of_motion():
    # the step at 8.5 s, the next move at 9 s
    est, corrections, detections, _ = fly(lambda t: 0.07 if t >= 8.5 else 0.0, seconds=16.0)
    assert detections and 8.5 < detections[0] < 10.5
    assert corrections[-1] == pytest.approx(0.07, abs=0.01)


def test_fixes_left_out_of_the_fit_teach_nothing():
    est = CameraDelayEstimator()
    for k in range(100):
        t = 0.05 * k
        est.innovation(t, [0.07, -0.07, 0.0], [-1.0, 1.0, 0.0], None, fit=False)
    assert est.offset_std_s == STD_CAP_S and est.fitted == 0 and not est.confident


def test_transport_median_reports_one_step_and_ignores_jitter():
    est = CameraDelayEstimator()
    rng = np.random.default_rng(0)
    t = 0.0
    steps = []
    for k in range(200):   # 50 ms + up to 10 ms (the 100 Hz loop that takes the fix), a late one now and then
        t += 0.05
        d = (0.05 if k < 100 else 0.12) + rng.uniform(0.0, 0.01) + (0.08 if k % 17 == 0 else 0.0)
        if est.transport(t, t - d):
            steps.append(k)
    assert len(steps) == 1 and 100 <= steps[0] <= 100 + est.params.window // 2 + 1
    assert est.transport_s == pytest.approx(0.125, abs=0.006) and est.transport_steps == 1
    assert 0.0 < est.transport_spread_s < 0.1


def test_transport_before_a_full_window_reports_no_step():
    est = CameraDelayEstimator()
    assert math.isnan(est.transport_s) and est.transport_spread_s == 0.0
    assert not any(est.transport(0.05 * k + (0.3 if k > 3 else 0.0), 0.05 * k) for k in range(10))
    assert est.transport_level_s is None


def test_bad_inputs_and_parameters_are_refused_clearly():
    est = CameraDelayEstimator()
    with pytest.raises(CameraDelayError, match="finite"):
        est.transport(math.nan, 0.0)
    with pytest.raises(CameraDelayError, match="finite"):
        est.innovation(1.0, [math.inf, 0.0, 0.0], [0.0, 0.0, 0.0])
    with pytest.raises(CameraDelayError, match="window"):
        CameraDelayParams(window=1)
    with pytest.raises(CameraDelayError, match="no_such_key"):
        CameraDelayParams.from_dict({"no_such_key": 1.0})
