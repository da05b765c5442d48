"""The gyro-vertical of 004, batched in JAX, for training.

Training (004's criterion (10)) runs the filter over 9 sequences per flight
for every parameter vector the optimiser tries; the filter that flies
(:class:`flight.estimation.gyrovertical.GyroVertical`, one sample per Python
call) would take seconds per evaluation.  This module runs the same per-sample
step, :func:`flight.estimation.gyrovertical.step` (written once, generic over
its math namespace), with :data:`JAX_OPS`: ``lax.scan`` over time and ``vmap``
over sequences under one ``jit``; one evaluation of (10) on a minute of 400 Hz
data is tens of milliseconds.  Only the arithmetic's rounding differs from the
flight path (XLA against Python floats and numpy); unit tests hold the two
equal through inversion, gimbal lock and free fall.

Only roll/pitch come out; the state is (q, V, P, n*) as in GyroVertical.
"""
from __future__ import annotations

import math
from functools import partial
from types import SimpleNamespace
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from flight.estimation.gyrovertical import (DT_REF, P0_DIAG, G, TrainingSequence, compensated_gravity, euler_rp, step,
                                            step_constants, world_from_body, yaw_of)
from flight.quat import quat_from_euler, wrap_angle

LOG_CLIP = (-60.0, 30.0)   # as GyroVerticalParams.from_vector: exp() finite and positive


def _cond(pred, if_true, if_false, *args):
    """Both branches evaluated, the result selected: branch-free under scan and vmap.  The branch not
    taken may hold NaN (0/0 at a zero tilt): fine for values, which is all training takes."""
    return jax.tree_util.tree_map(partial(jnp.where, pred), if_true(*args), if_false(*args))


def _add_diag(M, a, b, c):
    return M + jnp.diag(jnp.stack([a, b, c]))


# the math namespace of flight.estimation.gyrovertical.step (see FLOAT_OPS there), traceable
JAX_OPS = SimpleNamespace(
    sqrt=jnp.sqrt, sin=jnp.sin, cos=jnp.cos, atan2=jnp.arctan2, asin=jnp.arcsin, hypot=jnp.hypot,
    abs=jnp.abs, isfinite=jnp.isfinite, clip=jnp.clip, both=jnp.logical_and, where=jnp.where, cond=_cond,
    array=jnp.array, solve=jnp.linalg.solve, add_diag=_add_diag,
    eye_minus=lambda M: jnp.eye(3, dtype=M.dtype) - M, unstack=tuple)


def _scan_step(c, carry, sample):
    gyro, accel = sample
    carry, _, _ = step(carry, tuple(gyro), tuple(accel), c, JAX_OPS)
    return carry, jnp.stack(euler_rp(carry[0], JAX_OPS))


def _scan_step_compensated(c, window, delay, carry, sample):
    """:func:`_scan_step` with the acceleration compensation of GyroVertical.update: the carry holds
    the last window + delay world-frame specific forces, newest first, as GyroVertical's history."""
    state, forces = carry
    gyro, accel, accel_ref, heading = sample
    mean = jnp.mean(forces[delay - 1:delay - 1 + window], axis=0)   # samples k-delay-window+1 .. k-delay
    offset = jnp.where(jnp.isfinite(heading), yaw_of(state[0], JAX_OPS) - heading, 0.0)
    gravity = compensated_gravity(tuple(mean), tuple(accel_ref), c.g, JAX_OPS, offset)
    state, _, _ = step(state, tuple(gyro), tuple(accel), c, JAX_OPS, gravity=gravity)
    forces = jnp.roll(forces, 1, axis=0).at[0].set(jnp.stack(world_from_body(state[0], tuple(accel))))
    return (state, forces), jnp.stack(euler_rp(state[0], JAX_OPS))


