"""Executing a rotor-speed plan (pure numpy; no JAX, no I/O): what the motor driver needs.

A plan (flight/control/ilqr.py's Plan, carried on planner/plan) starts at t0_s from the
state it was solved from: states (H+1, n), controls (H, 4) rotor speeds rad/s,
gains (H, 4, n), n = 13 (body state) or 17 (body state + rotor forces, when the
solver models the motors' lag). At time t the driver applies

    u = u_plan(t) + K(t) (x - x_plan(t)),   clipped to [0, max_rotor_speed]

(the same law as flight.control.ilqr.feedback_control, repeated here so that the 400 Hz
driver does not import JAX), and the rotor forces kf u^2 go to the motor map.

x is built from the latest estimates: position and velocity (pos/state) and
attitude and body rate (att/state), each carried to t over its age (constant
velocity, constant body rate), and, for n = 17, the rotor forces the driver's own
commands imply through the motor lag (flight.motor_model.thrust_step).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flight.quat import quat_integrate, quat_to_rotation, unit_floats

BODY_DIM = 13
QUAT = slice(6, 10)


@dataclass(frozen=True)
class RotorPlan:
    t0_s: float
    dt_s: float
    states: np.ndarray   # (H+1, n)
    controls: np.ndarray  # (H, 4) rad/s
    gains: np.ndarray    # (H, 4, n)

    @property
    def horizon(self) -> int:
        return self.controls.shape[0]

    @property
    def state_dim(self) -> int:
        return self.states.shape[1]

    @property
    def end_s(self) -> float:
        return self.t0_s + self.horizon * self.dt_s

    def valid_at(self, t_s: float) -> bool:
        return self.t0_s - 1e-9 <= t_s < self.end_s - 1e-9

    @classmethod
    def from_message(cls, msg: dict) -> "RotorPlan":
        h, n = msg["horizon"], msg["state_dim"]
        return cls(float(msg["t0_s"]), float(msg["dt_s"]),
                   np.asarray(msg["states"], dtype=np.float64).reshape(h + 1, n),
                   np.asarray(msg["controls_rad_s"], dtype=np.float64).reshape(h, 4),
                   np.asarray(msg["gains"], dtype=np.float64).reshape(h, 4, n))

    def control(self, t_s: float, x, u_max_rad_s: float) -> np.ndarray:
        """u = u_plan + K (x - x_plan) at t_s (see :func:`plan_feedback`)."""
        return plan_feedback(self.states, self.controls, self.gains, self.dt_s, t_s - self.t0_s, x, u_max_rad_s)


def plan_feedback(states, controls, gains, dt_s: float, elapsed_s: float, x, u_max_rad_s: float) -> np.ndarray:
    """u = u_plan + K (x - x_plan), elapsed_s into a plan; controls and gains held over each
    step, the planned state interpolated; x's quaternion sign-aligned with the plan's."""
    horizon = controls.shape[0]
    s = min(max(elapsed_s / dt_s, 0.0), horizon - 1e-9)
    k = int(s)
    frac = s - k
    x_plan = (1 - frac) * states[k] + frac * states[k + 1]
    x = np.array(x, dtype=np.float64)
    if np.dot(x[QUAT], x_plan[QUAT]) < 0:
        x[QUAT] = -x[QUAT]
    u = controls[k] + gains[k] @ (x - x_plan)
    return np.clip(u, 0.0, u_max_rad_s)


def body_state(t_s: float, att: dict, pos: dict, vehicle=None, rotor_forces_n=None) -> np.ndarray:
    """The 13-state [p, v, q, w] at t_s from an att/state and a pos/state message,
    each carried forward over its age (never backward).

    With the vehicle and the rotor forces being flown (the plan's model: the motor lag
    state), the translation is carried by the model (000's delay compensation by model
    extrapolation): acceleration = body z * thrust / m - g - drag v / m at the carried
    attitude. Without, at constant velocity. A pos/state is up to a period and a hop old
    (10-12 ms at 100 Hz): through a flip the vertical acceleration swings by 2 g, and a
    velocity 0.1-0.2 m/s stale made the plan, and the driver's feedback on it, lag the turn
    (docs/flip-history.md, "Estimation through the flip")."""
    a_age = max(0.0, t_s - att["header"]["t_s"])
    p_age = max(0.0, t_s - pos["header"]["t_s"])
    try:   # in Python floats: the same operations in the same order as below, without numpy's per-call cost
        return np.array(_body_state_floats(a_age, p_age, att, pos, vehicle, rotor_forces_n))
    except (ZeroDivisionError, ValueError, TypeError):   # a zero quaternion, odd values: numpy's way
        return _body_state_arrays(a_age, p_age, att, pos, vehicle, rotor_forces_n)


def _body_state_arrays(a_age: float, p_age: float, att: dict, pos: dict, vehicle, rotor_forces_n) -> np.ndarray:
    """body_state in numpy (the definition _body_state_floats follows)."""
    v = np.asarray(pos["velocity_m_s"], dtype=np.float64)
    p = np.asarray(pos["position_m"], dtype=np.float64)
    w = np.asarray(att["rate_rad_s"], dtype=np.float64)
    q = quat_integrate(att["quaternion_wxyz"], w, a_age)
    if vehicle is not None and rotor_forces_n is not None and p_age > 0.0:
        accel = thrust_acceleration(vehicle, q, rotor_forces_n, v)
        return np.concatenate([p + v * p_age + 0.5 * accel * p_age ** 2, v + accel * p_age, q, w])
    return np.concatenate([p + v * p_age, v, q, w])


def _body_state_floats(a_age: float, p_age: float, att: dict, pos: dict, vehicle, rotor_forces_n) -> list:
    """body_state's 13 values as floats, bit for bit (tests/unit/flight/control/test_plan.py):
    quat_integrate, thrust_acceleration and the carry written out; the norms and the sum of
    the forces in numpy's order for 3- and 4-vectors (squares, then terms, summed in order)."""
    px, py, pz = [float(c) for c in pos["position_m"]]
    vx, vy, vz = [float(c) for c in pos["velocity_m_s"]]
    wx, wy, wz = [float(c) for c in att["rate_rad_s"]]
    qw, qx, qy, qz = [float(c) for c in att["quaternion_wxyz"]]
    norm = math.sqrt(wx * wx + wy * wy + wz * wz)
    angle = norm * a_age
    if not angle < 1e-12:   # quat_integrate: q (x) exp(0.5 w h), normalised
        s = math.sin(0.5 * angle)
        dw, dx, dy, dz = math.cos(0.5 * angle), s * (wx / norm), s * (wy / norm), s * (wz / norm)
        qw, qx, qy, qz = (qw * dw - qx * dx - qy * dy - qz * dz, qw * dx + qx * dw + qy * dz - qz * dy,
                          qw * dy - qx * dz + qy * dw + qz * dx, qw * dz + qx * dy - qy * dx + qz * dw)
        n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qw, qx, qy, qz = qw / n, qx / n, qy / n, qz / n
    if vehicle is not None and rotor_forces_n is not None and p_age > 0.0:
        forces = rotor_forces_n.tolist() if isinstance(rotor_forces_n, np.ndarray) else [float(f) for f in rotor_forces_n]
        if len(forces) > 7:   # numpy sums longer arrays pairwise
            raise ValueError("more than 7 rotor forces")
        collective = forces[0]
        for f in forces[1:]:
            collective += f
        w, x, y, z = unit_floats(qw, qx, qy, qz)   # quat_to_rotation's third column
        bx, by, bz = 2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)
        drag, mass = vehicle.drag_n_per_m_s, vehicle.mass_kg
        ax = (bx * collective - drag * vx) / mass - 0.0
        ay = (by * collective - drag * vy) / mass - 0.0
        az = (bz * collective - drag * vz) / mass - vehicle.gravity_m_s2
        age2 = p_age ** 2
        return [px + vx * p_age + 0.5 * ax * age2, py + vy * p_age + 0.5 * ay * age2,
                pz + vz * p_age + 0.5 * az * age2, vx + ax * p_age, vy + ay * p_age, vz + az * p_age,
                qw, qx, qy, qz, wx, wy, wz]
    return [px + vx * p_age, py + vy * p_age, pz + vz * p_age, vx, vy, vz, qw, qx, qy, qz, wx, wy, wz]


