"""`zenpilot calibrate-camera`: intrinsics recovered from checkerboard images that the simulator's
own renderer made with known intrinsics and distortion."""

import math

import cv2
import numpy as np
import pytest

from deploy.calibrate import CalibrationError, calibrate_folder, parse_pattern, write_calibration
from deploy.cli import main
from flight.camera import Intrinsics, load_intrinsics
from simulator.render import FloorRenderer, _rot_exp

TRUE = Intrinsics(640, 480, 410.0, 405.0, 325.0, 236.0, (-0.12, 0.03, 0.001, -0.0005, 0.0))


def board_images(folder, n=14, seed=0):
    """n views of a 9 x 6 board (30 mm squares) from 0.35..0.6 m, tilted up to ~25 deg, all over the image."""
    r = FloorRenderer.checkerboard(TRUE, 9, 6, 0.03, noise_grey=1.5)
    rng = np.random.default_rng(seed)
    for k in range(n):
        tilt = rng.uniform(-0.45, 0.45, 2)
        r_wb = _rot_exp([tilt[0], tilt[1], rng.uniform(-math.pi, math.pi)])
        p = np.array([*rng.uniform(-0.12, 0.12, 2), rng.uniform(0.35, 0.6)])
        img = r.render(p, r_wb, np.zeros(3), np.zeros(3), 0.0, rng)
        cv2.imwrite(str(folder / f"board{k:02d}.png"), img)


def test_the_renderers_intrinsics_are_recovered(tmp_path):
    board_images(tmp_path)
    cal = calibrate_folder(tmp_path, (9, 6), 0.03)
    i = cal.intrinsics
    assert len(cal.used) >= 10 and cal.rms_px < 0.5
    assert (i.width_px, i.height_px) == (640, 480)
    assert abs(i.fx_px / TRUE.fx_px - 1) < 0.01 and abs(i.fy_px / TRUE.fy_px - 1) < 0.01
    assert abs(i.cx_px - TRUE.cx_px) < 3.0 and abs(i.cy_px - TRUE.cy_px) < 3.0
    assert abs(i.distortion[0] - TRUE.distortion[0]) < 0.02 and abs(i.distortion[1] - TRUE.distortion[1]) < 0.05
    # the whole lens, not only its coefficients: the same pixels for rays across the image
    rays = np.array([[x, y, 1.0] for x in (-0.7, 0.0, 0.7) for y in (-0.5, 0.0, 0.5)])
    proj = [cv2.projectPoints(rays, np.zeros(3), np.zeros(3), c.matrix, c.dist_coeffs)[0] for c in (i, TRUE)]
    assert np.abs(proj[0] - proj[1]).max() < 1.5
    out = tmp_path / "camera.toml"
    write_calibration(cal, out, tmp_path)
    assert load_intrinsics(out) == i


def test_the_command_writes_the_file_and_refuses_a_folder_without_boards(tmp_path, capsys):
    board_images(tmp_path, n=6)
    out = tmp_path / "cam.toml"
    with pytest.raises(SystemExit) as done:
        main(["calibrate-camera", str(tmp_path), "--out", str(out), "--pattern", "9x6", "--square", "0.03"])
    assert done.value.code == 0 and load_intrinsics(out).width_px == 640
    with pytest.raises(SystemExit) as done:   # the wrong pattern: no board found, said plainly
        main(["calibrate-camera", str(tmp_path), "--out", str(tmp_path / "x.toml"), "--pattern", "7x5"])
    assert done.value.code == 2
    err = capsys.readouterr().err
    assert "7 x 5 board found in 0 image(s)" in err and "Traceback" not in err
    with pytest.raises(CalibrationError, match="expected COLSxROWS"):
        parse_pattern("nine by six")
    with pytest.raises(CalibrationError, match="not a folder"):
        calibrate_folder(tmp_path / "nothing")
