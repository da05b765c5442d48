"""The flip's rollouts that re-plan: the flown controller's loop in JAX (issue 25 item 1).

flight/control/predict.py's default rollouts replay a time-varying affine policy (the plans and
gains the controller flew on each vehicle, interpolated between the knots' flights); the flown
controller (flight/control/flip_runner.FlipController) re-plans from the state at 100 Hz, so
it answers the wind, the gusts, the start's error and the vehicle itself, which one set of
gains does not (docs/flip-history.md). These rollouts put that loop inside the batch: per case,

* the phase machine of flight/control/flip.FlipPhaseMachine (the project's flip: flip ->
  recovery -> the settle's hold) and its targets, on the case's own state, every tick;
* every `replan_ticks` ticks a re-plan from the state (the file's model, as the planner's),
  warm-started from the previous plan shifted by the time since: exact=True the planner's own
  solve (flight/control/ilqr.make_solver: the flown loop); else `iterations` passes of
  linearisation, Riccati backward pass and line search, the linearisation the case's own or,
  reference=True, the nominal flight's at the same time (make_reference; the gradient and the
  line search stay the case's);
* between re-plans the motor driver's law u = u_plan + K (x - x_plan) (flight/control/plan.plan_feedback),
  the control delay, the case's plant (predict._plant_step) and gusts, as predict.make_rollouts.

No anchor flights: each case's answer to its vehicle is its own re-planning. Measured
(docs/flip-history.md, "Re-planning inside the rollouts"): the exact loop models each flown case
to 0.01 m and 0.2 deg but costs ~0.5 s a re-plan for 1000 cases on a 2-core CPU (~30-40 min a
prediction); below 100 Hz the controller is another one, and the nominal's linearisation
(~20 s) spreads less than flown. predict.Predictor(replan=Replan(...)) flies them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flight import motor_model
from flight.control.flip import PROJECT_FLIP
from flight.control.predict import (TICK_RATE_HZ, PredictError, _jnp_root, _plant_step, euler_roll, fly_nominal,
                                    start_body)
from flight.quat import quat_multiply, wrap_angle

TWO_PI = 2.0 * math.pi
FLIP, RECOVERY, SETTLE = 0, 1, 2     # the phases a rollout goes through (it starts at the flip's)


def euler_yaw(q, jnp):
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def nominal_solves(nominal) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The nominal flight flown again (lockstep: the same flight), each of its solves kept:
    (states (J, H+1, n_x), controls (J, H, 4), targets (J, H+1, n_x)), float32, one a solve
    (every 1 / solve_rate_hz from t = 0; a solve that was not used kept all the same)."""
    c = nominal.controller
    planner = c.planner
    kept = []
    solve = planner.solve

    def recording(x0, x_targets, u_targets=None, warm=None):
        plan = solve(x0, x_targets, u_targets, warm)
        kept.append((plan.states, plan.controls, planner.full_state(x_targets)))
        return plan
    planner.solve = recording   # an instance attribute over the method, removed below
    try:
        fly_nominal(nominal.vehicle, nominal.method, nominal.altitude_m, controller=c)
    finally:
        del planner.solve
    return tuple(np.stack([k[i] for k in kept]).astype(np.float32) for i in range(3))


