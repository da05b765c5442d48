"""Failsafe laws: keep the vehicle level and bring it down when a level above has gone.

Pure (no I/O): the motor driver runs them when the attitude level's commands are stale or
absent, the attitude level when the position level's are (services/motors.py,
services/attitude.py).

- `LevelEstimate`: roll/pitch/yaw from gyro and accelerometer alone (Mahony's complementary
  filter: the gyro integrated, the accelerometer's vertical pulling roll and pitch back);
  started from the last estimate the lost level published, so it needs no settling.
- `Descent`: the collective thrust of a controlled descent. The vertical speed is the
  accelerometer's specific force rotated to the world, minus gravity, integrated (started
  from the last velocity estimate); the thrust follows a sink-rate reference that ramps from 0
  to `sink_rate_m_s` over `ramp_s`, through a PI loop, and is itself rate-limited (a ramp, not
  a step, from the thrust flying when the failsafe took over). The descent is over (`landed`)
  once the integrated height has gone `ground_margin_m` below the ground (the last altitude
  estimate minus the distance descended; the margin covers the integration's drift) or after
  `max_descent_s`: then the caller cuts the motors. An accelerometer does not see a touchdown
  whose impact a simulator applies instantaneously (nor, reliably, a soft one on a real
  vehicle), hence the height bound rather than an impact detector.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from flight.param import Declared, declared
from flight.quat import quat_from_euler, quat_multiply, quat_normalize, quat_to_euler

GRAVITY_BAND = 0.15   # the accelerometer corrects roll/pitch only within 15 % of 1 g


def _rotate(q, v) -> tuple[float, float, float]:
    """Body vector v to world with q = [w, x, y, z] (floats)."""
    w, x, y, z = q
    vx, vy, vz = v
    r00, r01, r02 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    r10, r11, r12 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    return (r00 * vx + r01 * vy + r02 * vz, r10 * vx + r11 * vy + r12 * vz, r20 * vx + r21 * vy + r22 * vz)


class LevelEstimate:
    """Complementary (Mahony) attitude filter on raw IMU samples, in floats."""

    def __init__(self, q0, t0: float, accel_gain: float = 1.0):
        self.q = [float(v) for v in quat_normalize(q0)]
        self.t = float(t0)
        self.gain = float(accel_gain)   # 1/s: how fast the accelerometer's vertical pulls roll/pitch
        self.rate = (0.0, 0.0, 0.0)

    @classmethod
    def from_accel(cls, t0: float, accel, yaw: float = 0.0, **kw) -> "LevelEstimate":
        ax, ay, az = (float(v) for v in accel)
        roll, pitch = math.atan2(ay, az), math.atan2(-ax, math.hypot(ay, az))
        return cls(quat_from_euler(roll, pitch, yaw), t0, **kw)

    def update(self, t: float, gyro, accel) -> None:
        """One IMU sample (sample time t); older samples than the last one are ignored."""
        dt = t - self.t
        if dt <= 0.0:
            return
        dt = min(dt, 0.05)   # a gap in the samples: do not integrate a stale rate over it
        self.t = t
        gx, gy, gz = (float(v) for v in gyro)
        self.rate = (gx, gy, gz)
        ax, ay, az = (float(v) for v in accel)
        norm = math.sqrt(ax * ax + ay * ay + az * az)
        if norm > 0.0 and abs(norm / 9.80665 - 1.0) < GRAVITY_BAND:
            w, x, y, z = self.q
            # world "up" in the body frame, as the estimate sees it; the measurement's cross it
            ux, uy, uz = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
            ax, ay, az = ax / norm, ay / norm, az / norm
            gx += self.gain * (ay * uz - az * uy)
            gy += self.gain * (az * ux - ax * uz)
            gz += self.gain * (ax * uy - ay * ux)
        half = 0.5 * dt
        self.q = [float(v) for v in quat_normalize(quat_multiply(self.q, (1.0, gx * half, gy * half, gz * half)))]

    @property
    def euler(self) -> tuple[float, float, float]:
        return quat_to_euler(self.q)


@dataclass(frozen=True)
class DescentParams(Declared):
    """The controlled descent's settings (the attitude level's and the motor driver's
    `failsafe_descent` table)."""

    sink_rate_m_s: float = declared(0.5, "m/s", 0.0, min_exclusive=True, doc="the descent's speed once ramped in")
    ramp_s: float = declared(1.0, "s", 0.0, min_exclusive=True,
                             doc="the sink-rate reference ramps in from 0 over this long (and the thrust slews a "
                                 "hover thrust per ramp_s at most)")
    velocity_gain: float = declared(3.0, "1/s", 0.0, min_exclusive=True, doc="P of the sink-rate loop")
    # the I term takes up a wrong mass or thrust scale
    integral_gain: float = declared(2.0, "1/s^2", 0.0, min_exclusive=True, doc="I of the sink-rate loop")
    ground_margin_m: float = declared(1.0, "m", 0.0, min_exclusive=True,
                                      doc="descend this far past the estimated ground before cutting the motors")
    max_descent_s: float = declared(60.0, "s", 0.0, min_exclusive=True,
                                    doc="cut the motors after this long whatever the height says")
    max_thrust_fraction: float = declared(0.8, "", 0.0, 1.0, min_exclusive=True,
                                          doc="the most collective thrust the descent asks, of the rotors' total")


class Descent:
    """The collective thrust of a controlled descent to the ground (module docstring)."""

    def __init__(self, params: DescentParams, mass_kg: float, gravity_m_s2: float, max_thrust_n: float):
        self.p = params
        self.m, self.g = float(mass_kg), float(gravity_m_s2)
        self.max_thrust = params.max_thrust_fraction * float(max_thrust_n)
        self.started = False
        self.landed = False

    def start(self, t: float, height_m: float | None, vz_m_s: float, thrust_n: float) -> None:
        """Take over at t from a vehicle `height_m` above the ground (None: unknown), climbing at
        vz_m_s, flying on thrust_n."""
        self.t0 = self.t = float(t)
        self.z = float(height_m) if height_m is not None else math.inf
        self.vz = float(vz_m_s)
        self.thrust = min(max(float(thrust_n), 0.0), self.max_thrust)
        self.integral = 0.0
        self.started, self.landed = True, False

    def update(self, t: float, q, accel=None, thrust_scale: float = 1.0) -> float:
        """Advance to t with the attitude q and the specific force `accel` (body, m/s^2; None:
        no new sample) and return the collective thrust (N); 0 once landed."""
        dt = t - self.t
        if dt > 0.0:
            self.t = t
            if accel is not None:
                self.vz += (_rotate(q, accel)[2] - self.g) * dt
            self.z += self.vz * dt
            elapsed = t - self.t0
            ref = -self.p.sink_rate_m_s * min(1.0, elapsed / self.p.ramp_s)
            err = ref - self.vz
            self.integral = min(max(self.integral + self.p.integral_gain * err * dt, -0.5 * self.g), 0.5 * self.g)
            w, x, y, _ = q
            tilt_cos = max(1 - 2 * (x * x + y * y), 0.5)
            want = (self.m / thrust_scale) * (self.g + self.p.velocity_gain * err + self.integral) / tilt_cos
            want = min(max(want, 0.0), self.max_thrust)
            slew = self.m * self.g / self.p.ramp_s * dt   # a full hover thrust per ramp_s at most
            self.thrust += min(max(want - self.thrust, -slew), slew)
            if self.z < -self.p.ground_margin_m or elapsed > self.p.max_descent_s:
                self.landed = True
        return 0.0 if self.landed else self.thrust
