"""zenpilot-attitude: the attitude level (200 Hz) of 000: filter and law (8).

State source `estimate` (default): every IMU sample goes through the
low-pass filters (12) and a linear Kalman filter per axis on
[w, w_f, angle, angle_f] with the torque input (13), (16)-(20); the analytic
extrapolator (15) carries the estimate over the measured transport delay
(newest IMU sample time to now) with the stored torques. With
`estimator = "gyro-vertical"` the adaptive gyro-vertical of 004 runs on every
raw IMU sample and its roll/pitch replace the accelerometer angles as the
filter's angle measurement (trained parameters from `gyrovertical_params`,
written by `zenpilot train-gyrovertical`). State source
`truth`: the simulator's ground truth (an explicit ablation setting).
Law (8) u = I [-(alpha+k) w - alpha k (angle - ref)] tracks the position
level's reference; the collective thrust is passed on to the motor driver.

Stale inputs: a run whose newest IMU sample (or truth) is older than `state_timeout_s`
publishes no command (counted once per sample, "stale_state": a loop resumed after a freeze must not steer on
old samples; the motor driver's failsafe covers the gap). A position setpoint older than
`setpoint_timeout_s` is not used: in the air (the last fresh one asked for thrust) the level
holds level and descends on its own (flight/failsafe.Descent: the accelerometer's vertical
speed, a thrust ramp to a slow sink, thrust cut past the ground estimated from the last
pos/state; counted "failsafe_engaged", "failsafe_landed"); fresh setpoints take over again.
"""

from __future__ import annotations

import bisect
from collections import deque
from operator import itemgetter

import numpy as np

import schemas
from flight.estimation.attitude_filter import (
    AttitudeFilter,
    AttitudeFilterParams,
    accel_roll_pitch,
)
from flight.estimation.camera_level import CameraLevel
from flight.estimation.gyro_carrier import GyroCarrier
from flight.control.laws import STOPPING_ACCEL_FRACTION, attitude_law, stopping_accel
from flight.control.failsafe import Descent, DescentParams
from flight.estimation.gyrovertical import DEFAULT_PARAMS_FILE, GyroVertical, load_trained
from flight.quat import quat_from_euler, quat_to_euler, quat_to_rotation, rotate_vector
from flight.vehicle import load_vehicle
from services.runtime import Runtime, main_guard, service_parser

