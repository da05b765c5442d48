"""The gyro-vertical of 004, batched in JAX, for training.

Training (004's criterion (10)) runs the filter over 9 sequences per flight
for every parameter vector the optimiser tries; the reference
implementation (:class:`flight.estimation.gyrovertical.GyroVertical`, one sample per
Python call, ~30 us) would take seconds per evaluation.  This module is the
same per-sample step as a pure function, ``lax.scan`` over time and ``vmap``
over sequences under one ``jit``: one evaluation of (10) on a minute of
400 Hz data is tens of milliseconds.  The reference stays the one the attitude
service runs; a unit test holds the two equal on a flight through inversion.

Only roll/pitch come out; the state is (q, V, P, n*) as in the reference.
"""
from __future__ import annotations

import math
from functools import partial
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from flight.estimation.gyrovertical import DT_REF, G, TrainingSequence
from flight.quat import quat_from_euler, wrap_angle

LOG_CLIP = (-60.0, 30.0)   # as GyroVerticalParams.from_vector: exp() finite and positive


def _variances(log_params, n_star):
    """(7) for the four functions, from the 12 natural-log parameters (order of GyroVerticalParams.names())."""
    p = jnp.exp(jnp.clip(log_params, *LOG_CLIP)).reshape(4, 3)   # rows pitch, roll, speed, n
    var0, n2, var2 = p[:, 0], p[:, 1], p[:, 2]
    a = jnp.abs(n_star)
    return jnp.where(a >= n2, var2, var0 + (var2 - var0) * (a / n2))


def _euler_rp(q):
    w, x, y, z = q
    roll = jnp.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = jnp.arcsin(jnp.clip(2 * (w * y - z * x), -1.0, 1.0))
    return roll, pitch


