"""The motors as the rotors behave: the one motor model of the plant and of every model the
estimators and the planner carry.

Rotor i spins at w_i (rad/s), lagging its command w_c with a first-order time constant tau
(the vehicle file's motor_time_constant_s):

    w' = (w_c - w) / tau        held command over h:  w(h) = w_c + (w - w_c) d,  d = exp(-h / tau)

Its thrust and its reaction torque about body z go with w^2 (the vehicle file's
thrust_coefficient_kf, moment_coefficient_km):

    f = kf w^2,   torque_z = sign_i km w^2 = sign_i (km / kf) f = sign_i yaw_moment_m f

A thrust command c (N) asks for w_c = sqrt(max(c, 0) / kf). The ESC takes it as a pulse width,
linear in thrust between the vehicle file's pwm_min_us (0 N) and pwm_max_us (max_thrust_n),
document 000's map (thrust_to_pwm, pwm_to_thrust): the motor driver sends it, the simulator
reads it back.

The models that carry rotor forces (N) rather than speeds (the plan, the motor driver's
estimate, the position EKF's input) step them through the rotor speed: with s = sqrt(f)
(= sqrt(kf) w) the same lag holds for s and sqrt(c), so kf cancels:

    f(h) = (sqrt(c) + (sqrt(f) - sqrt(c)) d)^2

and the force's mean over the step, exact for a held command (e = sqrt(f) - sqrt(c)):

    mean f = c + 2 sqrt(c) e w1 + e^2 w2,   w1 = (tau / h)(1 - d),   w2 = (tau / 2h)(1 - d^2)

A rotor lags in speed, not in thrust: against RotorPy's multirotor this model agrees to
rounding where a thrust lag drifts by millimetres (tests/unit/flight/test_motor_model.py;
docs/flip-history.md, "The motors lag in rotor speed").

Pure numpy and math. root_step and root_step_and_mean are plain arithmetic, so they run on
floats, numpy arrays and JAX arrays alike (flight/control/ilqr.py, flight/control/predict.py);
the *_floats forms are the same operations on lists of Python floats for the 400 Hz paths
(the motor driver, the simulator, the position EKF's input), the same bits without numpy's
per-call cost.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flight.vehicle import per_vehicle_cache


def decay(dt_s: float, time_constant_s, exp=math.exp):
    """exp(-dt / tau): the fraction of a rotor-speed error left after dt_s. exp: jnp.exp
    for a time constant that is a JAX array (flight/control/predict.py draws it per case)."""
    return exp(-dt_s / time_constant_s)


def mean_weights(dt_s: float, time_constant_s, exp=math.exp) -> tuple:
    """(d, w1, w2) of a step of dt_s (module docstring): the decay, the mean of d(t) and
    the mean of d(t)^2 over the step."""
    d = decay(dt_s, time_constant_s, exp)
    th = time_constant_s / dt_s
    return d, th * (1.0 - d), 0.5 * th * (1.0 - d * d)


def rk4_stage_decays(dt_s: float, time_constant_s: float) -> tuple[float, float, float, float]:
    """The decays of a held command's lag at the times RK4's stages 2, 3 and 4 look at
    (dt/2, dt/2, dt) and at the step's end (dt): there the rotor speeds are exactly
    w = c + d (w0 - c), so a rigid-body integrator can take them from the lag's solution."""
    half, full = decay(0.5 * dt_s, time_constant_s), decay(dt_s, time_constant_s)
    return half, half, full, full


def speed_derivative(speed_rad_s, command_rad_s, time_constant_s: float):
    """w' = (w_c - w) / tau, the lag's differential equation (floats or arrays)."""
    return (command_rad_s - speed_rad_s) / time_constant_s


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


def speed_command_floats(thrust_n, kf: float) -> list:
    """rotor_speed_command on a sequence of Python floats, as a list."""
    return [math.sqrt(c / kf) if c > 0.0 else 0.0 for c in thrust_n]


def speed_step(speed_rad_s, command_rad_s, dt_s: float, time_constant_s: float):
    """Rotor speeds after dt_s under a held speed command: the lag's exact step (root_step:
    sqrt(f) is sqrt(kf) w)."""
    return root_step(np.asarray(speed_rad_s, dtype=np.float64), np.asarray(command_rad_s, dtype=np.float64),
                     decay(dt_s, time_constant_s))


def root_step(root_forces, root_command, d):
    """s = sqrt(f) after a step whose decay is d, from s and s_c = sqrt(c): the lag's exact
    step (s is sqrt(kf) w). Floats or arrays of any array module."""
    return root_command + (root_forces - root_command) * d


def root_step_and_mean(root_forces, root_command, weights):
    """(forces after the step, their mean over it) from s = sqrt(f) and s_c = sqrt(c), with
    weights = mean_weights(dt_s, tau): both exact for a held command (module docstring).
    Floats or arrays of any array module."""
    d, w1, w2 = weights
    e = root_forces - root_command
    s = root_command + e * d
    return s * s, root_command * root_command + 2.0 * root_command * e * w1 + e * e * w2


def _np_sqrt(x):
    return np.sqrt(np.maximum(x, 0.0))


def thrust_step(forces_n, command_n, dt_s: float, time_constant_s: float) -> np.ndarray:
    """Rotor forces (N) after dt_s under a held thrust command (N): the rotor-speed lag's
    exact step in thrust space (kf cancels). Two 4-vectors (the 400 Hz motor driver) go
    through thrust_step_floats."""
    d = decay(dt_s, time_constant_s)
    f, c = np.asarray(forces_n, dtype=np.float64), np.asarray(command_n, dtype=np.float64)
    if f.shape == (4,) and c.shape == (4,):
        return np.array(thrust_step_floats(f.tolist(), c.tolist(), d))
    s = root_step(_np_sqrt(f), _np_sqrt(c), d)
    return s * s


