"""Adaptive gyro-vertical: roll/pitch from gyros + accelerometers (document 004).

Kachanov, Kulabukhov, Tuktaryov, Grishin, "Adaptive algorithm of a UAV
gyro-vertical computer".  Pure algorithm, no I/O.

Two models (004):

* model 1, deterministic, every gyro sample: quaternion propagation
  ``q_{i+1} = q_i + 1/2 q_i o q_w dt`` (then normalised);
* model 2, stochastic and static: state ``x = [theta (pitch), gamma (roll), V]``
  observed by the load factor ``n = specific force / g`` through (5)::

      f_x = sin(theta)
      f_y = cos(theta) cos(gamma) + V w_z / g
      f_z = -cos(theta) sin(gamma) - V w_y / g

  with Jacobian (6), one Joseph-form Kalman step (8) per sample, and the
  variances of Q = diag(s_theta^2, s_gamma^2, s_V^2) and R = s_n^2 I all
  functions of ``n* = |n| - 1`` (7): the farther the apparent vertical is from
  gravity, the less the accelerometer is trusted.

Axes.  004 writes (5)-(6) in aircraft axes: x forward, y up, z right.  The
project's body frame is FLU (x forward, y left, z up).  The one mapping used
everywhere is :func:`flu_to_doc` (a proper rotation, see ``FLU_TO_DOC``)::

      doc_x = body_x,   doc_y = body_z,   doc_z = -body_y

(its inverse is the transpose, :func:`doc_to_flu`).  Under it the document's
angles are ``theta = -pitch`` (004's pitch is nose-up positive, the project's
ZYX pitch about body-left is nose-down positive) and ``gamma = roll`` (both
right-wing-down positive); :func:`doc_observation` evaluated at
``(theta, gamma) = (-pitch, roll)`` equals ``flu_to_doc(R^T e_z)``.

Singularities and inversion (the deviation from a literal (5)-(6)).  The Euler
parameterisation of model 2 breaks where a quadcopter goes: (6)'s roll column
carries a ``cos(theta)`` factor (roll unobservable at pitch +-90 deg, where roll
and yaw merge) and a correction written on Euler angles wraps at roll +-180 deg.
So the correction is done as a small-angle *error-state* update around the
propagated quaternion:

* the angle part of the state is the tilt error ``[d_theta, d_gamma]``, a
  rotation about the two horizontal axes of the heading frame (world frame
  turned by the propagated yaw): ``d_gamma`` about heading-forward,
  ``-d_theta`` about heading-left (so, near level, exactly the document's pitch
  and roll errors).  It is reset to zero after every correction; ``V`` is kept
  (frozen between samples as in 004);
* Z-bar is (5) evaluated at the propagated attitude, i.e.
  ``flu_to_doc(R^T e_z) + V [0, w_z, -w_y] / g`` (doc axes), valid at any
  attitude including inverted;
* H is the derivative of that with respect to the tilt error.  Its pitch column
  is exactly (6)'s; its roll column is (6)'s divided by ``cos(theta)`` (an
  Euler-roll change is a body-x rotation whose tilt part is ``cos(theta)``
  times a heading-forward tilt).  The columns are ``R^T`` of two orthonormal
  horizontal vectors, so H never loses rank: no singularity at pitch +-90 deg,
  no wrap at roll 180 deg;
* Q, R from the adaptive functions of n*, Joseph form (8), P kept between
  samples (``P-bar_{i+1} = P_i`` as 004 says, then ``+ Q``);
* the correction is applied as a world-frame rotation of the quaternion about
  that horizontal axis, then the yaw of the *propagated* quaternion is restored
  by a rotation about world z (which cannot change roll/pitch).  This is 004's
  "rebuild the quaternion from the corrected angles, keeping yaw", done without
  passing through Euler angles.  Within ~11 deg of pitch +-90 deg, where ZYX
  yaw is ill-conditioned, the yaw restoration is skipped (the horizontal-axis
  correction alone never drives heading to first order).
* n* is passed through a short low-pass (``n_star_tau_s``, 0.05 s; 0 gives
  004's raw per-sample n*) so that accelerometer noise does not inflate R at rest.
* When ``|n| < min_load_factor`` (free fall, thrust cut in a flip) the
  accelerometer direction is meaningless and the correction is skipped;
  covariance still grows by Q.

With the accelerometer reading "level" (thrust along body z) through a whole
flip, an inverted prior gives an innovation along the predicted vertical, which
is orthogonal to both H columns, so it produces no correction; where the
prior is side-on the large |n*| of a flip makes R large.  Roll is therefore
carried through by the gyros (model 1) as it should be.

One step, two arithmetics.  The per-sample step is :func:`step` (model 1 by
:func:`propagate`, then (8) with :func:`observe` and :func:`apply_tilt`), a pure
function of (state, gyro, accel, constants) written once over a math namespace
``ops``, as :mod:`flight.quat`'s functions take ``xp``.  :class:`GyroVertical`
runs it with :data:`FLOAT_OPS` (Python floats, numpy for the 3x3, branches
taken lazily): the attitude service's 200-400 Hz path, where the per-call cost
counts.  :mod:`flight.estimation.gyrovertical_jax` runs it with ``JAX_OPS``
(jax.numpy, branch-free) under ``lax.scan`` and ``vmap`` for training.

Acceleration compensation (an option, not in 004).  The accelerometer of a multirotor reads thrust
along body z plus drag, "level" through any coordinated acceleration.  Given the vehicle's mean
acceleration over a past window (the position estimate's velocity change) and the heading, the
observation of (8) becomes the gravity that window measures: the mean over it of the IMU's specific
force turned into the world by the filter's own attitude, less that acceleration
(:func:`compensated_gravity`, :meth:`GyroVertical.update`); without a usable one, the accelerometer
sample as 004.  Trained alike (:mod:`flight.estimation.gyrovertical_jax`, ``accel_ref``).

Baselines: :class:`GyroIntegrator` (model 1 alone) and
``GyroVertical(..., adaptive=False)`` (every variance fixed at its n* = 0 value).
Helpers: :func:`run_sequence`, :func:`rms_error_deg` (wrapped), :func:`evaluate`
(criterion (10)), :func:`make_training_sequences` (the 9 sequences), :func:`train`.

Sample-rate scaling: the parameters are the document's per-sample variances
*at the reference rate* ``DT_REF`` = 1/400 s (the simulator's IMU rate).  For
another ``dt`` Q is scaled by ``dt / DT_REF`` and R by ``DT_REF / dt`` so the
correction time constant (~ dt sqrt(R/Q)) is independent of the sample rate;
at ``dt == DT_REF`` this is exactly 004.
"""
from __future__ import annotations

