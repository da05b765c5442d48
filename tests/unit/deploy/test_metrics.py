import json
import math

import numpy as np
import pytest
from scipy.optimize import brentq

from deploy.metrics import compute_metrics, format_table, step_response
from deploy.plots import make_plots
from flight.quat import quat_from_euler
from schemas.flightlog import read_log, write_log

INFO = {"mission": "test", "mode": "lockstep", "seed": 7, "vehicle": "x250"}
P = "zp/0/"


# --------------------------------------------------------------------------- builders

def hdr(t, seq, source):
    return {"t_s": float(t), "seq": int(seq), "source": source}


def truth(t, seq, pos, roll=0.0, pitch=0.0, yaw=0.0, landed=False, thrust=(2.0, 2.0, 2.0, 2.0)):
    return {"version": 1, "header": hdr(t, seq, "sim"),
            "position_m": [float(v) for v in pos], "velocity_m_s": [0.0] * 3,
            "quaternion_wxyz": [float(v) for v in quat_from_euler(roll, pitch, yaw)],
            "rate_rad_s": [0.0] * 3, "acceleration_m_s2": [0.0] * 3,
            "motor_thrust_n": [float(v) for v in thrust], "wind_m_s": [0.0] * 3, "landed": bool(landed)}


def setpoint(t, seq, mode="position", pos=(0.0, 0.0, 1.0), att=(0.0, 0.0, 0.0), measure=False,
             state="running", item=0, phase="hold"):
    return {"version": 1, "header": hdr(t, seq, "planner"), "mode": mode, "armed": mode != "idle",
            "position_m": [float(v) for v in pos], "attitude_rad": [float(v) for v in att],
            "item": item, "phase": phase, "measure": bool(measure), "mission_state": state}


def health(t, seq, service, state="running", rate=100.0, rejected=None):
    return {"version": 1, "header": hdr(t, seq, service), "state": state, "rate_hz": float(rate),
            "target_rate_hz": 100.0, "overruns": 0, "jitter_p99_ms": 0.1,
            "rejected": dict(rejected or {}), "detail": ""}


def pwm(t, seq, imu_t, armed=True):
    return {"version": 1, "header": hdr(t, seq, "motors"), "pwm_us": [1500.0, 1510.0, 1490.0, 1505.0],
            "thrust_n": [2.0] * 4, "armed": armed, "saturated": False, "imu_t_s": float(imu_t)}


def att_state(t, seq, roll, pitch, ref, source="truth"):
    return {"version": 1, "header": hdr(t, seq, "attitude"),
            "quaternion_wxyz": [float(v) for v in quat_from_euler(roll, pitch, 0.0)],
            "euler_rad": [roll + (0.01 if source == "estimate" else 0.0), pitch, 0.0],
            "rate_rad_s": [0.0] * 3, "euler_ref_rad": [float(v) for v in ref], "state_source": source}


def pos_state(t, seq, pos, ref, source="truth"):
    return {"version": 1, "header": hdr(t, seq, "position"),
            "position_m": [float(v) + (0.02 if source == "estimate" else 0.0) for v in pos],
            "velocity_m_s": [0.0] * 3, "position_ref_m": [float(v) for v in ref], "state_source": source}


def hover_log():
    """Hover at (1, 2, 3); measured segment 1 s <= t < 3 s with a constant 0.05 m error,
    1 m error elsewhere (must not count)."""
    ref = np.array([1.0, 2.0, 3.0])
    tr, sp = [], []
    for k in range(401):  # truth 100 Hz, 0..4 s
        t = k / 100
        measured = 1.0 <= t < 3.0
        off = np.array([0.03, 0.04, 0.0]) if measured else np.array([0.0, 0.0, 1.0])
        tr.append(truth(t, k, ref + off))
    for j in range(201):  # planner 50 Hz
        t = j / 50
        sp.append(setpoint(t, j, pos=ref, measure=1.0 <= t < 3.0,
                           state="completed" if j == 200 else "running"))
    return {P + "sim/truth": tr, P + "planner/setpoint": sp}


def assert_json_clean(m):
    json.dumps(m, allow_nan=False)


# --------------------------------------------------------------------------- tests

