"""Rotations and angles: quaternions [w, x, y, z], Euler angles, angle wrap, tilt.

Quaternions are numpy float64 [w, x, y, z], body->world. Euler angles are ZYX:
R = Rz(yaw) @ Ry(pitch) @ Rx(roll). Angles wrap to [-pi, pi) as (a + pi) mod 2 pi - pi.
"""
from __future__ import annotations

import math

import numpy as np

TWO_PI = 2.0 * math.pi


def wrap_angle(a, xp=np):
    """Angle(s) wrapped to [-pi, pi): (a + pi) mod 2 pi - pi. xp is the array module: numpy
    (the result float64) or jax.numpy (the array's own dtype, traceable)."""
    a = np.asarray(a, dtype=np.float64) if xp is np else xp.asarray(a)
    return (a + math.pi) % TWO_PI - math.pi


def wrap_angle_float(a: float) -> float:
    """wrap_angle on a Python float, the same bits without numpy's per-call cost (the
    200/400 Hz loops)."""
    return (a + math.pi) % TWO_PI - math.pi


def _q(q) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    if q.shape != (4,):
        raise ValueError(f"quaternion must have shape (4,), got {q.shape}")
    return q


def quat_normalize(q) -> np.ndarray:
    q = _q(q)
    n = np.linalg.norm(q)
    if n == 0.0 or not np.isfinite(n):
        raise ValueError("cannot normalise a zero or non-finite quaternion")
    return q / n


def quat_conjugate(q) -> np.ndarray:
    w, x, y, z = _q(q)
    return np.array([w, -x, -y, -z])


def quat_multiply(a, b) -> np.ndarray:
    """Hamilton product a (x) b (apply b first, then a, as rotations)."""
    aw, ax, ay, az = _q(a)
    bw, bx, by, bz = _q(b)
    return np.array([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ])


def quat_to_rotation(q) -> np.ndarray:
    """3x3 rotation matrix body->world (v_world = R @ v_body); q need not be unit."""
    w, x, y, z = quat_normalize(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def quat_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """q = qz(yaw) (x) qy(pitch) (x) qx(roll), i.e. R = Rz Ry Rx."""
    if isinstance(roll, float) and isinstance(pitch, float) and isinstance(yaw, float):
        # scalars (the control loops' case): math's functions, several times cheaper than numpy's
        cr, sr = math.cos(roll / 2), math.sin(roll / 2)
        cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
        cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
        return np.array([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                         cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy])
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    return np.array([
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ])


def quat_to_euler(q) -> tuple[float, float, float]:
    """(roll, pitch, yaw) of the ZYX convention; pitch in [-pi/2, pi/2]."""
    w, x, y, z = quat_normalize(q).tolist()
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    # clip: rounding can push the sine just past +-1 at gimbal lock
    pitch = math.asin(min(1.0, max(-1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def rotate_vector(q, v) -> np.ndarray:
    """Rotate body vector(s) v, shape (3,) or (N, 3), into the world frame."""
    v = np.asarray(v, dtype=np.float64)
    return v @ quat_to_rotation(q).T


def quat_tilt(q) -> float:
    """Angle between the body z axis and the world z axis, rad (0 level, pi inverted)."""
    w, x, y, z = q.tolist() if isinstance(q, np.ndarray) else (float(v) for v in q)
    r22 = (w * w - x * x - y * y + z * z) / (w * w + x * x + y * y + z * z)
    return math.acos(min(1.0, max(-1.0, r22)))
