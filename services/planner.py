"""zenpilot-planner: flies a mission file (arm, take off, hold, go to points, land).

Publishes planner/setpoint at its rate from the phase machine in
flight/mission.py, fed by the position level's state.
"""

from __future__ import annotations

import schemas
from flight.mission import MissionRunner, load_mission
from services.runtime import Runtime, main_guard, service_parser

NAME = "planner"
PARAMS = {"mission": "hover"}


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS)
    mission = load_mission(args.mission or rt.params["mission"])
    runner = MissionRunner(mission)
    state = rt.inbox(schemas.POSITION_STATE, "position")
    out = rt.publisher(schemas.PLANNER_SETPOINT)
    reported = {"state": None}

    def step(t: float) -> None:
        s = state.latest()
        if s is None:  # the mission starts once the position level reports a state
            out.put(runner.sp.as_message(), t_s=t)
            return
        sp = runner.update(t, s["position_m"], s["velocity_m_s"])
        out.put(sp.as_message(), t_s=t)
        if sp.mission_state != reported["state"]:
            reported["state"] = sp.mission_state
            if sp.mission_state == "failed":
                rt.problem(f"mission {mission.name} failed: {sp.phase}")

    rt.run(step)


def main(argv=None) -> None:
    parser = service_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--mission", help="mission name (deploy/missions/NAME.toml) or file")
    args = parser.parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
