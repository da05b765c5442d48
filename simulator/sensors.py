"""Sensor models. Each sensor owns its numpy Generator so they do not perturb each other."""
from __future__ import annotations

import bisect
import math

import numpy as np

from flight.camera import _MIN_DEPTH_M, R_CAM_FROM_BODY, Camera, Intrinsics, load_intrinsics, marker_grid
from simulator.config import SimConfig

SEA_LEVEL_PA = 101325.0
TEMPERATURE_K = 288.15
# IMU samples whose noise is drawn in one call: numpy's per-call cost (and, in the one-process
# lockstep, its release of the GIL) once per 64 samples, not per sample
IMU_DRAW_BLOCK = 64
_CAM_T = R_CAM_FROM_BODY.T   # as Camera.project multiplies by it


class Imu:
    """gyro = w + bias + noise; accel = R^T (a - g) + bias + noise (reads +g on z at rest).

    Bias: constant drawn at start from the bias variance, plus a random walk.
    """

    def __init__(self, cfg: SimConfig, rng: np.random.Generator):
        self.rng = rng
        self.dt_s = 1.0 / cfg.imu_rate_hz
        self.gyro_std = math.sqrt(cfg.gyro_noise_var)
        self.accel_std = math.sqrt(cfg.accel_noise_var)
        self.gyro_walk = cfg.gyro_bias_walk * math.sqrt(self.dt_s)   # per-sample walk std
        self.accel_walk = cfg.accel_bias_walk * math.sqrt(self.dt_s)
        self.gyro_bias = rng.normal(0.0, math.sqrt(cfg.gyro_bias_var), 3)
        self.accel_bias = rng.normal(0.0, math.sqrt(cfg.accel_bias_var), 3)
        self._z: list = []      # standard normals drawn ahead (IMU_DRAW_BLOCK samples' worth), used in order
        self._z_next = 0

    @property
    def draws_ahead(self) -> int:
        """Standard normals drawn from rng that no sample has used yet (the block's rest)."""
        return len(self._z) - self._z_next

    # the biases are kept as floats (sampled at 400 Hz); read and set as arrays
    @property
    def gyro_bias(self) -> np.ndarray:
        return np.array(self._gyro_bias)

    @gyro_bias.setter
    def gyro_bias(self, value) -> None:
        self._gyro_bias = np.asarray(value, dtype=np.float64).reshape(3).tolist()

    @property
    def accel_bias(self) -> np.ndarray:
        return np.array(self._accel_bias)

    @accel_bias.setter
    def accel_bias(self, value) -> None:
        self._accel_bias = np.asarray(value, dtype=np.float64).reshape(3).tolist()

    def sample(self, rotation, rate_rad_s, accel_world_m_s2, gravity_m_s2: float) -> dict:
        r = np.asarray(rotation, dtype=np.float64).reshape(9).tolist()
        return self.sample_rows(r, np.asarray(rate_rad_s, dtype=np.float64).reshape(3).tolist(),
                                np.asarray(accel_world_m_s2, dtype=np.float64).reshape(3).tolist(),
                                float(gravity_m_s2))

    def sample_rows(self, r, rate_rad_s, accel_world_m_s2, gravity_m_s2: float) -> dict:
        """sample() on floats: r = R body->world row-major (9), rate and acceleration (3 each).

        The draws are those of four normal(0, std, 3) calls in turn (gyro noise, accel noise,
        gyro walk, accel walk), taken as 12 standard normals: numpy's normal(0, s) is s * its
        standard normal. They come from a block of IMU_DRAW_BLOCK samples' worth drawn at once:
        standard_normal(12 k) is k standard_normal(12) in a row, so each sample's noise is the
        one drawn per sample (same seed, same noise); the generator itself is ahead by the
        block's unused rest (it is the IMU's own: nothing else draws from it)."""
        i = self._z_next
        if i == len(self._z):
            self._z = self.rng.standard_normal(12 * IMU_DRAW_BLOCK).tolist()
            i = 0
        self._z_next = i + 12
        z0, z1, z2, z3, z4, z5, z6, z7, z8, z9, z10, z11 = self._z[i:i + 12]
        gs, as_, gw, aw = self.gyro_std, self.accel_std, self.gyro_walk, self.accel_walk
        gb0, gb1, gb2 = self._gyro_bias
        ab0, ab1, ab2 = self._accel_bias
        sx, sy, sz = accel_world_m_s2
        sz = sz + gravity_m_s2  # specific force: a - g
        wx, wy, wz = rate_rad_s
        r0, r1, r2, r3, r4, r5, r6, r7, r8 = r
        gyro = [wx + gb0 + gs * z0, wy + gb1 + gs * z1, wz + gb2 + gs * z2]
        accel = [r0 * sx + r3 * sy + r6 * sz + ab0 + as_ * z3,
                 r1 * sx + r4 * sy + r7 * sz + ab1 + as_ * z4,
                 r2 * sx + r5 * sy + r8 * sz + ab2 + as_ * z5]
        # bias walk after the sample: the bias of this sample is the one drawn before
        self._gyro_bias = [gb0 + gw * z6, gb1 + gw * z7, gb2 + gw * z8]
        self._accel_bias = [ab0 + aw * z9, ab1 + aw * z10, ab2 + aw * z11]
        return {"gyro_rad_s": gyro, "accel_m_s2": accel}


