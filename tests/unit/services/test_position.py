"""The position level's logic (services/position.py PositionLoop) without a router."""

import numpy as np
import pytest

import schemas
from flight.control.laws import position_law
from flight.quat import quat_from_euler
from flight.vehicle import load_vehicle
from services.position import PARAMS, PositionLoop
from tests.unit.services.fake_io import FakeIO, defaults

DEFAULT = defaults(PARAMS)

X250 = load_vehicle("x250")


def truth(pos, vel=(0.0, 0.0, 0.0), yaw=0.0):
    return {"position_m": list(pos), "velocity_m_s": list(vel), "quaternion_wxyz": list(quat_from_euler(0.0, 0.0, yaw)),
            "rate_rad_s": [0.0, 0.0, 0.0], "acceleration_m_s2": [0.0, 0.0, 0.0], "motor_thrust_n": [1.0] * 4,
            "wind_m_s": [0.0, 0.0, 0.0], "landed": False}


def setpoint(pos, mode="position", armed=True, yaw=0.0, phase="hold"):
    return {"mode": mode, "armed": armed, "position_m": list(pos), "attitude_rad": [0.0, 0.0, yaw], "item": 1,
            "phase": phase, "measure": False, "mission_state": "running"}


def truth_loop(**params):
    io = FakeIO("position", PARAMS, {"state_source": "truth", **params}, rate_hz=100.0)
    return io, PositionLoop(io)


def test_truth_source_turns_the_reference_into_laws_9_to_11():
    io, loop = truth_loop()
    io.received(schemas.TRUTH, "sim").push(2.0, truth([0.0, 0.0, 1.0], vel=[0.1, 0.0, 0.0]))
    io.received(schemas.PLANNER_SETPOINT, "planner").push(2.0, setpoint([1.0, 0.0, 1.5]))
    loop.step(2.0)
    [(t, sp)] = io.sent(schemas.POSITION_SETPOINT)
    r, pt, thrust = position_law(X250.mass_kg, X250.gravity_m_s2, np.array([0.0, 0.0, 1.0]), np.array([0.1, 0.0, 0.0]),
                                 np.array([1.0, 0.0, 1.5]), np.array(DEFAULT["k"]), np.array(DEFAULT["alpha"]), 0.0,
                                 max_tilt_rad=X250.tilt_limit_rad(DEFAULT["max_tilt_deg"]))
    assert t == 2.0 and sp["attitude_ref_rad"] == pytest.approx([r, pt, 0.0]) and sp["thrust_n"] == pytest.approx(thrust)
    assert pt > 0.0   # towards +x: pitch forward (FLU: positive pitch tips the nose down)
    [(_, state)] = io.sent(schemas.POSITION_STATE)
    assert list(state["position_ref_m"]) == [1.0, 0.0, 1.5] and state["state_source"] == "truth"


def test_idle_or_disarmed_asks_for_no_thrust():
    io, loop = truth_loop()
    io.received(schemas.TRUTH, "sim").push(1.0, truth([0.0, 0.0, 0.0], yaw=0.4))
    io.received(schemas.PLANNER_SETPOINT, "planner").push(1.0, setpoint([0.0, 0.0, 1.0], armed=False))
    loop.step(1.0)
    _, sp = io.sent(schemas.POSITION_SETPOINT)[-1]
    assert sp["thrust_n"] == 0.0 and sp["attitude_ref_rad"] == pytest.approx([0.0, 0.0, 0.4])


def test_planner_lost_holds_then_lands_then_idles():
    _landed_by_the_failsafe()


