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

    def sample(self, rotation, rate_rad_s, accel_world_m_s2, gravity_m_s2: float) -> dict:
        specific_world = np.asarray(accel_world_m_s2) - np.array([0.0, 0.0, -gravity_m_s2])
        gyro = rate_rad_s + self.gyro_bias + self.rng.normal(0.0, self.gyro_std, 3)
        accel = rotation.T @ specific_world + self.accel_bias + self.rng.normal(0.0, self.accel_std, 3)
        # bias walk after the sample: the bias of this sample is the one drawn before
        self.gyro_bias = self.gyro_bias + self.rng.normal(0.0, self.gyro_walk, 3)
        self.accel_bias = self.accel_bias + self.rng.normal(0.0, self.accel_walk, 3)
        return {"gyro_rad_s": [float(e) for e in gyro], "accel_m_s2": [float(e) for e in accel]}


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
        b = rotation.T @ self.field_world_ut + self.rng.normal(0.0, self.noise_ut, 3)
        return {"field_ut": [float(e) for e in b]}


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
