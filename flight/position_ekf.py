"""Position-level extended Kalman filter of document 000 (slow loop, 100 Hz).

Gerasimov et al., "Quadcopter motion control based on cascaded Kalman filters"
(Avtometriya 2022), "Position level": an EKF on the full 12-state model
(1)-(2), linearised at the current estimate (21)-(23), corrected by the
measurement (24) ``z = [x, y, z, roll, pitch, yaw, wx, wy, wz]``: the position
from an external camera (20 Hz, delayed), the angles and body rates from the
attitude level's Kalman filter (100 Hz, already delay-compensated there).
Pure algorithm, no I/O.

State and conventions
---------------------
``x = [x, y, z, vx, vy, vz, roll, pitch, yaw, wx, wy, wz]``: world ENU
position and velocity (z up), ZYX Euler angles listed [roll, pitch, yaw]
(``R = Rz(yaw) Ry(pitch) Rx(roll)``), body FLU angular rates.  Input
``u = [u1, u2, u3, u4]``: total thrust (N) and body torques (N m), held over a
step (zero-order hold, as the controller applies it).  The filter adds a 13th
state, the thrust scale s (:class:`PositionEKF`): the model runs with s u1.

Model (:func:`f`)::

    p' = v
    v' = (u1 / m) R e3 - (c / m) v - g e3
         R e3 = [sy sr + cy cr sp,  -cy sr + sy cr sp,  cr cp]       (1)
    [roll', pitch', yaw'] = W(roll, pitch) w                        (ZYX kinematics)
    Ixx wx' = u2 - (Izz - Iyy) wy wz
    Iyy wy' = u3 - (Ixx - Izz) wz wx                                 (2)
    Izz wz' = u4 - (Iyy - Ixx) wx wy

Two deliberate differences from the printed (1)-(2):

* the linear drag ``-c v / m`` of the vehicle (``drag_n_per_m_s``), as the
  plant (simulator/plant.py) has it;
* 000 writes (2) on Euler-angle rates, i.e. it identifies ``[roll', pitch',
  yaw']`` with the body rates.  Here the rates are the body rates (that is what
  the attitude level measures, and what the plant integrates), so (2) is
  Euler's rigid-body equation exactly, and the angles follow the exact ZYX
  kinematics ``W``.  Near hover ``W = I`` and the two coincide; at 20 deg bank
  with a yaw rate they do not.  ``W`` is singular at pitch = +-90 deg (gimbal
  lock), which a position-holding quadcopter does not reach (flips belong to
  the quaternion planner of 001).

Discretisation (:func:`discretize`): RK4 for the mean with ``u`` held (23);
``F_d = I + A + A^2 / 2`` with ``A = J dt`` (second-order series of
``expm(J dt)``, ``J`` the analytic Jacobian (22) of :func:`jacobian_f` at the
step's start); ``Q_d = Q_c dt`` with ``Q_c`` the diagonal of continuous
white-noise densities per state group (:class:`PositionEKFParams`).
Corrections (18)-(20) in Joseph form, NIS-gated by a chi-square test.

Why the camera is fused at its own time and the predictions re-run, rather than
through the extrapolator (15)
----------------------------------------------------------------------------------
The extrapolator (15) starts the model at the delayed measurement and
integrates it N steps forward with the stored controls.  It suits the attitude
level, whose measurement is that level's whole state (angles and rates at
270 Hz) with a fixed, short transport delay; it is used there.  For the camera
it does not fit:

1. the camera measures 3 of the 12 states.  To "start the model at the
   measurement" one needs the velocity, angles and rates at the exposure time
   too, and those are exactly the filter's own past estimates: the filter's
   history is the extrapolator's missing initial condition;
2. an extrapolated position carries the camera noise *plus* the error of the
   estimates used to extrapolate (velocity x 150 ms is 1.5 cm at 0.1 m/s of
   velocity error), correlated with the current state.  Fused as a fresh,
   independent measurement with the camera's R, it makes the filter
   overconfident (NEES too high) and the chi-square gate meaningless; the
   right R would be the covariance of the extrapolation, which is what the
   re-prediction computes anyway;
3. the camera's delay is not a fixed N steps: exposure, marker detection and
   transport vary from frame to frame (50-150 ms), each frame carries its own
   exposure time stamp;
4. the gate must compare the measurement with the state *at the time it
   refers to*; compared with the current state, a vehicle moving at 1 m/s is
   10-15 cm away from a correct 100-150 ms old fix, and the fix would be gated
   out (or, with a wide gate, drag the estimate backwards).

Fusing at the exposure time and re-running the predictions with the stored
inputs (re-applying the attitude corrections recorded meanwhile) is the exact
Kalman solution for the delayed measurement (up to the re-linearisation along
the corrected trajectory, which only helps).  The cost is bounded: at 100 Hz
and 150 ms at most 15 predictions per camera frame, 20 frames a second.

Delayed fusion details (:meth:`PositionEKF.update_position`): the history holds
one node per prediction (its time, the input that led to it, the *prior* mean
and covariance there, and the measurements accepted there).  A measurement at
``t_meas`` is applied at the node nearest not after ``t_meas``; a remaining
offset ``d = t_meas - t_node`` (< dt) is taken into the measurement model
``h = p + d v``.  Accepted measurements are stored in their node, so a later,
older measurement re-applies them when it replays; rejected ones leave no
trace but a counter.  Measurements older than the history (``max_delay_s``) or
ahead of the filter's time are refused and counted.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
from scipy.stats import chi2

from flight.plan import motor_forces_update
from flight.vehicle import Vehicle

__all__ = [
    "PositionEKFError", "PositionEKFParams", "PositionEKF",
    "f", "jacobian_f", "rk4_step", "discretize", "wrap_angle",
    "POSITION", "VELOCITY", "EULER", "RATES", "THRUST_SCALE", "N_MODEL", "N_STATE", "LaggedMotorInput",
]

N_MODEL = 12       # the states of (1)-(2)
THRUST_SCALE = 12  # the filter's 13th state (see PositionEKF)
N_STATE = 13
POSITION = slice(0, 3)
VELOCITY = slice(3, 6)
EULER = slice(6, 9)
RATES = slice(9, 12)
THRUST_SCALE_LIMITS = (0.5, 2.0)  # a physical bound: beyond it the vehicle cannot hover anyway

_TWO_PI = 2.0 * math.pi
_KINDS = ("attitude", "position", "pin")
_REASONS = ("gate", "too_old", "future", "invalid")


class PositionEKFError(ValueError):
    """Bad parameters or malformed inputs to the position EKF."""


def wrap_angle(a):
    """Wrap to [-pi, pi)."""
    return (np.asarray(a, dtype=np.float64) + math.pi) % _TWO_PI - math.pi


# --------------------------------------------------------------------------- #
# Parameters
# --------------------------------------------------------------------------- #
@dataclass(frozen=True)
class PositionEKFParams:
    """Noise, gate and history settings.

    Process noise is given as continuous white-noise spectral densities per
    state group (``Q_d = Q_c dt``), so it does not change meaning with dt:

    * ``q_position_m2_s``: the kinematics p' = v are exact; a small floor for
      time-stamp jitter and integration error.
    * ``q_velocity_m2_s3``: unmodelled accelerations: thrust error (motor lag
      20 ms, battery sag, the PWM map), drag error, draughts; indoor flight
      (000 flies indoors under a camera).  0.005 m^2/s^3 is e.g. a 0.1 m/s^2
      (1 % of g) disturbance with a 0.25 s correlation time (2 sigma^2 tau);
      it lets the velocity drift by 0.1 m/s and the position by 0.08 m over
      a 2 s camera outage (1 sigma).  A slow thrust bias is followed through
      the camera (a few mm of lag at 20 Hz); it is not a state of (1)-(2).
    * ``q_angles_rad2_s``: the ZYX kinematics are exact; small floor.
    * ``q_rates_rad2_s3``: unmodelled torques: the 20 ms motor lag at the
      attitude loop's 16 rad/s bandwidth, prop imbalance, inertia error.
      0.5 rad^2/s^3 gives 0.07 rad/s of rate uncertainty per 10 ms step, above
      the attitude level's 0.02 rad/s, so the rate states follow that level.
    * ``gate_probability``: chi-square gate on the innovation's NIS
      (Mahalanobis distance squared); 0.999 refuses a fix more than ~4 sigma
      away for 3 dof (threshold 16.3).  1.0 disables the gate.
    * ``max_delay_s``: history kept for delayed measurements; 0.3 s covers
      twice the camera's worst delay (150 ms).
    * ``q_thrust_scale_1_s``: random walk of the thrust scale (real collective force
      per commanded newton): battery sag and a payload change it over seconds to
      minutes; 1e-4 /s lets it move 0.03 in 10 s (1 sigma).
    * ``init_std_*``: 1-sigma of the initial covariance: position from a
      first camera fix, at rest, level within a few degrees; the thrust scale
      within 10 % of the airframe file's (mass, payload, rotor wear).
    """

    q_position_m2_s: float = 1e-6
    q_velocity_m2_s3: float = 0.02
    q_angles_rad2_s: float = 1e-6
    q_rates_rad2_s3: float = 0.5
    gate_probability: float = 0.999
    max_delay_s: float = 0.3
    init_std_position_m: float = 0.05
    init_std_velocity_m_s: float = 0.1
    init_std_angles_rad: float = 0.05
    init_std_rates_rad_s: float = 0.05
    q_thrust_scale_1_s: float = 1e-4
    init_std_thrust_scale: float = 0.1

    def __post_init__(self):
        for fld in fields(self):
            v = getattr(self, fld.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise PositionEKFError(f"PositionEKFParams.{fld.name}: must be a finite number (got {v!r})")
            object.__setattr__(self, fld.name, float(v))
            if fld.name.startswith("q_") and v < 0:
                raise PositionEKFError(f"PositionEKFParams.{fld.name}: must be >= 0 (got {v!r})")
            if fld.name.startswith("init_std_") and v <= 0:
                raise PositionEKFError(f"PositionEKFParams.{fld.name}: must be > 0 (got {v!r})")
        if not 0.0 < self.gate_probability <= 1.0:
            raise PositionEKFError(f"PositionEKFParams.gate_probability: must be in (0, 1] "
                                   f"(got {self.gate_probability!r})")
        if self.max_delay_s < 0:
            raise PositionEKFError(f"PositionEKFParams.max_delay_s: must be >= 0 (got {self.max_delay_s!r})")

    @classmethod
    def from_dict(cls, d: dict) -> "PositionEKFParams":
        if not isinstance(d, dict):
            raise PositionEKFError(f"PositionEKFParams: expected a table, got {type(d).__name__}")
        known = {fld.name for fld in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise PositionEKFError(f"PositionEKFParams: unknown key(s) {unknown}; known: {sorted(known)}")
        return cls(**d)

    def to_dict(self) -> dict:
        return {fld.name: getattr(self, fld.name) for fld in fields(self)}

    @property
    def process_noise_density(self) -> np.ndarray:
        """Diagonal of Q_c (13,)."""
        return np.r_[np.repeat([self.q_position_m2_s, self.q_velocity_m2_s3,
                                self.q_angles_rad2_s, self.q_rates_rad2_s3], 3), self.q_thrust_scale_1_s]

    @property
    def initial_covariance(self) -> np.ndarray:
        return np.diag(np.r_[np.repeat([self.init_std_position_m, self.init_std_velocity_m_s,
                                        self.init_std_angles_rad, self.init_std_rates_rad_s], 3),
                             self.init_std_thrust_scale] ** 2)


# --------------------------------------------------------------------------- #
# Model (1)-(2), its Jacobian (22), discretisation (23)
# --------------------------------------------------------------------------- #
def f(x, u, vehicle: Vehicle) -> np.ndarray:
    """Continuous dynamics x' = f(x, u) of the 12-state model (see module doc)."""
    # scalar maths: numpy's per-call overhead on 3-vectors dominates at this size
    _, _, _, vx, vy, vz, r, p, y, wx, wy, wz = x.tolist() if isinstance(x, np.ndarray) else list(x)
    u1, u2, u3, u4 = u.tolist() if isinstance(u, np.ndarray) else list(u)
    m = vehicle.mass_kg
    c = vehicle.drag_n_per_m_s
    ixx, iyy, izz = vehicle.inertia_kg_m2
    sr, cr = math.sin(r), math.cos(r)
    sp, cp = math.sin(p), math.cos(p)
    sy, cy = math.sin(y), math.cos(y)
    a = u1 / m
    k = c / m
    tp = sp / cp
    q = sr * wy + cr * wz
    return np.array([
        vx, vy, vz,
        a * (sy * sr + cy * cr * sp) - k * vx,
        a * (-cy * sr + sy * cr * sp) - k * vy,
        a * (cr * cp) - k * vz - vehicle.gravity_m_s2,
        wx + tp * q,
        cr * wy - sr * wz,
        q / cp,
        (u2 - (izz - iyy) * wy * wz) / ixx,
        (u3 - (ixx - izz) * wz * wx) / iyy,
        (u4 - (iyy - ixx) * wx * wy) / izz,
    ])


