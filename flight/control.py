"""Control laws of document 000 (critically damped second order per axis).

Gains k, alpha are 3-vectors (one per axis); 000 uses 16 for attitude and 4
for position. Each law places the closed-loop poles at -k and -alpha.
"""
from __future__ import annotations

import numpy as np


def wrap_angle(a):
    """Wrap to [-pi, pi)."""
    return (np.asarray(a, dtype=np.float64) + np.pi) % (2 * np.pi) - np.pi


def attitude_law(inertia, angles, rates, angles_ref, k, alpha) -> np.ndarray:
    """Law (8): u = I [-(alpha+k) rate - alpha k (angle - ref)] per axis.

    inertia: diagonal (Ixx, Iyy, Izz); angles, angles_ref: (roll, pitch, yaw);
    rates: angular rates (000 uses body rates as Euler rates near hover).
    Returns body torque (3,) N m.
    """
    inertia = np.asarray(inertia, dtype=np.float64)
    if inertia.shape == (3, 3):
        inertia = np.diag(inertia)
    k = np.asarray(k, dtype=np.float64)
    alpha = np.asarray(alpha, dtype=np.float64)
    err = np.asarray(angles, dtype=np.float64) - np.asarray(angles_ref, dtype=np.float64)
    err[2] = wrap_angle(err[2])  # yaw: take the short way round
    return inertia * (-(alpha + k) * np.asarray(rates, dtype=np.float64) - alpha * k * err)


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
                 max_tilt_rad: float = 0.6) -> tuple[float, float, float]:
    """Laws (10), (9), (11): desired acceleration H -> (roll_ref, pitch_ref, thrust_n).

    H = -(alpha+k) v - alpha k (p - p_ref) + [0, 0, g]. Hz is kept >= 0.1 g (never
    ask for upside down) and the tilt of H is clamped to max_tilt_rad by shrinking
    its horizontal part (vertical authority is kept).
    """
    k = np.asarray(k, dtype=np.float64)
    alpha = np.asarray(alpha, dtype=np.float64)
    p = np.asarray(position, dtype=np.float64)
    v = np.asarray(velocity, dtype=np.float64)
    h = -(alpha + k) * v - alpha * k * (p - np.asarray(position_ref, dtype=np.float64))
    h[2] += g
    h[2] = max(h[2], 0.1 * g)
    horiz = np.hypot(h[0], h[1])
    max_horiz = h[2] * np.tan(max_tilt_rad)
    if horiz > max_horiz:
        h[:2] *= max_horiz / horiz
    roll_ref, pitch_ref = attitude_from_thrust_vector(h, yaw)
    return roll_ref, pitch_ref, float(mass * np.linalg.norm(h))


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