import bisect
import dataclasses
import math
import tomllib
from collections import deque
from dataclasses import dataclass
from operator import itemgetter
from pathlib import Path
from types import SimpleNamespace
from typing import NamedTuple, Sequence

import numpy as np

from flight.quat import quat_from_euler, quat_normalize, wrap_angle

# 004's training (+-0.05 deg/s gyro biases): the figures and tests of 004
PAPER_PARAMS_FILE = Path(__file__).resolve().parent.parent / "params" / "gyrovertical_x250.toml"
# trained alike with +-0.2 deg/s, the bias the simulated MEMS gyro has (SimConfig.gyro_bias_var):
# the file the attitude service reads by default (a filter must be trained for the gyro it runs on)
DEFAULT_PARAMS_FILE = Path(__file__).resolve().parent.parent / "params" / "gyrovertical_x250_mems.toml"
G = 9.80665                 # m/s^2, normalises specific force to the load factor
DT_REF = 1.0 / 400.0        # s, rate at which the parameters are per-sample variances
P0_DIAG = (0.04, 0.04, 1.0)  # default initial variances of [d_theta, d_gamma, V]

# v_doc = FLU_TO_DOC @ v_flu; a proper rotation (det +1) so cross products map too.
FLU_TO_DOC = np.array([[1.0, 0.0, 0.0],
                       [0.0, 0.0, 1.0],
                       [0.0, -1.0, 0.0]])


def flu_to_doc(v) -> np.ndarray:
    """Body FLU -> 004's aircraft axes: (x, y, z)_doc = (x, z, -y)_flu. Works on (3,) or (N, 3)."""
    return np.asarray(v, dtype=np.float64) @ FLU_TO_DOC.T


def doc_to_flu(v) -> np.ndarray:
    """Inverse of :func:`flu_to_doc` (the transpose): (x, y, z)_flu = (x, -z, y)_doc."""
    return np.asarray(v, dtype=np.float64) @ FLU_TO_DOC


def doc_observation(theta: float, gamma: float, V: float = 0.0, omega_doc=(0.0, 0.0, 0.0),
                    g: float = G) -> np.ndarray:
    """(5)/(9) of 004, doc axes: predicted load factor [n_x, n_y, n_z]."""
    wx, wy, wz = omega_doc
    return np.array([math.sin(theta),
                     math.cos(theta) * math.cos(gamma) + V * wz / g,
                     -math.cos(theta) * math.sin(gamma) - V * wy / g])


def doc_jacobian(theta: float, gamma: float, omega_doc=(0.0, 0.0, 0.0), g: float = G) -> np.ndarray:
    """(6) of 004: dZ/d[theta, gamma, V] (reference; the filter uses the error-state form)."""
    wx, wy, wz = omega_doc
    ct, st, cg, sg = math.cos(theta), math.sin(theta), math.cos(gamma), math.sin(gamma)
    return np.array([[ct, 0.0, 0.0],
                     [-st * cg, -ct * sg, wz / g],
                     [st * sg, -ct * cg, -wy / g]])


# ---------------------------------------------------------------- the math the step is written in
# The filter's per-sample step is written once, below, over a math namespace ``ops`` (as
# flight.quat's functions take ``xp``):
#   scalars: sqrt sin cos atan2 asin hypot abs isfinite, clip(v, lo, hi), both(a, b) (logical and),
#            where(c, a, b) (both evaluated);
#   cond(c, if_true, if_false, *args): a branch.  The float one calls only the branch taken, so the
#            flight path keeps its early skips (and divides by no zero it would not use); the JAX one
#            evaluates both and selects, branch-free for scan and vmap;
#   3-vectors and 3x3 matrices (used with @, .T, + - *): array, solve, add_diag(M, a, b, c)
#            (M + diag(a, b, c), a new matrix), eye_minus(M) (I - M), unstack (a 3-vector -> 3 scalars).
# FLOAT_OPS is the flight path (Python floats, numpy for the 3x3: the per-call cost at 200-400 Hz);
# flight.estimation.gyrovertical_jax.JAX_OPS the training one (jax.numpy, traceable).


def _float_cond(pred, if_true, if_false, *args):
    return if_true(*args) if pred else if_false(*args)


def _float_add_diag(M, a, b, c):
    M = M.copy()
    M[0, 0] += a
    M[1, 1] += b
    M[2, 2] += c
    return M


_I3 = np.eye(3)
_I3.flags.writeable = False

FLOAT_OPS = SimpleNamespace(
    sqrt=math.sqrt, sin=math.sin, cos=math.cos, atan2=math.atan2, asin=math.asin, hypot=math.hypot,
    abs=abs, isfinite=math.isfinite, clip=lambda v, lo, hi: max(lo, min(hi, v)),
    both=lambda a, b: a and b, where=lambda c, a, b: a if c else b, cond=_float_cond,
    array=np.array, solve=np.linalg.solve, add_diag=_float_add_diag, eye_minus=lambda M: _I3 - M,
    unstack=np.ndarray.tolist)


def piecewise_variance(n_star, var0, n2, var2, ops=FLOAT_OPS):
    """(7): linear through (0, var0) and (n2, var2) in |n*|, held at var2 beyond n2."""
    a = ops.abs(n_star)
    return ops.where(a >= n2, var2, var0 + (var2 - var0) * (a / n2))


_FUNCS = ("pitch", "roll", "speed", "n")
_SUFFIX = ("var0", "n2", "var2")


