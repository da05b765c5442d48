"""Rigid-body 6-DOF quadcopter with first-order motors, linear drag and ground contact.

State x (17,): position_m (3, world ENU), velocity_m_s (3), quaternion (4, [w,x,y,z]
body->world), rate_rad_s (3, body FLU), rotor_speed_rad_s (4). The motors are
flight.motor_model's: each rotor's speed lags its command sqrt(c / kf) by the vehicle's
motor_time_constant_s, its thrust is kf w^2 (motor_thrust_n) and its yaw torque
km w^2 = yaw_moment_m kf w^2 (the allocation). The rigid body is integrated with RK4, the
rotor speeds with the lag's exact step (RK4's stages see the exact speeds at their times).

The integrator runs on plain Python floats: the simulator takes 5 RK4 steps (20
derivative evaluations) per 400 Hz tick, and numpy's ~1 us per call on 3- and
4-vectors made that most of the simulator's time. The equations are the ones of
:meth:`Plant.derivative`; tests/unit/simulator/test_fast.py checks it against a plain numpy
integrator (bench/support/sim_reference.py): the two agree to rounding.
"""
from __future__ import annotations

import math

import numpy as np

from flight.motor_model import (
    MotorModel,
    rk4_stage_decays,
    speed_command_floats,
    speed_derivative,
)
from flight.quat import quat_from_euler, quat_to_rotation
from flight.vehicle import Vehicle

P, V, Q, W, F = slice(0, 3), slice(3, 6), slice(6, 10), slice(10, 13), slice(13, 17)


def rotation_rows(qw: float, qx: float, qy: float, qz: float) -> tuple:
    """R(q) body->world row-major as 9 floats (q normalised first, as flight.quat.quat_to_rotation)."""
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    if n == 0.0 or not math.isfinite(n):
        raise ValueError("cannot normalise a zero or non-finite quaternion")
    w, x, y, z = qw / n, qx / n, qy / n, qz / n
    return (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))


def _floats(v, n: int) -> list:
    """v (n numbers, or what broadcasts to n as in numpy arithmetic) as a list of Python floats."""
    if type(v) is np.ndarray and v.shape == (n,):
        return v.astype(np.float64, copy=False).tolist()
    if type(v) in (list, tuple) and len(v) == n:
        try:
            return [float(e) for e in v]
        except TypeError:
            pass
    return np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)).tolist()


