"""Transcription of the thesis's iLQR (001, Appendices A and B) as the benchmark baseline.

Kept as the thesis wrote it: Python loops over the horizon inside @jit functions
(unrolled at trace time), jacobian/grad/hessian per step, jnp.linalg.inv of Quu + 1e-6 I,
alpha = 1 with no line search, and a Python loop over the iterations calling the jitted
pieces. Two changes, both needed to run it: simulate_trajectory rolls the state forward
(the thesis's vmap applies every control to x0), and the constants come from the vehicle
file (the thesis's values). Not project code.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import grad, hessian, jacobian, jit

from flight.vehicle import Vehicle

Q = jnp.diag(jnp.array([1.0, 1.0, 10.0, 1.0, 1.0, 1.0, 0.0, 50.0, 50.0, 0.0, 5.0, 5.0, 1.0]))
R = jnp.diag(jnp.array([0.001, 0.001, 0.001, 0.001]))
Qf = jnp.diag(jnp.array([1.0, 1.0, 10.0, 0.1, 0.1, 0.1, 0.0, 100.0, 100.0, 0.0, 10.0, 10.0, 1.0]))


def quat_multiply(q1, q2):
    w1, x1, y1, z1 = q1
    w2, x2, y2, z2 = q2
    return jnp.array([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ])


def quat_to_rot_matrix(q):
    w, x, y, z = q
    return jnp.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def make_thesis_ilqr(vehicle: Vehicle, dt: float = 0.1, horizon: int = 10, compiler_options: dict | None = None):
    """The thesis's ILQROptimizer.solve(x0, u_init, x_target_traj, u_target_traj, ...).
    compiler_options: XLA options for the four functions solve calls (the benchmark gives
    it the project solver's, to show what they are worth here); None: JAX's defaults."""
    top_jit = functools.partial(jit, compiler_options=compiler_options) if compiler_options else jit
    m, arm = vehicle.mass_kg, vehicle.motor_positions_m[0][0]
    inertia = jnp.diag(jnp.asarray(vehicle.inertia_kg_m2))
    kf, km = vehicle.thrust_coefficient_kf, vehicle.moment_coefficient_km
    drag, max_speed = vehicle.drag_n_per_m_s, vehicle.max_rotor_speed_rad_s
    n_u = 4

    @jit
    def f(x, u, dt):
        g = jnp.array([0.0, 0.0, vehicle.gravity_m_s2])
        pos, vel, quat, omega = x[0:3], x[3:6], x[6:10], x[10:13]
        quat_norm = jnp.linalg.norm(quat)
        quat = jax.lax.cond(quat_norm < 1e-8, lambda _: jnp.array([1.0, 0.0, 0.0, 0.0]),
                            lambda _: quat / quat_norm, operand=None)
        r_bw = quat_to_rot_matrix(quat)
        rpm = jnp.clip(u, 0.0, max_speed)
        w_squared = rpm ** 2
        thrusts = kf * w_squared
        fz_body = jnp.array([0.0, 0.0, jnp.sum(thrusts)])
        f_world = r_bw @ fz_body - m * g - drag * vel
        acc = f_world / m
        new_vel = vel + acc * dt
        new_pos = pos + vel * dt + 0.5 * acc * dt ** 2
        tau = jnp.array([
            arm * (thrusts[1] - thrusts[3]),
            arm * (thrusts[2] - thrusts[0]),
            km * (w_squared[0] - w_squared[1] + w_squared[2] - w_squared[3]),
        ])
        omega_dot = jnp.linalg.solve(inertia, tau - jnp.cross(omega, inertia @ omega))
        new_omega = omega + omega_dot * dt
        dq = 0.5 * quat_multiply(quat, jnp.concatenate([jnp.array([0.0]), new_omega]))
        new_quat = quat + dq * dt
        new_quat /= jnp.linalg.norm(new_quat + 1e-8)
        return jnp.concatenate([new_pos, new_vel, new_quat, new_omega])

    @top_jit
    def simulate_trajectory(x0, U):
        X = [x0]
        for k in range(horizon):
            X.append(f(X[-1], U[k], dt))
        return jnp.stack(X)

    @jit
    def linearize_dynamics(x, u):
        return jacobian(f, argnums=0)(x, u, dt), jacobian(f, argnums=1)(x, u, dt)

    @jit
    def quadratize_cost(x, u, x_target, u_target, Q, R):
        def scalar_cost(x_, u_):
            dx = x_ - x_target
            du = u_ - u_target
            return dx @ Q @ dx + du @ R @ du
        lx = grad(scalar_cost, argnums=0)(x, u)
        lu = grad(scalar_cost, argnums=1)(x, u)
        lxx = hessian(scalar_cost, argnums=0)(x, u)
        luu = hessian(scalar_cost, argnums=1)(x, u)
        lux = jacobian(grad(scalar_cost, argnums=1), argnums=0)(x, u)
        return lx, lu, lxx, luu, lux

    @top_jit
    def backward_pass(X, U, x_target_traj, u_target_traj, Q, R, Qf):
        Vx = grad(lambda x: jnp.dot(x - x_target_traj[-1], Qf @ (x - x_target_traj[-1])))(X[-1])
        Vxx = Qf
        K_list, k_list = [], []
        for k in reversed(range(horizon)):
            A, B = linearize_dynamics(X[k], U[k])
            lx, lu, lxx, luu, lux = quadratize_cost(X[k], U[k], x_target_traj[k], u_target_traj[k], Q, R)
            Qx = lx + A.T @ Vx
            Qu = lu + B.T @ Vx
            Qxx = lxx + A.T @ Vxx @ A
            Quu = luu + B.T @ Vxx @ B
            Qux = lux + B.T @ Vxx @ A
            Quu_inv = jnp.linalg.inv(Quu + 1e-6 * jnp.eye(n_u))
            K = -Quu_inv @ Qux
            kff = -Quu_inv @ Qu
            Vx = Qx + K.T @ Quu @ kff + K.T @ Qu + Qux.T @ kff
            Vxx = Qxx + K.T @ Quu @ K + K.T @ Qux + Qux.T @ K
            K_list.insert(0, K)
            k_list.insert(0, kff)
        return K_list, k_list

    @top_jit
    def forward_pass(X, U, k_list, K_list, alpha):
        x = X[0]
        X_new, U_new = [x], []
        for k in range(horizon):
            u_new = U[k] + alpha * (k_list[k] + K_list[k] @ (x - X[k]))
            U_new.append(u_new)
            x = f(x, u_new, dt)
            X_new.append(x)
        return jnp.stack(X_new), jnp.stack(U_new)

    @top_jit
    def cost_function_traj_flip(x_traj, u_traj, x_target_traj, u_target_traj, Q, R, Qf):
        def step_cost(x, u, x_target, u_target, is_terminal=False):
            position_error = x[0:3] - x_target[0:3]
            position_cost = position_error @ Q[0:3, 0:3] @ position_error
            q_current = x[6:10] / jnp.linalg.norm(x[6:10])
            q_target = x_target[6:10] / jnp.linalg.norm(x_target[6:10])
            dot = jnp.clip(jnp.dot(q_current, q_target), -1.0, 1.0)
            orientation_error = 2.0 * jnp.arccos(jnp.abs(dot))
            cost = position_cost + orientation_error ** 2 * Q[6, 6] + (u - u_target) @ R @ (u - u_target)
            if is_terminal:
                cost = cost + position_error @ Qf[0:3, 0:3] @ position_error + orientation_error ** 2 * Qf[6, 6]
            return cost
        total = 0.0
        for k in range(horizon):
            total = total + step_cost(x_traj[k], u_traj[k], x_target_traj[k], u_target_traj[k],
                                      is_terminal=k == horizon - 1)
        return total

    def solve(x0, u_init, x_target_traj, u_target_traj, Q=Q, R=R, Qf=Qf, max_iters=5, tol=1e-3, alpha=1.0):
        X = simulate_trajectory(x0, u_init)
        U = u_init
        for i in range(max_iters):
            cost_prev = cost_function_traj_flip(X, U, x_target_traj, u_target_traj, Q, R, Qf)
            K_list, k_list = backward_pass(X, U, x_target_traj, u_target_traj, Q, R, Qf)
            X_new, U_new = forward_pass(X, U, k_list, K_list, alpha)
            cost_new = cost_function_traj_flip(X_new, U_new, x_target_traj, u_target_traj, Q, R, Qf)
            if jnp.abs(cost_prev - cost_new) < tol:
                break
            X, U = X_new, U_new
        return X, U, i, cost_new

    return solve
