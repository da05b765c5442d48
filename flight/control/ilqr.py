"""iLQR in JAX for the quadrotor of document 001 (the flip planner).

Contracts (trajax style, stated once here):
    dynamics(x, u) -> x_next        one step of dt_s; x (13,), u (4,)
    stage_cost(x, u, x_target, u_target) -> scalar
    terminal_cost(x, x_target) -> scalar
    x = [position_m (3, world ENU), velocity_m_s (3), quaternion (4, [w,x,y,z]
         body->world, flight/quat.py), rate_rad_s (3, body FLU)]
    u = rotor speeds, rad/s (as the thesis: thrust_i = kf * u_i**2, Appendix A)
    plans: states (H+1, 13), controls (H, 4), gains K (H, 4, 13), feedforward (H, 4);
    the feedback law is u = u_plan + K (x - x_plan).

Everything over the horizon is lax.scan (rollout, backward pass, forward pass)
and the iterations are one lax.while_loop, so a solve is one jitted call that
is compiled once when the ILQRSolver is built. Rotor limits [0, max_rotor_speed]
are enforced by clamping in the forward pass rather than inside f (the thesis
clips inside f, which zeroes f's Jacobian at the limits and stalls the solver).
"""
from __future__ import annotations

import functools
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from flight import motor_model
from flight.quat import quat_multiply
from flight.vehicle import Vehicle

# How XLA runs the solver on the CPU. Its runtime launches a kernel per fused operation and
# goes through its executor at every step of a while loop (the scans), which on matrices this
# small costs more than the arithmetic. Two settings, which leave the plans the same
# (tests/unit/flight/control/test_ilqr.py; their speed-up: bench/ilqr.py, docs/changelog.md):
# - YNNPACK off for the solver's jit: XLA hands it the small dots (the backward pass's F' V F),
#   each call several of XLA's own fused loops, and a loop holding one is never compiled whole;
# - XLA's small-while-loop hoisting for loops touching under SMALL_LOOP_BYTES: such a loop is
#   compiled as one function. Its default (~1 KB) takes none of the solver's; 1 MB takes the
#   THESIS solve whole and the PROJECT one's scans, but not its iteration loop (slower whole).
CPU_SOLVER_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": ""}
SMALL_LOOP_BYTES = 1_000_000


def request_small_loop_hoisting() -> bool:
    """Add the small-loop threshold to XLA_FLAGS. XLA reads XLA_FLAGS once, at the process's
    first JAX operation, and it has no per-jit form: the first ILQRSolver of a process asks for
    it before compiling (importing this module computes nothing with JAX). After an earlier JAX
    operation it has no effect (slower, same plans): returns False then. Left alone when
    XLA_FLAGS already sets backend options, or with ZENPILOT_XLA_DEFAULTS=1."""
    from jax._src import xla_bridge
    flags = os.environ.get("XLA_FLAGS", "")
    if os.environ.get("ZENPILOT_XLA_DEFAULTS") == "1" or "xla_backend_extra_options" in flags:
        return True
    if xla_bridge.backends_are_initialized():
        return False
    option = f"--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold={SMALL_LOOP_BYTES}"
    os.environ["XLA_FLAGS"] = f"{flags} {option}".strip()
    return True


def use_one_solver_thread() -> bool:
    """Run every solve on one XLA thread, dispatched synchronously: for a process that
    solves in a real-time loop (the planner service), called before its first JAX operation.

    By default XLA's CPU client dispatches a call asynchronously (a thread of its own takes
    it, the caller waits on a future) and runs it on an intra-op pool of one thread per CPU:
    several thread wake-ups per solve, and in a real-time flight each hand-off waits for a CPU
    that the real-time loops may hold. Synchronous dispatch (jax_cpu_enable_async_dispatch off)
    and a pool of one thread (NPROC=1, which XLA's DefaultThreadPoolSize reads when the client
    is created) leave one wake-up per solve and less CPU (docs/flip-history.md, "In real
    time"). The same executable runs: the plans are the same bits. Returns False when JAX's
    CPU client exists already (too late: nothing changed)."""
    from jax._src import xla_bridge
    if xla_bridge.backends_are_initialized():  # the client is created once, at the first JAX operation
        return False
    os.environ["NPROC"] = "1"
    jax.config.update("jax_cpu_enable_async_dispatch", False)
    return True


BODY_DIM = 13
STATE_DIM = BODY_DIM  # without the motor model; ILQRSolver.state_dim is 17 with it
CONTROL_DIM = 4
POS, VEL, QUAT, RATE = slice(0, 3), slice(3, 6), slice(6, 10), slice(10, 13)
MOTOR = slice(13, 17)  # rotor forces, N, when ILQRConfig.models_motors


