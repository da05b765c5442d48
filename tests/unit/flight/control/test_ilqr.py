"""iLQR behaviour: model, cost, convergence, gains, warm start, compile-once."""
import dataclasses
import itertools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from flight.control.ilqr import (
    THESIS,
    _backward_pass,
    _solve_spd,
    ILQRSolver,
    attitude_error_sq_rad2,
    feedback_control,
    hover_rotor_speed_rad_s,
    hover_state,
    PROJECT,
    make_cost,
    make_cost_derivatives,
    make_dynamics,
    solver_compiler_options,
    warm_start,
)
from flight.motor_model import thrust_step
from flight.quat import quat_from_euler
from flight.vehicle import load_vehicle

VEHICLE = load_vehicle("q820")


@pytest.fixture(scope="module")
def planner():
    return ILQRSolver(VEHICLE, THESIS)


@pytest.fixture(scope="module")
def solver_for():
    """One ILQRSolver per distinct config in this module (compiled at its first solve): tests
    that ask for the same config share it instead of tracing and compiling it again. Configs
    that differ only in max_iterations or relative_tolerance are one program (the stops are its
    arguments), loaded from the run's compilation cache after the first."""
    built = {}

    def get(config):
        if config not in built:
            built[config] = ILQRSolver(VEHICLE, config, warm_up=False)
        return built[config]
    return get


def test_hover_is_an_equilibrium_of_both_integrators():
    x = jnp.asarray(hover_state([1.0, 2.0, 5.0]))
    u = jnp.full(4, hover_rotor_speed_rad_s(VEHICLE))
    for integrator in ("euler", "rk4"):
        np.testing.assert_allclose(make_dynamics(VEHICLE, 0.1, integrator)(x, u), x, atol=1e-5)


def test_roll_torque_sign_matches_vehicle_allocation():
    """Rotor 2 (left, +y) faster rolls right-side down: +x body rate (FLU)."""
    u = jnp.full(4, hover_rotor_speed_rad_s(VEHICLE)).at[1].add(100.0)
    x1 = make_dynamics(VEHICLE, 0.02, "rk4")(jnp.asarray(hover_state([0, 0, 5])), u)
    assert x1[10] > 0 and abs(x1[11]) < 1e-6


@pytest.mark.parametrize("q", [quat_from_euler(0.3, -0.2, 1.0), quat_from_euler(3.0, 0.1, 0.0)])
def test_attitude_error_zero_at_q_and_minus_q_with_finite_gradient(q):
    q = jnp.asarray(q, jnp.float32)
    grad, hessian = jax.jit(jax.grad(attitude_error_sq_rad2)), jax.jit(jax.hessian(attitude_error_sq_rad2))
    for target in (q, -q):  # jitted as the solver runs them: a compile each, not one per operation
        assert float(attitude_error_sq_rad2(q, target)) == pytest.approx(0.0, abs=1e-6)
        g = grad(q, target)
        h = hessian(q, target)
        assert np.all(np.isfinite(g)) and np.all(np.isfinite(h))


def test_attitude_error_is_the_rotation_angle():
    for angle in (0.01, 0.5, 2.0, 3.0):
        e2 = attitude_error_sq_rad2(jnp.asarray(quat_from_euler(angle, 0, 0)), jnp.array([1.0, 0, 0, 0]))
        assert np.sqrt(float(e2)) == pytest.approx(angle, rel=5e-3)  # float32 near 0


def test_solver_cost_decreases_monotonically_with_iterations(planner, solver_for):
    x0 = hover_state([0.3, -0.2, 4.5])
    targets = np.repeat(hover_state([0, 0, 5])[None], THESIS.horizon + 1, axis=0)
    costs = []
    for iterations in range(1, 6):
        p = solver_for(dataclasses.replace(THESIS, max_iterations=iterations, relative_tolerance=0.0))
        costs.append(p.solve(x0, targets).cost)
    initial = planner.solve(x0, targets).initial_cost
    assert costs[0] < initial
    assert all(b <= a + 1e-6 * a for a, b in itertools.pairwise(costs))


