"""Every message of the zenpilot data flow: the only place fields are written down.

Frames: world ENU (x east, y north, z up), body FLU (x forward, y left,
z up); quaternions [w, x, y, z] rotate body to world; Euler angles are ZYX
(yaw, pitch, roll) and listed as [roll, pitch, yaw]. MAVLink's NED/FRD
appears only at the MAVLink edge.

Key expressions are `zp/<vehicle>/<topic>`; liveliness tokens are
`zp/<vehicle>/alive/<service>`.
"""

from __future__ import annotations

import re

from .core import Field, Message

F = Field

BIG = 1e6  # generous bound for positions etc.: catches garbage, not physics


def _vec(name, doc, unit, n=3, lo=-BIG, hi=BIG):
    return F(name, "float[]", doc, unit, length=n, min=lo, max=hi)


def _camera_lengths(doc: dict) -> str | None:
    if len(doc["corners_px"]) != 8 * len(doc["marker_ids"]):
        return f"corners_px has {len(doc['corners_px'])} values for {len(doc['marker_ids'])} markers (8 each)"
    return None


CLOCK = Message(
    "clock", "@lockstep/clock/{service}", 1,
    "Lockstep only, one per service due at `tick`: the service runs the work due "
    "at that simulated time, then answers on @lockstep/sync/<service>.",
    (
        F("tick", "int", "tick index; t = tick / tick_rate_hz", min=0),
        F("tick_rate_hz", "float", "ticks per simulated second", "Hz", min=1.0, max=100000.0),
        F("published", "str[]", "simulator topics published for this tick, before this message"),
        F("done", "counts", "per service, the last tick it finished before this one (-1: none yet)", min=-1),
    ),
    reliable=True,
)

SYNC_DONE = Message(
    "sync_done", "@lockstep/sync/{service}", 2,
    "Lockstep only: a service finished `tick` (its outputs for it are published) "
    "and says when it next needs to run. header.source names the service.",
    (
        F("tick", "int", "tick handled (-1: ready, nothing handled yet)", min=-1),
        F("next_tick", "int", "next tick this service must run at; -1 when it only "
          "runs on the simulator topics in `triggers`", min=-1),
        F("triggers", "str[]", "simulator topics whose publication makes this service run"),
        F("period_ticks", "int", "ticks between two runs of a rate service (0: it runs on its triggers); "
          "the clock's schedule, fixed before the first tick", min=0),
    ),
    reliable=True,
)

IMU = Message(
    "imu", "sim/imu", 1, "Inertial measurement, body FLU.",
    (
        _vec("gyro_rad_s", "angular rate", "rad/s", lo=-100.0, hi=100.0),
        _vec("accel_m_s2", "specific force (reads +9.81 on z at rest)", "m/s^2", lo=-500.0, hi=500.0),
    ),
)

BARO = Message(
    "baro", "sim/baro", 1,
    "Static pressure; the receiver turns it into altitude with "
    "h = 44330 (1 - (p / 101325)^0.1903).",
    (
        F("pressure_pa", "float", "static pressure", "Pa", min=10000.0, max=120000.0),
        F("temperature_k", "float", "air temperature", "K", min=150.0, max=400.0),
    ),
)

MAG = Message(
    "mag", "sim/mag", 1, "Magnetic field, body FLU.",
    (_vec("field_ut", "magnetic flux density", "uT", lo=-1000.0, hi=1000.0),),
)

CAMERA = Message(
    "camera", "sim/camera", 1,
    "Fiducial markers seen by the downward camera. header.t_s is the exposure "
    "time; the message arrives about camera_latency_s later. Empty lists: no "
    "marker in view.",
    (
        F("marker_ids", "int[]", "id of each marker seen", min=0),
        F("corners_px", "float[]", "pixel corners, 8 per marker: u0,v0,u1,v1,u2,v2,u3,v3 "
          "(corner order of flight.camera.marker_grid)", "px", min=-1e5, max=1e5),
    ),
    check=_camera_lengths,
    max_bytes=1 << 20,   # ~13,000 markers in view
)