@dataclass(frozen=True)
class GyroVerticalParams:
    """The 12 parameters of (7): four adaptive variance functions of n* = |n| - 1.

    Each function f(n*) is piecewise linear in |n*| through two nodes
    ``(0, var0)`` and ``(n2, var2)`` and limited to ``var2`` beyond ``n2``
    (004: left node at n* = 0, i.e. |n| = 1; 3 parameters a function).  |n*| is
    used because |n| < 1 (thrust cut, descent) is as far from gravity as |n| > 1.

    * ``pitch_*``: sigma_theta^2 of Q, rad^2 per sample (at DT_REF);
    * ``roll_*``:  sigma_gamma^2 of Q, rad^2 per sample;
    * ``speed_*``: sigma_V^2 of Q, (m/s)^2 per sample;
    * ``n_*``:     sigma_n^2 of R (same on the three axes), load factor^2 (g^2).
    ``*_var0`` is the variance at |n| = 1, ``*_n2`` the |n*| at which the
    function reaches ``*_var2``, the limit held beyond it.

    Defaults (hand-set, not trained): at |n| = 1 the correction time constant
    is ~ DT_REF sqrt(R/Q) = 2.5 s (a 0.05 deg/s gyro bias leaves ~0.13 deg);
    at |n*| = 0.015 (a quadcopter holding 10 deg of tilt) ~ 15 s; at
    |n*| >= 0.044 (3 m/s^2 of sustained horizontal acceleration) ~ 30 s.
    """

    pitch_var0: float = 1e-8
    pitch_n2: float = 0.1
    pitch_var2: float = 2e-8
    roll_var0: float = 1e-8
    roll_n2: float = 0.1
    roll_var2: float = 2e-8
    speed_var0: float = 1e-4
    speed_n2: float = 0.1
    speed_var2: float = 1e-4
    n_var0: float = 1e-2
    n_n2: float = 0.05
    n_var2: float = 3.0

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or v <= 0:
                raise ValueError(f"gyrovertical: {f.name} must be a positive finite number, got {v!r}")

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return tuple(f"{fn}_{s}" for fn in _FUNCS for s in _SUFFIX)

    def function(self, which: str) -> tuple[float, float, float]:
        """(var0, n2, var2) of one of 'pitch', 'roll', 'speed', 'n'."""
        return tuple(getattr(self, f"{which}_{s}") for s in _SUFFIX)

    def variances(self, n_star: float) -> tuple[float, float, float, float]:
        """(sigma_theta^2, sigma_gamma^2, sigma_V^2, sigma_n^2) at n* (per sample at DT_REF)."""
        return tuple(piecewise_variance(n_star, *self.function(fn)) for fn in _FUNCS)

    def to_vector(self) -> np.ndarray:
        """Natural-log vector of the 12 parameters, order of :meth:`names` (for optimisers)."""
        return np.log(np.array([getattr(self, k) for k in self.names()], dtype=np.float64))

    @classmethod
    def from_vector(cls, v) -> "GyroVerticalParams":
        v = np.asarray(v, dtype=np.float64)
        if v.shape != (12,):
            raise ValueError(f"gyrovertical: vector must have shape (12,), got {v.shape}")
        v = np.clip(v, -60.0, 30.0)  # keep exp() finite and positive whatever the optimiser tries
        return cls(**{k: float(math.exp(x)) for k, x in zip(cls.names(), v)})

    def to_dict(self) -> dict:
        """Flat table {name: value} (TOML/JSON friendly)."""
        return {k: float(getattr(self, k)) for k in self.names()}

    @classmethod
    def from_dict(cls, d: dict) -> "GyroVerticalParams":
        """Inverse of :meth:`to_dict`; missing keys take defaults, unknown keys -> ValueError."""
        if not isinstance(d, dict):
            raise ValueError(f"gyrovertical: expected a table, got {type(d).__name__}")
        unknown = set(d) - set(cls.names())
        if unknown:
            raise ValueError(f"gyrovertical: unknown parameter(s) {sorted(unknown)}")
        kw = {}
        for k, v in d.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ValueError(f"gyrovertical: {k} must be a number, got {v!r}")
            kw[k] = float(v)
        return cls(**kw)


# ---------------------------------------------------------------- the per-sample step (written once)
class StepConstants(NamedTuple):
    """What :func:`step` needs besides the state and the sample; made by :func:`step_constants`."""

    half_dt: float          # s, model 1's dt / 2
    q_scale: float          # Q per sample = (7) * dt / DT_REF
    r_scale: float          # R per sample = (7) * DT_REF / dt
    n_alpha: float          # gain of the n* low-pass per sample
    min_load_factor: float  # below this |n| the accelerometer is not used
    g: float
    adaptive: bool          # False: every variance at its n* = 0 value
    nodes: tuple            # (var0, n2, var2) of (7)'s pitch, roll, speed and n functions
    # the same of the variances used where a compensated step has no reference (None: nodes)
    fallback_nodes: tuple | None = None


def step_constants(nodes, dt: float, adaptive: bool = True, min_load_factor: float = 0.2,
                   n_star_tau_s: float = 0.05, g: float = G, fallback_nodes=None) -> StepConstants:
    """The constants of :func:`step`; ``nodes`` as :meth:`GyroVerticalParams.function` for
    pitch, roll, speed, n (floats, or JAX scalars when traced); ``fallback_nodes`` alike or None."""
    if not dt > 0:
        raise ValueError(f"gyrovertical: dt must be > 0, got {dt!r}")
    if not n_star_tau_s >= 0:
        raise ValueError(f"gyrovertical: n_star_tau_s must be >= 0, got {n_star_tau_s!r}")
    dt = float(dt)
    n_alpha = 1.0 if n_star_tau_s == 0 else 1.0 - math.exp(-dt / n_star_tau_s)
    nodes = tuple(tuple(node) for node in nodes)
    return StepConstants(0.5 * dt, dt / DT_REF, DT_REF / dt, n_alpha, float(min_load_factor), float(g),
                         bool(adaptive), nodes,
                         None if fallback_nodes is None else matched_nodes(nodes, fallback_nodes))


