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


def test_intrinsics_file_round_trip_and_bad_files_refused_naming_file_and_key(tmp_path):
    import pytest

    from flight.camera import DEFAULT_CAMERA, Intrinsics, IntrinsicsError, load_intrinsics

    good = Intrinsics(640, 480, 401.5, 399.25, 321.0, 238.5, (-0.1, 0.02, 0.001, 0.0, -0.003))
    path = tmp_path / "cam.toml"
    path.write_text(good.to_toml("a comment\nof two lines"))
    assert load_intrinsics(path) == good
    assert Intrinsics.of(DEFAULT_CAMERA).matrix[0, 2] == 320.0
    cases = {
        "nothing.toml": (None, "camera intrinsics file not found"),
        "not-toml.toml": ("width_px = [", "not valid TOML"),
        "missing.toml": ("width_px = 640\n", "missing key(s)"),
        "focal.toml": (good.to_toml().replace("fx_px = 401.5", "fx_px = -3.0"), "focal lengths must be > 0"),
        "dist.toml": (good.to_toml().replace("distortion = [", "distortion = [1.0, "), "expected 5 finite numbers"),
        "size.toml": (good.to_toml().replace("width_px = 640", "width_px = 64.5"), "width_px = 64.5"),
        "extra.toml": (good.to_toml() + "fov = 3\n", "unknown key(s) ['fov']"),
        "centre.toml": (good.to_toml().replace("cx_px = 321.0", "cx_px = 900.0"), "outside the 640 x 480 image"),
    }
    for name, (text, said) in cases.items():
        p = tmp_path / name
        if text is not None:
            p.write_text(text)
        with pytest.raises(IntrinsicsError) as err:
            load_intrinsics(p)
        assert str(p) in str(err.value) and said in str(err.value), name
