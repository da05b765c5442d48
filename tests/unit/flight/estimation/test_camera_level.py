"""CameraLevel: the estimate's roll/pitch offset against the camera's attitude."""
import numpy as np
import pytest

from flight.estimation.camera_level import CameraLevel, CameraLevelParams
from flight.quat import quat_from_euler


def fly_level(level, bias, seconds=10.0, rate=0.0, noise_rad=0.0025, seed=0):
    """A vehicle swaying slowly in roll; the estimate is off by `bias` (roll, pitch); the camera
    sees the true attitude with noise, its frames (20 Hz) arriving 50 ms after exposure."""
    rng = np.random.default_rng(seed)
    pending = []
    for k in range(int(seconds * 200)):
        t = k / 200
        truth = np.array([0.1 * np.sin(0.5 * t), 0.05, 0.0])
        level.record(t, truth + [*bias, 0.0], [rate, 0.0, 0.0])
        if k % 10 == 0:
            seen = truth[:2] + rng.normal(0.0, noise_rad, 2)
            pending.append((t + 0.05, t, quat_from_euler(seen[0], seen[1], 0.0)))
        while pending and pending[0][0] <= t:
            _, exposure, q = pending.pop(0)
            level.fuse(exposure, q)


def test_offset_converges_to_the_estimates_bias():
    level = CameraLevel(CameraLevelParams(time_constant_s=2.0))
    fly_level(level, bias=(0.003, -0.002))
    np.testing.assert_allclose(level.offset_rad, [0.003, -0.002], atol=7e-4)
    assert level.fused > 150 and not level.rejected
    np.testing.assert_allclose(level.apply([0.103, 0.048, 1.0]), [0.1, 0.05, 1.0], atol=7e-4)


def test_frames_while_turning_or_out_of_history_are_rejected_not_fused():
    level = CameraLevel()
    fly_level(level, bias=(0.003, 0.0), seconds=2.0, rate=2.0)
    assert level.fused == 0 and level.rejected["camera_level_turning"] > 30
    assert np.all(level.offset_rad == 0.0)
    assert not level.fuse(100.0, [1.0, 0.0, 0.0, 0.0])
    assert level.rejected["camera_level_outside_history"] == 1
    assert not level.fuse(1.0, [np.nan, 0.0, 0.0, 0.0])
    assert level.rejected["camera_level_bad_quaternion"] == 1


def test_inconsistent_frame_is_gated():
    level = CameraLevel(CameraLevelParams(gate_rad=0.05))
    level.record(0.0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    level.record(0.01, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    assert not level.fuse(0.005, quat_from_euler(0.2, 0.0, 0.0))  # 11 deg off: a bad solve
    assert level.rejected == {"camera_level_inconsistent": 1}
    assert level.fuse(0.005, quat_from_euler(0.01, 0.0, 0.0))
    assert level.offset_rad[0] < 0


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match=r"CameraLevelParams.time_constant_s: 0.0 outside \(0, inf\) s"):
        CameraLevelParams(time_constant_s=0.0)
    with pytest.raises(ValueError, match=r"here.gate_rad: -0.1 outside \(0, inf\) rad"):
        CameraLevelParams.from_dict({"gate_rad": -0.1}, "here")
