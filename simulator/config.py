"""Simulator configuration (frozen dataclass, validated on construction)."""
from __future__ import annotations

import math
import typing
from dataclasses import dataclass, fields

from flight.camera import DEFAULT_CAMERA, DEFAULT_MARKERS, DEFAULT_PIXEL_NOISE_PX

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class SimConfig:
    tick_rate_hz: float = 400.0         # rate the caller calls step()
    physics_substeps: int = 5           # RK4 steps per tick (2 kHz by default)
    imu_rate_hz: float = 400.0
    baro_rate_hz: float = 50.0
    mag_rate_hz: float = 50.0
    camera_rate_hz: float = 20.0
    truth_rate_hz: float = 100.0
    camera_latency_s: float = 0.05      # publication delay after exposure (rounded up to a tick)
    imu_latency_s: float = 0.0          # transport delay of the IMU samples (the bus, the driver)
    camera_drop_rate: float = 0.0       # probability a frame is lost
    camera_outage_start_s: float = -1.0  # the camera is silent from here (negative: never) ...
    camera_outage_s: float = 0.0        # ... for this long (fault injection)
    camera_pixel_noise_px: float = DEFAULT_PIXEL_NOISE_PX  # std of the pixel noise per coordinate
    camera_width_px: int = DEFAULT_CAMERA.width_px
    camera_height_px: int = DEFAULT_CAMERA.height_px
    camera_focal_px: float = DEFAULT_CAMERA.focal_px
    marker_size_m: float = DEFAULT_MARKERS.size_m
    marker_spacing_m: float = DEFAULT_MARKERS.spacing_m
    marker_grid_half_extent_m: float = DEFAULT_MARKERS.half_extent_m
    gyro_noise_var: float = 1e-5        # rad^2/s^2 per sample (001)
    accel_noise_var: float = 1e-4       # m^2/s^4 per sample (001)
    gyro_bias_var: float = 1e-5         # initial constant bias variance, rad^2/s^2
    accel_bias_var: float = 1e-4        # m^2/s^4
    gyro_bias_walk: float = 1e-5        # rad/s/sqrt(s)
    accel_bias_walk: float = 1e-4       # m/s^2/sqrt(s)
    baro_noise_pa: float = 3.0          # std
    mag_noise_ut: float = 0.5           # std
    mag_field_ut: Vec3 = (0.0, 20.0, -45.0)  # world ENU
    wind_m_s: Vec3 = (0.0, 0.0, 0.0)    # constant wind, world ENU
    gust_std_m_s: float = 0.0           # Gauss-Markov gust std per axis
    gust_tau_s: float = 2.0             # gust correlation time
    initial_position_m: Vec3 = (0.0, 0.0, 0.0)
    initial_yaw_rad: float = 0.0
    battery_rate_hz: float = 10.0
    battery_capacity_mah: float = 1300.0   # 3S 1300 mAh: the usual pack of a 250 frame
    battery_cells: int = 3
    battery_internal_resistance_ohm: float = 0.05  # whole pack: the voltage sags 0.4 V in hover
    battery_current_a_per_n: float = 2.0   # current per newton of total thrust (~8 A hovering 0.4 kg)
    battery_idle_current_a: float = 0.3    # electronics

    @classmethod
    def from_dict(cls, d: dict) -> "SimConfig":
        """Build from a plain dict (e.g. a TOML table); unknown keys / wrong types -> ValueError."""
        if not isinstance(d, dict):
            raise ValueError(f"simulator: expected a table, got {type(d).__name__}")
        hints = typing.get_type_hints(cls)
        kwargs = {}
        for key, value in d.items():
            if key not in hints:
                raise ValueError(f"simulator.{key}: unknown key")
            kwargs[key] = _coerce(key, hints[key], value)
        return cls(**kwargs)

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def __post_init__(self):
        hints = typing.get_type_hints(type(self))
        for f in fields(self):
            # also coerce on direct construction (lists -> tuples, ints -> floats)
            object.__setattr__(self, f.name, _coerce(f.name, hints[f.name], getattr(self, f.name)))
        for key in ("tick_rate_hz", "camera_focal_px", "marker_size_m", "marker_spacing_m", "gust_tau_s"):
            if getattr(self, key) <= 0:
                raise ValueError(f"simulator.{key}: must be > 0")
        for key in ("battery_capacity_mah",):
            if getattr(self, key) <= 0:
                raise ValueError(f"simulator.{key}: must be > 0")
        for key in ("battery_internal_resistance_ohm", "battery_current_a_per_n", "battery_idle_current_a"):
            if getattr(self, key) < 0:
                raise ValueError(f"simulator.{key}: must be >= 0")
        for key in ("physics_substeps", "camera_width_px", "camera_height_px", "battery_cells"):
            if getattr(self, key) < 1:
                raise ValueError(f"simulator.{key}: must be >= 1")
        for key in ("camera_latency_s", "camera_pixel_noise_px", "marker_grid_half_extent_m",
                    "gyro_noise_var", "accel_noise_var", "gyro_bias_var", "accel_bias_var",
                    "gyro_bias_walk", "accel_bias_walk", "baro_noise_pa", "mag_noise_ut",
                    "gust_std_m_s"):
            if getattr(self, key) < 0:
                raise ValueError(f"simulator.{key}: must be >= 0")
        if not 0.0 <= self.camera_drop_rate <= 1.0:
            raise ValueError("simulator.camera_drop_rate: must be in [0, 1]")
        if self.marker_size_m >= self.marker_spacing_m:
            raise ValueError("simulator.marker_size_m: markers would overlap (must be < marker_spacing_m)")
        if self.initial_position_m[2] < 0:
            raise ValueError("simulator.initial_position_m: z must be >= 0 (ground is z = 0)")
        for key in ("imu_rate_hz", "baro_rate_hz", "mag_rate_hz", "camera_rate_hz", "truth_rate_hz",
                    "battery_rate_hz"):
            self.ticks_per_sample(key)  # raises if not an integer ratio

    def ticks_per_sample(self, rate_key: str) -> int:
        """tick_rate / rate as an int; a sensor is due where tick % this == 0."""
        rate = getattr(self, rate_key)
        if rate <= 0:
            raise ValueError(f"simulator.{rate_key}: must be > 0")
        ratio = self.tick_rate_hz / rate
        n = round(ratio)
        if n < 1 or abs(ratio - n) > 1e-9 * max(1.0, ratio):
            raise ValueError(f"simulator.{rate_key}: tick_rate_hz / {rate_key} = {ratio:g} "
                             "must be a whole number >= 1")
        return int(n)


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _coerce(key: str, typ, value):
    if typ is float:
        if not _is_num(value) or not math.isfinite(value):
            raise ValueError(f"simulator.{key}: expected a finite number, got {value!r}")
        return float(value)
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"simulator.{key}: expected an integer, got {value!r}")
        return value
    if typ == Vec3:
        if (not isinstance(value, (list, tuple)) or len(value) != 3
                or not all(_is_num(e) and math.isfinite(e) for e in value)):
            raise ValueError(f"simulator.{key}: expected a list of 3 numbers, got {value!r}")
        return tuple(float(e) for e in value)
    raise AssertionError(f"unhandled type {typ!r} for {key}")