def _image_size(doc: dict) -> str | None:
    if len(doc["pixels"]) != doc["width_px"] * doc["height_px"]:
        return (f"pixels has {len(doc['pixels'])} bytes for a {doc['width_px']} x {doc['height_px']} mono8 image "
                f"({doc['width_px'] * doc['height_px']})")
    return None


CAMERA_IMAGE = Message(
    "camera_image", "sim/@image", 1,
    "What the downward camera sees (the simulator's image mode): one mono8 frame, row "
    "major. header.t_s is the middle of the exposure; the message arrives about "
    "camera_latency_s later. The key sits under a verbatim chunk (`@image`) that "
    "`zp/<vehicle>/**` never matches: the recorder and the ground tools are not sent "
    "the ~6 MB/s of pixels, and a secured stack's router does not let them leave the "
    "vehicle (services/security.py).",
    (
        F("width_px", "int", "image width", "px", min=1, max=4096),
        F("height_px", "int", "image height", "px", min=1, max=4096),
        F("encoding", "str", "pixel format: one byte per pixel, 0 black .. 255 white", choices=("mono8",)),
        F("exposure_s", "float", "exposure time (motion blur spans it)", "s", min=0.0, max=1.0),
        F("pixels", "bytes", "width_px x height_px bytes, row by row from the image's top left"),
    ),
    check=_image_size,
    max_bytes=4096 * 4096 + 1024,
    priority="bulk",
)

TRUTH = Message(
    "truth", "sim/truth", 1,
    "Simulator ground truth, for the recorder and metrics only: no flight "
    "service may use it unless its state source is explicitly `truth`.",
    (
        _vec("position_m", "position, world ENU", "m"),
        _vec("velocity_m_s", "velocity, world ENU", "m/s"),
        _vec("quaternion_wxyz", "attitude, body to world", "", 4, -1.0, 1.0),
        _vec("rate_rad_s", "angular rate, body FLU", "rad/s"),
        _vec("acceleration_m_s2", "acceleration, world ENU", "m/s^2"),
        _vec("motor_thrust_n", "thrust of each motor", "N", 4, 0.0, 1000.0),
        _vec("wind_m_s", "wind velocity, world ENU", "m/s"),
        F("landed", "bool", "resting on the ground"),
    ),
)

PLANNER_SETPOINT = Message(
    "planner_setpoint", "planner/setpoint", 1,
    "What the mission asks for now. mode `position`: hold position_m and yaw; "
    "mode `attitude`: hold roll/pitch/yaw with altitude position_m[2]; `idle`: "
    "motors off; `plan`: the motor driver flies planner/plan while it is valid, the "
    "position and attitude levels holding position_m as its fallback.",
    (
        F("mode", "str", "control mode", choices=("idle", "position", "attitude", "plan")),
        F("armed", "bool", "motors may spin"),
        _vec("position_m", "position reference, world ENU", "m", lo=-1e4, hi=1e4),
        _vec("attitude_rad", "[roll, pitch, yaw] reference", "rad", lo=-7.0, hi=7.0),
        F("item", "int", "index of the mission item being flown", min=0),
        F("phase", "str", "name of the mission item's phase"),
        F("measure", "bool", "this is a hold segment counted in position_rms_m"),
        F("mission_state", "str", "mission progress",
          choices=("waiting", "running", "completed", "failed")),
    ),
)

VISION_POSE = Message(
    "vision_pose", "vision/pose", 1,
    "Vehicle pose solved from one camera frame's markers (perspective-n-point). "
    "header.t_s is the frame's exposure time, not the time it was solved.",
    (
        _vec("position_m", "body origin, world ENU", "m"),
        _vec("quaternion_wxyz", "attitude, body to world", "", 4, -1.0, 1.0),
        _vec("position_cov_m2", "position covariance, row-major 3x3", "m^2", 9, -1e6, 1e6),
        _vec("attitude_var_rad2", "variance of the small attitude error about world x, y, z", "rad^2", 3, 0.0, 1e6),
        F("reprojection_rms_px", "float", "RMS reprojection error of the solution", "px", min=0.0),
        F("markers", "int", "markers used", min=1),
    ),
)

