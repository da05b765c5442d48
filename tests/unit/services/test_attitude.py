"""The attitude level's logic (services/attitude.py AttitudeLoop) without a router."""

import math

import numpy as np
import pytest

import schemas
from flight.control.laws import attitude_law, stopping_accel
from flight.quat import quat_from_euler
from flight.vehicle import load_vehicle
from services.attitude import PARAMS, AttitudeLoop
from tests.unit.services.fake_io import FakeIO, defaults

DEFAULT = defaults(PARAMS)

X250 = load_vehicle("x250")
HOVER_N = X250.mass_kg * X250.gravity_m_s2


def truth(t, roll=0.0, pitch=0.0, yaw=0.0, rate=(0.0, 0.0, 0.0)):
    return {"position_m": [0.0, 0.0, 1.0], "velocity_m_s": [0.0, 0.0, 0.0],
            "quaternion_wxyz": list(quat_from_euler(roll, pitch, yaw)), "rate_rad_s": list(rate),
            "acceleration_m_s2": [0.0, 0.0, 0.0], "motor_thrust_n": [HOVER_N / 4] * 4,
            "wind_m_s": [0.0, 0.0, 0.0], "landed": False}


def truth_loop(**params):
    io = FakeIO("attitude", PARAMS, {"state_source": "truth", **params})
    return io, AttitudeLoop(io)


def test_truth_source_commands_law_8_and_passes_the_thrust_on():
    io, loop = truth_loop()
    io.received(schemas.TRUTH, "sim").push(1.0, truth(1.0, roll=0.1, rate=(0.2, 0.0, 0.0)))
    io.received(schemas.POSITION_SETPOINT, "position").push(1.0, {"attitude_ref_rad": [0.0, 0.05, 0.0],
                                                                   "thrust_n": HOVER_N})
    loop.step(1.0)
    [(t, cmd)] = io.sent(schemas.ATTITUDE_COMMAND)
    expected = attitude_law(X250.inertia_kg_m2, [0.1, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.05, 0.0],
                            np.array(DEFAULT["k"]), np.array(DEFAULT["alpha"]),
                            stopping_accel(X250.max_angular_accel_rad_s2, DEFAULT["stopping_accel_fraction"]))
    assert t == 1.0 and cmd["thrust_n"] == pytest.approx(HOVER_N) and cmd["imu_t_s"] == 1.0
    np.testing.assert_allclose(cmd["torque_nm"], expected, rtol=1e-9, atol=1e-12)
    [(_, state)] = io.sent(schemas.ATTITUDE_STATE)
    np.testing.assert_allclose(state["euler_ref_rad"], [0.0, 0.05, 0.0])
    assert io.rejected == {}


def test_a_new_gain_from_param_set_applies_from_the_next_step():
    io, loop = truth_loop()
    io.received(schemas.TRUTH, "sim").push(1.0, truth(1.0, roll=0.1))
    io.received(schemas.POSITION_SETPOINT, "position").push(1.0, {"attitude_ref_rad": [0.0, 0.0, 0.0],
                                                                   "thrust_n": HOVER_N})
    loop.step(1.0)
    io.set_param("k", [8.0, 8.0, 8.0])
    loop.step(1.0)
    first, second = (np.array(c["torque_nm"]) for _, c in io.sent(schemas.ATTITUDE_COMMAND))
    assert abs(second[0]) < abs(first[0])   # a softer gain: less torque for the same roll error


def test_no_command_before_any_setpoint_and_none_on_stale_state():
    io, loop = truth_loop()
    io.received(schemas.TRUTH, "sim").push(1.0, truth(1.0))
    loop.step(1.0)
    assert io.sent(schemas.ATTITUDE_COMMAND) == [] and len(io.sent(schemas.ATTITUDE_STATE)) == 1
    io.received(schemas.POSITION_SETPOINT, "position").push(1.2, {"attitude_ref_rad": [0.0, 0.0, 0.0],
                                                                   "thrust_n": HOVER_N})
    loop.step(1.2)   # the newest truth is 0.2 s old: past state_timeout_s
    loop.step(1.205)
    assert io.sent(schemas.ATTITUDE_COMMAND) == []
    assert io.rejected == {"stale_state": 1}   # once per sample, not per run