def thrust_step_and_mean(forces_n, command_n, dt_s: float, time_constant_s, sqrt=_np_sqrt, exp=math.exp):
    """(forces after dt_s, their mean over the step), a held thrust command: both exact.
    sqrt: the square root of forces >= 0 and exp (numpy's and math's by default; jnp ones
    for JAX arrays)."""
    return root_step_and_mean(sqrt(forces_n), sqrt(command_n), mean_weights(dt_s, time_constant_s, exp))


def thrust_step_floats(forces_n: list, command_n: list, d: float) -> list:
    """thrust_step on lists of Python floats with the decay d given (the 400 Hz paths)."""
    out = []
    for f, c in zip(forces_n, command_n):
        sc = math.sqrt(c) if c > 0.0 else 0.0
        s = sc + ((math.sqrt(f) if f > 0.0 else 0.0) - sc) * d   # root_step, written out
        out.append(s * s)
    return out


def thrust_step_and_mean_floats(forces_n: list, command_n: list, weights) -> tuple[list, list]:
    """thrust_step_and_mean on lists of Python floats (forces and commands, N), with
    weights = mean_weights(dt_s, tau): (forces after the step, their means)."""
    d, w1, w2 = weights
    ends, means = [], []
    for f, c in zip(forces_n, command_n):
        sc = math.sqrt(c) if c > 0.0 else 0.0
        e = (math.sqrt(f) if f > 0.0 else 0.0) - sc   # root_step_and_mean, written out
        s = sc + e * d
        ends.append(s * s)
        means.append(sc * sc + 2.0 * sc * e * w1 + e * e * w2)
    return ends, means


@dataclass(frozen=True)
class MotorModel:
    """The coefficients of a vehicle's rotors: kf (N s^2), km (N m s^2), tau (s)."""
    kf: float
    km: float
    time_constant_s: float

    @classmethod
    def of(cls, vehicle) -> "MotorModel":
        """From the vehicle file: thrust_coefficient_kf and moment_coefficient_km when given;
        else kf from max_thrust_n at max_rotor_speed_rad_s (the loader requires one of the two)
        and km = yaw_moment_m kf."""
        kf = vehicle.thrust_coefficient_kf
        if kf is None:
            top = vehicle.max_rotor_speed_rad_s
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


# --------------------------------------------------------------------------- the ESC's PWM map

def clip_float(x: float, lo: float, hi: float) -> float:
    """np.clip on floats: min(max(x, lo), hi), NaN kept (the 400 Hz paths)."""
    x = lo if x < lo else x
    return hi if x > hi else x


class _PwmConsts:
    """What the PWM map reads of a vehicle, as floats (vehicles are frozen)."""

    __slots__ = ("max_thrust", "min_thrust", "pwm_max", "pwm_min", "pwm_span")

    def __init__(self, vehicle):
        self.pwm_min, self.pwm_max = float(vehicle.pwm_min_us), float(vehicle.pwm_max_us)
        self.pwm_span = vehicle.pwm_max_us - vehicle.pwm_min_us
        self.max_thrust = vehicle.max_thrust_n
        self.min_thrust = float(vehicle.min_thrust_n)


_pwm_consts = per_vehicle_cache(_PwmConsts)


def thrust_to_pwm(vehicle, forces_n) -> np.ndarray:
    """Linear map of 000: pwm = pwm_min + F/max_thrust*(pwm_max-pwm_min), clipped. A
    4-vector (the 400 Hz driver) goes through thrust_to_pwm_floats."""
    f = np.asarray(forces_n, dtype=np.float64)
    if f.shape == (4,):
        return np.array(thrust_to_pwm_floats(vehicle, f.tolist()))
    span = vehicle.pwm_max_us - vehicle.pwm_min_us
    pwm = vehicle.pwm_min_us + f / vehicle.max_thrust_n * span
    return np.clip(pwm, vehicle.pwm_min_us, vehicle.pwm_max_us)


def thrust_to_pwm_floats(vehicle, forces_n) -> list:
    """thrust_to_pwm on a sequence of floats, as a list."""
    c = _pwm_consts(vehicle)
    lo, hi, span, f_max = c.pwm_min, c.pwm_max, c.pwm_span, c.max_thrust
    return [clip_float(lo + f / f_max * span, lo, hi) for f in forces_n]


def pwm_to_thrust(vehicle, pwm_us) -> np.ndarray:
    """Inverse of thrust_to_pwm, clipped to [min_thrust_n, max_thrust_n]."""
    p = np.asarray(pwm_us, dtype=np.float64)
    if p.shape == (4,):
        return np.array(pwm_to_thrust_floats(vehicle, p.tolist()))
    span = vehicle.pwm_max_us - vehicle.pwm_min_us
    f = (p - vehicle.pwm_min_us) / span * vehicle.max_thrust_n
    return np.clip(f, vehicle.min_thrust_n, vehicle.max_thrust_n)


def pwm_to_thrust_floats(vehicle, pwm_us) -> list:
    """pwm_to_thrust on a sequence of floats, as a list (the simulator's 400 Hz tick)."""
    c = _pwm_consts(vehicle)
    p_min, span, f_max, f_min = c.pwm_min, c.pwm_span, c.max_thrust, c.min_thrust
    return [clip_float((p - p_min) / span * f_max, f_min, f_max) for p in pwm_us]