def altitude_to_pressure_pa(altitude_m: float) -> float:
    """Inverse of h = 44330 (1 - (p/101325)^0.1903)."""
    return SEA_LEVEL_PA * (1.0 - altitude_m / 44330.0) ** (1.0 / 0.1903)


def pressure_to_altitude_m(pressure_pa: float) -> float:
    return 44330.0 * (1.0 - (pressure_pa / SEA_LEVEL_PA) ** 0.1903)


class Barometer:
    def __init__(self, cfg: SimConfig, rng: np.random.Generator):
        self.rng = rng
        self.noise_pa = cfg.baro_noise_pa

    def sample(self, altitude_m: float) -> dict:
        p = altitude_to_pressure_pa(altitude_m) + self.rng.normal(0.0, self.noise_pa)
        return {"pressure_pa": float(p), "temperature_k": TEMPERATURE_K}


class Magnetometer:
    def __init__(self, cfg: SimConfig, rng: np.random.Generator):
        self.rng = rng
        self.field_world_ut = np.asarray(cfg.mag_field_ut, dtype=np.float64)
        self.noise_ut = cfg.mag_noise_ut

    def sample(self, rotation) -> dict:
        return self.sample_rows(np.asarray(rotation, dtype=np.float64).reshape(9).tolist())

    def sample_rows(self, r) -> dict:
        """sample() with R body->world row-major as 9 floats."""
        fx, fy, fz = self.field_world_ut.tolist()
        n0, n1, n2 = self.rng.normal(0.0, self.noise_ut, 3).tolist()
        return {"field_ut": [r[0] * fx + r[3] * fy + r[6] * fz + n0,
                             r[1] * fx + r[4] * fy + r[7] * fz + n1,
                             r[2] * fx + r[5] * fy + r[8] * fz + n2]}


def _rotation(quaternion) -> np.ndarray:
    """flight.quat.quat_to_rotation of a finite, non-zero quaternion, the same bits for a
    third of its cost: its norm is numpy's (np.linalg.norm of a vector is sqrt(q.dot(q))), the
    rest the same operations on floats in place of numpy scalars."""
    q = np.asarray(quaternion, dtype=np.float64)
    n = math.sqrt(q.dot(q))
    w, x, y, z = (q / n).tolist()
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


