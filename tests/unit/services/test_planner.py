"""The planner's logic (services/planner.py PlannerLoop) without a router: missions and
commands (the flip's controllers are tested in tests/unit/test_flip*.py)."""

import pytest

import schemas
from services.planner import PARAMS, PlannerLoop
from tests.unit.services.fake_io import FakeIO


def state(pos=(0.0, 0.0, 0.0)):
    return {"position_m": list(pos), "velocity_m_s": [0.0, 0.0, 0.0], "position_ref_m": list(pos),
            "position_cov_m2": [0.0] * 9, "acceleration_m_s2": [0.0, 0.0, 0.0], "thrust_scale": 1.0,
            "state_source": "truth"}


def command(name, altitude_m=0.0):
    return {"command": name, "altitude_m": altitude_m, "position_m": [0.0, 0.0, 0.0], "yaw_rad": 0.0,
            "origin": "test"}


def loop_for(mission, **params):
    io = FakeIO("planner", PARAMS, params, rate_hz=50.0)
    io.tick_rate = 400.0
    return io, PlannerLoop(io, mission)


def test_waits_for_a_state_then_flies_the_mission():
    io, loop = loop_for("hover")
    loop.step(0.0)
    [(_, sp)] = io.sent(schemas.PLANNER_SETPOINT)
    assert not sp["armed"] and sp["mission_state"] == "waiting"
    states = io.received(schemas.POSITION_STATE, "position")
    for n in range(1, 100):   # 2 s on the ground: armed, then taking off
        states.push(n / 50, state())
        loop.step(n / 50)
    _, sp = io.sent(schemas.PLANNER_SETPOINT)[-1]
    assert sp["armed"] and sp["mission_state"] == "running" and sp["position_m"][2] > 0.0


def test_commands_replace_the_mission_and_a_bad_one_is_refused_and_counted():
    io, loop = loop_for("none")
    states, commands = io.received(schemas.POSITION_STATE, "position"), io.received(schemas.PLANNER_COMMAND, "mavlink")
    states.push(0.0, state())
    commands.push(0.0, command("takeoff", altitude_m=500.0))   # outside (0, 100] m
    commands.push(0.0, command("flip"))                         # no flip controller without a flip item
    loop.step(0.0)
    assert io.rejected == {"command_refused": 2} and "refused" in io.problems[-1]
    commands.push(0.02, command("arm"))
    commands.push(0.02, command("takeoff", altitude_m=2.0))
    for n in range(1, 50):
        states.push(n / 50, state())
        loop.step(n / 50)
    _, sp = io.sent(schemas.PLANNER_SETPOINT)[-1]
    assert sp["armed"] and sp["position_m"][2] > 0.0
    commands.push(1.0, command("disarm"))
    loop.step(1.0)
    assert not io.sent(schemas.PLANNER_SETPOINT)[-1][1]["armed"]


def test_an_unknown_mission_or_flip_method_is_refused_at_start():
    with pytest.raises(ValueError, match="nonesuch"):
        loop_for("nonesuch")
    with pytest.raises(ValueError, match="services.planner.params.*flip_method"):
        loop_for("flip", flip_method="cartwheel")


def attitude():
    return {"quaternion_wxyz": [1.0, 0.0, 0.0, 0.0], "euler_rad": [0.0, 0.0, 0.0], "rate_rad_s": [0.0, 0.0, 0.0],
            "euler_ref_rad": [0.0, 0.0, 0.0], "euler_var_rad2": [0.0] * 3, "rate_var_rad2_s2": [0.0] * 3,
            "state_source": "truth"}


@pytest.mark.parametrize("mission, params, expected", [
    ("hover", {}, ([], None)),                                              # the default: nothing built
    ("flip", {}, (["ilqr-project"], "ilqr-project")),                      # the mission's item, as before
    ("none", {"flip_methods": ["ilqr-thesis", "baseline"]}, (["baseline", "ilqr-thesis"], "ilqr-thesis")),
    ("flip", {"flip_methods": ["baseline"]}, (["baseline", "ilqr-project"], "baseline")),
    ("flip", {"flip_method": "baseline", "flip_methods": ["ilqr-thesis"]}, (["baseline"], "baseline")),
    ("hover", {"flip_method": "baseline"}, ([], None)),                    # an override builds no flip
])
def test_flip_methods_are_the_missions_and_the_parameters(mission, params, expected):
    from services.planner import flip_methods
    from services.stack import load_mission
    io = FakeIO("planner", PARAMS, params)
    assert flip_methods(None if mission == "none" else load_mission(mission), io.params) == expected