NAME = "attitude"
PARAMS = {
    "state_source": "estimate",
    "k": [16.0, 16.0, 16.0],      # law (8) gains per axis (roll, pitch, yaw), 1/s
    "alpha": [16.0, 16.0, 16.0],
    # Law (8)'s angle loop asks at most for the rate this fraction of the airframe's angular
    # acceleration can stop (flight/control.stopping_rate): beyond a few degrees of error on a
    # heavy frame the linear law saturates the rotors, overshoots and can limit-cycle. Errors
    # below (fraction a_max) / (alpha k / (alpha + k))^2 see law (8) exactly. 0: law (8) as printed.
    "stopping_accel_fraction": STOPPING_ACCEL_FRACTION,
    # stale position setpoint -> in the air: level, controlled descent (failsafe); on the ground: idle
    "setpoint_timeout_s": 0.1,
    "state_timeout_s": 0.05,      # newest IMU sample (truth) older than this -> no command
    "failsafe_descent": {},       # flight/failsafe.DescentParams overrides
    "filter": {},                 # AttitudeFilterParams overrides (flight/estimation/attitude_filter.py)
    # Subtract the position level's acceleration estimate from the accelerometer
    # (the V' terms of 004's observation (5)) before deriving roll and pitch: a
    # multirotor's accelerometer reads "level" whenever it tilts to accelerate, so
    # 000's plain accelerometer angles pull the estimate toward level in every
    # manoeuvre. False: 000 as printed.
    "compensate_acceleration": True,
    # How the acceleration is compensated (compensate_acceleration = true):
    # "window" compares the position level's velocity change over the last
    # `accel_window_s` with the one the accelerometer gives at the filter's own attitude
    # over the same window (AttitudeFilter accel_ref: no lag between the two, so a tilt
    # step is not read as a pull towards level); "slope" subtracts the position
    # level's published acceleration (its velocity slope, ~50 ms late) from the samples.
    "acceleration_compensation": "window",
    "accel_window_s": 0.1,
    # Angle measurement of the filter: "kalman-000" the accelerometer angles of
    # 000; "gyro-vertical" the adaptive gyro-vertical of 004 (raw IMU in, its own
    # adaptive accelerometer trust; compensate_acceleration does not apply).
    "estimator": "kalman-000",
    "gyrovertical_params": "",    # trained parameter file; "" = the shipped one for the x250
    "imu_rate_hz": 400.0,         # the gyro-vertical's sample period (its variances are per sample)
    # Remove the accelerometer bias's tilt with the camera's attitude (vision/pose): the
    # estimate minus the camera's roll/pitch at each frame's exposure time, low-passed
    # (flight/attitude_filter.CameraLevel). False: no camera at the attitude level (000).
    "camera_level": True,
    "camera_level_settings": {"time_constant_s": 2.0},
    # Flips (001): beyond these the 000 filter (Euler axes, body rate as Euler rate) cannot
    # follow the vehicle; a gyro-integrated quaternion carries the estimate instead and the
    # filter restarts from it back near level (flight/attitude_filter.GyroCarrier).
    "carrier": {"enter_tilt_deg": 45.0, "exit_tilt_deg": 30.0, "enter_rate_rad_s": 6.0, "exit_rate_rad_s": 2.0},
}
STATE_SOURCES = ("truth", "estimate")
COMPENSATIONS = ("window", "slope")
VELOCITY_KEEP_S = 0.2  # pos/state history kept beyond the window: covers an IMU transport delay
ESTIMATORS = ("kalman-000", "gyro-vertical")
_sample_time = itemgetter(0)


def truth_specific_force(truth: dict, gravity_m_s2: float):
    """(t, body specific force) from a truth message: R^T (a + g z)."""
    a, q = truth["acceleration_m_s2"], np.asarray(truth["quaternion_wxyz"])
    return truth["header"]["t_s"], rotate_vector(q * [1.0, -1.0, -1.0, -1.0], [a[0], a[1], a[2] + gravity_m_s2])