@dataclass(frozen=True)
class ILQRConfig:
    """Solver settings. Weights are per error component: position (3), velocity (3),
    attitude (1, on the squared geodesic angle 2*arccos|<q, q*>|, rad^2), body rate (3).
    """
    name: str
    dt_s: float
    horizon: int
    max_iterations: int
    integrator: str  # "euler" (the thesis's Appendix A update) or "rk4"
    state_weight: tuple[float, ...]      # 10 values: p(3), v(3), attitude, rate(3)
    terminal_weight: tuple[float, ...]   # 10 values, same order
    control_weight: float                # R = control_weight * I, per (rad/s)^2
    relative_tolerance: float = 1e-3     # stop when the cost falls by less than this fraction
    line_search_alphas: tuple[float, ...] = (1.0, 0.5, 0.25, 0.1, 0.03)
    regularisation_init: float = 1e-6    # Levenberg-Marquardt mu on Quu
    regularisation_min: float = 1e-8
    regularisation_max: float = 1e4
    regularisation_factor: float = 10.0
    # False: the thesis's model, rotor speeds act at once. True: the rotor forces are
    # states, the rotors' speeds lagging the command by the vehicle file's
    # motor_time_constant_s (flight/motor_model.py, the plant's motors).
    models_motors: bool = False
    # True: once the iterations are over, one more linearisation and backward pass at the
    # returned plan, so its gains K are that plan's. False: the gains of the last backward
    # pass (linearised at the plan the last line search started from; the usual iLQR
    # output, and one backward pass less per solve).
    gains_at_returned_plan: bool = True

    def __post_init__(self):
        if self.integrator not in ("euler", "rk4"):
            raise ValueError(f"integrator must be 'euler' or 'rk4', got {self.integrator!r}")
        if len(self.state_weight) != 10 or len(self.terminal_weight) != 10:
            raise ValueError("state_weight and terminal_weight need 10 values")
        if self.dt_s <= 0 or self.horizon < 1 or self.max_iterations < 1:
            raise ValueError("dt_s > 0, horizon >= 1 and max_iterations >= 1 required")


# The thesis's Q diag(1,1,10, 1,1,1, 0,50,50,0, 5,5,1) weights qx, qy by 50; for a
# rotation e about x or y, qx = sin(e/2) ~ e/2, so the same small-angle curvature on
# the geodesic angle is 50/4 = 12.5 (Qf: 100/4 = 25).
THESIS = ILQRConfig(
    name="thesis", dt_s=0.1, horizon=10, max_iterations=5, integrator="euler",
    state_weight=(1.0, 1.0, 10.0, 1.0, 1.0, 1.0, 12.5, 5.0, 5.0, 1.0),
    terminal_weight=(1.0, 1.0, 10.0, 0.1, 0.1, 0.1, 25.0, 10.0, 10.0, 1.0),
    control_weight=1e-3, gains_at_returned_plan=False,  # the thesis's solve ends at its last pass
)

# Horizontal position weighted 900: the flip's drift is the lateral impulse of the one
# rotor pair that rolls a plus frame, and the plan keeps it small at the price of height,
# which the flip's climb (PROJECT_FLIP.climb_m, flight/control/flip.py) buys back (the weights
# and climbs tried: docs/flip-history.md, "A climb before the turn").
PROJECT = ILQRConfig(
    name="project", dt_s=0.025, horizon=32, max_iterations=8, integrator="rk4",
    state_weight=(900.0, 900.0, 40.0, 4.0, 4.0, 4.0, 60.0, 10.0, 10.0, 5.0),
    terminal_weight=(900.0, 900.0, 40.0, 4.0, 4.0, 4.0, 60.0, 10.0, 10.0, 5.0),
    control_weight=1e-5, models_motors=True,
)


# --- model ---------------------------------------------------------------------------

def _body_z_in_world(q):
    """Third column of R(q) (flight/quat.py's body->world matrix)."""
    w, x, y, z = q
    return jnp.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])


def hover_rotor_speed_rad_s(vehicle: Vehicle) -> float:
    return float(np.sqrt(vehicle.hover_thrust_per_motor_n / _thrust_coefficient(vehicle)))


def _thrust_coefficient(vehicle: Vehicle) -> float:
    if vehicle.thrust_coefficient_kf is None or vehicle.max_rotor_speed_rad_s is None:
        raise ValueError(f"vehicle {vehicle.name!r} lacks thrust_coefficient_kf / max_rotor_speed_rad_s")
    return vehicle.thrust_coefficient_kf


def rigid_body_derivative(x, forces_n, mass, inertia, allocation, drag, gravity, wind=None):
    """xdot (13,) of the rigid body under rotor forces (4,): the model of 001 with the
    vehicle's allocation and linear drag against the air (wind (3,), world; None: still).
    The vehicle's numbers are arguments so that flight/control/predict.py can draw them per case."""
    v, q, w = x[VEL], x[QUAT], x[RATE]
    thrust_torque = jnp.sum(allocation * forces_n, axis=1)  # allocation @ forces, fusible
    air = v if wind is None else v - wind
    accel = (_body_z_in_world(q) * thrust_torque[0] - drag * air) / mass - gravity
    q_dot = 0.5 * quat_multiply(q, jnp.concatenate([jnp.zeros(1), w]), jnp)
    w_dot = (thrust_torque[1:] - jnp.cross(w, inertia * w)) / inertia
    return jnp.concatenate([v, accel, q_dot, w_dot])