class Plant:
    def __init__(self, vehicle: Vehicle, position_m=(0.0, 0.0, 0.0), yaw_rad: float = 0.0,
                 motor_thrust_n=None, velocity_m_s=(0.0, 0.0, 0.0), rate_rad_s=(0.0, 0.0, 0.0)):
        self.vehicle = vehicle
        self._m = float(vehicle.mass_kg)
        self._inertia = np.asarray(vehicle.inertia_kg_m2, dtype=np.float64)
        self._inertia_t = tuple(float(i) for i in self._inertia)
        self._alloc = vehicle.allocation
        self._alloc_rows = tuple(tuple(float(e) for e in row) for row in np.asarray(self._alloc, dtype=np.float64))
        self._g = np.array([0.0, 0.0, -vehicle.gravity_m_s2])
        self._gz = float(self._g[2])
        self._drag = float(vehicle.drag_n_per_m_s)
        self.motors = MotorModel.of(vehicle)
        self._kf = self.motors.kf
        self._tau = self.motors.time_constant_s
        self._lag = {}  # dt -> the lag's decays at RK4's stage times (see _lag_factors)
        self.x = np.zeros(17)
        self.x[P] = position_m
        self.x[V] = velocity_m_s
        self.x[Q] = quat_from_euler(0.0, 0.0, yaw_rad)
        self.x[W] = rate_rad_s
        if motor_thrust_n is not None:
            self.x[F] = self.motors.speed_command(motor_thrust_n)
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
        """Thrust of each rotor now (N): kf w^2."""
        return self.motors.thrust(self.x[F])

    def motor_thrust_floats(self) -> list:
        """motor_thrust_n as 4 Python floats."""
        kf = self._kf
        return [kf * w * w for w in self.x[F].tolist()]

    @property
    def rotor_speed_rad_s(self) -> np.ndarray:
        return self.x[F].copy()

    @property
    def rotation(self) -> np.ndarray:
        return quat_to_rotation(self.x[Q])

    def rotation_rows(self) -> tuple:
        """R body->world now, row-major as 9 floats (what :attr:`rotation` holds)."""
        return rotation_rows(*self.x[Q].tolist())

    # --- dynamics -------------------------------------------------------------
    def derivative(self, x: np.ndarray, thrust_cmd_n: np.ndarray, wind_m_s: np.ndarray) -> np.ndarray:
        """dx/dt (17,) at state x under the command and the wind (the model; step() integrates it)."""
        vx, vy, vz, qw, qx, qy, qz, wx, wy, wz, o0, o1, o2, o3 = _floats(x, 17)[3:]
        kf = self._kf
        f0, f1, f2, f3 = kf * o0 * o0, kf * o1 * o1, kf * o2 * o2, kf * o3 * o3
        (a00, a01, a02, a03), (a10, a11, a12, a13), (a20, a21, a22, a23), (a30, a31, a32, a33) = self._alloc_rows
        u0 = a00 * f0 + a01 * f1 + a02 * f2 + a03 * f3
        u1 = a10 * f0 + a11 * f1 + a12 * f2 + a13 * f3
        u2 = a20 * f0 + a21 * f1 + a22 * f2 + a23 * f3
        u3 = a30 * f0 + a31 * f1 + a32 * f2 + a33 * f3
        # third column of R(q): the body z axis in the world
        r02 = 2.0 * (qx * qz + qw * qy)
        r12 = 2.0 * (qy * qz - qw * qx)
        r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
        m, c = self._m, self._drag
        windx, windy, windz = _floats(wind_m_s, 3)
        c0, c1, c2, c3 = speed_command_floats(_floats(thrust_cmd_n, 4), kf)
        ix, iy, iz = self._inertia_t
        tau = self._tau
        return np.array([
            vx, vy, vz,
            (r02 * u0 - c * (vx - windx)) / m,
            (r12 * u0 - c * (vy - windy)) / m,
            (r22 * u0 - c * (vz - windz)) / m + self._gz,
            0.5 * (-qx * wx - qy * wy - qz * wz), 0.5 * (qw * wx + qy * wz - qz * wy),
            0.5 * (qw * wy - qx * wz + qz * wx), 0.5 * (qw * wz + qx * wy - qy * wx),
            # Euler: I w' = tau - w x I w
            (u1 - (wy * iz * wz - wz * iy * wy)) / ix,
            (u2 - (wz * ix * wx - wx * iz * wz)) / iy,
            (u3 - (wx * iy * wy - wy * ix * wx)) / iz,
            speed_derivative(o0, c0, tau), speed_derivative(o1, c1, tau),
            speed_derivative(o2, c2, tau), speed_derivative(o3, c3, tau),
        ])

    def acceleration_floats(self, wind_m_s) -> tuple:
        """World acceleration now as 3 floats (zero while resting on the ground).

        It does not depend on the command: the motors' thrust is a state."""
        if self.landed:
            return (0.0, 0.0, 0.0)
        return self._acceleration(self.x.tolist(), _floats(wind_m_s, 3))

    def _acceleration(self, x: list, wind: list) -> tuple:
        """acceleration_floats (in the air) from the state x (17 floats) and the wind (3 floats)."""
        _, _, _, vx, vy, vz, qw, qx, qy, qz, _, _, _, o0, o1, o2, o3 = x
        a00, a01, a02, a03 = self._alloc_rows[0]
        u0 = self._kf * (a00 * o0 * o0 + a01 * o1 * o1 + a02 * o2 * o2 + a03 * o3 * o3)
        windx, windy, windz = wind
        m, c = self._m, self._drag
        return ((2.0 * (qx * qz + qw * qy) * u0 - c * (vx - windx)) / m,
                (2.0 * (qy * qz - qw * qx) * u0 - c * (vy - windy)) / m,
                ((1.0 - 2.0 * (qx * qx + qy * qy)) * u0 - c * (vz - windz)) / m + self._gz)

    def acceleration_m_s2(self, thrust_cmd_n, wind_m_s) -> np.ndarray:
        """World acceleration now (zero while resting on the ground)."""
        return np.array(self.acceleration_floats(wind_m_s))

    def step(self, dt_s: float, thrust_cmd_n, wind_m_s) -> None:
        """One RK4 step with the command and wind held constant over dt."""
        self.advance(dt_s, 1, thrust_cmd_n, wind_m_s)

    def _lag_factors(self, dt_s: float) -> tuple:
        """The rotor-speed lag's exact decays at RK4's stage times, (beta_2, beta_3, beta_4,
        end) of flight.motor_model.rk4_stage_decays: the stages see w = c + beta_i e (e = w - c)
        and the step ends at w = c + end e. Cached per dt."""
        k = self._lag.get(dt_s)
        if k is None:
            k = self._lag[dt_s] = rk4_stage_decays(dt_s, self._tau)
        return k

    def advance(self, dt_s: float, steps: int, thrust_cmd_n, wind_m_s) -> None:
        """`steps` RK4 steps of dt_s (ground contact after each) with the command and
        wind held constant: the same as calling step() `steps` times."""
        self._advance(float(dt_s), int(steps), _floats(thrust_cmd_n, 4), _floats(wind_m_s, 3))

    def _advance(self, dt_s: float, steps: int, thrust_cmd_n: list, wind_m_s: list) -> None:
        """advance() on Python floats: the command (4) and the wind (3) as lists of floats."""
        kf = self._kf
        c0, c1, c2, c3 = speed_command_floats(thrust_cmd_n, kf)  # rotor speeds
        windx, windy, windz = wind_m_s
        px, py, pz, vx, vy, vz, qw, qx, qy, qz, wx, wy, wz, f0, f1, f2, f3 = self.x.tolist()  # f: rotor speeds
        (a00, a01, a02, a03), (a10, a11, a12, a13), (a20, a21, a22, a23), (a30, a31, a32, a33) = self._alloc_rows
        m, c, gz = self._m, self._drag, self._gz
        ix, iy, iz = self._inertia_t
        b2, b3, b4, lag = self._lag_factors(dt_s)
        h2, h, h6 = 0.5 * dt_s, dt_s, dt_s / 6.0
        landed = self.landed
        # the forces kf (c + beta e)^2 = kf c^2 + beta 2 kf c e + beta^2 kf e^2 at each stage
        # (e = w - c), so the wrench A f = A fc + beta (A g) + beta^2 (A h)
        fc0, fc1, fc2, fc3 = kf * c0 * c0, kf * c1 * c1, kf * c2 * c2, kf * c3 * c3
        uc0 = a00 * fc0 + a01 * fc1 + a02 * fc2 + a03 * fc3
        uc1 = a10 * fc0 + a11 * fc1 + a12 * fc2 + a13 * fc3
        uc2 = a20 * fc0 + a21 * fc1 + a22 * fc2 + a23 * fc3
        uc3 = a30 * fc0 + a31 * fc1 + a32 * fc2 + a33 * fc3
        k2 = 2.0 * kf
        for _ in range(steps):
            # e, A g and A h from the speeds each step, so n steps here are n calls of step() exactly
            e0, e1, e2, e3 = f0 - c0, f1 - c1, f2 - c2, f3 - c3
            g0, g1, g2, g3 = k2 * c0 * e0, k2 * c1 * e1, k2 * c2 * e2, k2 * c3 * e3
            j0, j1, j2, j3 = kf * e0 * e0, kf * e1 * e1, kf * e2 * e2, kf * e3 * e3
            d0 = a00 * g0 + a01 * g1 + a02 * g2 + a03 * g3
            d1 = a10 * g0 + a11 * g1 + a12 * g2 + a13 * g3
            d2 = a20 * g0 + a21 * g1 + a22 * g2 + a23 * g3
            d3 = a30 * g0 + a31 * g1 + a32 * g2 + a33 * g3
            s0 = a00 * j0 + a01 * j1 + a02 * j2 + a03 * j3
            s1 = a10 * j0 + a11 * j1 + a12 * j2 + a13 * j3
            s2 = a20 * j0 + a21 * j1 + a22 * j2 + a23 * j3
            s3 = a30 * j0 + a31 * j1 + a32 * j2 + a33 * j3
            # k1 at (v, q, w); the position enters no derivative
            u0, u1, u2, u3 = uc0 + d0 + s0, uc1 + d1 + s1, uc2 + d2 + s2, uc3 + d3 + s3
            ax1 = (2.0 * (qx * qz + qw * qy) * u0 - c * (vx - windx)) / m
            ay1 = (2.0 * (qy * qz - qw * qx) * u0 - c * (vy - windy)) / m
            az1 = ((1.0 - 2.0 * (qx * qx + qy * qy)) * u0 - c * (vz - windz)) / m + gz
            qw1 = 0.5 * (-qx * wx - qy * wy - qz * wz)
            qx1 = 0.5 * (qw * wx + qy * wz - qz * wy)
            qy1 = 0.5 * (qw * wy - qx * wz + qz * wx)
            qz1 = 0.5 * (qw * wz + qx * wy - qy * wx)
            wx1 = (u1 - (wy * iz * wz - wz * iy * wy)) / ix
            wy1 = (u2 - (wz * ix * wx - wx * iz * wz)) / iy
            wz1 = (u3 - (wx * iy * wy - wy * ix * wx)) / iz
            # k2 at x + dt/2 k1
            vx2, vy2, vz2 = vx + h2 * ax1, vy + h2 * ay1, vz + h2 * az1
            sw, sx, sy, sz = qw + h2 * qw1, qx + h2 * qx1, qy + h2 * qy1, qz + h2 * qz1
            rx, ry, rz = wx + h2 * wx1, wy + h2 * wy1, wz + h2 * wz1
            bb = b2 * b2
            u0, u1, u2, u3 = (uc0 + b2 * d0 + bb * s0, uc1 + b2 * d1 + bb * s1,
                              uc2 + b2 * d2 + bb * s2, uc3 + b2 * d3 + bb * s3)
            ax2 = (2.0 * (sx * sz + sw * sy) * u0 - c * (vx2 - windx)) / m
            ay2 = (2.0 * (sy * sz - sw * sx) * u0 - c * (vy2 - windy)) / m
            az2 = ((1.0 - 2.0 * (sx * sx + sy * sy)) * u0 - c * (vz2 - windz)) / m + gz
            qw2 = 0.5 * (-sx * rx - sy * ry - sz * rz)
            qx2 = 0.5 * (sw * rx + sy * rz - sz * ry)
            qy2 = 0.5 * (sw * ry - sx * rz + sz * rx)
            qz2 = 0.5 * (sw * rz + sx * ry - sy * rx)
            wx2 = (u1 - (ry * iz * rz - rz * iy * ry)) / ix
            wy2 = (u2 - (rz * ix * rx - rx * iz * rz)) / iy
            wz2 = (u3 - (rx * iy * ry - ry * ix * rx)) / iz
            # k3 at x + dt/2 k2
            vx3, vy3, vz3 = vx + h2 * ax2, vy + h2 * ay2, vz + h2 * az2
            sw, sx, sy, sz = qw + h2 * qw2, qx + h2 * qx2, qy + h2 * qy2, qz + h2 * qz2
            rx, ry, rz = wx + h2 * wx2, wy + h2 * wy2, wz + h2 * wz2
            bb = b3 * b3
            u0, u1, u2, u3 = (uc0 + b3 * d0 + bb * s0, uc1 + b3 * d1 + bb * s1,
                              uc2 + b3 * d2 + bb * s2, uc3 + b3 * d3 + bb * s3)
            ax3 = (2.0 * (sx * sz + sw * sy) * u0 - c * (vx3 - windx)) / m
            ay3 = (2.0 * (sy * sz - sw * sx) * u0 - c * (vy3 - windy)) / m
            az3 = ((1.0 - 2.0 * (sx * sx + sy * sy)) * u0 - c * (vz3 - windz)) / m + gz
            qw3 = 0.5 * (-sx * rx - sy * ry - sz * rz)
            qx3 = 0.5 * (sw * rx + sy * rz - sz * ry)
            qy3 = 0.5 * (sw * ry - sx * rz + sz * rx)
            qz3 = 0.5 * (sw * rz + sx * ry - sy * rx)
            wx3 = (u1 - (ry * iz * rz - rz * iy * ry)) / ix
            wy3 = (u2 - (rz * ix * rx - rx * iz * rz)) / iy
            wz3 = (u3 - (rx * iy * ry - ry * ix * rx)) / iz
            # k4 at x + dt k3
            vx4, vy4, vz4 = vx + h * ax3, vy + h * ay3, vz + h * az3
            sw, sx, sy, sz = qw + h * qw3, qx + h * qx3, qy + h * qy3, qz + h * qz3
            rx, ry, rz = wx + h * wx3, wy + h * wy3, wz + h * wz3
            bb = b4 * b4
            u0, u1, u2, u3 = (uc0 + b4 * d0 + bb * s0, uc1 + b4 * d1 + bb * s1,
                              uc2 + b4 * d2 + bb * s2, uc3 + b4 * d3 + bb * s3)
            ax4 = (2.0 * (sx * sz + sw * sy) * u0 - c * (vx4 - windx)) / m
            ay4 = (2.0 * (sy * sz - sw * sx) * u0 - c * (vy4 - windy)) / m
            az4 = ((1.0 - 2.0 * (sx * sx + sy * sy)) * u0 - c * (vz4 - windz)) / m + gz
            qw4 = 0.5 * (-sx * rx - sy * ry - sz * rz)
            qx4 = 0.5 * (sw * rx + sy * rz - sz * ry)
            qy4 = 0.5 * (sw * ry - sx * rz + sz * rx)
            qz4 = 0.5 * (sw * rz + sx * ry - sy * rx)
            wx4 = (u1 - (ry * iz * rz - rz * iy * ry)) / ix
            wy4 = (u2 - (rz * ix * rx - rx * iz * rz)) / iy
            wz4 = (u3 - (rx * iy * ry - ry * ix * rx)) / iz
            # x + dt/6 (k1 + 2 k2 + 2 k3 + k4), the quaternion normalised
            sw = qw + h6 * (qw1 + 2.0 * qw2 + 2.0 * qw3 + qw4)
            sx = qx + h6 * (qx1 + 2.0 * qx2 + 2.0 * qx3 + qx4)
            sy = qy + h6 * (qy1 + 2.0 * qy2 + 2.0 * qy3 + qy4)
            sz = qz + h6 * (qz1 + 2.0 * qz2 + 2.0 * qz3 + qz4)
            n = math.sqrt(sw * sw + sx * sx + sy * sy + sz * sz)
            if n == 0.0 or not math.isfinite(n):
                self._store(px, py, pz, vx, vy, vz, qw, qx, qy, qz, wx, wy, wz, f0, f1, f2, f3)
                raise ValueError("cannot normalise a zero or non-finite quaternion")
            px = px + h6 * (vx + 2.0 * vx2 + 2.0 * vx3 + vx4)
            py = py + h6 * (vy + 2.0 * vy2 + 2.0 * vy3 + vy4)
            pz = pz + h6 * (vz + 2.0 * vz2 + 2.0 * vz3 + vz4)
            vx = vx + h6 * (ax1 + 2.0 * ax2 + 2.0 * ax3 + ax4)
            vy = vy + h6 * (ay1 + 2.0 * ay2 + 2.0 * ay3 + ay4)
            vz = vz + h6 * (az1 + 2.0 * az2 + 2.0 * az3 + az4)
            wx = wx + h6 * (wx1 + 2.0 * wx2 + 2.0 * wx3 + wx4)
            wy = wy + h6 * (wy1 + 2.0 * wy2 + 2.0 * wy3 + wy4)
            wz = wz + h6 * (wz1 + 2.0 * wz2 + 2.0 * wz3 + wz4)
            qw, qx, qy, qz = sw / n, sx / n, sy / n, sz / n
            f0, f1, f2, f3 = c0 + lag * e0, c1 + lag * e1, c2 + lag * e2, c3 + lag * e3
            if pz < 0.0 or (landed and pz <= 0.0):
                # _apply_ground: rest unless the net vertical force (as if at rest) lifts off
                pz = 0.0
                fz = ((1.0 - 2.0 * (qx * qx + qy * qy)) * kf * (f0 * f0 + f1 * f1 + f2 * f2 + f3 * f3)
                      + m * gz + c * windz)
                if fz <= 0.0:
                    yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
                    vx = vy = vz = wx = wy = wz = 0.0
                    qw, qx, qy, qz = math.cos(yaw / 2.0), 0.0, 0.0, math.sin(yaw / 2.0)
                    landed = True
                else:
                    vz = max(vz, 0.0)  # lifting off: never move into the floor
                    landed = False
            else:
                landed = False
        self._store(px, py, pz, vx, vy, vz, qw, qx, qy, qz, wx, wy, wz, f0, f1, f2, f3)
        self.landed = landed

    def _store(self, *state: float) -> None:
        self.x = np.array(state)  # a new array: views of the old state stay put

    def _apply_ground(self, wind_m_s) -> None:
        """At z = 0: rest (zero motion, level, keep yaw) unless the net force lifts off."""
        x = self.x
        qw, qx, qy, qz = x[Q].tolist()
        r22 = rotation_rows(qw, qx, qy, qz)[8]
        # vertical force as if at rest (v = 0) so a fast impact's drag does not count as lift
        fz = r22 * sum(self.motor_thrust_floats()) + self._m * self._gz + self._drag * float(wind_m_s[2])
        if fz <= 0.0:
            n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            qw, qx, qy, qz = qw / n, qx / n, qy / n, qz / n
            yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
            x[V] = 0.0
            x[W] = 0.0
            x[Q] = (math.cos(yaw / 2.0), 0.0, 0.0, math.sin(yaw / 2.0))
            self.landed = True
        else:
            x[5] = max(x[5], 0.0)  # lifting off: never move into the floor
            self.landed = False