def test_lost_setpoints_in_the_air_descend_then_hand_back():
    io, loop = truth_loop()
    truths, setpoints = io.received(schemas.TRUTH, "sim"), io.received(schemas.POSITION_SETPOINT, "position")
    io.received(schemas.POSITION_STATE, "position").push(1.0, {
        "position_m": [0.0, 0.0, 1.0], "velocity_m_s": [0.0, 0.0, 0.0], "position_ref_m": [0.0, 0.0, 1.0],
        "position_cov_m2": [0.0] * 9, "acceleration_m_s2": [0.0, 0.0, 0.0], "state_source": "truth",
        "thrust_scale": 1.0})
    truths.push(1.0, truth(1.0))
    setpoints.push(1.0, {"attitude_ref_rad": [0.0, 0.0, 0.3], "thrust_n": HOVER_N})
    loop.step(1.0)
    truths.push(1.5, truth(1.5))
    loop.step(1.5)   # setpoint 0.5 s old: the failsafe levels and descends
    _, cmd = io.sent(schemas.ATTITUDE_COMMAND)[-1]
    assert 0.0 < cmd["thrust_n"] <= HOVER_N
    assert io.rejected.get("failsafe_engaged") == 1 and "failsafe" in io.problems[-1]
    _, state = io.sent(schemas.ATTITUDE_STATE)[-1]
    assert list(state["euler_ref_rad"][:2]) == [0.0, 0.0]   # level, the yaw kept
    setpoints.push(1.5, {"attitude_ref_rad": [0.0, 0.0, 0.0], "thrust_n": HOVER_N})
    loop.step(1.5)
    assert io.rejected.get("failsafe_recovered") == 1 and io.sent(schemas.ATTITUDE_COMMAND)[-1][1]["thrust_n"] == HOVER_N


def test_the_estimate_converges_level_from_imu_samples_at_rest():
    io = FakeIO("attitude", PARAMS, {"camera_level": False, "compensate_acceleration": False})
    loop = AttitudeLoop(io)
    imu = io.received(schemas.IMU, "sim")
    for n in range(1, 801):   # 2 s at 400 Hz, a run every second sample
        imu.push(n / 400, {"gyro_rad_s": [0.0, 0.0, 0.0], "accel_m_s2": [0.0, 0.0, X250.gravity_m_s2]})
        if n % 2 == 0:
            loop.step(n / 400)
    _, state = io.sent(schemas.ATTITUDE_STATE)[-1]
    assert all(math.isfinite(v) for v in state["euler_rad"])
    assert max(abs(v) for v in state["euler_rad"][:2]) < math.radians(0.1)


@pytest.mark.parametrize("params, key", [({"stopping_accel_fraction": 2.0}, "stopping_accel_fraction"),
                                         ({"estimator": "nonesuch"}, "estimator"),
                                         ({"accel_window_s": 0.0}, "accel_window_s"),
                                         ({"carrier": {"enter_tilt_deg": "x"}}, "carrier")])
def test_bad_parameters_are_refused_naming_the_key(params, key):
    with pytest.raises(ValueError, match=f"services.attitude.params.*{key}"):
        AttitudeLoop(FakeIO("attitude", PARAMS, params))


def test_restarted_mid_flight_no_command_until_its_filter_has_settled():
    io = FakeIO("attitude", PARAMS, {"state_source": "truth", "restart_settle_s": 0.5}, restarted=True)
    loop = AttitudeLoop(io)
    truths, setpoints = io.received(schemas.TRUTH, "sim"), io.received(schemas.POSITION_SETPOINT, "position")
    for k in range(12):   # 0.55 s of samples and setpoints from t = 1.0
        t = 1.0 + 0.05 * k
        truths.push(t, truth(t))
        setpoints.push(t, {"attitude_ref_rad": [0.0, 0.0, 0.0], "thrust_n": HOVER_N})
        loop.step(t)
    sent = [t for t, _ in io.sent(schemas.ATTITUDE_COMMAND)]
    assert sent and min(sent) == pytest.approx(1.5), sent   # from the first sample + restart_settle_s
    assert len(io.sent(schemas.ATTITUDE_STATE)) == 12 and "restarted: commands from t=1.500" in io.problems[0]


