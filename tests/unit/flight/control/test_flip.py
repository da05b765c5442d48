"""Flip phase machine, accumulated roll, targets, metrics, baseline, closed loop."""
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from flight.control.flip import (
    BASELINE_CLIMB_M,
    BaselineConfig,
    BaselineFlip,
    FlipConfig,
    FlipPhaseMachine,
    Phase,
    RollAccumulator,
    braking_reference,
    flip_metrics,
    quat_from_roll,
)
from flight.control.ilqr import hover_state
from flight.quat import quat_from_euler, quat_to_euler
from flight.vehicle import load_vehicle

sys.path.insert(0, str(Path(__file__).resolve().parents[4]))


def state(z=5.0, roll=0.0, rates=(0.0, 0.0, 0.0), v=(0.0, 0.0, 0.0)):
    x = hover_state([0.0, 0.0, z])
    x[3:6] = v
    x[6:10] = quat_from_roll(roll)
    x[10:13] = rates
    return x


def machine_in_flip(config: FlipConfig) -> FlipPhaseMachine:
    """A phase machine (horizon 10, dt 0.1 s) that took off and started its flip at (0, 0, 5)."""
    m = FlipPhaseMachine(config, horizon=10, dt_s=0.1)
    m.start(0.0, state(z=0.0))
    m.update(0.0, state())
    return m


def machine_in_recovery(config: FlipConfig) -> FlipPhaseMachine:
    """machine_in_flip, then turned to 355 deg: in recovery."""
    m = machine_in_flip(config)
    for roll in np.linspace(0.0, 2 * math.pi - 0.05, 30):
        m.update(0.5, state(roll=roll, rates=(3.0, 0, 0)))
    assert m.phase == Phase.RECOVERY
    return m


def test_roll_accumulates_through_inversion():
    acc = RollAccumulator()
    acc.reset(quat_from_roll(0.0))
    for roll in np.linspace(0, 2 * math.pi + 0.3, 80):
        acc.update(quat_from_euler(roll, 0.02, 0.1))
    assert acc.roll_rad == pytest.approx(2 * math.pi + 0.3, abs=1e-6)


def test_phase_machine_transitions_on_feedback():
    m = FlipPhaseMachine(FlipConfig(), horizon=10, dt_s=0.1)
    m.start(0.0, state(z=0.0))
    assert m.update(0.0, state(z=2.0)) == Phase.TAKEOFF
    assert m.update(0.1, state(z=5.05, v=(0, 0, 1.0))) == Phase.TAKEOFF  # still climbing
    assert m.update(0.2, state(z=5.05)) == Phase.FLIP
    for roll in np.linspace(0.0, 2 * math.pi - 0.2, 30):
        assert m.update(0.3, state(roll=roll, rates=(6.0, 0, 0))) == Phase.FLIP
    assert m.update(0.4, state(roll=2 * math.pi - 0.05, rates=(6.0, 0, 0))) == Phase.RECOVERY
    assert m.update(0.5, state(roll=2 * math.pi + 0.02, rates=(2.0, 0, 0))) == Phase.RECOVERY  # spinning
    assert m.update(0.6, state(roll=2 * math.pi + 0.02, rates=(0.1, 0, 0))) == Phase.LAND
    assert m.update(0.7, state(z=0.1)) == Phase.DONE


def test_flip_targets_lead_the_roll_adaptively():
    config = FlipConfig()
    m = FlipPhaseMachine(config, horizon=10, dt_s=0.1)
    m.start(0.0, state(z=0.0))
    m.update(0.0, state())
    assert m.phase == Phase.FLIP
    m.update(0.5, state(roll=1.0))
    targets = m.targets(0.5, state(roll=1.0))
    assert targets.shape == (11, 13)
    error = math.pi - 1.0  # expected 2 pi * 0.5 / 1.0
    lead = (0.8 + 0.3 * math.tanh(error)) * error
    last_roll = 2 * math.atan2(targets[-2, 7], targets[-2, 6])
    assert last_roll == pytest.approx(1.0 + 0.9 * lead, abs=1e-9)
    assert targets[0, 10] == pytest.approx(2 * math.pi + 0.2 * error)
    np.testing.assert_array_equal(targets[-1], targets[-2])