def make_derivative(vehicle: Vehicle) -> Callable:
    """Continuous model xdot(x, u) of 001 with the vehicle's allocation (thrust kf*u^2).
    derivative.with_forces(x, forces_n) is the same rigid body driven by rotor forces."""
    kf = _thrust_coefficient(vehicle)
    mass = vehicle.mass_kg
    inertia = jnp.asarray(vehicle.inertia_kg_m2)
    allocation = jnp.asarray(vehicle.allocation)
    drag = vehicle.drag_n_per_m_s
    gravity = jnp.array([0.0, 0.0, vehicle.gravity_m_s2])

    def wrench(u):
        return allocation @ (kf * u * u)  # [thrust_n, torque_x, torque_y, torque_z]

    def with_forces(x, forces_n):
        return rigid_body_derivative(x, forces_n, mass, inertia, allocation, drag, gravity)

    def derivative(x, u):
        return with_forces(x, kf * u * u)

    derivative.wrench = wrench
    derivative.with_forces = with_forces
    return derivative


def make_dynamics(vehicle: Vehicle, dt_s: float, integrator: str = "euler",
                  models_motors: bool = False) -> Callable:
    """Discrete f(x, u) -> x_next. "euler" is the thesis's update (Appendix A): velocity
    and rate by Euler, position with the dt^2/2 term, quaternion with the new rate.

    With models_motors the state has 4 more components, the rotor forces (N), which
    follow the commanded kf u^2 through flight/motor_model.py's motors (the rotor speed
    lagging u by the vehicle's motor_time_constant_s, thrust kf w^2): they are advanced exactly
    (zero-order hold on the command) and the rigid body is integrated with their exact
    mean over the step."""
    derivative = make_derivative(vehicle)
    body = derivative.with_forces

    def euler(x, forces):
        xdot = body(x, forces)
        p, v, q, w = x[POS], x[VEL], x[QUAT], x[RATE]
        accel, w_dot = xdot[VEL], xdot[RATE]
        w_new = w + w_dot * dt_s
        q_new = q + 0.5 * quat_multiply(q, jnp.concatenate([jnp.zeros(1), w_new]), jnp) * dt_s
        return jnp.concatenate([p + v * dt_s + 0.5 * accel * dt_s ** 2, v + accel * dt_s,
                                q_new / jnp.linalg.norm(q_new), w_new])

    def rk4(x, forces):
        k1 = body(x, forces)
        k2 = body(x + 0.5 * dt_s * k1, forces)
        k3 = body(x + 0.5 * dt_s * k2, forces)
        k4 = body(x + dt_s * k3, forces)
        x_new = x + dt_s / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        return jnp.concatenate([x_new[:QUAT.start], x_new[QUAT] / jnp.linalg.norm(x_new[QUAT]),
                                x_new[QUAT.stop:]])

    step = {"euler": euler, "rk4": rk4}[integrator]
    kf = _thrust_coefficient(vehicle)
    if not models_motors:
        return lambda x, u: step(x, kf * u * u)

    weights = motor_model.mean_weights(dt_s, vehicle.motor_time_constant_s)
    root_kf = float(np.sqrt(kf))

    def lagged(x, u):
        # sqrt of the command's force is sqrt(kf) u (smooth in u); of the state's, floored
        # away from 0, where the square root's derivative is infinite
        forces, mean = motor_model.root_step_and_mean(jnp.sqrt(jnp.maximum(x[MOTOR], _FORCE_FLOOR_N)),
                                                      root_kf * u, weights)
        return jnp.concatenate([step(x[:BODY_DIM], mean), forces])

    return lagged


_FORCE_FLOOR_N = 1e-12  # rotor force below which the lag model's sqrt(f) is taken at this


# --- cost --------------------------------------------------------------------------

_SERIES_BELOW = 1e-3  # 1 - |<q, q*>| below which the attitude error uses its series


def attitude_error_sq_rad2(q, q_target):
    """(2 arccos|<q, q*>|)^2: the squared rotation angle between q and q* (0 at q* and -q*).

    arccos has an infinite slope at 1, so within 1e-3 of it the square is taken from its
    series 4 (2 s + s^2 / 3), s = 1 - |<q, q*>|, which is smooth with finite derivatives
    of every order; the other branch sees a harmless argument there (double-where).
    Sums rather than jnp.dot: XLA fuses them with the rest (a dot is a call of its own)."""
    d = jnp.abs(jnp.sum(q * q_target)) / jnp.sqrt(jnp.sum(q * q) * jnp.sum(q_target * q_target))
    s = 1.0 - d
    near = s < _SERIES_BELOW
    series = 4.0 * (2.0 * s + s * s / 3.0)
    d_far = jnp.where(near, 0.5, jnp.clip(d, 0.0, 1.0))
    return jnp.where(near, series, 4.0 * jnp.arccos(d_far) ** 2)


