"""zenpilot-planner: flies a mission file (arm, take off, hold, go to points, land).

Publishes planner/setpoint at its rate from the phase machine in
flight/mission.py, fed by the position level's state. It also follows
planner/command (from the MAVLink bridge): a command replaces whatever is
being flown. Mission "none" (or ""): idle on the ground, waiting for commands.
"""

from __future__ import annotations

import schemas
from flight.mission import MissionError, Planner, load_mission
from services.runtime import Runtime, main_guard, service_parser

NAME = "planner"
PARAMS = {"mission": "hover"}
NO_MISSION = ("", "none")


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS)
    name = args.mission if args.mission is not None else rt.params["mission"]
    mission = None if name in NO_MISSION else load_mission(name)
    planner = Planner(mission)
    state = rt.inbox(schemas.POSITION_STATE, "position")
    commands = rt.inbox(schemas.PLANNER_COMMAND, "mavlink", keep=16)
    out = rt.publisher(schemas.PLANNER_SETPOINT)
    reported = {"state": None}

    def follow_commands() -> None:
        for c in commands.take():
            try:
                planner.command(c["command"], c["altitude_m"], c["position_m"], c["yaw_rad"])
            except MissionError as exc:
                rt.rejected["command_refused"] = rt.rejected.get("command_refused", 0) + 1
                rt.problem(f"command {c['command']} from {c['origin']} refused: {exc}")
                continue
            print(f"zenpilot-planner: command {c['command']} from {c['origin']}", flush=True)

    def step(t: float) -> None:
        follow_commands()
        s = state.latest()
        if s is None:  # the mission starts once the position level reports a state
            out.put(planner.sp.as_message(), t_s=t)
            return
        sp = planner.update(t, s["position_m"], s["velocity_m_s"])
        out.put(sp.as_message(), t_s=t)
        if sp.mission_state != reported["state"]:
            reported["state"] = sp.mission_state
            if sp.mission_state == "failed":
                rt.problem(f"mission {name} failed: {sp.phase}")

    rt.run(step)


def main(argv=None) -> None:
    parser = service_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--mission", help="mission name (deploy/missions/NAME.toml) or file; "
                        "'none': wait for commands")
    args = parser.parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