def make_reference(nominal, horizon: int | None = None):
    """Per nominal solve j (J, H, ...): the model's Jacobians A, B at its plan and the Riccati
    pass's gains K and inverse Quu (regularised as the solver's): the linearisation the
    reference re-plans reuse (make_replan_rollouts(reference=True))."""
    import jax
    import jax.numpy as jnp

    from flight.control.ilqr import make_cost_derivatives, make_dynamics
    c = nominal.controller
    config = c.ilqr_config
    h = horizon or config.horizon
    states, controls, targets = nominal_solves(nominal)
    states, controls, targets = states[:, :h + 1], controls[:, :h], targets[:, :h + 1]
    dynamics = make_dynamics(nominal.vehicle, config.dt_s, config.integrator, True)
    stage_d, terminal_d = make_cost_derivatives(config)
    u_hover = float(np.sqrt(nominal.vehicle.hover_thrust_per_motor_n / nominal.vehicle.thrust_coefficient_kf))
    mu = config.regularisation_init

    def one(xs, us, ts):
        A, B = jax.vmap(jax.jacfwd(dynamics, argnums=(0, 1)))(xs[:-1], us)
        _, _, lxx, luu, lux = jax.vmap(stage_d)(xs[:-1], us, ts[:-1], jnp.full_like(us, u_hover))
        _, vxx_final = terminal_d(xs[-1], ts[-1])

        def step(vxx, d):
            a, b, qxx_l, quu_l, qux_l = d
            vxx = 0.5 * (vxx + vxx.T)
            qxx = qxx_l + a.T @ vxx @ a
            quu = quu_l + b.T @ vxx @ b + mu * jnp.eye(4)
            qux = qux_l + b.T @ vxx @ a
            quu_inv = jnp.linalg.inv(quu)
            k = -quu_inv @ qux
            return qxx + k.T @ quu @ k + k.T @ qux + qux.T @ k, (k, quu_inv)
        _, (K, quu_inv) = jax.lax.scan(step, vxx_final, (A, B, lxx, luu, lux), reverse=True)
        return A, B, K, quu_inv
    out = jax.jit(jax.vmap(one))(states, controls, targets)
    return tuple(np.asarray(a, np.float32) for a in out)


