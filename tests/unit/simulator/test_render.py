"""The image mode's renderer (simulator/render.py) against the corner mode's projection, and the
detector (flight/estimation/markers.py) on its images."""

import cv2
import numpy as np
import pytest

from flight.camera import DEFAULT_CAMERA, Intrinsics, marker_grid
from flight.estimation.markers import MarkerDetector
from flight.quat import quat_from_rotation
from simulator.config import SimConfig
from simulator.render import FloorRenderer, _rot_exp
from simulator.sensors import MarkerCamera
from simulator.world import Simulator
from flight.vehicle import load_vehicle

IDS, CORNERS = marker_grid(0.2, 0.5, 5.0)


@pytest.fixture(scope="module")
def renderer():
    return FloorRenderer.markers(Intrinsics.of(DEFAULT_CAMERA), IDS, CORNERS, noise_grey=0.0)


def corner_mode(position, r_wb):
    """What the corner mode sends for this pose, noise-free: {id: (4, 2) pixels}."""
    cam = MarkerCamera(SimConfig(camera_pixel_noise_px=0.0), np.random.default_rng(0))
    frame = cam.sample(position, quat_from_rotation(r_wb))
    return dict(zip(frame["marker_ids"], np.reshape(frame["corners_px"], (-1, 4, 2))))


@pytest.mark.parametrize("altitude_m, tilt", [(1.0, (0.0, 0.0, 0.0)), (1.3, (0.25, -0.15, 2.0)),
                                              (5.0, (0.1, 0.2, -0.7))])
def test_markers_are_rendered_where_the_corner_mode_projects_them(renderer, altitude_m, tilt):
    """With the lens's distortion undone, every corner within a pixel (half a pixel at hover) of the
    corner mode's pinhole projection, unbiased, and the markers the corner mode sees whole away from
    the edge found."""
    p, r_wb = np.array([0.13, -0.21, altitude_m]), _rot_exp(tilt)
    image = renderer.render(p, r_wb, np.zeros(3), np.zeros(3), 0.0, None)
    ids, corners = MarkerDetector(renderer.intr, len(IDS)).detect(image)
    truth = corner_mode(p, r_wb)
    inner = {i for i, c in truth.items() if (c.min(axis=0) > 8).all() and (c.max(axis=0) < [632, 472]).all()}
    near = altitude_m < 2
    # at hover every one; at 5 m, 16 px markers seen at a slant, nine in ten
    assert inner and (inner <= set(ids) if near else len(inner & set(ids)) >= 0.9 * len(inner))
    errors = np.concatenate([(c - truth[i]).ravel() for i, c in zip(ids, corners) if i in truth])
    if near:
        assert np.abs(errors).max() < 0.5
    else:   # the detector's sub-pixel window spans a 16 px marker's neighbours: a few corners off by more
        assert np.median(np.abs(errors)) < 0.3 and np.percentile(np.abs(errors), 99) < 1.5
    assert abs(errors.mean()) < 0.05   # no bias


def test_far_floor_is_unbiased_from_the_mipmaps(renderer):
    """At 5 m the texture is sampled from a coarser level: its texel centres must not shift the markers."""
    p, r_wb = np.array([0.1, 0.05, 5.0]), np.eye(3)
    assert renderer._level(p, r_wb) >= 1
    ids, corners = MarkerDetector(renderer.intr, len(IDS)).detect(renderer.render(p, r_wb, np.zeros(3), np.zeros(3),
                                                                                  0.0, None))
    truth = corner_mode(p, r_wb)
    offset = np.concatenate([(c - truth[i]) for i, c in zip(ids, corners) if i in truth]).mean(axis=0)
    assert np.abs(offset).max() < 0.05   # the level's half-texel offset was 0.42 px


def test_motion_blurs_and_the_horizon_and_the_floor_render(renderer):
    p, still = np.array([0.0, 0.0, 1.0]), np.eye(3)
    sharp = renderer.render(p, still, np.zeros(3), np.zeros(3), 0.004, None)
    blurred = renderer.render(p, still, np.zeros(3), np.array([8.0, 0.0, 0.0]), 0.004, None)
    # a fast roll smears the black cells: fewer pure black pixels, the image moved ~13 px
    assert renderer.motion_px(p, still, np.zeros(3), [8.0, 0, 0], 0.004) > 10
    assert (blurred < 20).sum() < 0.8 * (sharp < 20).sum()
    side = renderer.render(np.array([0.0, 0.0, 1.0]), _rot_exp([1.4, 0.0, 0.0]), np.zeros(3), np.zeros(3), 0.0, None)
    assert side.shape == (480, 640)   # the horizon in view: the rays above it see the plain floor's grey
    assert not renderer.render(np.array([0.0, 0.0, 0.0]), still, np.zeros(3), np.zeros(3), 0.0, None).any()


def test_image_mode_is_deterministic_per_seed_and_the_drop_draw_comes_first():
    def frames(seed, **cfg):
        sim = Simulator(load_vehicle("x250"), SimConfig(camera_mode="image", initial_position_m=(0, 0, 1.0), **cfg),
                        seed=seed)
        out = []
        for _ in range(60):
            out += [f for topic, _, f in sim.outputs() if topic == "camera_image"]
            sim.step([1500.0] * 4, True)
        return out
    a, b, c = frames(3), frames(3), frames(4)
    assert len(a) == 2 and [f["pixels"] for f in a] == [f["pixels"] for f in b]
    assert a[0]["pixels"] != c[0]["pixels"]   # the noise is the seed's
    assert frames(3, camera_drop_rate=1.0) == []
    f = a[0]
    assert (f["width_px"], f["height_px"], f["encoding"], len(f["pixels"])) == (640, 480, "mono8", 640 * 480)


def test_a_checkerboard_floor_for_the_calibration():
    intr = Intrinsics.of(DEFAULT_CAMERA, (0.0,) * 5)
    img = FloorRenderer.checkerboard(intr, 9, 6, 0.03, noise_grey=0.0).render(
        np.array([0.0, 0.0, 0.5]), np.eye(3), np.zeros(3), np.zeros(3), 0.0, None)
    found, corners = cv2.findChessboardCornersSB(img, (9, 6))
    assert found and len(corners) == 54
