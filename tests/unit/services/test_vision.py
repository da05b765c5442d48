"""The vision service's logic (services/vision.py VisionLoop) without a router."""

import numpy as np
import pytest

import schemas
from flight.quat import quat_from_euler
from services.vision import PARAMS, VisionLoop
from simulator.config import SimConfig
from simulator.sensors import MarkerCamera
from tests.unit.services.fake_io import FakeIO


def test_a_pose_per_frame_at_its_exposure_time_and_empty_frames_counted():
    io = FakeIO("vision", PARAMS, {}, rate_hz=0.0)
    loop = VisionLoop(io)
    frames = io.received(schemas.CAMERA, "sim")
    cam = MarkerCamera(SimConfig(camera_pixel_noise_px=0.0), np.random.default_rng(0))
    truth = np.array([0.3, -0.2, 1.5])
    frame = cam.sample(truth, quat_from_euler(0.02, -0.01, 0.4))
    frames.push(2.0, {"marker_ids": frame["marker_ids"], "corners_px": frame["corners_px"]})
    frames.push(2.05, {"marker_ids": [], "corners_px": []})
    loop.step(2.1)
    [(t, pose)] = io.sent(schemas.VISION_POSE)
    assert t == 2.0 and pose["markers"] == len(frame["marker_ids"]) >= 4
    np.testing.assert_allclose(pose["position_m"], truth, atol=1e-6)
    assert io.rejected == {"pose_no_markers": 1}


def test_garbage_corners_give_no_pose_and_a_reason():
    io = FakeIO("vision", PARAMS, {}, rate_hz=0.0)
    loop = VisionLoop(io)
    io.received(schemas.CAMERA, "sim").push(1.0, {"marker_ids": [3], "corners_px": [0.0, 0.0] * 4})
    loop.step(1.0)
    assert io.sent(schemas.VISION_POSE) == []
    assert len(io.rejected) == 1 and next(iter(io.rejected)).startswith("pose_")


def test_a_bad_camera_parameter_is_refused_naming_the_key():
    with pytest.raises(Exception, match="camera_focal_px"):
        VisionLoop(FakeIO("vision", PARAMS, {"camera_focal_px": "wide"}, rate_hz=0.0))