# ---------------------------------------------------------------- the gyro-vertical's parameter file
GV = {"estimator": "gyro-vertical"}


def gyrovertical_of(loop):
    return loop.make_gyrovertical([1.0, 0.0, 0.0, 0.0]).params


@pytest.mark.parametrize("vehicle, file, compensated", [("q820", "gyrovertical_q820_compensated.toml", True),
                                                       ("x250", "gyrovertical_x250_mems.toml", False)])
def test_each_vehicle_flies_the_gyrovertical_file_its_airframe_names(vehicle, file, compensated):
    """q820.toml names the file trained on q820 flights with the acceleration compensation (flown with it);
    the x250 keeps the one it flew before (without)."""
    from flight.estimation.gyrovertical import load_trained
    from flight.vehicle import PARAMS_DIR
    loop = AttitudeLoop(FakeIO("attitude", PARAMS, GV, vehicle=vehicle))
    assert load_vehicle(vehicle).gyrovertical_params == file
    trained = load_trained(PARAMS_DIR / file)
    assert gyrovertical_of(loop) == trained.adaptive
    assert loop.gv_compensated is compensated
    # compensated, the file's [fallback] for samples without a reference (the q820's: its uncompensated file's)
    assert loop.make_gyrovertical([1.0, 0.0, 0.0, 0.0]).fallback == (trained.fallback if compensated else None)
    if compensated:
        assert trained.fallback == load_trained(PARAMS_DIR / "gyrovertical_q820_mems.toml").adaptive
        off = AttitudeLoop(FakeIO("attitude", PARAMS, {**GV, "gyrovertical_compensation": "none"}, vehicle=vehicle))
        assert gyrovertical_of(off) == trained.fallback   # flown without: the uncompensated filter


def test_the_services_gyrovertical_params_overrides_the_airframes():
    from flight.estimation.gyrovertical import PAPER_PARAMS_FILE, load_trained
    loop = AttitudeLoop(FakeIO("attitude", PARAMS, {**GV, "gyrovertical_params": str(PAPER_PARAMS_FILE)},
                               vehicle="q820"))
    assert gyrovertical_of(loop) == load_trained(PAPER_PARAMS_FILE).adaptive
    assert gyrovertical_of(loop) != load_trained(load_vehicle("q820").gyrovertical_params_path).adaptive


def test_a_bad_gyrovertical_file_named_by_the_airframe_is_refused_naming_both(tmp_path, monkeypatch):
    from flight import vehicle as vehicle_module
    from flight.vehicle import VEHICLES_DIR
    monkeypatch.setattr(vehicle_module, "PARAMS_DIR", tmp_path)
    (tmp_path / "broken.toml").write_text("[adaptive]\npitch_var0 = 'x'\n")
    frame = tmp_path / "frame.toml"
    frame.write_text((VEHICLES_DIR / "q820.toml").read_text().replace("gyrovertical_q820_compensated.toml", "broken.toml"))
    with pytest.raises(ValueError, match=r"vehicle q820's gyrovertical_params: .*broken\.toml: .*pitch_var0"):
        AttitudeLoop(FakeIO("attitude", PARAMS, GV, vehicle=str(frame)))
    frame.write_text((VEHICLES_DIR / "q820.toml").read_text().replace("gyrovertical_q820_compensated.toml", "nonesuch.toml"))
    with pytest.raises(ValueError, match=r"vehicle q820's gyrovertical_params: .*nonesuch\.toml: cannot read"):
        AttitudeLoop(FakeIO("attitude", PARAMS, GV, vehicle=str(frame)))
    AttitudeLoop(FakeIO("attitude", PARAMS, {}, vehicle=str(frame)))   # kalman-000 never opens it


# ---------------------------------------------------------------- the gyro-vertical's acceleration compensation
def pos_state(v=(0.0, 0.0, 0.0)):
    return {"position_m": [0.0, 0.0, 1.0], "velocity_m_s": list(v), "position_ref_m": [0.0, 0.0, 1.0],
            "position_cov_m2": [0.0] * 9, "acceleration_m_s2": [0.0, 0.0, 0.0], "state_source": "estimate",
            "thrust_scale": 1.0}