POSITION_SETPOINT = Message(
    "position_setpoint", "pos/setpoint", 1,
    "Position level output (laws (9)-(11)): attitude reference and collective thrust.",
    (
        _vec("attitude_ref_rad", "[roll, pitch, yaw] reference", "rad", lo=-7.0, hi=7.0),
        F("thrust_n", "float", "collective thrust u1", "N", min=0.0, max=1000.0),
    ),
)

POSITION_STATE = Message(
    "position_state", "pos/state", 1,
    "The translational state the position level used.",
    (
        _vec("position_m", "position, world ENU", "m"),
        _vec("velocity_m_s", "velocity, world ENU", "m/s"),
        _vec("position_ref_m", "position reference", "m", lo=-1e4, hi=1e4),
        _vec("position_cov_m2", "position covariance, row-major 3x3 (zeros for truth)", "m^2", 9, -1e6, 1e6),
        _vec("acceleration_m_s2", "acceleration, world ENU (slope of the velocity estimate over ~0.1 s)",
             "m/s^2", lo=-1e4, hi=1e4),
        F("thrust_scale", "float", "collective force the vehicle really gets per newton commanded "
          "(the EKF's estimate; 1 for truth); the laws and the motor driver divide by it",
          min=0.1, max=10.0),
        F("state_source", "str", "where the state came from", choices=("truth", "estimate")),
    ),
)

POSITION_EKF_HEALTH = Message(
    "position_ekf_health", "pos/ekf_health", 2,
    "The position EKF's health, at 1 Hz beside the service's: its camera fixes, and the camera's "
    "delay watched two ways (flight/estimation/camera_delay.py): as the stamps show it (arrival "
    "minus exposure stamp) and, for a delay the stamps do not show, as the innovations show it "
    "(the offset of the fixes' real time from their stamps), with the correction the fusion applies.",
    (
        F("camera_delay_s", "float", "running median of a fix's arrival minus its exposure stamp "
          "(-1: no fix yet)", "s", min=-1.0, max=1e3),
        F("camera_delay_spread_s", "float", "max - min of that delay over the median's window", "s",
          min=0.0, max=1e3),
        F("camera_delay_steps", "int", "steps of that median reported since start", min=0),
        F("camera_delay_step_t_s", "float", "when the last was reported (-1: none)", "s", min=-1.0),
        F("camera_offset_s", "float", "offset of the fixes' real time from their stamps, estimated from the "
          "innovations (positive: the fixes are older than stamped)", "s", min=-1e3, max=1e3),
        F("camera_offset_std_s", "float", "its standard error (1: nothing learnt, the vehicle has not moved)",
          "s", min=0.0, max=1.0),
        F("camera_offset_confident", "bool", "the std is below the confidence threshold"),
        F("camera_offset_correction_s", "float", "what the fusion takes off each fix's stamp now", "s",
          min=-1e3, max=1e3),
        F("camera_offset_detections", "int", "offsets detected (confident, outside the deadband) since start",
          min=0),
        F("camera_offset_detected_t_s", "float", "when the last was detected (-1: none)", "s", min=-1.0),
        F("camera_fixes", "counts", "camera fixes since start: accepted, and refused by reason (gate, too_old, "
          "future, invalid)"),
        _vec("disturbance_m_s2", "the EKF's horizontal disturbance acceleration, world x and y: the wind's pull "
             "with position.wind_estimation (0 without)", "m/s^2", n=2, lo=-100.0, hi=100.0),
        F("disturbance_estimated", "bool", "position.wind_estimation is on (else the disturbance is held at 0)"),
    ),
)

ATTITUDE_COMMAND = Message(
    "attitude_command", "att/command", 1,
    "Attitude level output (law (8)): body torques and the collective thrust, "
    "for the motor driver.",
    (
        F("thrust_n", "float", "collective thrust u1", "N", min=0.0, max=1000.0),
        _vec("torque_nm", "body torques [u2, u3, u4]", "N m", lo=-100.0, hi=100.0),
        F("imu_t_s", "float", "sample time of the newest IMU sample used (-1: none)", "s", min=-1.0),
    ),
)