def test_recovery_coast_levels_without_braking():
    """recovery_coast: the horizontal targets move on at the current velocity (nothing asks
    for a braking tilt); the altitude is the flip's, the attitude level at rest."""
    m = machine_in_recovery(FlipConfig(recovery_coast=True))
    x = state(z=4.5, roll=2 * math.pi + 0.1, rates=(1.0, 0, 0), v=(0.5, -1.0, -0.8))
    x[0:2] = (0.3, 0.2)
    targets = m.targets(0.6, x)
    k = np.arange(10) * 0.1
    np.testing.assert_allclose(targets[:10, 0], 0.3 + 0.5 * k)
    np.testing.assert_allclose(targets[:10, 1], 0.2 - 1.0 * k)
    np.testing.assert_allclose(targets[:10, 2], 5.0)
    np.testing.assert_allclose(targets[:10, 3:6], np.tile([0.5, -1.0, 0.0], (10, 1)))
    np.testing.assert_allclose(targets[:10, 10:13], 0.0)
    # without it (the thesis): hold where it is, at rest
    m.config = FlipConfig()
    held = m.targets(0.6, x)
    np.testing.assert_allclose(held[:10, 0:2], np.tile([0.3, 0.2], (10, 1)))
    np.testing.assert_allclose(held[:10, 3:6], 0.0)


def test_recovery_hold_heading_levels_at_the_current_yaw():
    """recovery_hold_heading: the recovery's targets keep the yaw the vehicle has (roll and
    pitch still go to level); without it they turn back to yaw 0 as well."""
    m = machine_in_recovery(FlipConfig(recovery_hold_heading=True))
    x = state(rates=(1.0, 0, 0.4))
    x[6:10] = quat_from_euler(0.15, 0.0, 0.2)
    for q in m.targets(0.6, x)[:10, 6:10]:
        roll, pitch, yaw = quat_to_euler(q)
        assert yaw == pytest.approx(0.2, abs=1e-9) and pitch == pytest.approx(0.0, abs=1e-9)
    m.config = FlipConfig()
    assert all(abs(quat_to_euler(q)[2]) < 1e-9 for q in m.targets(0.6, x)[:10, 6:10])


def test_braking_reference_stops_in_a_straight_line():
    t = np.array([0.0, 0.5, 1.0, 2.0, 10.0])
    p, v = braking_reference([1.0, 2.0], [0.6, -0.8], t, 0.5)   # 1 m/s, stops after 2 s, 1 m on
    direction = np.array([0.6, -0.8])
    np.testing.assert_allclose(v, np.outer([1.0, 0.75, 0.5, 0.0, 0.0], direction), atol=1e-12)
    np.testing.assert_allclose(p, [1.0, 2.0] + np.outer([0.0, 0.4375, 0.75, 1.0, 1.0], direction), atol=1e-12)
    p, v = braking_reference([1.0, 2.0], [0.0, 0.0], t, 0.5)
    np.testing.assert_allclose(p, np.tile([1.0, 2.0], (5, 1)))
    np.testing.assert_allclose(v, 0.0)


def test_settle_brakes_gently_and_turns_back_slowly():
    """The hold after recovery (the project's settle_decel_m_s2, settle_yaw_rate_rad_s): a
    straight stop from the velocity the recovery ended with, held where it stops, and the
    heading back to 0 at the set rate; without them (the thesis) hover where it recovered."""
    config = FlipConfig(settle_decel_m_s2=0.5, settle_yaw_rate_rad_s=0.25)
    m = machine_in_flip(config)   # flip from (0, 0, 5)
    x = state(z=4.6, v=(0.0, 0.5, 0.1))
    x[0:2] = (0.2, -0.1)
    x[6:10] = quat_from_euler(0.0, 0.0, 0.23)
    hold = m.settle_hold_point(3.0, x)
    np.testing.assert_allclose(hold, [0.2, -0.1 + 0.25, 5.0])   # 0.5^2 / (2 0.5) on along +y
    targets = m.settle_targets(3.4, state(z=4.8))   # later calls keep the hold's start
    k = 0.4 + np.arange(11) * 0.1
    np.testing.assert_allclose(targets[:, 1], -0.1 + np.where(k < 1.0, 0.5 * k - 0.25 * k * k, 0.25))
    np.testing.assert_allclose(targets[:, 4], np.maximum(0.5 - 0.5 * k, 0.0), atol=1e-12)
    np.testing.assert_allclose(targets[:, 0], 0.2)
    np.testing.assert_allclose(targets[:, 2], 5.0)
    yaws = np.array([quat_to_euler(q)[2] for q in targets[:, 6:10]])
    np.testing.assert_allclose(yaws, np.maximum(0.23 - 0.25 * k, 0.0), atol=1e-9)
    np.testing.assert_allclose(targets[:, 12], np.where(k < 0.92, -0.25, 0.0))
    np.testing.assert_allclose(targets[:, 10:12], 0.0)
    thesis = machine_in_flip(FlipConfig())
    np.testing.assert_allclose(thesis.settle_hold_point(3.0, x), [0.2, -0.1, 5.0])
    held = thesis.settle_targets(3.0, x)
    np.testing.assert_allclose(held, np.repeat(hover_state([0.2, -0.1, 5.0])[None], 11, axis=0))