def attitude_error_derivatives(q, q_target):
    """Gradient (4,) and Hessian (4, 4) in q of attitude_error_sq_rad2, in closed form
    (the same values as jax.grad / jax.hessian, a test holds them equal, as elementwise
    work XLA fuses: autodiff's Hessian was the solver's costliest step).

    With u = q/|q|, c = q*/|q*|, sg = sign<u, c> and d = |<u, c>|:
    dd/dq = (sg c - d u)/|q|, d2d/dq2 = -[(sg c - d u) u' + u (sg c - d u)' + d (I - u u')]/|q|^2,
    and the error e(d) = 4 arccos(d)^2 (near d = 1 its series) by the chain rule."""
    n = jnp.sqrt(jnp.sum(q * q))
    u = q / n
    c = q_target / jnp.sqrt(jnp.sum(q_target * q_target))
    dot = jnp.sum(u * c)
    sg = jnp.where(dot >= 0.0, 1.0, -1.0).astype(q.dtype)
    d = jnp.abs(dot)
    r = sg * c - d * u
    grad_d = r / n
    eye = jnp.eye(q.shape[-1], dtype=q.dtype)
    hess_d = -(r[:, None] * u[None, :] + u[:, None] * r[None, :] + d * (eye - u[:, None] * u[None, :])) / (n * n)
    s = 1.0 - d
    near = s < _SERIES_BELOW
    d_far = jnp.where(near, 0.5, jnp.clip(d, 0.0, 1.0))
    angle = jnp.arccos(d_far)
    root = jnp.sqrt(1.0 - d_far * d_far)
    de_far = -8.0 * angle / root
    d2e_far = 8.0 * (1.0 / (root * root) - angle * d_far / (root * root * root))
    de = jnp.where(near, -8.0 - 8.0 * s / 3.0, de_far)
    d2e = jnp.where(near, 8.0 / 3.0, d2e_far)
    return de * grad_d, d2e * grad_d[:, None] * grad_d[None, :] + de * hess_d


def _weighted_state_error(x, x_target, weight):
    w = jnp.asarray(weight)
    dp = x[POS] - x_target[POS]
    dv = x[VEL] - x_target[VEL]
    dw = x[RATE] - x_target[RATE]
    return (jnp.sum(w[0:3] * dp * dp) + jnp.sum(w[3:6] * dv * dv)
            + w[6] * attitude_error_sq_rad2(x[QUAT], x_target[QUAT]) + jnp.sum(w[7:10] * dw * dw))


def make_cost(config: ILQRConfig) -> tuple[Callable, Callable]:
    """(stage_cost, terminal_cost) of the thesis: quadratic in p, v, rate and u, the
    attitude through the geodesic angle."""
    def stage_cost(x, u, x_target, u_target):
        du = u - u_target
        return _weighted_state_error(x, x_target, config.state_weight) + config.control_weight * jnp.sum(du * du)

    def terminal_cost(x, x_target):
        return _weighted_state_error(x, x_target, config.terminal_weight)

    return stage_cost, terminal_cost


def make_cost_derivatives(config: ILQRConfig) -> tuple[Callable, Callable]:
    """Exact derivatives of make_cost's costs, using their structure: the p, v, rate and u
    terms are quadratic (constant Hessians), the attitude term's in closed form on the
    4 quaternion components alone. Same values as jax.grad/jax.hessian of the costs (a
    test holds them equal) for a fraction of the work: a generic Hessian of the stage cost
    differentiates all 13 (17) states twice.

    stage_derivatives(x, u, x_target, u_target) -> (lx, lu, lxx, luu, lux)
    terminal_derivatives(x, x_target) -> (lx, lxx); x of any size >= 13 (extra states
    carry no cost)."""
    def state_derivatives(x, x_target, weight):
        w = np.asarray(weight, dtype=np.float64)
        diag = np.zeros(x.shape[-1])
        diag[POS], diag[VEL], diag[RATE] = w[0:3], w[3:6], w[7:10]
        diag = jnp.asarray(diag, x.dtype)
        att_grad, att_hess = attitude_error_derivatives(x[QUAT], x_target[QUAT])
        after = x.shape[-1] - QUAT.stop  # padding, not .at[].set: it fuses
        lx = 2.0 * diag * (x - x_target) + jnp.pad(w[6] * att_grad, (QUAT.start, after))
        lxx = jnp.diag(2.0 * diag) + jnp.pad(w[6] * att_hess, ((QUAT.start, after),) * 2)
        return lx, lxx

    def stage_derivatives(x, u, x_target, u_target):
        lx, lxx = state_derivatives(x, x_target, config.state_weight)
        cw = config.control_weight
        lu = 2.0 * cw * (u - u_target)
        luu = 2.0 * cw * jnp.eye(u.shape[-1], dtype=u.dtype)
        return lx, lu, lxx, luu, jnp.zeros((u.shape[-1], x.shape[-1]), x.dtype)

    def terminal_derivatives(x, x_target):
        return state_derivatives(x, x_target, config.terminal_weight)

    return stage_derivatives, terminal_derivatives


# --- solver ------------------------------------------------------------------------

class Solution(NamedTuple):
    states: jax.Array        # (H+1, 13)
    controls: jax.Array      # (H, 4) rotor speeds, rad/s
    gains: jax.Array         # (H, 4, 13) feedback K (at the returned plan: gains_at_returned_plan)
    feedforward: jax.Array   # (H, 4) k of the last backward pass (~0 when converged)
    cost: jax.Array          # final cost
    initial_cost: jax.Array  # cost of the initial (warm-start) rollout
    iterations: jax.Array    # iterations used
    converged: jax.Array     # relative cost decrease fell below the tolerance


