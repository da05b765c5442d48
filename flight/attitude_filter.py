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
exponentials for a step h.  ``kf.F``/``kf.B`` hold the ones for the nominal
``dt``; the filter itself steps at every IMU sample (400 Hz, two per 200 Hz
call) with the exact F, B, Q of the actual interval, split wherever the
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

import dataclasses
import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import KalmanFilter
from scipy.linalg import expm

from flight.quat import quat_from_euler, quat_multiply, quat_to_euler

W, WF, A, AF, B = 0, 1, 2, 3, 4    # state indices per axis (B: the gyro bias)
NX = 5
G_REF = 9.80665
_BIG_ANGLE_VAR = math.pi ** 2      # yaw variance before any magnetometer sample


def wrap(a):
    """Wrap to [-pi, pi) (scalar or array)."""
    return (np.asarray(a, dtype=np.float64) + np.pi) % (2 * np.pi) - np.pi


def _wrap1(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def rotation_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Body -> world rotation R = Rz(yaw) Ry(pitch) Rx(roll) (ZYX, as quat_from_euler)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def accel_roll_pitch(accel) -> tuple[float, float]:
    """(roll, pitch) from specific force in body FLU (exact for the ZYX convention at rest)."""
    ax, ay, az = (float(v) for v in accel)
    return math.atan2(ay, az), math.atan2(-ax, math.hypot(ay, az))


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
    return _wrap1(beta - math.atan2(hy, hx))


# ------------------------------------------------------------------ parameters
def _vec3(name, v):
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        v = (v, v, v)
    try:
        t = tuple(float(e) for e in v)
    except TypeError:
        raise ValueError(f"attitude_filter: {name} must be a number or 3 numbers, got {v!r}") from None
    if len(t) != 3:
        raise ValueError(f"attitude_filter: {name} must have 3 values, got {v!r}")
    return t


_VEC_FIELDS = ("rate_meas_var", "angle_meas_var", "rate_process_var", "angle_process_var", "bias_process_var")


@dataclass(frozen=True)
class AttitudeFilterParams:
    """Parameters of :class:`AttitudeFilter`.  Per-axis tuples are (roll, pitch, yaw).

    Variances of the measurements are per IMU sample (400 Hz); the process
    noises are continuous densities (discretised exactly for each step).
    """
    # (12): first-order low-pass on the gyro and on the accel/mag angles, k_f = 1/tau
    lpf_tau_s: float = 0.02
    # R: low-passed gyro rate, rad^2/s^2.  The raw gyro noise is 1e-5 per sample;
    # after the low-pass it is ~6e-7 but coloured (correlated over ~tau), so the
    # raw per-sample value is kept as a conservative white-noise equivalent.
    rate_meas_var: tuple = (1e-5, 1e-5, 1e-5)
    # R: low-passed accelerometer / magnetometer angle, rad^2.  The sensor noise
    # alone is ~1e-6 (accel) and ~6e-4 (mag, 0.5 uT over a 20 uT horizontal field);
    # roll/pitch use a larger value so the gyro carries the short term (the
    # accelerometer pulls with a ~0.5 s time constant). In flight a multirotor's
    # accelerometer reads "level" whenever it tilts to accelerate: the attitude
    # service subtracts the position level's acceleration estimate first (without
    # that, 1e-3 left the hover estimate 5 deg off; 5e-2 only slowed the drift).
    # Yaw: the 50 Hz magnetometer is held over 8 IMU samples, so its per-sample
    # variance is ~8x the sensor's 6e-4.
    angle_meas_var: tuple = (1e-3, 1e-3, 5e-3)
    # Q: density of the unmodelled angular acceleration (torque error, motor lag,
    # disturbances), rad^2/s^3
    rate_process_var: tuple = (50.0, 50.0, 20.0)
    # Q: density of a random walk on the angle (what the model leaves out: scale errors,
    # vibration), rad^2/s; sets how fast the angle measurement pulls the gyro-integrated
    # angle.  1e-5 (~0.5 s) in 000, which also had to absorb the gyro bias and the
    # body-vs-Euler rate; both are modelled here (bias state, euler_kinematics), so roll
    # and pitch trust the gyro longer and average the acceleration reference's noise
    # (~0.3 m/s^2, i.e. ~1.7 deg) over ~1 s.  Yaw (magnetometer) keeps 1e-5.
    angle_process_var: tuple = (3e-6, 3e-6, 1e-5)
    # Q: density of the gyro bias random walk, rad^2/s^3 (the simulator's walk is 1e-10;
    # a MEMS gyro's bias also moves with temperature, hence the margin)
    bias_process_var: tuple = (1e-9, 1e-9, 1e-9)
    model_filter_lag: bool = True    # False: ablation "cascade without the filter lag in the model"
    # True: the angles integrate the ZYX Euler rates of the estimated body rates (the other
    # axes' estimates enter as a known input); False: 000 as printed, the body rate taken as the
    # Euler rate (off by 12 % of the pitch rate in roll at 20 deg of roll and pitch)
    euler_kinematics: bool = True
    extrapolate: bool = True         # False: ablation without the extrapolator (15)
    max_delay_steps: int = 10        # extrapolate at most this many dt (longer delays are capped)
    mag_field_world_ut: tuple = (0.0, 20.0, -45.0)  # ENU, only its horizontal direction is used
    init_angle_var: float = 1e-2     # rad^2 at initialisation (roll/pitch; yaw once the mag is seen)
    init_rate_var: float = 1e-2      # rad^2/s^2
    # gyro bias variance at start, rad^2/s^2 (a MEMS gyro's turn-on bias, ~0.2 deg/s);
    # 0 with bias_process_var ~0 is the ablation "no bias state" (the bias stays 0)
    init_bias_var: float = 1e-5
    min_accel_g: float = 0.3         # |specific force| below this: no accel angle update (free fall)
    max_gap_s: float = 0.5           # IMU silent for longer: re-initialise from the next sample
    # Acceleration reference (``update(..., accel_ref=...)``, see AttitudeFilter): the
    # correction c = a_ref - mean(R f + g) is bounded to this magnitude (an attitude error
    # of ~18 deg in hover; the position level's acceleration noise is ~0.3 m/s^2), so a
    # wrong reference or a stale history (after a flip) can only pull at a bounded rate ...
    aid_max_correction_m_s2: float = 3.0
    # ... and a reference whose window ended longer ago than this is not used (the raw
    # accelerometer angles of 000 are, as without a reference)
    aid_max_age_s: float = 0.25

    def __post_init__(self):
        for name in _VEC_FIELDS:
            t = _vec3(name, getattr(self, name))
            if not all(math.isfinite(e) and e > 0 for e in t):
                raise ValueError(f"attitude_filter: {name} must be positive finite, got {t}")
            object.__setattr__(self, name, t)
        fw = _vec3("mag_field_world_ut", self.mag_field_world_ut)
        if not all(math.isfinite(e) for e in fw) or math.hypot(fw[0], fw[1]) <= 0:
            raise ValueError(f"attitude_filter: mag_field_world_ut needs a horizontal component, got {fw}")
        object.__setattr__(self, "mag_field_world_ut", fw)
        for name in ("lpf_tau_s", "init_angle_var", "init_rate_var", "max_gap_s", "aid_max_correction_m_s2",
                     "aid_max_age_s"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ValueError(f"attitude_filter: {name} must be a positive number, got {v!r}")
            object.__setattr__(self, name, float(v))
        for name in ("min_accel_g", "init_bias_var"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"attitude_filter: {name} must be >= 0, got {v!r}")
            object.__setattr__(self, name, float(v))
        for name in ("model_filter_lag", "extrapolate", "euler_kinematics"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"attitude_filter: {name} must be true or false, got {getattr(self, name)!r}")
        m = self.max_delay_steps
        if isinstance(m, bool) or not isinstance(m, int) or m < 0:
            if isinstance(m, float) and m.is_integer() and m >= 0:
                object.__setattr__(self, "max_delay_steps", int(m))
            else:
                raise ValueError(f"attitude_filter: max_delay_steps must be an integer >= 0, got {m!r}")

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def from_dict(cls, d: dict | None) -> "AttitudeFilterParams":
        """Missing keys take defaults; unknown keys -> ValueError."""
        if d is None:
            return cls()
        if not isinstance(d, dict):
            raise ValueError(f"attitude_filter: expected a table, got {type(d).__name__}")
        unknown = set(d) - set(cls.names())
        if unknown:
            raise ValueError(f"attitude_filter: unknown parameter(s) {sorted(unknown)}")
        return cls(**d)

    def to_dict(self) -> dict:
        out = {}
        for k in self.names():
            v = getattr(self, k)
            out[k] = list(v) if isinstance(v, tuple) else v
        return out


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


def euler_rate_excess(roll: float, pitch: float, rate) -> np.ndarray:
    """ZYX Euler rates less the body rates: W(roll, pitch) w - w (0 when level).

    roll' = p + sin(roll) tan(pitch) q + cos(roll) tan(pitch) r; pitch' = cos(roll) q - sin(roll) r;
    yaw' = (sin(roll) q + cos(roll) r) / cos(pitch).  |cos(pitch)| is floored at 0.2."""
    p, q, r = (float(v) for v in rate)
    sr, cr = math.sin(roll), math.cos(roll)
    cp = math.cos(pitch)
    cp = math.copysign(max(abs(cp), _MIN_COS_PITCH), cp)
    tp = math.sin(pitch) / cp
    return np.array([(sr * q + cr * r) * tp,
                     (cr - 1.0) * q - sr * r,
                     (sr * q + cr * r) / cp - r])


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


class _Discretiser:
    """Exact F, B and unit process-noise matrices for a step h, cached.

    Steps are rounded to 0.1 ms: in real time every interval differs, and three
    matrix exponentials per miss cost more than the 200 Hz loop can afford
    (measured: the attitude service fell to 36 Hz); 0.1 ms is far below the
    model's time constants (tau = 20 ms)."""

    def __init__(self, lpf_tau_s: float):
        self.a, self.b = continuous_model(lpf_tau_s)
        self.cache: dict[int, tuple] = {}

    def __call__(self, h: float):
        key = int(round(h * 1e4))
        hit = self.cache.get(key)
        if hit is not None:
            return hit
        if len(self.cache) > 4096:
            self.cache.clear()
        h = key * 1e-4
        n = NX
        nu = self.b.shape[1]
        m = np.zeros((n + nu, n + nu))
        m[:n, :n] = self.a
        m[:n, n:] = self.b
        e = expm(m * h)
        f, bd = e[:n, :n], e[:n, n:n + nu]
        qs = []
        for idx in (W, A, B):   # unit densities on w', a' and b'
            lc = np.zeros((n, n))
            lc[idx, idx] = 1.0
            vl = np.zeros((2 * n, 2 * n))
            vl[:n, :n] = -self.a
            vl[:n, n:] = lc
            vl[n:, n:] = self.a.T
            ev = expm(vl * h)
            qd = ev[n:, n:].T @ ev[:n, n:]
            qs.append(0.5 * (qd + qd.T))
        hit = (f, bd, qs[0], qs[1], qs[2])
        self.cache[key] = hit
        return hit


# ------------------------------------------------------------------ filter
class AttitudeFilter:
    """Attitude level of 000: low-pass (12) + per-axis linear KF (13), (16)-(20) + extrapolator (15).

    inertia_kg_m2: diagonal (Ixx, Iyy, Izz) (a 3x3 matrix is accepted, its diagonal used).
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
        self.gravity = float(gravity_m_s2)
        self.params = params if params is not None else AttitudeFilterParams()
        self.dt = float(dt)
        self._disc = _Discretiser(self.params.lpf_tau_s)
        p = self.params
        # the gyro reads the rate plus the bias; the angle measurement the angle
        if p.model_filter_lag:
            self._h = np.array([[0.0, 1.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0, 0.0]])
        else:
            self._h = np.array([[1.0, 0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 1.0, 0.0, 0.0]])
        self._h_rate_only = self._h.copy()
        self._h_rate_only[1, :] = 0.0
        self._angle_meas_idx = AF if p.model_filter_lag else A
        self._r = [np.diag([p.rate_meas_var[i], p.angle_meas_var[i]]) for i in range(3)]
        self.reset()

    # -------------------------------------------------------------- state
    def reset(self) -> None:
        f, bd, qw, qa, qb = self._disc(self.dt)
        self.kfs = []
        for i in range(3):
            kf = KalmanFilter(dim_x=NX, dim_z=2, dim_u=2)
            kf.F = f.copy()
            kf.B = bd.copy()
            kf.Q = self._q(i, qw, qa, qb)
            kf.H = self._h.copy()
            kf.R = self._r[i].copy()
            kf.x = np.zeros((NX, 1))
            kf.P = self._p0(0.0)
            self.kfs.append(kf)
        self.kfs[2].P[A, A] = self.kfs[2].P[AF, AF] = _BIG_ANGLE_VAR
        self._t_kf: float | None = None          # time of the KF state (newest processed IMU sample)
        self._bias_started = False    # the bias state has been initialised (kept over re-initialisations)
        self._t_prev_call: float | None = None
        self._segs: list[tuple[float, float, np.ndarray]] = []   # (t0, t1, torque/I) applied
        self._wf = np.zeros(3)        # low-pass states (12)
        self._af = np.zeros(3)
        self._g_prev = np.zeros(3)    # previous raw samples (input averaging over the step)
        self._a_prev = np.zeros(3)
        self._yaw_hold: float | None = None   # newest magnetometer yaw, carried by the z gyro
        self._yaw_hold_t: float = 0.0
        self._yaw_seen = False        # the KF yaw has been set from the magnetometer
        self._pending_mag = None      # magnetometer sample seen before the first IMU sample
        self._clear_aid()

    def _clear_aid(self) -> None:
        # (t, a_model = R f + g) per processed IMU sample, R the filter's attitude there
        self._amodel: deque = deque()
        self._aid_ref = None          # newest accel_ref (t0, t1, a_mean) given to update()
        self._aid_done = None         # the (t0, t1) that self._aid_c was computed for
        self._aid_c: np.ndarray | None = None   # c = a_ref - mean(a_model) over the reference's window
        self._aid_t1 = -math.inf      # end of that window

    def _excess(self, xs) -> np.ndarray:
        """The Euler rate less the body rate at the states xs (zero with euler_kinematics off)."""
        if not self.params.euler_kinematics:
            return np.zeros(3)
        return euler_rate_excess(float(xs[0][A, 0]), float(xs[1][A, 0]),
                                 np.array([float(x[W, 0]) for x in xs]))

    def _q(self, i: int, qw, qa, qb) -> np.ndarray:
        p = self.params
        return p.rate_process_var[i] * qw + p.angle_process_var[i] * qa + p.bias_process_var[i] * qb

    def _p0(self, bias_var: float | None) -> np.ndarray:
        """Initial covariance; bias_var None: the configured initial bias variance."""
        p = self.params
        return np.diag([p.init_rate_var, p.init_rate_var, p.init_angle_var, p.init_angle_var,
                        p.init_bias_var if bias_var is None else bias_var])

    @property
    def gyro_bias(self) -> np.ndarray:
        """The estimated gyro bias (roll, pitch, yaw axes), rad/s."""
        return np.array([float(kf.x[B, 0]) for kf in self.kfs])

    @property
    def initialized(self) -> bool:
        return self._t_kf is not None

    @property
    def last_sample_t(self) -> float | None:
        """Time of the newest IMU sample processed (the time the KF state refers to)."""
        return self._t_kf

    # -------------------------------------------------------------- torque history
    def _add_torque(self, torque_nm, t_now: float) -> None:
        u = np.asarray(torque_nm, dtype=np.float64).reshape(-1)
        if u.shape != (3,) or not np.all(np.isfinite(u)):
            u = np.zeros(3)
        u = u / self.inertia
        t0 = self._t_prev_call if self._t_prev_call is not None else t_now - self.dt
        if self._segs:
            t0 = max(t0, self._segs[-1][1])
        if t_now > t0:
            self._segs.append((t0, t_now, u))
        # prune: the KF only moves forward; keep a margin for late samples
        if self._t_kf is not None:
            keep_from = self._t_kf - 1.0
            while self._segs and self._segs[0][1] < keep_from:
                self._segs.pop(0)
        if len(self._segs) > 2000:
            del self._segs[: len(self._segs) - 2000]

    def _pieces(self, t0: float, t1: float) -> list[tuple[float, np.ndarray]]:
        """[(duration, u)] covering [t0, t1): stored torques, gaps held at the previous one (0 before any)."""
        out = []
        t = t0
        u_last = np.zeros(3)
        for s0, s1, u in self._segs:
            if t >= t1:
                break
            if s1 <= t:
                u_last = u
                continue
            if s0 >= t1:
                break
            if s0 > t:
                out.append((s0 - t, u_last))
                t = s0
            e = min(s1, t1)
            out.append((e - t, u))
            t = e
            u_last = u
        if t < t1:
            out.append((t1 - t, u_last))
        return [(h, u) for h, u in out if h > 1e-9]

    # -------------------------------------------------------------- helpers
    @staticmethod
    def _rewrap(x: np.ndarray) -> None:
        """Wrap the angle state to [-pi, pi) and move af by the same turn (keeps af - a small)."""
        a = float(x[A, 0])
        s = _wrap1(a) - a
        if s != 0.0:
            x[A, 0] += s
            x[AF, 0] += s
        x[AF, 0] = x[A, 0] + _wrap1(float(x[AF, 0] - x[A, 0]))

    def _predict(self, t0: float, t1: float) -> None:
        for h, u in self._pieces(t0, t1):
            f, bd, qw, qa, qb = self._disc(h)
            e = self._excess([kf.x for kf in self.kfs])
            for i, kf in enumerate(self.kfs):
                kf.predict(u=np.array([[u[i]], [e[i]]]), B=bd, F=f, Q=self._q(i, qw, qa, qb))

    def _compute_mag_yaw(self, field, roll: float, pitch: float) -> float | None:
        field = np.asarray(field, dtype=np.float64).reshape(-1)
        if field.shape != (3,) or not np.all(np.isfinite(field)):
            return None
        yaw = mag_yaw(field, roll, pitch, self.params.mag_field_world_ut)
        return yaw if math.isfinite(yaw) else None

    def _set_yaw_from_mag(self, yaw: float) -> None:
        kf = self.kfs[2]
        kf.x[A, 0] = kf.x[AF, 0] = yaw
        kf.P[A, :] = 0.0
        kf.P[:, A] = 0.0
        kf.P[AF, :] = 0.0
        kf.P[:, AF] = 0.0
        kf.P[A, A] = kf.P[AF, AF] = self.params.init_angle_var
        self._af[2] = yaw
        self._a_prev[2] = yaw
        self._yaw_seen = True

    def _accel_angles(self, accel) -> tuple[float, float] | None:
        n = float(np.linalg.norm(accel))
        if not math.isfinite(n) or n < self.params.min_accel_g * G_REF or n == 0.0:
            return None
        return accel_roll_pitch(accel)

    def _initialise(self, t: float, gyro: np.ndarray, accel: np.ndarray) -> None:
        rp = self._accel_angles(accel)
        roll, pitch = rp if rp is not None else (0.0, 0.0)
        yaw = 0.0
        if self._pending_mag is not None:
            y = self._compute_mag_yaw(self._pending_mag[1], roll, pitch)
            if y is not None:
                yaw = y
                self._yaw_hold = y
                self._yaw_hold_t = t
        angles = np.array([roll, pitch, yaw])
        self._wf = gyro.copy()
        self._g_prev = gyro.copy()
        self._af = angles.copy()
        self._a_prev = angles.copy()
        for i, kf in enumerate(self.kfs):
            # the bias is the sensor's: it survives a re-initialisation (with its variance)
            bias, bias_var = float(kf.x[B, 0]), float(kf.P[B, B])
            if not self._bias_started:
                bias, bias_var = 0.0, None
            rate = gyro[i] - bias
            kf.x = np.array([[rate], [rate], [angles[i]], [angles[i]], [bias]])
            kf.P = self._p0(bias_var)
        self._bias_started = True
        self._yaw_seen = self._yaw_hold is not None
        if not self._yaw_seen:
            self.kfs[2].P[A, A] = self.kfs[2].P[AF, AF] = _BIG_ANGLE_VAR
        self._drop_aid_history()
        self._t_kf = t

    def _process_mag(self, t_m: float, field) -> None:
        if self._t_kf is None:
            self._pending_mag = (t_m, field)
            return
        roll, pitch = float(self.kfs[0].x[A, 0]), float(self.kfs[1].x[A, 0])
        yaw = self._compute_mag_yaw(field, roll, pitch)
        if yaw is None:
            return
        if not self._yaw_seen:
            self._set_yaw_from_mag(yaw)
        self._yaw_hold = yaw
        self._yaw_hold_t = t_m

    def _process_imu(self, t: float, gyro: np.ndarray, accel: np.ndarray, tilt=None) -> None:
        if self._t_kf is None:
            self._initialise(t, gyro, accel)
            return
        h = t - self._t_kf
        if not h > 0:
            return    # stale or duplicate sample: the KF only moves forward
        if h > self.params.max_gap_s:
            yaw_keep = float(self.kfs[2].x[A, 0])
            seen = self._yaw_seen
            self._t_kf = None
            self._initialise(t, gyro, accel)
            if seen and self._yaw_hold is None:
                self._set_yaw_from_mag(yaw_keep)
            return
        # low-pass (12), exact for an input linear over the step (mean of the two samples)
        c = 1.0 - math.exp(-h / self.params.lpf_tau_s)
        self._wf += c * (0.5 * (self._g_prev + gyro) - self._wf)
        self._g_prev = gyro.copy()
        # Kalman filter prediction over [t_kf, t) with the applied torques
        self._predict(self._t_kf, t)
        aid = self._aid_correction(t) if tilt is None else None
        if aid is not None:
            rp = self._aided_angles(aid)
        else:
            rp = self._accel_angles(accel) if tilt is None else tilt
        angle_ok = [rp is not None, rp is not None, False]
        if rp is not None:
            for i in range(2):
                cur = rp[i]
                mid = self._a_prev[i] + 0.5 * _wrap1(cur - self._a_prev[i])
                self._af[i] = _wrap1(self._af[i] + c * _wrap1(mid - self._af[i]))
                self._a_prev[i] = cur
        if self._yaw_hold is not None:
            # carry the held magnetometer yaw on with the z gyro up to this sample
            dt_hold = t - max(self._yaw_hold_t, t - h)
            if dt_hold > 0:
                self._yaw_hold = _wrap1(self._yaw_hold + float(gyro[2]) * dt_hold)
                self._yaw_hold_t = t
            cur = self._yaw_hold
            mid = self._a_prev[2] + 0.5 * _wrap1(cur - self._a_prev[2])
            self._af[2] = _wrap1(self._af[2] + c * _wrap1(mid - self._af[2]))
            self._a_prev[2] = cur
            angle_ok[2] = self._yaw_seen
        # Kalman filter update with [wf, af]
        for i, kf in enumerate(self.kfs):
            if angle_ok[i]:
                pred = float(kf.x[self._angle_meas_idx, 0])
                z = np.array([[self._wf[i]], [pred + _wrap1(self._af[i] - pred)]])
                kf.update(z, R=self._r[i], H=self._h)
            else:
                z = np.array([[self._wf[i]], [0.0]])
                kf.update(z, R=self._r[i], H=self._h_rate_only)
            self._rewrap(kf.x)
            kf.P = 0.5 * (kf.P + kf.P.T)
        self._t_kf = t
        self._record_amodel(t, accel)

    # -------------------------------------------------------------- acceleration reference
    def _drop_aid_history(self) -> None:
        """Forget the a_model history and the correction (the attitude they were made with is gone)."""
        self._amodel.clear()
        self._aid_c = None
        self._aid_done = None
        self._aid_t1 = -math.inf

    def _record_amodel(self, t: float, accel: np.ndarray) -> None:
        """a_model(t) = R f + g: the acceleration that the specific force f implies at the filter's attitude."""
        r = rotation_zyx(*(float(kf.x[A, 0]) for kf in self.kfs))
        a = r @ accel
        a[2] -= self.gravity
        self._amodel.append((t, a))
        while self._amodel and self._amodel[0][0] < t - 1.0:
            self._amodel.popleft()

    def _amodel_mean(self, t0: float, t1: float) -> np.ndarray | None:
        """Mean of a_model over [t0, t1] (trapezoid, ends interpolated); None unless the history covers it."""
        if not self._amodel or not t1 > t0:
            return None
        eps = 1e-6
        if self._amodel[0][0] > t0 + eps or self._amodel[-1][0] < t1 - eps:
            return None
        ts = np.array([e[0] for e in self._amodel])
        vals = np.array([e[1] for e in self._amodel])
        inner = ts[(ts > t0) & (ts < t1)]
        grid = np.concatenate(([t0], inner, [t1]))
        on_grid = np.stack([np.interp(grid, ts, vals[:, i]) for i in range(3)], axis=1)
        mean = np.sum(0.5 * (on_grid[1:] + on_grid[:-1]) * np.diff(grid)[:, None], axis=0) / (t1 - t0)
        return mean if np.all(np.isfinite(mean)) else None

    def _aid_correction(self, t: float) -> np.ndarray | None:
        """c = a_ref - mean(a_model) over the reference's window (bounded), or None (no usable reference)."""
        ref = self._aid_ref
        if ref is None:
            return None
        t0, t1, a_ref = ref
        if self._aid_done != (t0, t1):
            mean = self._amodel_mean(t0, t1)
            if mean is not None:
                corr = a_ref - mean
                n = float(np.linalg.norm(corr))
                cap = self.params.aid_max_correction_m_s2
                self._aid_c = corr * (cap / n) if n > cap else corr
                self._aid_done = (t0, t1)
                self._aid_t1 = t1
        if self._aid_c is None or t - self._aid_t1 > self.params.aid_max_age_s:
            return None
        return self._aid_c

    def _aided_angles(self, corr: np.ndarray) -> tuple[float, float]:
        """(roll, pitch) of the accelerometer compensated with a = R f + g + c at the predicted attitude R:
        f - R^T a = R^T ([0, 0, g] - c), i.e. the predicted attitude moved by the correction c."""
        r = rotation_zyx(*(float(kf.x[A, 0]) for kf in self.kfs))
        return accel_roll_pitch(r.T @ (np.array([0.0, 0.0, self.gravity]) - corr))

    def sample_state(self) -> tuple[np.ndarray, np.ndarray]:
        """(euler, rate) of the KF at its newest IMU sample (not extrapolated)."""
        return (wrap(np.array([kf.x[A, 0] for kf in self.kfs])), np.array([kf.x[W, 0] for kf in self.kfs]))

    def reinitialise(self, euler, rate) -> None:
        """Restart the angle and rate states (and the low-passes) at a known attitude, keeping P
        and the gyro bias.

        rate: the gyro's reading there (the rate states take it less the bias estimate).
        Used after a manoeuvre the filter cannot follow (a flip: see GyroCarrier); the
        accelerometer and magnetometer low-passes restart there too, so they pull from it."""
        if self._t_kf is None:
            return
        euler = wrap(np.asarray(euler, dtype=np.float64))
        rate = np.asarray(rate, dtype=np.float64)
        for i, kf in enumerate(self.kfs):
            kf.x[W, 0] = kf.x[WF, 0] = rate[i] - kf.x[B, 0]
            kf.x[A, 0] = kf.x[AF, 0] = euler[i]
        self._wf, self._g_prev = rate.copy(), rate.copy()
        self._af, self._a_prev = euler.copy(), euler.copy()
        if self._yaw_hold is not None:
            self._yaw_hold = float(euler[2])
        self._drop_aid_history()

    def _healthy(self) -> bool:
        for kf in self.kfs:
            if not (np.all(np.isfinite(kf.x)) and np.all(np.isfinite(kf.P))):
                return False
        return True

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
        Returns the estimate at t_now (extrapolated over the delay when ``extrapolate``).
        """
        t_now = float(t_now)
        self._aid_ref = None
        if accel_ref is not None:
            try:
                t0, t1, a_ref = float(accel_ref[0]), float(accel_ref[1]), np.asarray(accel_ref[2], dtype=np.float64)
            except (TypeError, ValueError, IndexError):
                t0 = t1 = math.nan
                a_ref = np.zeros(0)
            if math.isfinite(t0) and math.isfinite(t1) and t1 > t0 and a_ref.shape == (3,) \
                    and np.all(np.isfinite(a_ref)):
                self._aid_ref = (t0, t1, a_ref)
        self._add_torque(torque_nm, t_now)
        self._t_prev_call = t_now
        samples = []
        for s in imu_samples or ():
            t, g, a = s[:3]
            tilt = s[3] if len(s) > 3 else None
            g = np.asarray(g, dtype=np.float64).reshape(-1)
            a = np.asarray(a, dtype=np.float64).reshape(-1)
            t = float(t)
            if tilt is not None and not all(math.isfinite(v) for v in tilt):
                tilt = None
            if g.shape == (3,) and a.shape == (3,) and math.isfinite(t) and np.all(np.isfinite(g)) \
                    and np.all(np.isfinite(a)):
                samples.append((t, g, a, tilt))
        samples.sort(key=lambda s: s[0])
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

    def _estimate(self, t_now: float) -> AttitudeEstimate:
        p = self.params
        if self._t_kf is None:
            var_a = np.array([kf.P[A, A] for kf in self.kfs])
            var_w = np.array([kf.P[W, W] for kf in self.kfs])
            return AttitudeEstimate(np.zeros(3), np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]),
                                    var_a, var_w, 0.0)
        delay = max(0.0, t_now - self._t_kf)
        xs = [kf.x.copy() for kf in self.kfs]
        ps = [kf.P.copy() for kf in self.kfs]
        if p.extrapolate and delay > 0.0:
            horizon = min(delay, p.max_delay_steps * self.dt)
            for h, u in self._pieces(self._t_kf, self._t_kf + horizon):
                f, bd, qw, qa, qb = self._disc(h)
                e = self._excess(xs)
                for i in range(3):
                    xs[i] = f @ xs[i] + bd @ np.array([[u[i]], [e[i]]])
                    ps[i] = f @ ps[i] @ f.T + self._q(i, qw, qa, qb)
        euler = wrap(np.array([x[A, 0] for x in xs]))
        rate = np.array([x[W, 0] for x in xs])
        euler_var = np.array([pp[A, A] for pp in ps])
        rate_var = np.array([pp[W, W] for pp in ps])
        if not (np.all(np.isfinite(euler)) and np.all(np.isfinite(rate))):
            euler, rate = np.zeros(3), np.zeros(3)
        q = quat_from_euler(*euler)
        return AttitudeEstimate(euler, rate, q, euler_var, rate_var, float(delay))


# ------------------------------------------------------------------ camera level
class CameraLevel:
    """Roll/pitch offset of the attitude estimate, measured against the camera's attitude.

    The accelerometer's bias tilts the estimate's "level": 0.01 m/s^2 is 0.06 deg, and the
    acceleration reference cannot see it (the filter's attitude settles where the rotated
    accelerometer agrees with the EKF's velocity change). The vision pose's attitude has no
    such bias (about 0.15 deg of noise per frame, stamped with the exposure time), so the
    difference between the estimate at a frame's exposure time (from a short history) and
    the frame's roll/pitch, low-passed over time_constant_s, is the offset to subtract from
    the published estimate. Frames taken while the vehicle turned faster than max_rate_rad_s
    (a millisecond of timing error is then visible), tilted past max_tilt_rad, outside the
    history, or disagreeing by more than gate_rad with the current offset are not used
    (counted by reason in `rejected`). Pure: no I/O."""

    def __init__(self, time_constant_s: float = 2.0, max_rate_rad_s: float = 1.0,
                 max_tilt_rad: float = 0.5, gate_rad: float = 0.05, history_s: float = 0.5,
                 max_offset_rad: float = 0.05):
        if not (time_constant_s > 0 and max_rate_rad_s > 0 and max_tilt_rad > 0 and gate_rad > 0
                and history_s > 0 and max_offset_rad > 0):
            raise ValueError("camera level: every setting must be positive")
        self.time_constant_s = time_constant_s
        self.max_rate_rad_s = max_rate_rad_s
        self.max_tilt_rad = max_tilt_rad
        self.gate_rad = gate_rad
        self.history_s = history_s
        self.max_offset_rad = max_offset_rad
        self.offset_rad = np.zeros(2)   # (roll, pitch): estimate minus camera
        self.fused = 0
        self.rejected: dict[str, int] = {}
        self._history: deque = deque()  # (t, roll, pitch, |rate|), oldest first
        self._last_fused_t = None

    def record(self, t_s: float, euler_rad, rate_rad_s) -> None:
        """The estimate (before the offset is removed) at t_s, in time order."""
        if self._history and t_s <= self._history[-1][0]:
            return
        self._history.append((float(t_s), float(euler_rad[0]), float(euler_rad[1]),
                              float(np.linalg.norm(rate_rad_s))))
        while self._history and self._history[0][0] < t_s - self.history_s:
            self._history.popleft()

    def _reject(self, reason: str) -> bool:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        return False

    def fuse(self, t_exposure_s: float, quaternion_wxyz) -> bool:
        """One camera attitude at its exposure time; True when it moved the offset."""
        q = np.asarray(quaternion_wxyz, dtype=np.float64)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 0.5:
            return self._reject("camera_level_bad_quaternion")
        roll, pitch, _ = quat_to_euler(q / np.linalg.norm(q))
        h = self._history
        if len(h) < 2 or not (h[0][0] <= t_exposure_s <= h[-1][0]):
            return self._reject("camera_level_outside_history")
        i = next(k for k in range(1, len(h)) if h[k][0] >= t_exposure_s)
        (t0, r0, p0, w0), (t1, r1, p1, w1) = h[i - 1], h[i]
        f = (t_exposure_s - t0) / (t1 - t0) if t1 > t0 else 1.0
        est = np.array([r0 + f * (r1 - r0), p0 + f * (p1 - p0)])
        if max(w0, w1) > self.max_rate_rad_s:
            return self._reject("camera_level_turning")
        if max(abs(roll), abs(pitch), *np.abs(est)) > self.max_tilt_rad:
            return self._reject("camera_level_tilted")
        diff = est - np.array([roll, pitch])
        if np.any(np.abs(diff - self.offset_rad) > self.gate_rad):
            return self._reject("camera_level_inconsistent")
        dt = (t_exposure_s - self._last_fused_t) if self._last_fused_t is not None else 0.05
        gain = min(1.0, max(dt, 0.0) / self.time_constant_s)
        self.offset_rad = np.clip(self.offset_rad + gain * (diff - self.offset_rad),
                                  -self.max_offset_rad, self.max_offset_rad)
        self._last_fused_t = t_exposure_s
        self.fused += 1
        return True

    def apply(self, euler_rad) -> np.ndarray:
        """The estimate's (roll, pitch, yaw) with the offset removed."""
        out = np.array(euler_rad, dtype=np.float64)
        out[:2] -= self.offset_rad
        return out


# ------------------------------------------------------------------ inversion carrier
def quat_integrate(q, rate_rad_s, h: float) -> np.ndarray:
    """q (x) exp(0.5 w h): a body->world quaternion turned by the body rate w over h (exact for constant w)."""
    w = np.asarray(rate_rad_s, dtype=np.float64)
    angle = float(np.linalg.norm(w)) * h
    if angle < 1e-12:
        return np.asarray(q, dtype=np.float64).copy()
    axis = w / np.linalg.norm(w)
    s = math.sin(0.5 * angle)
    dq = np.array([math.cos(0.5 * angle), *(s * axis)])
    qn = quat_multiply(q, dq)
    return qn / np.linalg.norm(qn)


def quat_tilt(q) -> float:
    """Angle between the body z axis and the world z axis, rad (0 level, pi inverted)."""
    w, x, y, z = (float(v) for v in q)
    r22 = (w * w - x * x - y * y + z * z) / (w * w + x * x + y * y + z * z)
    return math.acos(min(1.0, max(-1.0, r22)))


class GyroCarrier:
    """A quaternion carried by the gyros through attitudes the 000 filter cannot hold.

    The 000 filter is three independent Euler-angle axes with the body rate taken
    as the Euler rate: fine near level, wrong when tilted far or turning fast, and
    it cannot represent inversion.  Near level the carrier just follows that
    filter (``follow``: its estimate is used unchanged, so normal flight is
    exactly 000).  Once tilted past ``enter_tilt_deg`` or turning faster than
    ``enter_rate_rad_s`` it becomes ``active``: every IMU sample turns the
    quaternion by the gyro (``propagate``; gyro bias ~3e-3 rad/s, so a 1 s flip
    drifts well under a degree), and the attitude service publishes it.  When
    back within ``exit_tilt_deg`` and slower than ``exit_rate_rad_s``,
    ``back_near_level`` says so and the service re-initialises the 000 filter
    from it (hysteresis between the two thresholds avoids chattering).
    """

    def __init__(self, enter_tilt_deg: float = 45.0, exit_tilt_deg: float = 30.0,
                 enter_rate_rad_s: float = 6.0, exit_rate_rad_s: float = 2.0):
        if not (0.0 < exit_tilt_deg <= enter_tilt_deg < 180.0 and 0.0 < exit_rate_rad_s <= enter_rate_rad_s):
            raise ValueError("GyroCarrier: need 0 < exit_tilt <= enter_tilt < 180 and 0 < exit_rate <= enter_rate")
        self.enter_tilt = math.radians(enter_tilt_deg)
        self.exit_tilt = math.radians(exit_tilt_deg)
        self.enter_rate = float(enter_rate_rad_s)
        self.exit_rate = float(exit_rate_rad_s)
        self.q = np.array([1.0, 0.0, 0.0, 0.0])
        self.t: float | None = None
        self.gyro = np.zeros(3)
        self.active = False
        self.activations = 0

    def follow(self, t_s: float, q, gyro) -> None:
        """Inactive: take the 000 filter's attitude at its newest sample time and that sample's gyro."""
        self.q = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
        self.t = float(t_s)
        self.gyro = np.asarray(gyro, dtype=np.float64).copy()

    def check_enter(self, q, rate) -> bool:
        """Become active when the attitude (q, rate) is beyond what the 000 filter represents."""
        if not self.active and self.t is not None and (
                quat_tilt(q) > self.enter_tilt or float(np.linalg.norm(rate)) > self.enter_rate):
            self.active = True
            self.activations += 1
        return self.active

    def propagate(self, t_s: float, gyro) -> None:
        """One IMU sample: turn by the mean of the previous and this gyro over the interval."""
        gyro = np.asarray(gyro, dtype=np.float64)
        if self.t is None or not t_s > self.t:
            return
        self.q = quat_integrate(self.q, 0.5 * (self.gyro + gyro), t_s - self.t)
        self.t = float(t_s)
        self.gyro = gyro.copy()

    def back_near_level(self) -> bool:
        return self.active and quat_tilt(self.q) < self.exit_tilt and float(np.linalg.norm(self.gyro)) < self.exit_rate

    def estimate(self, t_now: float, max_delay_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(quaternion, body rate) at t_now: carried over the transport delay by the newest gyro."""
        delay = min(max(0.0, t_now - (self.t if self.t is not None else t_now)), max_delay_s)
        return quat_integrate(self.q, self.gyro, delay), self.gyro.copy()


# The per-axis filter of 000 as printed (an ablation): no gyro-bias state, the body rate taken
# as the Euler rate, the angle random walk 000 needs to absorb both; with the attitude
# service's acceleration_compensation = "slope" it is the stack's estimator before the
# aided tilt (README: attitude steps on estimates 5-12 % / 0.6-1.0 s with it).
FILTER_000 = {"angle_process_var": (1e-5, 1e-5, 1e-5), "euler_kinematics": False,
              "init_bias_var": 0.0, "bias_process_var": (1e-12, 1e-12, 1e-12)}