def make_replan_rollouts(nominal, uncertainty, max_delay_ticks: int, replan_ticks: int = 10,
                         iterations: int = 1, alphas=(1.0, 0.5, 0.25), horizon: int | None = None,
                         replan_until_s: float | None = None, reference: bool = False, exact: bool = False):
    """A jitted rollouts(cases, x0, controls0, gains0) -> per tick (N, T, 6), make_rollouts'
    columns (z, x, y, accumulated roll, tilt, body-rate norm); cases as predict.draw_cases
    gives them; controls0 (H, 4), gains0 (H, 4, n_x): the controller's first plan from the
    nominal's start (initial_plan), which each case's first re-plan starts from."""
    import jax
    import jax.numpy as jnp

    from flight.control.ilqr import _backward_pass, make_cost, make_cost_derivatives, make_dynamics, make_solver

    c = nominal.controller
    if c is None or getattr(c, "planner", None) is None or c.flip_config != PROJECT_FLIP:
        raise ValueError("the re-planning rollouts fly the project's iLQR flip (ilqr-project)")
    vehicle = nominal.vehicle
    config = c.ilqr_config
    fc = c.flip_config
    if not config.models_motors:
        raise ValueError("the re-planning rollouts need the solver's motor model (PROJECT)")
    dt_s = nominal.tick_s
    h, plan_dt = (horizon or config.horizon), config.dt_s
    n_x = c.state_dim
    kf = float(vehicle.thrust_coefficient_kf)
    u_max = float(vehicle.max_rotor_speed_rad_s)
    ctrl_decay = motor_model.decay(dt_s, c.motor_time_constant_s)
    step = _plant_step(vehicle, dt_s).raw
    gust_decay = float(np.exp(-dt_s / uncertainty.gust_time_s)) if uncertainty.gust_m_s > 0 else 0.0
    gust_gain = uncertainty.gust_m_s * math.sqrt(1.0 - gust_decay ** 2)
    hover_f = float(vehicle.hover_thrust_per_motor_n)
    u_hover = float(np.sqrt(hover_f / kf))
    ticks = nominal.ticks
    blocks = -(-ticks // replan_ticks)
    solve_ticks = max(1, round(1.0 / (c.solve_rate_hz * dt_s)))
    if reference and replan_ticks % solve_ticks:
        raise ValueError(f"reference re-plans every multiple of the controller's {solve_ticks} ticks")
    alphas = jnp.asarray(alphas, jnp.float32)
    mu = float(config.regularisation_init)

    dynamics = make_dynamics(vehicle, plan_dt, config.integrator, True)
    stage_cost, terminal_cost = make_cost(config)
    stage_d, terminal_d = make_cost_derivatives(config)
    solver = make_solver(dynamics, stage_cost, terminal_cost, config, 0.0, u_max, (stage_d, terminal_d))
    jac = jax.vmap(jax.jacfwd(dynamics, argnums=(0, 1)))
    u_targets = jnp.full((h, 4), u_hover, jnp.float32)
    k_steps = jnp.arange(h + 1, dtype=jnp.float32) * plan_dt
    alphas_h = jnp.arange(h, dtype=jnp.float32) / config.horizon   # the recovery's ramp, as flown
    # re-plans up to replan_until_s, then the last plan held (its last step's control and gains):
    # the figures are made by then (the recovery's hold), and the re-plans are the cost
    active = blocks if replan_until_s is None else min(blocks, max(1, int(math.ceil(
        replan_until_s / (replan_ticks * dt_s)))))

    def rollout(x0, controls):
        def f(x, u):
            x1 = dynamics(x, u)
            return x1, x1
        _, xs = jax.lax.scan(f, x0, controls)
        return jnp.concatenate([x0[None], xs])

    def cost_of(states, controls, targets):
        stage = jax.vmap(stage_cost)(states[:-1], controls, targets[:-1], u_targets)
        return jnp.sum(stage) + terminal_cost(states[-1], targets[-1])

    def forward(states, controls, gains, ffs, alpha):
        def f(x, d):
            x_ref, u_ref, gain, ff = d
            u = jnp.clip(u_ref + alpha * ff + jnp.sum(gain * (x - x_ref), axis=1), 0.0, u_max)
            x1 = dynamics(x, u)
            return x1, (x1, u)
        _, (xs, us) = jax.lax.scan(f, states[0], (states[:-1], controls, gains, ffs))
        return jnp.concatenate([states[:1], xs]), us

    def ilqr_step(states, controls, targets):
        """One iLQR iteration from a rolled-out plan: (states, controls, gains, cost, improved)."""
        A, B = jac(states[:-1], controls)
        lx, lu, lxx, luu, lux = jax.vmap(stage_d)(states[:-1], controls, targets[:-1], u_targets)
        gains, ffs, pd = _backward_pass((A, B, lx, lu, lxx, luu, lux, *terminal_d(states[-1], targets[-1])), mu)
        cand_x, cand_u = jax.vmap(forward, in_axes=(None, None, None, None, 0))(states, controls, gains, ffs, alphas)
        costs = jax.vmap(cost_of, in_axes=(0, 0, None))(cand_x, cand_u, targets)
        costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)
        best = jnp.argmin(costs)
        return cand_x[best], cand_u[best], gains, costs[best], pd

    def reference_step(states, controls, targets, ref):
        """An iLQR iteration on the nominal's linearisation at the same time (ref: its A, B, K and
        Quu^-1): the gradient of the case's own cost along its own rolled-out plan, the
        Riccati recursion's vector part, the line search on the model itself."""
        A, B, K, quu_inv = ref
        lx, lu, _, _, _ = jax.vmap(stage_d)(states[:-1], controls, targets[:-1], u_targets)
        vx_final, _ = terminal_d(states[-1], targets[-1])

        def back(vx, d):
            a, b, k, qi, lx_k, lu_k = d
            qx = lx_k + vx @ a
            qu = lu_k + vx @ b
            return qx + qu @ k, -qi @ qu
        _, ffs = jax.lax.scan(back, vx_final, (A, B, K, quu_inv, lx, lu), reverse=True)
        cand_x, cand_u = jax.vmap(forward, in_axes=(None, None, None, None, 0))(states, controls, K, ffs, alphas)
        costs = jax.vmap(cost_of, in_axes=(0, 0, None))(cand_x, cand_u, targets)
        costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)
        best = jnp.argmin(costs)
        return cand_x[best], cand_u[best], K, costs[best], jnp.bool_(True)

    def quat_roll(r):
        return jnp.stack([jnp.cos(r / 2), jnp.sin(r / 2), jnp.zeros_like(r), jnp.zeros_like(r)], axis=-1)

    def targets_of(ctl, t, x):
        """FlipPhaseMachine.targets / settle_targets for the case's phase (H+1, n_x)."""
        phase, roll_now, flip_point = ctl["phase"], ctl["roll"], ctl["flip_point"]
        # the flip: the look-ahead turn about the flip point, climb_m above it
        roll_ref, rate_ref = flip_reference_jnp(t + k_steps[:h])
        error = roll_ref - roll_now
        lead = (fc.flip_gain_base + fc.flip_gain_tanh * jnp.tanh(error)) * error
        flip_rolls = roll_now + jnp.clip(lead, -fc.max_lead_rad, fc.max_lead_rad)
        flip_pos = jnp.broadcast_to(flip_point + jnp.array([0.0, 0.0, fc.climb_m]), (h, 3))
        flip_q = quat_roll(flip_rolls)
        flip_rate = jnp.zeros((h, 3)).at[:, 0].set(rate_ref + fc.flip_rate_error_gain * error[0])
        flip_v = jnp.zeros((h, 3))
        # the recovery: level at the heading it has, coasting at its horizontal velocity
        rerr = TWO_PI - roll_now
        gain = fc.recovery_gain_base + fc.recovery_gain_error * jnp.abs(rerr) / math.pi
        rec_rolls = roll_now + alphas_h * gain * rerr
        yaw = euler_yaw(x[6:10], jnp)
        heading = jnp.array([jnp.cos(yaw / 2), 0.0, 0.0, jnp.sin(yaw / 2)])
        rec_q = jax.vmap(lambda r: quat_multiply(heading, quat_roll(r), jnp))(rec_rolls)
        rec_pos = jnp.concatenate([x[0:2] + x[3:5] * k_steps[:h, None],
                                   jnp.full((h, 1), flip_point[2])], axis=1)
        rec_v = jnp.concatenate([jnp.broadcast_to(x[3:5], (h, 2)), jnp.zeros((h, 1))], axis=1)
        rec_rate = jnp.zeros((h, 3))
        # the settle's hold: a straight stop at settle_decel_m_s2, yaw back to 0 at its rate
        decel = fc.settle_decel_m_s2
        v0 = ctl["brake_v"]
        speed = jnp.linalg.norm(v0)
        direction = jnp.where(speed > 1e-9, v0 / jnp.maximum(speed, 1e-9), 0.0)
        tau = jnp.minimum(jnp.maximum(t - ctl["brake_t"] + k_steps, 0.0), speed / decel)
        travelled = speed * tau - 0.5 * decel * tau * tau
        set_xy = ctl["brake_xy"] + travelled[:, None] * direction
        set_v = (speed - decel * tau)[:, None] * direction
        start_yaw = ctl["settle_yaw"]
        yaw_rate = -jnp.sign(start_yaw) * fc.settle_yaw_rate_rad_s
        times = t - ctl["settle_t"] + k_steps
        turning = times < jnp.abs(start_yaw) / jnp.maximum(jnp.abs(yaw_rate), 1e-9)
        yaws = jnp.where(turning, start_yaw + yaw_rate * times, 0.0)
        set_q = jnp.stack([jnp.cos(yaws / 2), jnp.zeros_like(yaws), jnp.zeros_like(yaws), jnp.sin(yaws / 2)], axis=1)
        set_rate = jnp.zeros((h + 1, 3)).at[:, 2].set(jnp.where(turning, yaw_rate, 0.0))
        settle = jnp.concatenate([set_xy, jnp.full((h + 1, 1), flip_point[2]), set_v, jnp.zeros((h + 1, 1)),
                                  set_q, set_rate], axis=1)

        def padded(pos, v, q, rate):
            rows = jnp.concatenate([pos, v, q, rate], axis=1)
            return jnp.concatenate([rows, rows[-1:]])
        body = jnp.where(phase == FLIP, padded(flip_pos, flip_v, flip_q, flip_rate),
                         jnp.where(phase == RECOVERY, padded(rec_pos, rec_v, rec_q, rec_rate), settle))
        return jnp.concatenate([body, jnp.zeros((h + 1, n_x - 13))], axis=1)

    def flip_reference_jnp(t):
        s = jnp.clip((t - fc.windup_s) / fc.flip_duration_s, 0.0, 1.0)
        roll = TWO_PI * (10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5)
        rate = TWO_PI / fc.flip_duration_s * (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4)
        return roll, rate   # no wind-up roll in the project's flip (windup_rad 0)

    def machine_update(ctl, t, x):
        """FlipPhaseMachine.update and the runner's settle bookkeeping after the tick's state."""
        q = x[6:10]
        r = euler_roll(q, jnp)
        roll = ctl["roll"] + wrap_angle(r - ctl["last"], jnp)
        rate_norm = jnp.linalg.norm(x[10:13])
        phase = ctl["phase"]
        to_recovery = (phase == FLIP) & (roll >= TWO_PI - fc.turn_tolerance_rad)
        to_settle = (phase == RECOVERY) & (jnp.abs(roll - TWO_PI) <= fc.level_tolerance_rad) & \
            (rate_norm < fc.level_rate_rad_s)
        new_phase = jnp.where(to_recovery, RECOVERY, jnp.where(to_settle, SETTLE, phase))
        out = dict(ctl, roll=roll, last=r, phase=new_phase)
        # the hold's start: where and how fast it is, its heading (settle_hold_point's first call)
        out["settle_t"] = jnp.where(to_settle, t, ctl["settle_t"])
        out["settle_yaw"] = jnp.where(to_settle, euler_yaw(q, jnp), ctl["settle_yaw"])
        # while the stop lasts, a vehicle that would stop further on moves the stop on
        decel = fc.settle_decel_m_s2
        v0, xy0 = ctl["brake_v"], ctl["brake_xy"]
        speed = jnp.linalg.norm(v0)
        sp_now = x[0:2] + x[3:5] * jnp.linalg.norm(x[3:5]) / (2 * decel)
        sp_then = xy0 + v0 * speed / (2 * decel)
        moves_on = (phase == SETTLE) & (speed > 0) & (t - ctl["brake_t"] < speed / decel) & \
            (jnp.dot(sp_now - sp_then, v0) > 0)
        renew = to_settle | moves_on
        out["brake_t"] = jnp.where(renew, t, ctl["brake_t"])
        out["brake_xy"] = jnp.where(renew, x[0:2], xy0)
        out["brake_v"] = jnp.where(renew, x[3:5], v0)
        return out

    def one(case, x0, controls0, gains0, ref):
        body0, q0 = start_body(case, x0, jnp)
        forces0 = jnp.full(4, hover_f, jnp.float32)
        params = {k: case[k] for k in ("mass", "inertia", "thrust_scale", "tau")}
        buffer0 = jnp.tile((kf * u_hover ** 2) * jnp.ones((1, 4), jnp.float32), (max_delay_ticks + 1, 1))
        r0 = euler_roll(q0, jnp)
        ctl0 = {"phase": jnp.int32(FLIP), "roll": jnp.float32(0.0), "last": r0, "flip_point": body0[0:3],
                "settle_t": jnp.float32(0.0), "settle_yaw": jnp.float32(0.0), "brake_t": jnp.float32(0.0),
                "brake_xy": jnp.zeros(2, jnp.float32), "brake_v": jnp.zeros(2, jnp.float32)}
        x_ctrl0 = jnp.concatenate([body0, forces0])
        plan0 = (rollout(x_ctrl0, controls0), controls0, gains0, jnp.float32(0.0))
        noise = case["gust_noise"]
        pad = blocks * replan_ticks - noise.shape[0]
        noise = jnp.concatenate([noise, jnp.zeros((pad, 3), noise.dtype)]).reshape(blocks, replan_ticks, 3)

        def replan(plan, ctl, t, x_ctrl, ref_j):
            states, controls, gains, plan_t = plan
            shift = jnp.floor((t - plan_t) / plan_dt + 1e-4).astype(jnp.int32)
            warm = controls[jnp.clip(shift + jnp.arange(h), 0, h - 1)]
            targets = targets_of(ctl, t, x_ctrl)
            if exact:   # the planner's own solve, its stops and its usable test (ILQRSolver, Plan.usable)
                sol = solver(x_ctrl, warm, targets, u_targets)
                usable = (jnp.isfinite(sol.cost) & jnp.all(jnp.isfinite(sol.controls)) & jnp.all(jnp.isfinite(sol.gains))
                          & (sol.converged | (sol.cost < sol.initial_cost)))
                return jax.tree_util.tree_map(lambda new, old: jnp.where(usable, new, old),
                                              (sol.states, sol.controls, sol.gains, t), plan)
            xs = rollout(x_ctrl, jnp.clip(warm, 0.0, u_max))
            us = jnp.clip(warm, 0.0, u_max)
            cost0 = cost_of(xs, us, targets)
            cost, ok = cost0, jnp.bool_(True)
            g = gains
            for _ in range(iterations):
                if reference:
                    xs, us, g, cost, pd = reference_step(xs, us, targets, ref_j)
                else:
                    xs, us, g, cost, pd = ilqr_step(xs, us, targets)
                ok = ok & pd
            usable = ok & jnp.isfinite(cost) & (cost < cost0)
            return jax.tree_util.tree_map(lambda new, old: jnp.where(usable, new, old),
                                          (xs, us, g, t), plan)

        def tick(carry, inputs):
            body, forces, est, buffer, gust, roll, last, ctl, plan = carry
            t, nz = inputs
            states, controls, gains, plan_t = plan
            x_ctrl = jnp.concatenate([body, est])
            sk = jnp.clip((t - plan_t) / plan_dt, 0.0, h - 1e-3)
            k = sk.astype(jnp.int32)
            frac = sk - k
            xp = (1 - frac) * states[k] + frac * states[k + 1]
            sign = jnp.where(jnp.sum(x_ctrl[6:10] * xp[6:10]) < 0, -1.0, 1.0)
            aligned = x_ctrl.at[6:10].multiply(sign)
            u = jnp.clip(controls[k] + gains[k] @ (aligned - xp), 0.0, u_max)
            command = kf * u * u
            # the driver's delay line starts full of the first command (bench/predict_calibration.fly_case)
            buffer = jnp.where(t > 0, jnp.concatenate([command[None], buffer[:-1]]),
                               jnp.broadcast_to(command, buffer.shape))
            applied = buffer[case["delay_ticks"]]
            body_next, forces_next = step(body, forces, applied, params | {"wind": case["wind"] + gust})
            est_next = motor_model.root_step(_jnp_root(est), _jnp_root(command), ctrl_decay) ** 2
            gust_next = gust * gust_decay + gust_gain * nz
            r = euler_roll(body[6:10], jnp)
            roll_next = roll + wrap_angle(r - last, jnp)
            q = body[6:10]
            tilt = jnp.arccos(jnp.clip((q[0] ** 2 - q[1] ** 2 - q[2] ** 2 + q[3] ** 2) / jnp.sum(q * q), -1.0, 1.0))
            out = jnp.stack([body[2], body[0], body[1], roll_next, tilt, jnp.linalg.norm(body[10:13])])
            ctl = machine_update(ctl, t + dt_s, jnp.concatenate([body_next, est_next]))
            return (body_next, forces_next, est_next, buffer, gust_next, roll_next, r, ctl, plan), out

        def block(carry, inputs):
            body, forces, est, buffer, gust, roll, last, ctl, plan = carry
            b, nz, ref_j = inputs
            t0 = b.astype(jnp.float32) * (replan_ticks * dt_s)
            plan = replan(plan, ctl, t0, jnp.concatenate([body, est]), ref_j)
            times = t0 + jnp.arange(replan_ticks, dtype=jnp.float32) * dt_s
            carry, outs = jax.lax.scan(tick, (body, forces, est, buffer, gust, roll, last, ctl, plan), (times, nz))
            return carry, outs

        carry0 = (body0, forces0, forces0, buffer0, jnp.zeros(3, jnp.float32), jnp.float32(0.0), r0, ctl0, plan0)
        if reference:   # the nominal's solve at each re-plan's time (solves every solve_ticks from 0)
            ref_rows = jax.tree_util.tree_map(lambda a: a[::replan_ticks // solve_ticks][:active], ref)
        else:
            ref_rows = jnp.zeros(active)
        carry, outs = jax.lax.scan(block, carry0, (jnp.arange(active), noise[:active], ref_rows))
        outs = outs.reshape(active * replan_ticks, 6)
        if active < blocks:
            times = jnp.arange(active * replan_ticks, blocks * replan_ticks, dtype=jnp.float32) * dt_s
            _, tail = jax.lax.scan(tick, carry, (times, noise[active:].reshape(-1, 3)))
            outs = jnp.concatenate([outs, tail])
        return outs[:ticks]

    def sized(case, x0, controls0, gains0, ref=None):
        return one(case, x0, controls0[:h], gains0[:h], ref)

    batched = jax.vmap(sized, in_axes=(0, None, None, None, None))
    return jax.jit(batched)


def initial_plan(nominal) -> tuple[np.ndarray, np.ndarray]:
    """(controls (H, 4), gains (H, 4, n_x)), float32: the controller's converged plan at the
    nominal's start (its first solve, from hover warm start, up to max_iterations)."""
    c = nominal.controller
    c.start(0.0, nominal.x0, nominal.altitude_m)
    c.step(0.0, nominal.x0, 1.0, solve=True)
    return c.plan.controls.astype(np.float32), c.plan.gains.astype(np.float32)


@dataclass(frozen=True)
class Replan:
    """The re-planning rollouts' settings: an iLQR step every
    1 / rate_hz from the case's state (the flown controller: 100 Hz, to convergence), with
    `iterations` passes, over `horizon` steps of the plan (None: the controller's), until
    hold_s after the nominal's recovery (then the last plan held). linearise "case": each pass
    linearises the model along the case's own plan (the solver's iteration); "nominal": the
    nominal flight's linearisation and Riccati matrices at the same time, the gradient and the
    line search the case's own (flight/control/replan.make_reference; ~20x cheaper); "solver":
    the planner's own solve per case (its iterations, stops and gains: the flown loop; the
    iterations and alphas settings unused)."""
    rate_hz: float = 40.0
    iterations: int = 1
    horizon: int | None = None
    hold_s: float = 0.8
    alphas: tuple = (1.0, 0.5, 0.25)
    linearise: str = "case"

    def __post_init__(self):
        ticks = TICK_RATE_HZ / self.rate_hz if math.isfinite(self.rate_hz) and self.rate_hz > 0 else 0.0
        if not (abs(ticks - round(ticks)) < 1e-6 and round(ticks) >= 1):
            raise PredictError(f"replan rate_hz must divide {TICK_RATE_HZ:g} Hz (got {self.rate_hz!r})")
        if self.iterations < 1 or (self.horizon is not None and self.horizon < 2) or not self.hold_s >= 0:
            raise PredictError(f"replan iterations >= 1, horizon >= 2, hold_s >= 0 (got {self!r})")
        if not self.alphas or not all(0 < a <= 1 for a in self.alphas):
            raise PredictError(f"replan alphas in (0, 1] (got {self.alphas!r})")
        if self.linearise not in ("case", "nominal", "solver"):
            raise PredictError(f"replan linearise 'case', 'nominal' or 'solver' (got {self.linearise!r})")

    @property
    def ticks(self) -> int:
        return int(round(TICK_RATE_HZ / self.rate_hz))

    def rollouts(self, nominal, uncertainty, max_delay_ticks: int) -> tuple:
        """(the jitted rollouts, their tables after the start state) for Predictor(replan=self)."""
        if nominal.method != "ilqr-project":
            raise PredictError(f"the re-planning rollouts fly the project's flip (ilqr-project), not {nominal.method}")
        if "land" not in nominal.phases:
            raise PredictError("the nominal flight never recovered: nothing to re-plan to")
        until_s = nominal.phases.index("land") * nominal.tick_s + self.hold_s
        nominal_lin = self.linearise == "nominal"
        rollouts = make_replan_rollouts(nominal, uncertainty, max_delay_ticks, self.ticks, self.iterations,
                                        self.alphas, self.horizon, until_s, reference=nominal_lin,
                                        exact=self.linearise == "solver")
        return rollouts, initial_plan(nominal) + (make_reference(nominal, self.horizon) if nominal_lin else None,)

