"""The motors as the rotors behave: the one motor model of the plant and of every model the
estimators and the planner carry.

Rotor i spins at w_i (rad/s), lagging its command w_c with a first-order time constant tau
(the vehicle file's motor_time_constant_s):

    w' = (w_c - w) / tau        held command over h:  w(h) = w_c + (w - w_c) d,  d = exp(-h / tau)

Its thrust and its reaction torque about body z go with w^2 (the vehicle file's
thrust_coefficient_kf, moment_coefficient_km):

    f = kf w^2,   torque_z = sign_i km w^2 = sign_i (km / kf) f = sign_i yaw_moment_m f

A thrust command c (N) asks for w_c = sqrt(max(c, 0) / kf).

The models that carry rotor forces (N) rather than speeds (the plan, the motor driver's
estimate, the position EKF's input) step them through the rotor speed: with s = sqrt(f)
(= sqrt(kf) w) the same lag holds for s and sqrt(c), so kf cancels:

    f(h) = (sqrt(c) + (sqrt(f) - sqrt(c)) d)^2

and the force's mean over the step, exact for a held command (e = sqrt(f) - sqrt(c)):

    mean f = c + 2 sqrt(c) e w1 + e^2 w2,   w1 = (tau / h)(1 - d),   w2 = (tau / 2h)(1 - d^2)

(The former model lagged the force itself, f' = (c - f) / tau: against RotorPy's multirotor,
whose rotors lag in speed, it drifted 8.5 mm over 3 s on the x250 and 4.8 cm and 3 deg of yaw
on the q820; this one agrees to ~1e-9 m, tests/unit/test_motor_model.py.)

Pure numpy and math; the functions taking `sqrt` work on JAX arrays too when given a
jnp square root (flight/control/ilqr.py).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def decay(dt_s: float, time_constant_s: float) -> float:
    """exp(-dt / tau): the fraction of a rotor-speed error left after dt_s."""
    return math.exp(-dt_s / time_constant_s)


def mean_weights(dt_s: float, time_constant_s: float) -> tuple[float, float, float]:
    """(d, w1, w2) of a step of dt_s (module docstring): the decay, the mean of d(t) and
    the mean of d(t)^2 over the step."""
    d = decay(dt_s, time_constant_s)
    th = time_constant_s / dt_s
    return d, th * (1.0 - d), 0.5 * th * (1.0 - d * d)


def rotor_speed_command(thrust_n, kf: float):
    """The rotor speed (rad/s) a thrust command (N) asks for: sqrt(max(c, 0) / kf)."""
    return np.sqrt(np.maximum(np.asarray(thrust_n, dtype=np.float64), 0.0) / kf)


def rotor_thrust(speed_rad_s, kf: float):
    """Thrust (N) of rotors spinning at these speeds: kf w^2."""
    w = np.asarray(speed_rad_s, dtype=np.float64)
    return kf * w * w


def rotor_torque(speed_rad_s, km: float):
    """Reaction torque magnitude (N m) of rotors at these speeds: km w^2 (the sign is the
    rotor's spin direction, the vehicle's motor_yaw_torque_sign)."""
    w = np.asarray(speed_rad_s, dtype=np.float64)
    return km * w * w


def speed_step(speed_rad_s, command_rad_s, dt_s: float, time_constant_s: float):
    """Rotor speeds after dt_s under a held speed command: the lag's exact step."""
    d = decay(dt_s, time_constant_s)
    c = np.asarray(command_rad_s, dtype=np.float64)
    return c + (np.asarray(speed_rad_s, dtype=np.float64) - c) * d


def _np_sqrt(x):
    return np.sqrt(np.maximum(x, 0.0))


def thrust_step(forces_n, command_n, dt_s: float, time_constant_s: float, sqrt=_np_sqrt):
    """Rotor forces (N) after dt_s under a held thrust command (N): the rotor-speed lag's
    exact step in thrust space (kf cancels)."""
    d = decay(dt_s, time_constant_s)
    sc = sqrt(command_n)
    s = sc + (sqrt(forces_n) - sc) * d
    return s * s


def thrust_step_and_mean(forces_n, command_n, dt_s: float, time_constant_s: float, sqrt=_np_sqrt):
    """(forces after dt_s, their mean over the step), a held thrust command: both exact."""
    d, w1, w2 = mean_weights(dt_s, time_constant_s)
    sc = sqrt(command_n)
    e = sqrt(forces_n) - sc
    s = sc + e * d
    return s * s, sc * sc + 2.0 * sc * e * w1 + e * e * w2


def thrust_step_floats(forces_n: list, command_n: list, d: float) -> list:
    """thrust_step on lists of Python floats with the decay d given (the 400 Hz paths)."""
    out = []
    for f, c in zip(forces_n, command_n):
        sc = math.sqrt(c) if c > 0.0 else 0.0
        s = sc + ((math.sqrt(f) if f > 0.0 else 0.0) - sc) * d
        out.append(s * s)
    return out


@dataclass(frozen=True)
class MotorModel:
    """The coefficients of a vehicle's rotors: kf (N s^2), km (N m s^2), tau (s)."""
    kf: float
    km: float
    time_constant_s: float

    @classmethod
    def of(cls, vehicle) -> "MotorModel":
        """From the vehicle file: thrust_coefficient_kf and moment_coefficient_km when given;
        else kf from max_thrust_n at max_rotor_speed_rad_s (1000 rad/s when that is missing
        too: kf only scales the speeds, not the forces' dynamics) and km = yaw_moment_m kf."""
        kf = vehicle.thrust_coefficient_kf
        if kf is None:
            top = vehicle.max_rotor_speed_rad_s or 1000.0
            kf = vehicle.max_thrust_n / (top * top)
        km = vehicle.moment_coefficient_km
        if km is None:
            km = vehicle.yaw_moment_m * kf
        return cls(float(kf), float(km), float(vehicle.motor_time_constant_s))

    def speed_command(self, thrust_n):
        return rotor_speed_command(thrust_n, self.kf)

    def thrust(self, speed_rad_s):
        return rotor_thrust(speed_rad_s, self.kf)

    def torque(self, speed_rad_s):
        return rotor_torque(speed_rad_s, self.km)

    def speed_step(self, speed_rad_s, command_rad_s, dt_s: float):
        return speed_step(speed_rad_s, command_rad_s, dt_s, self.time_constant_s)

    def thrust_step(self, forces_n, command_n, dt_s: float):
        return thrust_step(forces_n, command_n, dt_s, self.time_constant_s)