def rollout(dynamics, x0, controls):
    """States (H+1, 13) from x0 under the open-loop controls."""
    def step(x, u):
        x_next = dynamics(x, u)
        return x_next, x_next
    _, xs = jax.lax.scan(step, x0, controls)
    return jnp.concatenate([x0[None], xs])


def trajectory_cost(stage_cost, terminal_cost, states, controls, x_targets, u_targets):
    stage = jax.vmap(stage_cost)(states[:-1], controls, x_targets[:-1], u_targets)
    return jnp.sum(stage) + terminal_cost(states[-1], x_targets[-1])


def _matmul(a, b):
    """a @ b as a broadcast product and a sum: for these 4..18-wide matrices XLA fuses it
    with its neighbours, where a dot is an Eigen call of its own (most of a step's time)."""
    return jnp.sum(a[:, :, None] * b[None, :, :], axis=1)


def _solve_spd(a, rhs):
    """Solve a x = rhs for a symmetric 4 x 4 a (the controls' Quu) by its adjugate over its
    determinant, from the 2 x 2 minors of its top and bottom row pairs. Every entry is a
    polynomial in a's entries and one reciprocal, so XLA fuses the inverse into one kernel
    (an L D L' factorisation chains a division per pivot: a kernel each, in every step of
    the backward pass). Positive definite by Sylvester's criterion (leading minors > 0).
    Returns x, all NaN when a is not positive definite."""
    (a00, a01, a02, a03), (a10, a11, a12, a13), (a20, a21, a22, a23), (a30, a31, a32, a33) = (
        [a[i, j] for j in range(4)] for i in range(4))
    s0, s1, s2 = a00 * a11 - a10 * a01, a00 * a12 - a10 * a02, a00 * a13 - a10 * a03
    s3, s4, s5 = a01 * a12 - a11 * a02, a01 * a13 - a11 * a03, a02 * a13 - a12 * a03
    c5, c4, c3 = a22 * a33 - a32 * a23, a21 * a33 - a31 * a23, a21 * a32 - a31 * a22
    c2, c1, c0 = a20 * a33 - a30 * a23, a20 * a32 - a30 * a22, a20 * a31 - a30 * a21
    det = s0 * c5 - s1 * c4 + s2 * c3 + s3 * c2 - s4 * c1 + s5 * c0
    minor3 = a00 * (a11 * a22 - a12 * a21) - a01 * (a10 * a22 - a12 * a20) + a02 * (a10 * a21 - a11 * a20)
    pd = (a00 > 0.0) & (s0 > 0.0) & (minor3 > 0.0) & (det > 0.0)
    adjugate = jnp.stack([
        jnp.stack([a11 * c5 - a12 * c4 + a13 * c3, -a01 * c5 + a02 * c4 - a03 * c3,
                   a31 * s5 - a32 * s4 + a33 * s3, -a21 * s5 + a22 * s4 - a23 * s3]),
        jnp.stack([-a10 * c5 + a12 * c2 - a13 * c1, a00 * c5 - a02 * c2 + a03 * c1,
                   -a30 * s5 + a32 * s2 - a33 * s1, a20 * s5 - a22 * s2 + a23 * s1]),
        jnp.stack([a10 * c4 - a11 * c2 + a13 * c0, -a00 * c4 + a01 * c2 - a03 * c0,
                   a30 * s4 - a31 * s2 + a33 * s0, -a20 * s4 + a21 * s2 - a23 * s0]),
        jnp.stack([-a10 * c3 + a11 * c1 - a12 * c0, a00 * c3 - a01 * c1 + a02 * c0,
                   -a30 * s3 + a31 * s1 - a32 * s0, a20 * s3 - a21 * s1 + a22 * s0])])
    return _matmul(adjugate, rhs) / jnp.where(pd, det, jnp.nan)  # divided last: it fuses


