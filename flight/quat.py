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


def quat_multiply(a, b, xp=np):
    """Hamilton product a (x) b (apply b first, then a, as rotations). xp is the array module:
    numpy (4-vectors, checked) or jax.numpy (the iLQR model, traceable)."""
    if xp is np:
        a, b = _q(a), _q(b)
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (np.array if xp is np else xp.stack)([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ])


def quat_integrate(q, rate_rad_s, h: float) -> np.ndarray:
    """q (x) exp(0.5 w h): a body->world quaternion turned by the body rate w over h (exact
    for a constant w)."""
    w = np.asarray(rate_rad_s, dtype=np.float64)
    angle = float(np.linalg.norm(w)) * h
    if angle < 1e-12:
        return np.asarray(q, dtype=np.float64).copy()
    axis = w / np.linalg.norm(w)
    s = math.sin(0.5 * angle)
    dq = np.array([math.cos(0.5 * angle), *(s * axis)])
    qn = quat_multiply(q, dq)
    return qn / np.linalg.norm(qn)


def quat_to_rotation(q) -> np.ndarray:
    """3x3 rotation matrix body->world (v_world = R @ v_body); q need not be unit."""
    w, x, y, z = quat_normalize(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def quat_from_rotation(r) -> np.ndarray:
    """Unit quaternion [w, x, y, z] (w >= 0) of a rotation matrix (Shepperd)."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = np.asarray(r, dtype=np.float64).tolist()
    tr = r00 + r11 + r22
    cands = [tr, r00, r11, r22]
    k = cands.index(max(cands))       # the first maximum, like np.argmax
    if k == 0:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        q = [0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s]
    elif k == 1:
        s = 2.0 * math.sqrt(max(1.0 + r00 - r11 - r22, 0.0))
        q = [(r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(max(1.0 - r00 + r11 - r22, 0.0))
        q = [(r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s]
    else:
        s = 2.0 * math.sqrt(max(1.0 - r00 - r11 + r22, 0.0))
        q = [(r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def quat_from_euler_floats(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """quat_from_euler of three floats, as 4 floats (the 200 Hz loops' case: no array)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


def quat_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """q = qz(yaw) (x) qy(pitch) (x) qx(roll), i.e. R = Rz Ry Rx."""
    if isinstance(roll, float) and isinstance(pitch, float) and isinstance(yaw, float):
        # scalars (the control loops' case): math's functions, several times cheaper than numpy's
        return np.array(quat_from_euler_floats(roll, pitch, yaw))
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    return np.array([
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ])


def unit_floats(w: float, x: float, y: float, z: float) -> tuple[float, float, float, float]:
    """quat_normalize on 4 floats: the same bits (np.linalg.norm of a 4-vector sums the squares
    in order here, checked bit for bit in tests/unit/flight/test_quat.py), no array."""
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if n == 0.0 or not math.isfinite(n):
        raise ValueError("cannot normalise a zero or non-finite quaternion")
    return w / n, x / n, y / n, z / n


def roll_floats(w: float, x: float, y: float, z: float) -> float:
    """quat_to_euler(q)[0] of a quaternion given as 4 floats (the plan's 32 target rolls)."""
    w, x, y, z = unit_floats(w, x, y, z)
    return math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))


def quat_to_euler(q) -> tuple[float, float, float]:
    """(roll, pitch, yaw) of the ZYX convention; pitch in [-pi/2, pi/2]."""
    w, x, y, z = unit_floats(*_q(q).tolist())
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    # clip: rounding can push the sine just past +-1 at gimbal lock
    pitch = math.asin(min(1.0, max(-1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def quats_to_euler(q) -> np.ndarray:
    """quat_to_euler of many at once: (N, 4) [w, x, y, z] -> (N, 3) [roll, pitch, yaw] rad."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=1)


def rotate_vector(q, v) -> np.ndarray:
    """Rotate body vector(s) v, shape (3,) or (N, 3), into the world frame."""
    v = np.asarray(v, dtype=np.float64)
    return v @ quat_to_rotation(q).T


def quat_tilt(q) -> float:
    """Angle between the body z axis and the world z axis, rad (0 level, pi inverted)."""
    if type(q) is tuple and len(q) == 4:   # quat_from_euler_floats' (floats: as they are)
        w, x, y, z = q
        if not (type(w) is float and type(x) is float and type(y) is float and type(z) is float):
            w, x, y, z = (float(v) for v in q)
    else:
        w, x, y, z = q.tolist() if isinstance(q, np.ndarray) else (float(v) for v in q)
    r22 = (w * w - x * x - y * y + z * z) / (w * w + x * x + y * y + z * z)
    return math.acos(min(1.0, max(-1.0, r22)))