def test_hover_position_rms_exact_and_basic_fields():
    m = compute_metrics(hover_log(), INFO)
    assert_json_clean(m)
    assert m["position_rms_m"] == pytest.approx(0.05, abs=1e-12)
    assert m["max_position_error_m"] == pytest.approx(0.05, abs=1e-12)
    assert m["duration_s"] == pytest.approx(4.0)
    assert m["completed"] is True
    assert {k: m[k] for k in INFO} == INFO
    assert m["attitude_steps"] == [] and m["position_steps"] == []
    assert m["attitude_settle_s_max"] is None and m["position_step_settle_s_max"] is None
    assert m["latency_ms"]["imu_to_pwm_p50"] is None


def test_position_rms_none_without_measured_samples():
    log = hover_log()
    for s in log[P + "planner/setpoint"]:
        s["measure"] = False
    m = compute_metrics(log, INFO)
    assert m["position_rms_m"] is None and m["max_position_error_m"] is None
    # measure True but attitude mode does not count either
    for s in log[P + "planner/setpoint"]:
        s["measure"], s["mode"] = True, "attitude"
    assert compute_metrics(log, INFO)["position_rms_m"] is None


def test_completed_flag_uses_last_setpoint_by_time():
    log = hover_log()
    sp = log[P + "planner/setpoint"]
    assert compute_metrics(log, INFO)["completed"] is True
    sp.append(setpoint(5.0, 999, state="failed"))
    assert compute_metrics(log, INFO)["completed"] is False
    log[P + "planner/setpoint"] = []
    assert compute_metrics(log, INFO)["completed"] is False


TAU_ROLL = 0.1
ZETA, WN = 0.5, 10.0


def second_order(tau):
    """Unit step response of wn^2 / (s^2 + 2 zeta wn s + wn^2), zeta < 1."""
    if tau <= 0:
        return 0.0
    wd = WN * math.sqrt(1 - ZETA**2)
    phi = math.acos(ZETA)
    return 1 - math.exp(-ZETA * WN * tau) / math.sqrt(1 - ZETA**2) * math.sin(wd * tau + phi)


def attitude_log():
    """Position mode until 0.5 s; attitude mode after: roll 0 -> 10 deg at 1 s (first order,
    tau 0.1 s); pitch 0 -> -5 deg at 3 s (second order, zeta 0.5, wn 10); end 6 s."""
    d2r = math.pi / 180
    tr, sp = [], []
    for k in range(6001):  # truth 1 kHz
        t = k / 1000
        roll = 10 * d2r * (1 - math.exp(-(t - 1) / TAU_ROLL)) if t > 1 else 0.0
        pitch = -5 * d2r * second_order(t - 3)
        tr.append(truth(t, k, (0, 0, 2), roll=roll, pitch=pitch))
    for j in range(301):  # planner 50 Hz
        t = j / 50
        mode = "position" if t < 0.5 else "attitude"
        att = (10 * d2r if t >= 1 else 0.0, -5 * d2r if t >= 3 else 0.0, 0.0)
        sp.append(setpoint(t, j, mode=mode, pos=(0, 0, 2), att=att))
    return {P + "sim/truth": tr, P + "planner/setpoint": sp}



def test_attitude_steps_are_timed_where_the_attitude_level_gets_the_reference():
    """Entering attitude mode, the setpoint reaches the attitude level 15 ms late (planner ->
    position -> attitude) and the vehicle was rolling away from it meanwhile: the step is the
    loop's response from the reference's arrival and the angle flown then; the setpoint-timed
    figure stays beside it."""
    d2r, delay = math.pi / 180, 0.015
    tr, sp, att = [], [], []
    for k in range(3001):  # truth 1 kHz: drifting to -0.5 deg until the reference arrives
        t = k / 1000
        arrive = 1.0 + delay
        roll = (-0.5 * (t - 0.9) / (arrive - 0.9) if 0.9 < t <= arrive else 0.0) if t <= arrive else \
            -0.5 + 10.5 * (1 - math.exp(-(t - arrive) / TAU_ROLL))
        tr.append(truth(t, k, (0, 0, 2), roll=roll * d2r))
    for j in range(151):  # planner 50 Hz: position hold, then attitude mode with roll 10 deg at 1 s
        t = j / 50
        sp.append(setpoint(t, j, mode="position" if t < 1.0 else "attitude", pos=(0, 0, 2),
                           att=(10 * d2r if t >= 1 else 0.0, 0.0, 0.0)))
    for j in range(601):  # attitude level 200 Hz
        t = j / 200
        att.append({"version": 1, "header": hdr(t, j, "attitude"),
                    "euler_ref_rad": [10 * d2r if t >= 1.0 + delay - 1e-9 else 0.0, 0.0, 0.0],
                    "state_source": "truth"})
    log = {P + "sim/truth": tr, P + "planner/setpoint": sp}
    roll_from_setpoint = compute_metrics(log, INFO)["attitude_steps"][0]
    assert roll_from_setpoint["reference_delay_s"] is None

    log[P + "att/state"] = att
    m = compute_metrics(log, INFO)
    assert_json_clean(m)
    (roll,) = m["attitude_steps"]
    assert roll["t_s"] == pytest.approx(1.0) and roll["reference_delay_s"] == pytest.approx(delay)
    assert roll["from_deg"] == pytest.approx(-0.5, abs=1e-6) and roll["monotone"] is True
    assert roll["settle_s"] == pytest.approx(TAU_ROLL * math.log(20), abs=1e-3)
    assert roll["command_settle_s"] == roll_from_setpoint["settle_s"]
    assert roll["command_settle_s"] > roll["settle_s"] + delay - 1e-3
    assert m["attitude_settle_s_max"] == roll["settle_s"]
    assert m["attitude_command_settle_s_max"] == roll["command_settle_s"]

