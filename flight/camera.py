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