def matched_nodes(nodes, fallback_nodes) -> tuple:
    """The fallback's nodes with every variance times one factor c, so that its covariance lives on
    the scale of ``nodes``' (c = sqrt(Q R) of nodes over the fallback's, roll and load at n* = 0).

    Only the ratios of Q to R shape a Kalman filter's gains (Q, R and P all times c: the same gains), so
    the fallback filters as before; but P carries over a switch between the two: unmatched, a P grown
    under the compensated variances (~1e4 times the fallback's) meets the fallback's small R and the
    first bare accelerometer sample is taken whole (17 deg of error on a flip's log)."""
    (_, (r0, _, _), _, (n0, _, _)) = nodes
    fallback_nodes = tuple(tuple(node) for node in fallback_nodes)
    (_, (f0, _, _), _, (m0, _, _)) = fallback_nodes
    c = ((r0 * n0) / (f0 * m0)) ** 0.5   # floats or traced JAX scalars alike
    return tuple((v0 * c, n2, v2 * c) for v0, n2, v2 in fallback_nodes)


def matched_fallback(params: GyroVerticalParams, fallback: GyroVerticalParams) -> GyroVerticalParams:
    """:func:`matched_nodes` as parameters: the filter a compensated GyroVertical falls back to."""
    nodes = matched_nodes([params.function(fn) for fn in _FUNCS], [fallback.function(fn) for fn in _FUNCS])
    return GyroVerticalParams(**{f"{fn}_{k}": float(v) for fn, node in zip(_FUNCS, nodes)
                                 for k, v in zip(_SUFFIX, node)})


def euler_rp(q, ops=FLOAT_OPS):
    """(roll, pitch) of the project's ZYX convention from q = (w, x, y, z)."""
    w, x, y, z = q
    roll = ops.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = ops.asin(ops.clip(2 * (w * y - z * x), -1.0, 1.0))
    return roll, pitch


def propagate(q, gyro, half_dt, ops=FLOAT_OPS):
    """Model 1: q + 1/2 q o (0, w) dt, normalised; q = (w, x, y, z), gyro = (gx, gy, gz) body FLU, rad/s."""
    gx, gy, gz = gyro
    w, x, y, z = q
    h = half_dt
    w, x, y, z = (w + h * (-x * gx - y * gy - z * gz),
                  x + h * (w * gx + y * gz - z * gy),
                  y + h * (w * gy - x * gz + z * gx),
                  z + h * (w * gz + x * gy - y * gx))
    s = 1.0 / ops.sqrt(w * w + x * x + y * y + z * z)
    return (w * s, x * s, y * s, z * s)


def scaled_variances(n_star, c: StepConstants, ops=FLOAT_OPS, nodes=None):
    """(sigma_theta^2, sigma_gamma^2, sigma_V^2) of Q and sigma_n^2 of R at n*, per sample at the step's dt
    (of ``nodes``, default the constants')."""
    n = n_star if c.adaptive else 0.0
    pitch, roll, speed, load = c.nodes if nodes is None else nodes
    return (piecewise_variance(n, *pitch, ops) * c.q_scale, piecewise_variance(n, *roll, ops) * c.q_scale,
            piecewise_variance(n, *speed, ops) * c.q_scale, piecewise_variance(n, *load, ops) * c.r_scale)


def observe(q, V, gyro, g, ops=FLOAT_OPS):
    """(Z-bar, H, heading) at q and V, doc axes; H columns = [d_theta, d_gamma, V];
    heading = (psi, cos psi, sin psi) of q's yaw, the frame of the tilt error (:func:`apply_tilt`)."""
    w, x, y, z = q
    # rotation matrix body->world
    r00 = 1 - 2 * (y * y + z * z); r01 = 2 * (x * y - w * z); r02 = 2 * (x * z + w * y)
    r10 = 2 * (x * y + w * z); r11 = 1 - 2 * (x * x + z * z); r12 = 2 * (y * z - w * x)
    r20 = 2 * (x * z - w * y); r21 = 2 * (y * z + w * x); r22 = 1 - 2 * (x * x + y * y)
    # heading frame of the propagated yaw; near pitch +-90 any yaw gives a valid frame
    psi = ops.atan2(r10, r00)
    c, s = ops.cos(psi), ops.sin(psi)
    # R^T h_x and R^T h_y in body FLU (h_x = [c, s, 0], h_y = [-s, c, 0])
    ax, ay, az = r00 * c + r10 * s, r01 * c + r11 * s, r02 * c + r12 * s
    bx, by, bz = -r00 * s + r10 * c, -r01 * s + r11 * c, -r02 * s + r12 * c
    gx, gy, gz = gyro
    # doc axes: (x, y, z)_doc = (x, z, -y)_flu;  w_y,doc = gz,  w_z,doc = -gy
    wy_d, wz_d = gz, -gy
    zbar = ops.array([r20 + 0.0, r22 + V * wz_d / g, -r21 - V * wy_d / g])
    # d n_body / d(world tilt phi) = R^T (e_z x phi); phi = d_gamma h_x - d_theta h_y
    # e_z x h_x = h_y, e_z x h_y = -h_x  ->  d/d d_theta = R^T h_x, d/d d_gamma = R^T h_y
    H = ops.array([[ax, bx, 0.0],
                   [az, bz, wz_d / g],
                   [-ay, -by, -wy_d / g]])
    return zbar, H, (psi, c, s)


def _turn_about_horizontal(q, px, py, ang, ops):
    k = ops.sin(0.5 * ang) / ang
    cw, ex, ey = ops.cos(0.5 * ang), px * k, py * k
    w, x, y, z = q
    # q <- q_phi (x) q   (q_phi = [cw, ex, ey, 0]): a rotation in the world frame
    return (cw * w - ex * x - ey * y,
            cw * x + ex * w + ey * z,
            cw * y - ex * z + ey * w,
            cw * z + ex * y - ey * x)


def _restore_yaw(q, psi, ops):
    w, x, y, z = q
    psi_new = ops.atan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))
    d = 0.5 * (psi - psi_new)
    cz, sz = ops.cos(d), ops.sin(d)
    return (cz * w - sz * z, cz * x - sz * y, cz * y + sz * x, cz * z + sz * w)


def _same(q, *_):
    return q