def _landed_by_the_failsafe():
    io, loop = truth_loop(setpoint_timeout_s=0.5, planner_loss_land_after_s=1.0)
    truths, planner = io.received(schemas.TRUTH, "sim"), io.received(schemas.PLANNER_SETPOINT, "planner")
    truths.push(1.0, truth([0.5, 0.0, 2.0]))
    planner.push(1.0, setpoint([0.0, 0.0, 2.0]))
    loop.step(1.0)
    truths.push(1.6, truth([0.5, 0.0, 2.0]))
    loop.step(1.6)   # stale: hold where we were, not where the planner last said
    _, state = io.sent(schemas.POSITION_STATE)[-1]
    assert list(state["position_ref_m"]) == [0.5, 0.0, 2.0]
    assert io.rejected == {"planner_lost": 1} and "holding" in io.problems[-1]
    for n in range(300):   # 3 s past the hold: the held height sinks
        t = 2.7 + n / 100
        truths.push(t, truth([0.5, 0.0, 2.0]))
        loop.step(t)
    _, state = io.sent(schemas.POSITION_STATE)[-1]
    assert state["position_ref_m"][2] < 2.0 - 0.5 * DEFAULT["land_speed_m_s"] * 2.0
    for n in range(150):   # on the ground, slow: idle after LANDED_FOR_S
        t = 6.0 + n / 100
        truths.push(t, truth([0.5, 0.0, 0.0]))
        loop.step(t)
    assert io.rejected.get("planner_lost_landed") == 1
    assert io.sent(schemas.POSITION_SETPOINT)[-1][1]["thrust_n"] == 0.0
    return io, loop, truths, planner


def test_landed_by_the_failsafe_it_stays_down_until_the_planner_disarms():
    """The planner back after the failsafe landed the vehicle (its mission still flying, 2 m up):
    no take-off by itself; once the planner disarms, a new arm flies again."""
    io, loop, truths, planner = _landed_by_the_failsafe()
    for n in range(100):
        t = 7.5 + n / 100
        truths.push(t, truth([0.5, 0.0, 0.0]))
        planner.push(t, setpoint([0.0, 0.0, 2.0]))
        loop.step(t)
        assert io.sent(schemas.POSITION_SETPOINT)[-1][1]["thrust_n"] == 0.0
    assert io.rejected.get("planner_back_landed") == 1 and "stays down until the planner disarms" in io.problems[-1]
    for t, armed in ((8.5, False), (8.6, True)):
        truths.push(t, truth([0.5, 0.0, 0.0]))
        planner.push(t, setpoint([0.0, 0.0, 2.0], armed=armed))
        loop.step(t)
    assert io.sent(schemas.POSITION_SETPOINT)[-1][1]["thrust_n"] > 0.0   # armed again: it climbs


def test_the_planner_back_after_a_loss_is_reached_as_a_ramp_not_a_step():
    """A 2 s link outage in a landing: the planner's reference went on down while the position
    level held; stepped to it (0.9 m below) the law asked for the least thrust and the most tilt
    and the vehicle climbed to 3 m (once 83 m). Back, the reference moves from where the vehicle
    is at land_speed_m_s; a planner never lost (the first setpoint of a flight) is followed at once."""
    io, loop = truth_loop(setpoint_timeout_s=0.5, planner_loss_land_after_s=5.0)
    truths, planner = io.received(schemas.TRUTH, "sim"), io.received(schemas.PLANNER_SETPOINT, "planner")
    truths.push(1.0, truth([0.0, 0.0, 0.6]))
    planner.push(1.0, setpoint([0.0, 0.0, 0.6], phase="land"))
    loop.step(1.0)
    assert list(io.sent(schemas.POSITION_STATE)[-1][1]["position_ref_m"]) == [0.0, 0.0, 0.6]
    truths.push(2.0, truth([0.0, 0.0, 0.6]))
    loop.step(2.0)   # lost: held
    speed = DEFAULT["land_speed_m_s"]
    refs = []
    for n in range(300):   # back, its reference 0.9 m below
        t = 3.0 + n / 100
        truths.push(t, truth([0.0, 0.0, 0.6]))
        planner.push(t, setpoint([0.0, 0.0, -0.3], phase="land"))
        loop.step(t)
        refs.append(io.sent(schemas.POSITION_STATE)[-1][1]["position_ref_m"][2])
    assert io.rejected == {"planner_lost": 1, "planner_back": 1}
    assert refs[0] == pytest.approx(0.6) and refs[100] == pytest.approx(0.6 - speed * 1.0)
    assert all(a >= b for a, b in zip(refs, refs[1:])) and refs[-1] == -0.3   # reached, then the planner's own


