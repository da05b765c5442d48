"""Failsafes on the vehicle (issue 22, items 3-4): a service killed or frozen mid-hover, in
lockstep, judged on the simulator's truth: the vehicle lands gently (or holds), never falls.

The lockstep clock drops a killed participant (its liveliness token goes), so the others fly
on and the failsafe of the level below acts: attitude gone -> the motor driver levels and
descends; position gone -> the attitude level does; planner gone -> position holds, then lands;
vision gone -> the EKF coasts, then the attitude level lands."""

import pytest

from .conftest import ROOT
from .faults import TRUTH_STATE, fly_with_fault

pytestmark = pytest.mark.integration
# the fault 5 s into a hover with a 6 s hold (hover-fault.toml: in the hold from 4.7 s)
AT = dict(at_s=5.0, mission=str(ROOT / "tests" / "integration" / "missions" / "hover-fault.toml"))

GENTLE_M_S = 1.0     # touchdown speed of a controlled descent (0.5 m/s sink; a fall from 1 m: 4.4 m/s)
LEVEL_DEG = 15.0


def assert_no_stale_command_acted_on(log, bound_s=0.05 + 0.0025):
    """Every armed motor output came from an IMU sample at most the command bound (and a tick) old
    (log: the flight's, as fly_with_fault read it)."""
    pwm = [x for x in log["zp/0/motors/pwm"] if x["armed"] and x["imu_t_s"] >= 0]
    worst = max(x["header"]["t_s"] - x["imu_t_s"] for x in pwm)
    assert worst <= bound_s, worst


def assert_landed_gently(m, within_s):
    f = m["fault"]
    assert f["injected_at_s"] is not None and f["altitude_m"] > 0.8, f   # it was hovering
    assert not m["crashed"], m["crash_reason"]
    assert f["landed_at_end"] and f["ground_after_s"] is not None and f["ground_after_s"] < within_s, f
    assert m["touchdown_speed_m_s"] < GENTLE_M_S
    assert m["max_tilt_deg"] < LEVEL_DEG
    assert f["max_altitude_after_m"] < f["altitude_m"] + 0.3   # no climb away


def test_attitude_killed_the_motor_driver_lands(tmp_path):
    kept = {}
    m = fly_with_fault(tmp_path, "attitude", "kill", **AT, settings=TRUTH_STATE, keep=kept)
    assert_landed_gently(m, within_s=6.0)
    assert_no_stale_command_acted_on(kept["log"])
    assert m["failsafes"]["motors"]["failsafe_engaged"] == 1 and m["failsafes"]["motors"]["failsafe_landed"] == 1
    assert m["failsafes"]["sim"] == {"lockstep_dropped_attitude": 1}


def test_attitude_killed_on_the_estimates(tmp_path):
    m = fly_with_fault(tmp_path, "attitude", "kill", **AT, settings=("sim.max_duration_s=17",))
    assert_landed_gently(m, within_s=6.0)


def test_position_killed_the_attitude_level_lands(tmp_path):
    m = fly_with_fault(tmp_path, "position", "kill", **AT, settings=TRUTH_STATE + ("sim.max_duration_s=17",))
    assert_landed_gently(m, within_s=6.0)
    assert m["failsafes"]["attitude"]["failsafe_engaged"] == 1
    assert "motors" not in m["failsafes"] or "failsafe_engaged" not in m["failsafes"]["motors"]


def test_planner_killed_position_holds_then_lands(tmp_path):
    m = fly_with_fault(tmp_path, "planner", "kill", **AT, settings=TRUTH_STATE + ("sim.max_duration_s=19",))
    # held 5 s (planner_loss_land_after_s) where it was, then landed
    assert_landed_gently(m, within_s=10.0)
    assert m["fault"]["ground_after_s"] > 5.0
    assert m["failsafes"]["position"]["planner_lost"] == 1


def test_vision_killed_the_ekf_coasts_then_lands(tmp_path):
    m = fly_with_fault(tmp_path, "vision", "kill", **AT, settings=("sim.max_duration_s=19",))
    assert_landed_gently(m, within_s=10.0)
    assert m["fault"]["ground_after_s"] > 3.0   # coasted vision_timeout_s first
    assert m["failsafes"]["position"]["vision_lost"] == 1


# Real time: a frozen (SIGSTOP) service. On a quiet machine the runtime holds its rates; on a
# loaded one these flights are not a valid measure of anything but "it did not fall".

@pytest.mark.realtime
def test_attitude_frozen_2s_real_time_the_motor_driver_covers_and_hands_back(tmp_path):
    kept = {}
    m = fly_with_fault(tmp_path, "attitude", "stop", **AT, stop_s=2.0, lockstep=False, settings=TRUTH_STATE, keep=kept)
    f = m["fault"]
    assert not m["crashed"], m["crash_reason"]
    assert f["min_altitude_soon_m"] > 0.2, f            # descending slowly, not falling (fault + 5 s)
    assert m["failsafes"]["motors"]["failsafe_engaged"] >= 1
    assert m["failsafes"]["motors"]["failsafe_recovered"] >= 1   # fresh commands took over again
    assert m["completed"]
    assert_no_stale_command_acted_on(kept["log"])


@pytest.mark.realtime
def test_position_frozen_2s_real_time_the_attitude_level_covers(tmp_path):
    m = fly_with_fault(tmp_path, "position", "stop", **AT, stop_s=2.0, lockstep=False, settings=TRUTH_STATE)
    f = m["fault"]
    assert not m["crashed"], m["crash_reason"]
    assert f["min_altitude_soon_m"] > 0.2, f
    assert m["failsafes"]["attitude"]["failsafe_engaged"] >= 1
    assert m["completed"]