def apply_tilt(q, d_theta, d_gamma, heading, ops=FLOAT_OPS):
    """q turned by the tilt error [d_theta, d_gamma] of the heading frame (from :func:`observe`),
    then given back the heading's yaw; normalised."""
    psi, c, s = heading
    # world rotation vector phi = d_gamma h_x - d_theta h_y (horizontal)
    px, py = d_gamma * c + d_theta * s, d_gamma * s - d_theta * c
    ang = ops.hypot(px, py)
    q = ops.cond(ang > 0.0, _turn_about_horizontal, _same, q, px, py, ang, ops)
    # restore the propagated yaw by a world-z rotation (does not touch roll/pitch)
    w, x, y, z = q
    sin_pitch = -2 * (x * z - w * y)
    w, x, y, z = ops.cond(ops.abs(sin_pitch) < 0.98, _restore_yaw, _same, q, psi, ops)
    s_ = 1.0 / ops.sqrt(w * w + x * x + y * y + z * z)
    return (w * s_, x * s_, y * s_, z * s_)


def _correct(q, V, P, gyro, Z, sn, g, ops):
    """(8), Joseph form, at the propagated attitude: the corrected (q, V, P)."""
    zbar, H, heading = observe(q, V, gyro, g, ops)
    PHt = P @ H.T
    S = ops.add_diag(H @ PHt, sn, sn, sn)
    K = ops.solve(S, PHt.T).T          # K = P H^T S^-1 (S symmetric)
    A = ops.eye_minus(K @ H)
    P = A @ P @ A.T + sn * (K @ K.T)
    P = 0.5 * (P + P.T)
    d_theta, d_gamma, dV = ops.unstack(K @ (Z - zbar))
    return apply_tilt(q, d_theta, d_gamma, heading, ops), V + dV, P


def body_from_world(q, v):
    """R(q)^T v: a world-frame vector in body axes (q = (w, x, y, z) body->world)."""
    w, x, y, z = q
    v0, v1, v2 = v
    return ((1 - 2 * (y * y + z * z)) * v0 + 2 * (x * y + w * z) * v1 + 2 * (x * z - w * y) * v2,
            2 * (x * y - w * z) * v0 + (1 - 2 * (x * x + z * z)) * v1 + 2 * (y * z + w * x) * v2,
            2 * (x * z + w * y) * v0 + 2 * (y * z - w * x) * v1 + (1 - 2 * (x * x + y * y)) * v2)


def world_from_body(q, v):
    """R(q) v: a body-frame vector in world axes."""
    w, x, y, z = q
    v0, v1, v2 = v
    return ((1 - 2 * (y * y + z * z)) * v0 + 2 * (x * y - w * z) * v1 + 2 * (x * z + w * y) * v2,
            2 * (x * y + w * z) * v0 + (1 - 2 * (x * x + z * z)) * v1 + 2 * (y * z - w * x) * v2,
            2 * (x * z - w * y) * v0 + 2 * (y * z + w * x) * v1 + (1 - 2 * (x * x + y * y)) * v2)


def step(state, gyro, accel, c: StepConstants, ops=FLOAT_OPS, gravity=None):
    """One sample: model 1 with the gyro (body FLU, rad/s), then (8) with the accel (m/s^2).

    state = (q, V, P, n*): q = (w, x, y, z) body->world, V, the 3x3 covariance of
    [d_theta, d_gamma, V], the low-passed n*.  Returns (state, variances, corrected):
    the new state, the Q diagonal and sigma_n^2 used (:func:`scaled_variances`), and
    whether the accelerometer was used (not with |n| < min_load_factor or non-finite).

    gravity: None (004: the accelerometer sample is the observation), or (use, (g0, g1, g2)): where
    ``use`` holds, the observation is that world-frame vector (m/s^2) turned into body axes at the
    propagated attitude in place of the sample -- the acceleration compensation's measured gravity
    (:func:`compensated_gravity`); elsewhere the sample, with the variances of ``c.fallback_nodes``
    when there are some (a filter trained to trust the compensated observation trusts a bare
    accelerometer as much: a manoeuvre would pull it toward level).
    """
    q, V, P, n_star = state
    q = propagate(q, gyro, c.half_dt, ops)
    a0, a1, a2 = accel
    if gravity is not None:   # a Python-level choice: None traces no compensation at all
        use_gravity, g_world = gravity
        b0, b1, b2 = body_from_world(q, g_world)
        a0, a1, a2 = ops.where(use_gravity, b0, a0), ops.where(use_gravity, b1, a1), ops.where(use_gravity, b2, a2)
    Z = ops.array([a0, a2, -a1]) / c.g       # load factor, doc axes
    n = ops.sqrt(Z @ Z)
    finite = ops.isfinite(n)
    n_star = ops.where(finite, n_star + c.n_alpha * ((n - 1.0) - n_star), n_star)
    variances = scaled_variances(n_star, c, ops)
    if gravity is not None and c.fallback_nodes is not None:
        plain = scaled_variances(n_star, c, ops, c.fallback_nodes)
        variances = tuple(ops.where(use_gravity, v, f) for v, f in zip(variances, plain))
    sq, sg, sv, sn = variances
    P = ops.add_diag(P, sq, sg, sv)
    use = ops.both(finite, n >= c.min_load_factor)
    q, V, P = ops.cond(use, _correct, _same3, q, V, P, gyro, Z, sn, c.g, ops)
    return (q, V, P, n_star), variances, use


def _same3(q, V, P, *_):
    return q, V, P


def yaw_of(q, ops=FLOAT_OPS):
    """ZYX yaw of q = (w, x, y, z)."""
    w, x, y, z = q
    return ops.atan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))


