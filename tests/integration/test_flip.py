"""The flip of 001 through the whole stack (issue 5): lockstep, the project's iLQR, on truth
state (the ablation) and on the stack's own estimates (the default cascade, the attitude
level's gyro carrier through the inversion).

The figures are those of the pure closed loop on the same plant (bench/flip_sim.py,
project config at 100 Hz: altitude loss 0 m, drift 0.23 m, overshoot 12 deg,
recovery 0.43 s, duration 1.9 s) with a margin for the stack's transport delays
(one tick per hop) and its state taken from pos/state and att/state (on truth, seed 0:
0 m / 0.23 m / 12 deg / 0.42 s / 1.9 s, the climb peaking 1.6 m above the start).
"""

import json
from pathlib import Path

import pytest

from schemas import REASONS

from .conftest import TRUTH_STATE, fly

pytestmark = pytest.mark.integration

MISSION = str(Path(__file__).resolve().parent / "missions" / "flip-short.toml")
FROM_HOVER_MISSION = str(Path(__file__).resolve().parent / "missions" / "flip-short-baseline-from-hover.toml")


@pytest.fixture(scope="module")
def flip_lockstep(tmp_path_factory):
    out = tmp_path_factory.mktemp("flip-lockstep")
    return out, fly(out, MISSION, *TRUTH_STATE, plots=True)


def test_project_flip_completes_within_the_pure_loops_figures(flip_lockstep):
    out, (proc, m) = flip_lockstep
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert m["completed"] and not m["crashed"] and m["vehicle"] == "q820", proc.stdout
    f = m["flip"]
    assert f["completed"] and not f["aborted"] and f["method"] == "ilqr-project", f
    assert f["altitude_loss_m"] <= 0.5, f  # 0 m (the bench: 0)
    assert f["xy_drift_m"] <= 0.27, f      # 0.23 m (the bench: 0.23)
    assert 6.0 < f["max_altitude_m"] < 7.0, f  # the climb before the turn (target 1.5 m above)
    assert f["overshoot_deg"] < 20.0, f
    assert f["recovery_s"] <= 0.5, f
    assert f["duration_s"] < 2.4, f
    # the MPC ran at its rate, every solve usable, the motors never fell back
    assert f["plan_rate_hz"] == pytest.approx(100.0, rel=0.02), f
    assert f["failed_solves"] == 0 and f["solves"] > 200, f
    assert f["motor_fallbacks"] == {}, f
    assert m["rates_hz"]["planner"] == pytest.approx(100.0, rel=0.01)
    assert m["max_tilt_deg"] < 30.0  # outside the flip
    assert all(not set(r) & set(REASONS) for r in m["rejected_messages"].values())
    assert (out / "flip.png").stat().st_size > 10_000
    assert "NaN" not in (out / "metrics.json").read_text()


def test_flip_lockstep_is_deterministic(flip_lockstep, tmp_path):
    out, (_, first) = flip_lockstep
    _, again = fly(tmp_path, MISSION, *TRUTH_STATE, "--processes")   # as the one-process flight, too
    again_json = json.loads((tmp_path / "metrics.json").read_text())
    assert again == again_json
    # the solve times are wall-clock measurements: everything else must match bit for bit
    for m in (first, again):
        for k in ("solve_ms_p50", "solve_ms_p99", "solve_ms_max", "overrun_solves"):
            m["flip"].pop(k)
    assert again["flip"] == first["flip"]
    for k in ("position_rms_m", "max_tilt_deg", "duration_s", "completed"):
        assert again[k] == first[k], k


@pytest.fixture(scope="module")
def flown_on_estimates(tmp_path_factory):
    """fly_once(method, seed) -> (proc, metrics) of the flip mission on the stack's estimates,
    each flight flown once per module (the baseline comparison reuses the project's seed 0)."""
    flights = {}

    def fly_once(method: str, seed: int):
        if (method, seed) not in flights:
            out = tmp_path_factory.mktemp(f"flip-{method}-{seed}")
            flights[method, seed] = out, fly(out, MISSION, "--set", f"planner.flip_method={method}", seed=seed)
        return flights[method, seed]
    return fly_once


@pytest.mark.parametrize("seed", [0, 1])
def test_project_flip_meets_the_issue_targets_on_estimates(flown_on_estimates, seed):
    """The default estimators: the attitude filter (gyro-bias state, acceleration reference)
    hands over to the gyro-carried quaternion past 45 deg / 6 rad/s and takes back near level;
    the position EKF pins the attitude past 60 deg and predicts through the camera's ~0.5 s
    without markers, on the mean rotor force of every motor command. Issue 5's targets on two
    seeds (seeds 0 / 1 fly 0 / 0 m of altitude loss, 0.205 / 0.225 m drift, recovery
    0.40 / 0.41 s): altitude loss <= 0.5 m (the issue's aim; its target is 1.0 m), XY drift
    <= 0.27 m, recovery <= 0.5 s."""
    out, (proc, m) = flown_on_estimates("ilqr-project", seed)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert m["completed"] and not m["crashed"], proc.stdout
    f = m["flip"]
    assert f["completed"] and not f["aborted"] and not f["hit_ground"], f
    assert f["altitude_loss_m"] <= 0.5, f
    assert f["recovery_s"] <= 0.5, f
    assert f["xy_drift_m"] <= 0.27, f
    assert f["overshoot_deg"] < 20.0, f
    assert f["failed_solves"] == 0 and f["motor_fallbacks"] == {}, f
    # the attitude was pinned (not fused) in the position EKF through the inversion, and the
    # estimates stayed close to the truth over the flight
    assert m["rejected_messages"]["position"].get("attitude_pinned_tilted", 0) > 10, m["rejected_messages"]
    assert m["estimation"]["attitude_rms_deg"] < 5.0 and m["estimation"]["position_rms_m"] < 0.1, m["estimation"]
    assert "NaN" not in (out / "metrics.json").read_text()


