"""Mixer (body wrench -> rotor forces) and the linear force <-> PWM map of document 000."""
from __future__ import annotations

import numpy as np

from flight.vehicle import Vehicle

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


def mix(vehicle: Vehicle, thrust_n: float, torque_nm) -> tuple[np.ndarray, bool]:
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


def thrust_to_pwm(vehicle: Vehicle, forces_n) -> np.ndarray:
    """Linear map of 000: pwm = pwm_min + F/max_thrust*(pwm_max-pwm_min), clipped."""
    f = np.asarray(forces_n, dtype=np.float64)
    span = vehicle.pwm_max_us - vehicle.pwm_min_us
    pwm = vehicle.pwm_min_us + f / vehicle.max_thrust_n * span
    return np.clip(pwm, vehicle.pwm_min_us, vehicle.pwm_max_us)


def pwm_to_thrust(vehicle: Vehicle, pwm_us) -> np.ndarray:
    """Inverse of thrust_to_pwm, clipped to [min_thrust_n, max_thrust_n]."""
    p = np.asarray(pwm_us, dtype=np.float64)
    span = vehicle.pwm_max_us - vehicle.pwm_min_us
    f = (p - vehicle.pwm_min_us) / span * vehicle.max_thrust_n
    return np.clip(f, vehicle.min_thrust_n, vehicle.max_thrust_n)