ATTITUDE_STATE = Message(
    "attitude_state", "att/state", 1,
    "The attitude state the attitude level used, and its reference.",
    (
        _vec("quaternion_wxyz", "attitude, body to world", "", 4, -1.0, 1.0),
        _vec("euler_rad", "[roll, pitch, yaw]", "rad", lo=-7.0, hi=7.0),
        _vec("rate_rad_s", "angular rate, body FLU", "rad/s"),
        _vec("euler_ref_rad", "[roll, pitch, yaw] reference", "rad", lo=-7.0, hi=7.0),
        _vec("euler_var_rad2", "variance of the angle estimates (zeros for truth)", "rad^2", 3, 0.0, 1e6),
        _vec("rate_var_rad2_s2", "variance of the rate estimates (zeros for truth)", "rad^2/s^2", 3, 0.0, 1e6),
        F("state_source", "str", "where the state came from", choices=("truth", "estimate")),
    ),
)

MOTOR_PWM = Message(
    "motor_pwm", "motors/pwm", 1,
    "Motor driver output: PWM pulse widths for the ESCs (or the simulator).",
    (
        _vec("pwm_us", "pulse width per motor", "us", 4, 0.0, 3000.0),
        _vec("thrust_n", "thrust the mixer asked of each motor", "N", 4, 0.0, 1000.0),
        F("armed", "bool", "motors enabled"),
        F("saturated", "bool", "the mixer had to give up thrust or torque"),
        F("imu_t_s", "float", "sample time of the IMU sample behind this output (-1: none)", "s", min=-1.0),
    ),
)

HEALTH = Message(
    "health", "{service}/health", 2,
    "Every service, at 1 Hz (in its clock): how it is doing. Lateness is how long after "
    "its absolute deadline the main loop woke (real time, rate loops; 0 otherwise).",
    (
        F("state", "str", "service state", choices=("starting", "running", "degraded", "stopping", "failed")),
        F("rate_hz", "float", "achieved rate of the main task over the last second", "Hz", min=0.0),
        F("target_rate_hz", "float", "configured rate (0: event driven)", "Hz", min=0.0),
        F("overruns", "int", "main-task deadlines skipped since start (a step ran past the next one)", min=0),
        F("jitter_p99_ms", "float", "p99 of |period - nominal| over the last second", "ms", min=0.0),
        F("lateness_p50_ms", "float", "median wake-up lateness over the last second", "ms", min=0.0),
        F("lateness_p99_ms", "float", "p99 wake-up lateness over the last second", "ms", min=0.0),
        F("lateness_max_ms", "float", "largest wake-up lateness over the last second", "ms", min=0.0),
        F("late", "int", "deadlines woken more than 5 ms late, since start", min=0),
        F("cycles", "int", "main-task runs since start", min=0),
        F("step_s", "float", "wall time spent in the main task since start", "s", min=0.0),
        F("wait_s", "float", "lockstep: wall time spent waiting for upstream services since start", "s", min=0.0),
        F("rejected", "counts", "messages dropped since start, by reason"),
        F("dropped", "counts", "messages lost before this service read them, by key (sequence gaps, "
          "queue overflow), since start"),
        F("scheduling", "str", "how the OS schedules the process, e.g. 'fifo 80, cpu 1' or 'normal' "
          "(with the reason when a requested priority or affinity was refused)"),
        F("detail", "str", "last problem, human readable ('' if none)"),
    ),
)

BEAT = Message(
    "beat", "@beat/{service}", 1,
    "Real time only, every 0.1 s from a service's main loop: the loop runs (the supervisor "
    "judges a hang by their absence, deploy/supervisor.py). Under a verbatim chunk: not logged.",
    (
        F("cycles", "int", "main-task runs since start", min=0),
    ),
)

