"""Per-tick cost of the motor driver's failsafe law (flight/control/failsafe.py + law (8) + mixer),
against the normal path's mix of an attitude command: what the 400 Hz loop pays in each.

    python bench/failsafe_cost.py
"""

import timeit

import numpy as np

from flight.control.laws import STOPPING_ACCEL_FRACTION, attitude_law, stopping_accel
from flight.control.failsafe import Descent, DescentParams, LevelEstimate
from flight.control.mixer import mix
from flight.motor_model import thrust_to_pwm
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


# the normal path's read of the attitude command: before (latest) and now (take + two age checks)
import schemas  # noqa: E402
from services.runtime import Inbox  # noqa: E402


class _Rt:
    rejected, dropped, lockstep, event_driven, wakes = {}, {}, False, False, False

    def _sync_tick(self, upstream):
        return 0


payload = schemas.ATTITUDE_COMMAND.encode(1.0, 0, "attitude", {"thrust_n": 3.9, "torque_nm": [0.0, 0.0, 0.0],
                                                                "imu_t_s": 0.999})
import zenoh  # noqa: E402

sample = type("S", (), {"payload": zenoh.ZBytes(payload)})()   # the inbox checks its length before copying
box_latest, box_take = Inbox(_Rt(), schemas.ATTITUDE_COMMAND, "c", "attitude", 4), Inbox(_Rt(), schemas.ATTITUDE_COMMAND, "c", "attitude", 4)
held = {"cmd": None}


def read_latest():   # one command every other tick (200 Hz into 400 Hz)
    box_latest._on_sample(sample)
    box_latest.latest()
    box_latest.latest()


def read_take():
    box_take._on_sample(sample)
    for _ in range(2):
        t = 1.001
        for c in box_take.take():
            if t - c["header"]["t_s"] > 0.05 or (c["imu_t_s"] >= 0.0 and t - c["imu_t_s"] > 0.05):
                pass
            else:
                held["cmd"] = c
        c = held["cmd"]
        if c is not None and (t - c["header"]["t_s"] > 0.05 or (c["imu_t_s"] >= 0.0 and t - c["imu_t_s"] > 0.05)):
            held["cmd"] = None


for name, fn in (("latest (before)", read_latest), ("take + ages (now)", read_take)):
    n = 20000
    best = min(timeit.repeat(fn, number=n, repeat=5)) / n / 2
    print(f"{name:18s} {best * 1e6:7.2f} us per tick reading the command (decode included)")
