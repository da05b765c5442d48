"""A plan's lead over a link (flight/control/lead.py): the state predicted to the plan's start."""

import numpy as np
import pytest

from flight.control.ilqr import PROJECT, ILQRSolver, feedback_control, hover_state
from flight.control.lead import make_lead_predictor, plan_feedback_jnp
from flight.control.plan import plan_feedback
from flight.quat import quat_multiply
from flight.vehicle import load_vehicle
from simulator.plant import Plant

Q820 = load_vehicle("q820")
TICK_S = 1 / 400


@pytest.fixture(scope="module")
def solver():
    return ILQRSolver(Q820, PROJECT)


def _start(solver):
    """A vehicle rolling at 2 rad/s at 5 m and a plan from it to a hover 0.3 m aside."""
    plant = Plant(Q820, position_m=(0.0, 0.0, 5.0), rate_rad_s=(2.0, 0.0, 0.0),
                  motor_thrust_n=[Q820.hover_thrust_per_motor_n] * 4)
    x = np.concatenate([plant.x[:13], plant.motor_thrust_n])
    target = solver.full_state(hover_state([0.3, 0.0, 5.0]))
    plan = solver.solve(x, np.repeat(target[None], PROJECT.horizon + 1, axis=0))
    return plant, x, plan


def _fly(plant, plans, ticks):
    """The plant (2 kHz RK4, rotor-speed lag) under the driver's law, the newest plan started."""
    kf = Q820.thrust_coefficient_kf
    for k in range(ticks):
        t = k * TICK_S
        start, plan = [(s, p) for s, p in plans if s <= t + 1e-9][-1]
        x = np.concatenate([plant.x[:13], plant.motor_thrust_n])
        u = feedback_control(plan, t - start, x, Q820.max_rotor_speed_rad_s)
        for _ in range(5):
            plant.step(TICK_S / 5, kf * u * u, np.zeros(3))
    return np.concatenate([plant.x[:13], plant.motor_thrust_n])


def _angle_deg(q1, q2):
    d = quat_multiply(np.asarray(q1) * [1, -1, -1, -1], np.asarray(q2))
    return np.degrees(2 * np.arccos(min(1.0, abs(d[0]))))


def test_the_law_in_jax_is_the_drivers(solver):
    rng = np.random.default_rng(0)
    _, x, plan = _start(solver)
    for elapsed in (0.0, 0.013, 0.2, 5.0):
        xx = x + rng.normal(0, 0.05, x.shape)
        want = plan_feedback(plan.states, plan.controls, plan.gains, plan.dt_s, elapsed, xx, 2100.0)
        got = plan_feedback_jnp(plan.states.astype(np.float32), plan.controls.astype(np.float32),
                                plan.gains.astype(np.float32), np.float32(plan.dt_s), np.float32(elapsed),
                                xx.astype(np.float32), 2100.0)
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-4, atol=0.5)   # rad/s of ~1000


def test_the_prediction_flies_as_the_plant_under_the_plans_sent(solver):
    """60 ms (a link's round trip) on the model against the simulator's plant, two plans in
    flight: within a millimetre, 0.1 deg, 0.01 rad/s and 20 mN of rotor force (0.5 % of a hover's;
    float32 under a law whose gains reach thousands)."""
    plant, x, plan = _start(solver)
    later = solver.solve(x, np.repeat(solver.full_state(hover_state([0.0, 0.3, 5.2]))[None],
                                      PROJECT.horizon + 1, axis=0))
    sent = [(0.0, plan), (0.0312, later)]   # no tick on a plan step's boundary: there float32 and
    # float64 may hold the step before or after (one tick's control), the law itself ambiguous
    truth = _fly(plant, sent, 24)
    predicted = make_lead_predictor(Q820)(x, sent, 24 * TICK_S)
    assert np.linalg.norm(predicted[:3] - truth[:3]) < 1e-3
    assert _angle_deg(predicted[6:10], truth[6:10]) < 0.1
    assert np.abs(predicted[10:13] - truth[10:13]).max() < 0.01
    assert np.abs(predicted[13:] - truth[13:]).max() < 0.02
    assert np.linalg.norm(truth[10:13] - x[10:13]) > 0.5   # the rates did change: not a trivial case


def test_no_span_or_no_plan_is_the_state_itself(solver):
    _, x, plan = _start(solver)
    predict = make_lead_predictor(Q820)
    np.testing.assert_array_equal(predict(x, [(0.0, plan)], 0.0), x)
    np.testing.assert_array_equal(predict(x, [], 0.05), x)
