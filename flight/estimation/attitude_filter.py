"""Attitude-level estimator of document 000 (fast loop): low-pass (12), per-axis
Kalman filter on the model with the filter lag (13), (16)-(20), analytic
extrapolator (15) over the transport delay.  Pure algorithm, no I/O.

Per axis (roll, pitch, yaw alike; 000 uses the body rate as the Euler-angle
rate, valid near hover, and neglects the cross-coupling terms)::

    w'  = u                      u = torque / I  (the commanded torque)
    wf' = k_f (w - wf)           k_f = 1 / lpf_tau_s, the low-pass (12)
    a'  = w
    af' = k_f (a - af)

state ``x = [w, wf, a, af]`` (16), measurements ``z = [wf, af]``: the
low-passed gyro rate and the low-passed accelerometer (roll, pitch) or
tilt-compensated magnetometer (yaw) angle.  The low-pass therefore removes the
noise while the Kalman filter, knowing the filter's lag, undoes the lag.

Additions to 000 (each with its ablation in ``AttitudeFilterParams``):

* gyro bias state b per axis (x = [w, wf, a, af, b], the low-passed gyro reads
  wf + b): a MEMS gyro's turn-on bias (the simulator's: sigma ~0.18 deg/s)
  otherwise leaves b x (the angle correction time) of error, 0.1-0.3 deg.
  ``init_bias_var = 0`` (with a negligible ``bias_process_var``) is 000's filter.
* ZYX kinematics (``euler_kinematics``): the angles integrate the Euler rates
  W(roll, pitch) w of the estimated body rates, the other axes entering as a
  known input; 000 takes the body rate as the Euler rate (at 20 deg of roll and
  pitch, 12 % of the pitch rate goes missing from the roll rate).
* acceleration reference (``update(..., accel_ref=(t0, t1, a))``): a multirotor's
  accelerometer reads "level" whenever it tilts to accelerate, so the angle
  measurement needs the vehicle's acceleration.  Given the mean acceleration a over
  a past window [t0, t1] (the position level's velocity change), the filter
  compares it with the mean over the same window of a_model = R f + g, the
  acceleration the measured specific force f implies at the filter's own attitude
  R (kept per IMU sample), and measures the angles of the accelerometer
  compensated with R f + g + c, c = a - mean(a_model): f - R^T (R f + g + c) =
  R^T ([0, 0, g] - c), the predicted attitude moved by the bounded correction c.
  Comparing like with like removes the lag of the velocity slope (subtracting it
  directly, the angle is pulled towards level by ~1 deg after every tilt step).

Ablations of 000 itself:

* ``model_filter_lag=False``: the cascade without the filter lag in the model;
  the low-passed signals are taken as direct measurements of w and a
  (H picks w and a), so the estimate inherits the low-pass lag (about tau).
* ``extrapolate=False``: no extrapolator; the estimate refers to the newest
  IMU sample's time, i.e. it is late by the transport delay.

Discretisation.  The model is linear and time invariant, so F, B (and Q by
Van Loan's method from the continuous noise densities) are the exact matrix
exponentials for a step h, here in closed form (``discrete_model``).  The
filter steps at every IMU sample (400 Hz, two per 200 Hz call) with the exact
F, B, Q of the actual interval (rounded to 0.1 ms), split wherever the
commanded torque changed inside it (the torque is piecewise constant between
calls).

Extrapolator (15).  From the filtered state at the newest IMU sample time
t_s the model is integrated forward to t_now with the torques that were
applied over [t_s, t_now) (their history is kept).  000 writes this as
N = round((t_now - t_s)/dt) steps of dt; here the same model is integrated
exactly over the measured delay (so a delay that is not a multiple of dt,
e.g. 10 ms plus an IMU phase of 2.5 ms, is compensated in full), piecewise in
the stored torques, capped at ``max_delay_steps * dt``.  The covariance is
propagated with it (euler_var, rate_var grow with the delay).

Yaw.  From the magnetometer, tilt-compensated with the filter's current
roll/pitch; the world field's horizontal direction comes from
``mag_field_world_ut`` (ENU, north = +y).  Between magnetometer samples
(50 Hz) the held yaw is carried on by the z gyro, so the 400 Hz low-pass sees
no zero-order-hold lag.  Yaw innovations and every angle state are wrapped to
[-pi, pi).  Until the first magnetometer sample the yaw is 0 with a large
variance; the first sample sets it.
"""
from __future__ import annotations

import bisect
import math
import operator
from dataclasses import dataclass

import numpy as np

from flight.param import Declared, declared
from flight.quat import TWO_PI as _TWO_PI
from flight.quat import quat_from_euler_floats, wrap_angle_float

W, WF, A, AF, B = 0, 1, 2, 3, 4    # state indices per axis (B: the gyro bias)
NX = 5
G_REF = 9.80665
_PI = math.pi
_BIG_ANGLE_VAR = math.pi ** 2      # yaw variance before any magnetometer sample


def _rotation_rows(roll: float, pitch: float, yaw: float):
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return ((cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr),
            (sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr),
            (-sp, cp * sr, cp * cr))