def test_gains_of_the_last_pass_or_of_the_returned_plan(solver_for):
    """gains_at_returned_plan=False returns the last backward pass's gains: those of the plan
    the last line search started from, i.e. what one iteration fewer with the refresh gives
    (the refresh pass linearises at the plan it returns, with the same regularisation)."""
    x0 = hover_state([1.0, -0.5, 4.0])
    x0[6:10] = quat_from_euler(0.4, -0.2, 0.0)
    targets = np.repeat(hover_state([0, 0, 5])[None], THESIS.horizon + 1, axis=0)

    def solve(iterations, refresh):
        config = dataclasses.replace(THESIS, max_iterations=iterations, relative_tolerance=0.0,
                                     gains_at_returned_plan=refresh)
        return solver_for(config).solve(x0, targets)
    last_pass, refreshed_before, refreshed = solve(3, False), solve(2, True), solve(3, True)
    scale = np.abs(refreshed.gains).max()
    assert np.abs(last_pass.gains - refreshed_before.gains).max() <= 1e-6 * scale
    np.testing.assert_array_equal(last_pass.controls, refreshed.controls)  # same plan either way
    assert np.abs(last_pass.gains - refreshed.gains).max() > 1e-5 * scale  # not the same gains (close: iLQR converges)


def test_converges_to_hover_thrust_from_a_perturbed_state(planner):
    x0 = hover_state([0.2, -0.1, 4.8])
    x0[6:10] = quat_from_euler(0.1, -0.05, 0.0)
    targets = np.repeat(hover_state([0, 0, 5])[None], THESIS.horizon + 1, axis=0)
    plan = planner.solve(x0, targets)
    for _ in range(150):  # receding horizon on the model itself (the thesis's weights are slow)
        x0 = np.asarray(planner.dynamics(jnp.asarray(x0, jnp.float32), jnp.asarray(plan.controls[0], jnp.float32)))
        plan = planner.solve(x0, targets, warm=warm_start(plan, THESIS.dt_s))
    assert plan.usable
    np.testing.assert_allclose(x0[0:3], [0, 0, 5], atol=0.03)
    np.testing.assert_allclose(plan.controls[0], hover_rotor_speed_rad_s(VEHICLE), rtol=0.01)


def test_gains_have_shape_and_stabilise_the_linearisation():
    """With the thesis's motor-node horizon (50) the first gain is close to the stationary one."""
    config = dataclasses.replace(THESIS, horizon=50)
    planner = ILQRSolver(VEHICLE, config, warm_up=False)
    targets = np.repeat(hover_state([0, 0, 5])[None], config.horizon + 1, axis=0)
    plan = planner.solve(hover_state([0, 0, 5]), targets)
    assert plan.gains.shape == (config.horizon, 4, 13) and plan.feedforward.shape == (config.horizon, 4)
    x, u = jnp.asarray(plan.states[0], jnp.float32), jnp.asarray(plan.controls[0], jnp.float32)
    a = np.asarray(jax.jacfwd(planner.dynamics, 0)(x, u))
    b = np.asarray(jax.jacfwd(planner.dynamics, 1)(x, u))
    closed = a + b @ plan.gains[0]
    # the quaternion's norm direction is a unit (neutral) mode; everything else contracts
    radius = np.sort(np.abs(np.linalg.eigvals(closed)))
    assert radius[-1] <= 1.0 + 1e-3 and radius[-2] < 1.0


def test_warm_start_shifts_by_one_step():
    plan_controls = np.arange(40.0).reshape(10, 4)
    plan = dataclasses.make_dataclass("P", ["controls", "dt_s"])(plan_controls, 0.1)
    shifted = warm_start(plan, 0.1)
    np.testing.assert_array_equal(shifted[:-1], plan_controls[1:])
    np.testing.assert_array_equal(shifted[-1], plan_controls[-1])
    np.testing.assert_array_equal(warm_start(plan, 0.05), plan_controls)


def test_feedback_control_at_the_plan_is_the_plan(planner):
    targets = np.repeat(hover_state([0, 0, 5])[None], THESIS.horizon + 1, axis=0)
    plan = planner.solve(hover_state([0.2, 0, 4.9]), targets)
    np.testing.assert_allclose(feedback_control(plan, 0.0, plan.states[0], planner.u_max_rad_s),
                               np.clip(plan.controls[0], 0, planner.u_max_rad_s), atol=1e-6)
    x = plan.states[0].copy()
    x[6:10] *= -1  # the same attitude
    np.testing.assert_allclose(feedback_control(plan, 0.0, x, planner.u_max_rad_s),
                               feedback_control(plan, 0.0, plan.states[0], planner.u_max_rad_s), atol=1e-6)