@partial(jax.jit, static_argnames=("dt", "adaptive", "min_load_factor", "n_star_tau_s", "g", "window", "delay"))
def run_batch(log_params, gyro, accel, q0, accel_ref=None, heading=None, fallback_log_params=None, *, dt: float = DT_REF, adaptive: bool = True,
              min_load_factor: float = 0.2, n_star_tau_s: float = 0.05, g: float = G, window: int = 0,
              delay: int = 0):
    """(roll, pitch), each (S, N), for S sequences of N samples: gyro, accel (S, N, 3), q0 (S, 4).

    log_params: the 12 natural-log parameters (GyroVerticalParams.to_vector()).
    GyroVertical's defaults: P0 = diag(P0_DIAG), V0 = 0, n*0 = 0.
    accel_ref (S, N, 3): the acceleration compensation's reference at each sample, the vehicle's mean
    acceleration (world ENU) over the ``window`` sample intervals ending ``delay`` samples earlier
    (``a`` of :func:`flight.estimation.gyrovertical.fixed_windows`; NaN: none); None: the filter of 004.
    heading (S, N): the vehicle's yaw at each sample (GyroVertical.update's heading_rad; NaN or None:
    the filter's own).  fallback_log_params: GyroVertical's ``fallback`` (the variances of a sample
    without a reference), as log_params; None: log_params throughout.
    """
    nodes = jnp.exp(jnp.clip(log_params, *LOG_CLIP)).reshape(4, 3)   # rows pitch, roll, speed, n
    fallback = None
    if fallback_log_params is not None:
        fallback = [tuple(row) for row in jnp.exp(jnp.clip(fallback_log_params, *LOG_CLIP)).reshape(4, 3)]
        if accel_ref is None:   # no reference at any sample: the fallback's variances throughout
            nodes, fallback = jnp.stack([jnp.stack(row) for row in fallback]), None
    c = step_constants([tuple(row) for row in nodes], dt, adaptive, min_load_factor, n_star_tau_s, g, fallback)
    if accel_ref is not None and not (window >= 1 and delay >= 1):
        raise ValueError(f"gyrovertical: window and delay must be >= 1 sample, got {window}, {delay}")

    def one(gyro_s, accel_s, q0_s, ref_s=None, heading_s=None):
        carry = (tuple(q0_s), jnp.zeros((), q0_s.dtype), jnp.diag(jnp.array(P0_DIAG, q0_s.dtype)),
                 jnp.zeros((), q0_s.dtype))
        if ref_s is None:
            _, rp = jax.lax.scan(partial(_scan_step, c), carry, (gyro_s, accel_s))
        else:
            forces = jnp.zeros((window + delay, 3), q0_s.dtype)
            _, rp = jax.lax.scan(partial(_scan_step_compensated, c, window, delay), (carry, forces),
                                 (gyro_s, accel_s, ref_s, heading_s))
        return rp[:, 0], rp[:, 1]

    if accel_ref is None:
        return jax.vmap(one)(gyro, accel, q0)
    if heading is None:
        heading = jnp.full(accel_ref.shape[:2], jnp.nan, accel_ref.dtype)
    return jax.vmap(one)(gyro, accel, q0, accel_ref, heading)


@partial(jax.jit, static_argnames=("dt", "adaptive", "weights", "window", "delay"))
def _criterion(log_params, gyro, accel, q0, roll, pitch, accel_ref, heading, *, dt, adaptive, weights, window,
               delay):
    r, p = run_batch(log_params, gyro, accel, q0, accel_ref, heading, dt=dt, adaptive=adaptive, window=window, delay=delay)
    rms_p = jnp.degrees(jnp.sqrt(jnp.mean(wrap_angle(p - pitch, jnp) ** 2, axis=1)))
    rms_r = jnp.degrees(jnp.sqrt(jnp.mean(wrap_angle(r - roll, jnp) ** 2, axis=1)))
    return weights[0] * jnp.mean(rms_p) + weights[1] * jnp.mean(rms_r)


class BatchEvaluator:
    """Criterion (10) over fixed sequences (equal lengths), compiled once: ``evaluator(log_params) -> deg``."""

    def __init__(self, sequences: Sequence[TrainingSequence], dt: float = DT_REF,
                 weights: tuple[float, float] = (0.5, 0.5), adaptive: bool = True,
                 compensation: tuple[int, int] | None = None):
        """compensation: (window, delay) in samples of the sequences' accel_ref (run_batch), or None:
        the filter of 004 (the sequences' accel_ref unused)."""
        lengths = {len(s.roll) for s in sequences}
        if len(lengths) != 1:
            raise ValueError(f"gyrovertical: batched sequences must have one length, got {sorted(lengths)}")
        if compensation is not None and any(s.accel_ref is None for s in sequences):
            raise ValueError("gyrovertical: compensation needs every sequence's accel_ref")
        self.dt, self.weights, self.adaptive = float(dt), tuple(float(w) for w in weights), bool(adaptive)
        self.window, self.delay = compensation if compensation is not None else (0, 0)
        self._data = tuple(jnp.asarray(np.stack(a)) for a in (
            [s.gyro for s in sequences], [s.accel for s in sequences],
            [quat_from_euler(s.roll0, s.pitch0, 0.0) for s in sequences],
            [s.roll for s in sequences], [s.pitch for s in sequences]))
        self._ref = self._heading = None
        if compensation is not None:
            self._ref = jnp.asarray(np.stack([s.accel_ref for s in sequences]))
            self._heading = jnp.asarray(np.stack([s.heading if s.heading is not None else np.full(len(s.roll), np.nan)
                                                  for s in sequences]))

    def __call__(self, log_params) -> float:
        c = float(_criterion(jnp.asarray(log_params, dtype=self._data[0].dtype), *self._data, self._ref, self._heading,
                             dt=self.dt, adaptive=self.adaptive, weights=self.weights, window=self.window,
                             delay=self.delay))
        return c if math.isfinite(c) else 1e6