class MarkerCamera:
    """Downward camera seeing the floor marker grid (see flight.camera for conventions).

    Only the markers whose bounding box lies in that of the image's footprint on the floor (the
    four corner rays' hits, when all of them go down) are projected: the others cannot be seen
    whole. The projection of a subset gives the very pixels of the full grid's rows (row by
    row arithmetic; tests/unit/simulator/test_fast.py checks frames against the full grid's),
    so the frames are the same, for 9 of the 441 markers at 1 m."""

    def __init__(self, cfg: SimConfig, rng: np.random.Generator):
        self.rng = rng
        self.camera = cam = Camera(cfg.camera_width_px, cfg.camera_height_px, cfg.camera_focal_px)
        self.ids, self.corners_world = marker_grid(
            cfg.marker_size_m, cfg.marker_spacing_m, cfg.marker_grid_half_extent_m)
        self.noise_px = cfg.camera_pixel_noise_px
        self.drop_rate = cfg.camera_drop_rate
        c = self.corners_world
        self._floor = bool(np.all(c[:, :, 2] == 0.0))   # the footprint cull assumes the markers on z = 0
        lo, hi = c[:, :, :2].min(axis=1), c[:, :, :2].max(axis=1)
        # marker_grid's layout: id = iy n + ix, the boxes' x bounds those of column ix, y of row iy;
        # a box's markers are then a block of columns by a block of rows (bisect on the bounds)
        n = math.isqrt(len(c))
        self._grid = None
        if n * n == len(c) and n > 0:
            lx, hx, ly, hy = (a.reshape(n, n) for a in (lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1]))   # [iy, ix]
            bounds = (lx[0], hx[0], ly[:, 0], hy[:, 0])
            if ((lx == lx[0]).all() and (hx == hx[0]).all() and (ly == ly[:, :1]).all() and (hy == hy[:, :1]).all()
                    and all((np.diff(b) > 0).all() for b in bounds)):
                self._grid = (n, *(b.tolist() for b in bounds))
        # otherwise each marker's box (lo_x, -hi_x, lo_y, -hi_y) per row: in a box when all four >= (x0, -x1, y0, -y1)
        self._box = np.stack((lo[:, 0], -hi[:, 0], lo[:, 1], -hi[:, 1]), axis=1)
        # the image corners' rays in the body frame: x_b = -y_c, y_b = -x_c, z_b = -z_c (flight.camera)
        cx, cy = cam.principal_point_px
        f = self._f = cam.focal_px
        self._c = np.array([cx, cy])
        self._wh = np.array([cam.width_px, cam.height_px], dtype=np.float64)
        self._rays = tuple((-(v - cy) / f, -(u - cx) / f, -1.0)
                           for u in (0.0, float(cam.width_px)) for v in (0.0, float(cam.height_px)))

    def candidates(self, position_m, quaternion) -> np.ndarray | None:
        """Indices (ascending) of the markers that may be seen whole from this pose; None: all
        of them (the footprint is unbounded: a corner ray at or above the horizon)."""
        if not self._floor:
            return None
        px, py, pz = np.asarray(position_m, dtype=np.float64).tolist()
        qw, qx, qy, qz = np.asarray(quaternion, dtype=np.float64).tolist()
        n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if pz == 0.0 and qx == 0.0 and qy == 0.0 and n > 0.0 and math.isfinite(px + py + n):
            # resting level on the floor (the plant's rest): every marker corner at depth 0 exactly
            # (R's third column is (0, 0, 1)), none in front of the camera
            return np.zeros(0, dtype=np.intp)
        if not pz > 0.0 or not n > 0.0 or not math.isfinite(px + py + pz + n):
            return None
        w, x, y, z = qw / n, qx / n, qy / n, qz / n
        r00, r01, r02 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
        r10, r11, r12 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
        r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
        xs, ys = [], []
        for bx, by, bz in self._rays:
            dz = r20 * bx + r21 * by + r22 * bz
            if not dz < -1e-6:
                return None
            s = -pz / dz
            xs.append(px + s * (r00 * bx + r01 * by + r02 * bz))
            ys.append(py + s * (r10 * bx + r11 * by + r12 * bz))
        x0, x1, y0, y1 = min(xs), max(xs), min(ys), max(ys)
        # far beyond the rounding of either computation (~1e-16 relative)
        eps = 1e-6 * (1.0 + max(abs(x0), abs(x1), abs(y0), abs(y1)))
        x0, x1, y0, y1 = x0 - eps, x1 + eps, y0 - eps, y1 + eps
        # a marker seen whole has its corners in the footprint, so its box in the footprint's box
        if self._grid is not None:
            n, lx, hx, ly, hy = self._grid
            ix0, ix1 = bisect.bisect_left(lx, x0), bisect.bisect_right(hx, x1)
            iy0, iy1 = bisect.bisect_left(ly, y0), bisect.bisect_right(hy, y1)
            return np.array([iy * n + ix for iy in range(iy0, iy1) for ix in range(ix0, ix1)], dtype=np.intp)
        inside = self._box >= np.array([x0, -x1, y0, -y1])
        return np.flatnonzero(inside.all(axis=1))

    def sample(self, position_m, quaternion) -> dict | None:
        """One exposure: the fields, or None when the frame is dropped."""
        # draw the drop first so the stream of draws does not depend on what is seen
        if self.rng.random() < self.drop_rate:
            return None
        idx = self.candidates(position_m, quaternion)
        if idx is None:
            corners, ids = self.corners_world, self.ids
        elif len(idx) == 0:
            return {"marker_ids": [], "corners_px": []}   # nothing seen: no noise drawn either
        else:
            corners, ids = self.corners_world[idx], self.ids[idx]
        seen, ok = self._seen(corners.reshape(-1, 3), position_m, quaternion, idx is not None)
        seen = seen + self.rng.normal(0.0, self.noise_px, seen.shape)
        return {"marker_ids": ids[ok].tolist(), "corners_px": seen.reshape(-1).tolist()}

    def _seen(self, points, position_m, quaternion, near: bool) -> tuple[np.ndarray, np.ndarray]:
        """(pixels (K, 4, 2) of the markers seen whole, which of them (M,) bool) for their
        corners (4 M, 3). `near` (the footprint's markers): Camera.project's arithmetic without
        its masks and copies when every corner is in front, as there at any but extreme tilts."""
        cam = self.camera
        if near:
            p_cam = (points - np.asarray(position_m, dtype=np.float64)) @ _rotation(quaternion) @ _CAM_T
            depth = p_cam[:, 2:3]
            near = bool(depth.min() > _MIN_DEPTH_M)
        if not near:
            pix, in_front = cam.project(points, position_m, quaternion)
            ok = (in_front & cam.in_image(pix)).reshape(-1, 4).all(axis=1)
            return pix.reshape(-1, 4, 2)[ok], ok
        # u = f x / z + cx, v = f y / z + cy, each element as Camera.project computes it
        uv = self._f * p_cam[:, :2] / depth + self._c
        ok = np.logical_and.reduce(((uv >= 0.0) & (uv <= self._wh)).reshape(-1, 8), axis=1)
        return uv.reshape(-1, 4, 2)[ok], ok