BATTERY = Message(
    "battery", "sim/battery", 1,
    "Flight battery (simulated: open-circuit voltage falling with the charge used, "
    "sagging with the current the motors draw).",
    (
        F("voltage_v", "float", "terminal voltage under load", "V", min=0.0, max=100.0),
        F("current_a", "float", "current drawn", "A", min=0.0, max=1000.0),
        F("consumed_mah", "float", "charge used since start", "mAh", min=0.0, max=1e6),
        F("remaining", "float", "state of charge, 1 full .. 0 empty", "", min=0.0, max=1.0),
        F("cells", "int", "cells in series", min=1, max=14),
    ),
)

PLANNER_COMMAND = Message(
    "planner_command", "planner/command", 1,
    "A command for the planner from outside the mission (the MAVLink bridge): it "
    "replaces whatever the planner is flying. `takeoff` climbs to altitude_m above "
    "the take-off point; `goto` flies to position_m with yaw_rad; `hold` holds where "
    "the vehicle is; `land` descends and disarms.",
    (
        F("command", "str", "what to do",
          choices=("arm", "disarm", "takeoff", "land", "hold", "goto", "flip")),
        F("altitude_m", "float", "takeoff: altitude above the ground", "m", min=0.0, max=1e4),
        _vec("position_m", "goto: target, world ENU", "m", lo=-1e4, hi=1e4),
        F("yaw_rad", "float", "goto: yaw reference (ENU, 0 = east)", "rad", min=-7.0, max=7.0),
        F("origin", "str", "who sent it, for logs (e.g. 'mavlink:255/190')"),
    ),
    reliable=True,
)

FLIP_METHODS = ("ilqr-project", "ilqr-thesis", "baseline")
FLIP_PHASES = ("takeoff", "flip", "recovery", "settle")


MISSION_ITEM_TYPES = ("takeoff", "goto", "hold", "land", "flip")


def _mission_lengths(doc: dict) -> str | None:
    n = len(doc["types"])
    if n == 0:
        return "no items"
    for key, per in (("position_m", 3), ("yaw_rad", 1), ("hold_s", 1), ("acceptance_m", 1)):
        if len(doc[key]) != per * n:
            return f"{key} has {len(doc[key])} values for {n} items ({per} each)"
    return None


PLANNER_MISSION = Message(
    "planner_mission", "planner/mission", 1,
    "A mission for the planner to fly now (the MAVLink bridge's uploaded mission, from the "
    "current item): it replaces whatever the planner is flying, and planner/setpoint's `item` "
    "indexes these items. Per item: `takeoff` climbs to position_m[2]; `goto` flies to "
    "position_m with yaw_rad, done hold_s after coming within acceptance_m; `hold` holds "
    "hold_s (1e9: until the next command); `land` descends and disarms; `flip` flips (the "
    "planner's flip controller).",
    (
        F("types", "str[]", "item types", choices=MISSION_ITEM_TYPES),
        F("position_m", "float[]", "3 per item: target, world ENU", "m", min=-1e4, max=1e4),
        F("yaw_rad", "float[]", "1 per item: yaw reference (ENU, 0 = east)", "rad", min=-7.0, max=7.0),
        F("hold_s", "float[]", "1 per item: hold time", "s", min=0.0, max=1e9),
        F("acceptance_m", "float[]", "1 per item: goto acceptance radius", "m", min=0.01, max=1e3),
        F("origin", "str", "who sent it, for logs (e.g. 'mavlink:255/190')"),
    ),
    check=_mission_lengths,
    max_bytes=4 << 20,   # ~50,000 items
    reliable=True,
)

def _plan_lengths(doc: dict) -> str | None:
    h, n = doc["horizon"], doc["state_dim"]
    for name, expected in (("states", (h + 1) * n), ("controls_rad_s", 4 * h), ("gains", 4 * h * n),
                           ("target_roll_rad", h)):
        if len(doc[name]) != expected:
            return f"{name} has {len(doc[name])} values, expected {expected} (horizon {h}, state_dim {n})"
    return None