def thrust_acceleration(vehicle, q, rotor_forces_n, velocity_m_s) -> np.ndarray:
    """World acceleration (3,) of the rigid body under these rotor forces at attitude q:
    the collective along body z over the mass, gravity and the linear drag (the model of
    flight/control/ilqr.py and the simulator's plant)."""
    collective_n = float(np.sum(np.asarray(rotor_forces_n, dtype=np.float64)))
    body_z = quat_to_rotation(q)[:, 2]
    drag = vehicle.drag_n_per_m_s * np.asarray(velocity_m_s, dtype=np.float64)
    return (body_z * collective_n - drag) / vehicle.mass_kg - np.array([0.0, 0.0, vehicle.gravity_m_s2])


# allocation matrices seen by scale_collective -> (the matrix, the first column of its inverse);
# by identity: a vehicle's allocation is computed once (Vehicle.allocation) and never changed
_COLLECTIVE_COLUMN: dict[int, tuple[np.ndarray, tuple]] = {}


def _collective_column(allocation) -> tuple | None:
    """M^-1 [1, 0, 0, 0] as 4 floats for a 4x4 allocation array, else None."""
    entry = _COLLECTIVE_COLUMN.get(id(allocation))
    if entry is not None and entry[0] is allocation:
        return entry[1]
    if type(allocation) is not np.ndarray or allocation.shape != (4, 4):
        return None
    if len(_COLLECTIVE_COLUMN) >= 64:
        _COLLECTIVE_COLUMN.clear()
    column = tuple(np.linalg.solve(allocation, np.array([1.0, 0.0, 0.0, 0.0])).tolist())
    _COLLECTIVE_COLUMN[id(allocation)] = (allocation, column)
    return column


