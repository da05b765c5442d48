"""zenpilot-motors: the motor driver (400 Hz).

Turns the attitude level's thrust and torques into rotor forces with the
mixer F = M^-1 u (saturation keeps attitude authority before collective
thrust), then into PWM through the motor map of 000. Disarmed (or with no
command yet) it holds every motor at the minimum pulse.

Plans (the flip of 001): while the planner's setpoint is in mode `plan` and a
plan (planner/plan) is valid at t (t0_s <= t < t0_s + horizon dt_s), the driver
applies u = u_plan(t) + K(t) (x - x_plan(t)) (flight/control/plan.py) on the latest
estimate x (pos/state position/velocity and att/state quaternion/rates, each
carried forward over its age; with a 17-state plan, the rotor forces its own
commands imply through the motor lag), clipped to the rotor limits, as thrust
kf u^2 through the motor map, the collective divided by the position EKF's
thrust scale (pos/state; flight/control/plan.scale_collective). The newest plan that has
started is used (a planner across a link sends its plans ahead, planner.plan_lead_s: each
waits for its start); when the newest has ended, an older one while it lasts
("plan_fallback_previous"), then the attitude level's command ("plan_fallback_hover"):
both counted per output in health.

Stale commands and the failsafe: an attitude command is judged by its sample times against
the driver's clock (its header's, and the IMU sample behind it: a controller resumed after a
freeze publishes "now" from old samples); one older than `command_timeout_s` (50 ms) is never
mixed (counted per message: "stale_att_command"). Armed and flying with no fresh command, the
driver flies on its own (flight/control/failsafe.py, counted "failsafe_engaged"): it subscribes to the
IMU then (nothing of it costs the 400 Hz path before), keeps the vehicle level with law (8) on a
complementary estimate started from the last att/state, descends on a thrust ramp to a slow
sink from the last thrust, and disarms past the estimated ground (latched until the planner
disarms). A fresh command before that gives control back ("failsafe_recovered"). Restarted
mid-flight by the supervisor (`--restarted`), the driver sends nothing until it has heard the
planner and, armed, a fresh command: its idle output would cut the motors of a vehicle in the air.

Hot standby (`[services.motors] standby = true`, real time; services/standby.py): a second driver
process (`--instance motors.b`) runs this same loop on the same inputs, its state warm, and sends
nothing while the active driver's output arrives; it takes over when that output has been missing
for `standby_takeover_s`, and an active driver whose own last output is that old steps back before
it sends again. Each hears only the other's motors/pwm (counted "standby_took_over",
"standby_stepped_back"); the active one holds the liveliness token zp/<v>/motors/active/<instance>.

Output `sim` (default): motors/pwm for the simulator (or ESCs). Output
`mavlink`: the same, and at the motor rate the mixer's result goes to an
external autopilot as SET_ACTUATOR_CONTROL_TARGET group 0 (normalised FRD
torques and thrust, flight/mavframes.actuator_controls) on `mavlink_endpoint`.
"""

from __future__ import annotations

import numpy as np

import schemas
from flight.control.laws import STOPPING_ACCEL_FRACTION, attitude_law, stopping_accel
from flight.control.failsafe import Descent, DescentParams, LevelEstimate
from flight.control.mixer import mix, mix_floats
from flight.control.plan import RotorPlan, body_state, scale_collective_floats
from flight.motor_model import decay, pwm_to_thrust, thrust_step, thrust_step_floats, thrust_to_pwm, thrust_to_pwm_floats
from flight.vehicle import load_vehicle
from services.params.motors import PARAMS  # every parameter: default, unit, bounds, doc
from services.runtime import Runtime, main_guard, service_parser
from services.standby import INSTANCES, Standby

NAME = "motors"
HELD_PLANS = 16   # the plans received last: a planner's lead of ~0.1 s of them, and older ones to fall back on


