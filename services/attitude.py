"""zenpilot-attitude: the attitude level (200 Hz) of 000: filter and law (8).

State source `estimate` (default): every IMU sample goes through the
low-pass filters (12) and a linear Kalman filter per axis on
[w, w_f, angle, angle_f] with the torque input (13), (16)-(20); the analytic
extrapolator (15) carries the estimate over the measured transport delay
(newest IMU sample time to now) with the stored torques. With
`estimator = "gyro-vertical"` the adaptive gyro-vertical of 004 runs on every
raw IMU sample and its roll/pitch replace the accelerometer angles as the
filter's angle measurement (trained parameters from `gyrovertical_params`,
written by `zenpilot train-gyrovertical`), with the acceleration compensation
(`gyrovertical_compensation`, by default as the file was trained: the position level's velocity
change over accel_window_s and the estimate's heading; the accelerometer alone without them). State source
`truth`: the simulator's ground truth (an explicit ablation setting).
Law (8) u = I [-(alpha+k) w - alpha k (angle - ref)] tracks the position
level's reference; the collective thrust is passed on to the motor driver.

Stale inputs: a run whose newest IMU sample (or truth) is older than `state_timeout_s`
publishes no command (counted once per sample, "stale_state": a loop resumed after a freeze must not steer on
old samples; the motor driver's failsafe covers the gap). A position setpoint older than
`setpoint_timeout_s` is not used: in the air (the last fresh one asked for thrust) the level
holds level and descends on its own (flight/control/failsafe.Descent: the accelerometer's vertical
speed, a thrust ramp to a slow sink, thrust cut past the ground estimated from the last
pos/state; counted "failsafe_engaged", "failsafe_landed"); fresh setpoints take over again.
Restarted mid-flight by the supervisor (`--restarted`), the level sends no command for
`restart_settle_s` after its first sample: a filter just started is not yet one to steer on.
"""

from __future__ import annotations

import bisect
from collections import deque
from operator import itemgetter
from pathlib import Path

import numpy as np

import schemas
from flight.control.failsafe import Descent, DescentParams
from flight.control.laws import attitude_law_floats, stopping_accel
from flight.estimation.attitude_filter import AttitudeFilter, AttitudeFilterParams, accel_roll_pitch
from flight.estimation.camera_level import CameraLevel, CameraLevelParams
from flight.estimation.gyro_carrier import GyroCarrier, GyroCarrierParams
from flight.estimation.gyrovertical import DEFAULT_PARAMS_FILE, GyroVertical, load_trained, yaw_of
from flight.quat import quat_from_euler, quat_from_euler_floats, quat_to_euler, quat_to_rotation, rotate_vector
from flight.vehicle import load_vehicle
from services.params.attitude import PARAMS  # every parameter: default, unit, bounds, doc
from services.runtime import Runtime, main_guard, service_parser

NAME = "attitude"
VELOCITY_KEEP_S = 0.2  # pos/state history kept beyond the window: covers an IMU transport delay
_sample_time = itemgetter(0)


def truth_specific_force(truth: dict, gravity_m_s2: float):
    """(t, body specific force) from a truth message: R^T (a + g z)."""
    a, q = truth["acceleration_m_s2"], np.asarray(truth["quaternion_wxyz"])
    return truth["header"]["t_s"], rotate_vector(q * [1.0, -1.0, -1.0, -1.0], [a[0], a[1], a[2] + gravity_m_s2])


def gyrovertical_params_file(io, vehicle) -> tuple[Path, str]:
    """(file, where it was named): the service's gyrovertical_params when set, else the one the
    vehicle file names (trained on that airframe), else the shipped default."""
    if io.params["gyrovertical_params"]:
        return Path(io.params["gyrovertical_params"]), f"{io.where()} gyrovertical_params"
    if vehicle.gyrovertical_params_path is not None:
        return vehicle.gyrovertical_params_path, f"vehicle {vehicle.name}'s gyrovertical_params"
    return DEFAULT_PARAMS_FILE, "the default gyro-vertical parameters"