def test_second_solve_does_not_recompile(planner):
    before = planner.compiled_count()
    targets = np.repeat(hover_state([1, 1, 3])[None], THESIS.horizon + 1, axis=0)
    planner.solve(hover_state([0, 0, 2]), targets, warm=planner.hover_controls() * 1.01)
    planner.solve(hover_state([0, 1, 2]), targets)
    assert planner.compiled_count() == before == 1


def test_cost_is_thesis_quadratic_away_from_attitude():
    stage, terminal = make_cost(THESIS)
    x, xt = hover_state([1.0, 0, 0]), hover_state([0, 0, 0])
    u = np.full(4, 1000.0)
    assert float(stage(jnp.asarray(x), jnp.asarray(u), jnp.asarray(xt), jnp.asarray(u))) == pytest.approx(1.0)
    assert float(terminal(jnp.asarray(x), jnp.asarray(xt))) == pytest.approx(1.0)


@pytest.mark.parametrize("config,n", [(THESIS, 13), (PROJECT, 17)])
def test_structured_cost_derivatives_equal_autodiff(config, n):
    """make_cost_derivatives (what the solver uses) against jax.grad / jax.hessian of the costs,
    at random states far from and near the target attitude."""
    stage, terminal = make_cost(config)
    # both sides jitted, as the solver runs them: a compile each, where eager autodiff
    # dispatches (and compiles) every operation on its own
    stage_d, terminal_d = (jax.jit(f) for f in make_cost_derivatives(config))

    @jax.jit
    def autodiff(x, u, xt, ut):
        return ((jax.grad(stage, 0)(x, u, xt, ut), jax.grad(stage, 1)(x, u, xt, ut),
                 jax.hessian(stage, 0)(x, u, xt, ut), jax.hessian(stage, 1)(x, u, xt, ut),
                 jax.jacfwd(jax.grad(stage, 1), 0)(x, u, xt, ut)),
                (jax.grad(terminal)(x, xt), jax.hessian(terminal)(x, xt)))
    rng = np.random.default_rng(3)
    for near in (False, True):
        x, xt = (jnp.asarray(rng.normal(size=n)) for _ in range(2))
        if near:
            x = x.at[6:10].set(xt[6:10] * 1.3 + 1e-4 * rng.normal(size=4))
        u, ut = (jnp.asarray(rng.normal(size=4) * 100 + 700) for _ in range(2))
        expected_stage, expected_terminal = autodiff(x, u, xt, ut)
        for got, want in zip(stage_d(x, u, xt, ut), expected_stage):
            np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)  # float32
        for got, want in zip(terminal_d(x, xt), expected_terminal):
            np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)  # float32



def test_small_spd_solve_matches_numpy_and_flags_indefinite():
    """The adjugate solve of the backward pass: float32 accuracy as LAPACK's on Quu-like
    matrices (condition up to 1e4), and a matrix that is not positive definite gives NaN
    (an indefinite one whose determinant is positive too: Sylvester's other minors)."""
    rng = np.random.default_rng(5)
    for cond in (1.0, 1e2, 1e4):
        q, _ = np.linalg.qr(rng.normal(size=(4, 4)))
        a = (q * np.logspace(0, np.log10(cond), 4) * 1e-3) @ q.T
        rhs = rng.normal(size=(4, 14))
        x = _solve_spd(jnp.asarray(a, jnp.float32), jnp.asarray(rhs, jnp.float32))
        want = np.linalg.solve(a, rhs)
        assert np.abs(np.asarray(x) - want).max() <= 1e-5 * cond * np.abs(want).max()
    for diagonal in ([1.0, 2.0, -0.1, 3.0], [-1.0, 2.0, -0.1, 3.0], [1.0, -2.0, -0.1, 3.0], [1.0, 2.0, 3.0, 0.0]):
        x = _solve_spd(jnp.asarray(np.diag(diagonal), jnp.float32), jnp.ones((4, 3), jnp.float32))
        assert np.all(np.isnan(np.asarray(x))), diagonal


