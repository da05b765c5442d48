"""Control laws of document 000 (critically damped second order per axis).

Gains k, alpha are 3-vectors (one per axis); 000 uses 16 for attitude and 4
for position. Each law places the closed-loop poles at -k and -alpha.
"""
from __future__ import annotations

import math

import numpy as np

from flight.quat import wrap_angle_float

# Law (8)'s angle loop asks at most for the rate this fraction of the airframe's angular
# acceleration can stop (stopping_rate): the attitude service's default and the baseline
# flip's own hold (flight/control/flip.BaselineFlip) share it.
STOPPING_ACCEL_FRACTION = 0.5


def stopping_accel(max_angular_accel, fraction: float):
    """The max_accel attitude_law caps with: this fraction of the airframe's angular
    acceleration per axis; None (law (8) as printed) for a fraction of 0."""
    return fraction * np.asarray(max_angular_accel, dtype=np.float64) if fraction > 0 else None


def stopping_rate(error, gain, max_accel):
    """Rate that drives an angle error to zero: gain * error near zero, and beyond
    max_accel / gain^2 the rate from which max_accel still stops at the reference,
    sqrt(2 max_accel (|error| - max_accel / (2 gain^2))) (ArduPilot's sqrt_controller;
    the two branches meet with equal value and slope). max_accel may be inf (linear)."""
    error = np.asarray(error, dtype=np.float64)
    gain = np.broadcast_to(np.asarray(gain, dtype=np.float64), error.shape)
    max_accel = np.broadcast_to(np.asarray(max_accel, dtype=np.float64), error.shape)
    linear = gain * error
    with np.errstate(invalid="ignore", over="ignore"):
        limit = max_accel / (gain * gain)
        root = np.sign(error) * np.sqrt(2.0 * max_accel * np.maximum(np.abs(error) - 0.5 * limit, 0.0))
    return np.where(np.abs(error) > limit, root, linear)


def _stopping_rate1(error: float, gain: float, max_accel: float) -> float:
    """stopping_rate of one axis, in floats (the same operations)."""
    linear = gain * error
    gg = gain * gain
    if gg == 0.0:
        return linear     # the limit is infinite (or undefined): linear
    limit = max_accel / gg
    if not abs(error) > limit:
        return linear
    return math.copysign(math.sqrt(2.0 * max_accel * max(abs(error) - 0.5 * limit, 0.0)), error)


def _three(v) -> tuple[float, float, float]:
    """A per-axis value (a number or 3 of them) as three floats."""
    t = type(v)
    if t is list or t is tuple:   # the 200 Hz loops' lists of floats: as they are
        if len(v) == 3:
            a, b, c = v
            if type(a) is float and type(b) is float and type(c) is float:
                return a, b, c
    elif isinstance(v, np.ndarray):
        v = v.tolist()
    if isinstance(v, (int, float)):
        return float(v), float(v), float(v)
    a, b, c = v
    return float(a), float(b), float(c)


def attitude_law(inertia, angles, rates, angles_ref, k, alpha, max_accel=None) -> np.ndarray:
    """Law (8): u = I [-(alpha+k) rate - alpha k (angle - ref)] per axis.

    inertia: diagonal (Ixx, Iyy, Izz); angles, angles_ref: (roll, pitch, yaw);
    rates: angular rates (000 uses body rates as Euler rates near hover).
    Returns body torque (3,) N m.

    The law is a rate loop on a proportional angle loop: u = I (alpha+k) (w_ref - rate),
    w_ref = -alpha k / (alpha+k) (angle - ref). max_accel (3,), rad/s^2: w_ref is capped by
    stopping_rate at this angular acceleration, so a large error never asks for a rate the
    airframe cannot stop in time (saturated, the linear law overshoots and can limit-cycle);
    errors below max_accel / (alpha k / (alpha+k))^2 see law (8) exactly. None: law (8).
    """
    return np.array(attitude_law_floats(inertia, angles, rates, angles_ref, k, alpha, max_accel))