def jacobian_f(x, u, vehicle: Vehicle) -> np.ndarray:
    """Analytic 12x12 Jacobian df/dx of the model (1)-(2) at (x, u) (22)."""
    _, _, _, _, _, _, r, p, y, wx, wy, wz = x.tolist() if isinstance(x, np.ndarray) else list(x)
    u1 = float(u[0])
    m = vehicle.mass_kg
    k = vehicle.drag_n_per_m_s / m
    ixx, iyy, izz = vehicle.inertia_kg_m2
    sr, cr = math.sin(r), math.cos(r)
    sp, cp = math.sin(p), math.cos(p)
    sy, cy = math.sin(y), math.cos(y)
    a = u1 / m
    tp = sp / cp
    q = sr * wy + cr * wz      # d q / d roll = qd
    qd = cr * wy - sr * wz
    J = np.zeros((N_MODEL, N_MODEL))
    # p' = v
    J[0, 3] = J[1, 4] = J[2, 5] = 1.0
    # v' = a R e3 - k v - g e3
    J[3, 3] = J[4, 4] = J[5, 5] = -k
    J[3, 6] = a * (sy * cr - cy * sr * sp)
    J[3, 7] = a * (cy * cr * cp)
    J[3, 8] = a * (cy * sr - sy * cr * sp)
    J[4, 6] = a * (-cy * cr - sy * sr * sp)
    J[4, 7] = a * (sy * cr * cp)
    J[4, 8] = a * (sy * sr + cy * cr * sp)
    J[5, 6] = -a * sr * cp
    J[5, 7] = -a * cr * sp
    # roll' = wx + tan(p) q
    J[6, 6] = tp * qd
    J[6, 7] = q / (cp * cp)
    J[6, 9] = 1.0
    J[6, 10] = sr * tp
    J[6, 11] = cr * tp
    # pitch' = cr wy - sr wz
    J[7, 6] = -q
    J[7, 10] = cr
    J[7, 11] = -sr
    # yaw' = q / cos(p)
    J[8, 6] = qd / cp
    J[8, 7] = q * sp / (cp * cp)
    J[8, 10] = sr / cp
    J[8, 11] = cr / cp
    # Euler's equations
    J[9, 10] = -(izz - iyy) * wz / ixx
    J[9, 11] = -(izz - iyy) * wy / ixx
    J[10, 9] = -(ixx - izz) * wz / iyy
    J[10, 11] = -(ixx - izz) * wx / iyy
    J[11, 9] = -(iyy - ixx) * wy / izz
    J[11, 10] = -(iyy - ixx) * wx / izz
    return J