def test_backward_pass_is_the_riccati_recursion():
    """The augmented backward pass against the textbook recursion in float64 numpy, on random
    linearisations: gains K and feedforward k; a step that is not PD is reported and its
    pass returns zero gains."""
    rng = np.random.default_rng(8)
    horizon, n_x, n_u, mu = 5, 13, 4, 1e-3
    A = np.eye(n_x) + 0.1 * rng.normal(size=(horizon, n_x, n_x))
    B = 0.1 * rng.normal(size=(horizon, n_x, n_u))
    lx, lu = rng.normal(size=(horizon, n_x)), rng.normal(size=(horizon, n_u))
    lxx = np.stack([m @ m.T + np.eye(n_x) for m in rng.normal(size=(horizon, n_x, n_x))]) * 0.1
    luu = np.stack([np.eye(n_u)] * horizon) * 0.5
    lux = 0.01 * rng.normal(size=(horizon, n_u, n_x))
    vx_final, vxx_final = rng.normal(size=n_x), np.eye(n_x) * 2.0
    vx, vxx = vx_final, vxx_final
    want_gains, want_ffs = [], []
    for t in reversed(range(horizon)):
        a, b = A[t], B[t]
        qx, qu = lx[t] + a.T @ vx, lu[t] + b.T @ vx
        qxx, quu, qux = lxx[t] + a.T @ vxx @ a, luu[t] + b.T @ vxx @ b, lux[t] + b.T @ vxx @ a
        quu_reg = quu + mu * np.eye(n_u)
        gain, ff = -np.linalg.solve(quu_reg, qux), -np.linalg.solve(quu_reg, qu)
        vx = qx + gain.T @ quu @ ff + gain.T @ qu + qux.T @ ff
        vxx = qxx + gain.T @ quu @ gain + gain.T @ qux + qux.T @ gain
        vxx = 0.5 * (vxx + vxx.T)
        want_gains.insert(0, gain)
        want_ffs.insert(0, ff)
    derivs = tuple(jnp.asarray(v, jnp.float32) for v in (A, B, lx, lu, lxx, luu, lux, vx_final, vxx_final))
    backward_pass = jax.jit(_backward_pass)  # as the solver runs it; one compile for both calls
    gains, ffs, ok = backward_pass(derivs, mu)
    assert bool(ok)
    np.testing.assert_allclose(gains, np.stack(want_gains), rtol=1e-3, atol=1e-4)
    np.testing.assert_allclose(ffs, np.stack(want_ffs), rtol=1e-3, atol=1e-4)
    luu_indefinite = luu.copy()
    luu_indefinite[2] = -np.eye(n_u)  # a step whose Quu is not PD: reported, no NaN out
    derivs = (*derivs[:5], jnp.asarray(luu_indefinite, jnp.float32), *derivs[6:])
    gains, ffs, ok = backward_pass(derivs, mu)
    assert not bool(ok)
    assert np.all(np.asarray(gains) == 0.0) and np.all(np.asarray(ffs) == 0.0)


def test_motor_lag_model_forces_follow_the_command_exactly():
    """With models_motors the rotor forces are states: hover is an equilibrium and a
    step of the command is followed as the rotor speed's lag (flight/motor_model.py, the
    plant's motors): sqrt(f) moves to sqrt(c) as exp(-t / tau)."""
    tau, dt = VEHICLE.motor_time_constant_s, 0.025
    f = make_dynamics(VEHICLE, dt, "rk4", models_motors=True)
    hover_n = VEHICLE.hover_thrust_per_motor_n
    x = jnp.concatenate([jnp.asarray(hover_state([0, 0, 5])), jnp.full(4, hover_n)])
    u = jnp.full(4, hover_rotor_speed_rad_s(VEHICLE))
    np.testing.assert_allclose(f(x, u), x, atol=1e-5)
    x_step = f(x, u * np.sqrt(2.0))
    d = np.exp(-dt / tau)
    np.testing.assert_allclose(x_step[13:17], hover_n * (np.sqrt(2) - (np.sqrt(2) - 1) * d) ** 2, rtol=1e-6)
    np.testing.assert_allclose(thrust_step(np.full(4, hover_n), np.full(4, 2 * hover_n), dt, tau),
                               x_step[13:17], rtol=1e-6)
    assert 0 < x_step[5] < 2 * 9.81 * dt  # accelerates up, less than with the thrust at once


