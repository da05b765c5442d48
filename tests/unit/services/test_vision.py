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


def _rendered(position, quaternion, size=None):
    from simulator.sensors import ImageCamera
    cam = ImageCamera(SimConfig(camera_mode="image", camera_image_noise=1.0), np.random.default_rng(0))
    frame = cam.sample(position, quaternion, np.zeros(3), np.zeros(3))
    if size is not None:   # another camera's frame: cut to size
        img = np.frombuffer(frame["pixels"], np.uint8).reshape(480, 640)[:size[1], :size[0]]
        frame.update(width_px=size[0], height_px=size[1], pixels=img.tobytes())
    return frame


@pytest.mark.parametrize("method", ["hand", "opencv"])
def test_image_mode_pose_from_a_rendered_frame(method):
    """The image in, the same pose message out (exposure stamp, marker count), from either solver."""
    io = FakeIO("vision", PARAMS, {"pnp": method}, rate_hz=0.0)
    loop = VisionLoop(io)
    truth, q = np.array([0.3, -0.2, 1.2]), quat_from_euler(0.05, -0.03, 0.6)
    io.received(schemas.CAMERA_IMAGE, "sim").push(3.0, _rendered(truth, q))
    loop.step(3.05)
    [(t, pose)] = io.sent(schemas.VISION_POSE)
    assert t == 3.0 and pose["markers"] >= 4
    np.testing.assert_allclose(pose["position_m"], truth, atol=2e-3)
    assert np.sqrt(np.diag(np.reshape(pose["position_cov_m2"], (3, 3)))).max() < 0.01
    assert "images, markers found in 1 (100.0 %)" in loop.summary()


def test_an_image_of_another_size_is_counted_and_dropped_and_a_blank_one_has_no_markers():
    io = FakeIO("vision", PARAMS, {}, rate_hz=0.0)
    loop = VisionLoop(io)
    box = io.received(schemas.CAMERA_IMAGE, "sim")
    box.push(1.0, _rendered([0.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.0], size=(320, 240)))
    box.push(1.05, {"width_px": 640, "height_px": 480, "encoding": "mono8", "exposure_s": 0.004,
                    "pixels": bytes(640 * 480)})
    loop.step(1.1)
    assert io.sent(schemas.VISION_POSE) == []
    assert io.rejected == {"image_wrong_size": 1, "pose_no_markers": 1}
    assert any("320 x 240" in p for p in io.problems)


def test_opencv_and_hand_pnp_agree_on_the_same_corners():
    from flight.estimation.pnp import MarkerMap, solve_pose
    cam = MarkerCamera(SimConfig(), np.random.default_rng(1))
    frame = cam.sample(np.array([0.1, 0.2, 1.0]), quat_from_euler(0.1, 0.0, 1.0))
    markers = MarkerMap.grid(0.2, 0.5, 5.0)
    hand, cv = (solve_pose(cam.camera, markers, frame["marker_ids"], frame["corners_px"], method=m)
                for m in ("hand", "opencv"))
    assert hand.ok and cv.ok
    np.testing.assert_allclose(cv.position_m, hand.position_m, atol=1e-7)
    np.testing.assert_allclose(cv.covariance, hand.covariance, rtol=1e-5, atol=1e-12)


def test_a_crowded_view_is_searched_in_its_central_half_next_time():
    """At 5 m ~200 markers are in view: after such a frame the next is searched in its central 2/3
    (~80 markers, half the time), and the next (as many in view); with crop_above_markers 0, never."""
    truth, q = np.array([0.1, 0.05, 5.0]), quat_from_euler(0.02, 0.03, 0.3)
    frame = _rendered(truth, q)
    for crop_above, later in ((60, range(50, 110)), (0, range(150, 260))):
        io = FakeIO("vision", PARAMS, {"crop_above_markers": crop_above}, rate_hz=0.0)
        loop = VisionLoop(io)
        box = io.received(schemas.CAMERA_IMAGE, "sim")
        for t in (1.0, 1.05, 1.1):
            box.push(t, frame)
            loop.step(t)
        (_, first), (_, then), (_, third) = io.sent(schemas.VISION_POSE)
        assert first["markers"] > 150 and then["markers"] in later and third["markers"] in later, crop_above
        # fewer markers over a narrower view: a tilt error trades with a shift at 5 m; the covariance says so
        sigma = np.sqrt(np.diag(np.reshape(then["position_cov_m2"], (3, 3))))
        error = np.abs(np.asarray(then["position_m"]) - truth)
        assert error.max() < 0.01 and (error < 4 * sigma).all(), (error, sigma)
