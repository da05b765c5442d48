"""The camera's level: the attitude estimate's roll/pitch offset measured against the vision
pose's attitude (CameraLevel). Pure: no I/O."""
from __future__ import annotations

import bisect
import math
import operator
from collections import deque
from dataclasses import dataclass

import numpy as np

from flight.estimation.attitude_filter import floats3
from flight.param import Declared, declared

_first = operator.itemgetter(0)


@dataclass(frozen=True)
class CameraLevelParams(Declared):
    """CameraLevel's settings (the attitude service's `camera_level_settings` table)."""

    time_constant_s: float = declared(2.0, "s", 0.0, min_exclusive=True,
                                      doc="the offset is low-passed over this long")
    # a millisecond of timing error is visible while turning fast
    max_rate_rad_s: float = declared(1.0, "rad/s", 0.0, min_exclusive=True,
                                     doc="a frame taken while turning faster than this is not used")
    max_tilt_rad: float = declared(0.5, "rad", 0.0, min_exclusive=True,
                                   doc="a frame taken tilted past this is not used")
    gate_rad: float = declared(0.05, "rad", 0.0, min_exclusive=True,
                               doc="a frame disagreeing with the current offset by more than this is not used")
    history_s: float = declared(0.5, "s", 0.0, min_exclusive=True,
                                doc="the estimate's history kept to meet a frame at its exposure time")
    max_offset_rad: float = declared(0.05, "rad", 0.0, min_exclusive=True,
                                     doc="the offset is bounded to this (roll and pitch each)")


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
        self._offset = (0.0, 0.0)       # (roll, pitch): estimate minus camera
        self.fused = 0
        self.rejected: dict[str, int] = {}
        self._history: deque = deque()  # (t, roll, pitch, |rate|), oldest first
        self._last_fused_t = None

    @property
    def offset_rad(self) -> np.ndarray:
        """(roll, pitch) offset: estimate minus camera, rad."""
        return np.array(self._offset)

    @offset_rad.setter
    def offset_rad(self, value) -> None:
        roll, pitch = np.asarray(value, dtype=np.float64).reshape(2).tolist()
        self._offset = (roll, pitch)

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
        """One camera attitude at its exposure time; True when it moved the offset.

        In floats, with the operations of the array version: numpy's norm (np.linalg.norm of a
        vector is sqrt(q.dot(q))) and quat_to_euler's normalisation, then per component."""
        q = np.asarray(quaternion_wxyz, dtype=np.float64)
        if q.shape != (4,):
            return self._reject("camera_level_bad_quaternion")
        isfinite = math.isfinite
        w, x, y, z = q.tolist()
        if not (isfinite(w) and isfinite(x) and isfinite(y) and isfinite(z)):
            return self._reject("camera_level_bad_quaternion")
        n = math.sqrt(q.dot(q))
        if n < 0.5:
            return self._reject("camera_level_bad_quaternion")
        q = q / n
        w, x, y, z = (q / math.sqrt(q.dot(q))).tolist()    # quat_to_euler normalises it again
        roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
        pitch = math.asin(min(1.0, max(-1.0, 2 * (w * y - z * x))))
        h = self._history
        if len(h) < 2 or not (h[0][0] <= t_exposure_s <= h[-1][0]):
            return self._reject("camera_level_outside_history")
        i = bisect.bisect_left(h, t_exposure_s, lo=1, key=_first)   # the first sample at or after it
        (t0, r0, p0, w0), (t1, r1, p1, w1) = h[i - 1], h[i]
        f = (t_exposure_s - t0) / (t1 - t0) if t1 > t0 else 1.0
        est_r, est_p = r0 + f * (r1 - r0), p0 + f * (p1 - p0)
        if max(w0, w1) > self.max_rate_rad_s:
            return self._reject("camera_level_turning")
        if max(abs(roll), abs(pitch), abs(est_r), abs(est_p)) > self.max_tilt_rad:
            return self._reject("camera_level_tilted")
        diff_r, diff_p = est_r - roll, est_p - pitch
        o_r, o_p = self._offset
        if abs(diff_r - o_r) > self.gate_rad or abs(diff_p - o_p) > self.gate_rad:
            return self._reject("camera_level_inconsistent")
        dt = (t_exposure_s - self._last_fused_t) if self._last_fused_t is not None else 0.05
        gain = min(1.0, max(dt, 0.0) / self.time_constant_s)
        lim = self.max_offset_rad
        self._offset = (min(max(o_r + gain * (diff_r - o_r), -lim), lim),
                        min(max(o_p + gain * (diff_p - o_p), -lim), lim))
        self._last_fused_t = t_exposure_s
        self.fused += 1
        return True

    def apply(self, euler_rad) -> np.ndarray:
        """The estimate's (roll, pitch, yaw) with the offset removed."""
        return np.array(self.apply_floats(euler_rad))

    def apply_floats(self, euler_rad) -> list[float]:
        """apply() as a list of floats."""
        roll, pitch, yaw = floats3(euler_rad)
        d_roll, d_pitch = self._offset
        return [roll - d_roll, pitch - d_pitch, yaw]