def compensated_gravity(mean_specific_force, mean_acceleration, g: float = G, ops=FLOAT_OPS, heading_offset=0.0):
    """(use, gravity) for :func:`step`: the mean world-frame specific force over a window (the IMU's
    samples turned by the filter's own attitude at each) less the vehicle's mean acceleration over the
    same window (the position estimate's velocity change), both world ENU, m/s^2.

    The filter's world frame is turned from the true one by its yaw error (its yaw is the gyros'
    alone, from wherever it started): ``heading_offset`` (rad, the filter's yaw less the vehicle's)
    turns the acceleration into the filter's frame.  A horizontal acceleration a read with a yaw
    error e is a tilt of ~ e |a| / g: 0.1 rad of error in a 3 m/s^2 turn, 1.8 deg.

    Right attitude: gravity, [0, 0, g]; a tilt error turns it away from the vertical, the error the
    correction removes.  Comparing the two over one window removes the lag of the velocity slope
    (a published acceleration subtracted from each sample would be ~0.05 s late: through a flip's
    thrust changes, a worse reference than none).  ``use`` is false where either is not finite or
    the result is under a fifth of g (free fall: nothing to measure the vertical by)."""
    m0, m1, m2 = mean_specific_force
    a0, a1, a2 = mean_acceleration
    ch, sh = ops.cos(heading_offset), ops.sin(heading_offset)
    a0, a1 = ch * a0 - sh * a1, sh * a0 + ch * a1
    v = (m0 - a0, m1 - a1, m2 - a2)
    n = ops.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    use = ops.both(ops.isfinite(n), n >= 0.2 * g)
    return use, tuple(ops.where(use, e, 0.0) for e in v)


_time = itemgetter(0)
_NO_GRAVITY = (False, (0.0, 0.0, 0.0))


def _floats3(v, what: str) -> list:
    out = [float(e) for e in v]
    if len(out) != 3:
        raise ValueError(f"gyrovertical: {what} must have 3 elements, got {len(out)}")
    return out


class GyroIntegrator:
    """Baseline: model 1 alone (pure quaternion integration, no correction)."""

    def __init__(self, dt: float, q0=None):
        if not dt > 0:
            raise ValueError("gyrovertical: dt must be > 0")
        self.dt = float(dt)
        self._half_dt = 0.5 * self.dt
        self._q = (1.0, 0.0, 0.0, 0.0) if q0 is None else tuple(float(e) for e in quat_normalize(q0))

    def update(self, gyro_rad_s, accel_m_s2=None) -> tuple[float, float]:
        """Propagate with one gyro sample (body FLU, rad/s); accel ignored. Returns (roll, pitch)."""
        self._q = propagate(self._q, _floats3(gyro_rad_s, "gyro"), self._half_dt)
        return euler_rp(self._q)

    @property
    def quaternion(self) -> np.ndarray:
        return np.array(self._q)

    @property
    def roll(self) -> float:
        return euler_rp(self._q)[0]

    @property
    def pitch(self) -> float:
        return euler_rp(self._q)[1]