def test_entering_attitude_mode_an_axis_left_level_is_no_step():
    """The hold flies pitched 1.8 deg (the position law's own correction) when the attitude item
    starts with roll 10, pitch 0: the roll is a step, the pitch's return to level is not."""
    d2r = math.pi / 180
    tr, sp = [], []
    for k in range(3001):
        t = k / 1000
        roll = 10 * d2r * (1 - math.exp(-(t - 1) / TAU_ROLL)) if t > 1 else 0.0
        pitch = 1.8 * d2r * (math.exp(-(t - 1) / TAU_ROLL) if t > 1 else 1.0)
        tr.append(truth(t, k, (0, 0, 2), roll=roll, pitch=pitch))
    for j in range(151):
        t = j / 50
        sp.append(setpoint(t, j, mode="position" if t < 1.0 else "attitude", pos=(0, 0, 2),
                           att=(10 * d2r if t >= 1 else 0.0, 0.0, 0.0)))
    steps = compute_metrics({P + "sim/truth": tr, P + "planner/setpoint": sp}, INFO)["attitude_steps"]
    assert [s["axis"] for s in steps] == ["roll"]


def test_attitude_steps_match_analytic_responses():
    m = compute_metrics(attitude_log(), INFO)
    assert_json_clean(m)
    steps = m["attitude_steps"]
    assert [s["axis"] for s in steps] == ["roll", "pitch"]
    roll, pitch = steps

    assert roll["t_s"] == pytest.approx(1.0)
    assert roll["from_deg"] == pytest.approx(0.0) and roll["to_deg"] == pytest.approx(10.0)
    assert roll["rise_s"] == pytest.approx(TAU_ROLL * math.log(9), abs=1e-3)
    assert roll["settle_s"] == pytest.approx(TAU_ROLL * math.log(20), abs=1e-3)
    assert roll["overshoot_pct"] == pytest.approx(0.0, abs=1e-9)
    assert roll["monotone"] is True

    # second order: reference values from the closed form
    t10 = brentq(lambda x: second_order(x) - 0.1, 1e-9, 0.2)
    t90 = brentq(lambda x: second_order(x) - 0.9, 1e-9, 0.3)
    grid = np.arange(0, 3, 1e-5)
    out = np.nonzero(np.abs(np.array([second_order(x) for x in grid]) - 1) > 0.05)[0][-1]
    t_settle = brentq(lambda x: abs(second_order(x) - 1) - 0.05, grid[out], grid[out + 1])
    overshoot = 100 * math.exp(-ZETA * math.pi / math.sqrt(1 - ZETA**2))

    assert pitch["t_s"] == pytest.approx(3.0)
    assert pitch["from_deg"] == pytest.approx(0.0) and pitch["to_deg"] == pytest.approx(-5.0)
    assert pitch["rise_s"] == pytest.approx(t90 - t10, abs=1e-3)
    assert pitch["overshoot_pct"] == pytest.approx(overshoot, abs=0.01)
    assert pitch["settle_s"] == pytest.approx(t_settle, abs=1e-3)
    assert pitch["monotone"] is True

    assert m["attitude_rise_s_max"] == pytest.approx(max(roll["rise_s"], pitch["rise_s"]))
    assert m["attitude_overshoot_pct_max"] == pytest.approx(pitch["overshoot_pct"])
    assert m["attitude_settle_s_max"] == pytest.approx(max(roll["settle_s"], pitch["settle_s"]))
    assert m["attitude_steps_unsettled"] == 0


