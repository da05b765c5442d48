"""zenpilot-position: the position level (100 Hz), laws (9)-(11) of 000.

In `position` mode it turns the planner's position reference into an
attitude reference and collective thrust; in `attitude` mode it holds the
planner's altitude and passes its roll/pitch/yaw reference through. State
source: `truth` (explicit ablation setting) until the position EKF exists.
"""

from __future__ import annotations

import numpy as np

import schemas
from flight.control import altitude_law, position_law
from flight.quat import quat_to_euler
from flight.vehicle import load_vehicle
from services.runtime import Runtime, main_guard, service_parser

NAME = "position"
PARAMS = {
    "state_source": "truth",
    "k": [4.0, 4.0, 4.0],        # laws (10) gains per axis (x, y, z), 1/s
    "alpha": [4.0, 4.0, 4.0],
    "max_tilt_deg": 35.0,
    "setpoint_timeout_s": 0.5,   # stale planner setpoint -> hold where we are
}
STATE_SOURCES = ("truth",)


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS)
    p = rt.params
    if p["state_source"] not in STATE_SOURCES:
        raise ValueError(f"{rt.stack.path}: [services.position.params] state_source: "
                         f"{p['state_source']!r} not one of {STATE_SOURCES}")
    vehicle = load_vehicle(rt.vehicle_name)
    truth = rt.inbox(schemas.TRUTH, "sim")
    planner = rt.inbox(schemas.PLANNER_SETPOINT, "planner")
    setpoint_out = rt.publisher(schemas.POSITION_SETPOINT)
    state_out = rt.publisher(schemas.POSITION_STATE)
    k, alpha = np.asarray(p["k"]), np.asarray(p["alpha"])
    m, g = vehicle.mass_kg, vehicle.gravity_m_s2
    hold = {"position": None}

    def step(t: float) -> None:
        state, sp = truth.latest(), planner.latest()
        if state is None:
            return
        pos, vel = np.asarray(state["position_m"]), np.asarray(state["velocity_m_s"])
        roll, pitch, yaw = quat_to_euler(state["quaternion_wxyz"])
        stale = sp is None or t - sp["header"]["t_s"] > p["setpoint_timeout_s"]
        if stale and hold["position"] is None:
            hold["position"] = pos.copy()  # planner lost: hold the position we had
        if not stale:
            hold["position"] = None
        if sp is not None and not stale and (sp["mode"] == "idle" or not sp["armed"]):
            ref_pos, att_ref, thrust = pos, [0.0, 0.0, yaw], 0.0
        elif sp is not None and not stale and sp["mode"] == "attitude":
            ref_pos, att_ref = np.asarray(sp["position_m"]), list(sp["attitude_rad"])
            thrust = altitude_law(m, g, pos[2], vel[2], ref_pos[2], k[2], alpha[2], roll, pitch)
        else:
            ref_pos = hold["position"] if stale else np.asarray(sp["position_m"])
            yaw_ref = yaw if stale else sp["attitude_rad"][2]
            r, pt, thrust = position_law(m, g, pos, vel, ref_pos, k, alpha, yaw_ref,
                                         max_tilt_rad=np.radians(p["max_tilt_deg"]))
            att_ref = [r, pt, yaw_ref]
        thrust = float(min(thrust, 4 * vehicle.max_thrust_n))
        setpoint_out.put({"attitude_ref_rad": att_ref, "thrust_n": thrust}, t_s=t)
        state_out.put({"position_m": pos, "velocity_m_s": vel, "position_ref_m": ref_pos,
                       "state_source": p["state_source"]}, t_s=t)

    rt.run(step)


def main(argv=None) -> None:
    args = service_parser(NAME, __doc__.splitlines()[0]).parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
