"""Per-tick cost of the motor driver's failsafe law (flight/failsafe.py + law (8) + mixer),
against the normal path's mix of an attitude command: what the 400 Hz loop pays in each.

    python bench/failsafe_cost.py
"""

import timeit

import numpy as np

from flight.control import STOPPING_ACCEL_FRACTION, attitude_law, stopping_accel
from flight.failsafe import Descent, DescentParams, LevelEstimate
from flight.mixer import mix, thrust_to_pwm
from flight.vehicle import load_vehicle

v = load_vehicle("x250")
max_accel = stopping_accel(v.max_angular_accel_rad_s2, STOPPING_ACCEL_FRACTION)
k = alpha = np.array([8.0, 8.0, 2.0])
level = LevelEstimate((1.0, 0.0, 0.0, 0.0), 0.0)
descent = Descent(DescentParams(), v.mass_kg, v.gravity_m_s2, 4 * v.max_thrust_n)
descent.start(0.0, 1.0, 0.0, v.mass_kg * v.gravity_m_s2)
state = {"t": 0.0}
gyro, accel = [0.01, -0.02, 0.0], [0.05, -0.03, 9.8]


def failsafe_tick():
    state["t"] += 0.0025
    t = state["t"]
    level.update(t, gyro, accel)
    thrust = descent.update(t, level.q, accel)
    roll, pitch, yaw = level.euler
    torque = attitude_law(v.inertia_kg_m2, (roll, pitch, yaw), level.rate, (0.0, 0.0, 0.0), k, alpha, max_accel)
    forces, _ = mix(v, thrust, torque)
    thrust_to_pwm(v, np.asarray(forces))


def normal_tick():
    forces, _ = mix(v, 3.9, [0.001, -0.002, 0.0])
    thrust_to_pwm(v, forces)


for name, fn in (("normal mix", normal_tick), ("failsafe", failsafe_tick)):
    n = 20000
    best = min(timeit.repeat(fn, number=n, repeat=5)) / n
    print(f"{name:12s} {best * 1e6:7.1f} us per tick (best of 5 x {n})")
