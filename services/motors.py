"""zenpilot-motors: the motor driver (400 Hz).

Turns the attitude level's thrust and torques into rotor forces with the
mixer F = M^-1 u (saturation keeps attitude authority before collective
thrust), then into PWM through the motor map of 000. Disarmed (or with no
command yet) it holds every motor at the minimum pulse.
"""

from __future__ import annotations

import numpy as np

import schemas
from flight.mixer import mix, thrust_to_pwm
from flight.vehicle import load_vehicle
from services.runtime import Runtime, main_guard, service_parser

NAME = "motors"
PARAMS = {
    "command_timeout_s": 0.1,  # no fresh attitude command for this long -> motors to minimum
}


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS)
    vehicle = load_vehicle(rt.vehicle_name)
    command = rt.inbox(schemas.ATTITUDE_COMMAND, "attitude")
    setpoint = rt.inbox(schemas.PLANNER_SETPOINT, "planner")
    out = rt.publisher(schemas.MOTOR_PWM)
    idle = {"pwm_us": [vehicle.pwm_min_us] * 4, "thrust_n": [0.0] * 4, "armed": False,
            "saturated": False, "imu_t_s": -1.0}

    def step(t: float) -> None:
        cmd, sp = command.latest(), setpoint.latest()
        armed = sp is not None and sp["armed"]
        if not armed or cmd is None or t - cmd["header"]["t_s"] > rt.params["command_timeout_s"]:
            out.put({**idle, "armed": bool(armed)}, t_s=t)
            return
        forces, saturated = mix(vehicle, cmd["thrust_n"], cmd["torque_nm"])
        out.put({"pwm_us": thrust_to_pwm(vehicle, forces), "thrust_n": np.asarray(forces),
                 "armed": True, "saturated": bool(saturated), "imu_t_s": cmd["imu_t_s"]}, t_s=t)

    rt.run(step)


def main(argv=None) -> None:
    args = service_parser(NAME, __doc__.splitlines()[0]).parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