class GyroVertical(GyroIntegrator):
    """The adaptive gyro-vertical of 004 (see the module docstring for the error-state form).

    params: :class:`GyroVerticalParams`; dt: gyro/accelerometer sample period, s.
    adaptive=False gives the fixed-variance baseline (every variance at n* = 0).
    fallback: the parameters used for a sample without a usable acceleration reference (update's
    accel_ref), e.g. a compensated file's uncompensated counterpart; None: ``params`` throughout.
    q0: initial quaternion [w,x,y,z] body->world (default level, yaw 0).
    P0: initial 3x3 covariance of [d_theta, d_gamma, V] (default diag(0.2^2, 0.2^2, 1)).
    min_load_factor: below this |n| the accelerometer is not used.
    n_star_tau_s: time constant of a first-order low-pass on n* before it enters
    (7).  An addition to 004 (which uses the raw sample; pass 0 for that):
    because (7) rises linearly from n* = 0, accelerometer noise alone (~0.002 g
    per sample) would otherwise inflate R at rest several-fold.  0.05 s keeps
    the adaptation fast enough for manoeuvres.

    ``update(gyro, accel)`` = :func:`step` on Python floats: model 1 with the gyro
    sample, then the step (8) with the accelerometer sample of the same instant;
    returns (roll, pitch) of the project's ZYX convention.  ``.x`` gives 004's
    state [theta, gamma, V] (theta = -pitch, gamma = roll), ``.P`` the covariance
    of [d_theta, d_gamma, V], ``.n_star`` and ``.variances`` the last adaptive
    values (Q diag, sigma_n^2, scaled to dt), ``.corrected`` whether the last
    sample's accelerometer was used.
    """

    def __init__(self, params: GyroVerticalParams | None = None, dt: float = DT_REF, q0=None, P0=None,
                 adaptive: bool = True, min_load_factor: float = 0.2, n_star_tau_s: float = 0.05,
                 g: float = G, max_ref_age_s: float = 0.25, history_s: float = 1.0,
                 fallback: GyroVerticalParams | None = None):
        super().__init__(dt, q0)
        self.params = params if params is not None else GyroVerticalParams()
        self.adaptive = bool(adaptive)
        self.min_load_factor = float(min_load_factor)
        self.g = float(g)
        self.V = 0.0
        self._P = np.diag(P0_DIAG) if P0 is None else np.array(P0, dtype=np.float64)
        if self._P.shape != (3, 3):
            raise ValueError("gyrovertical: P0 must be 3x3")
        self.fallback = fallback
        self._c = step_constants([self.params.function(fn) for fn in _FUNCS], self.dt, self.adaptive,
                                 self.min_load_factor, n_star_tau_s, self.g,
                                 None if fallback is None else [fallback.function(fn) for fn in _FUNCS])
        self.n_star = 0.0
        self.variances = scaled_variances(0.0, self._c)
        self.corrected = False
        self.compensated = False
        if not (max_ref_age_s > 0 and history_s > 0):
            raise ValueError(f"gyrovertical: max_ref_age_s and history_s must be > 0, got {max_ref_age_s!r}, "
                             f"{history_s!r}")
        self.max_ref_age_s = float(max_ref_age_s)
        self.history_s = float(history_s)
        self._history: deque = deque()     # (t, world-frame specific force) of the samples, oldest first
        self._window_key = None            # the (t0, t1) whose mean force is _window_mean
        self._window_mean = None

    @property
    def P(self) -> np.ndarray:
        return self._P.copy()

    @property
    def x(self) -> np.ndarray:
        roll, pitch = euler_rp(self._q)
        return np.array([-pitch, roll, self.V])

    def observation_model(self, gyro_rad_s) -> tuple[np.ndarray, np.ndarray]:
        """(Z-bar, H) at the current quaternion and V, doc axes; H columns = [d_theta, d_gamma, V]."""
        zbar, H, _ = observe(self._q, self.V, _floats3(gyro_rad_s, "gyro"), self.g)
        return zbar, H

    def update(self, gyro_rad_s, accel_m_s2, t_s: float | None = None, accel_ref=None,
               heading_rad: float | None = None) -> tuple[float, float]:
        """One sample: model 1 with the gyro (body FLU, rad/s), then (8) with the accel (m/s^2).

        Acceleration compensation (:func:`compensated_gravity`): with the sample's time ``t_s`` (s)
        the filter keeps its samples' world-frame specific forces (``history_s`` of them); with
        ``accel_ref`` = (t0, t1, a), the vehicle's mean acceleration a (world ENU, m/s^2) over
        (t0, t1] from the position estimate, the observation is the gravity that window measures,
        when the kept samples cover it and t1 is at most ``max_ref_age_s`` old.  Otherwise (no
        reference, stale, not covered, not finite) the accelerometer sample, as 004.
        ``.compensated`` says which the last sample used.  ``heading_rad``: the vehicle's yaw (world,
        e.g. the attitude filter's, magnetometer-held): the reference is turned into this filter's
        frame by its yaw error (:func:`compensated_gravity`); None (or not finite): this filter's
        own yaw taken as right (true only for a start at the true yaw and a short flight)."""
        gyro = _floats3(gyro_rad_s, "gyro")
        accel = _floats3(accel_m_s2, "accel")
        if t_s is None and self.fallback is None:   # 004's filter (no compensation): the shortest way
            state, self.variances, self.corrected = step((self._q, self.V, self._P, self.n_star), gyro, accel, self._c)
            self._q, self.V, self._P, self.n_star = state
            return euler_rp(self._q)
        gravity = None
        if t_s is not None and accel_ref is not None:
            offset = 0.0
            if heading_rad is not None and math.isfinite(heading_rad):
                offset = yaw_of(self._q) - float(heading_rad)
            gravity = self._window_gravity(float(t_s), accel_ref, offset)
        if gravity is None and self.fallback is not None:   # no reference: the fallback's variances
            gravity = _NO_GRAVITY
        state, self.variances, self.corrected = step((self._q, self.V, self._P, self.n_star), gyro, accel,
                                                     self._c, gravity=gravity)
        self.compensated = gravity is not None and gravity[0]
        self._q, self.V, self._P, self.n_star = state
        if t_s is not None:
            self._record(float(t_s), accel)
        return euler_rp(self._q)

    def _record(self, t_s: float, accel) -> None:
        hist = self._history
        if hist and t_s <= hist[-1][0]:   # time went back (a restart): the kept forces are another flight's
            hist.clear()
        hist.append((t_s, world_from_body(self._q, accel)))
        while hist[0][0] < t_s - self.history_s:
            hist.popleft()

    def _window_gravity(self, t_s: float, accel_ref, heading_offset: float):
        """(use, gravity) from a reference (t0, t1, a) and the kept forces, or None (not usable)."""
        try:
            t0, t1 = float(accel_ref[0]), float(accel_ref[1])
            a = _floats3(accel_ref[2], "accel_ref acceleration")
        except (TypeError, ValueError, IndexError):
            return None
        hist, eps = self._history, 0.25 * self.dt
        if not (math.isfinite(t0) and math.isfinite(t1) and t1 > t0 and t_s - t1 <= self.max_ref_age_s
                and hist and hist[0][0] <= t0 + eps and hist[-1][0] >= t1 - eps):
            return None
        key = (t0, t1)
        if key != self._window_key:
            # samples in (t0, t1]: their mean is the specific force's over the velocity change's window
            lo = bisect.bisect_right(hist, t0 + eps, key=_time)
            hi = bisect.bisect_right(hist, t1 + eps, key=_time)
            if hi <= lo:
                return None
            n = hi - lo
            m = [sum(hist[i][1][k] for i in range(lo, hi)) / n for k in range(3)]
            self._window_key, self._window_mean = key, m
        return compensated_gravity(self._window_mean, a, self.g, heading_offset=heading_offset)


def run_sequence(filt, gyro, accel, reference=None, heading=None) -> tuple[np.ndarray, np.ndarray]:
    """Feed (N, 3) gyro (rad/s) and accel (m/s^2) samples; returns (roll (N,), pitch (N,)).

    reference (a :class:`GyroVertical` only): (t, t0, t1, a), the samples' times (N,) and at each
    the acceleration reference of :meth:`GyroVertical.update`: window (t0, t1] (N,) and mean
    acceleration (N, 3), world ENU (NaN: none at that sample), e.g. from :func:`fixed_windows`;
    heading (N,): the vehicle's yaw at each sample, rad (None: the filter's own)."""
    gyro = np.asarray(gyro, dtype=np.float64)
    accel = np.asarray(accel, dtype=np.float64)
    if gyro.ndim != 2 or gyro.shape[1] != 3 or accel.shape != gyro.shape:
        raise ValueError(f"gyrovertical: gyro and accel must both be (N, 3), got {gyro.shape}, {accel.shape}")
    n = gyro.shape[0]
    roll = np.empty(n)
    pitch = np.empty(n)
    if reference is None:
        for i in range(n):
            roll[i], pitch[i] = filt.update(gyro[i], accel[i])
        return roll, pitch
    t, t0, t1, a = (np.asarray(x, dtype=np.float64) for x in reference)
    if t.shape != (n,) or t0.shape != (n,) or t1.shape != (n,) or a.shape != (n, 3):
        raise ValueError("gyrovertical: reference must be (t, t0, t1) of (N,) and a of (N, 3)")
    psi = [None] * n if heading is None else np.asarray(heading, dtype=np.float64).tolist()
    for i in range(n):
        ref = (t0[i], t1[i], a[i]) if np.all(np.isfinite(a[i])) else None
        roll[i], pitch[i] = filt.update(gyro[i], accel[i], t[i], ref, psi[i])
    return roll, pitch