def _pose(position):
    return {"position_m": position, "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0],
            "position_cov_m2": list(np.eye(3).reshape(-1) * 1e-4),
            "attitude_var_rad2": [1e-4, 1e-4, 1e-4], "markers": 6, "reprojection_rms_px": 0.5}


def _attitude_runs(io, t):
    """The attitude level's estimate at `t`, level: what the position level waits for before its first state."""
    io.received(schemas.ATTITUDE_STATE, "attitude").push(t, {
        "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0], "euler_rad": [0.0, 0.0, 0.0], "rate_rad_s": [0.0, 0.0, 0.0],
        "euler_ref_rad": [0.0, 0.0, 0.0], "euler_var_rad2": [1e-4] * 3, "rate_var_rad2_s2": [1e-4] * 3,
        "state_source": "estimate"})


def test_only_gated_fixes_restart_the_ekf():
    """Fixes too old for the EKF's history are refused and counted, but say nothing of a lost
    vehicle: six in a row restart nothing; five gated in a row restart it at the fix."""
    io = FakeIO("position", PARAMS, {}, rate_hz=100.0)
    loop = PositionLoop(io)
    poses = io.received(schemas.VISION_POSE, "vision")
    io.received(schemas.PLANNER_SETPOINT, "planner").push(0.0, setpoint([0.0, 0.0, 0.0], armed=False))
    _attitude_runs(io, 0.0)
    n = 0
    for n in range(1, 101):   # 1 s at rest, a fix every 5th run
        if n % 5 == 0:
            poses.push(n / 100 - 0.05, _pose([0.0, 0.0, 0.0]))
        loop.step(n / 100)
    before = io.rejected.get("fusion_position_rejected", 0)
    for k in range(6):   # 0.4 s old: within pose_timeout_s, beyond the EKF's 0.3 s of history
        n += 5
        poses.push(n / 100 - 0.4, _pose([0.0, 0.0, 0.0]))
        loop.step(n / 100)
    assert io.rejected.get("fusion_position_rejected") == before + 6 and not io.rejected.get("fusion_position_reset")
    for k in range(5):   # 2 m off: gated
        n += 5
        poses.push(n / 100 - 0.05, _pose([2.0, 0.0, 0.0]))
        loop.step(n / 100)
    assert io.rejected.get("fusion_position_rejected") == before + 11 and io.rejected.get("fusion_position_reset") == 1


def _pwm(armed, thrust_each_n):
    return {"pwm_us": [1500.0] * 4, "thrust_n": [thrust_each_n] * 4, "armed": armed, "saturated": False, "imu_t_s": -1.0}


def test_restarted_in_flight_the_ekf_starts_at_the_first_camera_fix_not_at_home():
    """A position level started while the rotors carry the vehicle (a supervised restart, the
    attitude level's failsafe flying it) publishes nothing until a fresh camera fix, then starts
    the EKF there; one started with the motors idle starts at home at its first attitude estimate."""
    hover = X250.mass_kg * X250.gravity_m_s2 / 4
    for armed, thrust, in_flight in ((True, hover, True), (False, 0.0, False)):
        io = FakeIO("position", PARAMS, {}, rate_hz=100.0)
        loop = PositionLoop(io)
        motors, poses = io.received(schemas.MOTOR_PWM, "motors"), io.received(schemas.VISION_POSE, "vision")
        io.received(schemas.PLANNER_SETPOINT, "planner").push(10.0, setpoint([0.0, 0.0, 1.0]))
        motors.push(10.0, _pwm(armed, thrust))
        _attitude_runs(io, 10.0)
        loop.step(10.01)
        assert bool(io.sent(schemas.POSITION_STATE)) is not in_flight
        if not in_flight:
            assert io.sent(schemas.POSITION_STATE)[-1][1]["position_m"] == pytest.approx([0.0, 0.0, 0.0], abs=1e-6)
            continue
        poses.push(9.0, _pose([0.3, -0.2, 0.8]))   # older than pose_timeout_s: not a start
        motors.push(10.01, _pwm(armed, thrust))
        loop.step(10.02)
        assert not io.sent(schemas.POSITION_STATE)
        poses.push(10.0, _pose([0.3, -0.2, 0.8]))
        motors.push(10.02, _pwm(armed, thrust))
        loop.step(10.03)
        _, state = io.sent(schemas.POSITION_STATE)[-1]
        assert state["position_m"] == pytest.approx([0.3, -0.2, 0.8], abs=0.02)
        assert io.rejected.get("ekf_started_in_flight") == 1


