"""zenpilot-position: the position level (100 Hz) of 000: EKF and laws (9)-(11).

State source `estimate` (default): an extended Kalman filter on the
12-state model (1)-(2) with the thrust/torque input, fed with the attitude
level's angles and rates (200 Hz) and the vision poses (20 Hz, about 50 ms
old: fused at their exposure time and predicted forward, see
flight/estimation/position_ekf.py). Gated measurements are counted, never fused.
State source `truth`: the simulator's ground truth (an explicit ablation).
In `position` mode laws (10), (9), (11) turn the planner's reference into an
attitude reference and collective thrust; in `attitude` mode the altitude
is held and the planner's attitude reference passed through.

Failsafes (the vehicle's own, never waiting on the ground): the planner's setpoint older
than `setpoint_timeout_s` -> hold the position we had; after `planner_loss_land_after_s` of
it, land there (the height reference sinking at `land_speed_m_s`; on the ground -> idle,
"planner_lost_landed", and down until the planner disarms: "planner_back_landed"); in the air a
fresh setpoint takes over again, its position reached from where the vehicle is at
`land_speed_m_s` ("planner_back"), not as a step: the planner's mission went on while it was
lost (a landing's reference 0.9 m below, after a 2 s link outage, saturated the tilt and the
mixer's collective with it: the vehicle climbed to 3 m, once 83 m; docs/reliability.md). No
camera fix fused for `vision_timeout_s` while flying on the estimate -> the EKF coasts (its covariance grows) and
the position level withholds its setpoint, so that the attitude level's own descent lands the
vehicle ("vision_lost"); a fix fused again resumes it. A camera fix older than
`pose_timeout_s` at arrival is not fused ("stale_pose"), an attitude estimate older than
`attitude_timeout_s` neither ("stale_att_state").
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque

import numpy as np

import schemas
from flight.control.laws import (DisturbanceObserver, altitude_law, hold_integral_update, position_law,
                                 thrust_accel_xy)
from flight.estimation.camera_delay import CameraDelayEstimator, CameraDelayParams
from flight.estimation.position_ekf import DISTURBANCE, LaggedMotorInput, PositionEKF, PositionEKFParams
from flight.quat import quat_tilt, quat_to_euler
from flight.vehicle import load_vehicle
from services.params.position import PARAMS  # every parameter: default, unit, bounds, doc
from services.runtime import Runtime, main_guard, service_parser

NAME = "position"
ACCEL_WINDOW_S = 0.1  # acceleration = slope of the velocity over this window
# landing with no planner: the reference goes this far below home (pressing down), and the
# vehicle is down once this low and this slow for this long
LAND_BELOW_M = 0.3
LANDED_HEIGHT_M = 0.1
LANDED_SPEED_M_S = 0.2
LANDED_FOR_S = 1.0
DRAG_MIN_HEIGHT_M = 0.05   # the accelerometer as the air's force (fuse_drag): above the ground's reach
CARRYING_THRUST = 0.5      # of the weight: the rotors carry the vehicle (fuse_drag, start_ekf)
VISION_MIN_HEIGHT_M = 0.3   # below this the camera's silence is not a loss (too close to the markers)
EKF_HEALTH_PERIOD_S = 1.0   # pos/ekf_health, beside the service's own health
# the planner's phases where the integral learns: a hold and the settling before it (a take-off's
# wind offset is gone before the hold's measurement starts)
HOLD_PHASES = ("hold", "settle")
# the disturbance observer's model (the thrust's tilt) is trusted to here (45 degrees)
OBSERVER_MIN_TILT_COS = math.cos(math.radians(45.0))
# after the attitude was pinned (a flip) the EKF has coasted, after a position reset it starts
# again: its first fixes' innovations are that error, not the camera's timing, and stay out of
# the delay's fit this long
DELAY_FIT_AFTER_S = 1.0
# ... and while the EKF's thrust scale still moves by more than this over the last second (a
# vehicle heavier or lighter than its file, learnt in the first seconds of flight): the model's
# velocity, the delay's regressor, is wrong by the scale's error times the acceleration (a climb
# of a +10 % mass q820 read as an 87 ms offset, "corrected", and the flip then crashed)
THRUST_SCALE_SETTLED = 0.01


class PositionLoop:
    """The position level's logic: EKF (or truth), laws (9)-(11) and the failsafes (module
    docstring). `io` is the service's Runtime in flight, a fake in the unit tests; no Zenoh here."""

    def __init__(self, io):
        self.io = io
        p = self.p = io.params
        vehicle = self.vehicle = load_vehicle(io.vehicle_name)
        self.dt = 1.0 / io.rate_hz
        self.estimate = p["state_source"] == "estimate"
        if self.estimate:
            ekf_params = io.table("ekf", PositionEKFParams.from_dict)
            if not p["wind_estimation"]:   # the disturbance states held at 0: the filter of (1) as before them
                ekf_params = dataclasses.replace(ekf_params, q_disturbance_m2_s5=0.0, init_std_disturbance_m_s2=0.0,
                                                 q_accel_bias_m2_s5=0.0, init_std_accel_bias_m_s2=0.0)
            self.ekf = PositionEKF(vehicle, ekf_params, dt=self.dt)
            self.attitude = io.inbox(schemas.ATTITUDE_STATE, "attitude")
            self.motors = io.inbox(schemas.MOTOR_PWM, "motors", keep=32)  # every 400 Hz command of a step
            self.poses = io.inbox(schemas.VISION_POSE, "vision", keep=16)
            # the accelerometer observes the wind's pull (PositionEKF.update_drag): only when it is learnt
            self.imu = io.inbox(schemas.IMU, "sim", keep=16) if p["wind_estimation"] and p["drag_fusion"] else None
            self.rotor_forces = LaggedMotorInput(vehicle.motor_time_constant_s)  # the plant's motor lag
            self.delay = CameraDelayEstimator(io.table("camera_delay", CameraDelayParams.from_dict))
            self.ekf_health_out = io.publisher(schemas.POSITION_EKF_HEALTH)
            self.ekf_health_out.tracked = False   # as the service's health: nobody on the clock reads it
            self.next_ekf_health = 0.0
            self.delay_step_t = self.offset_detected_t = -1.0   # when (a) last saw a step, (b) an offset
            self.unsettled_t = -math.inf     # when the attitude was last pinned, the position reset
            self.thrust_scales: deque = deque()   # or the thrust scale moved; (t, scale) of the last second
        else:
            self.truth = io.inbox(schemas.TRUTH, "sim")
        self.ekf_started = False
        self.in_flight_at_start = None   # decided on the first run: the rotors already carry the vehicle
        self.carrying_n = CARRYING_THRUST * vehicle.mass_kg * vehicle.gravity_m_s2
        self.refused = 0             # camera fixes refused in a row
        self.fused_t = None          # when a camera fix was last fused
        self.stale_att_t = None      # the attitude message last counted stale
        self.planner = io.inbox(schemas.PLANNER_SETPOINT, "planner")
        self.setpoint_out = io.publisher(schemas.POSITION_SETPOINT)
        self.state_out = io.publisher(schemas.POSITION_STATE)
        self.k, self.alpha = io.live_array("k"), io.live_array("alpha")  # param/set applies them live
        self.allocation = vehicle.allocation
        self.hold_position = None    # planner lost: the position held (then landed at)
        self.lost_flying = False     # ... while flying on its setpoints (counted planner_lost)
        self.resume = None           # the planner back: (where from, when) of the ramp to its setpoint
        self.hold_since = 0.0
        self.landed = False
        self.landed_for = 0.0
        self.vision_lost = False
        self.camera_due_t = -math.inf   # since when a camera fix is due: the vehicle last left the ground
        self.integral = np.zeros(2)  # hold_ki's integral of the position error
        self.bias = None
        self.ekf_disturbance = None   # (x, y) of the EKF, m/s^2: read_state
        if p["disturbance_bandwidth_rad_s"] > 0.0 and p["wind_estimation"] and self.estimate:
            # both estimate the same pull: fed forward together they would ask for it twice
            raise ValueError(f"{io.where()}: wind_estimation and disturbance_bandwidth_rad_s > 0 (the observer) "
                             "both feed the wind forward: use one of them")
        self.observer = (DisturbanceObserver(p["disturbance_bandwidth_rad_s"], p["disturbance_limit_m_s2"],
                                             vehicle.drag_n_per_m_s / vehicle.mass_kg)
                         if p["disturbance_bandwidth_rad_s"] > 0.0 else None)
        self.collective_n = None    # the rotors' collective force the EKF last predicted with
        self.thrust_n = None        # the collective last asked for
        self.tilt_deg, self.tilt_rad = None, 0.0  # vehicle.tilt_limit_rad of the (live) max_tilt_deg
        self.velocities: deque = deque(maxlen=max(2, round(ACCEL_WINDOW_S * io.rate_hz) + 1))

    def count(self, reason: str) -> None:
        rejected = self.io.rejected
        rejected[reason] = rejected.get(reason, 0) + 1

    def read_state(self, t: float):
        """(position, velocity, euler, position covariance, thrust scale) or None."""
        if not self.estimate:
            s = self.truth.latest()
            if s is None:
                return None
            return (np.asarray(s["position_m"]), np.asarray(s["velocity_m_s"]),
                    np.array(quat_to_euler(s["quaternion_wxyz"])), np.zeros((3, 3)), 1.0)
        p, ekf, count = self.p, self.ekf, self.count
        outputs = self.motors.take()
        for out in outputs:  # what the mixer really asked of the motors (after saturation)
            self.rotor_forces.add(out["header"]["t_s"], out["thrust_n"])
        if not self.ekf_started and not self.start_ekf(t, outputs):
            return None
        if t > ekf.t:
            u = self.allocation @ self.rotor_forces.mean_to(t)
            self.collective_n = float(u[0])
            ekf.predict(t, u)
        att = self.attitude.latest()
        if att is not None and t - att["header"]["t_s"] > p["attitude_timeout_s"]:
            if att["header"]["t_s"] != self.stale_att_t:   # counted once per message
                self.stale_att_t = att["header"]["t_s"]
                count("stale_att_state")
            att = None   # the attitude level gone or late: predict on, never re-fuse an old estimate
        # the messages' lists go to the EKF as they are (it takes plain floats)
        pinned = False
        if att is not None and att["state_source"] == "estimate" \
                and quat_tilt(att["quaternion_wxyz"]) > math.radians(p["attitude_pin_tilt_deg"]):
            ekf.pin_attitude(att["header"]["t_s"], att["euler_rad"], att["rate_rad_s"])
            count("attitude_pinned_tilted")
            self.unsettled_t = t
            pinned = True
        elif att is not None and att["state_source"] == "estimate":
            if not ekf.update_attitude(att["header"]["t_s"], att["euler_rad"], att["rate_rad_s"],
                                       [max(v, f) for v, f in zip(att["euler_var_rad2"], p["attitude_var_floor"])],
                                       [max(v, f) for v, f in zip(att["rate_var_rad2_s2"], p["rate_var_floor"])]):
                count("fusion_attitude_gate")
        if self.imu is not None:
            self.fuse_drag(pinned)
        delay = self.delay
        for pose in self.poses.take():
            stamp = pose["header"]["t_s"]
            if delay.transport(t, stamp):
                count("camera_delay_step")
                self.delay_step_t = t
                self.io.problem(f"camera delay now {1e3 * delay.transport_s:.0f} ms (arrival - stamp) at t={t:.3f}")
            if t - stamp > p["pose_timeout_s"]:
                count("stale_pose")
                continue
            cov = np.asarray(pose["position_cov_m2"]).reshape(3, 3) + np.eye(3) * p["camera_var_floor"]
            t_fix = stamp if p["fuse_camera_at_exposure"] else ekf.t
            correction = delay.correction_s
            if correction and p["fuse_camera_at_exposure"]:   # the offset the innovations show and the stamps do not; never ahead of the filter
                t_fix -= correction
                if t_fix > ekf.t:
                    t_fix = max(stamp, ekf.t)
            accepted, _nis = ekf.update_position(t_fix, np.asarray(pose["position_m"]), cov)
            fix = ekf.camera_fix
            if not self.thrust_scale_settled(t, ekf.thrust_scale):
                self.unsettled_t = t
            if fix is not None and delay.innovation(t_fix, *fix, fit=t - self.unsettled_t > DELAY_FIT_AFTER_S):
                count("camera_offset_detected")
                self.offset_detected_t = t
                self.io.problem(f"camera fixes {1e3 * delay.offset_s:.0f} ms older than stamped "
                                f"(+-{1e3 * delay.offset_std_s:.0f} ms) at t={t:.3f}"
                                + (": correcting" if delay.params.correct else ""))
            if accepted:
                self.refused = 0
                self.fused_t = t
                continue
            count("fusion_position_rejected")
            if fix is None:   # too old, ahead of the filter, invalid: no sign the filter lost the vehicle
                continue
            self.refused += 1   # gated
            if self.refused >= p["position_reset_after"]:
                ekf.reset_position(pose["position_m"], cov, age_s=ekf.t - t_fix)
                delay.reset()
                self.unsettled_t = t
                count("fusion_position_reset")
                self.refused = 0
        x = ekf.x
        d0, d1 = x[DISTURBANCE]
        self.ekf_disturbance = (float(d0), float(d1))
        if t >= self.next_ekf_health:
            self.next_ekf_health = (math.floor(t / EKF_HEALTH_PERIOD_S) + 1) * EKF_HEALTH_PERIOD_S
            self.publish_ekf_health(t)
        return x[0:3], x[3:6], x[6:9], ekf.position_cov, float(x[12])

    def start_ekf(self, t: float, outputs: list) -> bool:
        """Start the EKF: at home, or, when this level starts with the rotors already carrying the
        vehicle (restarted in flight while the attitude level's failsafe flies it), at the first
        fresh camera fix, as a restart: from home it steered a vehicle 1 m up as if on the ground
        (a supervised restart's flight crashed). False while it waits for that fix."""
        ekf, p = self.ekf, self.p
        if self.in_flight_at_start is None:
            self.in_flight_at_start = any(o["armed"] and sum(o["thrust_n"]) > self.carrying_n for o in outputs)
            if self.in_flight_at_start:
                self.io.problem(f"started with the rotors carrying the vehicle at t={t:.3f}: the EKF starts "
                                "at the first camera fix (the attitude level flies meanwhile)")
        if not self.in_flight_at_start:
            # no state before the attitude level's first estimate (PX4's pre-arm "estimator not
            # ready"): the planner arms on the first state, and in real time this level starts first
            att = self.attitude.latest()
            if att is None or t - att["header"]["t_s"] > p["attitude_timeout_s"]:
                return False
            ekf.initialize(t, np.asarray(p["home_position_m"], dtype=float))
            self.ekf_started = True
            return True
        fresh = [x for x in self.poses.take() if t - x["header"]["t_s"] <= p["pose_timeout_s"]]
        if not fresh:
            return False
        pose = fresh[-1]
        position = np.asarray(pose["position_m"])
        cov = np.asarray(pose["position_cov_m2"]).reshape(3, 3) + np.eye(3) * p["camera_var_floor"]
        ekf.initialize(t, position)
        ekf.reset_position(position, cov, age_s=t - pose["header"]["t_s"])
        self.ekf_started = True
        self.count("ekf_started_in_flight")
        return True

    def fuse_drag(self, pinned: bool) -> None:
        """The accelerometer's body x and y since the last run, averaged, to the EKF as the air's
        force: in the air only (on the ground its friction holds against the wind), thrusting
        (not in a flip's coast or a cut), not while the attitude is pinned (a flip)."""
        samples = self.imu.take()
        ekf = self.ekf
        if not samples or pinned or self.collective_n is None \
                or self.collective_n < self.carrying_n \
                or ekf.x[2] < self.p["home_position_m"][2] + DRAG_MIN_HEIGHT_M:
            return
        ax = ay = 0.0
        for sample in samples:
            a = sample["accel_m_s2"]
            ax += a[0]
            ay += a[1]
        n = len(samples)
        var = ekf.params.r_drag_m2_s4
        accepted, _ = ekf.update_drag(min(samples[-1]["header"]["t_s"], ekf.t), (ax / n, ay / n), (var, var))
        if not accepted:
            self.count("fusion_drag_rejected")

    def publish_ekf_health(self, t: float) -> None:
        delay, counts = self.delay, self.ekf.counters["position"]
        median = delay.transport_s
        self.ekf_health_out.put({
            "camera_delay_s": median if math.isfinite(median) else -1.0,
            "camera_delay_spread_s": delay.transport_spread_s, "camera_delay_steps": delay.transport_steps,
            "camera_delay_step_t_s": self.delay_step_t,
            "camera_offset_s": delay.offset_s, "camera_offset_std_s": delay.offset_std_s,
            "camera_offset_confident": delay.confident, "camera_offset_correction_s": delay.correction_s,
            "camera_offset_detections": delay.detections, "camera_offset_detected_t_s": self.offset_detected_t,
            "camera_fixes": counts, "disturbance_m_s2": list(self.ekf_disturbance),
            "disturbance_estimated": bool(self.p["wind_estimation"])}, t_s=t)

    def thrust_scale_settled(self, t: float, scale: float) -> bool:
        """Record the EKF's thrust scale at t (each camera fix) and say whether it stayed within
        THRUST_SCALE_SETTLED over the last second (a second of history needed)."""
        scales = self.thrust_scales
        scales.append((t, scale))
        while scales[0][0] < t - 1.0:
            scales.popleft()
        spread = max(s for _, s in scales) - min(s for _, s in scales)
        return t - scales[0][0] >= 1.0 - 0.1 and spread <= THRUST_SCALE_SETTLED

    def step(self, t: float) -> None:
        """One run at time t: the state, then the setpoint for the attitude level."""
        p, vehicle, k, alpha = self.p, self.vehicle, self.k, self.alpha
        state, sp = self.read_state(t), self.planner.latest()
        if state is None:
            return
        pos, vel, (roll, pitch, yaw), cov, thrust_scale = state
        m_eff = vehicle.mass_kg / thrust_scale  # the mass the laws see: a vehicle that gets less thrust per newton
        g = vehicle.gravity_m_s2
        stale = sp is None or t - sp["header"]["t_s"] > p["setpoint_timeout_s"]
        if stale and self.hold_position is None:
            self.hold_position = pos.copy()  # planner lost: hold the position we had
            self.hold_since, self.landed = t, False
            if sp is not None and sp["armed"] and sp["mode"] != "idle":
                self.lost_flying = True
                self.count("planner_lost")
                self.io.problem(f"failsafe: no planner setpoint at t={t:.3f}: holding, landing after "
                                f"{p['planner_loss_land_after_s']} s")
        if not stale:
            if self.landed:   # landed by the failsafe: down until the planner disarms (as PX4 disarms)
                if sp["armed"] and sp["mode"] != "idle":
                    if self.lost_flying:
                        self.lost_flying = False
                        self.count("planner_back_landed")
                        self.io.problem(f"the planner is back at t={t:.3f}, the vehicle landed without it: it "
                                        "stays down until the planner disarms (then arm and take off again)")
                    self.setpoint_out.put({"attitude_ref_rad": [0.0, 0.0, yaw], "thrust_n": 0.0}, t_s=t)
                    self.publish_state(t, pos, vel, pos, cov, thrust_scale)
                    return
                self.landed = False
            if self.lost_flying:   # back after a loss in the air: its setpoint reached as a ramp
                self.lost_flying = False
                self.resume = (pos.copy(), t)
                self.count("planner_back")
            self.hold_position = None
        flying = sp is not None and sp["armed"] and sp["mode"] != "idle"
        # near the ground the camera sees too little of the marker map to solve (take-off, landing):
        # its silence there is no loss, and counts only from the last time the vehicle was there
        # (a second take-off must not find the fix of the last landing stale)
        low = pos[2] <= p["home_position_m"][2] + VISION_MIN_HEIGHT_M
        if not flying:
            self.vision_lost = False
        if not flying or (low and not self.vision_lost):
            self.camera_due_t = t
        if self.estimate and flying and self.fused_t is not None:
            lost = (t - max(self.fused_t, self.camera_due_t) > p["vision_timeout_s"]
                    and (self.vision_lost or not low))
            if lost != self.vision_lost:
                self.vision_lost = lost
                self.count("vision_lost" if lost else "vision_back")
                self.io.problem(f"failsafe: no camera fix for {p['vision_timeout_s']} s at t={t:.3f}: the attitude "
                                "level lands" if lost else f"camera fixes again at t={t:.3f}")
            if lost:   # the attitude level's own descent lands; the estimate still goes out
                self.publish_state(t, pos, vel, pos, cov, thrust_scale)
                return
        if stale and sp is not None and sp["armed"] and t - self.hold_since > p["planner_loss_land_after_s"]:
            self.land(t, pos, vel, yaw, m_eff)
            self.publish_state(t, pos, vel, self.hold_position, cov, thrust_scale)
            return
        if sp is not None and not stale and (sp["mode"] == "idle" or not sp["armed"]):
            ref_pos, att_ref, thrust = pos, [0.0, 0.0, yaw], 0.0
            self.integral, self.bias = np.zeros(2), None   # on the ground: nothing learnt stays
            if self.observer is not None:
                self.observer.reset()
        elif sp is not None and not stale and sp["mode"] == "attitude":
            if self.observer is not None:
                self.observer.hold()
            ref_pos, att_ref = np.asarray(sp["position_m"]), list(sp["attitude_rad"])
            thrust = altitude_law(m_eff, g, pos[2], vel[2], ref_pos[2], k[2], alpha[2], roll, pitch)
        else:
            ref_pos = self.hold_position if stale else np.asarray(sp["position_m"])
            if self.resume is not None and not stale:
                ref_pos = self.resumed(ref_pos, t)
            yaw_ref = yaw if stale else sp["attitude_rad"][2]
            if p["max_tilt_deg"] != self.tilt_deg:
                self.tilt_deg = p["max_tilt_deg"]
                self.tilt_rad = vehicle.tilt_limit_rad(self.tilt_deg)
            if p["hold_ki"] > 0.0:   # the integral learns while holding and is kept between holds
                holding = not stale and sp["phase"] in HOLD_PHASES
                error = (pos[:2] - ref_pos[:2]) if holding else np.zeros(2)
                self.integral, self.bias = hold_integral_update(
                    self.integral, error, self.dt, p["hold_ki"], p["hold_integral_limit_m_s2"])
            bias = self.bias
            if self.observer is not None:
                # the thrust the EKF predicted with (estimate), else the last one asked for (truth)
                collective = self.collective_n if self.estimate else self.thrust_n
                # a flip's phases: the attitude level flies it and the EKF coasts (pinned): hold the estimate
                # near the ground (resting on it, no camera fix) and without fresh fixes the
                # velocity does not say what the air does: hold
                if collective is None or (not stale and sp["phase"].startswith("flip")) \
                        or math.cos(roll) * math.cos(pitch) < OBSERVER_MIN_TILT_COS \
                        or pos[2] < p["home_position_m"][2] + VISION_MIN_HEIGHT_M \
                        or (self.estimate and (self.fused_t is None or t - self.fused_t > p["pose_timeout_s"])):
                    self.observer.hold()
                else:
                    self.observer.update(vel[:2], thrust_accel_xy(
                        collective * thrust_scale, vehicle.mass_kg, roll, pitch, yaw), self.dt)
                d0, d1 = self.observer.d
                bias = np.array([-d0, -d1]) if bias is None else bias - (d0, d1)
            if p["wind_estimation"] and self.estimate and self.ekf_disturbance is not None \
                    and (stale or not sp["phase"].startswith("flip")):
                d0, d1 = self.ekf_disturbance
                norm = math.hypot(d0, d1)
                if norm > p["disturbance_limit_m_s2"]:
                    d0, d1 = d0 * p["disturbance_limit_m_s2"] / norm, d1 * p["disturbance_limit_m_s2"] / norm
                bias = np.array([-d0, -d1]) if bias is None else bias - (d0, d1)
            r, pt, thrust = position_law(m_eff, g, pos, vel, ref_pos, k, alpha, yaw_ref,
                                         max_tilt_rad=self.tilt_rad, accel_bias_xy=bias)
            att_ref = [r, pt, yaw_ref]
        thrust = float(min(thrust, 4 * vehicle.max_thrust_n))
        self.thrust_n = thrust
        self.setpoint_out.put({"attitude_ref_rad": att_ref, "thrust_n": thrust}, t_s=t)
        self.publish_state(t, pos, vel, ref_pos, cov, thrust_scale)

    def resumed(self, target, t: float):
        """The planner back after a loss: the reference moves from where the vehicle was towards
        `target` at land_speed_m_s, then is the target (the ramp ends)."""
        start, t0 = self.resume
        step = target - start
        dist = float(np.linalg.norm(step))
        reach = self.p["land_speed_m_s"] * (t - t0)
        if reach >= dist:
            self.resume = None
            return target
        return start + step * (reach / dist)

    def publish_state(self, t, pos, vel, ref_pos, cov, thrust_scale) -> None:
        velocities = self.velocities
        velocities.append((t, vel))  # a fresh array each step
        (t0, v0), (t1, v1) = velocities[0], velocities[-1]
        accel = (v1 - v0) / (t1 - t0) if t1 > t0 else np.zeros(3)
        self.state_out.put({"position_m": pos, "velocity_m_s": vel, "position_ref_m": ref_pos,
                            "position_cov_m2": np.asarray(cov).reshape(-1), "acceleration_m_s2": accel,
                            "thrust_scale": thrust_scale, "state_source": self.p["state_source"]}, t_s=t)

    def land(self, t, pos, vel, yaw, m_eff) -> None:
        """Planner lost for planner_loss_land_after_s: land where we held; idle once down."""
        p, vehicle = self.p, self.vehicle
        home_z = p["home_position_m"][2]
        if not self.landed and pos[2] < home_z + LANDED_HEIGHT_M and abs(vel[2]) < LANDED_SPEED_M_S:
            self.landed_for += self.dt
            if self.landed_for >= LANDED_FOR_S:
                self.landed = True
                self.count("planner_lost_landed")
                self.io.problem(f"failsafe: landed at t={t:.3f} with no planner: idle")
        else:
            self.landed_for = 0.0
        if self.landed:
            self.setpoint_out.put({"attitude_ref_rad": [0.0, 0.0, yaw], "thrust_n": 0.0}, t_s=t)
            return
        sinking = t - self.hold_since - p["planner_loss_land_after_s"]
        held = self.hold_position
        held[2] = max(held[2] - p["land_speed_m_s"] / self.io.rate_hz, home_z - LAND_BELOW_M) if sinking > 0 else held[2]
        r, pt, thrust = position_law(m_eff, vehicle.gravity_m_s2, pos, vel, held, self.k, self.alpha, yaw,
                                     max_tilt_rad=vehicle.tilt_limit_rad(p["max_tilt_deg"]))
        self.setpoint_out.put({"attitude_ref_rad": [r, pt, yaw],
                               "thrust_n": float(min(thrust, 4 * vehicle.max_thrust_n))}, t_s=t)


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS)
    rt.run(PositionLoop(rt).step)


def main(argv=None) -> None:
    args = service_parser(NAME, __doc__.splitlines()[0]).parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