def fixed_windows(velocity, dt: float, window: int, delay: int):
    """The acceleration reference of every sample from velocities (N, 3) at the samples (world, m/s):
    (t, t0, t1, a) for :func:`run_sequence`, a = the mean acceleration over the ``window`` sample
    intervals ending ``delay`` samples before each sample (NaN before there is one).  The batched
    filter (:mod:`flight.estimation.gyrovertical_jax`) takes ``a`` with the same window and delay."""
    v = np.asarray(velocity, dtype=np.float64)
    n = v.shape[0]
    if window < 1 or delay < 1:
        raise ValueError(f"gyrovertical: window and delay must be >= 1 sample, got {window}, {delay}")
    t = np.arange(n) * dt
    a = np.full((n, 3), np.nan)
    k = np.arange(window + delay, n)
    a[k] = (v[k - delay] - v[k - delay - window]) / (window * dt)
    return t, t - (window + delay) * dt, t - delay * dt, a


def rms_error_deg(est, truth) -> float:
    """RMS of the wrapped angle difference, degrees (NaN anywhere -> NaN)."""
    d = wrap_angle(np.asarray(est, dtype=np.float64) - np.asarray(truth, dtype=np.float64))
    return float(np.degrees(np.sqrt(np.mean(d * d))))


@dataclass(frozen=True)
class TrainingSequence:
    """Consistent gyro (N,3) rad/s, accel (N,3) m/s^2 (body FLU) and truth roll/pitch (N,) rad.

    The filter starts at (roll0, pitch0), yaw 0 (roll/pitch evolution does not
    depend on the initial yaw).
    """

    gyro: np.ndarray
    accel: np.ndarray
    roll: np.ndarray
    pitch: np.ndarray
    roll0: float
    pitch0: float
    label: str = ""
    accel_ref: np.ndarray | None = None   # (N, 3) the compensation's reference, `a` of fixed_windows
    heading: np.ndarray | None = None     # (N,) the vehicle's yaw, rad, that turns it into the filter's frame


def make_training_sequences(gyro, accel, truth_roll, truth_pitch, bias_deg_s: float = 0.05,
                            roll0: float | None = None, pitch0: float | None = None, accel_ref=None,
                            heading=None) -> list[TrainingSequence]:
    """The 9 sequences of 004: 8 sign combinations of +-bias on the three gyros, plus the exact one.

    roll0/pitch0: initial attitude (default the first truth sample); accel_ref: (N, 3), the
    acceleration compensation's reference of every sample (``a`` of :func:`fixed_windows`), or None;
    heading: (N,) the vehicle's yaw with it (the filters start at yaw 0), or None.
    """
    if accel_ref is not None:
        accel_ref = np.asarray(accel_ref, dtype=np.float64)
    if heading is not None:
        heading = np.asarray(heading, dtype=np.float64)
    gyro = np.asarray(gyro, dtype=np.float64)
    accel = np.asarray(accel, dtype=np.float64)
    roll = np.asarray(truth_roll, dtype=np.float64)
    pitch = np.asarray(truth_pitch, dtype=np.float64)
    r0 = float(roll[0]) if roll0 is None else float(roll0)
    p0 = float(pitch[0]) if pitch0 is None else float(pitch0)
    b = math.radians(bias_deg_s)
    out = []
    for sx in (1, -1):
        for sy in (1, -1):
            for sz in (1, -1):
                bias = b * np.array([sx, sy, sz], dtype=np.float64)
                label = "bias " + "".join("+" if e > 0 else "-" for e in (sx, sy, sz))
                out.append(TrainingSequence(gyro + bias, accel, roll, pitch, r0, p0, label, accel_ref, heading))
    out.append(TrainingSequence(gyro.copy(), accel, roll, pitch, r0, p0, "exact", accel_ref, heading))
    return out


def evaluate(params: GyroVerticalParams, sequences: Sequence[TrainingSequence], dt: float,
             weights: tuple[float, float] = (0.5, 0.5), adaptive: bool = True,
             compensation: tuple[int, int] | None = None) -> float:
    """Criterion (10): a_theta * mean RMS pitch error + a_gamma * mean RMS roll error, degrees.

    compensation: (window, delay) in samples of the sequences' accel_ref, or None (004's filter)."""
    ep, er = [], []
    for s in sequences:
        f = GyroVertical(params, dt, q0=quat_from_euler(s.roll0, s.pitch0, 0.0), adaptive=adaptive)
        ref = None
        if compensation is not None:
            t = np.arange(len(s.roll)) * dt
            ref = (t, t - sum(compensation) * dt, t - compensation[1] * dt, s.accel_ref)
        r, p = run_sequence(f, s.gyro, s.accel, ref, s.heading if ref is not None else None)
        ep.append(rms_error_deg(p, s.pitch))
        er.append(rms_error_deg(r, s.roll))
    cost = weights[0] * float(np.mean(ep)) + weights[1] * float(np.mean(er))
    return cost if math.isfinite(cost) else 1e6


@dataclass(frozen=True)
class TrainedParams:
    """A trained parameter file: the adaptive filter's parameters, the fixed-variance
    baseline trained on the same data, and how they were made (``meta``)."""

    adaptive: GyroVerticalParams
    fixed: GyroVerticalParams
    meta: dict
    # a compensated file's parameters for samples without a reference ([fallback]; None: adaptive's)
    fallback: GyroVerticalParams | None = None

    def flown(self, compensated: bool) -> tuple[GyroVerticalParams, GyroVerticalParams | None]:
        """(params, fallback) of the GyroVertical that flies this file: compensated, the adaptive
        parameters with the fallback for samples without a reference; not, the fallback when there is
        one (the filter trusting a bare accelerometer as a manoeuvre leaves it), else the adaptive."""
        if compensated:
            return self.adaptive, self.fallback
        return (self.fallback if self.fallback is not None else self.adaptive), None


def load_trained(path: str | Path = DEFAULT_PARAMS_FILE) -> TrainedParams:
    """Read a file written by `zenpilot train-gyrovertical`; errors name the file."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read gyro-vertical parameters: {exc}") from None
    try:
        return TrainedParams(GyroVerticalParams.from_dict(data.get("adaptive", {})),
                             GyroVerticalParams.from_dict(data.get("fixed", {})), dict(data.get("meta", {})),
                             GyroVerticalParams.from_dict(data["fallback"]) if "fallback" in data else None)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