def test_flip_methods_build_a_flip_for_a_ground_station_without_a_flip_item():
    """A stack that wants MAVLink flips on any mission: the baseline built (no JAX) for a planner
    waiting for commands, its flip status said once a second, a commanded flip flown with it."""
    io, loop = loop_for("none", flip_methods=["baseline"])
    assert list(loop.controllers) == ["baseline"] and loop.flip_command_method == "baseline"
    states, commands = io.received(schemas.POSITION_STATE, "position"), io.received(schemas.PLANNER_COMMAND, "mavlink")
    atts = io.received(schemas.ATTITUDE_STATE, "attitude")
    commands.push(0.0, command("arm"))
    commands.push(0.0, command("takeoff", altitude_m=2.0))
    for n in range(0, 101):
        states.push(n / 50, state((0.0, 0.0, min(2.0, n / 25))))
        atts.push(n / 50, attitude())
        if n == 75:
            commands.push(n / 50, command("flip"))
        loop.step(n / 50)
    assert io.rejected == {} and not io.problems, io.problems
    status = io.sent(schemas.PLANNER_FLIP_STATUS)
    assert [t for t, _ in status] == [0.0, 1.0, 2.0]   # once a second, on the stack's clock
    assert status[0][1] == {"methods": ["baseline"], "method": "baseline", "altitude_m": 5.0, "refused": False,
                            "reason": ""}
    _, sp = io.sent(schemas.PLANNER_SETPOINT)[-1]
    assert sp["phase"].startswith("flip") and sp["mode"] == "plan" and sp["mission_state"] == "running", sp
    plans = io.sent(schemas.PLANNER_PLAN)
    assert plans and all(p["method"] == "baseline" for _, p in plans)


def test_the_default_planner_says_nothing_of_flips():
    io, loop = loop_for("hover")
    loop.step(0.0)
    assert loop.controllers == {} and io.sent(schemas.PLANNER_FLIP_STATUS) == []


@pytest.mark.parametrize("given, needle", [
    (["ilqr-project", "cartwheel"], "flip_methods: 'cartwheel' not one of ('ilqr-project', 'ilqr-thesis', 'baseline')"),
    ("ilqr-project", 'flip_methods: expected a list, e.g. ["ilqr-project"]'),
    ([3], "flip_methods: 3 not one of"),
])
def test_a_bad_flip_methods_value_is_refused_at_start_naming_the_parameter(given, needle):
    with pytest.raises(ValueError) as err:
        loop_for("none", flip_methods=given)
    assert "[services.planner.params]." + needle in str(err.value), str(err.value)


class FakeController:
    """Stands for a built iLQR flip controller (no JAX): what predict_flips and fly_flip read first."""
    state_dim, solve_rate_hz = 17, 100.0

    def __init__(self, method):
        from flight.vehicle import load_vehicle
        self.vehicle, self.method, self.planner = load_vehicle("x250"), method, None


class FakePrediction:
    """A predictor whose flip loses 4.9 m at p95: refused from a 5 m hover."""
    crash_probability = ground_probability = 0.0

    def __init__(self, altitude_m):
        self.altitude_m = altitude_m

    def predict(self, n, seed):
        return self

    def band(self, name):
        return [0.0, 0.1, 4.9]

    def refusal(self, clearance_m):
        return f"predicted loss 4.9 m from {self.altitude_m:g} m"


@pytest.fixture
def refusing_predictor(monkeypatch):
    import flight.control.predict as predict
    asked = []

    def build(vehicle, method, altitude_m, controller=None, adapt=True):
        asked.append((method, altitude_m, adapt))
        return FakePrediction(altitude_m)
    monkeypatch.setattr(predict, "build_predictor", build)
    return asked


