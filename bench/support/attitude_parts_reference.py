"""The attitude service's helpers as of zenpilot 6b2add1, verbatim: flight/quat.py
quat_from_euler and quat_tilt, flight/control/laws.py attitude_law (and its _three),
flight/estimation/camera_level.py CameraLevel, flight/estimation/gyro_carrier.py GyroCarrier,
flight/estimation/attitude_filter.py floats3.
bench/support/attitude_reference.py (the former AttitudeLoop) runs on them; the unit tests
check today's float versions against them bit for bit. Not used in flight."""
from __future__ import annotations

import bisect
import math
import operator
from collections import deque

import numpy as np

from flight.control.laws import _stopping_rate1
from flight.estimation.camera_level import CameraLevelParams
from flight.estimation.gyro_carrier import GyroCarrierParams
from flight.quat import quat_integrate, quat_to_euler, wrap_angle_float

_first = operator.itemgetter(0)


def floats3(v) -> tuple[float, float, float] | None:
    """v (a list, tuple or array of 3 numbers, any shape) as three Python floats; None if it
    is not (the attitude level's inputs, here and in camera_level.py and gyro_carrier.py)."""
    if isinstance(v, np.ndarray):
        if v.shape != (3,):
            v = v.reshape(-1)
            if v.shape != (3,):
                return None
        try:
            a, b, c = v.astype(np.float64, copy=False).tolist()
        except (TypeError, ValueError):
            return None
        return a, b, c
    try:
        if len(v) == 3:
            return float(v[0]), float(v[1]), float(v[2])
    except (TypeError, ValueError, LookupError):
        pass
    try:
        return floats3(np.asarray(v, dtype=np.float64))
    except (TypeError, ValueError):
        return None


def quat_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """q = qz(yaw) (x) qy(pitch) (x) qx(roll), i.e. R = Rz Ry Rx."""
    if isinstance(roll, float) and isinstance(pitch, float) and isinstance(yaw, float):
        # scalars (the control loops' case): math's functions, several times cheaper than numpy's
        cr, sr = math.cos(roll / 2), math.sin(roll / 2)
        cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
        cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
        return np.array([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                         cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy])
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    return np.array([
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ])


def quat_tilt(q) -> float:
    """Angle between the body z axis and the world z axis, rad (0 level, pi inverted)."""
    w, x, y, z = q.tolist() if isinstance(q, np.ndarray) else (float(v) for v in q)
    r22 = (w * w - x * x - y * y + z * z) / (w * w + x * x + y * y + z * z)
    return math.acos(min(1.0, max(-1.0, r22)))


def _three(v) -> tuple[float, float, float]:
    """A per-axis value (a number or 3 of them) as three floats."""
    if isinstance(v, np.ndarray):
        v = v.tolist()
    if isinstance(v, (int, float)):
        return float(v), float(v), float(v)
    a, b, c = v
    return float(a), float(b), float(c)


def attitude_law(inertia, angles, rates, angles_ref, k, alpha, max_accel=None) -> np.ndarray:
    """Law (8): u = I [-(alpha+k) rate - alpha k (angle - ref)] per axis.

    inertia: diagonal (Ixx, Iyy, Izz); angles, angles_ref: (roll, pitch, yaw);
    rates: angular rates (000 uses body rates as Euler rates near hover).
    Returns body torque (3,) N m.

    The law is a rate loop on a proportional angle loop: u = I (alpha+k) (w_ref - rate),
    w_ref = -alpha k / (alpha+k) (angle - ref). max_accel (3,), rad/s^2: w_ref is capped by
    stopping_rate at this angular acceleration, so a large error never asks for a rate the
    airframe cannot stop in time (saturated, the linear law overshoots and can limit-cycle);
    errors below max_accel / (alpha k / (alpha+k))^2 see law (8) exactly. None: law (8).
    """
    # per axis in floats: this runs every 200 Hz step, where numpy's per-call cost dominates
    inertia = np.asarray(inertia, dtype=np.float64)
    if inertia.shape == (3, 3):
        inertia = np.diag(inertia)
    inertia, k, alpha = _three(inertia), _three(k), _three(alpha)
    angles, angles_ref, rates = _three(angles), _three(angles_ref), _three(rates)
    err = [angles[0] - angles_ref[0], angles[1] - angles_ref[1], angles[2] - angles_ref[2]]
    err[2] = wrap_angle_float(err[2])  # yaw: take the short way round
    if max_accel is None:
        return np.array([inertia[i] * (-(alpha[i] + k[i]) * rates[i] - alpha[i] * k[i] * err[i]) for i in range(3)])
    max_accel = _three(max_accel)
    out = []
    for i in range(3):
        rate_ref = -_stopping_rate1(err[i], alpha[i] * k[i] / (alpha[i] + k[i]), max_accel[i])
        out.append(inertia[i] * (alpha[i] + k[i]) * (rate_ref - rates[i]))
    return np.array(out)