def _backward_pass(derivs, mu):
    """Riccati recursion with Quu + mu I.

    Written on the augmented vector z = [x, 1, u]: the value function is one matrix
    V = [Vxx vx; vx' .] and a step is M = F' V F + L with F = [A 0 B; 0 1 0] and L the
    stage cost's [lxx lx lxu; lx' 0 lu'; lux lu luu]; then Qxx, qx, Qux, qu, Quu are
    blocks of M, the gains [K k] = -Quu^-1 [Qux qu] and the new V is
    M_zz + G' Quu G + G' [Qux qu] + [Qux qu]' G, G = [K k] (the usual update, 13+1 wide).
    A step is a dozen XLA kernels, run horizon x iterations times per solve, so each
    is placed to fuse: V symmetrised as the next step reads it, the PD test carried as
    NaN (checked once after the scan) rather than as a flag in the loop.
    Returns (K, k, ok); K and k are 0 when not ok (some Quu + mu I not PD)."""
    A, B, lx, lu, lxx, luu, lux, vx_final, vxx_final = derivs
    horizon, n_x, n_u = B.shape
    n_a = n_x + 1
    dtype = A.dtype
    unit_row = jnp.concatenate([jnp.zeros(n_x, dtype), jnp.ones(1, dtype), jnp.zeros(n_u, dtype)])
    F = jnp.concatenate([jnp.concatenate([A, jnp.zeros((horizon, n_x, 1), dtype), B], axis=2),
                         jnp.broadcast_to(unit_row, (horizon, 1, n_a + n_u))], axis=1)
    L = jnp.concatenate([
        jnp.concatenate([lxx, lx[:, :, None], jnp.swapaxes(lux, 1, 2)], axis=2),
        jnp.concatenate([lx[:, None, :], jnp.zeros((horizon, 1, 1), dtype), lu[:, None, :]], axis=2),
        jnp.concatenate([lux, lu[:, :, None], luu], axis=2)], axis=1)
    v_final = jnp.block([[vxx_final, vx_final[:, None]], [vx_final[None, :], jnp.zeros((1, 1), dtype)]])
    regularisation = mu * jnp.eye(n_u, dtype=dtype)

    def step(v, d):
        v = 0.5 * (v + v.T)  # symmetrised here, where it fuses into the product, not after
        f, l = d
        m = _matmul(f.T, _matmul(v, f)) + l
        quu, q_u = m[n_a:, n_a:], m[n_a:, :n_a]          # Quu, [Qux qu]
        g = -_solve_spd(quu + regularisation, q_u)       # [K k]; NaN if not PD, and so
        quu_g = _matmul(quu, g)                           # every earlier step's too
        g_q = _matmul(g.T, q_u)
        return m[:n_a, :n_a] + _matmul(g.T, quu_g) + g_q + g_q.T, g

    _, g = jax.lax.scan(step, v_final, (F, L), reverse=True)
    ok = jnp.all(jnp.isfinite(g))
    g = jnp.where(ok, g, 0.0)
    return g[:, :, :n_x], g[:, :, n_x], ok


def make_solver(dynamics, stage_cost, terminal_cost, config: ILQRConfig, u_min, u_max,
                cost_derivatives=None) -> Callable:
    """solve(x0, controls_init, x_targets, u_targets, max_iterations=None, relative_tolerance=None)
    -> Solution; pure, jit it once. The two stops default to config's (constants in the program);
    given, they are arguments, so configs that differ only in them compile to one program.

    cost_derivatives: (stage_derivatives, terminal_derivatives) as make_cost_derivatives
    returns; None: jax.grad / jax.hessian of the costs."""
    alphas = jnp.asarray(config.line_search_alphas)
    jac_x = jax.vmap(jax.jacfwd(dynamics, argnums=0))
    jac_u = jax.vmap(jax.jacfwd(dynamics, argnums=1))
    if cost_derivatives is None:
        def stage_derivatives(x, u, xt, ut):
            return (jax.grad(stage_cost, argnums=0)(x, u, xt, ut), jax.grad(stage_cost, argnums=1)(x, u, xt, ut),
                    jax.hessian(stage_cost, argnums=0)(x, u, xt, ut), jax.hessian(stage_cost, argnums=1)(x, u, xt, ut),
                    jax.jacfwd(jax.grad(stage_cost, argnums=1), argnums=0)(x, u, xt, ut))

        def terminal_derivatives(x, xt):
            return jax.grad(terminal_cost)(x, xt), jax.hessian(terminal_cost)(x, xt)
    else:
        stage_derivatives, terminal_derivatives = cost_derivatives
    stage_derivatives_all = jax.vmap(stage_derivatives)
    mu_min, mu_max, factor = config.regularisation_min, config.regularisation_max, config.regularisation_factor

    def cost_of(states, controls, x_targets, u_targets):
        return trajectory_cost(stage_cost, terminal_cost, states, controls, x_targets, u_targets)

    def derivatives(states, controls, x_targets, u_targets):
        xs, xt = states[:-1], x_targets[:-1]
        lx, lu, lxx, luu, lux = stage_derivatives_all(xs, controls, xt, u_targets)
        return (jac_x(xs, controls), jac_u(xs, controls), lx, lu, lxx, luu, lux,
                *terminal_derivatives(states[-1], x_targets[-1]))

    def forward(states, controls, gains, ffs, alpha):
        def step(x, d):
            x_ref, u_ref, gain, ff = d
            u = jnp.clip(u_ref + alpha * ff + jnp.sum(gain * (x - x_ref), axis=1), u_min, u_max)
            x_next = dynamics(x, u)
            return x_next, (x_next, u)
        _, (xs, us) = jax.lax.scan(step, states[0], (states[:-1], controls, gains, ffs))
        return jnp.concatenate([states[:1], xs]), us

    def solve(x0, controls_init, x_targets, u_targets, max_iterations=None, relative_tolerance=None):
        max_iterations = config.max_iterations if max_iterations is None else max_iterations
        relative_tolerance = config.relative_tolerance if relative_tolerance is None else relative_tolerance
        controls0 = jnp.clip(controls_init, u_min, u_max)
        states0 = rollout(dynamics, x0, controls0)
        cost0 = cost_of(states0, controls0, x_targets, u_targets)

        def improve(states, controls, cost, mu, it, gains, ffs, pd):
            cand_states, cand_controls = jax.vmap(forward, in_axes=(None, None, None, None, 0))(
                states, controls, gains, ffs, alphas)
            cand_costs = jax.vmap(cost_of, in_axes=(0, 0, None, None))(
                cand_states, cand_controls, x_targets, u_targets)
            cand_costs = jnp.where(jnp.isfinite(cand_costs), cand_costs, jnp.inf)
            best = jnp.argmin(cand_costs)
            accept = pd & (cand_costs[best] < cost)
            rel_decrease = (cost - cand_costs[best]) / jnp.maximum(jnp.abs(cost), 1e-12)
            converged = accept & (rel_decrease < relative_tolerance)
            mu = jnp.where(accept, jnp.maximum(mu / factor, mu_min), jnp.minimum(mu * factor, mu_max))
            return (jnp.where(accept, cand_states[best], states), jnp.where(accept, cand_controls[best], controls),
                    jnp.where(accept, cand_costs[best], cost), mu, it + 1, converged)

        # Each pass linearises and runs the backward pass at the current plan, then the
        # line search. With gains_at_returned_plan, once the solve is over one more pass
        # only refreshes the gains, so the returned K belong to the returned plan and the
        # model is traced once; without, the loop stops as soon as the solve is over.
        refresh = config.gains_at_returned_plan

        def iterate(carry):
            states, controls, cost, mu, it, converged, _, _, over, _ = carry
            gains, ffs, pd = _backward_pass(derivatives(states, controls, x_targets, u_targets), mu)
            if refresh:
                states, controls, cost, mu, it, converged = jax.lax.cond(
                    over, lambda: (states, controls, cost, mu, it, converged),
                    lambda: improve(states, controls, cost, mu, it, gains, ffs, pd))
            else:
                states, controls, cost, mu, it, converged = improve(
                    states, controls, cost, mu, it, gains, ffs, pd)
            now_over = converged | (it >= max_iterations) | (mu >= mu_max)
            return states, controls, cost, mu, it, converged, gains, ffs, now_over, over

        init = (states0, controls0, cost0, jnp.asarray(config.regularisation_init, cost0.dtype),
                jnp.array(0), jnp.array(False), jnp.zeros(controls0.shape + (x0.shape[0],), cost0.dtype),
                jnp.zeros_like(controls0), jnp.array(False), jnp.array(False))
        done = -1 if refresh else -2  # refresh: one pass after the one that ended the solve
        states, controls, cost, _, it, converged, gains, ffs, _, _ = jax.lax.while_loop(
            lambda carry: ~carry[done], iterate, init)
        return Solution(states, controls, gains, ffs, cost, cost0, it, converged)

    return solve


