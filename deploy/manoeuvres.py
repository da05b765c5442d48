"""Manoeuvre flights in the simulator, in one process, for estimator training and evaluation.

The gyro-vertical of 004 is trained on recorded sequences and judged on
flights it was not trained on.  This module flies the simulated vehicle
through manoeuvres a quadcopter really flies (position steps, turns and
circles, yaw turns, attitude steps, sprints, a flip) with the control laws
of 000 on the *true* state (the estimator under study must not steer the
flight it is judged on), and records the IMU samples with the true roll and
pitch at each sample time.

Two manoeuvre menus with different shapes keep training and control flights
apart: ``"training"`` (steps, circles, yaw turns, attitude steps, a flip) and
``"control"`` (figure-eights, sprints, attitude doublets, climbs, a flip).
Everything is drawn from the seed: same seed, same flight.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from flight.control.laws import altitude_law, attitude_law, position_law
from flight.control.mixer import mix_floats
from flight.motor_model import thrust_to_pwm_floats
from flight.quat import quat_to_euler, wrap_angle
from flight.vehicle import Vehicle
from simulator.config import SimConfig
from simulator.world import Simulator

MENUS = ("training", "control")
START_M = (0.0, 0.0, 2.0)
XY_LIMIT_M = 4.0
FLIP_ALTITUDE_M = 4.0
FLIP_RATE_RAD_S = 4.0 * math.pi      # 720 deg/s roll rate through the flip
FLIP_THRUST_G = 0.3                  # collective during the turn (less height lost upside down)
# ... but at least the collective that leaves this roll acceleration to the differential: the q820's
# torque at 0.3 g gives 4 rad/s^2, a 3 s turn that fell 4 m to the ground (whose contact levels the
# truth with no gyro to see it); the x250's 0.3 g gives 13.9, unchanged
FLIP_ROLL_ACCEL_RAD_S2 = 12.0
# the roll the recovery may take to stop the turn at full torque: the rate is capped so that
# rate^2 / (2 max roll acceleration) fits (the q820's 21.8 rad/s^2 stops 720 deg/s in 208 deg, which
# tumbled it into a second turn; the x250's 58.9 allow 735 deg/s, so its 720 is unchanged)
FLIP_STOP_RAD = 1.4
FLIP_END_RAD = math.radians(320)     # accumulated roll at which recovery starts
YAW_SLEW_RAD_S = 1.0                 # yaw references are rate limited: yaw authority is small
ATTITUDE_GAINS = np.array([16.0, 16.0, 6.0])   # law (8) k = alpha per axis (roll, pitch, yaw)
MAX_TILT_RAD = 0.7                   # tilt the position laws and attitude steps may ask for (below a vehicle's own)

# The sensor errors of a training flight: gyro biases are added per sequence
# (004's 8 sign combinations), so the recorded gyro has none of its own.
TRAINING_SIM = SimConfig(initial_position_m=START_M, physics_substeps=2, gyro_bias_var=0.0,
                         gyro_bias_walk=0.0, camera_outage_start_s=0.0, camera_outage_s=1e9,
                         gust_std_m_s=0.5)


@dataclass(frozen=True)
class Segment:
    """One manoeuvre: kind in ('hover', 'goto', 'circle', 'eight', 'yaw', 'attitude', 'flip')."""

    kind: str
    duration_s: float
    target_m: tuple[float, float, float] = START_M   # goto target; circle/eight centre
    radius_m: float = 0.0
    period_s: float = 1.0
    yaw_rad: float = 0.0
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    gains: float = 4.0                               # k = alpha of the position laws


@dataclass(frozen=True)
class FlightData:
    """IMU samples (body FLU) with the truth at each sample time."""

    t_s: np.ndarray          # (N,)
    gyro_rad_s: np.ndarray   # (N, 3)
    accel_m_s2: np.ndarray   # (N, 3)
    roll_rad: np.ndarray     # (N,)
    pitch_rad: np.ndarray    # (N,)
    yaw_rad: np.ndarray      # (N,)
    position_m: np.ndarray   # (N, 3)
    torque_nm: np.ndarray    # (N, 3) body torque the motors were asked for from this sample on
    segments: tuple[Segment, ...]
    label: str

    def slice(self, n: int) -> "FlightData":
        return replace(self, t_s=self.t_s[:n], gyro_rad_s=self.gyro_rad_s[:n], accel_m_s2=self.accel_m_s2[:n],
                       roll_rad=self.roll_rad[:n], pitch_rad=self.pitch_rad[:n], yaw_rad=self.yaw_rad[:n],
                       position_m=self.position_m[:n], torque_nm=self.torque_nm[:n])


def _point(rng, z_lo=1.5, z_hi=5.0):
    return (float(rng.uniform(-XY_LIMIT_M, XY_LIMIT_M)), float(rng.uniform(-XY_LIMIT_M, XY_LIMIT_M)),
            float(rng.uniform(z_lo, z_hi)))


def manoeuvres(menu: str, duration_s: float, seed: int, flip: bool = True) -> tuple[Segment, ...]:
    """A random sequence of segments from one menu filling ``duration_s`` (one flip per ~60 s)."""
    if menu not in MENUS:
        raise ValueError(f"scenarios: menu must be one of {MENUS}, got {menu!r}")
    rng = np.random.default_rng([seed, MENUS.index(menu)])
    out: list[Segment] = [Segment("hover", 1.0)]
    total = 1.0
    next_flip = 20.0 if flip else math.inf
    if menu == "training":
        kinds, weights = ("goto", "circle", "yaw", "attitude", "hover"), (0.35, 0.25, 0.15, 0.15, 0.1)
    else:
        kinds, weights = ("sprint", "eight", "doublet", "climb", "hover"), (0.3, 0.3, 0.2, 0.1, 0.1)
    while total < duration_s:
        if total >= next_flip:
            seg = [Segment("goto", 3.0, (0.0, 0.0, FLIP_ALTITUDE_M)), Segment("flip", 3.0, (0.0, 0.0, FLIP_ALTITUDE_M))]
            next_flip = total + 60.0
        else:
            kind = str(rng.choice(kinds, p=weights))
            gains = float(rng.uniform(3.0, 5.0))
            if kind == "goto":
                seg = [Segment("goto", float(rng.uniform(3, 6)), _point(rng), gains=gains,
                               yaw_rad=float(rng.uniform(-math.pi, math.pi)))]
            elif kind == "sprint":   # far target, strong gains: large tilt, hard braking
                seg = [Segment("goto", float(rng.uniform(3, 5)), _point(rng, 2.0, 4.0), gains=gains + 2.0)]
            elif kind == "circle":
                seg = [Segment("circle", float(rng.uniform(6, 12)), (0.0, 0.0, float(rng.uniform(2, 4))),
                               radius_m=float(rng.uniform(1.5, 3.0)), period_s=float(rng.uniform(4, 8)),
                               gains=gains)]
            elif kind == "eight":
                seg = [Segment("eight", float(rng.uniform(8, 14)), (0.0, 0.0, float(rng.uniform(2, 4))),
                               radius_m=float(rng.uniform(1.5, 3.0)), period_s=float(rng.uniform(6, 10)),
                               gains=gains)]
            elif kind == "yaw":
                seg = [Segment("yaw", float(rng.uniform(3, 5)), yaw_rad=float(rng.uniform(-math.pi, math.pi)))]
            elif kind == "attitude":
                seg = [Segment("attitude", 1.5, roll_rad=math.radians(float(rng.uniform(-20, 20))),
                               pitch_rad=math.radians(float(rng.uniform(-20, 20)))), Segment("goto", 3.0)]
            elif kind == "doublet":
                a = math.radians(float(rng.uniform(10, 25)))
                axis = int(rng.integers(2))
                seg = [Segment("attitude", 0.8, roll_rad=a * (axis == 0), pitch_rad=a * (axis == 1)),
                       Segment("attitude", 0.8, roll_rad=-a * (axis == 0), pitch_rad=-a * (axis == 1)),
                       Segment("goto", 3.0)]
            elif kind == "climb":
                seg = [Segment("goto", 3.0, (0.0, 0.0, 4.5), gains=gains),
                       Segment("goto", 3.0, (0.0, 0.0, 2.0), gains=gains)]
            else:
                seg = [Segment("hover", float(rng.uniform(1, 3)))]
        # a segment without a target holds where the previous one ended
        for s in seg:
            if s.kind in ("hover", "yaw", "attitude") or (s.kind == "goto" and s.target_m == START_M and out):
                s = replace(s, target_m=_end_point(out))
            out.append(s)
            total += s.duration_s
    return tuple(out)


def _end_point(segments) -> tuple[float, float, float]:
    for s in reversed(segments):
        if s.kind in ("goto", "hover", "yaw", "attitude", "flip"):
            return s.target_m
        if s.kind in ("circle", "eight"):
            return s.target_m
    return START_M


def _reference(seg: Segment, tau: float, start_yaw: float):
    """(position_ref, velocity_ref, yaw_ref) of a path segment at tau seconds into it."""
    c = np.asarray(seg.target_m, dtype=np.float64)
    w = 2 * math.pi / seg.period_s
    ramp = min(1.0, tau / 2.0)   # ease into the path so it starts where the vehicle is
    if seg.kind == "circle":
        p = c + seg.radius_m * ramp * np.array([math.sin(w * tau), 1.0 - math.cos(w * tau), 0.0])
        v = seg.radius_m * ramp * w * np.array([math.cos(w * tau), math.sin(w * tau), 0.0])
        return p, v, math.atan2(v[1], v[0]) if ramp > 0.5 else start_yaw
    if seg.kind == "eight":
        p = c + seg.radius_m * ramp * np.array([math.sin(w * tau), 0.5 * math.sin(2 * w * tau), 0.0])
        v = seg.radius_m * ramp * w * np.array([math.cos(w * tau), math.cos(2 * w * tau), 0.0])
        return p, v, start_yaw
    yaw = seg.yaw_rad if seg.kind in ("goto", "yaw") and seg.yaw_rad != 0.0 else start_yaw
    return c, np.zeros(3), yaw


def fly(vehicle: Vehicle, segments, seed: int = 0, config: SimConfig = TRAINING_SIM,
        label: str = "") -> FlightData:
    """Fly the segments on the true state; record every IMU sample with the truth at its time."""
    sim = Simulator(vehicle, config, seed=seed)
    if config.imu_latency_s != 0.0:
        raise ValueError("scenarios: the recorded truth is at the tick, so imu_latency_s must be 0")
    m, g, inertia = vehicle.mass_kg, vehicle.gravity_m_s2, np.asarray(vehicle.inertia_kg_m2)
    att_k = ATTITUDE_GAINS
    # the airframe's own tilt limit (q820.toml: 10 deg; at 40 deg the laws of 000 drive its few
    # rad/s^2 of torque into a saturated limit cycle that tumbled a flight to the ground)
    max_tilt = MAX_TILT_RAD if vehicle.max_tilt_deg is None else min(MAX_TILT_RAD, math.radians(vehicle.max_tilt_deg))
    rows_t, rows_g, rows_a, rows_q, rows_p, rows_u = [], [], [], [], [], []
    yaw_hold = yaw_cmd = config.initial_yaw_rad
    max_yaw_step = YAW_SLEW_RAD_S / config.tick_rate_hz
    # below half the full collective, the differential's roll acceleration grows with the collective
    full_n = 4.0 * vehicle.max_thrust_n
    flip_rate = min(FLIP_RATE_RAD_S, math.sqrt(2.0 * vehicle.max_angular_accel_rad_s2[0] * FLIP_STOP_RAD))
    flip_thrust = max(FLIP_THRUST_G * m * g,
                      min(0.5 * full_n, FLIP_ROLL_ACCEL_RAD_S2 / vehicle.max_angular_accel_rad_s2[0] * 0.5 * full_n))
    zero3 = np.zeros(3)
    for seg in segments:
        n_ticks = int(round(seg.duration_s * config.tick_rate_hz))
        flip_roll = 0.0
        flip_phase = "climb"
        k = np.full(3, seg.gains)   # per segment, not per tick (~2 s of a ten-minute flight's Python)
        for i in range(n_ticks):
            tau = i / config.tick_rate_hz
            for topic, t_s, fields in sim.outputs():
                if topic == "imu":
                    rows_t.append(t_s)
                    rows_g.append(fields["gyro_rad_s"])
                    rows_a.append(fields["accel_m_s2"])
                    rows_q.append(sim.plant.quaternion.copy())
                    rows_p.append(sim.plant.position_m.copy())
            pos, vel = sim.plant.position_m, sim.plant.velocity_m_s
            rates = sim.plant.rate_rad_s
            euler = np.array(quat_to_euler(sim.plant.quaternion))
            if seg.kind == "flip" and flip_phase != "recover":
                # 001's baseline flip: climb at full thrust, then a fixed roll rate at low thrust
                if flip_phase == "climb":
                    thrust, torque = 4 * vehicle.max_thrust_n * 0.9, attitude_law(
                        inertia, euler, rates, [0.0, 0.0, yaw_cmd], att_k, att_k)
                    if tau >= 0.3:
                        flip_phase = "turn"
                else:
                    thrust = flip_thrust
                    rate_ref = np.array([flip_rate, 0.0, 0.0])
                    torque = inertia * 40.0 * (rate_ref - rates)
                    flip_roll += rates[0] / config.tick_rate_hz
                    if flip_roll >= FLIP_END_RAD:
                        flip_phase = "recover"
            elif seg.kind == "attitude":
                ref = np.array([np.clip(seg.roll_rad, -max_tilt, max_tilt), np.clip(seg.pitch_rad, -max_tilt, max_tilt),
                                yaw_cmd])
                thrust = altitude_law(m, g, pos[2], vel[2], seg.target_m[2], 4.0, 4.0, euler[0], euler[1])
                torque = attitude_law(inertia, euler, rates, ref, att_k, att_k)
            else:
                p_ref, v_ref, yaw_ref = _reference(seg, tau, yaw_hold)
                yaw_cmd = float(wrap_angle(yaw_cmd + np.clip(wrap_angle(yaw_ref - yaw_cmd), -max_yaw_step,
                                                                      max_yaw_step)))
                yaw_ref = yaw_cmd
                # velocity feed-forward: the law acts on the error (p - p_ref, v - v_ref)
                roll_ref, pitch_ref, thrust = position_law(m, g, pos - p_ref, vel - v_ref, zero3, k, k,
                                                           yaw_ref, max_tilt_rad=max_tilt)
                torque = attitude_law(inertia, euler, rates, [roll_ref, pitch_ref, yaw_ref], att_k, att_k)
            forces, _ = mix_floats(vehicle, thrust, torque)   # mix and thrust_to_pwm's floats, no arrays between
            if len(rows_u) < len(rows_t):
                u = (vehicle.allocation @ np.array(forces))[1:]
                while len(rows_u) < len(rows_t):
                    rows_u.append(u)
            sim.step(thrust_to_pwm_floats(vehicle, forces), armed=True)
        yaw_hold = yaw_cmd
    q = np.asarray(rows_q)
    w, x, y, z = q.T
    return FlightData(
        t_s=np.asarray(rows_t), gyro_rad_s=np.asarray(rows_g, dtype=np.float64),
        accel_m_s2=np.asarray(rows_a, dtype=np.float64),
        roll_rad=np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)),
        pitch_rad=np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0)),
        yaw_rad=np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)),
        position_m=np.asarray(rows_p), torque_nm=np.asarray(rows_u), segments=tuple(segments), label=label)


def record(vehicle: Vehicle, menu: str, duration_s: float, seed: int, flip: bool = True,
           config: SimConfig = TRAINING_SIM) -> FlightData:
    """Draw a manoeuvre sequence from ``menu`` and fly it (seed drives both)."""
    segs = manoeuvres(menu, duration_s, seed, flip)
    return fly(vehicle, segs, seed=seed, config=config, label=f"{menu} seed {seed}")
