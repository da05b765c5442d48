"""zenpilot-attitude: the attitude level (200 Hz), law (8) of 000.

Tracks the position level's attitude reference with body torques
u = I [-(alpha+k) w - alpha k (angle - ref)] and passes the collective thrust
on to the motor driver. State source: `truth` (the simulator's ground truth,
an explicit ablation setting) until the attitude filter exists.
"""

from __future__ import annotations

import numpy as np

import schemas
from flight.control import attitude_law
from flight.quat import quat_to_euler
from flight.vehicle import load_vehicle
from services.runtime import Runtime, main_guard, service_parser

NAME = "attitude"
PARAMS = {
    "state_source": "truth",
    "k": [16.0, 16.0, 16.0],      # law (8) gains per axis (roll, pitch, yaw), 1/s
    "alpha": [16.0, 16.0, 16.0],
    "setpoint_timeout_s": 0.1,    # stale position setpoint -> level, zero thrust
}
STATE_SOURCES = ("truth",)


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS)
    p = rt.params
    if p["state_source"] not in STATE_SOURCES:
        raise ValueError(f"{rt.stack.path}: [services.attitude.params] state_source: "
                         f"{p['state_source']!r} not one of {STATE_SOURCES}")
    vehicle = load_vehicle(rt.vehicle_name)
    truth = rt.inbox(schemas.TRUTH, "sim")
    setpoint = rt.inbox(schemas.POSITION_SETPOINT, "position")
    command = rt.publisher(schemas.ATTITUDE_COMMAND)
    state_out = rt.publisher(schemas.ATTITUDE_STATE)
    k, alpha = np.asarray(p["k"]), np.asarray(p["alpha"])

    def step(t: float) -> None:
        state, sp = truth.latest(), setpoint.latest()
        if state is None:
            return
        q = state["quaternion_wxyz"]
        euler = np.array(quat_to_euler(q))
        rates = np.asarray(state["rate_rad_s"])
        if sp is None or t - sp["header"]["t_s"] > p["setpoint_timeout_s"]:
            ref, thrust = np.array([0.0, 0.0, euler[2]]), 0.0
        else:
            ref, thrust = np.asarray(sp["attitude_ref_rad"]), sp["thrust_n"]
        torque = attitude_law(vehicle.inertia_kg_m2, euler, rates, ref, k, alpha)
        command.put({"thrust_n": float(thrust), "torque_nm": torque,
                     "imu_t_s": state["header"]["t_s"]}, t_s=t)  # truth stands in for the IMU sample
        state_out.put({"quaternion_wxyz": q, "euler_rad": euler, "rate_rad_s": rates,
                       "euler_ref_rad": ref, "state_source": p["state_source"]}, t_s=t)

    rt.run(step)


def main(argv=None) -> None:
    args = service_parser(NAME, __doc__.splitlines()[0]).parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