# --- planner (compiled once) -------------------------------------------------------

@functools.cache
def solver_compiler_options() -> dict:
    """CPU_SOLVER_OPTIONS on the CPU where this jaxlib knows them (a probe compile of a
    trivial function, once per process), else {} (the defaults)."""
    if jax.default_backend() != "cpu":
        return {}
    try:
        jax.jit(lambda x: x + 1, compiler_options=CPU_SOLVER_OPTIONS).lower(np.float32(0)).compile()
    except (jax.errors.JaxRuntimeError, ValueError, TypeError):  # an option this XLA lacks
        return {}
    return dict(CPU_SOLVER_OPTIONS)


def use_compile_cache(path: str) -> str:
    """Keep compiled solvers in path (JAX's persistent compilation cache): a service that
    starts again with the same vehicle, config and JAX loads the executable instead of
    compiling it (bench/ilqr.py measures both). Returns the absolute path."""
    import os
    path = os.path.abspath(os.path.expanduser(path))
    os.makedirs(path, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)  # the solvers, not every small op
    return path


@dataclass(frozen=True)
class Plan:
    """A solved plan in numpy, time 0 = the state it was solved from."""
    states: np.ndarray       # (H+1, 13)
    controls: np.ndarray     # (H, 4) rad/s
    gains: np.ndarray        # (H, 4, 13)
    feedforward: np.ndarray  # (H, 4)
    cost: float
    initial_cost: float      # of the warm start's rollout: no decrease means the solve failed
    iterations: int
    converged: bool
    dt_s: float

    @property
    def usable(self) -> bool:
        """Finite, and either converged or better than its warm start (else keep the old plan)."""
        finite = bool(np.isfinite(self.cost) and np.all(np.isfinite(self.controls))
                      and np.all(np.isfinite(self.gains)))
        return finite and (self.converged or self.cost < self.initial_cost)


