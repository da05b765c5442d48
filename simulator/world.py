"""Simulator: plant + sensors + wind on a fixed tick, deterministic for a seed.

Usage per tick: msgs = sim.outputs(); ...; sim.step(pwm_us, armed).
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from flight.mixer import pwm_to_thrust
from flight.vehicle import Vehicle
from simulator.battery import Battery
from simulator.config import SimConfig
from simulator.plant import Plant
from simulator.sensors import Barometer, Imu, Magnetometer, MarkerCamera

_RATE_KEYS = {"imu": "imu_rate_hz", "baro": "baro_rate_hz", "mag": "mag_rate_hz",
              "camera": "camera_rate_hz", "truth": "truth_rate_hz", "battery": "battery_rate_hz"}


class Simulator:
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
        self.imu = Imu(cfg, np.random.default_rng(imu_ss))
        self.baro = Barometer(cfg, np.random.default_rng(baro_ss))
        self.mag = Magnetometer(cfg, np.random.default_rng(mag_ss))
        self.camera = MarkerCamera(cfg, np.random.default_rng(cam_ss))
        self._wind_rng = np.random.default_rng(wind_ss)

        # Not in the spec: starting in the air, the motors start at hover thrust
        # (the vehicle "is flying"); otherwise it would drop g*tau while they spin up.
        start_in_air = cfg.initial_position_m[2] > 0.0
        motors = np.full(4, vehicle.hover_thrust_per_motor_n) if start_in_air else np.zeros(4)
        self.plant = Plant(vehicle, cfg.initial_position_m, cfg.initial_yaw_rad, motors)
        self._thrust_cmd_n = motors.copy()

        self._wind_const = np.asarray(cfg.wind_m_s, dtype=np.float64)
        self._gust = self._wind_rng.normal(0.0, cfg.gust_std_m_s, 3)  # stationary start
        self._pending_frames: deque = deque()   # (publish_tick, exposure_t_s, fields)
        self._outputs_tick = -1
        self._outputs: list = []
        self.battery = Battery(cfg.battery_capacity_mah, cfg.battery_cells, cfg.battery_internal_resistance_ohm,
                               cfg.battery_current_a_per_n, cfg.battery_idle_current_a)

    @property
    def t(self) -> float:
        return self.tick / self.config.tick_rate_hz

    @property
    def wind_m_s(self) -> np.ndarray:
        return self._wind_const + self._gust

    @property
    def landed(self) -> bool:
        return self.plant.landed

    @property
    def state(self) -> dict:
        """Ground truth now, as plain Python values (the 'truth' message fields)."""
        p = self.plant
        acc = p.acceleration_m_s2(self._thrust_cmd_n, self.wind_m_s)
        return {
            "position_m": [float(e) for e in p.position_m],
            "velocity_m_s": [float(e) for e in p.velocity_m_s],
            "quaternion_wxyz": [float(e) for e in p.quaternion],
            "rate_rad_s": [float(e) for e in p.rate_rad_s],
            "acceleration_m_s2": [float(e) for e in acc],
            "motor_thrust_n": [float(e) for e in p.motor_thrust_n],
            "wind_m_s": [float(e) for e in self.wind_m_s],
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
        t = self.t
        p = self.plant
        rot = p.rotation
        out: list[tuple[str, float, dict]] = []
        if self._due("imu"):
            acc = p.acceleration_m_s2(self._thrust_cmd_n, self.wind_m_s)
            sample = self.imu.sample(rot, p.rate_rad_s, acc, self.vehicle.gravity_m_s2)
            self._pending_imu.append((self.tick + self._imu_delay_ticks, t, sample))
        while self._pending_imu and self._pending_imu[0][0] <= self.tick:
            _, sample_t, sample = self._pending_imu.popleft()
            out.append(("imu", sample_t, sample))
        if self._due("baro"):
            out.append(("baro", t, self.baro.sample(float(p.position_m[2]))))
        if self._due("mag"):
            out.append(("mag", t, self.mag.sample(rot)))
        cfg = self.config
        silent = 0.0 <= cfg.camera_outage_start_s <= t < cfg.camera_outage_start_s + cfg.camera_outage_s
        if self._due("camera") and not silent:
            frame = self.camera.sample(p.position_m, p.quaternion)
            if frame is not None:
                self._pending_frames.append((self.tick + self._camera_delay_ticks, t, frame))
        while self._pending_frames and self._pending_frames[0][0] <= self.tick:
            _, exposure_t, frame = self._pending_frames.popleft()
            out.append(("camera", exposure_t, frame))
        if self._due("truth"):
            out.append(("truth", t, self.state))
        if self._due("battery"):
            out.append(("battery", t, self.battery.fields()))
        self._outputs_tick = self.tick
        self._outputs = out
        return list(out)

    def step(self, pwm_us, armed: bool) -> None:
        """Advance one tick with the PWM held constant (zero thrust when disarmed)."""
        pwm = np.asarray(pwm_us, dtype=np.float64)
        if pwm.shape != (4,) or not np.all(np.isfinite(pwm)):
            raise ValueError(f"step: pwm_us must be 4 finite numbers, got {pwm_us!r}")
        self.outputs()  # make sure this tick's samples/exposures happened (determinism)
        self._thrust_cmd_n = pwm_to_thrust(self.vehicle, pwm) if armed else np.zeros(4)
        wind = self.wind_m_s
        n = self.config.physics_substeps
        dt = self._dt_tick_s / n
        for _ in range(n):
            self.plant.step(dt, self._thrust_cmd_n, wind)
        self.battery.step(self._dt_tick_s, self.plant.motor_thrust_n)
        self.tick += 1
        # Gauss-Markov gust, exact discretisation over one tick
        cfg = self.config
        a = math.exp(-self._dt_tick_s / cfg.gust_tau_s)
        self._gust = a * self._gust + cfg.gust_std_m_s * math.sqrt(1.0 - a * a) * self._wind_rng.normal(0.0, 1.0, 3)
