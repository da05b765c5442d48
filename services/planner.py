"""zenpilot-planner: flies a mission file (arm, take off, hold, go to points, flip, land).

Publishes planner/setpoint at its rate from the phase machine in
flight/control/mission.py, fed by the position level's state. It also follows
planner/command (from the MAVLink bridge): a command replaces whatever is
being flown, and planner/mission (the bridge's uploaded MAVLink mission): a list
of items flown from the next tick. Mission "none" (or ""): idle on the ground,
waiting for commands.

Flip items (document 001): the flip controller of each method the mission's flip
items name, and of each in `flip_methods` (for a ground station's flips, which
need no flip item: a MAVLink command or uploaded item flies the first), is built at
start-up (the iLQR compiled and warmed up before the first tick, never in flight; the
executable is kept in `compile_cache_dir`, so a restart loads it instead of compiling)
and the loop runs at least at the re-solve rate (`mpc_rate_hz`, 0: the method's default,
see flight/control/flip_runner.py). With a flip controller, planner/flip_status says once
a second which flip a command would fly and whether its prediction refuses it (the MAVLink
bridge accepts a flip only then). While a flip item runs, the setpoint's mode is `plan`
and every re-solve from the latest estimate (pos/state + att/state, and the rotor forces
implied by motors/pwm) goes out on planner/plan for the motor driver.

Real time (bench/flip_realtime.py): the stack gives the planner a real-time priority below
the control loops and vision; the solver is built at normal scheduling and then runs on one
XLA thread, dispatched synchronously (flight.control.ilqr.use_one_solver_thread); at the position
level's rate the loop runs on each new position state.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import replace

import numpy as np

import schemas
from flight.control.mission import ITEM_KEYS, MissionError, MissionPlanner, mission_items
from flight.control.plan import body_state, scale_collective_floats
from flight.motor_model import decay, thrust_step_floats
from services.params.planner import PARAMS  # every parameter: default, unit, bounds, doc
from services.runtime import Runtime, main_guard, service_parser
from services.stack import load_mission

NAME = "planner"
NO_MISSION = ("", "none")
# woken by the position state: at most one run per this many periods (a late state and the next
# one on time both run; a step that overran runs the next one as soon as it ends)
WAKE_MIN_GAP = 0.25


def flip_methods(mission, params: dict) -> tuple[list[str], str | None]:
    """The flip methods to build, sorted, and the one a MAVLink flip (a command or an uploaded
    item, which name none) flies, None without a flip: the mission's flip items' and the
    `flip_methods` parameter's (the first flies MAVLink's; without it the item's default method
    if built, else the first built); only `flip_method` when it is set, as it flies every flip."""
    named = {item["method"] for item in mission.items if item["type"] == "flip"} if mission else set()
    extra = list(params["flip_methods"])
    if not named and not extra:
        return [], None
    if params["flip_method"]:
        return [params["flip_method"]], params["flip_method"]
    methods = sorted(named | set(extra))
    default = ITEM_KEYS["flip"]["method"]
    return methods, extra[0] if extra else default if default in methods else methods[0]


def flip_controllers(rt: Runtime, methods: list[str]) -> dict:
    """One FlipController per flip method (compiled now)."""
    if not methods:
        return {}
    from flight.control.flip_runner import FlipController, loop_rate_hz
    from flight.vehicle import load_vehicle
    vehicle = load_vehicle(rt.vehicle_name)
    rate = rt.params["mpc_rate_hz"] or None
    if any(m != "baseline" for m in methods):
        from flight.control.ilqr import use_one_solver_thread
        if not use_one_solver_thread():
            rt.problem("JAX started before the solver's thread settings (flight.control.ilqr.use_one_solver_thread)")
    if rt.params["compile_cache_dir"]:
        from flight.control.ilqr import use_compile_cache
        try:
            use_compile_cache(rt.params["compile_cache_dir"])
        except OSError as exc:
            raise ValueError(f"{rt.where()} compile_cache_dir: {exc}") from None
    controllers = {}
    for m in methods:
        print(f"zenpilot-planner: building the {m} flip controller", flush=True)
        t0 = time.monotonic()
        controllers[m] = FlipController(vehicle, m, rate)
        print(f"zenpilot-planner: {m}: built (JAX compile and warm-up) in {time.monotonic() - t0:.2f} s", flush=True)
        if controllers[m].planner is not None:  # XLA's small-loop option took (flight/control/ilqr.py), or not
            whole = controllers[m].planner.loops_compiled_whole()
            print(f"zenpilot-planner: {m}: {whole} of the solver's loops compiled whole", flush=True)
    lead = rt.params["plan_lead_s"] > 0.0 or rt.params["plan_lead_auto"]
    if lead and not rt.lockstep and any(c.state_dim == 17 for c in controllers.values()):
        from flight.control.lead import make_lead_predictor
        t0 = time.monotonic()
        for c in controllers.values():
            if c.state_dim == 17:   # compiled now, not in flight: one prediction of a hover
                c.lead = make_lead_predictor(vehicle)
                x = c.planner.full_state(np.array([0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0]))
                c.lead(x, [(0.0, c.planner.solve(x, np.repeat(x[None], c.planner.config.horizon + 1, axis=0)))], 0.01)
        print(f"zenpilot-planner: plans lead by {rt.params['plan_lead_s']:g} s"
              f"{' or the link latency' if rt.params['plan_lead_auto'] else ''}: predictor built in "
              f"{time.monotonic() - t0:.2f} s", flush=True)
    loop = loop_rate_hz(rt.rate_hz, rt.tick_rate, [c.solve_rate_hz for c in controllers.values()])
    if loop != rt.rate_hz:
        print(f"zenpilot-planner: loop at {loop:g} Hz for the flip's re-solves", flush=True)
        rt.rate_hz = loop
    return controllers


def predict_flips(rt: Runtime, mission, controllers: dict, command_method: str | None = None) -> tuple[dict, list]:
    """The flips this vehicle should not fly, {(method, altitude_m): reason}, from each iLQR
    flip's predicted envelope (the controllers' own solvers fly the nominal), and the
    planner/flip_prediction messages that say so: the mission's flip items and the MAVLink
    flip (`command_method` from the flip item's default altitude, where every MAVLink flip
    starts: it is known before any is commanded)."""
    n = rt.params["flip_predict_rollouts"]
    if n == 0 or not controllers:
        return {}, []
    from flight.control.predict import FIGURES, PredictError, build_predictor
    refused, messages = {}, []
    items = {(i["method"], float(i["altitude_m"])) for i in mission.items if i["type"] == "flip"} if mission else set()
    if command_method is not None:
        items.add((command_method, float(ITEM_KEYS["flip"]["altitude_m"])))
    for method, altitude in sorted(items):
        if method == "baseline":
            continue
        t0 = time.monotonic()
        try:
            result = build_predictor(controllers[method].vehicle, method, altitude, controller=controllers[method],
                                     adapt=bool(rt.params["flip_predict_adapt"])).predict(n, seed=0)
        except PredictError as exc:
            refused[(method, altitude)] = f"no prediction: {exc}"
            rt.problem(f"flip {method} at {altitude:g} m: no prediction: {exc}")
            continue
        loss = result.band("loss_from_hover_m")
        print(f"zenpilot-planner: flip {method} at {altitude:g} m predicted over {n} cases in "
              f"{time.monotonic() - t0:.1f} s: loss from the hover p50 {loss[1]:.2f} / p95 {loss[2]:.2f} m, "
              f"P(crash) {result.crash_probability:.3f}", flush=True)
        reason = result.refusal(float(rt.params["flip_clearance_m"]))
        if reason is not None:
            refused[(method, altitude)] = reason
            rt.problem(f"flip {method} at {altitude:g} m refused: {reason}")
        bands = {name: [v for v in result.band(name)] for name in FIGURES}
        messages.append({"method": method, "altitude_m": altitude, "rollouts": n,
                         **{k: (v if all(np.isfinite(v)) else []) for k, v in bands.items()},
                         "p_crash": result.crash_probability, "p_ground": result.ground_probability,
                         "refused": reason is not None, "reason": reason or ""})
    return refused, messages


class PlannerLoop:
    """The planner's logic: the mission (or commands and uploaded missions) and the flip's
    controllers and their envelopes. `io` is the service's Runtime in flight, a fake in the unit
    tests; no Zenoh here. `mission_name`: a shipped mission, a file, or "none"."""

    def __init__(self, io, mission_name: str):
        self.io = io
        self.name = mission_name
        mission = None if mission_name in NO_MISSION else load_mission(mission_name)
        if io.params["flip_method"] and mission is not None:
            method = io.params["flip_method"]
            mission = replace(mission, items=tuple({**i, "method": method} if i["type"] == "flip" else i
                                                   for i in mission.items))
        methods, self.flip_command_method = flip_methods(mission, io.params)
        self.controllers = flip_controllers(io, methods)   # at normal scheduling: the runtime raises it for the loop
        self.refused, self.predictions = predict_flips(io, mission, self.controllers, self.flip_command_method)
        self.state = io.inbox(schemas.POSITION_STATE, "position")
        self.commands = io.inbox(schemas.PLANNER_COMMAND, "mavlink", keep=16)
        self.missions = io.inbox(schemas.PLANNER_MISSION, "mavlink", keep=4)
        self.out = io.publisher(schemas.PLANNER_SETPOINT)
        self.reported_state = None
        self.flip_x = None      # the full state the flip's controllers start and step from
        self.flip_pos = None
        self.flip_plan = None   # the plan this run made, sent before the setpoint
        self.flip_steps = 0
        self.lead_s = 0.0 if io.lockstep else io.params["plan_lead_s"]   # lockstep: a plan flies in the tick after it
        self.lead_auto = not io.lockstep and io.params["plan_lead_auto"]
        self.state_ages = deque(maxlen=max(1, round(2.0 * io.rate_hz)))   # plan_lead_auto: the last 2 s
        self.flip_lead_s = self.lead_s   # fixed for a flip at its start: the plans' clock must not jump
        self.max_lead_s = io.params["flip_max_lead_s"]
        self.flip_measured = None   # with a lead: (sample time, full state at it, the pos/state)
        self.sent = deque(maxlen=8)   # with a lead: (start, Plan) of the plans sent, oldest first
        if self.controllers:
            self.attitude = io.inbox(schemas.ATTITUDE_STATE, "attitude")
            self.pwm = io.inbox(schemas.MOTOR_PWM, "motors", keep=32)
            self.plan_out = io.publisher(schemas.PLANNER_PLAN)
            self.prediction_out = io.publisher(schemas.PLANNER_FLIP_PREDICTION)
            self.flip_status_out = io.publisher(schemas.PLANNER_FLIP_STATUS)
            self.flip_status_due = -math.inf
            from flight.vehicle import load_vehicle
            self.vehicle = load_vehicle(io.vehicle_name)
            self.forces = None   # the rotor forces the motor driver's commands imply (floats)
            self.forces_decay = decay(1.0 / io.tick_rate, self.vehicle.motor_time_constant_s)   # their lag's, per tick
            self.planner = MissionPlanner(mission, self.fly_flip, self.flip_command_method)
        else:
            self.planner = MissionPlanner(mission)

    def flip_status(self) -> dict:
        """planner/flip_status: the flip a command or an uploaded item flies, and whether it is refused."""
        key = (self.flip_command_method, float(ITEM_KEYS["flip"]["altitude_m"]))
        return {"methods": sorted(self.controllers), "method": key[0], "altitude_m": key[1],
                "refused": key in self.refused, "reason": self.refused.get(key, "")}

    def fly_flip(self, item, t, starting):
        """MissionRunner's flip hook: one controller step on the state of this run."""
        # the mission's items name built methods; a commanded or uploaded flip names the one it flies
        method = item["method"] if item["method"] in self.controllers else self.flip_command_method
        c = self.controllers[method]
        if self.flip_x is None:  # no attitude state yet: wait (the fallback laws hold)
            return "takeoff", False, False, self.flip_pos
        x = self.flip_x if c.state_dim == 17 else self.flip_x[:13]
        if (method, float(item["altitude_m"])) in self.refused:  # predicted unsafe: never started
            return "refused", False, True, self.flip_pos
        if starting:
            self.sent.clear()
            self.flip_lead_s = max(self.lead_s, float(np.median(self.state_ages))) \
                if self.lead_auto and self.state_ages else self.lead_s
            if self.lead_auto:
                print(f"zenpilot-planner: flip plans lead by {self.flip_lead_s:.3f} s", flush=True)
                if self.max_lead_s and self.flip_lead_s > self.max_lead_s:
                    self.count("flip_refused_late_states")
                    self.io.problem(f"flip refused: the states reach the planner {self.flip_lead_s:.3f} s late, "
                                    f"more than flip_max_lead_s {self.max_lead_s:g} s: the vehicle holds")
                    return "refused", False, True, self.flip_pos
        lead = self.flip_lead_s if c.state_dim == 17 else 0.0   # the rotor-lag model's plans (ilqr-project)
        if lead:   # the plan starts where it will fly: the state predicted to then (flight/control/lead.py)
            t_x, x_measured, pos = self.flip_measured
            t = t + lead
            if self.sent:
                x = c.lead(x_measured, [(start - t_x, plan) for start, plan in self.sent], t - t_x)
            else:   # no plan flies yet (the hover laws do): carried at constant rates, as without a lead
                x = self.read_full_state(t, pos)
        if starting:
            c.start(t, x, item["altitude_m"], item["baseline_climb_m"])
            self.flip_steps = 0
        ratio = max(1, round(self.io.rate_hz / c.solve_rate_hz))
        s = c.step(t, x, item["settle_s"], solve=self.flip_steps % ratio == 0)
        self.flip_steps += 1
        self.flip_plan = s.plan
        if lead and s.plan is not None:
            self.sent.append((s.plan["t0_s"], c.plan))
        return s.phase, s.done, s.failed, s.position_ref_m

    def read_full_state(self, t: float, pos: dict) -> np.ndarray | None:
        """[p, v, q, w, rotor forces] at t, or None without an attitude state."""
        vehicle = self.vehicle
        for m in self.pwm.take():  # the rotor forces the motor driver's commands imply (its lag model),
            # as the plan's model (the airframe file's) sees them: collective times the thrust scale;
            # in floats (scale_collective's and thrust_step's own float paths: the same bits)
            f = scale_collective_floats(vehicle.allocation, [float(v) for v in m["thrust_n"]], pos["thrust_scale"])
            self.forces = f if self.forces is None else thrust_step_floats(self.forces, f, self.forces_decay)
        att = self.attitude.latest()
        if att is None:
            return None
        n = self.forces  # None until a motors message: carried at constant velocity
        return np.concatenate([body_state(t, att, pos, vehicle, n), n if n is not None else np.zeros(4)])

    def count(self, reason: str) -> None:
        rejected = self.io.rejected
        rejected[reason] = rejected.get(reason, 0) + 1

    def follow_commands(self) -> None:
        planner = self.planner
        for c in self.commands.take():
            try:
                planner.command(c["command"], c["altitude_m"], c["position_m"], c["yaw_rad"])
            except MissionError as exc:
                self.count("command_refused")
                self.io.problem(f"command {c['command']} from {c['origin']} refused: {exc}")
                continue
            print(f"zenpilot-planner: command {c['command']} from {c['origin']}", flush=True)
        for m in self.missions.take():  # after the commands: a mission and a command in one tick -> the mission
            try:
                planner.fly(mission_items(m), f"mission from {m['origin']}")
            except MissionError as exc:
                self.count("mission_refused")
                self.io.problem(f"mission from {m['origin']} refused: {exc}")
                continue
            print(f"zenpilot-planner: mission of {len(m['types'])} items from {m['origin']}", flush=True)

    def step(self, t: float) -> None:
        """One run at time t: commands and missions in, the setpoint (and a flip's plan) out."""
        while self.predictions:  # on the first tick: on the stack's clock, in the log before the flip
            self.prediction_out.put(self.predictions.pop(0), t_s=t)
        if self.controllers and t >= self.flip_status_due:  # once a second: a bridge started late hears it
            self.flip_status_out.put(self.flip_status(), t_s=t)
            self.flip_status_due = math.floor(t) + 1.0
        self.follow_commands()
        s = self.state.latest()
        if s is None:  # the mission starts once the position level reports a state
            self.out.put(self.planner.sp.as_message(), t_s=t)
            return
        if self.controllers:
            self.flip_x = self.read_full_state(t, s)
            if self.lead_auto:
                self.state_ages.append(max(0.0, t - s["header"]["t_s"]))
            if (self.lead_s or self.lead_auto) and self.flip_x is not None:   # the state at its newer sample time
                t_x = min(t, max(s["header"]["t_s"], self.attitude.latest()["header"]["t_s"]))
                self.flip_measured = (t_x, self.read_full_state(t_x, s), s)
            self.flip_pos = np.array(s["position_m"])
            self.flip_plan = None
        sp = self.planner.update(t, s["position_m"], s["velocity_m_s"])
        if self.controllers and self.flip_plan is not None:
            # the plan before the setpoint: a motor driver run between the two (real time)
            # would otherwise see the flip's first setpoint in mode `plan` with no plan yet
            self.plan_out.put(self.flip_plan, t_s=t)
        self.out.put(sp.as_message(), t_s=t)
        if sp.mission_state != self.reported_state:
            self.reported_state = sp.mission_state
            if sp.mission_state == "failed":
                self.io.problem(f"mission {self.name} failed: {sp.phase}")


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS)
    loop = PlannerLoop(rt, args.mission if args.mission is not None else rt.params["mission"])
    # With an iLQR flip at the position level's rate (the project's 100 Hz re-solves), the loop
    # runs as each position state arrives (real time; lockstep runs on its ticks): every solve
    # starts from a state that is new and fresh, not one up to a period old (or the same twice);
    # a step that overran is followed at once by the next one rather than the next period's.
    position = rt.stack.services.get("position")
    if loop.controllers and position is not None and abs(position.rate_hz - rt.rate_hz) < 1e-9:
        rt.run(loop.step, wake_on=loop.state, min_gap=WAKE_MIN_GAP)
    else:
        rt.run(loop.step)


def main(argv=None) -> None:
    parser = service_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--mission", help="mission name (deploy/missions/NAME.toml) or file; "
                        "'none': wait for commands")
    args = parser.parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