class ILQRSolver:
    """iLQR for one vehicle and config; compiles at construction (the warm-up), so that
    solve() in flight never compiles (same shapes every call)."""

    def __init__(self, vehicle: Vehicle, config: ILQRConfig, warm_up: bool = True):
        request_small_loop_hoisting()
        self.vehicle = vehicle
        self.config = config
        self.motor_time_constant_s = vehicle.motor_time_constant_s if config.models_motors else None
        self.dynamics = make_dynamics(vehicle, config.dt_s, config.integrator, config.models_motors)
        self.stage_cost, self.terminal_cost = make_cost(config)
        self.u_max_rad_s = float(vehicle.max_rotor_speed_rad_s)
        self.u_hover_rad_s = hover_rotor_speed_rad_s(vehicle)
        self.models_motors = config.models_motors
        self.state_dim = BODY_DIM + (CONTROL_DIM if self.models_motors else 0)
        solver = make_solver(self.dynamics, self.stage_cost, self.terminal_cost,
                             config, 0.0, self.u_max_rad_s, make_cost_derivatives(config))

        def solve_packed(*args):  # the four scalars in one array: fewer device->host copies
            sol = solver(*args)
            scalars = jnp.stack([sol.cost, sol.initial_cost, sol.iterations.astype(sol.cost.dtype),
                                 sol.converged.astype(sol.cost.dtype)])
            return sol.states, sol.controls, sol.gains, sol.feedforward, scalars
        self._solve = jax.jit(solve_packed, compiler_options=solver_compiler_options())
        # the stops as arguments: configs that differ only in them are one program, which the
        # compilation cache (use_compile_cache) then loads instead of compiling again
        self._stops = (np.int32(config.max_iterations), np.float32(config.relative_tolerance))
        # the default warm start and control targets, converted once (the same float32s each solve)
        self._hover_controls_f32 = np.asarray(self.hover_controls(), np.float32)
        self._hover_controls_f32.flags.writeable = False
        if warm_up:
            x0 = hover_state(np.zeros(3))
            self.solve(x0, np.repeat(x0[None], config.horizon + 1, axis=0))

    def hover_controls(self) -> np.ndarray:
        return np.full((self.config.horizon, CONTROL_DIM), self.u_hover_rad_s)

    def full_state(self, x, motor_forces_n=None) -> np.ndarray:
        """The planner's state from a body state (13,): with the motor model the rotor
        forces are appended (given, else hover; a 17-vector is passed through)."""
        x = np.asarray(x, dtype=np.float64)
        if not self.models_motors or x.shape[-1] == self.state_dim:
            return x
        forces = (np.full(CONTROL_DIM, self.vehicle.hover_thrust_per_motor_n) if motor_forces_n is None
                  else np.asarray(motor_forces_n, dtype=np.float64))
        return np.concatenate([x, np.broadcast_to(forces, x.shape[:-1] + (CONTROL_DIM,))], axis=-1)

    def solve(self, x0, x_targets, u_targets=None, warm=None) -> Plan:
        """x0 (13,) or (state_dim,) (with the motor model, the rotor forces: pass the
        estimate of flight.motor_model.thrust_step, else hover is assumed); x_targets (H+1, 13) or
        (H+1, state_dim) (rotor forces carry no cost); u_targets (H, 4) (default hover);
        warm (H, 4) initial controls (default hover; pass warm_start(previous plan, elapsed))."""
        hover = self._hover_controls_f32
        x0, x_targets = self.full_state(x0), self.full_state(x_targets)
        # numpy in (jit converts it on the way; jnp.asarray per argument costs more), one copy out
        states, controls, gains, ffs, (cost, cost0, iterations, converged) = jax.device_get(self._solve(
            np.asarray(x0, np.float32), hover if warm is None else np.asarray(warm, np.float32),
            np.asarray(x_targets, np.float32), hover if u_targets is None else np.asarray(u_targets, np.float32),
            *self._stops))
        return Plan(np.asarray(states, np.float64), np.asarray(controls, np.float64),
                    np.asarray(gains, np.float64), np.asarray(ffs, np.float64),
                    float(cost), float(cost0), int(iterations), bool(converged > 0.5), self.config.dt_s)

    def loops_compiled_whole(self) -> int:
        """How many of the solve's while loops XLA compiled as one function each (the
        small-loop hoisting above; 0 where it did not apply). A diagnostic for the bench."""
        x0 = self.full_state(hover_state(np.zeros(3)))
        args = [np.zeros(shape, np.float32) for shape in (
            x0.shape, (self.config.horizon, CONTROL_DIM), (self.config.horizon + 1,) + x0.shape,
            (self.config.horizon, CONTROL_DIM))]
        return self._solve.lower(*args, *self._stops).compile().as_text().count('xla_cpu_small_call="true"')

    def compiled_count(self) -> int:
        """Number of compiled versions of the solve (1 after warm-up if shapes never change)."""
        return self._solve._cache_size()


def hover_state(position_m) -> np.ndarray:
    x = np.zeros(STATE_DIM)
    x[POS] = position_m
    x[6] = 1.0
    return x


def warm_start(plan: Plan, elapsed_s: float) -> np.ndarray:
    """The previous plan's controls re-sampled from elapsed_s on (zero-order hold, last
    control repeated): for elapsed_s = dt this is the shift by one step."""
    horizon = plan.controls.shape[0]
    idx = np.floor(elapsed_s / plan.dt_s + 1e-9).astype(int) + np.arange(horizon)
    return plan.controls[np.clip(idx, 0, horizon - 1)]


def feedback_control(plan: Plan, elapsed_s: float, x, u_max_rad_s: float) -> np.ndarray:
    """u = u_plan(t) + K(t) (x - x_plan(t)), clipped to [0, u_max]; the controls and
    gains are held over each step, the planned state interpolated linearly. The
    quaternion of x is sign-aligned with the plan's (q and -q are the same attitude).
    x has the plan's state size (with the motor model: body state + rotor forces)."""
    from flight.control.plan import plan_feedback   # the motor driver's law: one implementation
    return plan_feedback(np.asarray(plan.states), np.asarray(plan.controls), np.asarray(plan.gains),
                         plan.dt_s, elapsed_s, x, u_max_rad_s)
