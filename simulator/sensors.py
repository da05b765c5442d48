"""Sensor models. Each sensor owns its numpy Generator so they do not perturb each other."""
from __future__ import annotations

import math

import numpy as np

from flight.camera import Camera, marker_grid
from simulator.config import SimConfig

SEA_LEVEL_PA = 101325.0
TEMPERATURE_K = 288.15


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
        gyro walk, accel walk), taken as one standard_normal(12): numpy's normal(0, s) is
        s * its standard normal, so the noise and the generator's state are unchanged."""
        z = self.rng.standard_normal(12).tolist()
        gs, as_, gw, aw = self.gyro_std, self.accel_std, self.gyro_walk, self.accel_walk
        gb, ab = self._gyro_bias, self._accel_bias
        sx, sy, sz = accel_world_m_s2
        sz = sz + gravity_m_s2  # specific force: a - g
        wx, wy, wz = rate_rad_s
        gyro = [wx + gb[0] + gs * z[0], wy + gb[1] + gs * z[1], wz + gb[2] + gs * z[2]]
        accel = [r[0] * sx + r[3] * sy + r[6] * sz + ab[0] + as_ * z[3],
                 r[1] * sx + r[4] * sy + r[7] * sz + ab[1] + as_ * z[4],
                 r[2] * sx + r[5] * sy + r[8] * sz + ab[2] + as_ * z[5]]
        # bias walk after the sample: the bias of this sample is the one drawn before
        self._gyro_bias = [gb[0] + gw * z[6], gb[1] + gw * z[7], gb[2] + gw * z[8]]
        self._accel_bias = [ab[0] + aw * z[9], ab[1] + aw * z[10], ab[2] + aw * z[11]]
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


class MarkerCamera:
    """Downward camera seeing the floor marker grid (see flight.camera for conventions)."""

    def __init__(self, cfg: SimConfig, rng: np.random.Generator):
        self.rng = rng
        self.camera = Camera(cfg.camera_width_px, cfg.camera_height_px, cfg.camera_focal_px)
        self.ids, self.corners_world = marker_grid(
            cfg.marker_size_m, cfg.marker_spacing_m, cfg.marker_grid_half_extent_m)
        self.noise_px = cfg.camera_pixel_noise_px
        self.drop_rate = cfg.camera_drop_rate

    def sample(self, position_m, quaternion) -> dict | None:
        """One exposure: the fields, or None when the frame is dropped."""
        # draw the drop first so the stream of draws does not depend on what is seen
        if self.rng.random() < self.drop_rate:
            return None
        pix, in_front = self.camera.project(self.corners_world.reshape(-1, 3), position_m, quaternion)
        ok = (in_front & self.camera.in_image(pix)).reshape(-1, 4).all(axis=1)
        seen = pix.reshape(-1, 4, 2)[ok]
        seen = seen + self.rng.normal(0.0, self.noise_px, seen.shape)
        return {"marker_ids": [int(i) for i in self.ids[ok]],
                "corners_px": [float(e) for e in seen.reshape(-1)]}
