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
    if isinstance(v, np.ndarray):
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
    # per axis in floats: this runs every 200 Hz step, where numpy's per-call cost dominates
    inertia = np.asarray(inertia, dtype=np.float64)
    if inertia.shape == (3, 3):
        inertia = np.diag(inertia)
    inertia, k, alpha = _three(inertia), _three(k), _three(alpha)
    angles, angles_ref, rates = _three(angles), _three(angles_ref), _three(rates)
    err = [angles[0] - angles_ref[0], angles[1] - angles_ref[1], angles[2] - angles_ref[2]]
    err[2] = wrap_angle_float(err[2])  # yaw: take the short way round
    if max_accel is None:
        return np.array([inertia[i] * (-(alpha[i] + k[i]) * rates[i] - alpha[i] * k[i] * err[i]) for i in range(3)])
    max_accel = _three(max_accel)
    out = []
    for i in range(3):
        rate_ref = -_stopping_rate1(err[i], alpha[i] * k[i] / (alpha[i] + k[i]), max_accel[i])
        out.append(inertia[i] * (alpha[i] + k[i]) * (rate_ref - rates[i]))
    return np.array(out)


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