def test_step_response_non_monotone_and_unsettled():
    t = np.linspace(0, 1, 1001)
    s = np.interp(t, [0, 0.2, 0.3, 0.6, 1.0], [0, 0.5, 0.4, 1.0, 1.0])  # dips by 0.1 before 90 %
    r = step_response(t, s, 0.0, 0.0, 1.0)
    assert r["monotone"] is False
    assert r["settle_s"] == pytest.approx(0.6 - 0.05 / 2.0, abs=1e-6)  # slope 2 /s
    r = step_response(t, 0.5 * t, 0.0, 0.0, 1.0)  # never reaches 90 %
    assert r["rise_s"] is None and r["settle_s"] is None and r["overshoot_pct"] == 0.0


TAU_X, TAU_Y = 0.3, 0.2


def position_log():
    """On the ground until 0.5 s; z reference jumps 0 -> 1 m while landed (ignored);
    airborne x step 0 -> 1 m at 3 s (tau 0.3 s) and y step 0 -> -0.5 m at 6 s (tau 0.2 s)."""
    tr, sp = [], []
    for k in range(8001):
        t = k / 1000
        z = 1 - math.exp(-(t - 0.5) / 0.2) if t > 0.5 else 0.0
        x = 1 - math.exp(-(t - 3) / TAU_X) if t > 3 else 0.0
        y = -0.5 * (1 - math.exp(-(t - 6) / TAU_Y)) if t > 6 else 0.0
        tr.append(truth(t, k, (x, y, z), landed=z < 0.02))
    for j in range(401):
        t = j / 50
        ref = (1.0 if t >= 3 else 0.0, -0.5 if t >= 6 else 0.0, 1.0 if t >= 0.5 else 0.0)
        sp.append(setpoint(t, j, pos=ref, phase="goto"))
    return {P + "sim/truth": tr, P + "planner/setpoint": sp}


def test_position_steps_only_airborne():
    m = compute_metrics(position_log(), INFO)
    assert_json_clean(m)
    steps = m["position_steps"]
    assert [s["axis"] for s in steps] == ["x", "y"]
    x, y = steps
    assert x["t_s"] == pytest.approx(3.0) and x["from_m"] == 0.0 and x["to_m"] == 1.0
    assert x["rise_s"] == pytest.approx(TAU_X * math.log(9), abs=1e-3)
    assert x["settle_s"] == pytest.approx(TAU_X * math.log(20), abs=1e-3)
    assert x["overshoot_pct"] == pytest.approx(0.0, abs=1e-9)
    assert y["to_m"] == -0.5
    assert y["rise_s"] == pytest.approx(TAU_Y * math.log(9), abs=1e-3)
    assert y["settle_s"] == pytest.approx(TAU_Y * math.log(20), abs=1e-3)
    assert m["position_step_settle_s_max"] == pytest.approx(TAU_X * math.log(20), abs=1e-3)
    assert m["position_step_overshoot_pct_max"] == pytest.approx(0.0, abs=1e-9)


def test_latency_percentiles():
    msgs = [pwm(0.0, 0, -1.0), pwm(0.1, 1, 0.0, armed=False)]  # neither counts
    lat_ms = np.arange(1, 101, dtype=float)
    for i, lat in enumerate(lat_ms):
        t = 1.0 + i * 0.01
        msgs.append(pwm(t, i + 2, t - lat / 1000))
    m = compute_metrics({P + "motors/pwm": msgs}, INFO)
    assert_json_clean(m)
    assert m["latency_ms"]["imu_to_pwm_p50"] == pytest.approx(np.percentile(lat_ms, 50), abs=1e-6)
    assert m["latency_ms"]["imu_to_pwm_p99"] == pytest.approx(np.percentile(lat_ms, 99), abs=1e-6)
    assert m["latency_ms"]["samples"] == 100
    assert m["duration_s"] is None and m["position_rms_m"] is None


