"""Rigid-body 6-DOF quadcopter with first-order motors, linear drag and ground contact.

State x (17,): position_m (3, world ENU), velocity_m_s (3), quaternion (4, [w,x,y,z]
body->world), rate_rad_s (3, body FLU), motor_thrust_n (4). Integrated with RK4.
"""
from __future__ import annotations

import numpy as np

from flight.quat import quat_from_euler, quat_normalize, quat_to_euler, quat_to_rotation
from flight.vehicle import Vehicle

P, V, Q, W, F = slice(0, 3), slice(3, 6), slice(6, 10), slice(10, 13), slice(13, 17)


class Plant:
    def __init__(self, vehicle: Vehicle, position_m=(0.0, 0.0, 0.0), yaw_rad: float = 0.0,
                 motor_thrust_n=None, velocity_m_s=(0.0, 0.0, 0.0), rate_rad_s=(0.0, 0.0, 0.0)):
        self.vehicle = vehicle
        self._m = vehicle.mass_kg
        self._inertia = np.asarray(vehicle.inertia_kg_m2, dtype=np.float64)
        self._inertia_t = tuple(float(i) for i in self._inertia)
        self._alloc = vehicle.allocation
        self._g = np.array([0.0, 0.0, -vehicle.gravity_m_s2])
        self.x = np.zeros(17)
        self.x[P] = position_m
        self.x[V] = velocity_m_s
        self.x[Q] = quat_from_euler(0.0, 0.0, yaw_rad)
        self.x[W] = rate_rad_s
        if motor_thrust_n is not None:
            self.x[F] = motor_thrust_n
        self.landed = False
        if self.x[2] <= 0.0:
            self.x[2] = 0.0
            self._apply_ground(np.zeros(3))

    # --- accessors -----------------------------------------------------------
    @property
    def position_m(self) -> np.ndarray:
        return self.x[P].copy()

    @property
    def velocity_m_s(self) -> np.ndarray:
        return self.x[V].copy()

    @property
    def quaternion(self) -> np.ndarray:
        return self.x[Q].copy()

    @property
    def rate_rad_s(self) -> np.ndarray:
        return self.x[W].copy()

    @property
    def motor_thrust_n(self) -> np.ndarray:
        return self.x[F].copy()

    @property
    def rotation(self) -> np.ndarray:
        return quat_to_rotation(self.x[Q])

    # --- dynamics -------------------------------------------------------------
    def derivative(self, x: np.ndarray, thrust_cmd_n: np.ndarray, wind_m_s: np.ndarray) -> np.ndarray:
        # Written with scalars: numpy's per-call overhead on 3-vectors dominated the
        # simulator's time (20 evaluations per 400 Hz tick).
        vx, vy, vz, qw, qx, qy, qz, wx, wy, wz = x[3:13].tolist()
        f = x[F]
        u0, u1, u2, u3 = (self._alloc @ f).tolist()
        # third column of R(q): the body z axis in the world
        r02 = 2.0 * (qx * qz + qw * qy)
        r12 = 2.0 * (qy * qz - qw * qx)
        r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
        m, c = self._m, self.vehicle.drag_n_per_m_s
        windx, windy, windz = wind_m_s.tolist()
        ix, iy, iz = self._inertia_t
        dx = np.empty(17)
        dx[0:3] = (vx, vy, vz)
        dx[3] = (r02 * u0 - c * (vx - windx)) / m
        dx[4] = (r12 * u0 - c * (vy - windy)) / m
        dx[5] = (r22 * u0 - c * (vz - windz)) / m + self._g[2]
        dx[6:10] = (0.5 * (-qx * wx - qy * wy - qz * wz), 0.5 * (qw * wx + qy * wz - qz * wy),
                    0.5 * (qw * wy - qx * wz + qz * wx), 0.5 * (qw * wz + qx * wy - qy * wx))
        # Euler: I w' = tau - w x I w
        dx[10] = (u1 - (wy * iz * wz - wz * iy * wy)) / ix
        dx[11] = (u2 - (wz * ix * wx - wx * iz * wz)) / iy
        dx[12] = (u3 - (wx * iy * wy - wy * ix * wx)) / iz
        dx[F] = (thrust_cmd_n - f) / self.vehicle.motor_time_constant_s
        return dx

    def acceleration_m_s2(self, thrust_cmd_n, wind_m_s) -> np.ndarray:
        """World acceleration now (zero while resting on the ground)."""
        if self.landed:
            return np.zeros(3)
        return self.derivative(self.x, np.asarray(thrust_cmd_n, float), np.asarray(wind_m_s, float))[V]

    def step(self, dt_s: float, thrust_cmd_n, wind_m_s) -> None:
        """One RK4 step with the command and wind held constant over dt."""
        cmd = np.asarray(thrust_cmd_n, dtype=np.float64)
        wind = np.asarray(wind_m_s, dtype=np.float64)
        x = self.x
        k1 = self.derivative(x, cmd, wind)
        k2 = self.derivative(x + 0.5 * dt_s * k1, cmd, wind)
        k3 = self.derivative(x + 0.5 * dt_s * k2, cmd, wind)
        k4 = self.derivative(x + dt_s * k3, cmd, wind)
        x = x + dt_s / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        x[Q] = quat_normalize(x[Q])
        self.x = x
        if x[2] < 0.0 or (self.landed and x[2] <= 0.0):
            x[2] = 0.0
            self._apply_ground(wind)
        else:
            self.landed = False

    def _apply_ground(self, wind_m_s: np.ndarray) -> None:
        """At z = 0: rest (zero motion, level, keep yaw) unless the net force lifts off."""
        x = self.x
        r = quat_to_rotation(x[Q])
        # vertical force as if at rest (v = 0) so a fast impact's drag does not count as lift
        fz = (r[2, 2] * np.sum(x[F]) + self._m * self._g[2]
              + self.vehicle.drag_n_per_m_s * wind_m_s[2])
        if fz <= 0.0:
            _, _, yaw = quat_to_euler(x[Q])
            x[V] = 0.0
            x[W] = 0.0
            x[Q] = quat_from_euler(0.0, 0.0, yaw)
            self.landed = True
        else:
            x[5] = max(x[5], 0.0)  # lifting off: never move into the floor
            self.landed = False