class ImageCamera:
    """The image mode's camera: what it sees of the marker floor as a mono8 frame
    (simulator/render.py), with the corner mode's drop rate. The intrinsics: the file
    `camera_intrinsics` names (the caller resolves a relative path), else the configured size
    and focal length with flight.camera.DEFAULT_DISTORTION."""

    def __init__(self, cfg: SimConfig, rng: np.random.Generator, intrinsics: Intrinsics | None = None):
        from simulator.render import FloorRenderer   # cv2: only the image mode imports it

        if intrinsics is None:
            if cfg.camera_intrinsics:
                intrinsics = load_intrinsics(cfg.camera_intrinsics)
            else:
                intrinsics = Intrinsics.of(Camera(cfg.camera_width_px, cfg.camera_height_px, cfg.camera_focal_px))
        self.intrinsics = intrinsics
        self.rng = rng
        self.drop_rate = cfg.camera_drop_rate
        self.exposure_s = cfg.camera_exposure_s
        ids, corners = marker_grid(cfg.marker_size_m, cfg.marker_spacing_m, cfg.marker_grid_half_extent_m)
        self.renderer = FloorRenderer.markers(intrinsics, ids, corners, noise_grey=cfg.camera_image_noise)

    def sample(self, position_m, quaternion, velocity_m_s, rate_rad_s) -> dict | None:
        """One exposure centred now: the camera_image fields, or None when the frame is dropped."""
        if self.rng.random() < self.drop_rate:   # drawn first, as the corner mode does
            return None
        img = self.renderer.render(position_m, _rotation(quaternion), velocity_m_s, rate_rad_s, self.exposure_s,
                                   self.rng)
        return {"width_px": img.shape[1], "height_px": img.shape[0], "encoding": "mono8",
                "exposure_s": self.exposure_s, "pixels": img.tobytes()}
