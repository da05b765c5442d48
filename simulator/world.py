"""Simulator: plant + sensors + wind on a fixed tick, deterministic for a seed.

Usage per tick: msgs = sim.outputs(); ...; sim.step(pwm_us, armed).
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from flight.motor_model import pwm_to_thrust_floats
from flight.vehicle import Vehicle
from simulator.battery import Battery
from simulator.config import SimConfig
from simulator.plant import Plant, rotation_rows
from simulator.sensors import Barometer, ImageCamera, Imu, Magnetometer, MarkerCamera
from simulator.turbulence import DrydenTurbulence, w20_from_wind

_RATE_KEYS = {"imu": "imu_rate_hz", "baro": "baro_rate_hz", "mag": "mag_rate_hz",
              "camera": "camera_rate_hz", "truth": "truth_rate_hz", "battery": "battery_rate_hz"}


class Simulator:
    TOPICS = ("imu", "baro", "mag", "camera", "truth", "battery")   # camera: camera_image in the image mode

    def __init__(self, vehicle: Vehicle, config: SimConfig | None = None, seed: int = 0):
        self.vehicle = vehicle
        self.config = cfg = config if config is not None else SimConfig()
        self.seed = seed
        self.tick = 0
        self._dt_tick_s = 1.0 / cfg.tick_rate_hz
        self._divisor = {topic: cfg.ticks_per_sample(key) for topic, key in _RATE_KEYS.items()}
        # latency rounded up to whole ticks (tolerance: 0.05 s * 400 Hz is 20.000000000000004)
        self._camera_delay_ticks = math.ceil(cfg.camera_latency_s * cfg.tick_rate_hz - 1e-9)
        self._camera_step_delay_ticks = math.ceil(cfg.camera_latency_step_s * cfg.tick_rate_hz - 1e-9)
        self._imu_delay_ticks = math.ceil(cfg.imu_latency_s * cfg.tick_rate_hz - 1e-9)
        self._pending_imu: deque = deque()  # (publish_tick, sample_t_s, fields)

        # one independent stream per sensor (and the wind) so they never perturb each other
        imu_ss, baro_ss, mag_ss, cam_ss, wind_ss = np.random.SeedSequence(seed).spawn(5)
        self.imu = Imu(cfg, np.random.default_rng(imu_ss))
        self.baro = Barometer(cfg, np.random.default_rng(baro_ss))
        self.mag = Magnetometer(cfg, np.random.default_rng(mag_ss))
        # the image mode's camera draws from the same stream (its drop, then its noise)
        self.camera = (ImageCamera(cfg, np.random.default_rng(cam_ss)) if cfg.camera_mode == "image"
                       else MarkerCamera(cfg, np.random.default_rng(cam_ss)))
        self._camera_topic = "camera_image" if cfg.camera_mode == "image" else "camera"
        self._wind_rng = np.random.default_rng(wind_ss)

        # Not in the spec: starting in the air, the motors start at hover thrust
        # (the vehicle "is flying"); otherwise it would drop g*tau while they spin up.
        start_in_air = cfg.initial_position_m[2] > 0.0
        motors = np.full(4, vehicle.hover_thrust_per_motor_n) if start_in_air else np.zeros(4)
        self.plant = Plant(vehicle, cfg.initial_position_m, cfg.initial_yaw_rad, motors)
        self._thrust_cmd_n = motors.tolist()  # floats

        self._wind_const = np.asarray(cfg.wind_m_s, dtype=np.float64)
        self._wind_const_f = self._wind_const.tolist()
        self._dryden = None
        if cfg.gust_model == "dryden":
            w20 = cfg.gust_w20_m_s or w20_from_wind(float(np.linalg.norm(self._wind_const)), cfg.gust_altitude_m)
            self._dryden = DrydenTurbulence(self._wind_const_f, cfg.gust_altitude_m, w20, self._dt_tick_s)
            self._gust = self._dryden.start(self._wind_rng)   # stationary start
            self._gust_a = self._gust_b = 0.0
        else:
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
        tick = self.tick
        if self._outputs_tick == tick:
            return list(self._outputs)
        cfg = self.config
        t = tick / cfg.tick_rate_hz
        p = self.plant
        d_imu, d_baro, d_mag, d_camera, d_truth, d_battery = self._divisors
        out: list[tuple[str, float, dict]] = []
        rot = acc = None
        if tick % d_imu == 0:
            x = p.x.tolist()
            rot = rotation_rows(x[6], x[7], x[8], x[9])
            acc = (0.0, 0.0, 0.0) if p.landed else p._acceleration(x, self._wind)
            sample = self.imu.sample_rows(rot, x[10:13], acc, self._g)
            self._pending_imu.append((tick + self._imu_delay_ticks, t, sample))
        pending = self._pending_imu
        while pending and pending[0][0] <= tick:
            _, sample_t, sample = pending.popleft()
            out.append(("imu", sample_t, sample))
        if tick % d_baro == 0:
            out.append(("baro", t, self.baro.sample(float(p.x[2]))))
        if tick % d_mag == 0:
            if rot is None:
                rot = p.rotation_rows()
            out.append(("mag", t, self.mag.sample_rows(rot)))
        if tick % d_camera == 0 and not (0.0 <= cfg.camera_outage_start_s <= t
                                         < cfg.camera_outage_start_s + cfg.camera_outage_s):
            if self._camera_topic == "camera":
                frame = self.camera.sample(p.position_m, p.quaternion)
            else:
                x = p.x
                frame = self.camera.sample(x[0:3], x[6:10], x[3:6], x[10:13])
            if frame is not None:
                self._queue_frame(tick, t, frame)
        while self._pending_frames and self._pending_frames[0][0] <= tick:
            _, exposure_t, frame = self._pending_frames.popleft()
            out.append((self._camera_topic, exposure_t, frame))
        if tick % d_truth == 0:
            out.append(("truth", t, self._truth(acc if acc is not None else p.acceleration_floats(self._wind))))
        if tick % d_battery == 0:
            out.append(("battery", t, self.battery.fields()))
        self._outputs_tick = tick
        self._outputs = out
        return list(out)

    def _queue_frame(self, tick: int, t: float, frame: dict) -> None:
        """A frame exposed at t, published camera_latency_s later (or camera_latency_step_s from
        camera_latency_step_at_s on, stamped as configured). Frames leave in the order taken,
        as a camera's do: a shorter delay after a longer one waits for the frames before it
        (outputs() releases the queue from its head)."""
        cfg = self.config
        stamp = t
        publish = tick + self._camera_delay_ticks
        if 0.0 <= cfg.camera_latency_step_at_s <= t:
            publish = tick + self._camera_step_delay_ticks
            if not cfg.camera_latency_step_stamped:   # stamped as if the old delay held
                stamp = (publish - self._camera_delay_ticks) / cfg.tick_rate_hz
        self._pending_frames.append((publish, stamp, frame))

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
        if self._dryden is not None:
            self._gust_f = self._dryden.step(self._wind_rng)
        elif self._gust_b != 0.0:
            # (with no gust, the wind's own generator is not drawn from: nothing else uses it)
            a, b = self._gust_a, self._gust_b
            n0, n1, n2 = self._wind_rng.normal(0.0, 1.0, 3).tolist()
            g0, g1, g2 = self._gust_f
            self._gust_f = [a * g0 + b * n0, a * g1 + b * n1, a * g2 + b * n2]