PLANNER_PLAN = Message(
    "planner_plan", "planner/plan", 1,
    "A rotor-speed plan for the motor driver (the flip of 001), solved from the state "
    "estimate at t0_s. The driver applies u = u_plan(t) + K(t) (x - x_plan(t)) at its rate "
    "while t0_s <= t < t0_s + horizon dt_s (controls and gains held over each step, states "
    "interpolated); x = [position_m, velocity_m_s (world ENU), quaternion_wxyz (body to "
    "world), rate_rad_s (body FLU)] and, when state_dim is 17, the 4 rotor forces (N). "
    "Sizes are fixed per method. The baseline flip sends its rotor commands as a plan of "
    "horizon 1 with zero gains.",
    (
        F("method", "str", "flip method", choices=FLIP_METHODS),
        F("phase", "str", "phase of the flip's phase machine", choices=FLIP_PHASES),
        F("t0_s", "float", "time of the plan's first state", "s", min=0.0),
        F("dt_s", "float", "plan step", "s", min=1e-4, max=10.0),
        F("horizon", "int", "plan steps H", min=1, max=1000),
        F("state_dim", "int", "state size n: 13, or 17 with the rotor forces", min=13, max=17),
        F("states", "float[]", "planned states, (H+1) x n row-major", "", min=-BIG, max=BIG),
        F("controls_rad_s", "float[]", "planned rotor speeds, H x 4 row-major", "rad/s", min=0.0, max=1e5),
        F("gains", "float[]", "feedback gains K, H x 4 x n row-major", "", min=-BIG, max=BIG),
        F("roll_rad", "float", "accumulated roll of the phase machine at t0_s", "rad", min=-100.0, max=100.0),
        F("target_roll_rad", "float[]", "the phase machine's (adaptive) accumulated roll target at each "
          "of the H plan steps", "rad", min=-100.0, max=100.0),
        F("solve_ms", "float", "compute time of this solve (0 for the baseline)", "ms", min=0.0),
        F("iterations", "int", "solver iterations", min=0),
        F("cost", "float", "plan cost", "", min=0.0),
        F("converged", "bool", "the solver met its tolerance"),
        F("solves", "int", "solves since the flip started", min=0),
        F("failed_solves", "int", "solves not usable (previous plan kept, or the hover laws)", min=0),
        F("overrun_solves", "int", "solves longer than the re-solve period", min=0),
    ),
    check=_plan_lengths,
    max_bytes=2 << 20,   # the largest plan (horizon 1000, state_dim 17) packs to ~0.8 MB
)

PLANNER_FLIP_PREDICTION = Message(
    "planner_flip_prediction", "planner/flip_prediction", 1,
    "A flip's predicted envelope (flight/control/predict.py), sent once on the planner's first "
    "tick for each iLQR flip item of its mission and for the flip a command would fly "
    "(planner/flip_status), where that is another: N closed-loop rollouts of the planner's plans "
    "and gains over drawn mass, inertia, thrust, motor lag, wind, gusts, delay and start error. "
    "Each figure is [p5, p50, p95], or [] where no case defines it (none turned, none "
    "recovered). refused: the planner will not start the item (reason says why).",
    (
        F("method", "str", "flip method", choices=FLIP_METHODS),
        F("altitude_m", "float", "the item's altitude (the hover the flip starts from)", "m", min=0.0, max=1e4),
        F("rollouts", "int", "cases drawn", min=1),
        F("loss_from_turn_m", "float[]", "altitude loss from the turn's start, [p5, p50, p95]", "m",
          min=-1e4, max=1e4),
        F("loss_from_hover_m", "float[]", "altitude loss from the hover height, [p5, p50, p95]", "m",
          min=-1e4, max=1e4),
        F("xy_drift_m", "float[]", "XY drift, [p5, p50, p95]", "m", min=0.0, max=1e4),
        F("overshoot_deg", "float[]", "roll overshoot, [p5, p50, p95]", "deg", min=0.0, max=1e5),
        F("recovery_s", "float[]", "recovery time, [p5, p50, p95]", "s", min=0.0, max=1e4),
        F("p_crash", "float", "fraction of cases that crash", "", min=0.0, max=1.0),
        F("p_ground", "float", "fraction of cases that touch the ground", "", min=0.0, max=1.0),
        F("refused", "bool", "the item will not be started"),
        F("reason", "str", "why it is refused ('' when it is not)"),
    ),
    check=lambda doc: next((f"{k} has {len(doc[k])} values, expected 3 (p5, p50, p95) or none"
                            for k in ("loss_from_turn_m", "loss_from_hover_m", "xy_drift_m", "overshoot_deg",
                                      "recovery_s") if len(doc[k]) not in (0, 3)), None),
    reliable=True,
)