def fly_at_rest(io, loop, t_from, t_to, pos_until=None):
    """IMU at 400 Hz (a run every second sample), pos/state at 100 Hz until pos_until; the
    gyro-vertical's compensated flag after each run."""
    imu, pos = io.received(schemas.IMU, "sim"), io.received(schemas.POSITION_STATE, "position")
    flags = []
    for n in range(round(t_from * 400), round(t_to * 400) + 1):
        t = n / 400
        if n % 4 == 0 and (pos_until is None or t <= pos_until):
            pos.push(t, pos_state())
        imu.push(t, {"gyro_rad_s": [0.0, 0.0, 0.0], "accel_m_s2": [0.0, 0.0, X250.gravity_m_s2]})
        if n % 2 == 0:
            loop.step(t)
            flags.append((t, loop.gyrovertical.compensated))
    return flags


def test_the_compensated_gyrovertical_takes_the_position_levels_velocity_and_falls_back_without_it():
    io = FakeIO("attitude", PARAMS, {**GV, "gyrovertical_compensation": "window", "camera_level": False})
    loop = AttitudeLoop(io)
    assert loop.gv_compensated and loop.motion is not None
    flags = fly_at_rest(io, loop, 0.0025, 1.0, pos_until=0.5)
    on = [t for t, c in flags if c]
    # from its first full window (0.1 s of pos/state kept) to 0.25 s after the last pos/state
    assert on and min(on) < 0.2 and 0.7 < max(on) <= 0.76 and all(not c for t, c in flags if t > 0.76)
    _, state = io.sent(schemas.ATTITUDE_STATE)[-1]
    assert all(math.isfinite(v) for v in state["euler_rad"]) and max(map(abs, state["euler_rad"][:2])) < 0.01


def test_without_pos_state_the_compensated_gyrovertical_is_the_accelerometers():
    io = FakeIO("attitude", PARAMS, {**GV, "gyrovertical_compensation": "window", "camera_level": False})
    loop = AttitudeLoop(io)
    flags = fly_at_rest(io, loop, 0.0025, 0.5, pos_until=-1.0)
    assert not any(c for _, c in flags)
    plain_io = FakeIO("attitude", PARAMS, {**GV, "gyrovertical_compensation": "none", "camera_level": False})
    plain = AttitudeLoop(plain_io)
    assert not plain.gv_compensated and plain.motion is None
    fly_at_rest(plain_io, plain, 0.0025, 0.5, pos_until=-1.0)
    assert io.sent(schemas.ATTITUDE_STATE) == plain_io.sent(schemas.ATTITUDE_STATE)


def test_by_default_the_file_says_whether_the_gyrovertical_is_compensated(tmp_path):
    from flight.estimation.gyrovertical import PAPER_PARAMS_FILE
    text = PAPER_PARAMS_FILE.read_text()
    assert "compensation" not in text   # trained without it: flown without it
    assert not AttitudeLoop(FakeIO("attitude", PARAMS, {**GV, "gyrovertical_params": str(PAPER_PARAMS_FILE)})).gv_compensated
    f = tmp_path / "comp.toml"
    f.write_text(text.replace("[meta]\n", '[meta]\ncompensation = "window"\n'))
    assert AttitudeLoop(FakeIO("attitude", PARAMS, {**GV, "gyrovertical_params": str(f)})).gv_compensated
    assert not AttitudeLoop(FakeIO("attitude", PARAMS, {**GV, "gyrovertical_params": str(f),
                                                        "gyrovertical_compensation": "none"})).gv_compensated
    f.write_text(text.replace("[meta]\n", '[meta]\ncompensation = "slope"\n'))
    with pytest.raises(ValueError, match=r"gyrovertical_params: .*comp\.toml: \[meta\] compensation .*'slope'"):
        AttitudeLoop(FakeIO("attitude", PARAMS, {**GV, "gyrovertical_params": str(f)}))
    with pytest.raises(ValueError, match="services.attitude.params.*gyrovertical_compensation"):
        AttitudeLoop(FakeIO("attitude", PARAMS, {**GV, "gyrovertical_compensation": "slope"}))
