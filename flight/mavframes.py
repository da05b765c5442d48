"""ENU/FLU <-> NED/FRD: the one place zenpilot's frames meet MAVLink's (pure).

zenpilot: world ENU (x east, y north, z up), body FLU (x forward, y left,
z up), quaternions [w, x, y, z] body->world, Euler ZYX listed
[roll, pitch, yaw] with yaw 0 = nose east, counter-clockwise positive.
MAVLink: world NED (x north, y east, z down), body FRD (x forward, y right,
z down), yaw 0 = nose north, clockwise positive.

World vectors: NED = (y, x, -z) of ENU (the swap is its own inverse).
Body vectors: FRD = (x, -y, -z) of FLU (also its own inverse).
Attitude: R_ned_frd = P_w R_enu_flu P_b with P_w, P_b the swaps above, so
roll keeps its sign, pitch and yaw change sign, and yaw_ned = pi/2 - yaw_enu.
"""

from __future__ import annotations

import math

import numpy as np

from flight.quat import (
    quat_from_euler,
    quat_multiply,
    quat_normalize,
    quat_to_euler,
    wrap_angle_float,
)

# q(ENU->NED world swap) and q(FLU->FRD body swap), both [w, x, y, z]
_Q_NED_ENU = np.array([0.0, math.sqrt(0.5), math.sqrt(0.5), 0.0])  # 180 deg about (1, 1, 0)/sqrt(2)
_Q_FLU_FRD = np.array([0.0, 1.0, 0.0, 0.0])  # 180 deg about x


# ---- world vectors (position, velocity, acceleration) -----------------------------
def enu_to_ned(v) -> np.ndarray:
    """World vector ENU -> NED (positions in m, velocities m/s, accelerations m/s^2)."""
    x, y, z = np.asarray(v, dtype=np.float64)
    return np.array([y, x, -z])


def ned_to_enu(v) -> np.ndarray:
    """World vector NED -> ENU."""
    n, e, d = np.asarray(v, dtype=np.float64)
    return np.array([e, n, -d])


# ---- body vectors (rates, specific force, magnetic field, torques) ------------------
def flu_to_frd(v) -> np.ndarray:
    """Body vector FLU -> FRD (rates rad/s, accelerations m/s^2, torques N m)."""
    x, y, z = np.asarray(v, dtype=np.float64)
    return np.array([x, -y, -z])


def frd_to_flu(v) -> np.ndarray:
    """Body vector FRD -> FLU."""
    return flu_to_frd(v)


# ---- attitude -------------------------------------------------------------------
def quat_enu_flu_to_ned_frd(q) -> np.ndarray:
    """Body(FLU)->world(ENU) quaternion -> body(FRD)->world(NED) quaternion, w >= 0."""
    q = quat_multiply(quat_multiply(_Q_NED_ENU, quat_normalize(q)), _Q_FLU_FRD)
    return q if q[0] >= 0 else -q


def quat_ned_frd_to_enu_flu(q) -> np.ndarray:
    """Inverse of quat_enu_flu_to_ned_frd (both swaps are their own inverse)."""
    q = quat_multiply(quat_multiply(_Q_NED_ENU, quat_normalize(q)), _Q_FLU_FRD)
    return q if q[0] >= 0 else -q


def euler_enu_to_ned(rpy) -> tuple[float, float, float]:
    """[roll, pitch, yaw] ENU/FLU -> NED/FRD (rad): roll kept, pitch negated, yaw = pi/2 - yaw."""
    roll, pitch, yaw = (float(a) for a in rpy)
    return roll, -pitch, wrap_angle_float(math.pi / 2 - yaw)


def euler_ned_to_enu(rpy) -> tuple[float, float, float]:
    """[roll, pitch, yaw] NED/FRD -> ENU/FLU (rad)."""
    roll, pitch, yaw = (float(a) for a in rpy)
    return roll, -pitch, wrap_angle_float(math.pi / 2 - yaw)


def yaw_enu_to_ned(yaw_rad: float) -> float:
    return wrap_angle_float(math.pi / 2 - float(yaw_rad))


def yaw_ned_to_enu(yaw_rad: float) -> float:
    return wrap_angle_float(math.pi / 2 - float(yaw_rad))


def euler_from_quat_ned(q_ned_frd) -> tuple[float, float, float]:
    """(roll, pitch, yaw) of a NED/FRD quaternion (ZYX, as MAVLink's ATTITUDE)."""
    return quat_to_euler(q_ned_frd)


def quat_ned_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """NED/FRD quaternion of MAVLink Euler angles (ZYX)."""
    return quat_from_euler(roll, pitch, yaw)


# ---- geodetic ---------------------------------------------------------------------
EARTH_RADIUS_M = 6378137.0


def ned_to_geodetic(ned_m, home_lat_deg: float, home_lon_deg: float, home_alt_m: float) -> tuple[float, float, float]:
    """Local NED (m) around home -> (lat deg, lon deg, alt m AMSL); flat earth, fine within km."""
    n, e, d = (float(x) for x in ned_m)
    lat = home_lat_deg + math.degrees(n / EARTH_RADIUS_M)
    lon = home_lon_deg + math.degrees(e / (EARTH_RADIUS_M * math.cos(math.radians(home_lat_deg))))
    return lat, lon, home_alt_m - d


def geodetic_to_ned(lat_deg: float, lon_deg: float, alt_m: float, home_lat_deg: float, home_lon_deg: float,
                    home_alt_m: float) -> np.ndarray:
    """(lat deg, lon deg, alt m AMSL) -> local NED (m) around home; the inverse of ned_to_geodetic."""
    n = math.radians(lat_deg - home_lat_deg) * EARTH_RADIUS_M
    e = math.radians(lon_deg - home_lon_deg) * EARTH_RADIUS_M * math.cos(math.radians(home_lat_deg))
    return np.array([n, e, home_alt_m - alt_m])


# ---- actuator controls (the motor driver's MAVLink output) ---------------------------
def actuator_controls(allocation, max_thrust_n: float, forces_n) -> list[float]:
    """Mixer forces -> MAVLink actuator control group 0 (as PX4's): [roll, pitch, yaw]
    torques normalised to [-1, 1] in FRD, collective thrust normalised to [0, 1],
    then four zeros. A torque of 1 is the one of one side's motors at full thrust
    and the other side's off (half the motors x their lever)."""
    a = np.asarray(allocation, dtype=np.float64)
    u = a @ np.asarray(forces_n, dtype=np.float64)
    scale = 0.5 * np.abs(a[1:]).sum(axis=1) * max_thrust_n
    torque = flu_to_frd(u[1:] / scale)
    thrust = u[0] / (4.0 * max_thrust_n)
    return [float(np.clip(v, -1.0, 1.0)) for v in torque] + [float(np.clip(thrust, 0.0, 1.0)), 0.0, 0.0, 0.0, 0.0]
