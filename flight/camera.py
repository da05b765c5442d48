"""Downward-looking pinhole camera and the floor marker grid.

Camera frame (OpenCV style): z_c along the optical axis, x_c to the image right
(u grows), y_c to the image bottom (v grows). The camera sits at the body origin
looking straight down:
    z_c = -z_body,  x_c = -y_body (image right = body right),
    y_c = -x_body (image up = body forward).
Pixels: u = f x_c / z_c + cx, v = f y_c / z_c + cy, principal point at the
image centre (width/2, height/2).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flight.quat import quat_to_rotation

# rows: camera axes expressed in body coordinates (p_cam = R_CAM_FROM_BODY @ p_body)
R_CAM_FROM_BODY = np.array([
    [0.0, -1.0, 0.0],
    [-1.0, 0.0, 0.0],
    [0.0, 0.0, -1.0],
])

_MIN_DEPTH_M = 1e-3  # points closer than this are treated as not in front


@dataclass(frozen=True)
class Camera:
    width_px: int
    height_px: int
    focal_px: float

    @property
    def principal_point_px(self) -> tuple[float, float]:
        return self.width_px / 2.0, self.height_px / 2.0

    def project(self, points_world, vehicle_position, vehicle_quat):
        """Project world points (N, 3) -> (pixels (N, 2), in_front (N,) bool).

        Pixels of points not in front of the camera are NaN.
        """
        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        r_wb = quat_to_rotation(vehicle_quat)
        rel = pts - np.asarray(vehicle_position, dtype=np.float64)
        p_cam = rel @ r_wb @ R_CAM_FROM_BODY.T   # (R_cb R_wb^T rel^T)^T
        depth = p_cam[:, 2]
        in_front = depth > _MIN_DEPTH_M
        pix = np.full((len(pts), 2), np.nan)
        cx, cy = self.principal_point_px
        d = depth[in_front]
        pix[in_front, 0] = self.focal_px * p_cam[in_front, 0] / d + cx
        pix[in_front, 1] = self.focal_px * p_cam[in_front, 1] / d + cy
        return pix, in_front

    def in_image(self, pixels) -> np.ndarray:
        """(N,) bool: pixel inside [0, width] x [0, height] (NaN -> False)."""
        pix = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        with np.errstate(invalid="ignore"):
            return ((pix[:, 0] >= 0) & (pix[:, 0] <= self.width_px)
                    & (pix[:, 1] >= 0) & (pix[:, 1] <= self.height_px))


def marker_grid(size_m: float, spacing_m: float, half_extent_m: float):
    """Square markers on the floor (z = 0), centres at every spacing in [-extent, extent]^2.

    ids: row-major, id = iy * n + ix with ix, iy counting from -extent along x, y
    (so id 0 is at (-extent, -extent)). corners_world (M, 4, 3): a marker's "up"
    is world +x (the body forward at yaw 0, so a level camera at yaw 0 sees it
    upright); order 0 top-left (+x, +y), 1 top-right (+x, -y), 2 bottom-right
    (-x, -y), 3 bottom-left (-x, +y) -- clockwise seen from above, like ArUco.
    """
    if size_m <= 0 or spacing_m <= 0 or half_extent_m < 0:
        raise ValueError("marker_grid: size and spacing must be > 0, extent >= 0")
    n = int(np.floor(2 * half_extent_m / spacing_m + 1e-9)) + 1
    coords = -half_extent_m + spacing_m * np.arange(n)
    cy, cx = np.meshgrid(coords, coords, indexing="ij")  # row = y index
    centres = np.stack([cx.ravel(), cy.ravel()], axis=1)
    h = size_m / 2.0
    offsets = np.array([[h, h], [h, -h], [-h, -h], [-h, h]])
    corners = np.zeros((n * n, 4, 3))
    corners[:, :, :2] = centres[:, None, :] + offsets[None, :, :]
    return np.arange(n * n), corners


@dataclass(frozen=True)
class MarkerGridLayout:
    """Square markers on the floor, on a square grid centred at the origin."""

    size_m: float
    spacing_m: float
    half_extent_m: float


# What both the simulator's camera and the vision service assume unless told otherwise (a real
# deployment sets the vision service's from its calibration and its floor).
DEFAULT_CAMERA = Camera(width_px=640, height_px=480, focal_px=400.0)
DEFAULT_PIXEL_NOISE_PX = 0.5  # std per coordinate
# dense enough that ~6 markers are in view at 1 m (one marker alone gives ~3 cm fixes)
DEFAULT_MARKERS = MarkerGridLayout(size_m=0.2, spacing_m=0.5, half_extent_m=5.0)


# ---------------------------------------------------------------- intrinsics with lens distortion
# The image mode's camera (the simulator renders with it, the vision service undistorts with it):
# OpenCV's model, K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] and distortion (k1, k2, p1, p2, k3).
# The corner mode stays the undistorted pinhole `Camera` above.
DEFAULT_DISTORTION = (-0.1, 0.02, 0.0, 0.0, 0.0)   # mild barrel, as a small M12 lens of ~77 deg across
# undoing the distortion to 1e-12 px (cv2.undistortPoints' default 5 iterations leave ~1e-3 px at the corners)
UNDISTORT_CRITERIA = (3, 50, 1e-12)   # cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, epsilon
INTRINSICS_KEYS = ("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px", "distortion")


class IntrinsicsError(ValueError):
    """An intrinsics file that cannot be used; the message names the file and the key."""


@dataclass(frozen=True)
class Intrinsics:
    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @classmethod
    def of(cls, camera: Camera, distortion=DEFAULT_DISTORTION) -> "Intrinsics":
        """The pinhole `camera` with `distortion` (the default image-mode camera)."""
        cx, cy = camera.principal_point_px
        return cls(camera.width_px, camera.height_px, camera.focal_px, camera.focal_px, cx, cy,
                   tuple(float(d) for d in distortion))

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        return np.array(self.distortion, dtype=np.float64)

    def check(self, where: str = "intrinsics") -> "Intrinsics":
        """Itself, or IntrinsicsError naming `where` and the key that cannot be right."""
        for key in ("width_px", "height_px"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 4096:
                raise IntrinsicsError(f"{where}: {key} = {v!r}: expected a whole number of pixels in 1..4096")
        for key in ("fx_px", "fy_px", "cx_px", "cy_px"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                raise IntrinsicsError(f"{where}: {key} = {v!r}: expected a finite number (pixels)")
        if not (self.fx_px > 0 and self.fy_px > 0):
            raise IntrinsicsError(f"{where}: fx_px, fy_px = {self.fx_px!r}, {self.fy_px!r}: focal lengths must be > 0")
        if not (0 <= self.cx_px <= self.width_px and 0 <= self.cy_px <= self.height_px):
            raise IntrinsicsError(f"{where}: principal point ({self.cx_px}, {self.cy_px}) lies outside the "
                                  f"{self.width_px} x {self.height_px} image")
        d = self.distortion
        if (not isinstance(d, (tuple, list)) or len(d) != 5
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) for x in d)):
            raise IntrinsicsError(f"{where}: distortion = {d!r}: expected 5 finite numbers [k1, k2, p1, p2, k3] "
                                  "(OpenCV's order)")
        if max(abs(x) for x in d) > 10.0:
            raise IntrinsicsError(f"{where}: distortion = {list(d)}: a coefficient beyond +-10 is no lens model")
        return self

    def to_toml(self, comment: str = "") -> str:
        lines = [f"# {line}" for line in comment.splitlines()]
        lines += [f"width_px = {self.width_px}", f"height_px = {self.height_px}",
                  f"fx_px = {self.fx_px!r}", f"fy_px = {self.fy_px!r}",
                  f"cx_px = {self.cx_px!r}", f"cy_px = {self.cy_px!r}",
                  f"distortion = [{', '.join(repr(float(x)) for x in self.distortion)}]   # k1, k2, p1, p2, k3 (OpenCV)"]
        return "\n".join(lines) + "\n"


def load_intrinsics(path) -> Intrinsics:
    """A camera's intrinsics from a TOML file (`zenpilot calibrate-camera` writes them); a missing,
    unreadable or wrong file raises IntrinsicsError saying what is wrong and where."""
    import tomllib
    from pathlib import Path

    p = Path(path)
    try:
        doc = tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise IntrinsicsError(f"{p}: camera intrinsics file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise IntrinsicsError(f"{p}: cannot read the camera intrinsics: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise IntrinsicsError(f"{p}: not valid TOML: {exc}") from None
    missing = [k for k in INTRINSICS_KEYS if k not in doc]
    if missing:
        raise IntrinsicsError(f"{p}: missing key(s) {missing} (expected {list(INTRINSICS_KEYS)})")
    unknown = sorted(set(doc) - set(INTRINSICS_KEYS) - {"rms_px", "images"})
    if unknown:
        raise IntrinsicsError(f"{p}: unknown key(s) {unknown} (expected {list(INTRINSICS_KEYS)})")
    d = doc["distortion"]
    intr = Intrinsics(doc["width_px"], doc["height_px"], doc["fx_px"], doc["fy_px"], doc["cx_px"], doc["cy_px"],
                      tuple(d) if isinstance(d, list) else d)
    intr.check(str(p))
    return Intrinsics(intr.width_px, intr.height_px, float(intr.fx_px), float(intr.fy_px), float(intr.cx_px),
                      float(intr.cy_px), tuple(float(x) for x in intr.distortion))


# The markers' dictionary (printed markers: ids 0..M-1 of OpenCV's DICT_4X4_1000, where M is the
# layout's count, 441 for the default grid): 4 x 4 bits keep the cells large for a far floor
# (at the flip's 5 m a 0.2 m marker is 16 px, 2.7 px a cell); the dictionary is cut to the
# layout's ids so a misread cannot give an id that is not on the floor.
MARKER_DICTIONARY = "DICT_4X4_1000"


def aruco_dictionary(n_markers: int):
    """cv2.aruco's MARKER_DICTIONARY holding ids 0..n_markers-1 (cv2 imported only here: the
    corner mode never needs it)."""
    import cv2

    base = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, MARKER_DICTIONARY))
    if not 1 <= n_markers <= len(base.bytesList):
        raise ValueError(f"{MARKER_DICTIONARY} holds {len(base.bytesList)} markers; the layout needs {n_markers}")
    return cv2.aruco.Dictionary(base.bytesList[:n_markers].copy(), base.markerSize, base.maxCorrectionBits)