def _step(carry, sample, *, log_params, dt, adaptive, min_load_factor, n_alpha, g):
    """One sample of GyroVertical.update (same order of operations)."""
    q, V, P, n_star = carry
    gyro, accel = sample
    gx, gy, gz = gyro
    # model 1
    w, x, y, z = q
    h = 0.5 * dt
    q = jnp.stack([w + h * (-x * gx - y * gy - z * gz), x + h * (w * gx + y * gz - z * gy),
                   y + h * (w * gy - x * gz + z * gx), z + h * (w * gz + x * gy - y * gx)])
    q = q / jnp.sqrt(jnp.sum(q * q))
    # load factor in doc axes, its low-passed n*
    Z = jnp.stack([accel[0], accel[2], -accel[1]]) / g
    n = jnp.sqrt(jnp.sum(Z * Z))
    finite = jnp.isfinite(n)
    n_star = jnp.where(finite, n_star + n_alpha * ((n - 1.0) - n_star), n_star)
    var = _variances(log_params, n_star) if adaptive else _variances(log_params, 0.0)
    q_scale, r_scale = dt / DT_REF, DT_REF / dt
    sq, sg, sv, sn = var[0] * q_scale, var[1] * q_scale, var[2] * q_scale, var[3] * r_scale
    P = P + jnp.diag(jnp.stack([sq, sg, sv]))
    # observation model at the propagated attitude (see GyroVertical.observation_model)
    w, x, y, z = q
    r00 = 1 - 2 * (y * y + z * z); r01 = 2 * (x * y - w * z); r02 = 2 * (x * z + w * y)
    r10 = 2 * (x * y + w * z); r11 = 1 - 2 * (x * x + z * z); r12 = 2 * (y * z - w * x)
    r20 = 2 * (x * z - w * y); r21 = 2 * (y * z + w * x); r22 = 1 - 2 * (x * x + y * y)
    psi = jnp.arctan2(r10, r00)
    c, s = jnp.cos(psi), jnp.sin(psi)
    ax, ay, az = r00 * c + r10 * s, r01 * c + r11 * s, r02 * c + r12 * s
    bx, by, bz = -r00 * s + r10 * c, -r01 * s + r11 * c, -r02 * s + r12 * c
    wy_d, wz_d = gz, -gy
    zbar = jnp.stack([r20, r22 + V * wz_d / g, -r21 - V * wy_d / g])
    zero = jnp.zeros_like(ax)
    H = jnp.stack([jnp.stack([ax, bx, zero]),
                   jnp.stack([az, bz, wz_d / g]),
                   jnp.stack([-ay, -by, -wy_d / g])])
    # Joseph-form update (8)
    PHt = P @ H.T
    S = H @ PHt + sn * jnp.eye(3)
    K = jnp.linalg.solve(S, PHt.T).T
    A = jnp.eye(3) - K @ H
    P_new = A @ P @ A.T + sn * (K @ K.T)
    P_new = 0.5 * (P_new + P_new.T)
    Z_safe = jnp.where(finite, Z, zbar)
    dx = K @ (Z_safe - zbar)
    # tilt correction as a world rotation about a horizontal axis, then restore the yaw
    d_theta, d_gamma = dx[0], dx[1]
    px, py = d_gamma * c + d_theta * s, d_gamma * s - d_theta * c
    ang = jnp.sqrt(px * px + py * py)
    k = jnp.where(ang > 0.0, jnp.sin(0.5 * ang) / jnp.where(ang > 0.0, ang, 1.0), 0.5)
    cw, ex, ey = jnp.cos(0.5 * ang), px * k, py * k
    w2, x2, y2, z2 = (cw * w - ex * x - ey * y, cw * x + ex * w + ey * z,
                      cw * y - ex * z + ey * w, cw * z + ex * y - ey * x)
    sin_pitch = -2 * (x2 * z2 - w2 * y2)
    psi_new = jnp.arctan2(2 * (x2 * y2 + w2 * z2), 1 - 2 * (y2 * y2 + z2 * z2))
    d = jnp.where(jnp.abs(sin_pitch) < 0.98, 0.5 * (psi - psi_new), 0.0)
    cz, sz = jnp.cos(d), jnp.sin(d)
    q_corr = jnp.stack([cz * w2 - sz * z2, cz * x2 - sz * y2, cz * y2 + sz * x2, cz * z2 + sz * w2])
    q_corr = q_corr / jnp.sqrt(jnp.sum(q_corr * q_corr))
    use = finite & (n >= min_load_factor)
    q = jnp.where(use, q_corr, q)
    V = jnp.where(use, V + dx[2], V)
    P = jnp.where(use, P_new, P)
    return (q, V, P, n_star), jnp.stack(_euler_rp(q))


@partial(jax.jit, static_argnames=("dt", "adaptive", "min_load_factor", "n_star_tau_s", "g"))
def run_batch(log_params, gyro, accel, q0, *, dt: float = DT_REF, adaptive: bool = True,
              min_load_factor: float = 0.2, n_star_tau_s: float = 0.05, g: float = G):
    """(roll, pitch), each (S, N), for S sequences of N samples: gyro, accel (S, N, 3), q0 (S, 4).

    log_params: the 12 natural-log parameters (GyroVerticalParams.to_vector()).
    The reference's defaults: P0 = diag(0.04, 0.04, 1), V0 = 0, n*0 = 0.
    """
    n_alpha = 1.0 if n_star_tau_s == 0 else 1.0 - math.exp(-dt / n_star_tau_s)
    step = partial(_step, log_params=log_params, dt=dt, adaptive=adaptive,
                   min_load_factor=min_load_factor, n_alpha=n_alpha, g=g)

    def one(gyro_s, accel_s, q0_s):
        carry = (q0_s, jnp.zeros((), q0_s.dtype), jnp.diag(jnp.array([0.04, 0.04, 1.0], q0_s.dtype)),
                 jnp.zeros((), q0_s.dtype))
        _, rp = jax.lax.scan(step, carry, (gyro_s, accel_s))
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