def test_settle_moves_the_stop_on_only_while_the_vehicle_outruns_it():
    """A vehicle still speeding up when the hold starts would be asked to come back against
    its own speed: while the planned stop lasts, a farther stop from the current state moves
    it on; a vehicle braking at least as planned, or one pushed after the stop (wind), keeps it."""
    m = machine_in_flip(FlipConfig(settle_decel_m_s2=0.5))
    x = state(v=(0.0, 0.5, 0.0))
    np.testing.assert_allclose(m.settle_hold_point(3.0, x), [0.0, 0.25, 5.0])
    faster = state(v=(0.0, 0.55, 0.0))
    faster[1] = 0.06
    np.testing.assert_allclose(m.settle_hold_point(3.1, faster), [0.0, 0.06 + 0.3025, 5.0])
    targets = m.settle_targets(3.1, faster)
    assert targets[0, 1] == pytest.approx(0.06) and targets[0, 4] == pytest.approx(0.55)
    braking = state(v=(0.0, 0.3, 0.0))
    braking[1] = 0.2
    np.testing.assert_allclose(m.settle_hold_point(3.5, braking), [0.0, 0.3625, 5.0])
    pushed = state(v=(0.0, 0.4, 0.0))
    pushed[1] = 0.36
    np.testing.assert_allclose(m.settle_hold_point(5.0, pushed), [0.0, 0.3625, 5.0])   # stop over: hold


def synthetic_flip(overshoot_rad=0.3, sink_m=0.8):
    t = np.arange(0.0, 3.0, 0.0025)
    turn_end = 1.5
    roll = np.interp(t, [0.0, 0.5, turn_end, turn_end + 0.2, turn_end + 0.4],
                     [0.0, 0.0, 2 * math.pi, 2 * math.pi + overshoot_rad, 2 * math.pi])
    rates = np.zeros((len(t), 3))
    rates[:, 0] = np.gradient(roll, t)
    z = 5.0 - sink_m * np.sin(np.clip((t - 0.5) / 1.4, 0, 1) * math.pi)
    position = np.stack([np.zeros_like(t), 0.1 * np.clip(t - 0.5, 0, 1), z], axis=1)
    phase = np.where(t < 0.5, "takeoff", np.where(t < turn_end, "flip", "recovery"))
    quats = np.array([quat_from_roll(r) for r in roll])
    return t, position, quats, rates, phase


def test_flip_metrics_on_a_synthetic_series():
    m = flip_metrics(*synthetic_flip())
    assert m.completed
    assert m.altitude_loss_m == pytest.approx(0.8, abs=1e-3)
    assert m.overshoot_deg == pytest.approx(math.degrees(0.3), abs=0.2)
    assert m.xy_drift_m == pytest.approx(0.1, abs=1e-3)
    # the turn completes at 360 - 5 deg (t = 0.5 + 355/360 s); the roll is back within 5 deg
    # at 1.84 s but still turning at 1.5 rad/s until 1.9 s, when recovery ends
    assert m.recovery_s == pytest.approx(1.9 - (0.5 + 355 / 360), abs=0.01)
    assert m.duration_s == pytest.approx(1.9 - 0.5, abs=0.01)


def test_flip_metrics_without_a_flip():
    t, position, quats, rates, _ = synthetic_flip()
    m = flip_metrics(t, position, quats, rates, ["takeoff"] * len(t))
    assert not m.completed and math.isnan(m.altitude_loss_m)


