"""The gyro carrier: a quaternion carried by the gyros through the attitudes (inversion, fast
turns) the per-axis filter of 000 (attitude_filter.py) cannot hold. Pure: no I/O."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flight.estimation.attitude_filter import floats3
from flight.param import Declared, declared
from flight.quat import quat_from_euler_floats, quat_integrate, quat_tilt


@dataclass(frozen=True)
class GyroCarrierParams(Declared):
    """When the carrier takes over and hands back (the attitude service's `carrier` table); the
    gap between the enter and exit thresholds is the hysteresis that avoids chattering."""

    enter_tilt_deg: float = declared(45.0, "deg", 0.0, 180.0, min_exclusive=True,
                                     doc="tilted past this, the gyro-integrated quaternion carries the estimate")
    exit_tilt_deg: float = declared(30.0, "deg", 0.0, 180.0, min_exclusive=True,
                                    doc="back within this tilt (and below exit_rate_rad_s) the filter restarts from "
                                        "it; at most enter_tilt_deg")
    enter_rate_rad_s: float = declared(6.0, "rad/s", 0.0, min_exclusive=True,
                                       doc="... or turning faster than this, the quaternion carries")
    exit_rate_rad_s: float = declared(2.0, "rad/s", 0.0, min_exclusive=True,
                                      doc="the body rate below which it hands back; at most enter_rate_rad_s")

    def __post_init__(self):
        super().__post_init__()
        if self.exit_tilt_deg > self.enter_tilt_deg or self.exit_rate_rad_s > self.enter_rate_rad_s:
            raise ValueError("GyroCarrierParams: need exit_tilt_deg <= enter_tilt_deg and "
                             "exit_rate_rad_s <= enter_rate_rad_s")


class GyroCarrier:
    """A quaternion carried by the gyros through attitudes the 000 filter cannot hold.

    The 000 filter is three independent Euler-angle axes with the body rate taken
    as the Euler rate: fine near level, wrong when tilted far or turning fast, and
    it cannot represent inversion.  Near level the carrier just follows that
    filter (``follow``: its estimate is used unchanged, so normal flight is
    exactly 000).  Once tilted past ``enter_tilt_deg`` or turning faster than
    ``enter_rate_rad_s`` it becomes ``active``: every IMU sample turns the
    quaternion by the gyro (``propagate``; gyro bias ~3e-3 rad/s, so a 1 s flip
    drifts well under a degree), and the attitude service publishes it.  When
    back within ``exit_tilt_deg`` and slower than ``exit_rate_rad_s``,
    ``back_near_level`` says so and the service re-initialises the 000 filter
    from it (hysteresis between the two thresholds avoids chattering).
    """

    def __init__(self, params: GyroCarrierParams = GyroCarrierParams()):
        self.enter_tilt = math.radians(params.enter_tilt_deg)
        self.exit_tilt = math.radians(params.exit_tilt_deg)
        self.enter_rate = params.enter_rate_rad_s
        self.exit_rate = params.exit_rate_rad_s
        self.q = np.array([1.0, 0.0, 0.0, 0.0])
        self.t: float | None = None
        self.gyro = np.zeros(3)
        self.active = False
        self.activations = 0

    # q and gyro as arrays; `follow` (every 200 Hz run near level) leaves floats that become
    # arrays only when read (when the carrier takes over, or by a test)
    @property
    def q(self) -> np.ndarray:
        if self._q is None:
            if self._q_floats is None:   # follow_euler's: the quaternion made now, as follow makes it
                w, x, y, z = quat_from_euler_floats(*self._euler)
                n = math.sqrt(w * w + x * x + y * y + z * z)
                self._q_floats = (w / n, x / n, y / n, z / n)
            self._q = np.array(self._q_floats)
        return self._q

    @q.setter
    def q(self, value) -> None:
        self._q = value

    @property
    def gyro(self) -> np.ndarray:
        if self._gyro is None:
            self._gyro = np.array(self._gyro_floats, dtype=np.float64)
        return self._gyro

    @gyro.setter
    def gyro(self, value) -> None:
        self._gyro = value

    def follow(self, t_s: float, q, gyro) -> None:
        """Inactive: take the 000 filter's attitude at its newest sample time and that sample's gyro."""
        w, x, y, z = q.tolist() if isinstance(q, np.ndarray) else q
        n = math.sqrt(w * w + x * x + y * y + z * z)
        self._q, self._q_floats = None, (w / n, x / n, y / n, z / n)
        self.t = float(t_s)
        self._follow_gyro(gyro)

    def follow_euler(self, t_s: float, euler, gyro) -> None:
        """follow() with the 000 filter's attitude as its (roll, pitch, yaw) floats: the
        quaternion follow() would make from quat_from_euler of them is made only when read."""
        self._q, self._q_floats, self._euler = None, None, tuple(euler)
        self.t = float(t_s)
        self._follow_gyro(gyro)

    def _follow_gyro(self, gyro) -> None:
        if type(gyro) is list or type(gyro) is tuple:
            self._gyro, self._gyro_floats = None, tuple(gyro)
        else:
            self._gyro = np.array(gyro, dtype=np.float64)

    def check_enter(self, q, rate) -> bool:
        """Become active when the attitude (q, rate) is beyond what the 000 filter represents."""
        if not self.active and self.t is not None and (
                quat_tilt(q) > self.enter_tilt or math.hypot(*floats3(rate)) > self.enter_rate):
            self.active = True
            self.activations += 1
        return self.active

    def propagate(self, t_s: float, gyro) -> None:
        """One IMU sample: turn by the mean of the previous and this gyro over the interval."""
        gyro = np.asarray(gyro, dtype=np.float64)
        if self.t is None or not t_s > self.t:
            return
        self.q = quat_integrate(self.q, 0.5 * (self.gyro + gyro), t_s - self.t)
        self.t = float(t_s)
        self.gyro = gyro.copy()

    def back_near_level(self) -> bool:
        return self.active and quat_tilt(self.q) < self.exit_tilt and float(np.linalg.norm(self.gyro)) < self.exit_rate

    def estimate(self, t_now: float, max_delay_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(quaternion, body rate) at t_now: carried over the transport delay by the newest gyro."""
        delay = min(max(0.0, t_now - (self.t if self.t is not None else t_now)), max_delay_s)
        return quat_integrate(self.q, self.gyro, delay), self.gyro.copy()