class MotorDriver:
    """The motor driver's logic: mix the attitude command (or fly the planner's rotor plan), the
    PWM map, and its own failsafe when the attitude level is gone. `io` is the service's Runtime
    in flight, a fake in the unit tests; no Zenoh here."""

    def __init__(self, io, on_role=None):
        """on_role(active): told when this driver's hot-standby role changes (and at start, active)."""
        self.io = io
        self.on_role = on_role
        vehicle = self.vehicle = load_vehicle(io.vehicle_name)
        self.link = actuator_link(io, vehicle) if io.params["output"] == "mavlink" else None
        self.command = io.inbox(schemas.ATTITUDE_COMMAND, "attitude")
        self.setpoint = io.inbox(schemas.PLANNER_SETPOINT, "planner")
        self.plans = io.inbox(schemas.PLANNER_PLAN, "planner", keep=4)
        self.att_state = io.inbox(schemas.ATTITUDE_STATE, "attitude")
        self.pos_state = io.inbox(schemas.POSITION_STATE, "position")
        self.out = io.publisher(schemas.MOTOR_PWM)
        self.kf = vehicle.thrust_coefficient_kf
        self.u_max = vehicle.max_rotor_speed_rad_s
        self.dt_tick = 1.0 / io.rate_hz if io.rate_hz > 0 else 1.0 / io.tick_rate
        self.decay = decay(self.dt_tick, vehicle.motor_time_constant_s)   # thrust_step's, per tick
        self.held_plans: list = []        # the last HELD_PLANS plans received, oldest first
        self.forces = np.zeros(4)         # the rotors' forces as the plan's model sees them
        self.cmd = None                   # the attitude command being flown
        self.max_age = io.params["command_timeout_s"]
        self.failsafe = MotorFailsafe(io, vehicle)
        self.waiting = io.restarted   # restarted mid-flight: silent until the planner and the level are heard
        self.idle = {"pwm_us": [vehicle.pwm_min_us] * 4, "thrust_n": [0.0] * 4, "armed": False,
                     "saturated": False, "imu_t_s": -1.0}
        # the hot standby (services/standby.py): two drivers, one publishing; None: a lone driver
        self.standby = self.peers = None
        spec = getattr(io, "spec", None)
        if spec is not None and spec.standby and not io.lockstep:
            me = getattr(io, "instance", io.name)
            self.standby = Standby(me, active=(me == INSTANCES[0] and not io.restarted), now=io.now(),
                                   takeover_s=io.params["standby_takeover_s"])
            self.peers = io.inbox(schemas.MOTOR_PWM, "motors", keep=16, others_only=True)
            io.on_param("standby_takeover_s", lambda v: setattr(self.standby, "takeover_s", float(v)))   # both drivers
            io.problem(f"hot standby: {me} starts {self.standby.role}")
            if self.standby.active and on_role is not None:
                on_role(True)

    def count(self, reason: str) -> None:
        rejected = self.io.rejected
        rejected[reason] = rejected.get(reason, 0) + 1

    def fresh_command(self, t: float):
        """The newest attitude command young enough to act on, or None; every one too old
        (by its header or by the IMU sample behind it) is counted and never used."""
        max_age = self.max_age
        for c in self.command.take():
            if t - c["header"]["t_s"] > max_age or (c["imu_t_s"] >= 0.0 and t - c["imu_t_s"] > max_age):
                self.count("stale_att_command")
            else:
                self.cmd = c
        c = self.cmd
        if c is not None and (t - c["header"]["t_s"] > max_age
                              or (c["imu_t_s"] >= 0.0 and t - c["imu_t_s"] > max_age)):
            self.cmd = c = None   # aged while held: the failsafe's from here
        return c

    def plan_forces(self, t: float, sp: dict):
        """Rotor forces from a valid plan (in the plan's model, the airframe file's),
        with the thrust scale of the latest pos/state; or None (fall back to the
        attitude command)."""
        held = self.held_plans
        for m in self.plans.take():   # each plan once
            held.append(RotorPlan.from_message(m))
        if sp is None or sp["mode"] != "plan":
            held.clear()
            return None
        del held[:-HELD_PLANS]
        att, pos = self.att_state.latest(), self.pos_state.latest()
        # the newest started; those after it start later (a planner's lead, plan_lead_s)
        plan = next((p for p in reversed(held) if p.valid_at(t)), None)
        if plan is None or att is None or pos is None or self.kf is None:
            self.count("plan_fallback_hover")
            return None
        if held[-1].t0_s <= t and plan is not held[-1]:
            self.count("plan_fallback_previous")   # the newest has started and ended: an older one flies
        x = body_state(t, att, pos, self.vehicle, self.forces)
        if plan.state_dim == 17:
            x = np.concatenate([x, self.forces])
        u = plan.control(t, x, self.u_max)
        return self.kf * u * u

    def speaks(self, t: float) -> bool:
        """Whether this driver sends its output of tick t: always alone; with a hot standby, only
        while active (services/standby.py). The standby has computed the tick all the same."""
        sb = self.standby
        if sb is None:
            return True
        was = sb.active
        for m in self.peers.take():
            h = m["header"]
            sb.heard(h["source"], h["t_s"], t)
        speak = sb.may_publish(t)
        if sb.active != was:
            self.count("standby_took_over" if sb.active else "standby_stepped_back")
            self.io.problem(f"hot standby: {sb.changed} at t={t:.3f}")
            if self.on_role is not None:
                self.on_role(sb.active)
        return speak

    def step(self, t: float) -> None:
        """One run at time t: the PWM for the motors."""
        vehicle, failsafe, link, out = self.vehicle, self.failsafe, self.link, self.out
        tau = vehicle.motor_time_constant_s
        cmd, sp = self.fresh_command(t), self.setpoint.latest()
        armed = sp is not None and sp["armed"]
        if self.waiting:   # idle output would cut the motors of a vehicle in the air: say nothing
            if sp is None or (armed and cmd is None):   # (the motors hold the last output sent) until
                return                                  # told it is disarmed, or commanded
            self.waiting = False
        if not armed:
            failsafe.disarmed()
        forces = None
        if armed and not failsafe.latched:
            if cmd is not None:
                failsafe.resume(t)
                failsafe.flying = cmd["thrust_n"]   # 0: idle on the ground, nothing to land
            elif failsafe.flying:   # in the air and the attitude level gone: fly on our own
                forces = failsafe.forces(t, self.att_state, self.pos_state)
        if forces is not None:
            pwm = thrust_to_pwm(vehicle, forces)
            self.forces = thrust_step(self.forces, forces, self.dt_tick, tau)
            if not self.speaks(t):
                return
            if link:
                link(t, forces)
            out.put({"pwm_us": pwm, "thrust_n": forces, "armed": True, "saturated": False,
                     "imu_t_s": failsafe.sample_t}, t_s=t)
            return
        if not armed or failsafe.latched or cmd is None:
            self.forces = thrust_step(self.forces, np.zeros(4), self.dt_tick, tau)
            if not self.speaks(t):
                return
            out.put({**self.idle, "armed": bool(armed and not failsafe.latched)}, t_s=t)
            if link:
                link(t, self.idle["thrust_n"])
            return
        pos = self.pos_state.latest()
        thrust_scale = pos["thrust_scale"] if pos is not None else 1.0
        forces = self.plan_forces(t, sp)
        if forces is not None:
            if thrust_scale != 1.0:  # the collective the plan needs from the real vehicle
                wrench = vehicle.allocation @ forces
                forces, _ = mix(vehicle, wrench[0] / thrust_scale, wrench[1:])
            pwm = thrust_to_pwm(vehicle, forces)
            forces = pwm_to_thrust(vehicle, pwm)  # what the motors will really be asked for
            saturated = bool(np.any(pwm <= vehicle.pwm_min_us) or np.any(pwm >= vehicle.pwm_max_us))
            forces, pwm = forces.tolist(), pwm.tolist()
        else:   # the 400 Hz path in Python floats (the same numbers as the arrays' functions)
            forces, saturated = mix_floats(vehicle, cmd["thrust_n"], cmd["torque_nm"])
            pwm = thrust_to_pwm_floats(vehicle, forces)
        # the plan's motor states: what was sent, as the plan's model (the airframe file's) sees it
        as_planned = scale_collective_floats(vehicle.allocation, forces, thrust_scale)
        self.forces = np.array(thrust_step_floats(self.forces.tolist(), as_planned, self.decay))
        if not self.speaks(t):
            return
        if link:
            link(t, np.array(forces))
        out.put({"pwm_us": pwm, "thrust_n": forces,
                 "armed": True, "saturated": bool(saturated), "imu_t_s": cmd["imu_t_s"]}, t_s=t)


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS)
    if rt.instance != NAME and not (rt.spec is not None and rt.spec.standby):
        raise ValueError(f"--instance {rt.instance}: {rt.stack.path} [services.motors] has no standby = true")
    if rt.lockstep and rt.spec is not None and rt.spec.standby:
        if rt.instance != NAME:
            raise ValueError(f"--instance {rt.instance}: the hot standby runs in real time only (lockstep "
                             f"is one driver, deterministic)")
        # said, not kept as the health's detail: the lockstep log stays the one a stack without it writes
        print(f"zenpilot-{NAME}: hot standby: real time only; this lockstep run flies one driver", flush=True)
    driver = MotorDriver(rt, on_role=active_token(rt))
    # a new attitude command is mixed and sent at once; between commands the 400 Hz timer runs
    rt.run(driver.step, wake_on=driver.command, min_gap=0.0)