def test_the_ground_stations_flip_is_predicted_and_a_refused_prediction_still_refuses(monkeypatch, refusing_predictor):
    """flip_methods builds an iLQR flip for a mission without a flip item: the flip a command
    would fly (from the flip item's default 5 m, where every MAVLink flip starts) is predicted at
    start-up like a mission's item; refused, the status says so and a commanded flip is never
    started (the phase machine's `flip-refused`, the vehicle held)."""
    import services.planner as planner
    monkeypatch.setattr(planner, "flip_controllers", lambda io, methods: {m: FakeController(m) for m in methods})
    io, loop = loop_for("none", flip_methods=["ilqr-project"])
    assert refusing_predictor == [("ilqr-project", 5.0, False)]
    assert loop.refused == {("ilqr-project", 5.0): "predicted loss 4.9 m from 5 m"}
    states, commands = io.received(schemas.POSITION_STATE, "position"), io.received(schemas.PLANNER_COMMAND, "mavlink")
    io.received(schemas.ATTITUDE_STATE, "attitude").push(0.0, attitude())
    states.push(0.0, state((0.0, 0.0, 5.0)))
    commands.push(0.0, command("flip"))
    loop.step(0.0)
    [(_, prediction)] = io.sent(schemas.PLANNER_FLIP_PREDICTION)
    assert prediction["method"] == "ilqr-project" and prediction["altitude_m"] == 5.0 and prediction["refused"]
    [(_, status)] = io.sent(schemas.PLANNER_FLIP_STATUS)
    assert status["refused"] and status["reason"] == "predicted loss 4.9 m from 5 m"
    _, sp = io.sent(schemas.PLANNER_SETPOINT)[-1]
    assert sp["phase"] == "flip-refused" and sp["mode"] == "position", sp
    assert io.sent(schemas.PLANNER_PLAN) == []


def test_a_missions_flip_item_is_predicted_once_when_the_ground_stations_is_the_same(monkeypatch, refusing_predictor):
    import services.planner as planner
    monkeypatch.setattr(planner, "flip_controllers", lambda io, methods: {m: FakeController(m) for m in methods})
    loop_for("flip", flip_predict_adapt=True)   # its item: ilqr-project from 5 m, what a command flies too
    assert refusing_predictor == [("ilqr-project", 5.0, True)]


def test_the_prediction_replays_the_nominal_in_every_case_when_asked(monkeypatch, refusing_predictor):
    """flip_predict_adapt=false (the default): no flights on the knots' vehicles at start-up."""
    import services.planner as planner
    monkeypatch.setattr(planner, "flip_controllers", lambda io, methods: {m: FakeController(m) for m in methods})
    loop_for("flip")
    assert refusing_predictor == [("ilqr-project", 5.0, False)]


def test_an_uploaded_flip_item_flies_the_ground_stations_method():
    """A MAVLink mission's flip item names no method: it flies the one flip_methods names first
    (not the item's default, ilqr-project)."""
    from services.mavlink_logic import mission_fields
    io, loop = loop_for("none", flip_methods=["baseline"])
    io.received(schemas.PLANNER_MISSION, "mavlink").push(0.0, mission_fields(
        [("takeoff", [0.0, 0.0, 5.0], 0.0, 0.0, 0.3), ("flip", [0.0, 0.0, 5.0], 0.0, 0.0, 0.3)], "test"))
    loop.step(0.0)
    assert io.rejected == {} and [i["method"] for i in loop.planner.runner.mission.items if i["type"] == "flip"] \
        == ["baseline"]