def attitude_law_floats(inertia, angles, rates, angles_ref, k, alpha, max_accel=None) -> tuple[float, float, float]:
    """attitude_law as three floats (the attitude service's 200 Hz path: no array made)."""
    # per axis in floats: this runs every 200 Hz step, where numpy's per-call cost dominates
    if not (type(inertia) is tuple and len(inertia) == 3 and type(inertia[0]) is float):   # else: a diagonal's floats
        inertia = np.asarray(inertia, dtype=np.float64)
        if inertia.shape == (3, 3):
            inertia = np.diag(inertia)
    i0, i1, i2 = _three(inertia)
    k0, k1, k2 = _three(k)
    a0, a1, a2 = _three(alpha)
    (e0, e1, e2), (f0, f1, f2), (w0, w1, w2) = _three(angles), _three(angles_ref), _three(rates)
    e0, e1, e2 = e0 - f0, e1 - f1, e2 - f2
    e2 = wrap_angle_float(e2)  # yaw: take the short way round
    if max_accel is None:
        return (i0 * (-(a0 + k0) * w0 - a0 * k0 * e0), i1 * (-(a1 + k1) * w1 - a1 * k1 * e1),
                i2 * (-(a2 + k2) * w2 - a2 * k2 * e2))
    m0, m1, m2 = _three(max_accel)
    return (i0 * (a0 + k0) * (-_stopping_rate1(e0, a0 * k0 / (a0 + k0), m0) - w0),
            i1 * (a1 + k1) * (-_stopping_rate1(e1, a1 * k1 / (a1 + k1), m1) - w1),
            i2 * (a2 + k2) * (-_stopping_rate1(e2, a2 * k2 / (a2 + k2), m2) - w2))