def test_estimate_fuses_camera_fixes_and_counts_stale_ones():
    io = FakeIO("position", PARAMS, {}, rate_hz=100.0)
    loop = PositionLoop(io)
    poses = io.received(schemas.VISION_POSE, "vision")
    io.received(schemas.PLANNER_SETPOINT, "planner").push(0.0, setpoint([0.0, 0.0, 0.0], armed=False))
    _attitude_runs(io, 0.0)
    for n in range(1, 201):   # 2 s on the ground, a fix every 5th run at (0.2, -0.1, 0)
        t = n / 100
        if n % 5 == 0:
            poses.push(t - 0.05, {"position_m": [0.2, -0.1, 0.0], "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0],
                                  "position_cov_m2": list(np.eye(3).reshape(-1) * 1e-4),
                                  "attitude_var_rad2": [1e-4, 1e-4, 1e-4], "markers": 6, "reprojection_rms_px": 0.5})
        loop.step(t)
    _, state = io.sent(schemas.POSITION_STATE)[-1]
    assert state["position_m"][:2] == pytest.approx([0.2, -0.1], abs=0.02)
    poses.push(2.0 - 1.0, {"position_m": [5.0, 5.0, 0.0], "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0],
                           "position_cov_m2": list(np.eye(3).reshape(-1) * 1e-4),
                           "attitude_var_rad2": [1e-4, 1e-4, 1e-4], "markers": 6, "reprojection_rms_px": 0.5})
    loop.step(2.01)   # a fix 1 s old at arrival: not fused
    assert io.rejected.get("stale_pose") == 1
    assert io.sent(schemas.POSITION_STATE)[-1][1]["position_m"][0] == pytest.approx(0.2, abs=0.02)
    # the EKF's health at 1 Hz: the delay the stamps show (50 ms), at rest nothing learnt of an offset
    health = io.sent(schemas.POSITION_EKF_HEALTH)
    assert [t for t, _ in health] == [0.01, 1.0, 2.0]
    last = health[-1][1]
    assert last["camera_delay_s"] == pytest.approx(0.05) and last["camera_delay_steps"] == 0
    assert sum(last["camera_fixes"].values()) == 40 and last["camera_fixes"]["accepted"] == 35   # the rest refused
    assert last["disturbance_m_s2"] == [0.0, 0.0]   # no wind estimation: the states held at 0
    assert not last["camera_offset_confident"]
    assert last["camera_offset_correction_s"] == 0.0 and last["camera_offset_detections"] == 0


def test_bad_parameters_are_refused_naming_the_key():
    with pytest.raises(ValueError, match="services.position.params.*state_source"):
        PositionLoop(FakeIO("position", PARAMS, {"state_source": "guess"}, rate_hz=100.0))
    with pytest.raises(ValueError, match="services.position.params.*ekf"):
        PositionLoop(FakeIO("position", PARAMS, {"ekf": {"no_such_key": 1.0}}, rate_hz=100.0))
    with pytest.raises(ValueError, match="services.position.params.*camera_delay.*window"):
        PositionLoop(FakeIO("position", PARAMS, {"camera_delay": {"window": 1}}, rate_hz=100.0))