def rk4_step(x, u, vehicle: Vehicle, dt: float) -> np.ndarray:
    """One RK4 step of f with u held (the prediction (23) of the mean)."""
    x = np.asarray(x, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    k1 = f(x, u, vehicle)
    k2 = f(x + 0.5 * dt * k1, u, vehicle)
    k3 = f(x + 0.5 * dt * k2, u, vehicle)
    k4 = f(x + dt * k3, u, vehicle)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def discretize(x, u, vehicle: Vehicle, dt: float, q_density=None):
    """One step: (x_next by RK4, F_d = I + A + A^2/2 with A = J dt, Q_d = diag(q_density) dt).

    x has the 12 states of (1)-(2), or 13 with the thrust scale s last (the filter's
    state): then the model runs with u1 scaled by s, and J gets the column
    d v' / d s = (u1 / m) R e3 (s itself is a random walk)."""
    x = np.asarray(x, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    if x.shape[0] == N_MODEL:
        x_next = rk4_step(x, u, vehicle, dt)
        A = jacobian_f(x, u, vehicle) * dt
    else:
        s = x[THRUST_SCALE]
        u_real = u.copy()
        u_real[0] *= s
        x_next = x.copy()
        x_next[:N_MODEL] = rk4_step(x[:N_MODEL], u_real, vehicle, dt)
        J = np.zeros((N_STATE, N_STATE))
        J[:N_MODEL, :N_MODEL] = jacobian_f(x[:N_MODEL], u_real, vehicle)
        r, p, y = x[EULER]
        sr, cr, sp, cp, sy, cy = math.sin(r), math.cos(r), math.sin(p), math.cos(p), math.sin(y), math.cos(y)
        J[VELOCITY, THRUST_SCALE] = (u[0] / vehicle.mass_kg) * np.array(
            [sy * sr + cy * cr * sp, -cy * sr + sy * cr * sp, cr * cp])
        A = J * dt
    F = np.eye(x.shape[0]) + A + 0.5 * (A @ A)
    Q = None if q_density is None else np.diag(np.asarray(q_density, dtype=np.float64) * dt)
    return x_next, F, Q


# --------------------------------------------------------------------------- #
# The filter
# --------------------------------------------------------------------------- #
class _Node:
    """One history entry: time, input that led here, prior (x, P) here, accepted measurements."""

    __slots__ = ("t", "u", "x", "P", "meas")

    def __init__(self, t, u, x, P):
        self.t = t
        self.u = u
        self.x = x
        self.P = P
        self.meas: list[tuple] = []  # (kind, z, R, offset_s), in the order applied


class PositionEKF:
    """EKF on the 12-state model with delayed camera fusion (see module doc).

    Its state has a 13th element, the thrust scale s: the collective force the
    vehicle really gets per newton commanded (1 for the airframe file's mass and
    rotors). (1) runs with s u1. A heavier vehicle (payload), a weaker battery or
    worn rotors change s; the camera's positions make it observable through the
    vertical (and, tilted, horizontal) acceleration, and the laws divide the
    collective by it (PX4 estimates its hover thrust for the same reason). Without
    it the laws of 000, which have no integral action, hold a heavier vehicle low,
    and the EKF's velocity is biased by the wrong acceleration.
    """

    def __init__(self, vehicle: Vehicle, params: PositionEKFParams | None = None, dt: float = 0.01):
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise PositionEKFError(f"dt must be a positive number (got {dt!r})")
        self.vehicle = vehicle
        self.params = params if params is not None else PositionEKFParams()
        self.dt = float(dt)
        self._qc = self.params.process_noise_density
        p = self.params.gate_probability
        self._gate = {n: (math.inf if p >= 1.0 else float(chi2.ppf(p, n))) for n in (3, 6)}
        self._eps = 1e-6 * self.dt
        self._x: np.ndarray | None = None
        self._P: np.ndarray | None = None
        self._t: float | None = None
        self._hist: list[_Node] = []
        self._counts = {k: {"accepted": 0, **{r: 0 for r in _REASONS}} for k in _KINDS}
        self.last_nis = {k: math.nan for k in _KINDS}

    # ---------------------------------------------------------------- state
    @property
    def initialized(self) -> bool:
        return self._x is not None

    @property
    def t(self) -> float:
        self._need_init()
        return self._t

    @property
    def x(self) -> np.ndarray:
        self._need_init()
        return self._x.copy()

    @property
    def P(self) -> np.ndarray:
        self._need_init()
        return self._P.copy()

    @property
    def position(self) -> np.ndarray:
        return self.x[POSITION]

    @property
    def velocity(self) -> np.ndarray:
        return self.x[VELOCITY]

    @property
    def euler(self) -> np.ndarray:
        return self.x[EULER]

    @property
    def rates(self) -> np.ndarray:
        return self.x[RATES]

    @property
    def thrust_scale(self) -> float:
        return float(self.x[THRUST_SCALE])

    @property
    def position_cov(self) -> np.ndarray:
        return self.P[POSITION, POSITION]

    @property
    def history_span_s(self) -> float:
        return self._hist[-1].t - self._hist[0].t if self._hist else 0.0

    @property
    def counters(self) -> dict:
        """{kind: {"accepted": n, "gate": n, "too_old": n, "future": n, "invalid": n}}, a copy."""
        return {k: dict(v) for k, v in self._counts.items()}

    def accepted(self, kind: str) -> int:
        return self._counts[kind]["accepted"]

    def rejected(self, kind: str, reason: str | None = None) -> int:
        c = self._counts[kind]
        return sum(c[r] for r in _REASONS) if reason is None else c[reason]

    # ---------------------------------------------------------------- steps
    def initialize(self, t_s: float, position, euler=(0.0, 0.0, 0.0), P0=None) -> None:
        """Start at rest at ``position`` with attitude ``euler``; P from the params (or P0)."""
        x = np.zeros(N_STATE)
        x[POSITION] = _vec(position, 3, "position")
        x[EULER] = _vec(euler, 3, "euler")
        x[THRUST_SCALE] = 1.0
        x[6] = float(wrap_angle(x[6]))
        x[8] = float(wrap_angle(x[8]))
        P = self.params.initial_covariance if P0 is None else np.array(P0, dtype=np.float64)
        if P.shape != (N_STATE, N_STATE) or not np.all(np.isfinite(P)):
            raise PositionEKFError(f"P0 must be a finite {N_STATE}x{N_STATE} matrix")
        self._t = float(t_s)
        self._x, self._P = x, 0.5 * (P + P.T)
        self._hist = [_Node(self._t, None, x.copy(), self._P.copy())]

    def reset_position(self, position, cov, velocity_std_m_s: float = 1.0) -> None:
        """Restart the translational states at a camera fix, keeping the attitude:
        the way out when the gate has refused every fix for a while (the filter
        has lost the vehicle and would otherwise never take a fix again)."""
        self._need_init()
        x, P = self._x.copy(), self._P.copy()
        x[POSITION] = _vec(position, 3, "position")
        P[:6, :] = 0.0
        P[:, :6] = 0.0
        P[:3, :3] = np.array(cov, dtype=np.float64).reshape(3, 3)
        P[3:6, 3:6] = np.eye(3) * velocity_std_m_s**2
        self._x, self._P = x, P
        self._hist = [_Node(self._t, None, x.copy(), P.copy())]

    def predict(self, t_s: float, u) -> None:
        """Advance to t_s with u = [u1 (N), u2, u3, u4 (N m)] held; record the step."""
        self._need_init()
        u = _vec(u, 4, "u")
        if not np.all(np.isfinite(u)):
            raise PositionEKFError(f"u must be finite (got {u})")
        h = float(t_s) - self._t
        if not h > self._eps:
            raise PositionEKFError(f"predict: time must advance (t={self._t}, t_s={t_s})")
        self._x, self._P = self._propagate(self._x, self._P, u, h)
        self._t = float(t_s)
        self._hist.append(_Node(self._t, u, self._x.copy(), self._P.copy()))
        # keep the newest node at or before (now - max_delay) and everything after it
        horizon = self._t - self.params.max_delay_s + self._eps
        drop = 0
        while drop + 1 < len(self._hist) and self._hist[drop + 1].t <= horizon:
            drop += 1
        if drop:
            del self._hist[:drop]

    def update_attitude(self, t_s: float, euler, rates, euler_var, rate_var) -> bool:
        """Rows 4..9 of (24): angles and body rates from the attitude level; gated, yaw wrapped.

        Normally t_s is the filter's time (the attitude level compensates its own
        delay with (15)); an older t_s within the history is fused there like the
        camera.  Returns whether it was accepted.
        """
        z = np.concatenate([_vec(euler, 3, "euler"), _vec(rates, 3, "rates")])
        var = np.concatenate([_vec(euler_var, 3, "euler_var"), _vec(rate_var, 3, "rate_var")])
        if np.any(var < 0):
            raise PositionEKFError(f"attitude variances must be >= 0 (got {var})")
        accepted, _ = self._fuse("attitude", float(t_s), z, np.diag(var))
        return accepted

    def pin_attitude(self, t_s: float, euler, rates) -> bool:
        """Set the angle and rate states to the attitude level's (no Kalman update, no gate).

        For attitudes where the Euler linearisation and the attitude level's variances are
        not to be trusted (a flip, past ~60 deg of tilt): the translational states keep
        predicting with the model, thrust along the body z of these angles, and the
        attitude follows the gyro-carried estimate rather than the open-loop torque model.
        Stored in the history like a measurement, so a delayed camera replay re-applies it."""
        z = np.concatenate([_vec(euler, 3, "euler"), _vec(rates, 3, "rates")])
        accepted, _ = self._fuse("pin", float(t_s), z, None)
        return accepted

    def update_position(self, t_meas_s: float, position, cov) -> tuple[bool, float]:
        """Camera position of (24) taken at t_meas_s (<= now): fused there, re-predicted to now."""
        z = _vec(position, 3, "position")
        R = np.array(cov, dtype=np.float64)
        if R.shape != (3, 3):
            raise PositionEKFError(f"cov must be 3x3 (got shape {R.shape})")
        return self._fuse("position", float(t_meas_s), z, 0.5 * (R + R.T))

    # ---------------------------------------------------------------- internals
    def _need_init(self):
        if self._x is None:
            raise RuntimeError("PositionEKF: call initialize() first")

    def _propagate(self, x, P, u, h):
        n = max(1, math.ceil(h / self.dt - 1e-6))
        sub = h / n
        for _ in range(n):
            x, F, Q = discretize(x, u, self.vehicle, sub, self._qc)
            P = F @ P @ F.T + Q
        P = 0.5 * (P + P.T)
        x[6] = (x[6] + math.pi) % _TWO_PI - math.pi
        x[8] = (x[8] + math.pi) % _TWO_PI - math.pi
        if x[2] <= 0.0:  # the floor: (1) alone would let a vehicle at idle thrust fall through it
            x[2], x[5] = 0.0, max(x[5], 0.0)
            if u[0] * x[THRUST_SCALE] < self.vehicle.mass_kg * self.vehicle.gravity_m_s2:
                x[3:6] = 0.0  # resting on it: no sliding either
        return x, P

    @staticmethod
    def _model(kind, x, offset):
        """(predicted measurement, H, angle-wrap mask) of one measurement kind."""
        if kind == "position":
            H = np.zeros((3, N_STATE))
            H[:, 0:3] = np.eye(3)
            if offset:
                H[:, 3:6] = offset * np.eye(3)
            return x[POSITION] + offset * x[VELOCITY], H, False
        H = np.zeros((6, N_STATE))
        H[:, 6:12] = np.eye(6)
        return x[6:12].copy(), H, True

    def _innovate(self, kind, x, P, z, R, offset):
        zhat, H, angles = self._model(kind, x, offset)
        y = z - zhat
        if angles:
            y[0:3] = (y[0:3] + math.pi) % _TWO_PI - math.pi
        S = H @ P @ H.T + R
        return y, H, S

    @staticmethod
    def _correct(x, P, y, H, S_inv, R):
        """Joseph-form correction (18)-(20)."""
        K = P @ H.T @ S_inv
        x = x + K @ y
        IKH = np.eye(N_STATE) - K @ H
        P = IKH @ P @ IKH.T + K @ R @ K.T
        x[6] = (x[6] + math.pi) % _TWO_PI - math.pi
        x[8] = (x[8] + math.pi) % _TWO_PI - math.pi
        x[THRUST_SCALE] = min(max(x[THRUST_SCALE], THRUST_SCALE_LIMITS[0]), THRUST_SCALE_LIMITS[1])
        return x, 0.5 * (P + P.T)

    def _apply(self, x, P, meas):
        kind, z, R, offset = meas
        if kind == "pin":
            x = x.copy()
            x[6:12] = z
            x[6] = (x[6] + math.pi) % _TWO_PI - math.pi
            x[8] = (x[8] + math.pi) % _TWO_PI - math.pi
            return x, P
        y, H, S = self._innovate(kind, x, P, z, R, offset)
        return self._correct(x, P, y, H, np.linalg.inv(S), R)

    def _reject(self, kind, reason, nis=math.nan):
        self._counts[kind][reason] += 1
        self.last_nis[kind] = nis
        return False, nis

    def _fuse(self, kind, t_meas, z, R):
        self._need_init()
        if not (math.isfinite(t_meas) and np.all(np.isfinite(z)) and (R is None or np.all(np.isfinite(R)))):
            return self._reject(kind, "invalid")
        if t_meas > self._t + self._eps:
            return self._reject(kind, "future")
        if t_meas < self._t - self.params.max_delay_s - self._eps or t_meas < self._hist[0].t - self._eps:
            return self._reject(kind, "too_old")
        # node nearest not after t_meas
        j = len(self._hist) - 1
        while self._hist[j].t > t_meas + self._eps:
            j -= 1
        node = self._hist[j]
        offset = t_meas - node.t
        if offset <= self._eps:
            offset = 0.0
        last = j == len(self._hist) - 1
        if last:
            x, P = self._x, self._P
        else:
            x, P = node.x.copy(), node.P.copy()
            for meas in node.meas:
                x, P = self._apply(x, P, meas)
        if kind == "pin":
            nis = math.nan
            x, P = self._apply(x, P, (kind, z, None, offset))
            node.meas.append((kind, z.copy(), None, offset))
        else:
            y, H, S = self._innovate(kind, x, P, z, R, offset)
            try:
                S_inv = np.linalg.inv(S)
                nis = float(y @ S_inv @ y)
            except np.linalg.LinAlgError:
                return self._reject(kind, "invalid")
            if not math.isfinite(nis) or nis < 0:
                return self._reject(kind, "invalid")
            if nis > self._gate[len(z)]:
                return self._reject(kind, "gate", nis)
            x, P = self._correct(x, P, y, H, S_inv, R)
            node.meas.append((kind, z.copy(), R.copy(), offset))
        # re-run the predictions to now with the stored inputs and measurements
        for k in range(j + 1, len(self._hist)):
            nk = self._hist[k]
            x, P = self._propagate(x, P, nk.u, nk.t - self._hist[k - 1].t)
            nk.x, nk.P = x.copy(), P.copy()
            for meas in nk.meas:
                x, P = self._apply(x, P, meas)
        self._x, self._P = x, P
        self._counts[kind]["accepted"] += 1
        self.last_nis[kind] = nis
        return True, nis


def _vec(v, n: int, name: str) -> np.ndarray:
    a = np.array(v, dtype=np.float64).reshape(-1)
    if a.shape != (n,):
        raise PositionEKFError(f"{name} must have {n} elements (got {np.shape(v)})")
    return a


class LaggedMotorInput:
    """The EKF's input over a step: the mean rotor forces, through the motors' first-order
    lag, of the commands as they were sent (each held from its time stamp to the next).

    The motor driver commands at 400 Hz; the filter steps at 100 Hz. Taking only the latest
    command, lagged over the whole step, puts the force of the step's end on all of it:
    through a flip the rotor forces swing by ~6 N within 60 ms, ~0.5 N (0.6 m/s^2) off
    for half a step at a time. The mean of the lagged force over each held command is
    exact for a held command: c + (f0 - c) (tau / h) (1 - exp(-h / tau))."""

    def __init__(self, time_constant_s: float):
        if not (math.isfinite(time_constant_s) and time_constant_s > 0):
            raise PositionEKFError(f"time_constant_s must be > 0 (got {time_constant_s!r})")
        self.tau = float(time_constant_s)
        self.forces = np.zeros(4)   # rotor forces at self.t
        self.command = np.zeros(4)  # the command held since self.t
        self.t: float | None = None
        self._pending: list[tuple[float, np.ndarray]] = []  # commands stamped after self.t

    def add(self, t_s: float, command_n) -> None:
        """A command sent at t_s (held from then until the next). One older than the
        forces already integrated is taken to hold from their time (it cannot be undone)."""
        c = np.asarray(command_n, dtype=np.float64).reshape(4)
        if self.t is None:
            self.t, self.forces, self.command = float(t_s), c.copy(), c
        elif t_s <= self.t:
            self.command = c
        else:
            self._pending.append((float(t_s), c))

    def mean_to(self, t_s: float) -> np.ndarray:
        """Mean rotor forces (4,) over [self.t, t_s]; advances to t_s. Commands stamped at or
        after t_s wait for the next step (a command sent at t_s acts from t_s on)."""
        if self.t is None or t_s <= self.t:
            return self.forces.copy()
        self._pending.sort(key=lambda e: e[0])
        total = np.zeros(4)
        start = self.t
        while True:
            end = t_s
            if self._pending and self._pending[0][0] < t_s:
                end = self._pending[0][0]
            h = end - self.t
            if h > 0.0:
                decay = math.exp(-h / self.tau)
                c, f0 = self.command, self.forces
                total += h * (c + (f0 - c) * (self.tau / h) * (1.0 - decay))
                self.forces = motor_forces_update(f0, c, h, self.tau)
                self.t = end
            if end >= t_s:
                break
            self.command = self._pending.pop(0)[1]
        return total / (t_s - start)