def load_gyrovertical(rt: Runtime):
    """A maker of the gyro-vertical (trained parameters, IMU period) from an initial quaternion.

    A missing or bad parameter file is refused at start-up with its name."""
    path = rt.params["gyrovertical_params"] or DEFAULT_PARAMS_FILE
    try:
        trained = load_trained(path)
    except ValueError as exc:
        raise ValueError(f"{rt.where()} gyrovertical_params: {exc}") from None
    rate = rt.params["imu_rate_hz"]
    if not (isinstance(rate, (int, float)) and rate > 0):
        raise ValueError(f"{rt.where()} imu_rate_hz: must be a positive number, got {rate!r}")
    return lambda q0: GyroVertical(trained.adaptive, dt=1.0 / rate, q0=q0)


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS)
    p = rt.params
    vehicle = load_vehicle(rt.vehicle_name)
    estimate = rt.choice("state_source", STATE_SOURCES) == "estimate"
    if estimate:
        params = rt.table("filter", AttitudeFilterParams.from_dict)
        filt = AttitudeFilter(np.asarray(vehicle.inertia_kg_m2), params, dt=1.0 / rt.rate_hz,
                              gravity_m_s2=vehicle.gravity_m_s2)
        try:
            carrier = GyroCarrier(**p["carrier"])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{rt.where()} carrier: {exc}") from None
        carrier_horizon_s = params.max_delay_steps / rt.rate_hz
        level = None
        if p["camera_level"]:
            try:
                level = CameraLevel(**p["camera_level_settings"])
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{rt.where()} camera_level_settings: {exc}") from None
            poses = rt.inbox(schemas.VISION_POSE, "vision", keep=8)
        imu = rt.inbox(schemas.IMU, "sim", keep=32)
        mag = rt.inbox(schemas.MAG, "sim", keep=8)
        motors = rt.inbox(schemas.MOTOR_PWM, "motors")
        make_gyrovertical = load_gyrovertical(rt) if rt.choice("estimator", ESTIMATORS) == "gyro-vertical" else None
        compensate = p["compensate_acceleration"] and make_gyrovertical is None
        print(f"zenpilot-attitude: estimator {p['estimator']}"
              + (f" ({p['gyrovertical_params'] or DEFAULT_PARAMS_FILE.name})" if make_gyrovertical else ""), flush=True)
        motion = rt.inbox(schemas.POSITION_STATE, "position") if compensate else None
        windowed = rt.choice("acceleration_compensation", COMPENSATIONS) == "window"
        accel_window_s = p["accel_window_s"]
        if not (isinstance(accel_window_s, (int, float)) and not isinstance(accel_window_s, bool)
                and 0.0 < accel_window_s <= 0.5):
            raise ValueError(f"{rt.where()} accel_window_s: must be in (0, 0.5] s, got {accel_window_s!r}")
        velocities: deque = deque()   # (t, velocity) of the position level's estimate, newest last
    else:
        truth = rt.inbox(schemas.TRUTH, "sim")
    setpoint = rt.inbox(schemas.POSITION_SETPOINT, "position")
    # the last altitude and climb rate when the position level goes (the descent's start)
    last_motion = (motion if estimate and motion is not None
                   else rt.inbox(schemas.POSITION_STATE, "position"))
    descent_params = rt.table("failsafe_descent", DescentParams.from_dict)
    failsafe = {"flying": 0.0, "descent": None, "accel": [], "stale_t": None}
    command = rt.publisher(schemas.ATTITUDE_COMMAND)
    state_out = rt.publisher(schemas.ATTITUDE_STATE)
    k, alpha = rt.live_array("k"), rt.live_array("alpha")
    fraction = p["stopping_accel_fraction"]
    if not (isinstance(fraction, (int, float)) and not isinstance(fraction, bool) and 0.0 <= fraction <= 1.0):
        raise ValueError(f"{rt.where()} stopping_accel_fraction: must be in [0, 1], got {fraction!r}")
    max_accel = stopping_accel(vehicle.max_angular_accel_rad_s2, fraction)
    last_torque = {"u": np.zeros(3)}
    filt_state = {"q": np.array([1.0, 0.0, 0.0, 0.0])}

    gyrovertical = {"filter": None, "last_t": None}

    def gyrovertical_update(t_s: float, gyro, accel) -> tuple[float, float]:
        """Feed one raw IMU sample to the gyro-vertical (once, in time order); its (roll, pitch)."""
        gv = gyrovertical["filter"]
        if gv is None:   # start from the accelerometer's vertical, as the 000 filter does
            gv = gyrovertical["filter"] = make_gyrovertical(quat_from_euler(*accel_roll_pitch(accel), 0.0))
        elif t_s <= gyrovertical["last_t"]:
            return gv.roll, gv.pitch
        gyrovertical["last_t"] = t_s
        return gv.update(gyro, accel)

    def velocity_window(moving, until: float):
        """(t0, t1, mean acceleration) from the position level's velocities over accel_window_s,
        ending at or before `until` (the newest IMU sample: the filter compares the window with its
        own samples, which arrive later than pos/state when the IMU has a transport delay), or None."""
        t_p = moving["header"]["t_s"]
        if not velocities or t_p > velocities[-1][0]:
            velocities.append((t_p, moving["velocity_m_s"]))
        elif t_p < velocities[-1][0]:      # time went back (a restart): start over
            velocities.clear()
            velocities.append((t_p, moving["velocity_m_s"]))
        while len(velocities) > 1 and velocities[0][0] < velocities[-1][0] - accel_window_s - VELOCITY_KEEP_S:
            velocities.popleft()
        # the usable ones (at or before `until`) are a prefix of the time-ordered history
        n_usable = bisect.bisect_right(velocities, until + 1e-9, key=_sample_time)
        if n_usable < 2:
            return None
        t1, v1 = velocities[n_usable - 1]
        t0, v0 = velocities[bisect.bisect_left(velocities, t1 - accel_window_s - 1e-9, hi=n_usable,
                                               key=_sample_time)]
        if t1 - t0 < 0.5 * accel_window_s:
            return None
        d = t1 - t0
        return t0, t1, ((v1[0] - v0[0]) / d, (v1[1] - v0[1]) / d, (v1[2] - v0[2]) / d)

    def read_state(t: float):
        """(quaternion, euler, rates, euler_var, rate_var, sample time) or None."""
        if not estimate:
            s = truth.latest()
            if s is None:
                return None
            q = s["quaternion_wxyz"]
            failsafe["accel"] = s   # the descent reads the specific force from it (truth_specific_force)
            return q, np.array(quat_to_euler(q)), np.asarray(s["rate_rad_s"]), np.zeros(3), np.zeros(3), s["header"]["t_s"]
        # the decoded lists go to the filter as they are (it reads floats); in time order, once
        samples = [(m["header"]["t_s"], m["gyro_rad_s"], m["accel_m_s2"]) for m in imu.take()]
        samples.sort(key=_sample_time)
        failsafe["accel"] = [(ts, acc) for ts, _, acc in samples]   # raw: the descent's vertical speed
        if make_gyrovertical is not None:
            samples = [(ts, gyro, acc, gyrovertical_update(ts, np.asarray(gyro), np.asarray(acc)))
                       for ts, gyro, acc in samples]
        moving = motion.latest() if motion is not None else None
        accel_ref = None
        if moving is not None and moving["state_source"] == "estimate" and filt.initialized:
            if windowed:
                newest_imu_t = samples[-1][0] if samples else filt.last_sample_t
                accel_ref = velocity_window(moving, newest_imu_t)
            else:
                # specific force f = R^T (a - g): remove R^T a so that what is left is gravity alone
                r_t = quat_to_rotation(filt_state["q"]).T
                a_body = r_t @ np.asarray(moving["acceleration_m_s2"])
                samples = [(ts, gyro, np.asarray(acc) - a_body) for ts, gyro, acc in samples]
        mags = mag.take()
        mag_sample = (mags[-1]["header"]["t_s"], mags[-1]["field_ut"]) if mags else None
        if not samples and filt.initialized is False:
            return None
        out = motors.latest()  # the torque the motors were really asked for (after saturation)
        applied = (vehicle.allocation @ np.asarray(out["thrust_n"]))[1:] if out is not None else last_torque["u"]
        est = filt.update(samples, mag_sample, applied, t, accel_ref=accel_ref)
        sample_t = samples[-1][0] if samples else filt.last_sample_t
        q, euler, rates = est.quaternion_wxyz, est.euler_rad, est.rate_rad_s
        if not carrier.active:
            if filt.initialized:   # near level: the carrier only follows the 000 filter
                sample_euler, sample_rate = filt.sample_state()
                carrier.follow(filt.last_sample_t, quat_from_euler(*sample_euler),
                               samples[-1][1] if samples else sample_rate)
                carrier.check_enter(q, rates)
        else:
            for s in samples:
                carrier.propagate(s[0], s[1])
        if carrier.active:
            q, rates = carrier.estimate(t, carrier_horizon_s)
            euler = np.array(quat_to_euler(q))
            if carrier.back_near_level():   # the 000 filter takes over again from here
                filt.reinitialise(quat_to_euler(carrier.q), carrier.gyro)  # both at the newest sample
                carrier.active = False
        filt_state["q"] = q
        if level is not None:
            frames = poses.take()
            if not carrier.active:
                level.record(t, euler, rates)
                for m in frames:
                    level.fuse(m["header"]["t_s"], m["quaternion_wxyz"])
                if frames:
                    rt.rejected.update(level.rejected)
                euler = level.apply(euler)
                q = quat_from_euler(*euler)
        return q, euler, rates, est.euler_var, est.rate_var, sample_t

    def count(reason: str) -> None:
        rt.rejected[reason] = rt.rejected.get(reason, 0) + 1

    def descend(t: float, q) -> float:
        """The failsafe's thrust with no position setpoint: 0 on the ground (or never flown),
        else a controlled descent (module docstring)."""
        if not failsafe["flying"]:
            return 0.0
        d = failsafe["descent"]
        if d is None:
            count("failsafe_engaged")
            rt.problem(f"failsafe: no position setpoint at t={t:.3f}: level, descend, cut on the ground")
            pos = last_motion.latest()
            d = failsafe["descent"] = Descent(descent_params, vehicle.mass_kg, vehicle.gravity_m_s2,
                                              4 * vehicle.max_thrust_n)
            d.scale = pos["thrust_scale"] if pos is not None else 1.0
            d.start(t, pos["position_m"][2] if pos is not None else None,
                    pos["velocity_m_s"][2] if pos is not None else 0.0, failsafe["flying"])
        samples = failsafe["accel"]
        if isinstance(samples, dict):   # truth: the specific force an IMU would read
            samples = [truth_specific_force(samples, vehicle.gravity_m_s2)]
        for ts, acc in samples:
            d.update(ts, q, acc, d.scale)
        if d.landed:
            failsafe["flying"], failsafe["descent"] = 0.0, None
            count("failsafe_landed")
            rt.problem(f"failsafe: descended past the ground at t={t:.3f}: thrust cut")
            return 0.0
        return d.thrust

    def step(t: float) -> None:
        state = read_state(t)
        sp = setpoint.latest()
        if state is None:
            return
        q, euler, rates, euler_var, rate_var, sample_t = state
        if t - sample_t > p["state_timeout_s"]:   # steering on old samples: worse than nothing
            if sample_t != failsafe["stale_t"]:       # counted once per sample, not per run
                failsafe["stale_t"] = sample_t
                count("stale_state")
            return
        if sp is None or t - sp["header"]["t_s"] > p["setpoint_timeout_s"]:
            ref, thrust = np.array([0.0, 0.0, euler[2]]), descend(t, q)
        else:
            ref, thrust = np.asarray(sp["attitude_ref_rad"]), sp["thrust_n"]
            if failsafe["descent"] is not None:
                failsafe["descent"] = None
                count("failsafe_recovered")
                rt.problem(f"failsafe: position setpoints again at t={t:.3f}: control handed back")
            failsafe["flying"] = thrust
        torque = attitude_law(vehicle.inertia_kg_m2, euler, rates, ref, k, alpha, max_accel)
        if thrust <= 0.0:
            torque = np.zeros(3)  # on the ground, idle: nothing to steer (and nothing to wind up)
        last_torque["u"] = torque
        if sp is not None:   # before any setpoint there is nothing to command: a level restarted in
            # the air would otherwise send zero thrust over the motor driver's own failsafe
            command.put({"thrust_n": float(thrust), "torque_nm": torque, "imu_t_s": sample_t}, t_s=t)
        state_out.put({"quaternion_wxyz": q, "euler_rad": euler, "rate_rad_s": rates,
                       "euler_ref_rad": ref, "euler_var_rad2": euler_var, "rate_var_rad2_s2": rate_var,
                       "state_source": p["state_source"]}, t_s=t)

    # run as the IMU sample (or the truth) arrives, every second one at 400 Hz: no period of waiting added
    rt.run(step, wake_on=imu if estimate else truth, min_gap=0.6)


def main(argv=None) -> None:
    args = service_parser(NAME, __doc__.splitlines()[0]).parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
