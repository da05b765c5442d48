"""Mixer of document 000: body wrench -> rotor forces, with saturation (the force <-> PWM
map that follows it is the motors' own, flight/motor_model.py).

The 400 Hz path (mix) works on Python floats with the vehicle's M^-1 and limits read once
per vehicle: numpy's ~1 us per call on 4-vectors was most of its time.
tests/unit/flight/control/test_mixer_fast.py checks it against a plain numpy version
(bench/support/sim_reference.py), saturation cases included.
"""
from __future__ import annotations

import numpy as np

from flight.motor_model import clip_float
from flight.vehicle import Vehicle, per_vehicle_cache

_EPS = 1e-12


class _Consts:
    """What the mixer reads of a vehicle, as floats (vehicles are frozen)."""

    __slots__ = ("m_inv", "lo", "hi", "limit")

    def __init__(self, vehicle: Vehicle):
        self.m_inv = tuple(tuple(row) for row in np.asarray(vehicle.allocation_inv, dtype=np.float64).tolist())
        self.lo, self.hi = float(vehicle.min_thrust_n), float(vehicle.max_thrust_n)
        self.limit = self.hi - self.lo


_consts = per_vehicle_cache(_Consts)


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


def _max_scale_floats(base, part, limit: float) -> float:
    """_max_scale on sequences of 4 floats."""
    s = 1.0
    for bi, pi in zip(base, part):
        for bj, pj in zip(base, part):
            dp = pi - pj
            if dp > _EPS:
                s = min(s, (limit - (bi - bj)) / dp)
    return max(0.0, s)


def mix(vehicle: Vehicle, thrust_n: float, torque_nm) -> tuple[np.ndarray, bool]:
    """F = M^-1 u with saturation to [min_thrust_n, max_thrust_n].

    Priority (why: losing attitude control is worse than losing altitude briefly):
    roll/pitch torque > yaw torque > collective thrust. If the torque part of the
    forces spreads wider than the motor range, yaw is scaled down first, then
    roll/pitch; then the collective is shifted so every motor fits.
    Returns (forces_n (4,), saturated).
    """
    forces, saturated = mix_floats(vehicle, thrust_n, torque_nm)
    return np.array(forces), saturated


def mix_floats(vehicle: Vehicle, thrust_n: float, torque_nm) -> tuple[list, bool]:
    """mix() with the forces as a list of 4 floats (the same numbers)."""
    if type(torque_nm) in (list, tuple) and len(torque_nm) == 3:
        t0, t1, t2 = float(torque_nm[0]), float(torque_nm[1]), float(torque_nm[2])
    else:
        t0, t1, t2 = np.asarray(torque_nm, dtype=np.float64).reshape(3).tolist()
    if (t0 - t0) + (t1 - t1) + (t2 - t2) != 0.0:  # a non-finite torque: numpy's NaN rules
        forces, saturated = _mix_array(vehicle, thrust_n, (t0, t1, t2))
        return forces.tolist(), saturated
    c = _consts(vehicle)
    lo, hi, limit = c.lo, c.hi, c.limit
    (_, a1, a2, a3), (_, b1, b2, b3), (_, c1, c2, c3), (_, d1, d2, d3) = c.m_inv
    saturated = False

    rp = [a1 * t0 + a2 * t1, b1 * t0 + b2 * t1, c1 * t0 + c2 * t1, d1 * t0 + d2 * t1]  # roll/pitch part
    yw = [a3 * t2, b3 * t2, c3 * t2, d3 * t2]                                          # yaw part
    both = [rp[0] + yw[0], rp[1] + yw[1], rp[2] + yw[2], rp[3] + yw[3]]
    if max(both) - min(both) > limit + _EPS:
        saturated = True
        spread_rp = max(rp) - min(rp)
        if spread_rp > limit:
            k = limit / spread_rp  # roll/pitch alone do not fit: drop yaw, scale them
            rp = [rp[0] * k, rp[1] * k, rp[2] * k, rp[3] * k]
            yw = [0.0, 0.0, 0.0, 0.0]
        else:
            k = _max_scale_floats(rp, yw, limit)
            yw = [yw[0] * k, yw[1] * k, yw[2] * k, yw[3] * k]
    diff = [rp[0] + yw[0], rp[1] + yw[1], rp[2] + yw[2], rp[3] + yw[3]]

    # Collective: the validated vehicle's M^-1 [T,0,0,0] is T/4 per motor.
    collective = float(thrust_n) / 4.0
    shifted = clip_float(collective, lo - min(diff), hi - max(diff))
    if abs(shifted - collective) > 1e-9:
        saturated = True
    # clip only removes rounding here
    return [clip_float(shifted + diff[0], lo, hi), clip_float(shifted + diff[1], lo, hi),
            clip_float(shifted + diff[2], lo, hi), clip_float(shifted + diff[3], lo, hi)], saturated


def _mix_array(vehicle: Vehicle, thrust_n: float, torque_nm) -> tuple[np.ndarray, bool]:
    """mix() in numpy: what mix_floats uses for a non-finite torque (NaN in, NaN out)."""
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
