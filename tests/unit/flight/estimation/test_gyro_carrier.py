"""GyroCarrier: the quaternion the gyros carry through a flip, handed back near level."""
import math

import numpy as np
import pytest

from flight.estimation.gyro_carrier import GyroCarrier, GyroCarrierParams
from flight.quat import quat_from_euler, quat_tilt, quat_to_euler


def test_gyro_carrier_carries_a_full_roll_flip_and_hands_back():
    c = GyroCarrier()
    dt, t = 1.0 / 400, 0.0
    c.follow(t, quat_from_euler(0.02, -0.01, 0.5), np.zeros(3))
    assert not c.check_enter(c.q, np.array([1.0, 0.5, 0.0]))  # normal flight: follows the 000 filter
    # a 360-deg roll at up to 20 rad/s (triangular rate profile over 0.63 s), biased gyro
    n = 252
    peak = 2 * math.pi / (0.5 * n * dt)
    bias = np.array([3e-3, -3e-3, 2e-3])
    tilts, roll_true, w_prev = [], 0.02, 0.0
    for k in range(1, n + 1):
        t = k * dt
        w = peak * (k / (n / 2) if k <= n / 2 else (n - k) / (n / 2))
        roll_true += 0.5 * (w + w_prev) * dt
        w_prev = w
        gyro = np.array([w, 0.0, 0.0]) + bias
        if not c.active:   # the 000 filter (here: the truth) is followed until the rate is too high
            q_filter = quat_from_euler(roll_true, -0.01, 0.5)
            c.follow(t, q_filter, gyro)
            assert c.check_enter(q_filter, gyro) == (w + bias[0] > 6.0)
            continue
        c.propagate(t, gyro)
        tilts.append(quat_tilt(c.q))
    assert c.active and c.activations == 1 and max(tilts) > math.radians(178)
    roll, pitch, yaw = quat_to_euler(c.q)
    assert abs(roll - 0.02) < math.radians(1.0) and abs(pitch + 0.01) < math.radians(1.0)
    assert abs(yaw - 0.5) < math.radians(1.0)
    assert c.back_near_level()
    q, rate = c.estimate(t + 0.01, 0.05)   # carried over the delay by the newest gyro
    assert rate == pytest.approx(c.gyro) and np.linalg.norm(q) == pytest.approx(1.0)


def test_gyro_carrier_rejects_bad_thresholds():
    with pytest.raises(ValueError, match="exit_tilt_deg <= enter_tilt_deg"):
        GyroCarrierParams(enter_tilt_deg=20.0, exit_tilt_deg=30.0)
    with pytest.raises(ValueError, match=r"here: GyroCarrierParams: need exit_tilt_deg"):
        GyroCarrierParams.from_dict({"exit_rate_rad_s": 7.0}, "here")
    with pytest.raises(ValueError, match=r"GyroCarrierParams.enter_tilt_deg: 200.0 outside \(0, 180\] deg"):
        GyroCarrierParams(enter_tilt_deg=200.0)
