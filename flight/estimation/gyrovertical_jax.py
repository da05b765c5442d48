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

from flight.estimation.gyrovertical import DT_REF, P0_DIAG, G, TrainingSequence, euler_rp, step, step_constants
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


@partial(jax.jit, static_argnames=("dt", "adaptive", "min_load_factor", "n_star_tau_s", "g"))
def run_batch(log_params, gyro, accel, q0, *, dt: float = DT_REF, adaptive: bool = True,
              min_load_factor: float = 0.2, n_star_tau_s: float = 0.05, g: float = G):
    """(roll, pitch), each (S, N), for S sequences of N samples: gyro, accel (S, N, 3), q0 (S, 4).

    log_params: the 12 natural-log parameters (GyroVerticalParams.to_vector()).
    GyroVertical's defaults: P0 = diag(P0_DIAG), V0 = 0, n*0 = 0.
    """
    nodes = jnp.exp(jnp.clip(log_params, *LOG_CLIP)).reshape(4, 3)   # rows pitch, roll, speed, n
    c = step_constants([tuple(row) for row in nodes], dt, adaptive, min_load_factor, n_star_tau_s, g)

    def one(gyro_s, accel_s, q0_s):
        carry = (tuple(q0_s), jnp.zeros((), q0_s.dtype), jnp.diag(jnp.array(P0_DIAG, q0_s.dtype)),
                 jnp.zeros((), q0_s.dtype))
        _, rp = jax.lax.scan(partial(_scan_step, c), carry, (gyro_s, accel_s))
        return rp[:, 0], rp[:, 1]

    return jax.vmap(one)(gyro, accel, q0)


@partial(jax.jit, static_argnames=("dt", "adaptive", "weights"))
def _criterion(log_params, gyro, accel, q0, roll, pitch, *, dt, adaptive, weights):
    r, p = run_batch(log_params, gyro, accel, q0, dt=dt, adaptive=adaptive)
    rms_p = jnp.degrees(jnp.sqrt(jnp.mean(wrap_angle(p - pitch, jnp) ** 2, axis=1)))
    rms_r = jnp.degrees(jnp.sqrt(jnp.mean(wrap_angle(r - roll, jnp) ** 2, axis=1)))
    return weights[0] * jnp.mean(rms_p) + weights[1] * jnp.mean(rms_r)


class BatchEvaluator:
    """Criterion (10) over fixed sequences (equal lengths), compiled once: ``evaluator(log_params) -> deg``."""

    def __init__(self, sequences: Sequence[TrainingSequence], dt: float = DT_REF,
                 weights: tuple[float, float] = (0.5, 0.5), adaptive: bool = True):
        lengths = {len(s.roll) for s in sequences}
        if len(lengths) != 1:
            raise ValueError(f"gyrovertical: batched sequences must have one length, got {sorted(lengths)}")
        self.dt, self.weights, self.adaptive = float(dt), tuple(float(w) for w in weights), bool(adaptive)
        self._data = tuple(jnp.asarray(np.stack(a)) for a in (
            [s.gyro for s in sequences], [s.accel for s in sequences],
            [quat_from_euler(s.roll0, s.pitch0, 0.0) for s in sequences],
            [s.roll for s in sequences], [s.pitch for s in sequences]))

    def __call__(self, log_params) -> float:
        c = float(_criterion(jnp.asarray(log_params, dtype=self._data[0].dtype), *self._data,
                             dt=self.dt, adaptive=self.adaptive, weights=self.weights))
        return c if math.isfinite(c) else 1e6
