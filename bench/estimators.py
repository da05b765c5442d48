"""Time per step of the estimators, against the loop period they must fit in.

    python bench/estimators.py

Prints the median time of one call (best of 5 rounds) and the share of the
loop's period it takes; the pure quaternion integration is the baseline for
the gyro-vertical.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from flight.estimation.attitude_filter import AttitudeFilter  # noqa: E402
from flight.control.laws import STOPPING_ACCEL_FRACTION, attitude_law, stopping_accel  # noqa: E402
from flight.estimation.gyrovertical import GyroIntegrator, GyroVertical, GyroVerticalParams  # noqa: E402
from flight.estimation.position_ekf import PositionEKF  # noqa: E402
from flight.vehicle import load_vehicle  # noqa: E402


def timeit(fn, n: int) -> float:
    rounds = []
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        rounds.append((time.perf_counter() - t0) / n)
    return min(rounds)


def main() -> None:
    rng = np.random.default_rng(0)
    vehicle = load_vehicle("x250")
    print("$ python bench/estimators.py")
    rows = []

    att = AttitudeFilter(np.asarray(vehicle.inertia_kg_m2))
    state = {"t": 0.0}

    def attitude_call():
        t = state["t"] = state["t"] + 0.005
        samples = [(t - 0.0025, rng.normal(0, 3e-3, 3), np.array([0, 0, 9.81]) + rng.normal(0, 1e-2, 3)),
                   (t, rng.normal(0, 3e-3, 3), np.array([0, 0, 9.81]) + rng.normal(0, 1e-2, 3))]
        att.update(samples, None, np.zeros(3), t)
    rows.append(("attitude filter, one 200 Hz call (2 IMU samples)", timeit(attitude_call, 400), 1 / 200))

    # as the attitude service calls it: decoded lists, the samples 4 ms old (the extrapolator
    # carries the estimate over the delay), the magnetometer every 4th call, an acceleration reference
    svc = AttitudeFilter(np.asarray(vehicle.inertia_kg_m2))
    imu = [(rng.normal(0, 3e-3, 3).tolist(), (np.array([0, 0, 9.81]) + rng.normal(0, 1e-2, 3)).tolist())
           for _ in range(512)]
    field = [0.0, 20.0, -45.0]
    clock_svc = {"t": 0.0, "k": 0}

    def service_call():
        t = clock_svc["t"] = clock_svc["t"] + 0.005
        k = clock_svc["k"] = (clock_svc["k"] + 2) % 512
        ts = t - 0.004
        svc.update([(ts - 0.0025, *imu[k]), (ts, *imu[k + 1])], (ts, field) if k % 8 == 0 else None,
                   [1e-3, -1e-3, 0.0], t, accel_ref=(ts - 0.11, ts - 0.01, [0.05, -0.02, 0.0]))
    rows.append(("attitude filter, as the service calls it (+ mag, ref)", timeit(service_call, 400), 1 / 200))

    inertia = vehicle.inertia_kg_m2
    gains = np.full(3, 16.0)
    max_accel = stopping_accel(vehicle.max_angular_accel_rad_s2, STOPPING_ACCEL_FRACTION)
    euler, rates, ref = np.array([0.1, -0.05, 0.3]), np.array([0.2, 0.1, -0.1]), np.array([0.0, 0.0, 0.25])
    rows.append(("attitude law (8), stopping limit (200 Hz)",
                 timeit(lambda: attitude_law(inertia, euler, rates, ref, gains, gains, max_accel), 2000), 1 / 200))

    ekf = PositionEKF(vehicle)
    ekf.initialize(0.0, [0.0, 0.0, 1.0])
    u = np.array([vehicle.mass_kg * vehicle.gravity_m_s2, 0, 0, 0])
    clock = {"t": 0.0}

    def ekf_call():
        t = clock["t"] = clock["t"] + 0.01
        ekf.predict(t, u)
        ekf.update_attitude(t, rng.normal(0, 1e-3, 3), rng.normal(0, 1e-3, 3), np.full(3, 3e-4), np.full(3, 2.5e-3))
    rows.append(("position EKF, predict + attitude update (100 Hz)", timeit(ekf_call, 400), 1 / 100))

    def camera_fix():
        ekf_call()
        ekf.update_position(clock["t"] - 0.05, [0.0, 0.0, 1.0] + rng.normal(0, 3e-3, 3), np.eye(3) * 1e-5)
    rows.append(("position EKF, + one camera fix 50 ms old (20 Hz)", timeit(camera_fix, 200), 1 / 100))

    gyro = rng.normal(0, 3e-3, 3)
    acc = np.array([0.0, 0.0, 9.81])
    gv = GyroVertical(GyroVerticalParams(), dt=0.0025)
    integ = GyroIntegrator(dt=0.0025)
    t_gv = timeit(lambda: gv.update(gyro, acc), 2000)
    t_int = timeit(lambda: integ.update(gyro, acc), 2000)
    rows.append(("gyro-vertical (004), one IMU sample", t_gv, 1 / 400))
    rows.append(("pure gyro integration (baseline), one IMU sample", t_int, 1 / 400))

    print(f"{'step':<52} {'time':>10} {'of period':>10}")
    for name, t, period in rows:
        print(f"{name:<52} {t * 1e6:>8.0f} us {100 * t / period:>9.1f}%")
    print(f"gyro-vertical / pure integration: {t_gv / t_int:.1f}x")


if __name__ == "__main__":
    main()