def rotation_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Body -> world rotation R = Rz(yaw) Ry(pitch) Rx(roll) (ZYX, as quat_from_euler)."""
    return np.array(_rotation_rows(roll, pitch, yaw))


def _roll_pitch(ax: float, ay: float, az: float) -> tuple[float, float]:
    return math.atan2(ay, az), math.atan2(-ax, math.hypot(ay, az))


def accel_roll_pitch(accel) -> tuple[float, float]:
    """(roll, pitch) from specific force in body FLU (exact for the ZYX convention at rest)."""
    ax, ay, az = (float(v) for v in accel)
    return _roll_pitch(ax, ay, az)


def mag_yaw(field_body, roll: float, pitch: float, field_world=(0.0, 20.0, -45.0)) -> float:
    """Yaw (ZYX, ENU) from a body-FLU magnetometer reading, tilt-compensated.

    Ry(pitch) Rx(roll) m_body is the field in the yaw-only frame, i.e.
    Rz(yaw)^T m_world; its horizontal direction is the world field's turned by -yaw.
    """
    mx, my, mz = (float(v) for v in field_body)
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    # Rx(roll) m
    y1 = cr * my - sr * mz
    z1 = sr * my + cr * mz
    # Ry(pitch) (.)
    hx = cp * mx + sp * z1
    hy = y1
    beta = math.atan2(float(field_world[1]), float(field_world[0]))
    return wrap_angle_float(beta - math.atan2(hy, hx))


# ------------------------------------------------------------------ parameters
@dataclass(frozen=True)
class AttitudeFilterParams(Declared):
    """Parameters of :class:`AttitudeFilter` (the attitude service's `filter` table).  Per-axis
    tuples are (roll, pitch, yaw); one number stands for all three.

    Variances of the measurements are per IMU sample (400 Hz); the process
    noises are continuous densities (discretised exactly for each step).
    """
    lpf_tau_s: float = declared(0.02, "s", 0.0, min_exclusive=True,
                                doc="(12): first-order low-pass on the gyro and on the accelerometer/magnetometer "
                                    "angles, k_f = 1/tau")
    # The raw gyro noise is 1e-5 per sample; after the low-pass it is ~6e-7 but coloured
    # (correlated over ~tau), so the raw per-sample value is kept as a conservative white-noise
    # equivalent.
    rate_meas_var: tuple = declared((1e-5, 1e-5, 1e-5), "rad^2/s^2", 0.0, min_exclusive=True, per_axis=True,
                                    doc="R: the low-passed gyro rate's variance per IMU sample")
    # The sensor noise alone is ~1e-6 (accel) and ~6e-4 (mag, 0.5 uT over a 20 uT horizontal
    # field); roll/pitch use a larger value so the gyro carries the short term (the accelerometer
    # pulls with a ~0.5 s time constant). In flight a multirotor's accelerometer reads "level"
    # whenever it tilts to accelerate: the attitude service subtracts the position level's
    # acceleration estimate first (without that, 1e-3 left the hover estimate 5 deg off; 5e-2
    # only slowed the drift). Yaw: the 50 Hz magnetometer is held over 8 IMU samples, so its
    # per-sample variance is ~8x the sensor's 6e-4.
    angle_meas_var: tuple = declared((1e-3, 1e-3, 5e-3), "rad^2", 0.0, min_exclusive=True, per_axis=True,
                                     doc="R: the low-passed accelerometer (roll, pitch) and magnetometer (yaw) "
                                         "angles' variance per IMU sample")
    rate_process_var: tuple = declared((50.0, 50.0, 20.0), "rad^2/s^3", 0.0, min_exclusive=True, per_axis=True,
                                       doc="Q: density of the unmodelled angular acceleration (torque error, "
                                           "motor lag, disturbances)")
    # What the model leaves out: scale errors, vibration. 1e-5 (~0.5 s) in 000, which also had
    # to absorb the gyro bias and the body-vs-Euler rate; both are modelled here (bias state,
    # euler_kinematics), so roll and pitch trust the gyro longer and average the acceleration
    # reference's noise (~0.3 m/s^2, i.e. ~1.7 deg) over ~1 s. Yaw (magnetometer) keeps 1e-5.
    angle_process_var: tuple = declared((3e-6, 3e-6, 1e-5), "rad^2/s", 0.0, min_exclusive=True, per_axis=True,
                                        doc="Q: density of a random walk on the angles: how fast the angle "
                                            "measurement pulls the gyro-integrated angle")
    # the simulator's walk is 1e-10; a MEMS gyro's bias also moves with temperature, hence the margin
    bias_process_var: tuple = declared((1e-9, 1e-9, 1e-9), "rad^2/s^3", 0.0, min_exclusive=True, per_axis=True,
                                       doc="Q: density of the gyro bias random walk")
    model_filter_lag: bool = declared(True, doc="the model holds the low-pass's lag; false: ablation \"cascade "
                                                "without the filter lag in the model\"")
    # Off by 12 % of the pitch rate in roll at 20 deg of roll and pitch when the body rate is
    # taken as the Euler rate
    euler_kinematics: bool = declared(True, doc="the angles integrate the ZYX Euler rates of the estimated body "
                                                "rates (the other axes' estimates a known input); false: 000 as "
                                                "printed, the body rate taken as the Euler rate")
    extrapolate: bool = declared(True, doc="extrapolate the delayed estimate to now (15); false: ablation")
    max_delay_steps: int = declared(10, "", 0, doc="extrapolate at most this many IMU steps (longer delays are "
                                                   "capped)")
    mag_field_world_ut: tuple = declared((0.0, 20.0, -45.0), "uT",
                                         doc="Earth's magnetic field, world ENU: only its horizontal direction is "
                                             "used (yaw)")
    init_angle_var: float = declared(1e-2, "rad^2", 0.0, min_exclusive=True,
                                     doc="angle variance at initialisation (roll, pitch; yaw once the "
                                         "magnetometer is seen)")
    init_rate_var: float = declared(1e-2, "rad^2/s^2", 0.0, min_exclusive=True,
                                    doc="rate variance at initialisation")
    # a MEMS gyro's turn-on bias, ~0.2 deg/s; 0 with bias_process_var ~0 is the ablation "no bias
    # state" (the bias stays 0)
    init_bias_var: float = declared(1e-5, "rad^2/s^2", 0.0, doc="gyro bias variance at start")
    min_accel_g: float = declared(0.3, "g", 0.0, doc="specific force below this: no accelerometer angle update "
                                                     "(free fall)")
    max_gap_s: float = declared(0.5, "s", 0.0, min_exclusive=True,
                                doc="IMU silent for longer: re-initialise from the next sample")
    # Acceleration reference (``update(..., accel_ref=...)``, see AttitudeFilter): an attitude
    # error of ~18 deg in hover; the position level's acceleration noise is ~0.3 m/s^2. A wrong
    # reference or a stale history (after a flip) can only pull at a bounded rate ...
    aid_max_correction_m_s2: float = declared(3.0, "m/s^2", 0.0, min_exclusive=True,
                                              doc="the acceleration reference's correction is bounded to this "
                                                  "magnitude")
    # ... and without a recent one the raw accelerometer angles of 000 are used
    aid_max_age_s: float = declared(0.25, "s", 0.0, min_exclusive=True,
                                    doc="an acceleration reference whose window ended longer ago is not used")

    def __post_init__(self):
        super().__post_init__()
        if math.hypot(self.mag_field_world_ut[0], self.mag_field_world_ut[1]) <= 0:
            raise ValueError(f"AttitudeFilterParams.mag_field_world_ut: needs a horizontal component, "
                             f"got {self.mag_field_world_ut}")


@dataclass
class AttitudeEstimate:
    euler_rad: np.ndarray        # (3,) roll, pitch, yaw at t_now (ZYX), wrapped to [-pi, pi)
    rate_rad_s: np.ndarray       # (3,) body rates (used as Euler rates, as 000 does)
    quaternion_wxyz: np.ndarray  # (4,) body -> world
    euler_var: np.ndarray        # (3,) Kalman variances of the angles, rad^2
    rate_var: np.ndarray         # (3,) Kalman variances of the rates, rad^2/s^2
    delay_s: float               # t_now - newest IMU sample time (the measured transport delay)


# ------------------------------------------------------------------ model
_MIN_COS_PITCH = 0.2   # the ZYX rates are singular at pitch +-90 deg (the filter hands over at 45)


def _euler_rate_excess(roll: float, pitch: float, p: float, q: float, r: float) -> tuple[float, float, float]:
    sr, cr = math.sin(roll), math.cos(roll)
    cp = math.cos(pitch)
    cp = math.copysign(max(abs(cp), _MIN_COS_PITCH), cp)
    tp = math.sin(pitch) / cp
    return ((sr * q + cr * r) * tp,
            (cr - 1.0) * q - sr * r,
            (sr * q + cr * r) / cp - r)


def euler_rate_excess(roll: float, pitch: float, rate) -> np.ndarray:
    """ZYX Euler rates less the body rates: W(roll, pitch) w - w (0 when level).

    roll' = p + sin(roll) tan(pitch) q + cos(roll) tan(pitch) r; pitch' = cos(roll) q - sin(roll) r;
    yaw' = (sin(roll) q + cos(roll) r) / cos(pitch).  |cos(pitch)| is floored at 0.2."""
    p, q, r = (float(v) for v in rate)
    return np.array(_euler_rate_excess(float(roll), float(pitch), p, q, r))


def continuous_model(lpf_tau_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(A, Bc) of (13) for one axis, state [w, wf, a, af, b], inputs [torque / I, e].

    b, the gyro bias, is constant (a random walk in Q); the low-passed gyro reads wf + b.
    e is added to the angle's rate: the Euler rate less the body rate (:func:`euler_rate_excess`)."""
    k = 1.0 / lpf_tau_s
    a = np.array([[0.0, 0.0, 0.0, 0.0, 0.0],
                  [k, -k, 0.0, 0.0, 0.0],
                  [1.0, 0.0, 0.0, 0.0, 0.0],
                  [0.0, 0.0, k, -k, 0.0],
                  [0.0, 0.0, 0.0, 0.0, 0.0]])
    b = np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    b[A, 1] = 1.0
    return a, b


def _power_series(n_terms: int = 20) -> tuple[list[float], ...]:
    """Taylor coefficients in x = k h of the integrals of _closed_form, scaled by powers of h: its
    differences cancel for small x (at x = 1e-3 the closed form keeps 4 digits of int psi^2);
    below x = 1 the first 20 terms are exact to rounding."""
    f = math.factorial
    c = [0.0] + [(-1) ** (n + 1) / f(n) for n in range(1, 2 * n_terms + 3)]   # phi_s = sum c_n (k s)^n
    d = [0.0, 0.0] + [-c[n] for n in range(2, 2 * n_terms + 3)]              # psi_s = sum d_n k^(n-1) s^n
    r = range(n_terms + 1)
    return ([c[j] / (j + 1) for j in r],                                          # psi / h
            [d[j + 1] / (j + 2) if j else 0.0 for j in r],                        # int psi / h^2
            [sum(c[m] * c[j - m] for m in range(1, j)) / (j + 1) for j in r],     # int phi^2 / h
            [c[j] / (j + 2) for j in r],                                          # int s phi / h^2
            [sum(c[m] * d[j + 1 - m] for m in range(1, j)) / (j + 2) for j in r],  # int phi psi / h^2
            [d[j + 1] / (j + 3) if j else 0.0 for j in r],                        # int s psi / h^3
            [sum(d[m] * d[j + 2 - m] for m in range(2, j + 1)) / (j + 3) for j in r])  # int psi^2 / h^3


_SERIES = _power_series()


def _horner(coefs: list[float], x: float) -> float:
    out = 0.0
    for c in reversed(coefs):
        out = out * x + c
    return out


def _closed_form(k: float, h: float):
    """The exact discretisation of (13) over h, in closed form (below k h = 1 the integrals from
    their power series, where the closed form's differences cancel).

    With E = exp(-k h), phi = 1 - E (the low-pass's step response) and psi = h - phi / k
    (its integral), F = exp(A h) is
        w:  [1, 0, 0, 0, 0]        wf: [phi, E, 0, 0, 0]        a: [h, 0, 1, 0, 0]
        af: [psi, 0, phi, E, 0]    b:  [0, 0, 0, 0, 1],
    B = [[h, psi, h^2/2, h^2/2 - psi/k, 0], [0, 0, h, psi, 0]]^T (inputs u, e), and the unit
    process noises on w', a', b' are the integrals over s in [0, h] of g g^T, g = F(s) e_{w, a, b}
    (Van Loan's Q): g_w = [1, phi_s, s, psi_s, 0], g_a = [0, 0, 1, phi_s, 0], g_b = e_b.
    Returns (coef, qw, qa) with coef = (h, E, phi, psi, h^2/2, h^2/2 - psi/k) and the non-zero
    upper-triangle integrals qw = (ww, w wf, w a, w af, wf wf, wf a, wf af, a a, a af, af af),
    qa = (a a, a af, af af); Qb is h on (b, b)."""
    x = k * h
    e = math.exp(-x)
    phi = -math.expm1(-x)
    h2 = 0.5 * h * h
    h3 = h * h * h / 3.0
    if x < 1.0:
        s_psi, s_u_af, s_phi2, s_sphi, s_phipsi, s_spsi, s_psi2 = (_horner(c, x) for c in _SERIES)
        psi, u_af = h * s_psi, h * h * s_u_af
        i_phi2, i_sphi, i_phipsi = h * s_phi2, h * h * s_sphi, h * h * s_phipsi
        i_spsi, i_psi2 = h * h * h * s_spsi, h * h * h * s_psi2
    else:
        psi = h - phi / k
        u_af = h2 - psi / k                                # int psi
        i_phi2 = psi - phi * phi / (2.0 * k)               # int phi^2
        i_sphi = h2 - (phi - x * e) / (k * k)              # int s phi
        i_phipsi = i_sphi - i_phi2 / k                     # int phi psi
        i_spsi = h3 - i_sphi / k                           # int s psi
        i_psi2 = h3 - 2.0 * i_sphi / k + i_phi2 / (k * k)  # int psi^2
    coef = (h, e, phi, psi, h2, u_af)
    qw = (h, psi, h2, u_af, i_phi2, i_sphi, i_phipsi, h3, i_spsi, i_psi2)
    qa = (h, psi, i_phi2)
    return coef, qw, qa


def discrete_model(lpf_tau_s: float, h: float) -> tuple[np.ndarray, ...]:
    """(F, B, Qw, Qa, Qb) of (13) for a step h: exp(A h), its input matrix and the process
    noise of a unit density on w', a' and b' (what the filter uses, as matrices)."""
    (h, e, phi, psi, h2, u_af), qw, qa = _closed_form(1.0 / lpf_tau_s, h)
    f = np.eye(NX)
    f[WF, W], f[WF, WF] = phi, e
    f[A, W] = h
    f[AF, W], f[AF, A], f[AF, AF] = psi, phi, e
    bd = np.zeros((NX, 2))
    bd[:, 0] = (h, psi, h2, u_af, 0.0)
    bd[A, 1], bd[AF, 1] = h, psi
    q_w, q_a, q_b = np.zeros((NX, NX)), np.zeros((NX, NX)), np.zeros((NX, NX))
    for (i, j), v in zip(((W, W), (W, WF), (W, A), (W, AF), (WF, WF), (WF, A), (WF, AF), (A, A), (A, AF),
                          (AF, AF)), qw):
        q_w[i, j] = q_w[j, i] = v
    for (i, j), v in zip(((A, A), (A, AF), (AF, AF)), qa):
        q_a[i, j] = q_a[j, i] = v
    q_b[B, B] = h
    return f, bd, q_w, q_a, q_b


# The covariance of an axis is kept as its upper triangle, row by row (15 floats):
# (00, 01, 02, 03, 04, 11, 12, 13, 14, 22, 23, 24, 33, 34, 44).
_TRI = [(i, j) for i in range(NX) for j in range(i, NX)]
_P_WW, _P_AA, _P_BB = _TRI.index((W, W)), _TRI.index((A, A)), _TRI.index((B, B))


def _tri_to_matrix(p) -> np.ndarray:
    m = np.zeros((NX, NX))
    for (i, j), v in zip(_TRI, p):
        m[i, j] = m[j, i] = v
    return m


class _Discretiser:
    """Per step h: the coefficients of F and B and each axis's Q (upper triangle), cached.

    Steps are rounded to 0.1 ms (the key is h in units of 0.1 ms): in real time every interval
    differs; 0.1 ms is far below the model's time constants (tau = 20 ms).  A miss costs a few
    microseconds (the closed form, not a matrix exponential)."""

    def __init__(self, lpf_tau_s: float, rate_var, angle_var, bias_var):
        self.k = 1.0 / lpf_tau_s
        self.noise = tuple(zip(rate_var, angle_var, bias_var))
        self.cache: dict[int, tuple] = {}

    def __call__(self, key: int):
        """(coef, (q_roll, q_pitch, q_yaw)) for the step key * 0.1 ms (coef as in _closed_form)."""
        hit = self.cache.get(key)
        if hit is not None:
            return hit
        if len(self.cache) > 4096:
            self.cache.clear()
        coef, (ww, wwf, wa, waf, wfwf, wfa, wfaf, aa, aaf, afaf), (a_a, a_af, af_af) = \
            _closed_form(self.k, key * 1e-4)
        h = coef[0]
        qs = tuple((rv * ww, rv * wwf, rv * wa, rv * waf, 0.0,
                    rv * wfwf, rv * wfa, rv * wfaf, 0.0,
                    rv * aa + av * a_a, rv * aaf + av * a_af, 0.0,
                    rv * afaf + av * af_af, 0.0,
                    bv * h) for rv, av, bv in self.noise)
        hit = self.cache[key] = (coef, qs)
        return hit


def _step_key(h: float) -> int:
    return int(round(h * 1e4))


def _predict_x(x, coef, u: float, e: float):
    """x = F x + B [u, e] for one axis."""
    w, wf, a, af, b = x
    h, ee, phi, psi, h2, u_af = coef
    return (w + h * u,
            (phi * w + ee * wf) + psi * u,
            (h * w + a) + (h2 * u + h * e),
            (psi * w + phi * a + ee * af) + (u_af * u + psi * e),
            b)


def _predict_p(p, coef, q):
    """P = F P F^T + Q for one axis (upper triangles; F's structure written out)."""
    p00, p01, p02, p03, p04, p11, p12, p13, p14, p22, p23, p24, p33, p34, p44 = p
    h, ee, phi, psi = coef[0], coef[1], coef[2], coef[3]
    # rows wf, a, af of F P
    n10, n11, n12, n13, n14 = (phi * p00 + ee * p01, phi * p01 + ee * p11, phi * p02 + ee * p12,
                               phi * p03 + ee * p13, phi * p04 + ee * p14)
    n20, n22, n23, n24 = h * p00 + p02, h * p02 + p22, h * p03 + p23, h * p04 + p24
    n30, n32, n33, n34 = (psi * p00 + phi * p02 + ee * p03, psi * p02 + phi * p22 + ee * p23,
                          psi * p03 + phi * p23 + ee * p33, psi * p04 + phi * p24 + ee * p34)
    return (p00 + q[0], n10 + q[1], n20 + q[2], n30 + q[3], p04,
            phi * n10 + ee * n11 + q[5], h * n10 + n12 + q[6], psi * n10 + phi * n12 + ee * n13 + q[7], n14,
            h * n20 + n22 + q[9], psi * n20 + phi * n22 + ee * n23 + q[10], n24,
            psi * n30 + phi * n32 + ee * n33 + q[12], n34,
            p44 + q[14])


def _update(x, p, z_rate: float, z_angle, r_rate: float, r_angle: float, lag: bool):
    """Kalman update of one axis with the low-passed gyro z_rate (and the angle z_angle, None: rate only).

    H = [[0, 1, 0, 0, 1], [0, 0, 0, 1, 0]] (lag: the gyro reads wf + b, the angle af) or
    [[1, 0, 0, 0, 1], [0, 0, 1, 0, 0]].  The Joseph form (I-KH) P (I-KH)^T + K R K^T (filterpy's,
    which the unit tests compare against) expands to P - K C^T - C K^T + K S K^T (C = P H^T,
    S = H C + R); with the optimal gain K = C S^-1 the last term is K C^T, so P - K C^T, computed
    here on the upper triangle (symmetric by construction).  S is 2x2 and inverted in closed
    form; rate only is the 1x1 case (filterpy's zeroed H row)."""
    w, wf, a, af, b = x
    p00, p01, p02, p03, p04, p11, p12, p13, p14, p22, p23, p24, p33, p34, p44 = p
    if lag:   # C = P H^T: c the rate column (P_1 + P_4), d the angle column (P_3)
        c0, c1, c2, c3, c4 = p01 + p04, p11 + p14, p12 + p24, p13 + p34, p14 + p44
        d0, d1, d2, d3, d4 = p03, p13, p23, p33, p34
        s00, s01, s11 = c1 + c4 + r_rate, d1 + d4, d3 + r_angle
        y0 = z_rate - (wf + b)
    else:
        c0, c1, c2, c3, c4 = p00 + p04, p01 + p14, p02 + p24, p03 + p34, p04 + p44
        d0, d1, d2, d3, d4 = p02, p12, p22, p23, p24
        s00, s01, s11 = c0 + c4 + r_rate, d0 + d4, d2 + r_angle
        y0 = z_rate - (w + b)
    if z_angle is None:
        g = 1.0 / s00
        k0, k1, k2, k3, k4 = c0 * g, c1 * g, c2 * g, c3 * g, c4 * g
        return ((w + k0 * y0, wf + k1 * y0, a + k2 * y0, af + k3 * y0, b + k4 * y0),
                (p00 - k0 * c0, p01 - k0 * c1, p02 - k0 * c2, p03 - k0 * c3, p04 - k0 * c4,
                 p11 - k1 * c1, p12 - k1 * c2, p13 - k1 * c3, p14 - k1 * c4,
                 p22 - k2 * c2, p23 - k2 * c3, p24 - k2 * c4,
                 p33 - k3 * c3, p34 - k3 * c4, p44 - k4 * c4))
    y1 = z_angle - (af if lag else a)
    det = s00 * s11 - s01 * s01
    i00, i01, i11 = s11 / det, -s01 / det, s00 / det
    # K = C S^-1: k the rate column, l the angle column
    k0, l0 = c0 * i00 + d0 * i01, c0 * i01 + d0 * i11
    k1, l1 = c1 * i00 + d1 * i01, c1 * i01 + d1 * i11
    k2, l2 = c2 * i00 + d2 * i01, c2 * i01 + d2 * i11
    k3, l3 = c3 * i00 + d3 * i01, c3 * i01 + d3 * i11
    k4, l4 = c4 * i00 + d4 * i01, c4 * i01 + d4 * i11
    return ((w + (k0 * y0 + l0 * y1), wf + (k1 * y0 + l1 * y1), a + (k2 * y0 + l2 * y1),
             af + (k3 * y0 + l3 * y1), b + (k4 * y0 + l4 * y1)),
            (p00 - (k0 * c0 + l0 * d0), p01 - (k0 * c1 + l0 * d1), p02 - (k0 * c2 + l0 * d2),
             p03 - (k0 * c3 + l0 * d3), p04 - (k0 * c4 + l0 * d4),
             p11 - (k1 * c1 + l1 * d1), p12 - (k1 * c2 + l1 * d2), p13 - (k1 * c3 + l1 * d3),
             p14 - (k1 * c4 + l1 * d4),
             p22 - (k2 * c2 + l2 * d2), p23 - (k2 * c3 + l2 * d3), p24 - (k2 * c4 + l2 * d4),
             p33 - (k3 * c3 + l3 * d3), p34 - (k3 * c4 + l3 * d4),
             p44 - (k4 * c4 + l4 * d4)))


def _kf_axis(x, p, coef, q, z_rate: float, z_angle, r_rate: float, r_angle: float):
    """_predict_p, then _update with the filter lag in H, then _rewrap, of one axis in one call:
    the same expressions, without the calls and the tuples between them (the filter runs this
    three times per IMU sample). coef, q: the step's (not None); z_angle None: rate only.
    Returns (x, P, gain): the gain's columns (k, then l unless rate only) for _kf_state, which
    updates an axis whose covariance is this one's (the same P, Q and R: the same gain)."""
    w, wf, a, af, b = x
    p00, p01, p02, p03, p04, p11, p12, p13, p14, p22, p23, p24, p33, p34, p44 = p
    h, ee, phi, psi = coef[0], coef[1], coef[2], coef[3]
    # _predict_p: rows wf, a, af of F P, then F P F^T + Q
    n10, n11, n12, n13, n14 = (phi * p00 + ee * p01, phi * p01 + ee * p11, phi * p02 + ee * p12,
                               phi * p03 + ee * p13, phi * p04 + ee * p14)
    n20, n22, n23, n24 = h * p00 + p02, h * p02 + p22, h * p03 + p23, h * p04 + p24
    n30, n32, n33, n34 = (psi * p00 + phi * p02 + ee * p03, psi * p02 + phi * p22 + ee * p23,
                          psi * p03 + phi * p23 + ee * p33, psi * p04 + phi * p24 + ee * p34)
    p00, p01, p02, p03, p04, p11, p12, p13, p14, p22, p23, p24, p33, p34, p44 = (
        p00 + q[0], n10 + q[1], n20 + q[2], n30 + q[3], p04,
        phi * n10 + ee * n11 + q[5], h * n10 + n12 + q[6], psi * n10 + phi * n12 + ee * n13 + q[7], n14,
        h * n20 + n22 + q[9], psi * n20 + phi * n22 + ee * n23 + q[10], n24,
        psi * n30 + phi * n32 + ee * n33 + q[12], n34,
        p44 + q[14])
    # _update, lag: C = P H^T, c the rate column (P_1 + P_4), d the angle column (P_3)
    c0, c1, c2, c3, c4 = p01 + p04, p11 + p14, p12 + p24, p13 + p34, p14 + p44
    s00 = c1 + c4 + r_rate
    y0 = z_rate - (wf + b)
    if z_angle is None:
        g = 1.0 / s00
        k0, k1, k2, k3, k4 = gain = (c0 * g, c1 * g, c2 * g, c3 * g, c4 * g)
        w, wf, a, af, b = w + k0 * y0, wf + k1 * y0, a + k2 * y0, af + k3 * y0, b + k4 * y0
        p = (p00 - k0 * c0, p01 - k0 * c1, p02 - k0 * c2, p03 - k0 * c3, p04 - k0 * c4,
             p11 - k1 * c1, p12 - k1 * c2, p13 - k1 * c3, p14 - k1 * c4,
             p22 - k2 * c2, p23 - k2 * c3, p24 - k2 * c4,
             p33 - k3 * c3, p34 - k3 * c4, p44 - k4 * c4)
    else:
        d0, d1, d2, d3, d4 = p03, p13, p23, p33, p34
        s01, s11 = d1 + d4, d3 + r_angle
        y1 = z_angle - af
        det = s00 * s11 - s01 * s01
        i00, i01, i11 = s11 / det, -s01 / det, s00 / det
        k0, k1, k2, k3, k4, l0, l1, l2, l3, l4 = gain = (
            c0 * i00 + d0 * i01, c1 * i00 + d1 * i01, c2 * i00 + d2 * i01, c3 * i00 + d3 * i01, c4 * i00 + d4 * i01,
            c0 * i01 + d0 * i11, c1 * i01 + d1 * i11, c2 * i01 + d2 * i11, c3 * i01 + d3 * i11, c4 * i01 + d4 * i11)
        w, wf, a, af, b = (w + (k0 * y0 + l0 * y1), wf + (k1 * y0 + l1 * y1), a + (k2 * y0 + l2 * y1),
                           af + (k3 * y0 + l3 * y1), b + (k4 * y0 + l4 * y1))
        p = (p00 - (k0 * c0 + l0 * d0), p01 - (k0 * c1 + l0 * d1), p02 - (k0 * c2 + l0 * d2),
             p03 - (k0 * c3 + l0 * d3), p04 - (k0 * c4 + l0 * d4),
             p11 - (k1 * c1 + l1 * d1), p12 - (k1 * c2 + l1 * d2), p13 - (k1 * c3 + l1 * d3),
             p14 - (k1 * c4 + l1 * d4),
             p22 - (k2 * c2 + l2 * d2), p23 - (k2 * c3 + l2 * d3), p24 - (k2 * c4 + l2 * d4),
             p33 - (k3 * c3 + l3 * d3), p34 - (k3 * c4 + l3 * d4),
             p44 - (k4 * c4 + l4 * d4))
    # _rewrap (wrap_angle_float written out)
    s = ((a + _PI) % _TWO_PI - _PI) - a
    if s != 0.0:
        a += s
        af += s
    return (w, wf, a, a + ((af - a + _PI) % _TWO_PI - _PI), b), p, gain


def _kf_state(x, gain, z_rate: float, z_angle):
    """The state part of _kf_axis with a gain it returned: the update of x, then _rewrap."""
    w, wf, a, af, b = x
    y0 = z_rate - (wf + b)
    if z_angle is None:
        k0, k1, k2, k3, k4 = gain
        w, wf, a, af, b = w + k0 * y0, wf + k1 * y0, a + k2 * y0, af + k3 * y0, b + k4 * y0
    else:
        k0, k1, k2, k3, k4, l0, l1, l2, l3, l4 = gain
        y1 = z_angle - af
        w, wf, a, af, b = (w + (k0 * y0 + l0 * y1), wf + (k1 * y0 + l1 * y1), a + (k2 * y0 + l2 * y1),
                           af + (k3 * y0 + l3 * y1), b + (k4 * y0 + l4 * y1))
    s = ((a + _PI) % _TWO_PI - _PI) - a
    if s != 0.0:
        a += s
        af += s
    return w, wf, a, a + ((af - a + _PI) % _TWO_PI - _PI), b


def _rewrap(x):
    """Wrap the angle state to [-pi, pi) and move af by the same turn (keeps af - a small)."""
    w, wf, a, af, b = x
    s = wrap_angle_float(a) - a
    if s != 0.0:
        a += s
        af += s
    return w, wf, a, a + wrap_angle_float(af - a), b


def _angle_lowpass(af: float, prev: float, cur: float, c: float) -> float:
    """One step of the low-pass (12) on an angle: its input the mean of the previous and this
    sample (the short way round), the output wrapped."""
    mid = prev + 0.5 * ((cur - prev + _PI) % _TWO_PI - _PI)    # wrap_angle_float written out
    af = af + c * ((mid - af + _PI) % _TWO_PI - _PI)
    return (af + _PI) % _TWO_PI - _PI


def floats3(v) -> tuple[float, float, float] | None:
    """v (a list, tuple or array of 3 numbers, any shape) as three Python floats; None if it
    is not (the attitude level's inputs, here and in camera_level.py and gyro_carrier.py)."""
    t = type(v)
    if (t is list or t is tuple) and len(v) == 3:   # a decoded message's list: no conversion needed
        a, b, c = v
        if type(a) is float and type(b) is float and type(c) is float:
            return a, b, c
    if isinstance(v, np.ndarray):
        if v.shape != (3,):
            v = v.reshape(-1)
            if v.shape != (3,):
                return None
        try:
            a, b, c = v.astype(np.float64, copy=False).tolist()
        except (TypeError, ValueError):
            return None
        return a, b, c
    try:
        if len(v) == 3:
            return float(v[0]), float(v[1]), float(v[2])
    except (TypeError, ValueError, LookupError):
        pass
    try:
        return floats3(np.asarray(v, dtype=np.float64))
    except (TypeError, ValueError):
        return None


_ZERO3 = (0.0, 0.0, 0.0)
_first = operator.itemgetter(0)
# m/s (the a_model integral's size at the oldest kept sample): beyond it the integral is moved to
# start there; a window's mean then carries at most ~1e-16 * 10 m/s / 0.1 s of rounding
_AMODEL_REBASE = 10.0


# ------------------------------------------------------------------ filter
class AttitudeFilter:
    """Attitude level of 000: low-pass (12) + per-axis linear KF (13), (16)-(20) + extrapolator (15).

    inertia_kg_m2: diagonal (Ixx, Iyy, Izz) (a 3x3 matrix is accepted, its diagonal used).

    The three axes' Kalman filters are held as plain floats (x: 5 per axis, P: its upper
    triangle), the structure of F and H written out: at this size that is several times
    cheaper than numpy (or filterpy) calls.  ``x`` and ``P`` give them as arrays.  With the
    filter lag in H, a step's covariance prediction, update and re-wrap are one call per axis
    (_kf_axis); roll and pitch with the same noise settings keep the same covariance, so pitch
    takes roll's gain (_kf_state).  ``update_floats`` returns the estimate as floats (the
    attitude service's path), ``update`` as arrays; the numbers are the same.
    """

    def __init__(self, inertia_kg_m2, params: AttitudeFilterParams | None = None, dt: float = 1.0 / 200.0,
                 gravity_m_s2: float = G_REF):
        inertia = np.asarray(inertia_kg_m2, dtype=np.float64)
        if inertia.shape == (3, 3):
            inertia = np.diag(inertia).copy()
        if inertia.shape != (3,) or not np.all(np.isfinite(inertia)) or np.any(inertia <= 0):
            raise ValueError(f"attitude_filter: inertia must be 3 positive values, got {inertia_kg_m2!r}")
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise ValueError(f"attitude_filter: dt must be positive, got {dt!r}")
        if not (isinstance(gravity_m_s2, (int, float)) and math.isfinite(gravity_m_s2) and gravity_m_s2 > 0):
            raise ValueError(f"attitude_filter: gravity_m_s2 must be positive, got {gravity_m_s2!r}")
        self.inertia = inertia
        self._inertia = tuple(inertia.tolist())
        self.gravity = float(gravity_m_s2)
        self.params = params if params is not None else AttitudeFilterParams()
        self.dt = float(dt)
        p = self.params
        self._disc = _Discretiser(p.lpf_tau_s, p.rate_process_var, p.angle_process_var, p.bias_process_var)
        # the gyro reads the rate plus the bias; the angle measurement the angle (af, or a without the lag)
        self._lag = p.model_filter_lag
        self._angle_meas_idx = AF if p.model_filter_lag else A
        self._r = tuple(zip(p.rate_meas_var, p.angle_meas_var))
        # roll and pitch with the same noise settings: their covariances stay equal (the same start,
        # the same steps and the same measurement flags), so pitch reuses roll's gain
        self._share_rp = all(v[0] == v[1] for v in (p.rate_meas_var, p.angle_meas_var, p.rate_process_var,
                                                      p.angle_process_var, p.bias_process_var))
        self._max_horizon = p.max_delay_steps * self.dt
        self._tau = p.lpf_tau_s
        self.reset()

    # -------------------------------------------------------------- state
    def reset(self) -> None:
        p0 = self._p0(0.0)
        self._xs = [(0.0,) * NX] * 3      # per axis (w, wf, a, af, b)
        self._ps = [p0, p0, self._big_angle_var(p0)]   # per axis, upper triangle of P
        self._t_kf: float | None = None          # time of the KF state (newest processed IMU sample)
        self._bias_started = False    # the bias state has been initialised (kept over re-initialisations)
        self._t_prev_call: float | None = None
        # torques applied, (t0, t1, torque/I) as three lists in time order (t1 sorted, for bisect)
        self._seg_t0: list[float] = []
        self._seg_t1: list[float] = []
        self._seg_u: list[tuple[float, float, float]] = []
        self._wf = [0.0, 0.0, 0.0]    # low-pass states (12)
        self._af = [0.0, 0.0, 0.0]
        self._g_prev = _ZERO3         # previous raw samples (input averaging over the step)
        self._c_h, self._c = None, 0.0   # the last step length and its low-pass factor
        self._a_prev = [0.0, 0.0, 0.0]
        self._yaw_hold: float | None = None   # newest magnetometer yaw, carried by the z gyro
        self._yaw_hold_t: float = 0.0
        self._yaw_seen = False        # the KF yaw has been set from the magnetometer
        self._pending_mag = None      # magnetometer sample seen before the first IMU sample
        self._clear_aid()

    def _clear_aid(self) -> None:
        # a_model = R f + g per processed IMU sample (R the filter's attitude there): times,
        # values and their running trapezoid integral (window means are two look-ups, not a pass)
        self._am_t: list[float] = []
        self._am_v: list[tuple[float, float, float]] = []
        self._am_c: list[tuple[float, float, float]] = []
        self._aid_ref = None          # newest accel_ref (t0, t1, a_mean) given to update()
        self._aid_done = None         # the (t0, t1) that self._aid_c was computed for
        self._aid_c: tuple | None = None   # c = a_ref - mean(a_model) over the reference's window
        self._aid_t1 = -math.inf      # end of that window

    @property
    def x(self) -> np.ndarray:
        """The Kalman states (3, 5): per axis (roll, pitch, yaw) [w, wf, a, af, b] (a copy)."""
        return np.array(self._xs)

    @property
    def P(self) -> np.ndarray:
        """The Kalman covariances (3, 5, 5) (a copy)."""
        return np.array([_tri_to_matrix(p) for p in self._ps])

    def _p0(self, bias_var: float | None) -> tuple:
        """Initial covariance (upper triangle); bias_var None: the configured initial bias variance."""
        p = self.params
        out = [0.0] * len(_TRI)
        for i, v in ((W, p.init_rate_var), (WF, p.init_rate_var), (A, p.init_angle_var), (AF, p.init_angle_var),
                     (B, p.init_bias_var if bias_var is None else bias_var)):
            out[_TRI.index((i, i))] = v
        return tuple(out)

    @staticmethod
    def _big_angle_var(p: tuple) -> tuple:
        """p with the angle variances (a, af) set to the yaw's before any magnetometer sample."""
        out = list(p)
        out[_P_AA] = out[_TRI.index((AF, AF))] = _BIG_ANGLE_VAR
        return tuple(out)

    @property
    def gyro_bias(self) -> np.ndarray:
        """The estimated gyro bias (roll, pitch, yaw axes), rad/s."""
        return np.array([x[B] for x in self._xs])

    @property
    def initialized(self) -> bool:
        return self._t_kf is not None

    @property
    def last_sample_t(self) -> float | None:
        """Time of the newest IMU sample processed (the time the KF state refers to)."""
        return self._t_kf

    # -------------------------------------------------------------- torque history
    def _add_torque(self, torque_nm, t_now: float) -> None:
        u = floats3(torque_nm)
        if u is None or not math.isfinite(u[0] + u[1] + u[2]):
            u = _ZERO3
        i0, i1, i2 = self._inertia
        u = (u[0] / i0, u[1] / i1, u[2] / i2)
        ends = self._seg_t1
        t0 = self._t_prev_call if self._t_prev_call is not None else t_now - self.dt
        if ends:
            t0 = max(t0, ends[-1])
        if t_now > t0:
            self._seg_t0.append(t0)
            ends.append(t_now)
            self._seg_u.append(u)
        # prune: the KF only moves forward; keep a margin for late samples
        n = bisect.bisect_left(ends, self._t_kf - 1.0) if self._t_kf is not None else 0
        n = max(n, len(ends) - 2000)
        if n > 0:
            del self._seg_t0[:n], ends[:n], self._seg_u[:n]

    def _pieces(self, t0: float, t1: float) -> list[tuple[float, tuple]]:
        """[(duration, u)] covering [t0, t1): stored torques, gaps held at the previous one (0 before any)."""
        starts, ends, us = self._seg_t0, self._seg_t1, self._seg_u
        i = bisect.bisect_right(ends, t0)      # the first segment ending after t0
        if i < len(ends) and starts[i] <= t0 and t1 <= ends[i] and t1 - t0 > 1e-9:
            return [(t1 - t0, us[i])]          # within one segment (the loop below gives the same)
        u_last = us[i - 1] if i else _ZERO3
        out = []
        t = t0
        for j in range(i, len(ends)):
            s0 = starts[j]
            if t >= t1 or s0 >= t1:
                break
            u = us[j]
            if s0 > t:
                if s0 - t > 1e-9:
                    out.append((s0 - t, u_last))
                t = s0
            e = min(ends[j], t1)
            if e - t > 1e-9:
                out.append((e - t, u))
            t = e
            u_last = u
        if t1 - t > 1e-9:
            out.append((t1 - t, u_last))
        return out

    def _propagate(self, xs, t0: float, t1: float):
        """The states xs carried over [t0, t1) with the applied torques; returns (xs, step key):
        the covariance is carried once over the summed steps (F and Q of a time-invariant model
        compose: F(h2) F(h1) = F(h1 + h2), F(h2) Q(h1) F(h2)^T + Q(h2) = Q(h1 + h2)).
        _predict_x and _euler_rate_excess written out for the three axes."""
        cache, kinematics = self._disc.cache, self.params.euler_kinematics
        keys = 0
        (w0, wf0, a0, af0, b0), (w1, wf1, a1, af1, b1), (w2, wf2, a2, af2, b2) = xs
        for h, (u0, u1, u2) in self._pieces(t0, t1):
            key = int(round(h * 1e4))          # _step_key
            if key == 0:     # rounded to 0.1 ms: F = I, B = 0, Q = 0
                continue
            hit = cache.get(key)
            h, ee, phi, psi, h2, u_af = (hit if hit is not None else self._disc(key))[0]
            # the Euler rate less the body rate at the piece's start (zero with euler_kinematics off)
            if kinematics:
                sr, cr = math.sin(a0), math.cos(a0)
                cp = math.cos(a1)
                cp = math.copysign(max(abs(cp), _MIN_COS_PITCH), cp)
                tp = math.sin(a1) / cp
                e0, e1, e2 = ((sr * w1 + cr * w2) * tp, (cr - 1.0) * w1 - sr * w2, (sr * w1 + cr * w2) / cp - w2)
            else:
                e0 = e1 = e2 = 0.0
            w0, wf0, a0, af0 = (w0 + h * u0, (phi * w0 + ee * wf0) + psi * u0, (h * w0 + a0) + (h2 * u0 + h * e0),
                                (psi * w0 + phi * a0 + ee * af0) + (u_af * u0 + psi * e0))
            w1, wf1, a1, af1 = (w1 + h * u1, (phi * w1 + ee * wf1) + psi * u1, (h * w1 + a1) + (h2 * u1 + h * e1),
                                (psi * w1 + phi * a1 + ee * af1) + (u_af * u1 + psi * e1))
            w2, wf2, a2, af2 = (w2 + h * u2, (phi * w2 + ee * wf2) + psi * u2, (h * w2 + a2) + (h2 * u2 + h * e2),
                                (psi * w2 + phi * a2 + ee * af2) + (u_af * u2 + psi * e2))
            keys += key
        if not keys:
            return xs, 0
        return [(w0, wf0, a0, af0, b0), (w1, wf1, a1, af1, b1), (w2, wf2, a2, af2, b2)], keys

    # -------------------------------------------------------------- helpers
    def _compute_mag_yaw(self, field, roll: float, pitch: float) -> float | None:
        field = floats3(field)
        if field is None or not math.isfinite(field[0] + field[1] + field[2]):
            return None
        yaw = mag_yaw(field, roll, pitch, self.params.mag_field_world_ut)
        return yaw if math.isfinite(yaw) else None

    def _set_yaw_from_mag(self, yaw: float) -> None:
        w, wf, _, _, b = self._xs[2]
        self._xs[2] = (w, wf, yaw, yaw, b)
        # rows and columns a, af of P restart uncorrelated, at the initial angle variance
        p = self._ps[2]
        v = self.params.init_angle_var
        self._ps[2] = (p[0], p[1], 0.0, 0.0, p[4], p[5], 0.0, 0.0, p[8], v, 0.0, 0.0, v, 0.0, p[14])
        self._af[2] = yaw
        self._a_prev[2] = yaw
        self._yaw_seen = True

    def _accel_angles(self, accel) -> tuple[float, float] | None:
        n = math.sqrt(accel[0] * accel[0] + accel[1] * accel[1] + accel[2] * accel[2])
        if not math.isfinite(n) or n < self.params.min_accel_g * G_REF or n == 0.0:
            return None
        return _roll_pitch(*accel)

    def _initialise(self, t: float, gyro, accel) -> None:
        rp = self._accel_angles(accel)
        roll, pitch = rp if rp is not None else (0.0, 0.0)
        yaw = 0.0
        if self._pending_mag is not None:
            y = self._compute_mag_yaw(self._pending_mag[1], roll, pitch)
            if y is not None:
                yaw = y
                self._yaw_hold = y
                self._yaw_hold_t = t
        angles = (roll, pitch, yaw)
        self._wf = list(gyro)
        self._g_prev = tuple(gyro)
        self._af = list(angles)
        self._a_prev = list(angles)
        for i in range(3):
            # the bias is the sensor's: it survives a re-initialisation (with its variance)
            bias, bias_var = self._xs[i][B], self._ps[i][_P_BB]
            if not self._bias_started:
                bias, bias_var = 0.0, None
            rate = gyro[i] - bias
            self._xs[i] = (rate, rate, angles[i], angles[i], bias)
            self._ps[i] = self._p0(bias_var)
        self._bias_started = True
        self._yaw_seen = self._yaw_hold is not None
        if not self._yaw_seen:
            self._ps[2] = self._big_angle_var(self._ps[2])
        self._drop_aid_history()
        self._t_kf = t

    def _process_mag(self, t_m: float, field) -> None:
        if self._t_kf is None:
            self._pending_mag = (t_m, field)
            return
        yaw = self._compute_mag_yaw(field, self._xs[0][A], self._xs[1][A])
        if yaw is None:
            return
        if not self._yaw_seen:
            self._set_yaw_from_mag(yaw)
        self._yaw_hold = yaw
        self._yaw_hold_t = t_m

    def _process_imu(self, t: float, gyro, accel, tilt=None) -> None:
        if self._t_kf is None:
            self._initialise(t, gyro, accel)
            return
        h = t - self._t_kf
        if not h > 0:
            return    # stale or duplicate sample: the KF only moves forward
        if h > self.params.max_gap_s:
            yaw_keep = self._xs[2][A]
            seen = self._yaw_seen
            self._t_kf = None
            self._initialise(t, gyro, accel)
            if seen and self._yaw_hold is None:
                self._set_yaw_from_mag(yaw_keep)
            return
        # low-pass (12), exact for an input linear over the step (mean of the two samples)
        if h != self._c_h:     # the factor of the last step length, kept (every step is 2.5 ms in lockstep)
            self._c_h, self._c = h, 1.0 - math.exp(-h / self._tau)
        c = self._c
        (wf0, wf1, wf2), (gp0, gp1, gp2), (g0, g1, g2) = self._wf, self._g_prev, gyro
        self._wf = wf = [wf0 + c * (0.5 * (gp0 + g0) - wf0), wf1 + c * (0.5 * (gp1 + g1) - wf1),
                         wf2 + c * (0.5 * (gp2 + g2) - wf2)]
        self._g_prev = gyro
        # Kalman filter prediction over [t_kf, t) with the applied torques (the states here, the
        # covariance with the update below)
        self._xs, key = self._propagate(self._xs, self._t_kf, t)
        aid = self._aid_correction(t) if tilt is None else None
        if aid is not None:
            rp = self._aided_angles(aid)
        else:
            rp = self._accel_angles(accel) if tilt is None else tilt
        af, a_prev = self._af, self._a_prev
        if rp is not None:
            # _angle_lowpass written out, on roll and pitch
            r_roll, r_pitch = rp
            prev, f = a_prev[0], af[0]
            mid = prev + 0.5 * ((r_roll - prev + _PI) % _TWO_PI - _PI)
            f = f + c * ((mid - f + _PI) % _TWO_PI - _PI)
            af[0], a_prev[0] = (f + _PI) % _TWO_PI - _PI, r_roll
            prev, f = a_prev[1], af[1]
            mid = prev + 0.5 * ((r_pitch - prev + _PI) % _TWO_PI - _PI)
            f = f + c * ((mid - f + _PI) % _TWO_PI - _PI)
            af[1], a_prev[1] = (f + _PI) % _TWO_PI - _PI, r_pitch
        yaw_ok = False
        if self._yaw_hold is not None:
            # carry the held magnetometer yaw on with the z gyro up to this sample
            dt_hold = t - max(self._yaw_hold_t, t - h)
            if dt_hold > 0:
                self._yaw_hold = wrap_angle_float(self._yaw_hold + gyro[2] * dt_hold)
                self._yaw_hold_t = t
            af[2], a_prev[2] = _angle_lowpass(af[2], a_prev[2], self._yaw_hold, c), self._yaw_hold
            yaw_ok = self._yaw_seen
        # Kalman filter: the covariance's prediction, then the update with [wf, af] (the angle
        # innovation wrapped)
        m, lag = self._angle_meas_idx, self._lag
        if key and lag:   # the filter's own case, the three axes written out (_kf_axis)
            hit = self._disc.cache.get(key)
            coef, (q0, q1, q2) = hit if hit is not None else self._disc(key)
            (x0, x1, x2), (p0, p1, p2), (r0, r1, r2) = self._xs, self._ps, self._r
            z0 = z1 = z2 = None
            if rp is not None:
                pred0, pred1 = x0[AF], x1[AF]
                z0, z1 = (pred0 + ((af[0] - pred0 + _PI) % _TWO_PI - _PI),
                          pred1 + ((af[1] - pred1 + _PI) % _TWO_PI - _PI))
            if yaw_ok:
                pred2 = x2[AF]
                z2 = pred2 + ((af[2] - pred2 + _PI) % _TWO_PI - _PI)
            x0, p0, gain = _kf_axis(x0, p0, coef, q0, wf[0], z0, *r0)
            if self._share_rp and (p1 is self._ps[0] or p1 == self._ps[0]):
                # roll's and pitch's P, Q and R are the same (equal noise settings): so is the gain
                x1, p1 = _kf_state(x1, gain, wf[1], z1), p0
            else:
                x1, p1, _ = _kf_axis(x1, p1, coef, q1, wf[1], z1, *r1)
            x2, p2, _ = _kf_axis(x2, p2, coef, q2, wf[2], z2, *r2)
            self._xs, self._ps = [x0, x1, x2], [p0, p1, p2]
        else:
            coef, qs = self._disc(key) if key else (None, (None, None, None))
            xs, ps = [], []
            for x, pp, q, angle_ok, z_rate, af_i, (r_rate, r_angle) in zip(
                    self._xs, self._ps, qs, (rp is not None, rp is not None, yaw_ok), wf, af, self._r):
                if key:
                    pp = _predict_p(pp, coef, q)
                z_angle = None
                if angle_ok:
                    pred = x[m]
                    z_angle = pred + wrap_angle_float(af_i - pred)
                x, pp = _update(x, pp, z_rate, z_angle, r_rate, r_angle, lag)
                xs.append(_rewrap(x))
                ps.append(pp)
            self._xs, self._ps = xs, ps
        self._t_kf = t
        self._record_amodel(t, accel)

    # -------------------------------------------------------------- acceleration reference
    def _drop_aid_history(self) -> None:
        """Forget the a_model history and the correction (the attitude they were made with is gone)."""
        self._am_t, self._am_v, self._am_c = [], [], []
        self._aid_c = None
        self._aid_done = None
        self._aid_t1 = -math.inf

    def _record_amodel(self, t: float, accel) -> None:
        """a_model(t) = R f + g: the acceleration that the specific force f implies at the filter's attitude."""
        (_, _, roll, _, _), (_, _, pitch, _, _), (_, _, yaw, _, _) = self._xs
        # _rotation_rows written out
        cr, sr = math.cos(roll), math.sin(roll)
        cp, sp = math.cos(pitch), math.sin(pitch)
        cy, sy = math.cos(yaw), math.sin(yaw)
        f0, f1, f2 = accel
        v = (cy * cp * f0 + (cy * sp * sr - sy * cr) * f1 + (cy * sp * cr + sy * sr) * f2,
             sy * cp * f0 + (sy * sp * sr + cy * cr) * f1 + (sy * sp * cr - cy * sr) * f2,
             -sp * f0 + cp * sr * f1 + cp * cr * f2 - self.gravity)
        ts, vs, cs = self._am_t, self._am_v, self._am_c
        if ts:
            dt, (v0, v1, v2), (c0, c1, c2) = t - ts[-1], vs[-1], cs[-1]
            cs.append((c0 + 0.5 * (v0 + v[0]) * dt, c1 + 0.5 * (v1 + v[1]) * dt, c2 + 0.5 * (v2 + v[2]) * dt))
        else:
            cs.append(_ZERO3)
        ts.append(t)
        vs.append(v)
        n = bisect.bisect_left(ts, t - 1.0)      # keep one second
        if n:
            del ts[:n], vs[:n], cs[:n]
            if abs(cs[0][0]) + abs(cs[0][1]) + abs(cs[0][2]) > _AMODEL_REBASE:
                # the integral grows over a flight and a window's mean is a difference of two of
                # its values: move its origin up to the oldest kept sample
                b0, b1, b2 = cs[0]
                self._am_c = [(c0 - b0, c1 - b1, c2 - b2) for c0, c1, c2 in cs]

    def _amodel_integral(self, t: float) -> tuple[float, float, float]:
        """Integral of a_model (linear between samples, held beyond the ends) up to t, from the origin of _am_c."""
        ts, vs, cs = self._am_t, self._am_v, self._am_c
        j = bisect.bisect_right(ts, t)
        if j == 0 or j == len(ts):        # before the first / after the last sample: held
            k = 0 if j == 0 else j - 1
            (v0, v1, v2), (c0, c1, c2), dt = vs[k], cs[k], t - ts[k]
            return c0 + v0 * dt, c1 + v1 * dt, c2 + v2 * dt
        ta, tb = ts[j - 1], ts[j]
        (a0, a1, a2), (b0, b1, b2), (c0, c1, c2) = vs[j - 1], vs[j], cs[j - 1]
        f = (t - ta) / (tb - ta)
        dt = 0.5 * (t - ta)
        return (c0 + (a0 + (a0 + f * (b0 - a0))) * dt, c1 + (a1 + (a1 + f * (b1 - a1))) * dt,
                c2 + (a2 + (a2 + f * (b2 - a2))) * dt)

    def _amodel_mean(self, t0: float, t1: float) -> tuple[float, float, float] | None:
        """Mean of a_model over [t0, t1] (trapezoid, ends interpolated); None unless the history covers it."""
        ts = self._am_t
        if not ts or not t1 > t0:
            return None
        eps = 1e-6
        if ts[0] > t0 + eps or ts[-1] < t1 - eps:
            return None
        i0, i1 = self._amodel_integral(t0), self._amodel_integral(t1)
        d = t1 - t0
        mean = ((i1[0] - i0[0]) / d, (i1[1] - i0[1]) / d, (i1[2] - i0[2]) / d)
        return mean if math.isfinite(mean[0] + mean[1] + mean[2]) else None

    def _aid_correction(self, t: float) -> tuple[float, float, float] | None:
        """c = a_ref - mean(a_model) over the reference's window (bounded), or None (no usable reference)."""
        ref = self._aid_ref
        if ref is None:
            return None
        t0, t1, a_ref = ref
        if self._aid_done != (t0, t1):
            mean = self._amodel_mean(t0, t1)
            if mean is not None:
                corr = (a_ref[0] - mean[0], a_ref[1] - mean[1], a_ref[2] - mean[2])
                n = math.sqrt(corr[0] * corr[0] + corr[1] * corr[1] + corr[2] * corr[2])
                cap = self.params.aid_max_correction_m_s2
                if n > cap:
                    s = cap / n
                    corr = (corr[0] * s, corr[1] * s, corr[2] * s)
                self._aid_c = corr
                self._aid_done = (t0, t1)
                self._aid_t1 = t1
        if self._aid_c is None or t - self._aid_t1 > self.params.aid_max_age_s:
            return None
        return self._aid_c

    def _aided_angles(self, corr) -> tuple[float, float]:
        """(roll, pitch) of the accelerometer compensated with a = R f + g + c at the predicted attitude R:
        f - R^T a = R^T ([0, 0, g] - c), i.e. the predicted attitude moved by the correction c."""
        (_, _, roll, _, _), (_, _, pitch, _, _), (_, _, yaw, _, _) = self._xs
        # _rotation_rows and _roll_pitch written out
        cr, sr = math.cos(roll), math.sin(roll)
        cp, sp = math.cos(pitch), math.sin(pitch)
        cy, sy = math.cos(yaw), math.sin(yaw)
        v0, v1, v2 = 0.0 - corr[0], 0.0 - corr[1], self.gravity - corr[2]
        ax = cy * cp * v0 + sy * cp * v1 + -sp * v2
        ay = (cy * sp * sr - sy * cr) * v0 + (sy * sp * sr + cy * cr) * v1 + cp * sr * v2
        az = (cy * sp * cr + sy * sr) * v0 + (sy * sp * cr - cy * sr) * v1 + cp * cr * v2
        return math.atan2(ay, az), math.atan2(-ax, math.hypot(ay, az))

    def sample_state(self) -> tuple[np.ndarray, np.ndarray]:
        """(euler, rate) of the KF at its newest IMU sample (not extrapolated)."""
        xs = self._xs
        return (np.array([wrap_angle_float(xs[0][A]), wrap_angle_float(xs[1][A]), wrap_angle_float(xs[2][A])]),
                np.array([xs[0][W], xs[1][W], xs[2][W]]))

    def reinitialise(self, euler, rate) -> None:
        """Restart the angle and rate states (and the low-passes) at a known attitude, keeping P
        and the gyro bias.

        rate: the gyro's reading there (the rate states take it less the bias estimate).
        Used after a manoeuvre the filter cannot follow (a flip: see GyroCarrier); the
        accelerometer and magnetometer low-passes restart there too, so they pull from it."""
        if self._t_kf is None:
            return
        euler = tuple(wrap_angle_float(v) for v in floats3(euler))
        rate = floats3(rate)
        for i, x in enumerate(self._xs):
            w = rate[i] - x[B]
            self._xs[i] = (w, w, euler[i], euler[i], x[B])
        self._wf, self._g_prev = list(rate), rate
        self._af, self._a_prev = list(euler), list(euler)
        if self._yaw_hold is not None:
            self._yaw_hold = euler[2]
        self._drop_aid_history()

    def _healthy(self) -> bool:
        # one finiteness test: a NaN or inf anywhere makes the sum non-finite (the sums of
        # sum(map(sum, xs)) + sum(map(sum, ps)) in its order; pitch's P often is roll's object)
        (x0, x1, x2), (p0, p1, p2) = self._xs, self._ps
        sp0 = sum(p0)
        return math.isfinite(sum(x0) + sum(x1) + sum(x2) + (sp0 + (sp0 if p1 is p0 else sum(p1)) + sum(p2)))

    # -------------------------------------------------------------- main entry
    def update(self, imu_samples, mag, torque_nm, t_now: float, accel_ref=None) -> AttitudeEstimate:
        """One attitude-level step.

        imu_samples: list of (t_s, gyro (3,) rad/s, accel (3,) m/s^2) since the last call (any order),
        or (t_s, gyro, accel, (roll, pitch)) where another estimator (the gyro-vertical of 004)
        gives the angle measurement in place of the accelerometer angles;
        mag: (t_s, field_ut (3,)) or None; torque_nm: the torque applied since the last call
        (the one commanded at the previous call); t_now: the current time, s;
        accel_ref: None, or (t0, t1, a) with a (3,) the vehicle's mean acceleration (world ENU, m/s^2)
        over [t0, t1] from another source (the position level's velocity slope): the roll/pitch
        measurement then comes from the acceleration reference (class docstring), not the raw
        accelerometer angles.
        Vectors may be lists, tuples or arrays.
        Returns the estimate at t_now (extrapolated over the delay when ``extrapolate``).
        """
        euler, rate, q, var_a, var_w, delay = self.update_floats(imu_samples, mag, torque_nm, t_now, accel_ref)
        return AttitudeEstimate(np.array(euler), np.array(rate), np.array(q), np.array(var_a), np.array(var_w),
                                delay)

    def update_floats(self, imu_samples, mag, torque_nm, t_now: float, accel_ref=None) -> tuple:
        """update() with the estimate as floats: (euler [3], rate [3], quaternion (4), euler_var [3],
        rate_var [3], delay_s), the fields of AttitudeEstimate (the attitude service's 200 Hz path)."""
        t_now = float(t_now)
        self._aid_ref = None
        if accel_ref is not None:
            try:
                t0, t1, a_ref = float(accel_ref[0]), float(accel_ref[1]), floats3(accel_ref[2])
            except (TypeError, ValueError, IndexError):
                t0 = t1 = math.nan
                a_ref = None
            if math.isfinite(t0) and math.isfinite(t1) and t1 > t0 and a_ref is not None \
                    and math.isfinite(a_ref[0] + a_ref[1] + a_ref[2]):
                self._aid_ref = (t0, t1, a_ref)
        self._add_torque(torque_nm, t_now)
        self._t_prev_call = t_now
        samples = []
        isfinite = math.isfinite
        for s in imu_samples or ():
            t, g, a = s[0], floats3(s[1]), floats3(s[2])
            tilt = s[3] if len(s) > 3 else None
            t = float(t)
            if tilt is not None:
                tilt = (float(tilt[0]), float(tilt[1]))
                if not isfinite(tilt[0] + tilt[1]):
                    tilt = None
            if g is not None and a is not None and isfinite(t + g[0] + g[1] + g[2] + a[0] + a[1] + a[2]):
                samples.append((t, g, a, tilt))
        if len(samples) > 1:
            samples.sort(key=_first)
        mag_item = None
        if mag is not None:
            t_m, field = mag
            if t_m is not None and math.isfinite(float(t_m)):
                mag_item = (float(t_m), field)
        for t, g, a, tilt in samples:
            if mag_item is not None and mag_item[0] <= t:
                self._process_mag(*mag_item)
                mag_item = None
            self._process_imu(t, g, a, tilt)
        if mag_item is not None:
            self._process_mag(*mag_item)
        if not self._healthy():
            # numerical trouble (should not happen): start over rather than return NaN
            self.reset()
        return self._estimate(t_now)

    def _estimate(self, t_now: float) -> tuple:
        """The estimate at t_now as update_floats returns it."""
        p = self.params
        ps = self._ps
        var_a = [ps[0][_P_AA], ps[1][_P_AA], ps[2][_P_AA]]
        var_w = [ps[0][_P_WW], ps[1][_P_WW], ps[2][_P_WW]]
        if self._t_kf is None:
            return [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], (1.0, 0.0, 0.0, 0.0), var_a, var_w, 0.0
        delay = max(0.0, t_now - self._t_kf)
        xs = self._xs
        if p.extrapolate and delay > 0.0:
            horizon = min(delay, self._max_horizon)
            xs, key = self._propagate(xs, self._t_kf, self._t_kf + horizon)
            if key:
                # only the angle and rate variances are published: rows w and a of F P F^T + Q
                (h, _, _, _, _, _), qs = self._disc(key)
                for i, (pp, q) in enumerate(zip(ps, qs)):
                    p00, p02, p22 = pp[0], pp[2], pp[9]
                    var_w[i] = p00 + q[0]
                    var_a[i] = h * (h * p00 + p02) + (h * p02 + p22) + q[9]
        (w0, _, a0, _, _), (w1, _, a1, _, _), (w2, _, a2, _, _) = xs
        euler = [(a0 + _PI) % _TWO_PI - _PI, (a1 + _PI) % _TWO_PI - _PI, (a2 + _PI) % _TWO_PI - _PI]
        rate = [w0, w1, w2]
        if not math.isfinite(sum(euler) + sum(rate)):
            euler, rate = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
        return euler, rate, quat_from_euler_floats(*euler), var_a, var_w, float(delay)

    def sample_state_floats(self) -> tuple[list, list]:
        """sample_state() as lists of floats."""
        (w0, _, a0, _, _), (w1, _, a1, _, _), (w2, _, a2, _, _) = self._xs
        return [(a0 + _PI) % _TWO_PI - _PI, (a1 + _PI) % _TWO_PI - _PI, (a2 + _PI) % _TWO_PI - _PI], [w0, w1, w2]


# The per-axis filter of 000 as printed (an ablation): no gyro-bias state, the body rate taken
# as the Euler rate, the angle random walk 000 needs to absorb both; with the attitude
# service's acceleration_compensation = "slope" it is 000's attitude level (its figures:
# docs/results.md).
FILTER_000 = {"angle_process_var": (1e-5, 1e-5, 1e-5), "euler_kinematics": False,
              "init_bias_var": 0.0, "bias_process_var": (1e-12, 1e-12, 1e-12)}