def test_planner_with_motor_model_pads_13_state_inputs():
    config = PROJECT  # the motor-model config that flies: the flip and prediction tests compile it
    # too, so the run's compilation cache (tests/unit/conftest.py) holds it
    assert config.models_motors
    p = ILQRSolver(VEHICLE, config, warm_up=False)
    targets = np.repeat(hover_state([0, 0, 5])[None], config.horizon + 1, axis=0)
    plan = p.solve(hover_state([0, 0, 4.9]), targets)
    assert p.state_dim == 17 and plan.states.shape == (config.horizon + 1, 17)
    assert plan.gains.shape == (config.horizon, 4, 17)
    np.testing.assert_allclose(plan.states[0, 13:], VEHICLE.hover_thrust_per_motor_n)
    u = feedback_control(plan, 0.0, p.full_state(hover_state([0, 0, 4.9])), p.u_max_rad_s)
    assert np.all(np.isfinite(u))


def test_solver_compiler_options_leave_the_plan_unchanged(planner, monkeypatch):
    """The CPU options (YNNPACK's small-dot fusion off) change how XLA runs the solve, not
    what it computes: the same plan, to float32 rounding, as XLA's defaults."""
    import flight.control.ilqr as ilqr
    if jax.default_backend() == "cpu":
        assert solver_compiler_options() == ilqr.CPU_SOLVER_OPTIONS
    x0 = hover_state([0.3, -0.2, 4.6])
    targets = np.repeat(hover_state([0.0, 0.0, 5.0])[None], THESIS.horizon + 1, axis=0)
    monkeypatch.setattr(ilqr, "solver_compiler_options", lambda: {})
    default = ILQRSolver(VEHICLE, THESIS, warm_up=False).solve(x0, targets)
    tuned = planner.solve(x0, targets)
    assert tuned.iterations == default.iterations
    np.testing.assert_allclose(tuned.controls, default.controls, rtol=1e-4, atol=1e-2)
    np.testing.assert_allclose(tuned.states, default.states, rtol=1e-4, atol=1e-5)
    assert tuned.cost == pytest.approx(default.cost, rel=1e-4)


PLAN_IN_A_FRESH_PROCESS = """
import json, sys, numpy as np
from flight.control.ilqr import THESIS, ILQRSolver, hover_state, use_compile_cache
from flight.vehicle import load_vehicle
use_compile_cache(sys.argv[1])
planner = ILQRSolver(load_vehicle("q820"), THESIS)
x0 = hover_state([0.3, -0.2, 4.6])
plan = planner.solve(x0, np.repeat(hover_state([0.0, 0.0, 5.0])[None], THESIS.horizon + 1, axis=0))
print(json.dumps({"whole": planner.loops_compiled_whole(), "controls": plan.controls.tolist(),
                  "cost": plan.cost}))
"""


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="XLA's CPU runtime option")
def test_small_loop_hoisting_compiles_the_thesis_solve_whole_and_plans_the_same(jax_compile_cache):
    """An ILQRSolver asks XLA (XLA_FLAGS, before its first compile) to compile small while loops as
    one function each: a fresh process that builds one gets the THESIS solve's loops so, and
    plans as a process left at XLA's defaults (ZENPILOT_XLA_DEFAULTS=1) does. Both use the run's
    compilation cache: its key holds XLA_FLAGS, so each loads only what was compiled as it asks."""
    import json
    import os
    import subprocess
    import sys
    root = str(Path(__file__).resolve().parents[4])
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "ZENPILOT_XLA_DEFAULTS")}
    runs = [subprocess.Popen([sys.executable, "-c", PLAN_IN_A_FRESH_PROCESS, jax_compile_cache], cwd=root,
                             text=True, stdout=subprocess.PIPE, env=dict(env, **extra))
            for extra in ({}, {"ZENPILOT_XLA_DEFAULTS": "1"})]
    hoisted, default = (json.loads(run.communicate(timeout=300)[0].splitlines()[-1]) for run in runs)
    assert hoisted["whole"] >= 3 and default["whole"] <= 1
    np.testing.assert_allclose(hoisted["controls"], default["controls"], rtol=1e-4, atol=1e-2)
    assert hoisted["cost"] == pytest.approx(default["cost"], rel=1e-4)


def test_importing_the_solver_changes_no_environment():
    import os
    import subprocess
    import sys
    root = str(Path(__file__).resolve().parents[4])
    code = ("import os, jax; before = dict(os.environ)\n"
            "import flight.control.ilqr, services.mavlink_logic, services.planner, services.motors\n"
            "print(sorted(k for k in os.environ if os.environ.get(k) != before.get(k)))")
    out = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120)
    assert out.stdout.strip().splitlines()[-1] == "[]", out.stderr
