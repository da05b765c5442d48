"""`zenpilot calibrate-camera FOLDER --out FILE`: a camera's intrinsics from checkerboard images.

OpenCV's calibration: cv2.findChessboardCornersSB (sub-pixel corners) in every
image of the folder, cv2.calibrateCamera on those found, the intrinsics written as the TOML
file the vision service and the simulator read (flight.camera.load_intrinsics: fx, fy, cx,
cy and the distortion k1, k2, p1, p2, k3). Ten or more views of the board, tilted and at
several places in the image, give a good calibration; the RMS reprojection error is
written beside them (well under a pixel for a good one).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flight.camera import Intrinsics, IntrinsicsError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")
MIN_VIEWS = 3       # calibrateCamera needs several views of the plane to fix the focal length
MAX_RMS_PX = 2.0    # above this the board was misdetected or the lens is not this model: refused


class CalibrationError(ValueError):
    """Images that do not calibrate; the message says what is missing and where."""


@dataclass(frozen=True)
class Calibration:
    intrinsics: Intrinsics
    rms_px: float
    used: list[str]       # image files whose board was found
    skipped: list[str]    # ... and those where it was not


def parse_pattern(text: str) -> tuple[int, int]:
    """"9x6" -> (9, 6): the board's inner corners per row and per column."""
    try:
        cols, rows = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise CalibrationError(f"--pattern {text!r}: expected COLSxROWS of inner corners, e.g. 9x6") from None
    if cols < 2 or rows < 2:
        raise CalibrationError(f"--pattern {text!r}: a board has at least 2 x 2 inner corners")
    return cols, rows


def calibrate_folder(folder: str | Path, pattern: tuple[int, int] = (9, 6), square_m: float = 0.025) -> Calibration:
    import cv2

    folder = Path(folder)
    if not folder.is_dir():
        raise CalibrationError(f"{folder}: not a folder of checkerboard images")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise CalibrationError(f"{folder}: no image files ({', '.join(IMAGE_SUFFIXES)})")
    if not square_m > 0:
        raise CalibrationError(f"--square {square_m}: the squares' side must be > 0 (metres)")
    cols, rows = pattern
    board = np.zeros((cols * rows, 3), np.float32)
    board[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    size = None
    obj_points, img_points, used, skipped = [], [], [], []
    for path in files:
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            skipped.append(f"{path.name} (not an image OpenCV reads)")
            continue
        if size is None:
            size = img.shape[::-1]
        elif img.shape[::-1] != size:
            raise CalibrationError(f"{path}: {img.shape[1]} x {img.shape[0]}, the others are {size[0]} x {size[1]}: "
                                   "one camera, one image size")
        # the sector-based detector: ~0.07 px RMS on the simulator's boards, where the classic one
        # with cornerSubPix gave 1 px (three views of fourteen 1.5-2.2 px off: tests/unit/deploy/test_calibrate.py)
        found, corners = cv2.findChessboardCornersSB(img, (cols, rows),
                                                     flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
        if not found:
            skipped.append(f"{path.name} (no {cols} x {rows} board found)")
            continue
        obj_points.append(board)
        img_points.append(corners)
        used.append(path.name)
    if len(used) < MIN_VIEWS:
        raise CalibrationError(f"{folder}: the {cols} x {rows} board found in {len(used)} image(s), at least "
                               f"{MIN_VIEWS} needed (is --pattern the inner corners' count?); skipped: "
                               + "; ".join(skipped[:5]) + (" ..." if len(skipped) > 5 else ""))
    rms, k, d, _, _ = cv2.calibrateCamera(obj_points, img_points, size, None, None)
    d = np.asarray(d, dtype=np.float64).reshape(-1)
    d = np.concatenate([d, np.zeros(5)])[:5]
    intr = Intrinsics(int(size[0]), int(size[1]), float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]),
                      tuple(float(x) for x in d))
    try:
        intr.check(str(folder))
    except IntrinsicsError as exc:
        raise CalibrationError(f"the calibration did not converge to a camera: {exc}") from None
    if not rms <= MAX_RMS_PX:
        raise CalibrationError(f"{folder}: RMS reprojection error {rms:.2f} px over {len(used)} images (at most "
                               f"{MAX_RMS_PX} px): a board misdetected, or blurred images")
    return Calibration(intr, float(rms), used, skipped)


def write_calibration(cal: Calibration, out: str | Path, folder: str | Path) -> None:
    text = cal.intrinsics.to_toml(
        f"camera intrinsics by `zenpilot calibrate-camera` from {len(cal.used)} images in {folder}\n"
        "read by the vision service and the simulator's image mode (camera_intrinsics)")
    text += f"rms_px = {cal.rms_px!r}   # RMS reprojection error of the calibration\nimages = {len(cal.used)}\n"
    Path(out).write_text(text)