class MotorFailsafe:
    """The driver's own flight when the attitude level is gone (module docstring)."""

    def __init__(self, rt: Runtime, vehicle):
        self.rt, self.vehicle = rt, vehicle
        self.descent_params = rt.table("failsafe_descent", DescentParams.from_dict)
        self.k, self.alpha = rt.live_array("failsafe_k"), rt.live_array("failsafe_alpha")
        self.max_accel = stopping_accel(vehicle.max_angular_accel_rad_s2, STOPPING_ACCEL_FRACTION)
        self.imu = None          # subscribed when first needed: no cost to the normal path
        self.flying = 0.0        # the last fresh command's thrust (0: on the ground or never flown)
        self.active = False
        self.latched = False     # landed and disarmed by the failsafe: until the planner disarms
        self.level = None
        self.descent = None
        self.yaw = 0.0
        self.sample_t = -1.0

    def _count(self, reason: str) -> None:
        self.rt.rejected[reason] = self.rt.rejected.get(reason, 0) + 1

    def disarmed(self) -> None:
        self.flying, self.latched, self.active = 0.0, False, False

    def resume(self, t: float) -> None:
        if self.active:
            self.active = False
            self._count("failsafe_recovered")
            self.rt.problem(f"failsafe: fresh attitude commands again at t={t:.3f}: control handed back")
            self.imu.idle()

    def _engage(self, t: float, att_state, pos_state) -> None:
        self.active = True
        self._count("failsafe_engaged")
        self.rt.problem(f"failsafe: no fresh attitude command at t={t:.3f}: level, descend, disarm on the ground")
        if self.imu is None:
            self.imu = self.rt.inbox(schemas.IMU, "sim", keep=64)
        self.imu.idle()   # what queued since the last use is not ours to integrate (let go undecoded)
        att, pos = att_state.latest(), pos_state.latest()
        self.level = None
        self.yaw = 0.0
        if att is not None:   # the attitude level's last word: level from it, no settling needed
            self.level = LevelEstimate(att["quaternion_wxyz"], att["header"]["t_s"])
            self.yaw = float(att["euler_rad"][2])
        self.scale = pos["thrust_scale"] if pos is not None else 1.0
        height = float(pos["position_m"][2]) if pos is not None else None
        vz = float(pos["velocity_m_s"][2]) if pos is not None else 0.0
        v = self.vehicle
        self.descent = Descent(self.descent_params, v.mass_kg, v.gravity_m_s2, 4 * v.max_thrust_n)
        self.descent.start(t, height, vz, self.flying)

    def forces(self, t: float, att_state, pos_state):
        """Rotor forces for tick t; None once landed (the driver then disarms, latched)."""
        if not self.active:
            self._engage(t, att_state, pos_state)
        thrust = None
        for m in self.imu.take():
            ts, gyro, accel = m["header"]["t_s"], m["gyro_rad_s"], m["accel_m_s2"]
            if self.level is None:
                self.level = LevelEstimate.from_accel(ts, accel, self.yaw)
            self.level.update(ts, gyro, accel)
            thrust = self.descent.update(ts, self.level.q, accel, self.scale)
            self.sample_t = ts
        if thrust is None:   # no new sample this tick: the ramp goes on, nothing to integrate
            thrust = self.descent.update(t, self.level.q if self.level else (1.0, 0.0, 0.0, 0.0), None, self.scale)
        if self.descent.landed:
            self.latched, self.active, self.flying = True, False, 0.0
            self._count("failsafe_landed")
            self.rt.problem(f"failsafe: descended past the ground at t={t:.3f}: disarmed")
            self.imu.idle()
            return None
        v = self.vehicle
        if self.level is None:
            torque = np.zeros(3)
        else:
            roll, pitch, yaw = self.level.euler
            torque = attitude_law(v.inertia_kg_m2, (roll, pitch, yaw), self.level.rate, (0.0, 0.0, self.yaw),
                                  self.k, self.alpha, self.max_accel)
        forces, _ = mix(v, thrust, torque)   # thrust as commanded: the descent divided by the scale
        return np.asarray(forces)