def test_baseline_rolls_at_low_thrust_then_recovers():
    vehicle = load_vehicle("q820")
    ctl = BaselineFlip(vehicle)
    ctl.command(0.0, state(z=5.0))
    assert ctl.phase == Phase.FLIP and ctl.reported_phase == Phase.TAKEOFF  # climbing first
    climb = ctl.command(0.01, state(z=5.5, v=(0, 0, 2)))
    assert np.sum(climb) == pytest.approx(4 * vehicle.max_thrust_n, rel=1e-6)
    roll = ctl.command(0.02, state(z=6.1))
    assert ctl.reported_phase == Phase.FLIP
    assert roll[1] > roll[3] + 1.0  # the left rotor pushes: +x roll (thrust gives way to torque in the mixer)
    at_rate = ctl.command(0.025, state(z=6.1, roll=0.05, rates=(ctl.config.roll_rate_rad_s, 0, 0)))
    assert at_rate[1] == pytest.approx(at_rate[3], abs=1e-6)  # rate loop: no torque at the commanded rate
    for r in np.linspace(0.1, math.radians(320), 30):
        ctl.command(0.03, state(z=6.1, roll=r, rates=(6, 0, 0)))
    assert ctl.phase == Phase.RECOVERY
    braking = ctl.command(0.04, state(z=6.1, roll=math.radians(350), rates=(6, 0, 0)))
    assert braking[3] > braking[1]  # the rate set-point is below the rate: decelerate the roll



def test_baseline_hold_caps_law_8_as_the_attitude_service_does():
    """The baseline's own hold (waiting to be calm before the flip, and after it) asks law (8)
    for no more rate than the q820's rotors can stop, as the stack's attitude service: a 30 deg
    roll error gets less roll torque than law (8) as printed (which saturated the q820's hold
    into a limit cycle that the mixer's collective shift turned into a climb to 138 m), a 2 deg
    one exactly law (8)'s. At 30 deg, already turning back at 3 rad/s, law (8) as printed still
    accelerates the turn with all the rotors have; capped, it almost coasts: 3.1 rad/s is what
    half the q820's angular acceleration can stop over the 30 deg."""
    vehicle = load_vehicle("q820")
    capped, printed = BaselineFlip(vehicle), BaselineFlip(vehicle, BaselineConfig(stopping_accel_fraction=0.0))
    for roll_deg, rate, same in ((30.0, -3.0, False), (2.0, 0.0, True)):
        x = state(z=3.0, roll=math.radians(roll_deg), rates=(rate, 0.0, 0.0))  # take-off, below the hover altitude
        a, b = capped.command(0.0, x), printed.command(0.0, x)
        torque_a, torque_b = a[1] - a[3], b[1] - b[3]
        if same:
            assert torque_a == pytest.approx(torque_b, rel=1e-9)
        else:
            assert abs(torque_a) < 0.3 * abs(torque_b)

@pytest.mark.timeout(60)
def test_closed_loop_baseline_completes():
    from bench.flip_sim import simulate_baseline
    m = simulate_baseline(load_vehicle("q820")).metrics
    assert m.completed and m.overshoot_deg < 20.0 and m.recovery_s <= 0.6


@pytest.mark.timeout(120)
def test_closed_loop_project_flip_meets_targets():
    """Slow (~15-25 s): take-off, flip and recovery of the PROJECT MPC on the simulator plant.

    At 50 Hz re-solve (the bench runs 100 Hz): 0 m / 0.24 m / 0.41 s (100 Hz: 0 / 0.23 /
    0.43), the climb (PROJECT_FLIP.climb_m) peaking ~1.6 m above the start. Drift is the
    lateral impulse of the rolling rotor pair (see PROJECT's horizontal weights)."""
    from bench.flip_sim import PROJECT_FLIP, PROJECT_SOLVE_RATE_HZ, simulate_mpc
    from flight.control.ilqr import PROJECT, ILQRSolver
    vehicle = load_vehicle("q820")
    run = simulate_mpc(vehicle, ILQRSolver(vehicle, PROJECT), PROJECT_FLIP, PROJECT_SOLVE_RATE_HZ / 2)
    m = run.metrics
    assert m.completed
    assert max(p[2] for p in run.position_m) >= 5.0 - 0.1
    assert m.altitude_loss_m <= 0.5
    assert m.xy_drift_m <= 0.27
    assert m.recovery_s <= 0.5


def test_flip_phase_targets_the_climb_and_recovery_the_start_altitude():
    c = FlipConfig(lookahead=True, flip_duration_s=0.9, windup_s=0.3, climb_m=1.0)
    m = FlipPhaseMachine(c, horizon=8, dt_s=0.05)
    m.start(0.0, state(z=0.0))
    assert m.update(1.0, state(z=5.02)) == Phase.FLIP
    np.testing.assert_allclose(m.targets(1.0, state(z=5.02))[:, 2], 6.02)
    m.phase = Phase.RECOVERY
    np.testing.assert_allclose(m.targets(2.0, state(z=5.9))[:, 2], 5.02)