def test_latency_from_the_first_output_of_each_sample():
    # 400 Hz outputs from 200 Hz commands: every command is mixed at once (1 ms after its IMU
    # sample), then again 2.5 ms later; the latency is the first, the second is an output's age
    msgs = []
    for i in range(100):
        imu_t = 1.0 + 0.005 * i
        msgs += [pwm(imu_t + 0.001, 2 * i, imu_t), pwm(imu_t + 0.0035, 2 * i + 1, imu_t)]
    m = compute_metrics({P + "motors/pwm": msgs}, INFO)
    assert m["latency_ms"]["samples"] == 100
    assert m["latency_ms"]["imu_to_pwm_p99"] == pytest.approx(1.0, abs=1e-6)
    assert m["latency_ms"]["imu_to_pwm_max"] == pytest.approx(1.0, abs=1e-6)
    assert m["latency_ms"]["output_age_p99"] == pytest.approx(3.5, abs=1e-6)


def test_rates_and_rejected_from_health():
    att = [health(0, 0, "attitude", "starting", 0.0),
           health(1, 1, "attitude", rate=199.0),
           health(2, 2, "attitude", "degraded", rate=20.0),  # not running: left out
           health(3, 3, "attitude", rate=201.0),
           health(4, 4, "attitude", "stopping", 50.0, {"wrong_type": 3, "out_of_range": 1})]
    plan = [health(0, 0, "planner", rate=1000.0), health(1, 1, "planner", rate=50.0),
            health(2, 2, "planner", rate=1000.0, rejected={"malformed": 2})]
    rec = [health(0, 0, "recorder", rate=5.0)]  # only one message: nothing left
    m = compute_metrics({P + "attitude/health": att, P + "planner/health": plan,
                         P + "recorder/health": rec, "zp/1/sim/health": rec}, INFO)
    assert_json_clean(m)
    assert m["rates_hz"] == {"attitude": pytest.approx(200.0), "planner": pytest.approx(50.0), "recorder": None}
    assert m["rejected_messages"] == {"attitude": {"wrong_type": 3, "out_of_range": 1},
                                      "planner": {"malformed": 2}, "recorder": {}}
    assert m["rejected_total"] == 6
    table = format_table(m)
    assert "service attitude" in table and "wrong_type=3" in table


def test_format_table_lists_scalars_and_steps():
    m = compute_metrics(attitude_log(), INFO)
    table = format_table(m)
    assert "position_rms_m" in table and "duration_s" in table
    assert "attitude_step roll @ 1.00 s" in table and "attitude_step pitch @ 3.00 s" in table


def full_log(source="truth"):
    log = attitude_log()
    tr = log[P + "sim/truth"]
    log[P + "att/state"] = [att_state(m["header"]["t_s"], i, 0.0, 0.0, (0.1, 0.0, 0.0), source)
                            for i, m in enumerate(tr[::5])]
    log[P + "pos/state"] = [pos_state(m["header"]["t_s"], i, m["position_m"], (0, 0, 2), source)
                            for i, m in enumerate(tr[::10])]
    log[P + "motors/pwm"] = [pwm(m["header"]["t_s"], i, m["header"]["t_s"] - 0.002) for i, m in enumerate(tr[::5])]
    log[P + "attitude/health"] = [health(t, t, "attitude", rate=200.0) for t in range(6)]
    return log


def test_make_plots_writes_pngs(tmp_path):
    paths = make_plots(full_log(), tmp_path / "truth")
    assert sorted(p.name for p in paths) == ["attitude.png", "motors.png", "position.png"]
    for p in paths:
        assert p.exists() and p.stat().st_size > 1000
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    paths = make_plots(full_log("estimate"), tmp_path / "est")
    assert "estimation.png" in [p.name for p in paths]
    assert all(p.stat().st_size > 1000 for p in paths)


def test_make_plots_skips_missing_topics(tmp_path):
    assert make_plots({}, tmp_path) == []
    paths = make_plots({P + "motors/pwm": [pwm(0.0, 0, 0.0), pwm(0.01, 1, 0.005)]}, tmp_path)
    assert [p.name for p in paths] == ["motors.png"]


def test_flightlog_round_trip_keeps_metrics(tmp_path):
    log = full_log()
    records = sorted(((k, m) for k, msgs in log.items() for m in msgs), key=lambda r: r[1]["header"]["t_s"])
    path = tmp_path / "flight.mcap"
    assert write_log(path, records) == len(records)
    back = read_log(path)
    assert back == log
    assert compute_metrics(back, INFO) == compute_metrics(log, INFO)