def actuator_link(rt: Runtime, vehicle):
    """A sender of the mixer's result to an external autopilot: link(t_s, forces_n)."""
    from flight.mavframes import actuator_controls
    from services.mavlink_logic import mavutil_v2
    mavutil = mavutil_v2()
    try:
        conn = mavutil.mavlink_connection(rt.params["mavlink_endpoint"], source_system=rt.params["mavlink_target_system"],
                                          source_component=mavutil.mavlink.MAV_COMP_ID_ONBOARD_COMPUTER)
    except Exception as exc:
        raise ValueError(f"{rt.where()} mavlink_endpoint: cannot open {rt.params['mavlink_endpoint']!r}: "
                         f"{exc}") from None
    target = rt.params["mavlink_target_system"]
    t0 = rt.now()

    def send(t_s: float, forces_n) -> None:
        controls = actuator_controls(vehicle.allocation, vehicle.max_thrust_n, forces_n)
        conn.mav.set_actuator_control_target_send(int(max(0.0, t_s - t0) * 1e6), 0, target, 1, controls)
    return send


def active_token(rt: Runtime):
    """role_changed(active): the active driver holds a liveliness token zp/<v>/motors/active/<instance>
    (`zenpilot status` shows it; gone with the process, as the service's own token)."""
    held = []
    key = rt.key(f"motors/active/{rt.instance}")

    def role_changed(active: bool) -> None:
        if active and not held:
            held.append(rt.session.liveliness().declare_token(key))
        elif not active and held:
            held.pop().undeclare()
    return role_changed


def main(argv=None) -> None:
    parser = service_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--instance", choices=INSTANCES, default=NAME,
                        help="which of the two drivers of a hot standby ([services.motors] standby = true): "
                             f"{INSTANCES[1]} starts as the standby")
    args = parser.parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
