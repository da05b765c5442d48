"""Simulator configuration (frozen dataclass, its fields declared with unit, bounds and a line of
description, checked on construction: flight/param.py). The simulator service declares these as
its parameters (services/params/sim.py)."""
from __future__ import annotations

from dataclasses import dataclass

from flight.camera import DEFAULT_CAMERA, DEFAULT_MARKERS, DEFAULT_PIXEL_NOISE_PX
from flight.param import Declared, declared

Vec3 = tuple[float, float, float]


def _field(default, doc: str, unit: str = "", min: float | None = None, max: float | None = None,
           min_exclusive: bool = False):
    """A setting declared with its line of description first (it reads best beside the default)."""
    return declared(default, unit, min, max, doc, min_exclusive=min_exclusive)


@dataclass(frozen=True)
class SimConfig(Declared):
    label = "simulator"   # its errors read "simulator.KEY: ..."

    tick_rate_hz: float = _field(400.0, "rate the caller calls step()", "Hz", 0.0, min_exclusive=True)
    physics_substeps: int = _field(5, "RK4 steps per tick (2 kHz by default)", "", 1)
    imu_rate_hz: float = _field(400.0, "IMU sample rate (divides the tick rate)", "Hz", 0.0, min_exclusive=True)
    baro_rate_hz: float = _field(50.0, "barometer sample rate", "Hz", 0.0, min_exclusive=True)
    mag_rate_hz: float = _field(50.0, "magnetometer sample rate", "Hz", 0.0, min_exclusive=True)
    camera_rate_hz: float = _field(20.0, "camera frame rate", "Hz", 0.0, min_exclusive=True)
    truth_rate_hz: float = _field(100.0, "ground truth rate (recorder, metrics, state_source = \"truth\")", "Hz",
                                  0.0, min_exclusive=True)
    camera_latency_s: float = _field(0.05, "publication delay of a frame after its exposure (rounded up to a tick)",
                                     "s", 0.0)
    # fault injection: the camera's delay steps mid-flight (a slower exposure, a loaded detector); with
    # stamps that do not follow, only the position level's innovations can tell (flight/estimation/camera_delay.py)
    camera_latency_step_at_s: float = _field(-1.0, "frames exposed from here (negative: never) are published ...", "s")
    camera_latency_step_s: float = _field(0.12, "... this long after their exposure instead of camera_latency_s", "s",
                                          0.0)
    camera_latency_step_stamped: bool = _field(True, "... and stamped with their exposure (false: stamped as if "
                                               "camera_latency_s still held, a late shutter stamp or a camera clock "
                                               "offset)")
    imu_latency_s: float = _field(0.0, "transport delay of the IMU samples (the bus, the driver)", "s")
    camera_drop_rate: float = _field(0.0, "probability a frame is lost", "", 0.0, 1.0)
    camera_outage_start_s: float = _field(-1.0, "the camera is silent from here (negative: never) ...", "s")
    camera_outage_s: float = _field(0.0, "... for this long (fault injection)", "s")
    camera_pixel_noise_px: float = _field(DEFAULT_PIXEL_NOISE_PX, "std of the pixel noise per coordinate", "px", 0.0)
    camera_width_px: int = _field(DEFAULT_CAMERA.width_px, "image width", "px", 1)
    camera_height_px: int = _field(DEFAULT_CAMERA.height_px, "image height", "px", 1)
    camera_focal_px: float = _field(DEFAULT_CAMERA.focal_px, "focal length", "px", 0.0, min_exclusive=True)
    # the image mode: `zenpilot fly --set sim.camera_mode=image` (the vision service follows: it
    # solves whichever the camera sends); the corner mode is the fast path, bit for bit as before
    camera_mode: str = declared("corners", "", None, None, "what the camera sends: \"corners\" (the markers' "
                                "pixel corners, sim/camera) or \"image\" (mono8 frames rendered from the "
                                "intrinsics, sim/@image)", choices=("corners", "image"))
    camera_intrinsics: str = declared("", "", None, None, "image mode: intrinsics file (`zenpilot calibrate-camera` "
                                      "writes it; relative to the stack file); \"\": the camera_* size and focal "
                                      "length with flight.camera.DEFAULT_DISTORTION")
    camera_exposure_s: float = _field(0.004, "image mode: exposure time; the motion across it blurs the frame",
                                      "s", 0.0, 0.05)
    camera_image_noise: float = _field(2.0, "image mode: sensor noise (std) in grey levels of 255", "", 0.0, 64.0)
    marker_size_m: float = _field(DEFAULT_MARKERS.size_m, "a marker's side", "m", 0.0, min_exclusive=True)
    marker_spacing_m: float = _field(DEFAULT_MARKERS.spacing_m, "distance between marker centres (above the size)",
                                     "m", 0.0, min_exclusive=True)
    marker_grid_half_extent_m: float = _field(DEFAULT_MARKERS.half_extent_m,
                                              "the marker grid spans this far from the origin in x and y", "m", 0.0)
    gyro_noise_var: float = _field(1e-5, "gyro white noise variance per sample (001)", "rad^2/s^2", 0.0)
    accel_noise_var: float = _field(1e-4, "accelerometer white noise variance per sample (001)", "m^2/s^4", 0.0)
    gyro_bias_var: float = _field(1e-5, "variance of the gyro's initial constant bias", "rad^2/s^2", 0.0)
    accel_bias_var: float = _field(1e-4, "variance of the accelerometer's initial constant bias", "m^2/s^4", 0.0)
    gyro_bias_walk: float = _field(1e-5, "random walk of the gyro bias", "rad/s/sqrt(s)", 0.0)
    accel_bias_walk: float = _field(1e-4, "random walk of the accelerometer bias", "m/s^2/sqrt(s)", 0.0)
    baro_noise_pa: float = _field(3.0, "barometer noise (std)", "Pa", 0.0)
    mag_noise_ut: float = _field(0.5, "magnetometer noise (std)", "uT", 0.0)
    mag_field_ut: Vec3 = _field((0.0, 20.0, -45.0), "Earth's magnetic field, world ENU", "uT")
    wind_m_s: Vec3 = _field((0.0, 0.0, 0.0), "constant wind, world ENU", "m/s")
    gust_std_m_s: float = _field(0.0, "Gauss-Markov gust std per axis", "m/s", 0.0)
    gust_tau_s: float = _field(2.0, "gust correlation time", "s", 0.0, min_exclusive=True)
    # Dryden (simulator/turbulence.py): MIL-F-8785C's low-altitude shaping filters, their length
    # scales and intensities from the altitude and W20, swept past at the mean wind's speed
    gust_model: str = declared("gauss-markov", "", None, None, "the gusts: \"gauss-markov\" (gust_std_m_s, "
                               "gust_tau_s per axis) or \"dryden\" (MIL-F-8785C low altitude: gust_altitude_m, "
                               "gust_w20_m_s; needs a mean wind)", choices=("gauss-markov", "dryden"))
    gust_altitude_m: float = _field(1.0, "Dryden: the height its length scales and intensities are taken at "
                                    "(the missions hover at 1 m)", "m", 0.0, 304.8, min_exclusive=True)
    gust_w20_m_s: float = _field(0.0, "Dryden: wind speed 20 ft above ground, sigma_w = 0.1 W20 (MIL-F-8785C light "
                                 "7.72, moderate 15.4, severe 23.2); 0: the mean wind's, by the spec's log "
                                 "profile from gust_altitude_m", "m/s", 0.0)
    initial_position_m: Vec3 = _field((0.0, 0.0, 0.0), "where the vehicle starts, world ENU (z >= 0: the ground "
                                      "is z = 0)", "m")
    initial_yaw_rad: float = _field(0.0, "heading at the start", "rad")
    battery_rate_hz: float = _field(10.0, "battery message rate", "Hz", 0.0, min_exclusive=True)

    def __post_init__(self):
        super().__post_init__()
        if self.marker_size_m >= self.marker_spacing_m:
            raise ValueError("simulator.marker_size_m: markers would overlap (must be < marker_spacing_m)")
        if self.initial_position_m[2] < 0:
            raise ValueError("simulator.initial_position_m: z must be >= 0 (ground is z = 0)")
        if self.gust_model == "dryden" and not any(self.wind_m_s):
            raise ValueError("simulator.gust_model: \"dryden\" needs a mean wind (its length scales are swept "
                             "past at the wind's speed): set wind_m_s")
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