def test_flip_reference_winds_up_then_turns():
    from flight.control.flip import flip_reference
    c = FlipConfig(lookahead=True, flip_duration_s=0.9, windup_rad=0.3, windup_s=0.3)
    roll, rate = flip_reference(np.array([0.0, 0.15, 0.3, 0.3 + 0.45, 0.3 + 0.9, 2.0]), c)
    np.testing.assert_allclose(roll, [0.0, -0.3, 0.0, math.pi, 2 * math.pi, 2 * math.pi], atol=1e-9)
    assert rate[1] == pytest.approx(0.0, abs=1e-9) and rate[3] > 0 and rate[-1] == 0.0


def test_thesis_take_off_checks_the_altitude_only():
    from flight.control.flip import THESIS_FLIP
    m = FlipPhaseMachine(THESIS_FLIP, horizon=10, dt_s=0.1)
    m.start(0.0, state(z=0.0))
    assert m.update(0.1, state(z=5.05, v=(0, 0, 1.0))) == Phase.FLIP


def _fly_baseline_item(climb_m: float = BASELINE_CLIMB_M, max_s: float = 12.0):
    """The planner service's baseline flip item (FlipController) from a 5 m hover on the truth
    plant, its controller at 200 Hz: yields (t_s, step, plant) at every controller step."""
    from bench.flip_sim import _plant_command, _tick, SIM
    from flight.control.flip_runner import FlipController
    from simulator.plant import Plant
    vehicle = load_vehicle("q820")
    hover = vehicle.hover_thrust_per_motor_n
    plant = Plant(vehicle, position_m=(0.0, 0.0, 5.0), motor_thrust_n=np.full(4, hover))
    ctrl = FlipController(vehicle, "baseline")
    ctrl.start(0.0, plant.x[:13], 5.0, baseline_climb_m=climb_m)
    kf = vehicle.thrust_coefficient_kf
    forces = np.full(4, hover)
    for tick in range(int(max_s * SIM.tick_rate_hz)):
        t = tick / SIM.tick_rate_hz
        if tick % 2 == 0:  # 200 Hz
            step = ctrl.step(t, plant.x[:13], settle_s=0.5, solve=True)
            yield t, step, plant
            forces = kf * np.asarray(step.plan["controls_rad_s"]) ** 2
        _tick(plant, SIM, _plant_command(vehicle, forces))


def test_baseline_flip_item_hands_back_after_recovery():
    """The flip item of the planner service with the baseline ends (done) once the vehicle is
    calm where the baseline holds after recovery: that is above the item's altitude (it climbs
    1 m to roll), so settling towards the item's altitude never ended (flip-aborted)."""
    phases = set()
    for t, step, plant in _fly_baseline_item():
        phases.add(step.phase)
        if step.done:
            break
    assert {"flip", "recovery", "settle"} <= phases
    assert step.done, f"not handed back after {t:.1f} s (z {plant.position_m[2]:.2f} m)"
    assert plant.position_m[2] > 5.0


@pytest.mark.parametrize("climb_m", [1.0, 0.0])
def test_baseline_needs_its_climb_to_keep_its_height(climb_m):
    """Appendix И's fixed sequence rolls at low thrust: ~1 s of the turn without lift. With its
    full-thrust climb first (1 m, the default) it reaches the roll fast enough to rise through
    it; rolled from the hover (baseline_climb_m 0) it falls metres (on the stack: to the ground
    from 5 m). Truth plant, no noise, the planner service's FlipController."""
    lowest_m = 5.0
    for _, step, plant in _fly_baseline_item(climb_m, max_s=4.0):
        lowest_m = min(lowest_m, plant.position_m[2])
        if step.phase == "settle":  # recovered
            break
    assert step.phase == "settle"
    if climb_m > 0:
        assert lowest_m > 5.0 - 0.01
    else:
        assert lowest_m < 5.0 - 2.0, lowest_m


def test_stopping_point_is_braking_reference_at_rest_to_rounding():
    """stopping_point computes in floats; braking_reference at t = inf is its definition (the
    same to the last bits: numpy's SIMD kernels round differently on some CPUs)."""
    from flight.control.flip import braking_reference, stopping_point
    rng = np.random.default_rng(4)
    for i in range(20000):
        start, v = rng.normal(size=3) * 3, rng.normal(size=2) * 10 ** rng.uniform(-10, 1)
        decel = (0.5, 1.0, float(rng.uniform(0.1, 3)))[i % 3]
        expected = braking_reference(start, v, [np.inf], decel)[0][0]
        np.testing.assert_allclose(stopping_point(start, v, decel), expected, rtol=1e-14, atol=1e-15)
    assert stopping_point(np.array([1.0, 2.0, 3.0]), np.zeros(2), 0.5).tolist() == [1.0, 2.0]