def test_crash_is_seen_from_the_truth_not_the_planner():
    log = hover_log()
    m = compute_metrics(log, INFO)
    assert m["crashed"] is False and m["max_tilt_deg"] < 1e-6
    # the truth sits on the ground during a hold while the planner (on estimates) says completed
    log[P + "sim/truth"][150] = truth(1.5, 150, (1.0, 2.0, 0.0), landed=True)
    m = compute_metrics(log, INFO)
    assert m["completed"] and m["crashed"]
    log = hover_log()
    log[P + "sim/truth"][10] = truth(0.1, 10, (1.0, 2.0, 3.0), roll=math.radians(70))
    m = compute_metrics(log, INFO)
    assert m["crashed"] and m["max_tilt_deg"] == pytest.approx(70.0)


def test_the_flight_ends_when_the_simulator_stops():
    # in real time the services go on publishing while the stack winds down after the
    # simulator stopped: those outputs are not the flight's
    imu = [{"version": 1, "header": hdr(1.0 + 0.0025 * i, i, "sim"), "gyro_rad_s": [0.0] * 3,
            "accel_m_s2": [0.0, 0.0, 9.8]} for i in range(400)]   # up to t = 2.0
    msgs = [pwm(1.0 + 0.005 * i + 0.001, i, 1.0 + 0.005 * i) for i in range(200)]
    msgs += [pwm(4.0 + 0.005 * i, 200 + i, 2.0) for i in range(50)]   # 2 s later, on the last sample
    m = compute_metrics({P + "sim/imu": imu, P + "motors/pwm": msgs}, INFO)
    assert m["latency_ms"]["samples"] == 200
    assert m["latency_ms"]["output_age_p99"] == pytest.approx(1.0, abs=1e-6)


def test_a_disarm_or_motor_cut_in_the_air_is_a_crash_whatever_the_planner_says():
    # the planner was told to disarm at 2 s and says "completed"; the truth falls from 3 m
    log = hover_log()
    out = [pwm(k / 400, k, k / 400) for k in range(1600)]
    log[P + "motors/pwm"] = out
    m = compute_metrics(log, INFO)
    assert m["crashed"] is False and m["crash_reason"] is None
    for k in range(800, 1600):
        out[k] = {**pwm(k / 400, k, k / 400, armed=False), "thrust_n": [0.0] * 4}
    m = compute_metrics(log, INFO)
    assert m["completed"] and m["crashed"] and m["crash_reason"].startswith("motors cut in the air at t=2.00")
    # armed, but the mixer asks for no thrust at all (attitude commanded zero): a cut too
    for k in range(800, 1600):
        out[k] = {**pwm(k / 400, k, k / 400), "thrust_n": [0.0] * 4}
    assert compute_metrics(log, INFO)["crashed"]
    # a disarm on the ground after a landing is not
    log = hover_log()
    for k in range(300, 401):
        log[P + "sim/truth"][k] = truth(k / 100, k, (1.0, 2.0, 0.0), landed=True)
    log[P + "planner/setpoint"] = [setpoint(j / 50, j, phase="hold" if j < 140 else "landed",
                                            state="completed" if j == 200 else "running") for j in range(201)]
    log[P + "motors/pwm"] = [pwm(k / 400, k, k / 400, armed=k < 1250) for k in range(1600)]
    m = compute_metrics(log, INFO)
    assert not m["crashed"], m["crash_reason"]


def test_a_hard_touchdown_is_a_crash():
    def landing(speed):
        tr = []
        for k in range(301):
            t = k / 100
            z = max(0.0, 1.0 - speed * max(0.0, t - 1.0))
            rec = truth(t, k, (0.0, 0.0, z), landed=z == 0.0)
            rec["velocity_m_s"] = [0.0, 0.0, -speed if 0.0 < z < 1.0 else 0.0]
            tr.append(rec)
        sp = [setpoint(j / 50, j, phase="land", state="completed" if j == 150 else "running") for j in range(151)]
        return compute_metrics({P + "sim/truth": tr, P + "planner/setpoint": sp}, INFO)
    soft, hard = landing(0.5), landing(4.0)
    assert soft["touchdown_speed_m_s"] == pytest.approx(0.5) and not soft["crashed"]
    assert hard["touchdown_speed_m_s"] == pytest.approx(4.0) and hard["crashed"]
    assert hard["crash_reason"] == "touchdown at 4.00 m/s"
