"""A plan's lead over a link: the state predicted to the time the plan will fly (JAX, pure).

A planner across a link from the vehicle (the ground placement of docs/reliability.md) sees
each state some tens of milliseconds after it was measured, and its plan reaches the motor
driver as late again. Solved from the state it has and started at its own clock, every plan
begins in the past: the driver flies its later part from a state the plan did not start
from, and the flip's braking comes late (bench/flip_delay.py: 30 + 45 ms cost 13 deg of
overshoot and 0.16 s of recovery on the plant alone; without a time-consistent start, 1.4 m
of height). So the planner starts its plan where the plan will be flown, as 000 compensates
its camera's transport delay by model extrapolation: the measured state is flown forward,
from its sample time to the plan's start, on the iLQR's model (rigid body and rotor lag, the
vehicle file's), under the law the driver applies meanwhile, u = u_plan + K (x - x_plan), of
the plan sent last (flight/control/plan.py's, in JAX).
"""
from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from flight import motor_model
from flight.control.ilqr import _thrust_coefficient, make_derivative
from flight.vehicle import Vehicle

QUAT = slice(6, 10)
TICK_S = 1.0 / 400.0   # the motor driver's tick: the law's zero-order hold
MAX_TICKS = 48         # ticks flown at most (120 ms): a longer span is flown in longer ones
PLANS = 8              # the plans a prediction can fly: a link's round trip of re-solves (80 ms at 100 Hz)


def plan_feedback_jnp(states, controls, gains, dt_s, elapsed_s, x, u_max_rad_s):
    """flight.control.plan.plan_feedback in JAX (the same law, traceable)."""
    horizon = controls.shape[0]
    s = jnp.clip(elapsed_s / dt_s, 0.0, horizon - 1e-6)
    k = jnp.floor(s).astype(jnp.int32)
    frac = s - k
    x_plan = (1 - frac) * states[k] + frac * states[k + 1]
    x = jnp.asarray(x)
    sign = jnp.where(jnp.dot(x[QUAT], x_plan[QUAT]) < 0, -1.0, 1.0)
    x = x.at[QUAT].multiply(sign)
    return jnp.clip(controls[k] + gains[k] @ (x - x_plan), 0.0, u_max_rad_s)


def make_lead_predictor(vehicle: Vehicle, tick_s: float = TICK_S, plans: int = PLANS) -> Callable:
    """predict(x, sent, span) -> the state span seconds after x (the 17-state: body and rotor
    forces), flown in the driver's ticks (a span over MAX_TICKS of them: in as many longer
    ones). sent: the plans sent last, oldest first, each
    (t0 - time of x, RotorPlan-like: states, controls, gains, dt_s); at each tick the newest one
    started flies, as the motor driver picks it (before any has started: the oldest, from its
    first step). Jitted once (fixed shapes: `plans` plans of one size); numpy in and out."""
    body = make_derivative(vehicle).with_forces
    kf = float(_thrust_coefficient(vehicle))
    tau = float(vehicle.motor_time_constant_s)
    u_max = float(vehicle.max_rotor_speed_rad_s)

    def root(f):
        return jnp.sqrt(jnp.maximum(f, 0.0))

    def predict(x, starts, states, controls, gains, plan_dt_s, span_s):
        tick_len = jnp.maximum(tick_s, span_s / MAX_TICKS)

        def tick(x, k):
            now = k * tick_len
            dt = jnp.clip(span_s - now, 1e-6, tick_len)   # the last tick cut at the span; after it, none
            i = jnp.maximum(jnp.sum(starts <= now + 1e-6) - 1, 0)   # the newest plan started
            u = plan_feedback_jnp(states[i], controls[i], gains[i], plan_dt_s, now - starts[i], x, u_max)
            forces, mean = motor_model.thrust_step_and_mean(x[13:], kf * u * u, dt, tau, root, jnp.exp)
            b = x[:13]
            k1 = body(b, mean)
            k2 = body(b + 0.5 * dt * k1, mean)
            k3 = body(b + 0.5 * dt * k2, mean)
            k4 = body(b + dt * k3, mean)
            b = b + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
            b = b.at[QUAT].set(b[QUAT] / jnp.linalg.norm(b[QUAT]))
            return jnp.where(now < span_s - 1e-6, jnp.concatenate([b, forces]), x), None

        x, _ = jax.lax.scan(tick, x, jnp.arange(MAX_TICKS, dtype=x.dtype))
        return x

    compiled = jax.jit(predict)

    def run(x, sent, span_s: float) -> np.ndarray:
        if span_s <= 0.0 or not sent:
            return np.asarray(x, dtype=np.float64)
        sent = list(sent)[-plans:]
        sent = [sent[0]] * (plans - len(sent)) + sent   # padded with the oldest: never chosen over it
        f32 = np.float32
        out = compiled(np.asarray(x, f32), np.array([s for s, _ in sent], f32),
                       np.stack([p.states for _, p in sent]).astype(f32),
                       np.stack([p.controls for _, p in sent]).astype(f32),
                       np.stack([p.gains for _, p in sent]).astype(f32), f32(sent[-1][1].dt_s), f32(span_s))
        return np.asarray(jax.device_get(out), dtype=np.float64)

    return run