def load_gyrovertical(io, vehicle):
    """(maker, compensated): a maker of the gyro-vertical (trained parameters, IMU period) from an
    initial quaternion, and whether it gets the acceleration compensation (gyrovertical_compensation).

    A missing or bad parameter file is refused at start-up with its name and who named it."""
    path, named_by = gyrovertical_params_file(io, vehicle)
    try:
        trained = load_trained(path)
    except ValueError as exc:
        raise ValueError(f"{named_by}: {exc}") from None
    rate = io.params["imu_rate_hz"]
    mode = io.params["gyrovertical_compensation"]
    if mode == "file":
        mode = trained.meta.get("compensation", "none")
        if mode not in ("window", "none"):
            raise ValueError(f"{named_by}: {path}: [meta] compensation must be \"window\" or \"none\", got {mode!r}")
    params, fallback = trained.flown(mode == "window")   # the file's [fallback] where there is no reference
    return (lambda q0: GyroVertical(params, dt=1.0 / rate, q0=q0, fallback=fallback)), mode == "window"


class AttitudeLoop:
    """The attitude level's logic: filter (or truth), law (8) and the failsafe descent.

    `io` is what it reads and writes through: the service's Runtime in flight, a fake in the
    unit tests (tests/unit/services/): params, inboxes (latest/take), publishers (put), the
    rejection counters and problem reports. No Zenoh here."""

    def __init__(self, io):
        self.io = io
        p = self.p = io.params
        vehicle = self.vehicle = load_vehicle(io.vehicle_name)
        self.estimate = p["state_source"] == "estimate"
        self.motion = self.level = self.poses = self.make_gyrovertical = None
        if self.estimate:
            params = io.table("filter", AttitudeFilterParams.from_dict)
            self.filt = AttitudeFilter(np.asarray(vehicle.inertia_kg_m2), params, dt=1.0 / io.rate_hz,
                                       gravity_m_s2=vehicle.gravity_m_s2)
            self.carrier = GyroCarrier(io.table("carrier", GyroCarrierParams.from_dict))
            self.carrier_horizon_s = params.max_delay_steps / io.rate_hz
            if p["camera_level"]:
                self.level = CameraLevel(io.table("camera_level_settings", CameraLevelParams.from_dict))
                self.poses = io.inbox(schemas.VISION_POSE, "vision", keep=8)
            self.imu = io.inbox(schemas.IMU, "sim", keep=32)
            self.mag = io.inbox(schemas.MAG, "sim", keep=8)
            self.motors = io.inbox(schemas.MOTOR_PWM, "motors")
            gv_file, self.gv_compensated = None, False
            if p["estimator"] == "gyro-vertical":
                self.make_gyrovertical, self.gv_compensated = load_gyrovertical(io, vehicle)
                gv_file = gyrovertical_params_file(io, vehicle)[0]
            # the 000 filter's own compensation (not with the gyro-vertical: its angles come compensated or not)
            self.compensate_000 = p["compensate_acceleration"] and self.make_gyrovertical is None
            print(f"zenpilot-attitude: estimator {p['estimator']}"
                  + (f" ({gv_file.name}, acceleration compensation "
                     f"{'window' if self.gv_compensated else 'none'})" if gv_file else ""), flush=True)
            self.motion = (io.inbox(schemas.POSITION_STATE, "position")
                           if self.compensate_000 or self.gv_compensated else None)
            self.windowed = p["acceleration_compensation"] == "window"
            self.accel_window_s = p["accel_window_s"]
            self.velocities: deque = deque()   # (t, velocity) of the position level's estimate, newest last
        else:
            self.truth = io.inbox(schemas.TRUTH, "sim")
        self.wake_on = self.imu if self.estimate else self.truth
        self.setpoint = io.inbox(schemas.POSITION_SETPOINT, "position")
        # the last altitude and climb rate when the position level goes (the descent's start)
        self.last_motion = self.motion if self.motion is not None else io.inbox(schemas.POSITION_STATE, "position")
        self.descent_params = io.table("failsafe_descent", DescentParams.from_dict)
        self.flying = 0.0          # the thrust of the last fresh setpoint (0: on the ground, or never flown)
        self.descent = None        # the failsafe's descent while it runs
        self.accel_samples = []    # this run's raw specific forces (or the truth message) for the descent
        self.stale_t = None        # the sample time last counted stale
        # restarted mid-flight: commands only from this sample time on (set at the first sample)
        self.command_from = None if io.restarted else float("-inf")
        self.command = io.publisher(schemas.ATTITUDE_COMMAND)
        self.state_out = io.publisher(schemas.ATTITUDE_STATE)
        self.k, self.alpha = io.live_array("k"), io.live_array("alpha")
        self.max_accel = stopping_accel(vehicle.max_angular_accel_rad_s2, p["stopping_accel_fraction"])
        # the law's per-axis values as floats, the gains' refreshed after live_array's own update on param/set
        self.law_max_accel = tuple(self.max_accel.tolist()) if self.max_accel is not None else None
        self.gains = (tuple(self.k.tolist()), tuple(self.alpha.tolist()))
        for key in ("k", "alpha"):
            io.on_param(key, self._gains_changed)
        self.inertia = tuple(float(i) for i in vehicle.inertia_kg_m2)   # the law reads floats
        self.last_torque = (0.0, 0.0, 0.0)
        self.filt_q = np.array([1.0, 0.0, 0.0, 0.0])
        self.gyrovertical = None
        self.gyrovertical_t = None

    def _gains_changed(self, _value) -> None:
        self.gains = (tuple(self.k.tolist()), tuple(self.alpha.tolist()))

    def gyrovertical_update(self, t_s: float, gyro, accel, moving=None) -> tuple[float, float]:
        """Feed one raw IMU sample to the gyro-vertical (once, in time order); its (roll, pitch).

        moving: the newest pos/state when the gyro-vertical is compensated: its velocity window that
        ends before this sample is the reference (none yet, or stale: the accelerometer alone), turned
        into the gyro-vertical's frame by the heading of the stack's last estimate (the gyro-vertical's
        own yaw is the gyros' alone, from 0 at its start)."""
        gv = self.gyrovertical
        if gv is None:   # start from the accelerometer's vertical, as the 000 filter does
            gv = self.gyrovertical = self.make_gyrovertical(quat_from_euler(*accel_roll_pitch(accel), 0.0))
        elif t_s <= self.gyrovertical_t:
            return gv.roll, gv.pitch
        self.gyrovertical_t = t_s
        if not self.gv_compensated:
            return gv.update(gyro, accel)
        # a window ending before the sample: the gyro-vertical keeps forces only up to the previous one
        ref = self.velocity_window(moving, t_s - 0.5 * gv.dt) if moving is not None else None
        return gv.update(gyro, accel, t_s, ref, yaw_of(tuple(self.filt_q)) if ref is not None else None)

    def velocity_window(self, moving, until: float):
        """(t0, t1, mean acceleration) from the position level's velocities over accel_window_s,
        ending at or before `until` (the newest IMU sample: the filter compares the window with its
        own samples, which arrive later than pos/state when the IMU has a transport delay), or None."""
        velocities, window = self.velocities, self.accel_window_s
        t_p = moving["header"]["t_s"]
        if not velocities or t_p > velocities[-1][0]:
            velocities.append((t_p, moving["velocity_m_s"]))
        elif t_p < velocities[-1][0]:      # time went back (a restart): start over
            velocities.clear()
            velocities.append((t_p, moving["velocity_m_s"]))
        while len(velocities) > 1 and velocities[0][0] < velocities[-1][0] - window - VELOCITY_KEEP_S:
            velocities.popleft()
        # the usable ones (at or before `until`) are a prefix of the time-ordered history
        n_usable = bisect.bisect_right(velocities, until + 1e-9, key=_sample_time)
        if n_usable < 2:
            return None
        t1, v1 = velocities[n_usable - 1]
        t0, v0 = velocities[bisect.bisect_left(velocities, t1 - window - 1e-9, hi=n_usable, key=_sample_time)]
        if t1 - t0 < 0.5 * window:
            return None
        d = t1 - t0
        return t0, t1, ((v1[0] - v0[0]) / d, (v1[1] - v0[1]) / d, (v1[2] - v0[2]) / d)

    def read_state(self, t: float):
        """(quaternion, euler, rates, euler_var, rate_var, sample time) or None."""
        if not self.estimate:
            s = self.truth.latest()
            if s is None:
                return None
            q = s["quaternion_wxyz"]
            self.accel_samples = s   # the descent reads the specific force from it (truth_specific_force)
            return q, np.array(quat_to_euler(q)), np.asarray(s["rate_rad_s"]), np.zeros(3), np.zeros(3), s["header"]["t_s"]
        filt, carrier, level = self.filt, self.carrier, self.level
        # the decoded lists go to the filter as they are (it reads floats); in time order, once
        samples = [(m["header"]["t_s"], m["gyro_rad_s"], m["accel_m_s2"]) for m in self.imu.take()]
        if len(samples) > 1:
            samples.sort(key=_sample_time)
        self.accel_samples = [(ts, acc) for ts, _, acc in samples]   # raw: the descent's vertical speed
        moving = self.motion.latest() if self.motion is not None else None
        if self.make_gyrovertical is not None:
            samples = [(ts, gyro, acc, self.gyrovertical_update(ts, np.asarray(gyro), np.asarray(acc), moving))
                       for ts, gyro, acc in samples]
        accel_ref = None
        if (self.compensate_000 and moving is not None and moving["state_source"] == "estimate"
                and filt.initialized):
            if self.windowed:
                newest_imu_t = samples[-1][0] if samples else filt.last_sample_t
                accel_ref = self.velocity_window(moving, newest_imu_t)
            else:
                # specific force f = R^T (a - g): remove R^T a so that what is left is gravity alone
                r_t = quat_to_rotation(self.filt_q).T
                a_body = r_t @ np.asarray(moving["acceleration_m_s2"])
                samples = [(ts, gyro, np.asarray(acc) - a_body) for ts, gyro, acc in samples]
        mags = self.mag.take()
        mag_sample = (mags[-1]["header"]["t_s"], mags[-1]["field_ut"]) if mags else None
        if not samples and filt.initialized is False:
            return None
        out = self.motors.latest()  # the torque the motors were really asked for (after saturation)
        applied = (self.vehicle.allocation @ np.asarray(out["thrust_n"]))[1:] if out is not None else self.last_torque
        # the estimate as floats (lists and tuples) from here to the messages: no arrays on the way
        euler, rates, q, euler_var, rate_var, _ = filt.update_floats(samples, mag_sample, applied, t,
                                                                     accel_ref=accel_ref)
        sample_t = samples[-1][0] if samples else filt.last_sample_t
        if not carrier.active:
            if filt.initialized:   # near level: the carrier only follows the 000 filter
                sample_euler, sample_rate = filt.sample_state_floats()
                carrier.follow_euler(filt.last_sample_t, sample_euler, samples[-1][1] if samples else sample_rate)
                carrier.check_enter(q, rates)
        else:
            for s in samples:
                carrier.propagate(s[0], s[1])
        if carrier.active:
            q, rates = carrier.estimate(t, self.carrier_horizon_s)
            euler = np.array(quat_to_euler(q))
            if carrier.back_near_level():   # the 000 filter takes over again from here
                filt.reinitialise(quat_to_euler(carrier.q), carrier.gyro)  # both at the newest sample
                carrier.active = False
        self.filt_q = q
        if level is not None:
            frames = self.poses.take()
            if not carrier.active:
                level.record(t, euler, rates)
                for m in frames:
                    level.fuse(m["header"]["t_s"], m["quaternion_wxyz"])
                if frames:
                    self.io.rejected.update(level.rejected)
                euler = level.apply_floats(euler)
                q = quat_from_euler_floats(*euler)
        return q, euler, rates, euler_var, rate_var, sample_t

    def count(self, reason: str) -> None:
        rejected = self.io.rejected
        rejected[reason] = rejected.get(reason, 0) + 1

    def descend(self, t: float, q) -> float:
        """The failsafe's thrust with no position setpoint: 0 on the ground (or never flown),
        else a controlled descent (module docstring)."""
        if not self.flying:
            return 0.0
        d, vehicle = self.descent, self.vehicle
        if d is None:
            self.count("failsafe_engaged")
            self.io.problem(f"failsafe: no position setpoint at t={t:.3f}: level, descend, cut on the ground")
            pos = self.last_motion.latest()
            d = self.descent = Descent(self.descent_params, vehicle.mass_kg, vehicle.gravity_m_s2,
                                       4 * vehicle.max_thrust_n)
            d.scale = pos["thrust_scale"] if pos is not None else 1.0
            d.start(t, pos["position_m"][2] if pos is not None else None,
                    pos["velocity_m_s"][2] if pos is not None else 0.0, self.flying)
        samples = self.accel_samples
        if isinstance(samples, dict):   # truth: the specific force an IMU would read
            samples = [truth_specific_force(samples, vehicle.gravity_m_s2)]
        for ts, acc in samples:
            d.update(ts, q, acc, d.scale)
        if d.landed:
            self.flying, self.descent = 0.0, None
            self.count("failsafe_landed")
            self.io.problem(f"failsafe: descended past the ground at t={t:.3f}: thrust cut")
            return 0.0
        return d.thrust

    def step(self, t: float) -> None:
        """One run at time t: read the state, command thrust and torques, publish the state."""
        p = self.p
        state = self.read_state(t)
        sp = self.setpoint.latest()
        if state is None:
            return
        q, euler, rates, euler_var, rate_var, sample_t = state
        if t - sample_t > p["state_timeout_s"]:   # steering on old samples: worse than nothing
            if sample_t != self.stale_t:       # counted once per sample, not per run
                self.stale_t = sample_t
                self.count("stale_state")
            return
        if sp is None or t - sp["header"]["t_s"] > p["setpoint_timeout_s"]:
            ref, thrust = [0.0, 0.0, float(euler[2])], self.descend(t, q)
        else:
            ref, thrust = sp["attitude_ref_rad"], sp["thrust_n"]
            if self.descent is not None:
                self.descent = None
                self.count("failsafe_recovered")
                self.io.problem(f"failsafe: position setpoints again at t={t:.3f}: control handed back")
            self.flying = thrust
        k, alpha = self.gains
        torque = attitude_law_floats(self.inertia, euler, rates, ref, k, alpha, self.law_max_accel)
        if thrust <= 0.0:
            torque = (0.0, 0.0, 0.0)  # on the ground, idle: nothing to steer (and nothing to wind up)
        self.last_torque = torque
        if self.command_from is None:
            self.command_from = sample_t + p["restart_settle_s"]
            self.io.problem(f"restarted: commands from t={self.command_from:.3f}, the filter settled")
        if sp is not None and sample_t >= self.command_from:   # before any setpoint there is nothing to
            # command: a level restarted in the air would otherwise send zero thrust over the motor
            # driver's own failsafe; nor before a restarted filter has settled
            self.command.put({"thrust_n": float(thrust), "torque_nm": torque, "imu_t_s": sample_t}, t_s=t)
        self.state_out.put({"quaternion_wxyz": q, "euler_rad": euler, "rate_rad_s": rates,
                            "euler_ref_rad": ref, "euler_var_rad2": euler_var, "rate_var_rad2_s2": rate_var,
                            "state_source": p["state_source"]}, t_s=t)


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS)
    loop = AttitudeLoop(rt)
    # run as the IMU sample (or the truth) arrives, every second one at 400 Hz: no period of waiting added
    rt.run(loop.step, wake_on=loop.wake_on, min_gap=0.6)


def main(argv=None) -> None:
    args = service_parser(NAME, __doc__.splitlines()[0]).parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
