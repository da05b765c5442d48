"""zenpilot-motors: the motor driver (400 Hz).

Turns the attitude level's thrust and torques into rotor forces with the
mixer F = M^-1 u (saturation keeps attitude authority before collective
thrust), then into PWM through the motor map of 000. Disarmed (or with no
command yet) it holds every motor at the minimum pulse.

Plans (the flip of 001): while the planner's setpoint is in mode `plan` and a
plan (planner/plan) is valid at t (t0_s <= t < t0_s + horizon dt_s), the driver
applies u = u_plan(t) + K(t) (x - x_plan(t)) (flight/plan.py) on the latest
estimate x (pos/state position/velocity and att/state quaternion/rates, each
carried forward over its age; with a 17-state plan, the rotor forces its own
commands imply through the motor lag), clipped to the rotor limits, as thrust
kf u^2 through the motor map, the collective divided by the position EKF's
thrust scale (pos/state; flight/plan.scale_collective). The newest plan is used; when it has expired the
previous one while it lasts ("plan_fallback_previous"), then the attitude
level's command ("plan_fallback_hover"): both counted per output in health.

Output `sim` (default): motors/pwm for the simulator (or ESCs). Output
`mavlink`: the same, and at the motor rate the mixer's result goes to an
external autopilot as SET_ACTUATOR_CONTROL_TARGET group 0 (normalised FRD
torques and thrust, flight/mavframes.actuator_controls) on `mavlink_endpoint`.
"""

from __future__ import annotations

import numpy as np

import schemas
from flight.mixer import mix, pwm_to_thrust, thrust_to_pwm
from flight.plan import RotorPlan, body_state, motor_forces_update, scale_collective
from flight.vehicle import load_vehicle
from services.runtime import Runtime, main_guard, service_parser

NAME = "motors"
PARAMS = {
    # no fresh attitude command for this long -> motors to minimum (counted: "command_timeout").
    # Until then the last command holds: a controller that misses a few cycles on a busy computer
    # must not drop the vehicle, one that has died must not fly it for long.
    "command_timeout_s": 0.25,
    "output": "sim",            # "sim" | "mavlink"
    "mavlink_endpoint": "udpout:127.0.0.1:14560",  # pymavlink connection string (output = "mavlink")
    "mavlink_target_system": 1,
}
OUTPUTS = ("sim", "mavlink")


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS)
    vehicle = load_vehicle(rt.vehicle_name)
    link = actuator_link(rt, vehicle) if rt.choice("output", OUTPUTS) == "mavlink" else None
    command = rt.inbox(schemas.ATTITUDE_COMMAND, "attitude")
    setpoint = rt.inbox(schemas.PLANNER_SETPOINT, "planner")
    plans = rt.inbox(schemas.PLANNER_PLAN, "planner", keep=4)
    att_state = rt.inbox(schemas.ATTITUDE_STATE, "attitude")
    pos_state = rt.inbox(schemas.POSITION_STATE, "position")
    out = rt.publisher(schemas.MOTOR_PWM)
    kf = vehicle.thrust_coefficient_kf
    u_max = vehicle.max_rotor_speed_rad_s
    dt_tick = 1.0 / rt.rate_hz if rt.rate_hz > 0 else 1.0 / rt.tick_rate
    held = {"plans": [], "forces": np.zeros(4), "mode": "", "stale": False}

    def count(reason: str) -> None:
        rt.rejected[reason] = rt.rejected.get(reason, 0) + 1

    def plan_forces(t: float, sp: dict):
        """Rotor forces from a valid plan (in the plan's model, the airframe file's),
        with the thrust scale of the latest pos/state; or None (fall back to the
        attitude command)."""
        for m in plans.take():   # each plan once
            held["plans"] = (held["plans"] + [RotorPlan.from_message(m)])[-2:]  # newest two
        if sp is None or sp["mode"] != "plan":
            held["plans"] = []
            return None
        att, pos = att_state.latest(), pos_state.latest()
        valid = [p for p in held["plans"] if p.valid_at(t)]
        if not valid or att is None or pos is None or kf is None:
            count("plan_fallback_hover")
            return None
        plan = valid[-1]
        if plan is not held["plans"][-1]:
            count("plan_fallback_previous")
        x = body_state(t, att, pos, vehicle, held["forces"])
        if plan.state_dim == 17:
            x = np.concatenate([x, held["forces"]])
        u = plan.control(t, x, u_max)
        return kf * u * u
    idle = {"pwm_us": [vehicle.pwm_min_us] * 4, "thrust_n": [0.0] * 4, "armed": False,
            "saturated": False, "imu_t_s": -1.0}

    def step(t: float) -> None:
        cmd, sp = command.latest(), setpoint.latest()
        armed = sp is not None and sp["armed"]
        stale = cmd is not None and t - cmd["header"]["t_s"] > rt.params["command_timeout_s"]
        if armed and stale and not held["stale"]:
            count("command_timeout")
            rt.problem(f"no attitude command for {t - cmd['header']['t_s']:.3f} s: motors to minimum")
        held["stale"] = stale
        if not armed or cmd is None or stale:
            held["forces"] = motor_forces_update(held["forces"], np.zeros(4), dt_tick, vehicle.motor_time_constant_s)
            out.put({**idle, "armed": bool(armed)}, t_s=t)
            if link:
                link(t, idle["thrust_n"])
            return
        pos = pos_state.latest()
        thrust_scale = pos["thrust_scale"] if pos is not None else 1.0
        forces = plan_forces(t, sp)
        if forces is not None:
            if thrust_scale != 1.0:  # the collective the plan needs from the real vehicle
                wrench = vehicle.allocation @ forces
                forces, _ = mix(vehicle, wrench[0] / thrust_scale, wrench[1:])
            pwm = thrust_to_pwm(vehicle, forces)
            forces = pwm_to_thrust(vehicle, pwm)  # what the motors will really be asked for
            saturated = bool(np.any(pwm <= vehicle.pwm_min_us) or np.any(pwm >= vehicle.pwm_max_us))
        else:
            forces, saturated = mix(vehicle, cmd["thrust_n"], cmd["torque_nm"])
            pwm = thrust_to_pwm(vehicle, forces)
        # the plan's motor states: what was sent, as the plan's model (the airframe file's) sees it
        as_planned = scale_collective(vehicle.allocation, forces, thrust_scale)
        held["forces"] = motor_forces_update(held["forces"], as_planned, dt_tick, vehicle.motor_time_constant_s)
        if link:
            link(t, forces)
        out.put({"pwm_us": pwm, "thrust_n": np.asarray(forces),
                 "armed": True, "saturated": bool(saturated), "imu_t_s": cmd["imu_t_s"]}, t_s=t)

    # a new attitude command is mixed and sent at once; between commands the 400 Hz timer runs
    rt.run(step, wake_on=command, min_gap=0.0)


def actuator_link(rt: Runtime, vehicle):
    """A sender of the mixer's result to an external autopilot: link(t_s, forces_n)."""
    import os
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    from flight.mavframes import actuator_controls
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


def main(argv=None) -> None:
    args = service_parser(NAME, __doc__.splitlines()[0]).parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
