"""What the downward camera sees: the floor's ArUco markers rendered as a mono8 image.

The floor is the plane z = 0, so (lens distortion apart) floor -> image is a homography. A
floor texture of the marker layout (cv2.aruco.generateImageMarker per id, a white margin
round each marker, a plain grey floor) is made once, with its mipmaps; the ray of each
pixel through the lens (the distorted pixel grid undistorted once, cv2.undistortPoints) is
made once too. Per frame only the pose's image -> floor homography changes: every pixel's
normalised ray is mapped to texture coordinates in one (N, 3) @ (3, 3) product and the
texture sampled at once with cv2.remap (bilinear, from the mipmap level whose texel best
matches a pixel's footprint, so a far floor does not alias).

Exposure blur: the exposure is split into sub-exposures (as many as the image moves in
pixels across it, up to MAX_SUB_EXPOSURES), each rendered at the pose extrapolated with the
velocity and body rate, and averaged. Sensor noise: Gaussian grey levels from the camera's own
seeded generator, so a lockstep flight is the same image for image.

Conventions as flight/camera.py: OpenCV's camera frame, pixel centres at integer
coordinates, the marker corners in marker_grid's order (ArUco's: clockwise from top-left
as the marker is seen upright, its "up" world +x).
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from flight.camera import R_CAM_FROM_BODY, UNDISTORT_CRITERIA, Intrinsics, aruco_dictionary

FLOOR_GREY = 150          # a plain floor, between the markers' black and their white margin
WHITE = 255
TEXEL_MAX_M = 0.005       # the texture's resolution: at most this many metres a texel (~5 mm)
MARGIN_CELLS = 1.0        # white quiet zone round each marker, in marker cells
MAX_SUB_EXPOSURES = 8     # motion blur: at most this many renders averaged per frame
SUB_EXPOSURE_PX = 1.0     # one sub-exposure per this many pixels the image moves during the exposure
_MIN_W = 1e-9             # homogeneous w at or below this: the ray misses the floor (at or above the horizon)


def _rot_exp(w) -> np.ndarray:
    """exp([w]x) (Rodrigues)."""
    x, y, z = (float(a) for a in w)
    th = math.sqrt(x * x + y * y + z * z)
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    if th < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + math.sin(th) / th * k + (1.0 - math.cos(th)) / (th * th) * (k @ k)


class FloorRenderer:
    """Renders a textured floor (z = 0) seen from a body pose: the marker layout (`markers`) or a
    calibration checkerboard (`checkerboard`)."""

    def __init__(self, intrinsics: Intrinsics, texture: np.ndarray, origin_xy, texel_m: float,
                 noise_grey: float = 2.0, background: int = FLOOR_GREY):
        """A floor painted with `texture` (uint8; row a along world x, column b along world y, the
        texel (a, b) centred on origin + ((a + 0.5) t, (b + 0.5) t)); `background` beyond it."""
        self.intr = intr = intrinsics
        self.noise_grey = float(noise_grey)
        self.texel_m = float(texel_m)
        self.origin = np.asarray(origin_xy, dtype=np.float64).reshape(2)
        self.background = int(background)
        self.levels = [np.ascontiguousarray(texture, dtype=np.uint8)]
        while min(self.levels[-1].shape) > 64:
            self.levels.append(cv2.pyrDown(self.levels[-1]))
        # each pixel's undistorted ray (x_n, y_n, 1) in the camera frame, float32 (N, 3)
        w, h = intr.width_px, intr.height_px
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        grid = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
        norm = cv2.undistortPointsIter(grid, intr.matrix, intr.dist_coeffs, None, None, UNDISTORT_CRITERIA).reshape(-1, 2)
        self.rays = np.ascontiguousarray(np.concatenate([norm, np.ones((len(norm), 1))], axis=1), dtype=np.float32)
        self._rays2 = np.ascontiguousarray(self.rays[:, :2]).reshape(-1, 1, 2)
        edge = np.zeros((h, w), dtype=bool)
        edge[0, :] = edge[-1, :] = edge[:, 0] = edge[:, -1] = True
        self._border = self.rays[edge.ravel()].astype(np.float64)
        self._acc = np.zeros((h, w), dtype=np.float32)

    @classmethod
    def markers(cls, intrinsics: Intrinsics, ids, corners_world, noise_grey: float = 2.0) -> "FloorRenderer":
        """The marker floor: `ids` (M,) and `corners_world` (M, 4, 3) as flight.camera.marker_grid
        gives them (square markers on z = 0, "up" along world +x), ids of MARKER_DICTIONARY."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        corners = np.asarray(corners_world, dtype=np.float64).reshape(-1, 4, 3)
        if len(ids) == 0:
            raise ValueError("FloorRenderer: no markers to render")
        dictionary = aruco_dictionary(int(ids.max()) + 1)
        cells = dictionary.markerSize + 2                          # the bits and a black border
        side = float(np.linalg.norm(corners[0, 0, :2] - corners[0, 1, :2]))
        # a whole number of texels per cell, at most TEXEL_MAX_M each: the marker edges on texel edges
        per_cell = max(1, math.ceil(side / cells / TEXEL_MAX_M))
        t = side / cells / per_cell
        margin = MARGIN_CELLS * side / cells
        lo = corners[:, :, :2].min(axis=(0, 1)) - margin - 4 * t
        hi = corners[:, :, :2].max(axis=(0, 1)) + margin + 4 * t
        c0 = corners[0, :, :2].min(axis=0)                         # the first marker's corner on a texel edge
        origin = c0 - np.ceil((c0 - lo) / t) * t
        n_a, n_b = (np.ceil((hi - origin) / t).astype(int) + 1).tolist()
        tex = np.full((n_a, n_b), FLOOR_GREY, dtype=np.uint8)
        m_tex = cells * per_cell
        m_margin = int(round(margin / t))
        for marker_id, c in zip(ids.tolist(), corners):
            img = cv2.aruco.generateImageMarker(dictionary, marker_id, cells)
            img = cv2.resize(img, (m_tex, m_tex), interpolation=cv2.INTER_NEAREST)
            # the marker image's rows go down its "up" (world -x), its columns to its right (world -y)
            a0, b0 = np.round((c[:, :2].min(axis=0) - origin) / t).astype(int).tolist()
            tex[a0 - m_margin:a0 + m_tex + m_margin, b0 - m_margin:b0 + m_tex + m_margin] = WHITE
            tex[a0:a0 + m_tex, b0:b0 + m_tex] = img[::-1, ::-1]
        out = cls(intrinsics, tex, origin, t, noise_grey)
        out.dictionary = dictionary
        return out

    @classmethod
    def checkerboard(cls, intrinsics: Intrinsics, inner_cols: int, inner_rows: int, square_m: float,
                     noise_grey: float = 2.0) -> "FloorRenderer":
        """A calibration checkerboard on the floor, centred on the origin: (inner_cols + 1) squares
        along world y, (inner_rows + 1) along world x, a white border of one square round it."""
        per = max(1, math.ceil(square_m / TEXEL_MAX_M))
        t = square_m / per
        nx, ny = inner_rows + 1, inner_cols + 1
        board = ((np.arange(nx)[:, None] + np.arange(ny)[None, :]) % 2 * WHITE).astype(np.uint8)
        board = np.pad(board, 1, constant_values=WHITE)
        tex = cv2.resize(board, ((ny + 2) * per, (nx + 2) * per), interpolation=cv2.INTER_NEAREST)
        origin = -np.array([(nx + 2) * square_m, (ny + 2) * square_m]) / 2.0
        return cls(intrinsics, tex, origin, t, noise_grey, background=WHITE)

    # -------------------------------------------------------------- geometry
    def _to_texture(self, position_m, r_wb: np.ndarray, level: int) -> np.ndarray:
        """The 3 x 3 map from a pixel's ray (x_n, y_n, 1) to homogeneous texture coordinates
        (column b, row a, w) of mipmap `level`: the ray in the world, R_wc d, meets z = 0 at
        p - p_z R_wc d / (R_wc d)_z."""
        r_wc = r_wb @ R_CAM_FROM_BODY.T
        px, py, pz = (float(a) for a in position_m)
        # floor point times the ray's depth factor w = -(R_wc d)_z / p_z (positive when it goes down)
        rx, ry, rz = r_wc
        floor_h = np.stack([px * (-rz) / pz + rx, py * (-rz) / pz + ry, -rz / pz])   # rows: X w, Y w, w
        s = 2.0 ** level
        t = self.texel_m * s
        # pyrDown: texel i of level L is centred on level 0's texel 2^L i, so a_L = a_0 / 2^L with
        # a_0 = (X - x0) / t_0 - 0.5: b = (Y - y0) / t - 0.5 / 2^L, a = (X - x0) / t - 0.5 / 2^L
        half = 0.5 / s
        to_tex = np.array([[0.0, 1.0 / t, -self.origin[1] / t - half],
                           [1.0 / t, 0.0, -self.origin[0] / t - half],
                           [0.0, 0.0, 1.0]])
        return to_tex @ floor_h

    def _level(self, position_m, r_wb) -> int:
        """The mipmap level whose texel is nearest (below) a pixel's footprint at the image centre."""
        axis_z = float((r_wb @ R_CAM_FROM_BODY.T)[2, 2])   # optical axis' world z (negative: looking down)
        pz = float(position_m[2])
        if not (axis_z < -1e-3 and pz > 0):
            return 0
        footprint = pz / -axis_z / max(self.intr.fx_px, self.intr.fy_px)
        level = int(math.floor(math.log2(max(footprint / self.texel_m, 1.0))))
        return min(level, len(self.levels) - 1)

    def render_still(self, position_m, r_wb: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """float32 (H, W) grey levels of one instant (no blur, no noise)."""
        intr = self.intr
        pz = float(position_m[2])
        if not pz > 1e-4:   # on (or under) the floor: the lens sees nothing
            img = np.zeros((intr.height_px, intr.width_px), dtype=np.float32)
            if out is not None:
                out[:] = img
                return out
            return img
        level = self._level(position_m, r_wb)
        m = self._to_texture(position_m, r_wb, level)
        # w is linear in the ray, so its least over the image is on the image's border: when the
        # border's rays all meet the floor every pixel does, and OpenCV's transform does the lot
        if float((self._border @ m[2]).min()) > _MIN_W:
            maps = cv2.perspectiveTransform(self._rays2, m).reshape(intr.height_px, intr.width_px, 2)
        else:   # the horizon in view (the flip): the rays that miss the floor sample the border
            hom = self.rays @ m.T.astype(np.float32)
            wv = hom[:, 2]
            bad = wv <= _MIN_W
            wv[bad] = 1.0
            maps = hom[:, :2] / wv[:, None]
            maps[bad] = -1e4
            maps = maps.reshape(intr.height_px, intr.width_px, 2)
        img = cv2.remap(self.levels[level], maps, None, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=self.background)
        if out is not None:
            out[:] = img
            return out
        return img.astype(np.float32)

    def motion_px(self, position_m, r_wb, velocity_m_s, rate_rad_s, exposure_s: float) -> float:
        """About how far the image moves across the exposure (pixels): rotation f |w| e plus
        translation f |v| e / height."""
        f = max(self.intr.fx_px, self.intr.fy_px)
        w = float(np.linalg.norm(rate_rad_s))
        pz = max(float(position_m[2]), 0.05)
        return f * exposure_s * (w + float(np.linalg.norm(velocity_m_s)) / pz)

    def render(self, position_m, r_wb, velocity_m_s, rate_rad_s, exposure_s: float,
               rng: np.random.Generator | None) -> np.ndarray:
        """uint8 (H, W): the exposure centred on this pose, blurred by the motion across it, with noise.

        The sub-exposures' poses: p + v dt, R_wb exp([w_body] dt) for dt across [-e/2, e/2]."""
        p = np.asarray(position_m, dtype=np.float64)
        v = np.asarray(velocity_m_s, dtype=np.float64)
        w = np.asarray(rate_rad_s, dtype=np.float64)
        n = 1
        if exposure_s > 0:
            n = min(MAX_SUB_EXPOSURES, max(1, math.ceil(self.motion_px(p, r_wb, v, w, exposure_s) / SUB_EXPOSURE_PX)))
        if n == 1:
            img = self.render_still(p, r_wb)
        else:
            acc = self._acc
            acc[:] = 0.0
            for k in range(n):
                dt = exposure_s * ((k + 0.5) / n - 0.5)
                acc += self.render_still(p + v * dt, r_wb @ _rot_exp(w * dt))
            img = acc * np.float32(1.0 / n)
        if rng is not None and self.noise_grey > 0:
            img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(self.noise_grey)
        np.clip(img, 0.0, 255.0, out=img)
        return np.rint(img).astype(np.uint8)