def scale_collective(allocation, forces_n, factor: float) -> np.ndarray:
    """Rotor forces with the collective thrust times factor and the body torques kept.

    A plan is solved on the airframe file's model; the position EKF estimates the
    thrust scale s (real collective per newton commanded, < 1 when the vehicle is
    heavier). The driver sends scale_collective(A, plan forces, 1/s) so the vehicle
    accelerates as planned, and the planner models what was sent as
    scale_collective(A, sent, s). Torques are left alone: a payload changes mass, not
    what a rotor force does about the centre.

    Computed as F + M^-1 [(factor - 1) T, 0, 0, 0] with T the collective of F (M^-1's
    first column cached per allocation): the same as solving M F' = [factor T, torques]."""
    f = np.asarray(forces_n, dtype=np.float64)
    column = _collective_column(allocation) if f.shape == (4,) else None
    if column is None:
        wrench = np.asarray(allocation) @ f
        wrench[0] *= factor
        return np.linalg.solve(allocation, wrench)
    return np.array(_scale_collective_4(allocation, f.tolist(), factor, column))


def scale_collective_floats(allocation, forces_n: list, factor: float) -> list:
    """scale_collective of 4 Python floats with a 4x4 allocation array, as a list (the same
    numbers: the 400 Hz motor driver keeps its forces in floats)."""
    column = _collective_column(allocation)
    if column is None or len(forces_n) != 4:
        return scale_collective(allocation, forces_n, factor).tolist()
    return _scale_collective_4(allocation, forces_n, factor, column)


def _scale_collective_4(allocation, forces_n, factor: float, column: tuple) -> list:
    f0, f1, f2, f3 = forces_n
    r0, r1, r2, r3 = allocation[0].tolist()
    extra = (factor - 1.0) * (r0 * f0 + r1 * f1 + r2 * f2 + r3 * f3)
    k0, k1, k2, k3 = column
    return [f0 + k0 * extra, f1 + k1 * extra, f2 + k2 * extra, f3 + k3 * extra]