def test_disturbance_observer_learns_holds_through_a_flip_and_resets_on_the_ground():
    # the vehicle pitched 0.05 rad (its thrust pushing to +x) and not moving: something pulls it
    # back with (T / m) sin(0.05), and the observer's estimate comes to that within 3 s (3 rad/s)
    io, loop = truth_loop(disturbance_bandwidth_rad_s=3.0)
    truths, planner = io.received(schemas.TRUTH, "sim"), io.received(schemas.PLANNER_SETPOINT, "planner")
    tilted = {**truth([0.0, 0.0, 1.0]), "quaternion_wxyz": list(quat_from_euler(0.0, 0.05, 0.0))}

    def step(t, phase="hold", mode="position", armed=True):
        truths.push(t, tilted)
        planner.push(t, setpoint([0.0, 0.0, 1.0], phase=phase, mode=mode, armed=armed))
        loop.step(t)

    for i in range(300):
        step(0.01 * i)
    d = loop.observer.d
    pull = -loop.thrust_n / X250.mass_kg * np.sin(0.05)
    assert d[0] == pytest.approx(pull, rel=0.02) and abs(d[1]) < 1e-9
    _, sp = io.sent(schemas.POSITION_SETPOINT)[-1]
    assert sp["attitude_ref_rad"][1] > 0.04   # the feed-forward: pitched on against the pull
    for i in range(300, 350):
        step(0.01 * i, phase="flip")
    assert loop.observer.d == d   # a flip's phases: held
    step(3.5, mode="idle", armed=False)
    assert loop.observer.d == (0.0, 0.0)


def test_the_camera_delay_fit_waits_for_the_thrust_scale_to_settle():
    """The delay's regressor is the model's velocity: while the EKF still learns the thrust scale
    (a vehicle heavier than its file, in its first seconds of flight) the fit waits, and it takes
    up again once the scale has held within THRUST_SCALE_SETTLED for a second."""
    from services.position import THRUST_SCALE_SETTLED
    loop = PositionLoop(FakeIO("position", PARAMS, {}, rate_hz=100.0))
    assert not loop.thrust_scale_settled(0.0, 1.0)   # no second of history yet
    assert [loop.thrust_scale_settled(n * 0.05, 1.0) for n in range(1, 21)][-1]
    assert not loop.thrust_scale_settled(1.05, 1.0 - 2 * THRUST_SCALE_SETTLED)   # learning
    held = {round(1.05 + n * 0.05, 2): loop.thrust_scale_settled(1.05 + n * 0.05, 0.98) for n in range(1, 30)}
    assert not any(ok for t, ok in held.items() if t <= 2.0)   # the scale before the step still within the last second
    assert all(ok for t, ok in held.items() if t >= 2.05)      # then settled at the learnt scale


def test_no_state_and_so_no_mission_before_the_attitude_level_estimates():
    """As PX4's pre-arm "estimator not ready": the planner arms at the first state, and in real
    time this level starts before the simulator and the attitude level run."""
    io = FakeIO("position", PARAMS, {}, rate_hz=100.0)
    loop = PositionLoop(io)
    io.received(schemas.PLANNER_SETPOINT, "planner").push(0.0, setpoint([0.0, 0.0, 1.0]))
    for n in range(1, 11):
        loop.step(n / 100)
    assert not io.sent(schemas.POSITION_STATE) and not io.sent(schemas.POSITION_SETPOINT)
    _attitude_runs(io, 0.05)   # older than attitude_timeout_s at the next run: not yet
    loop.step(0.11)
    assert not io.sent(schemas.POSITION_STATE)
    _attitude_runs(io, 0.115)
    loop.step(0.12)
    assert io.sent(schemas.POSITION_STATE)[-1][1]["position_m"] == pytest.approx([0.0, 0.0, 0.0], abs=1e-6)