def test_baseline_flip_flies_through_the_stack_and_the_project_loses_at_most_half_its_height(
        flown_on_estimates):
    """Appendix И's baseline, a selectable flip method of the same stack: full thrust from the
    5 m hover to 6 m, 6 rad/s of roll at thrust 0.25 until 315 deg, recovery thrust 0.6. On the
    q820 (thrust/weight 3.2) it reaches the roll climbing at ~6.5 m/s and loses no height at
    all (seed 0: 0.00 m, peak 10.8 m, drift 2.1 m); the project's flip climbs 1.5 m before its
    turn and loses none either, so "at most half the baseline's" holds as 0 <= 0."""
    _, (proc, base) = flown_on_estimates("baseline", 0)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert base["completed"] and not base["crashed"], proc.stdout
    b = base["flip"]
    assert b["completed"] and b["method"] == "baseline", b
    assert b["recovery_s"] <= 0.6 and b["overshoot_deg"] < 20.0, b
    _, (_, project) = flown_on_estimates("ilqr-project", 0)
    p = project["flip"]
    assert p["altitude_loss_m"] <= 0.5 * b["altitude_loss_m"] + 1e-9, (p, b)
    assert p["xy_drift_m"] < 0.5 * b["xy_drift_m"], (p, b)


def test_baseline_rolled_from_the_hover_falls_and_the_project_loses_less_than_half_of_that(
        flown_on_estimates, tmp_path):
    """The same comparison from the same 5 m hover: the baseline without its full-thrust climb
    (the mission's baseline_climb_m = 0) rolls at thrust 0.25, has no lift for ~1 s of turn and
    falls to the ground (seed 0: 5.0 m lost, as on 20 seeds of bench/flip_stack.py), where
    the project's flip loses none; even measured from its turn's start the project's loses
    0.38 m (bench/flip_heights.py), under half of that fall."""
    proc, base = fly(tmp_path, FROM_HOVER_MISSION, seed=0)
    b = base["flip"]
    assert b["method"] == "baseline", b
    assert b["altitude_loss_m"] > 2.0, b
    _, (_, project) = flown_on_estimates("ilqr-project", 0)
    p = project["flip"]
    assert p["completed"] and p["altitude_loss_m"] <= 0.5 * b["altitude_loss_m"], (p, b)


def test_project_flip_completes_on_estimates_10_percent_heavier(tmp_path):
    """The plant is 10 % heavier than the airframe file says (the services are not told): the
    position EKF learns the thrust scale in the hover before the flip, the laws and the motor
    driver divide the collective by it, and the flip completes (seed 0: 0 m / 0.22 m /
    14 deg / 0.42 s; with the 1 m climb of before 0.54 m / 0.20 m / 24 deg / 0.51 s). Without the thrust-scale state the vehicle held 0.15 m low and the flip
    never started, or, started, crashed."""
    proc, m = fly(tmp_path, MISSION, "--set", "sim.mass_scale=1.1")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert m["completed"] and not m["crashed"], proc.stdout
    f = m["flip"]
    assert f["completed"] and not f["aborted"] and not f["hit_ground"], f
    assert f["altitude_loss_m"] < 1.5 and f["xy_drift_m"] < 1.5 and f["recovery_s"] < 2.5, f
    assert m["estimation"]["thrust_scale_final"] == pytest.approx(1 / 1.1, abs=0.03), m["estimation"]


def test_a_flip_predicted_to_lose_more_than_the_height_available_is_refused_before_it_starts(tmp_path):
    """The planner predicts each flip item at start-up (flight/control/predict.py, 256 rollouts); asked
    to keep 4.98 m of a 5 m hover clear of the ground, the flip's predicted 95th-percentile loss
    does not fit: the item is refused with that reason and never started, and the vehicle holds
    where it was."""
    proc, m = fly(tmp_path, MISSION, "--set", "planner.flip_clearance_m=4.98")
    log = (tmp_path / "logs" / "planner.log").read_text()
    assert "refused: predicted 95th-percentile altitude loss" in log, log
    assert not m["completed"] and not m["crashed"], m
    f = m["flip"]
    assert f["refused"] and not f["completed"] and f["solves"] == 0, f
    assert m["max_tilt_deg"] < 15, m