class CameraLevel:
    """Roll/pitch offset of the attitude estimate, measured against the camera's attitude.

    The accelerometer's bias tilts the estimate's "level": 0.01 m/s^2 is 0.06 deg, and the
    acceleration reference cannot see it (the filter's attitude settles where the rotated
    accelerometer agrees with the EKF's velocity change). The vision pose's attitude has no
    such bias (about 0.15 deg of noise per frame, stamped with the exposure time), so the
    difference between the estimate at a frame's exposure time (from a short history) and
    the frame's roll/pitch, low-passed over time_constant_s, is the offset to subtract from
    the published estimate. Frames taken while the vehicle turned faster than max_rate_rad_s
    (a millisecond of timing error is then visible), tilted past max_tilt_rad, outside the
    history, or disagreeing by more than gate_rad with the current offset are not used
    (counted by reason in `rejected`). Pure: no I/O."""

    def __init__(self, params: CameraLevelParams = CameraLevelParams()):
        self.time_constant_s = params.time_constant_s
        self.max_rate_rad_s = params.max_rate_rad_s
        self.max_tilt_rad = params.max_tilt_rad
        self.gate_rad = params.gate_rad
        self.history_s = params.history_s
        self.max_offset_rad = params.max_offset_rad
        self.offset_rad = np.zeros(2)   # (roll, pitch): estimate minus camera
        self.fused = 0
        self.rejected: dict[str, int] = {}
        self._history: deque = deque()  # (t, roll, pitch, |rate|), oldest first
        self._last_fused_t = None

    def record(self, t_s: float, euler_rad, rate_rad_s) -> None:
        """The estimate (before the offset is removed) at t_s, in time order."""
        if self._history and t_s <= self._history[-1][0]:
            return
        p, q, r = floats3(rate_rad_s)
        self._history.append((float(t_s), float(euler_rad[0]), float(euler_rad[1]), math.sqrt(p * p + q * q + r * r)))
        while self._history and self._history[0][0] < t_s - self.history_s:
            self._history.popleft()

    def _reject(self, reason: str) -> bool:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        return False

    def fuse(self, t_exposure_s: float, quaternion_wxyz) -> bool:
        """One camera attitude at its exposure time; True when it moved the offset."""
        q = np.asarray(quaternion_wxyz, dtype=np.float64)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 0.5:
            return self._reject("camera_level_bad_quaternion")
        roll, pitch, _ = quat_to_euler(q / np.linalg.norm(q))
        h = self._history
        if len(h) < 2 or not (h[0][0] <= t_exposure_s <= h[-1][0]):
            return self._reject("camera_level_outside_history")
        i = bisect.bisect_left(h, t_exposure_s, lo=1, key=_first)   # the first sample at or after it
        (t0, r0, p0, w0), (t1, r1, p1, w1) = h[i - 1], h[i]
        f = (t_exposure_s - t0) / (t1 - t0) if t1 > t0 else 1.0
        est = np.array([r0 + f * (r1 - r0), p0 + f * (p1 - p0)])
        if max(w0, w1) > self.max_rate_rad_s:
            return self._reject("camera_level_turning")
        if max(abs(roll), abs(pitch), *np.abs(est)) > self.max_tilt_rad:
            return self._reject("camera_level_tilted")
        diff = est - np.array([roll, pitch])
        if np.any(np.abs(diff - self.offset_rad) > self.gate_rad):
            return self._reject("camera_level_inconsistent")
        dt = (t_exposure_s - self._last_fused_t) if self._last_fused_t is not None else 0.05
        gain = min(1.0, max(dt, 0.0) / self.time_constant_s)
        self.offset_rad = np.clip(self.offset_rad + gain * (diff - self.offset_rad),
                                  -self.max_offset_rad, self.max_offset_rad)
        self._last_fused_t = t_exposure_s
        self.fused += 1
        return True

    def apply(self, euler_rad) -> np.ndarray:
        """The estimate's (roll, pitch, yaw) with the offset removed."""
        roll, pitch, yaw = floats3(euler_rad)
        d_roll, d_pitch = self.offset_rad.tolist()
        return np.array([roll - d_roll, pitch - d_pitch, yaw])


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

    def follow(self, t_s: float, q, gyro) -> None:
        """Inactive: take the 000 filter's attitude at its newest sample time and that sample's gyro."""
        w, x, y, z = q.tolist() if isinstance(q, np.ndarray) else q
        n = math.sqrt(w * w + x * x + y * y + z * z)
        self.q = np.array([w / n, x / n, y / n, z / n])
        self.t = float(t_s)
        self.gyro = np.array(gyro, dtype=np.float64)

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
