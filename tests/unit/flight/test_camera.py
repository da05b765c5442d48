import numpy as np

from flight.camera import Camera, marker_grid
from flight.quat import quat_from_euler


def test_downward_camera_axes():
    cam = Camera(640, 480, 400.0)
    q = quat_from_euler(0, 0, 0)
    pts = [[0, 0, 0], [0.5, 0, 0], [0, 0.5, 0], [0, 0, 2]]
    pix, front = cam.project(pts, [0, 0, 1], q)
    assert list(front) == [True, True, True, False]
    np.testing.assert_allclose(pix[0], [320, 240])
    np.testing.assert_allclose(pix[1], [320, 240 - 200])   # forward -> image up
    np.testing.assert_allclose(pix[2], [320 - 200, 240])   # left -> image left
    assert np.all(np.isnan(pix[3]))
    assert list(cam.in_image(pix)) == [True, True, True, False]


def test_marker_grid_ids_and_corner_order():
    ids, corners = marker_grid(0.2, 1.0, 5.0)
    assert len(ids) == 121 and corners.shape == (121, 4, 3)
    np.testing.assert_allclose(corners[0].mean(axis=0), [-5, -5, 0])
    np.testing.assert_allclose(corners[1].mean(axis=0), [-4, -5, 0])
    np.testing.assert_allclose(corners[11].mean(axis=0), [-5, -4, 0])
    c = corners[60]
    np.testing.assert_allclose(c, [[0.1, 0.1, 0], [0.1, -0.1, 0], [-0.1, -0.1, 0], [-0.1, 0.1, 0]])
    # seen from a level camera with yaw 0: TL, TR, BR, BL in the image too
    pix, _ = Camera(640, 480, 400.0).project(c, [0, 0, 1], [1, 0, 0, 0])
    np.testing.assert_allclose(pix, [[280, 200], [360, 200], [360, 280], [280, 280]])