PLANNER_FLIP_STATUS = Message(
    "planner_flip_status", "planner/flip_status", 1,
    "The flip a command (planner/command `flip`) or an uploaded item (planner/mission `flip`) "
    "would fly, once a second on the planner's clock, only while the planner has a flip "
    "controller (built at start-up: its mission's flip items and its `flip_methods` parameter): "
    "no message, no flip. Such a flip starts from a hover at altitude_m (where the flip "
    "climbs or descends first); refused: its prediction (planner/flip_prediction) says it "
    "should not be flown, and the planner will not start it. The MAVLink bridge accepts a "
    "flip only while this is fresh and not refused.",
    (
        F("methods", "str[]", "the flip methods built", choices=FLIP_METHODS),
        F("method", "str", "the method a commanded or uploaded flip flies", choices=FLIP_METHODS),
        F("altitude_m", "float", "the altitude it flies from", "m", min=0.0, max=1e4),
        F("refused", "bool", "its prediction refuses it: a flip would not be started"),
        F("reason", "str", "why it is refused ('' when it is not)"),
    ),
)

PARAM_SET = Message(
    "param_set", "param/set", 1,
    "Set a running service's parameter (the MAVLink parameter protocol): the "
    "service named applies it if the value passes the check of its declaration that "
    "start-up makes (a numeric parameter, this length, within its bounds); otherwise it "
    "counts the message as rejected (param_rejected) and keeps the old value.",
    (
        F("service", "str", "service the parameter belongs to"),
        F("key", "str", "parameter key in the stack file"),
        F("value", "float[]", "new value: one number for a scalar, all elements for an array",
          min=-1e9, max=1e9),
    ),
    reliable=True,
)

ALL = (
    CLOCK, SYNC_DONE, IMU, BARO, MAG, CAMERA, CAMERA_IMAGE, TRUTH, VISION_POSE, PLANNER_SETPOINT,
    POSITION_SETPOINT, POSITION_STATE, POSITION_EKF_HEALTH, ATTITUDE_COMMAND, ATTITUDE_STATE, MOTOR_PWM, HEALTH, BEAT,
    BATTERY, PLANNER_COMMAND, PARAM_SET, PLANNER_PLAN, PLANNER_MISSION, PLANNER_FLIP_PREDICTION,
    PLANNER_FLIP_STATUS,
)

BY_NAME = {m.name: m for m in ALL}

# Simulator topics as named in CLOCK.published and SYNC_DONE.triggers.
SIM_TOPICS = {"imu": IMU, "baro": BARO, "mag": MAG, "camera": CAMERA, "camera_image": CAMERA_IMAGE, "truth": TRUTH,
              "battery": BATTERY}

# Lockstep: the message a service publishes last in a run, stamped with the run's time. When a
# run ends with it, it stands for the run's SYNC_DONE (no sync is sent: one message less to every
# follower, each tick); a run that ends otherwise sends the sync. Every follower of the service
# receives it (as an input, or on a subscription of its own).
RUN_DONE = {"motors": MOTOR_PWM, "attitude": ATTITUDE_STATE, "position": POSITION_STATE,
            "planner": PLANNER_SETPOINT}


def _pattern(topic: str) -> re.Pattern:
    return re.compile("^" + re.escape(topic).replace(re.escape("{service}"), "[^/]+") + "$")


_PATTERNS = [(_pattern(m.topic), m) for m in ALL]


def message_for_key(key: str) -> Message | None:
    """The definition behind a concrete key expression (for tools and the recorder)."""
    parts = key.split("/", 2)
    if len(parts) < 3 or parts[0] != "zp":
        return None
    for pattern, m in _PATTERNS:
        if pattern.match(parts[2]):
            return m
    return None
