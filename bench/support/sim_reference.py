"""The simulator and the mixer in plain numpy (from zenpilot a2ef311): the reference the
float versions are checked against (tests/unit/simulator/test_fast.py,
tests/unit/flight/control/test_mixer_fast.py) and timed against (bench/sim_step.py). Not used in flight.

RefPlant's motors are the plant's: the rotor speeds are the motor states (flight.motor_model),
advanced by the lag's exact step, RK4's stages seeing the exact speeds at their times.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from flight.motor_model import MotorModel
from flight.quat import quat_from_euler, quat_normalize, quat_to_euler, quat_to_rotation
from flight.vehicle import Vehicle
from simulator.battery import Battery
from simulator.config import SimConfig
from flight.camera import Camera, marker_grid
from simulator.sensors import TEMPERATURE_K, altitude_to_pressure_pa

P, V, Q, W, F = slice(0, 3), slice(3, 6), slice(6, 10), slice(10, 13), slice(13, 17)


class RefPlant:
    def __init__(self, vehicle: Vehicle, position_m=(0.0, 0.0, 0.0), yaw_rad: float = 0.0,
                 motor_thrust_n=None, velocity_m_s=(0.0, 0.0, 0.0), rate_rad_s=(0.0, 0.0, 0.0)):
        self.vehicle = vehicle
        self._m = vehicle.mass_kg
        self._inertia = np.asarray(vehicle.inertia_kg_m2, dtype=np.float64)
        self._inertia_t = tuple(float(i) for i in self._inertia)
        self._alloc = vehicle.allocation
        self._g = np.array([0.0, 0.0, -vehicle.gravity_m_s2])
        self._kf = MotorModel.of(vehicle).kf
        self.x = np.zeros(17)
        self.x[P] = position_m
        self.x[V] = velocity_m_s
        self.x[Q] = quat_from_euler(0.0, 0.0, yaw_rad)
        self.x[W] = rate_rad_s
        if motor_thrust_n is not None:
            self.x[F] = np.sqrt(np.maximum(np.asarray(motor_thrust_n, float), 0.0) / self._kf)
        self.landed = False
        if self.x[2] <= 0.0:
            self.x[2] = 0.0
            self._apply_ground(np.zeros(3))

    # --- accessors -----------------------------------------------------------
    @property
    def position_m(self) -> np.ndarray:
        return self.x[P].copy()

    @property
    def velocity_m_s(self) -> np.ndarray:
        return self.x[V].copy()

    @property
    def quaternion(self) -> np.ndarray:
        return self.x[Q].copy()

    @property
    def rate_rad_s(self) -> np.ndarray:
        return self.x[W].copy()

    @property
    def motor_thrust_n(self) -> np.ndarray:
        return self._kf * self.x[F] ** 2

    @property
    def rotation(self) -> np.ndarray:
        return quat_to_rotation(self.x[Q])

    # --- dynamics -------------------------------------------------------------
    def derivative(self, x: np.ndarray, thrust_cmd_n: np.ndarray, wind_m_s: np.ndarray) -> np.ndarray:
        # Written with scalars: numpy's per-call overhead on 3-vectors dominated the
        # simulator's time (20 evaluations per 400 Hz tick).
        vx, vy, vz, qw, qx, qy, qz, wx, wy, wz = x[3:13].tolist()
        f = self._kf * x[F] ** 2
        u0, u1, u2, u3 = (self._alloc @ f).tolist()
        # third column of R(q): the body z axis in the world
        r02 = 2.0 * (qx * qz + qw * qy)
        r12 = 2.0 * (qy * qz - qw * qx)
        r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
        m, c = self._m, self.vehicle.drag_n_per_m_s
        windx, windy, windz = wind_m_s.tolist()
        ix, iy, iz = self._inertia_t
        dx = np.empty(17)
        dx[0:3] = (vx, vy, vz)
        dx[3] = (r02 * u0 - c * (vx - windx)) / m
        dx[4] = (r12 * u0 - c * (vy - windy)) / m
        dx[5] = (r22 * u0 - c * (vz - windz)) / m + self._g[2]
        dx[6:10] = (0.5 * (-qx * wx - qy * wy - qz * wz), 0.5 * (qw * wx + qy * wz - qz * wy),
                    0.5 * (qw * wy - qx * wz + qz * wx), 0.5 * (qw * wz + qx * wy - qy * wx))
        # Euler: I w' = tau - w x I w
        dx[10] = (u1 - (wy * iz * wz - wz * iy * wy)) / ix
        dx[11] = (u2 - (wz * ix * wx - wx * iz * wz)) / iy
        dx[12] = (u3 - (wx * iy * wy - wy * ix * wx)) / iz
        speed_cmd = np.sqrt(np.maximum(np.asarray(thrust_cmd_n, float), 0.0) / self._kf)
        dx[F] = (speed_cmd - x[F]) / self.vehicle.motor_time_constant_s
        return dx

    def acceleration_m_s2(self, thrust_cmd_n, wind_m_s) -> np.ndarray:
        """World acceleration now (zero while resting on the ground)."""
        if self.landed:
            return np.zeros(3)
        return self.derivative(self.x, np.asarray(thrust_cmd_n, float), np.asarray(wind_m_s, float))[V]

    def step(self, dt_s: float, thrust_cmd_n, wind_m_s) -> None:
        """One RK4 step with the command and wind held constant over dt."""
        cmd = np.asarray(thrust_cmd_n, dtype=np.float64)
        wind = np.asarray(wind_m_s, dtype=np.float64)
        x = self.x
        tau = self.vehicle.motor_time_constant_s
        speed_cmd = np.sqrt(np.maximum(cmd, 0.0) / self._kf)
        e = x[F] - speed_cmd
        w_half = speed_cmd + math.exp(-0.5 * dt_s / tau) * e  # the lag's exact speeds
        w_end = speed_cmd + math.exp(-dt_s / tau) * e

        def at(xs, w):
            xs[F] = w
            return xs

        k1 = self.derivative(x, cmd, wind)
        k2 = self.derivative(at(x + 0.5 * dt_s * k1, w_half), cmd, wind)
        k3 = self.derivative(at(x + 0.5 * dt_s * k2, w_half), cmd, wind)
        k4 = self.derivative(at(x + dt_s * k3, w_end), cmd, wind)
        x = x + dt_s / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        x[F] = w_end
        x[Q] = quat_normalize(x[Q])
        self.x = x
        if x[2] < 0.0 or (self.landed and x[2] <= 0.0):
            x[2] = 0.0
            self._apply_ground(wind)
        else:
            self.landed = False

    def _apply_ground(self, wind_m_s: np.ndarray) -> None:
        """At z = 0: rest (zero motion, level, keep yaw) unless the net force lifts off."""
        x = self.x
        r = quat_to_rotation(x[Q])
        # vertical force as if at rest (v = 0) so a fast impact's drag does not count as lift
        fz = (r[2, 2] * np.sum(self._kf * x[F] ** 2) + self._m * self._g[2]
              + self.vehicle.drag_n_per_m_s * wind_m_s[2])
        if fz <= 0.0:
            _, _, yaw = quat_to_euler(x[Q])
            x[V] = 0.0
            x[W] = 0.0
            x[Q] = quat_from_euler(0.0, 0.0, yaw)
            self.landed = True
        else:
            x[5] = max(x[5], 0.0)  # lifting off: never move into the floor
            self.landed = False


_EPS = 1e-12


def _spread(f: np.ndarray) -> float:
    return float(f.max() - f.min())


def _max_scale(base: np.ndarray, part: np.ndarray, limit: float) -> float:
    """Largest s in [0, 1] with spread(base + s*part) <= limit (assumes spread(base) <= limit).

    spread is the max over motor pairs (i, j) of (base_i - base_j) + s (part_i - part_j),
    so each pair with part_i > part_j bounds s linearly.
    """
    s = 1.0
    db = base[:, None] - base[None, :]
    dp = part[:, None] - part[None, :]
    grow = dp > _EPS
    if np.any(grow):
        s = min(s, float(np.min((limit - db[grow]) / dp[grow])))
    return max(0.0, s)


def ref_mix(vehicle: Vehicle, thrust_n: float, torque_nm) -> tuple[np.ndarray, bool]:
    """F = M^-1 u with saturation to [min_thrust_n, max_thrust_n].

    Priority (why: losing attitude control is worse than losing altitude briefly):
    roll/pitch torque > yaw torque > collective thrust. If the torque part of the
    forces spreads wider than the motor range, yaw is scaled down first, then
    roll/pitch; then the collective is shifted so every motor fits.
    Returns (forces_n (4,), saturated).
    """
    torque = np.asarray(torque_nm, dtype=np.float64).reshape(3)
    m_inv = vehicle.allocation_inv
    lo, hi = vehicle.min_thrust_n, vehicle.max_thrust_n
    limit = hi - lo
    saturated = False

    rp = m_inv[:, 1:3] @ torque[:2]   # roll/pitch part of the forces
    yw = m_inv[:, 3] * torque[2]      # yaw part
    if _spread(rp + yw) > limit + _EPS:
        saturated = True
        if _spread(rp) > limit:
            rp = rp * (limit / _spread(rp))  # roll/pitch alone do not fit: drop yaw, scale them
            yw = np.zeros(4)
        else:
            yw = yw * _max_scale(rp, yw, limit)
    diff = rp + yw

    # Collective: the validated vehicle's M^-1 [T,0,0,0] is T/4 per motor.
    collective = float(thrust_n) / 4.0
    shifted = float(np.clip(collective, lo - diff.min(), hi - diff.max()))
    if abs(shifted - collective) > 1e-9:
        saturated = True
    forces = np.clip(shifted + diff, lo, hi)  # clip only removes rounding here
    return forces, saturated


def ref_thrust_to_pwm(vehicle: Vehicle, forces_n) -> np.ndarray:
    """Linear map of 000: pwm = pwm_min + F/max_thrust*(pwm_max-pwm_min), clipped."""
    f = np.asarray(forces_n, dtype=np.float64)
    span = vehicle.pwm_max_us - vehicle.pwm_min_us
    pwm = vehicle.pwm_min_us + f / vehicle.max_thrust_n * span
    return np.clip(pwm, vehicle.pwm_min_us, vehicle.pwm_max_us)


def ref_pwm_to_thrust(vehicle: Vehicle, pwm_us) -> np.ndarray:
    """Inverse of ref_thrust_to_pwm, clipped to [min_thrust_n, max_thrust_n]."""
    p = np.asarray(pwm_us, dtype=np.float64)
    span = vehicle.pwm_max_us - vehicle.pwm_min_us
    f = (p - vehicle.pwm_min_us) / span * vehicle.max_thrust_n
    return np.clip(f, vehicle.min_thrust_n, vehicle.max_thrust_n)


def ref_motor_forces_update(forces_n, command_n, dt_s: float, motor_time_constant_s: float) -> np.ndarray:
    """Rotor forces after dt_s under a held command, the rotor speed lagging."""
    decay = math.exp(-dt_s / motor_time_constant_s)
    sc = np.sqrt(np.maximum(np.asarray(command_n, float), 0.0))
    s = sc + (np.sqrt(np.maximum(np.asarray(forces_n, float), 0.0)) - sc) * decay
    return s * s


def ref_scale_collective(allocation, forces_n, factor: float) -> np.ndarray:
    """Rotor forces with the collective thrust times factor and the body torques kept.

    A plan is solved on the airframe file's model; the position EKF estimates the
    thrust scale s (real collective per newton commanded, < 1 when the vehicle is
    heavier). The driver sends scale_collective(A, plan forces, 1/s) so the vehicle
    accelerates as planned, and the planner models what was sent as
    scale_collective(A, sent, s). Torques are left alone: a payload changes mass, not
    what a rotor force does about the centre."""
    wrench = np.asarray(allocation) @ np.asarray(forces_n, dtype=np.float64)
    wrench[0] *= factor
    return np.linalg.solve(allocation, wrench)


class RefImu:
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


class RefBarometer:
    def __init__(self, cfg: SimConfig, rng: np.random.Generator):
        self.rng = rng
        self.noise_pa = cfg.baro_noise_pa

    def sample(self, altitude_m: float) -> dict:
        p = altitude_to_pressure_pa(altitude_m) + self.rng.normal(0.0, self.noise_pa)
        return {"pressure_pa": float(p), "temperature_k": TEMPERATURE_K}


class RefMagnetometer:
    def __init__(self, cfg: SimConfig, rng: np.random.Generator):
        self.rng = rng
        self.field_world_ut = np.asarray(cfg.mag_field_ut, dtype=np.float64)
        self.noise_ut = cfg.mag_noise_ut

    def sample(self, rotation) -> dict:
        b = rotation.T @ self.field_world_ut + self.rng.normal(0.0, self.noise_ut, 3)
        return {"field_ut": [float(e) for e in b]}


class RefMarkerCamera:
    """simulator.sensors.MarkerCamera as of zenpilot 6b2add1: every marker of the grid projected."""

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


_RATE_KEYS = {"imu": "imu_rate_hz", "baro": "baro_rate_hz", "mag": "mag_rate_hz",
              "camera": "camera_rate_hz", "truth": "truth_rate_hz", "battery": "battery_rate_hz"}


class RefSimulator:
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
        self.imu = RefImu(cfg, np.random.default_rng(imu_ss))
        self.baro = RefBarometer(cfg, np.random.default_rng(baro_ss))
        self.mag = RefMagnetometer(cfg, np.random.default_rng(mag_ss))
        self.camera = RefMarkerCamera(cfg, np.random.default_rng(cam_ss))
        self._wind_rng = np.random.default_rng(wind_ss)

        # Not in the spec: starting in the air, the motors start at hover thrust
        # (the vehicle "is flying"); otherwise it would drop g*tau while they spin up.
        start_in_air = cfg.initial_position_m[2] > 0.0
        motors = np.full(4, vehicle.hover_thrust_per_motor_n) if start_in_air else np.zeros(4)
        self.plant = RefPlant(vehicle, cfg.initial_position_m, cfg.initial_yaw_rad, motors)
        self._thrust_cmd_n = motors.copy()

        self._wind_const = np.asarray(cfg.wind_m_s, dtype=np.float64)
        self._gust = self._wind_rng.normal(0.0, cfg.gust_std_m_s, 3)  # stationary start
        self._pending_frames: deque = deque()   # (publish_tick, exposure_t_s, fields)
        self._outputs_tick = -1
        self._outputs: list = []
        self.battery = Battery.of(vehicle)

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
        self._thrust_cmd_n = ref_pwm_to_thrust(self.vehicle, pwm) if armed else np.zeros(4)
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