def _flip_across_a_link(params: dict, age_s: float, runs: int) -> FakeIO:
    """A real-time planner (50 Hz) hovering at 5 m on states `age_s` old, as across a link, asked
    for a flip at its sixth run, stepped `runs` times from t = 1 s; its FakeIO."""
    io = FakeIO("planner", PARAMS, {"flip_methods": ["ilqr-project"], "flip_predict_rollouts": 0, **params},
                rate_hz=50.0, lockstep=False)
    io.tick_rate = 400.0
    loop = PlannerLoop(io, "none")
    states, commands = io.received(schemas.POSITION_STATE, "position"), io.received(schemas.PLANNER_COMMAND, "mavlink")
    atts = io.received(schemas.ATTITUDE_STATE, "attitude")
    commands.push(0.0, command("arm"))
    commands.push(0.0, command("takeoff", altitude_m=5.0))
    for n in range(runs):
        t = 1.0 + n / io.rate_hz
        states.push(t - age_s, state((0.0, 0.0, 5.0)))
        atts.push(t - age_s, attitude())
        if n == 5:
            commands.push(t, command("flip"))
        loop.step(t)
    return io


@pytest.mark.parametrize("params, lead", [({"plan_lead_s": 0.04}, 0.04),
                                          ({"plan_lead_auto": True}, 0.03),   # the states' age on arrival
                                          ({"plan_lead_s": 0.05, "plan_lead_auto": True}, 0.05)])
def test_with_a_lead_the_flips_plans_start_that_far_ahead_from_the_predicted_state(params, lead):
    """A planner across a link (planner.plan_lead_s, plan_lead_auto): each plan starts lead
    seconds after the run that made it, solved from the state flown forward on the model to then."""
    io = _flip_across_a_link(params, age_s=0.03, runs=75)   # states measured 30 ms ago
    problems = [p for p in io.problems if "use_one_solver_thread" not in p]   # JAX started by another test first
    assert io.rejected == {} and not problems, problems
    plans = io.sent(schemas.PLANNER_PLAN)
    assert len(plans) > 10
    assert all(p["t0_s"] == pytest.approx(t + lead) for t, p in plans)
    # the state it was solved from: 70 ms of the plans flown on from the 5 m hover, not the hover
    first = [p for _, p in plans if p["phase"] == "flip"]
    assert first and abs(first[5]["states"][2] - 5.0) > 1e-4
    io, loop = loop_for("none", flip_methods=["ilqr-project"], plan_lead_s=0.04, flip_predict_rollouts=0)
    assert loop.lead_s == 0.0   # lockstep: a plan flies in the tick after it is made


class StartingController(FakeController):
    """A flip controller that only notes that it was started."""
    def __init__(self, method):
        super().__init__(method)
        self.started = False

    def lead(self, x, sent, dt):
        return x

    def start(self, *args):
        self.started = True

    def step(self, t, x, settle_s, solve):
        from types import SimpleNamespace
        return SimpleNamespace(plan=None, phase="flip", done=False, failed=False, position_ref_m=[0.0, 0.0, 5.0])


@pytest.mark.parametrize("bound, refused", [(0.15, True), (0.25, False), (0.0, False)])
def test_a_flip_whose_states_come_too_late_is_refused_and_the_vehicle_held(monkeypatch, bound, refused):
    """plan_lead_auto across a link whose states arrive 0.2 s old (TLS at 5 % loss, where such a
    flip fell): over flip_max_lead_s the flip is never started - no plan, `flip-refused`, the
    position held, the reason in the log and the counts; under the bound, or with none, it starts."""
    import services.planner as planner
    controllers = {}
    monkeypatch.setattr(planner, "flip_controllers",
                        lambda io, methods: controllers.update({m: StartingController(m) for m in methods}) or controllers)
    io = _flip_across_a_link({"plan_lead_auto": True, "flip_max_lead_s": bound}, age_s=0.2, runs=60)
    _, sp = io.sent(schemas.PLANNER_SETPOINT)[-1]
    if refused:
        assert sp["phase"] == "flip-refused" and sp["mode"] == "position" and sp["position_m"][2] == 5.0, sp
        assert io.sent(schemas.PLANNER_PLAN) == [] and io.rejected == {"flip_refused_late_states": 1}
        assert any("flip refused: the states reach the planner 0.200 s late" in p for p in io.problems), io.problems
    else:
        assert sp["phase"] == "flip" and io.rejected == {}, sp
    assert controllers["ilqr-project"].started is not refused
