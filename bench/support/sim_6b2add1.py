"""The simulator's tick as of zenpilot 6b2add1 (simulator/world.py Simulator, simulator/sensors.py
Imu and MarkerCamera), verbatim but for the names: the baseline bench/sim_step.py times the
block-drawn IMU noise and the camera's footprint cull against. Not used in flight.

The plant, the barometer, the magnetometer and the battery are today's (unchanged since).
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from bench.support.sim_reference import RefMarkerCamera as MarkerCamera
from flight.motor_model import pwm_to_thrust_floats
from flight.vehicle import Vehicle
from simulator.battery import Battery
from simulator.config import SimConfig
from simulator.plant import Plant, rotation_rows
from simulator.sensors import Barometer, Magnetometer


class Imu6b2add1:
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


_RATE_KEYS = {"imu": "imu_rate_hz", "baro": "baro_rate_hz", "mag": "mag_rate_hz",
              "camera": "camera_rate_hz", "truth": "truth_rate_hz", "battery": "battery_rate_hz"}


class Simulator6b2add1:
    TOPICS = ("imu", "baro", "mag", "camera", "truth", "battery")

    def __init__(self, vehicle: Vehicle, config: SimConfig | None = None, seed: int = 0):
        self.vehicle = vehicle
        self.config = cfg = config if config is not None else SimConfig()
        self.seed = seed
        self.tick = 0
        self._dt_tick_s = 1.0 / cfg.tick_rate_hz
        self._divisor = {topic: cfg.ticks_per_sample(key) for topic, key in _RATE_KEYS.items()}
        # latency rounded up to whole ticks (tolerance: 0.05 s * 400 Hz is 20.000000000000004)
        self._camera_delay_ticks = math.ceil(cfg.camera_latency_s * cfg.tick_rate_hz - 1e-9)
        self._imu_delay_ticks = math.ceil(cfg.imu_latency_s * cfg.tick_rate_hz - 1e-9)
        self._pending_imu: deque = deque()  # (publish_tick, sample_t_s, fields)

        # one independent stream per sensor (and the wind) so they never perturb each other
        imu_ss, baro_ss, mag_ss, cam_ss, wind_ss = np.random.SeedSequence(seed).spawn(5)
        self.imu = Imu6b2add1(cfg, np.random.default_rng(imu_ss))
        self.baro = Barometer(cfg, np.random.default_rng(baro_ss))
        self.mag = Magnetometer(cfg, np.random.default_rng(mag_ss))
        self.camera = MarkerCamera(cfg, np.random.default_rng(cam_ss))
        self._wind_rng = np.random.default_rng(wind_ss)

        # Not in the spec: starting in the air, the motors start at hover thrust
        # (the vehicle "is flying"); otherwise it would drop g*tau while they spin up.
        start_in_air = cfg.initial_position_m[2] > 0.0
        motors = np.full(4, vehicle.hover_thrust_per_motor_n) if start_in_air else np.zeros(4)
        self.plant = Plant(vehicle, cfg.initial_position_m, cfg.initial_yaw_rad, motors)
        self._thrust_cmd_n = motors.tolist()  # floats

        self._wind_const = np.asarray(cfg.wind_m_s, dtype=np.float64)
        self._wind_const_f = self._wind_const.tolist()
        self._gust = self._wind_rng.normal(0.0, cfg.gust_std_m_s, 3)  # stationary start
        # Gauss-Markov gust, exact discretisation over one tick: g <- a g + b n
        self._gust_a = a = math.exp(-self._dt_tick_s / cfg.gust_tau_s)
        self._gust_b = cfg.gust_std_m_s * math.sqrt(1.0 - a * a)
        self._divisors = tuple(self._divisor[topic] for topic in self.TOPICS)
        self._g = float(vehicle.gravity_m_s2)
        self._pending_frames: deque = deque()   # (publish_tick, exposure_t_s, fields)
        self._outputs_tick = -1
        self._outputs: list = []
        self.battery = Battery.of(vehicle)

    @property
    def t(self) -> float:
        return self.tick / self.config.tick_rate_hz

    @property
    def wind_m_s(self) -> np.ndarray:
        return np.array(self._wind)

    @property
    def _wind(self) -> list:
        """The wind now as 3 floats: constant + gust."""
        (a, b, c), (d, e, f) = self._wind_const_f, self._gust_f
        return [a + d, b + e, c + f]

    @property
    def _gust(self) -> np.ndarray:
        return np.array(self._gust_f)

    @_gust.setter
    def _gust(self, value) -> None:
        self._gust_f = np.asarray(value, dtype=np.float64).reshape(3).tolist()

    @property
    def landed(self) -> bool:
        return self.plant.landed

    @property
    def state(self) -> dict:
        """Ground truth now, as plain Python values (the 'truth' message fields)."""
        return self._truth(self.plant.acceleration_floats(self._wind))

    def _truth(self, acc) -> dict:
        p = self.plant
        x = p.x.tolist()
        return {
            "position_m": x[0:3],
            "velocity_m_s": x[3:6],
            "quaternion_wxyz": x[6:10],
            "rate_rad_s": x[10:13],
            "acceleration_m_s2": list(acc),
            "motor_thrust_n": p.motor_thrust_floats(),
            "wind_m_s": list(self._wind),
            "landed": bool(p.landed),
        }

    def _due(self, topic: str) -> bool:
        return self.tick % self._divisor[topic] == 0

    def outputs(self) -> list[tuple[str, float, dict]]:
        """Messages due at the current tick: (topic, sample_time_s, fields).

        Idempotent within a tick (a second call returns the same messages), so
        noise draws and camera captures do not depend on how often it is called.
        """
        if self._outputs_tick == self.tick:
            return list(self._outputs)
        tick = self.tick
        t = self.t
        p = self.plant
        d_imu, d_baro, d_mag, d_camera, d_truth, d_battery = self._divisors
        out: list[tuple[str, float, dict]] = []
        rot = acc = None
        if tick % d_imu == 0:
            x = p.x.tolist()
            rot = rotation_rows(*x[6:10])
            acc = p.acceleration_floats(self._wind)
            sample = self.imu.sample_rows(rot, x[10:13], acc, self._g)
            self._pending_imu.append((tick + self._imu_delay_ticks, t, sample))
        while self._pending_imu and self._pending_imu[0][0] <= tick:
            _, sample_t, sample = self._pending_imu.popleft()
            out.append(("imu", sample_t, sample))
        if tick % d_baro == 0:
            out.append(("baro", t, self.baro.sample(float(p.x[2]))))
        if tick % d_mag == 0:
            if rot is None:
                rot = p.rotation_rows()
            out.append(("mag", t, self.mag.sample_rows(rot)))
        cfg = self.config
        silent = 0.0 <= cfg.camera_outage_start_s <= t < cfg.camera_outage_start_s + cfg.camera_outage_s
        if tick % d_camera == 0 and not silent:
            frame = self.camera.sample(p.position_m, p.quaternion)
            if frame is not None:
                self._pending_frames.append((tick + self._camera_delay_ticks, t, frame))
        while self._pending_frames and self._pending_frames[0][0] <= tick:
            _, exposure_t, frame = self._pending_frames.popleft()
            out.append(("camera", exposure_t, frame))
        if tick % d_truth == 0:
            out.append(("truth", t, self._truth(acc if acc is not None else p.acceleration_floats(self._wind))))
        if tick % d_battery == 0:
            out.append(("battery", t, self.battery.fields()))
        self._outputs_tick = tick
        self._outputs = out
        return list(out)

    def step(self, pwm_us, armed: bool) -> None:
        """Advance one tick with the PWM held constant (zero thrust when disarmed)."""
        pwm = np.asarray(pwm_us, dtype=np.float64)
        if pwm.shape != (4,):
            raise ValueError(f"step: pwm_us must be 4 finite numbers, got {pwm_us!r}")
        p0, p1, p2, p3 = pwm.tolist()
        if not (math.isfinite(p0) and math.isfinite(p1) and math.isfinite(p2) and math.isfinite(p3)):
            raise ValueError(f"step: pwm_us must be 4 finite numbers, got {pwm_us!r}")
        if self._outputs_tick != self.tick:
            self.outputs()  # make sure this tick's samples/exposures happened (determinism)
        cmd = pwm_to_thrust_floats(self.vehicle, (p0, p1, p2, p3)) if armed else [0.0, 0.0, 0.0, 0.0]
        self._thrust_cmd_n = cmd
        n = self.config.physics_substeps
        self.plant._advance(self._dt_tick_s / n, n, cmd, self._wind)
        self.battery.step(self._dt_tick_s, self.plant.motor_thrust_floats())
        self.tick += 1
        if self._gust_b != 0.0:
            # (with no gust, the wind's own generator is not drawn from: nothing else uses it)
            a, b = self._gust_a, self._gust_b
            n0, n1, n2 = self._wind_rng.normal(0.0, 1.0, 3).tolist()
            g0, g1, g2 = self._gust_f
            self._gust_f = [a * g0 + b * n0, a * g1 + b * n1, a * g2 + b * n2]