def attitude_from_thrust_vector(h_world, yaw: float) -> tuple[float, float]:
    """(roll, pitch) whose thrust direction R e3 (ZYX, given yaw) is parallel to h_world.

    With yaw 0, R e3 = [cos(roll) sin(pitch), -sin(roll), cos(roll) cos(pitch)];
    so rotate h into the yaw frame and solve. This is (9) of 000 with signs for ENU/FLU.
    """
    hx, hy, hz = np.asarray(h_world, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    hx_y = c * hx + s * hy   # Rz(-yaw) h
    hy_y = -s * hx + c * hy
    pitch = np.arctan2(hx_y, hz)
    roll = np.arctan2(-hy_y, np.hypot(hx_y, hz))
    return float(roll), float(pitch)


def position_law(mass, g, position, velocity, position_ref, k, alpha, yaw,
                 max_tilt_rad: float = 0.6, accel_bias_xy=None) -> tuple[float, float, float]:
    """Laws (10), (9), (11): desired acceleration H -> (roll_ref, pitch_ref, thrust_n).

    H = -(alpha+k) v - alpha k (p - p_ref) + [0, 0, g]. Hz is kept >= 0.1 g (never
    ask for upside down) and the tilt of H is clamped to max_tilt_rad by shrinking
    its horizontal part (vertical authority is kept). accel_bias_xy: a horizontal
    acceleration added to H (the hold integral's, `hold_integral_update`).
    """
    k = np.asarray(k, dtype=np.float64)
    alpha = np.asarray(alpha, dtype=np.float64)
    p = np.asarray(position, dtype=np.float64)
    v = np.asarray(velocity, dtype=np.float64)
    h = -(alpha + k) * v - alpha * k * (p - np.asarray(position_ref, dtype=np.float64))
    if accel_bias_xy is not None:
        h[:2] += accel_bias_xy
    h[2] += g
    h[2] = max(h[2], 0.1 * g)
    horiz = np.hypot(h[0], h[1])
    max_horiz = h[2] * np.tan(max_tilt_rad)
    if horiz > max_horiz:
        h[:2] *= max_horiz / horiz
    roll_ref, pitch_ref = attitude_from_thrust_vector(h, yaw)
    return roll_ref, pitch_ref, float(mass * np.linalg.norm(h))


def hold_integral_update(integral_xy, error_xy, dt: float, ki: float, limit_m_s2: float):
    """The horizontal position-error integral of the hold (a steady wind is a steady force:
    laws (10) alone hold it with an offset of a_wind / (alpha k)). Returns (integral, bias):
    bias = -ki * integral is the acceleration it adds to H, its norm clamped to limit_m_s2
    with the integral held there (no wind-up past what it may ask)."""
    integral = np.asarray(integral_xy, dtype=np.float64) + np.asarray(error_xy, dtype=np.float64) * dt
    if ki <= 0.0:
        return np.zeros(2), np.zeros(2)
    bias = -ki * integral
    norm = float(np.hypot(bias[0], bias[1]))
    if norm > limit_m_s2:
        bias *= limit_m_s2 / norm
        integral = -bias / ki
    return integral, bias


def thrust_accel_xy(thrust_n: float, mass: float, roll: float, pitch: float, yaw: float) -> tuple[float, float]:
    """The horizontal acceleration (world) a collective thrust_n gives at (roll, pitch, yaw), ZYX:
    (thrust / mass) (R e3)_xy."""
    sr, cr, sp, sy, cy = math.sin(roll), math.cos(roll), math.sin(pitch), math.sin(yaw), math.cos(yaw)
    a = thrust_n / mass
    return a * (sy * sr + cy * cr * sp), a * (-cy * sr + sy * cr * sp)


class DisturbanceObserver:
    """A horizontal disturbance-acceleration observer (wind, a payload's pull, a tilt bias): what
    the velocity does beyond the model, d = v' - (thrust (R e3)_xy / m - drag v / m), low-passed at
    bandwidth_rad_s without differentiating v: z' = a_model + d_hat, d_hat = L (v - z), so
    d_hat = L / (s + L) d. The position law subtracts d_hat from H (a feed-forward: a steady wind
    leaves no offset and a gust is met as it builds, not once the position has moved). Its norm is
    clamped to limit_m_s2; hold() freezes it (a flip, the attitude mode: the model does not hold)."""

    def __init__(self, bandwidth_rad_s: float, limit_m_s2: float, drag_per_s: float):
        self.bandwidth, self.limit, self.drag = float(bandwidth_rad_s), float(limit_m_s2), float(drag_per_s)
        self.reset()

    def reset(self) -> None:
        self.d = (0.0, 0.0)
        self.z = None     # None: (re)started at the next update, d kept

    def hold(self) -> None:
        self.z = None

    def update(self, velocity_xy, accel_thrust_xy, dt: float) -> tuple[float, float]:
        """One step: the estimate (2 floats) from the velocity now and the thrust's acceleration."""
        v0, v1 = float(velocity_xy[0]), float(velocity_xy[1])
        L = self.bandwidth
        if self.z is None:   # start where d_hat is what it was
            self.z = (v0 - self.d[0] / L, v1 - self.d[1] / L)
        z0, z1 = self.z
        d0, d1 = L * (v0 - z0), L * (v1 - z1)
        norm = math.hypot(d0, d1)
        if norm > self.limit:   # no wind-up: z follows the clamped estimate
            d0, d1 = d0 * self.limit / norm, d1 * self.limit / norm
            z0, z1 = v0 - d0 / L, v1 - d1 / L
        self.d = (d0, d1)
        a0, a1 = accel_thrust_xy
        self.z = (z0 + dt * (a0 - self.drag * v0 + d0), z1 + dt * (a1 - self.drag * v1 + d1))
        return self.d


def altitude_law(mass, g, z, vz, z_ref, k, alpha, roll, pitch,
                 min_tilt_cos: float = 0.5) -> float:
    """Collective thrust holding altitude while tilted (for attitude-step missions).

    thrust = m Hz / (cos roll cos pitch); the cosine product is floored at
    min_tilt_cos so a large tilt does not ask for unbounded thrust. k, alpha scalars.
    """
    hz = -(alpha + k) * vz - alpha * k * (z - z_ref) + g
    hz = max(hz, 0.0)
    tilt_cos = max(np.cos(roll) * np.cos(pitch), min_tilt_cos)
    return float(mass * hz / tilt_cos)
