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
state, the thrust scale s (:class:`PositionEKF`): the model runs with s u1; and a 14th
and 15th, the horizontal disturbance acceleration d (the wind's pull), added to v'.

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
ahead of the filter's time are refused and counted.  Each node also keeps its
posterior (after its measurements), which is what re-applying them to its prior
gives: a delayed measurement starts from it.  The predictions after a measurement fused
in the past, and a new prediction, are not run at once: the nodes from there on are
marked stale and run when something needs them (the state read, a measurement at a stale
node, the next prediction), in the same order on the same numbers, so with the same
results.  In flight the attitude state arrives 5 ms after the position level's run and is
fused at the node before, and a camera fix six nodes back: run at once, the new prediction
ran twice a step, three times with a fix.

The stamps are trusted as they come. Whether they should be is watched outside the filter
(flight/estimation/camera_delay.py): each camera fix leaves its innovation, the velocity at
its time and its gain in ``camera_fix``, from which the position level fits the offset of the
fixes' real time from their stamps, and fuses them at their stamp less it once it is sure.

Cost: at this size numpy's per-call overhead, not the flops, is the price, so the
mean, f and the Jacobian run in plain floats (:func:`_step`, term for term the
expressions of :func:`f`, :func:`rk4_step` and :func:`jacobian_f`), products with an
H that only selects states are taken as P's blocks and columns (exactly what the
products with the 0/1 matrix give), and the chi-square gate comes from a closed form
rather than scipy.stats (~0.3 s of import).  The unit tests hold the filter to an
all-numpy form of it (tests/unit/flight/estimation/test_position_ekf.py, ``_RefEKF``), and
to the filter before the stale nodes bit for bit (bench/support/position_ekf_reference.py;
bench/position_ekf.py times the position level's run against it, replaying a flight log).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from flight import motor_model
from flight.param import Declared, declared
from flight.quat import wrap_angle_float
from flight.vehicle import Vehicle

__all__ = [
    "PositionEKFError", "PositionEKFParams", "PositionEKF",
    "f", "jacobian_f", "rk4_step", "discretize",
    "POSITION", "VELOCITY", "EULER", "RATES", "THRUST_SCALE", "DISTURBANCE", "ACCEL_BIAS", "N_MODEL", "N_STATE",
    "LaggedMotorInput",
]

N_MODEL = 12       # the states of (1)-(2)
THRUST_SCALE = 12  # the filter's 13th state (see PositionEKF)
DISTURBANCE = slice(13, 15)   # its 14th and 15th: the horizontal disturbance acceleration (see PositionEKF)
ACCEL_BIAS = slice(15, 17)    # its 16th and 17th: the accelerometer's bias on body x and y (update_drag)
N_STATE = 17
POSITION = slice(0, 3)
VELOCITY = slice(3, 6)
EULER = slice(6, 9)
RATES = slice(9, 12)
THRUST_SCALE_LIMITS = (0.5, 2.0)  # a physical bound: beyond it the vehicle cannot hover anyway

_KINDS = ("attitude", "position", "pin", "drag")
_REASONS = ("gate", "too_old", "future", "invalid")


class PositionEKFError(ValueError):
    """Bad parameters or malformed inputs to the position EKF."""


# --------------------------------------------------------------------------- #
# Parameters
# --------------------------------------------------------------------------- #
@dataclass(frozen=True)
class PositionEKFParams(Declared):
    """Noise, gate and history settings (the position service's `ekf` table).

    Process noise is given as continuous white-noise spectral densities per
    state group (``Q_d = Q_c dt``), so it does not change meaning with dt.
    """

    error = PositionEKFError

    # the kinematics p' = v are exact; a small floor for time-stamp jitter and integration error
    q_position_m2_s: float = declared(1e-6, "m^2/s", 0.0, doc="process noise density of the position")
    # unmodelled accelerations: thrust error (motor lag 20 ms, battery sag, the PWM map), drag
    # error, draughts; indoor flight (000 flies indoors under a camera). 0.005 m^2/s^3 is e.g. a
    # 0.1 m/s^2 (1 % of g) disturbance with a 0.25 s correlation time (2 sigma^2 tau); it lets
    # the velocity drift by 0.1 m/s and the position by 0.08 m over a 2 s camera outage (1
    # sigma). A slow thrust bias is followed through the camera (a few mm of lag at 20 Hz).
    q_velocity_m2_s3: float = declared(0.02, "m^2/s^3", 0.0,
                                       doc="process noise density of the velocity (unmodelled accelerations)")
    # the ZYX kinematics are exact; small floor
    q_angles_rad2_s: float = declared(1e-6, "rad^2/s", 0.0, doc="process noise density of the angles")
    # unmodelled torques: the 20 ms motor lag at the attitude loop's 16 rad/s bandwidth, prop
    # imbalance, inertia error. 0.5 rad^2/s^3 gives 0.07 rad/s of rate uncertainty per 10 ms step,
    # above the attitude level's 0.02 rad/s, so the rate states follow that level.
    q_rates_rad2_s3: float = declared(0.5, "rad^2/s^3", 0.0,
                                      doc="process noise density of the body rates (unmodelled torques)")
    # chi-square gate on the innovation's NIS (Mahalanobis distance squared); 0.999 refuses a fix
    # more than ~4 sigma away for 3 dof (threshold 16.3)
    gate_probability: float = declared(0.999, "", 0.0, 1.0, min_exclusive=True,
                                       doc="chi-square gate on a fix's innovation (NIS); 1: no gate")
    # 0.3 s covers twice the camera's worst delay (150 ms)
    max_delay_s: float = declared(0.3, "s", 0.0, doc="history kept for delayed measurements (a camera fix older "
                                                     "than this is dropped)")
    # init_std_*: the position from a first camera fix, at rest, level within a few degrees
    init_std_position_m: float = declared(0.05, "m", 0.0, min_exclusive=True,
                                          doc="initial position std (1 sigma)")
    init_std_velocity_m_s: float = declared(0.1, "m/s", 0.0, min_exclusive=True,
                                            doc="initial velocity std (1 sigma)")
    init_std_angles_rad: float = declared(0.05, "rad", 0.0, min_exclusive=True, doc="initial angles std (1 sigma)")
    init_std_rates_rad_s: float = declared(0.05, "rad/s", 0.0, min_exclusive=True,
                                           doc="initial body rates std (1 sigma)")
    # real collective force per commanded newton: battery sag and a payload change it over
    # seconds to minutes; 1e-4 /s lets it move 0.03 in 10 s (1 sigma)
    q_thrust_scale_1_s: float = declared(1e-4, "1/s", 0.0, doc="random walk density of the thrust scale")
    # within 10 % of the airframe file's (mass, payload, rotor wear)
    init_std_thrust_scale: float = declared(0.1, "", 0.0, min_exclusive=True,
                                            doc="initial thrust scale std (1 sigma)")

    # the wind's pull on the airframe (drag of the air speed, not of the ground speed: 2 m/s on
    # the x250 is 0.5 m/s^2), a payload's, a tilt bias: a random walk, so the model's prediction
    # between fixes carries it instead of the gate refusing every fix once it has built up.
    # 0.01 (m/s^2)^2/s lets it move 0.3 m/s^2 in 10 s (1 sigma): a gust front, not the
    # turbulence's fast part (that stays in q_velocity)
    q_disturbance_m2_s5: float = declared(0.01, "m^2/s^5", 0.0,
                                          doc="random walk density of the horizontal disturbance acceleration "
                                              "(wind, payload pull)")
    # a 2 m/s wind on the ground at start is 0.5 m/s^2 on the x250
    init_std_disturbance_m_s2: float = declared(0.5, "m/s^2", 0.0,
                                                doc="initial horizontal disturbance acceleration std (1 sigma)")

    # the accelerometer's body x and y averaged over a 10 ms step: its noise (0.01 m/s^2 a sample)
    # is small against what the linear drag leaves out (rotor drag grows with the rotors'
    # speed, the air's pull on a tilted body): a 0.1 m/s^2 std, a fifth of 2 m/s of wind's pull
    r_drag_m2_s4: float = declared(0.01, "m^2/s^4", 0.0, min_exclusive=True,
                                   doc="variance of the accelerometer's body x and y as a measurement of the "
                                       "air's force (update_drag, with position.wind_estimation)")

    # the accelerometer's bias on body x and y, which the drag reading would otherwise take for a
    # wind, and a slow walk; learnt where the camera says the vehicle does not accelerate as the
    # reading would. 0.1 m/s^2 (PX4's EKF2_ABIAS_INIT is 0.2) learns the simulator's (0.01 m/s^2,
    # 1 sigma) within the hover's first seconds: at 0.03 still air held 4.5 mm where 2.8 without
    init_std_accel_bias_m_s2: float = declared(0.1, "m/s^2", 0.0,
                                               doc="initial accelerometer bias std on body x and y (1 sigma; "
                                                   "with the drag fusion)")
    q_accel_bias_m2_s5: float = declared(1e-6, "m^2/s^5", 0.0,
                                         doc="random walk density of the accelerometer bias on body x and y")

    @property
    def process_noise_density(self) -> np.ndarray:
        """Diagonal of Q_c (N_STATE,)."""
        return np.r_[np.repeat([self.q_position_m2_s, self.q_velocity_m2_s3,
                                self.q_angles_rad2_s, self.q_rates_rad2_s3], 3), self.q_thrust_scale_1_s,
                     self.q_disturbance_m2_s5, self.q_disturbance_m2_s5,
                     self.q_accel_bias_m2_s5, self.q_accel_bias_m2_s5]

    @property
    def initial_covariance(self) -> np.ndarray:
        return np.diag(np.r_[np.repeat([self.init_std_position_m, self.init_std_velocity_m_s,
                                        self.init_std_angles_rad, self.init_std_rates_rad_s], 3),
                             self.init_std_thrust_scale, self.init_std_disturbance_m_s2,
                             self.init_std_disturbance_m_s2, self.init_std_accel_bias_m_s2,
                             self.init_std_accel_bias_m_s2] ** 2)


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
    if x.shape != (N_MODEL,) or u.shape != (4,):
        raise PositionEKFError(f"rk4_step: x must have {N_MODEL} elements and u 4 "
                               f"(got {x.shape}, {u.shape})")
    x_next, _ = _step(x.tolist(), *u.tolist(), float(dt), _constants(vehicle), jacobian=False)
    return np.array(x_next)


def discretize(x, u, vehicle: Vehicle, dt: float, q_density=None):
    """One step: (x_next by RK4, F_d = I + A + A^2/2 with A = J dt, Q_d = diag(q_density) dt).

    x has the 12 states of (1)-(2), or the filter's 15 with the thrust scale s and the
    horizontal disturbance acceleration d: then the model runs with u1 scaled by s and
    d added to the horizontal acceleration, and J gets the column d v' / d s = (u1 / m) R e3
    and the unit entries d v'_xy / d d (s and d themselves are random walks)."""
    x = np.asarray(x, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    n = x.shape[0]
    if x.shape not in ((N_MODEL,), (N_STATE,)) or u.shape != (4,):
        raise PositionEKFError(f"discretize: x must have {N_MODEL} or {N_STATE} elements and u 4 "
                               f"(got {x.shape}, {u.shape})")
    xs = x.tolist()
    u1, u2, u3, u4 = u.tolist()
    dt = float(dt)
    if n == N_MODEL:
        x_next, vals = _step(xs, u1, u2, u3, u4, dt, _constants(vehicle))
    else:
        x_next, vals = _step(xs, u1 * xs[THRUST_SCALE], u2, u3, u4, dt, _constants(vehicle), u_col=u1)
        x_next += xs[N_MODEL:]
    F = _transition(vals, n)
    Q = None if q_density is None else np.diag(np.asarray(q_density, dtype=np.float64) * dt)
    return np.array(x_next), F, Q


# The step's arithmetic in plain floats: at the filter's size numpy's per-call overhead,
# not the flops, is the cost.  _step is f, rk4_step and jacobian_f above term for term (the
# same expressions in the same order, so the same roundings); the unit tests hold it to them.
def _constants(vehicle: Vehicle) -> tuple:
    m = vehicle.mass_kg
    ixx, iyy, izz = vehicle.inertia_kg_m2
    return (m, vehicle.drag_n_per_m_s / m, vehicle.gravity_m_s2, ixx, iyy, izz,
            izz - iyy, ixx - izz, iyy - ixx)


# where the non-zero entries of J (row-major) go; the last five only with the filter's states
# (the thrust scale's column, the disturbance's two)
_J_ROWS = (0, 1, 2, 3, 4, 5, 3, 3, 3, 4, 4, 4, 5, 5, 6, 6, 6, 6, 6, 7, 7, 7, 8, 8, 8, 8,
           9, 9, 10, 10, 11, 11, 3, 4, 5, 3, 4)
_J_COLS = (3, 4, 5, 3, 4, 5, 6, 7, 8, 6, 7, 8, 6, 7, 6, 7, 9, 10, 11, 6, 10, 11, 6, 7, 10, 11,
           10, 11, 9, 11, 9, 10, 12, 12, 12, 13, 14)
_J_FLAT = {n: np.array([r * n + c for r, c in zip(_J_ROWS, _J_COLS) if c < n]) for n in (N_MODEL, N_STATE)}
_EYE = {n: np.eye(n) for n in (N_MODEL, N_STATE)}
_J_FLAT_FULL, _EYE_FULL = _J_FLAT[N_STATE], _EYE[N_STATE]


def _step(xs, u1, u2, u3, u4, dt, C, u_col=None, jacobian=True):
    """RK4 step of (1)-(2) from the floats xs[:12] with u held: (x_next as 12 floats,
    the entries of A = J dt at _J_ROWS/_J_COLS, or None).  u1 is the thrust the model
    runs with (s u1 for the filter); u_col, when given (the filter's full state), the
    commanded u1 of the thrust scale's column d v' / d s = (u_col / m) R e3, followed by the
    disturbance's unit columns.  The filter's disturbance xs[13:15], when there, is added
    to the horizontal acceleration (+ 0.0 without it: the same numbers).  Written out stage
    by stage: each stage is f (a .. i its rows 3..11; rows 0..2 are the stage's velocity)."""
    m, k, g, ixx, iyy, izz, dzy, dxz, dyx = C
    sin, cos = math.sin, math.cos
    a = u1 / m
    px, py, pz, vx, vy, vz, r, p, y, wx, wy, wz = xs[:12]
    dx, dy = (xs[13], xs[14]) if len(xs) == N_STATE else (0.0, 0.0)
    hh = 0.5 * dt
    # stage 1, at the start (its sines and cosines serve the Jacobian too)
    sr0, cr0, sp0, cp0, sy0, cy0 = sin(r), cos(r), sin(p), cos(p), sin(y), cos(y)
    tp0 = sp0 / cp0
    q0 = sr0 * wy + cr0 * wz
    a1 = a * (sy0 * sr0 + cy0 * cr0 * sp0) - k * vx + dx
    b1 = a * (-cy0 * sr0 + sy0 * cr0 * sp0) - k * vy + dy
    c1 = a * (cr0 * cp0) - k * vz - g
    d1 = wx + tp0 * q0
    e1 = cr0 * wy - sr0 * wz
    f1 = q0 / cp0
    g1 = (u2 - dzy * wy * wz) / ixx
    h1 = (u3 - dxz * wz * wx) / iyy
    i1 = (u4 - dyx * wx * wy) / izz
    # stage 2 at x + dt/2 k1
    vx2, vy2, vz2 = vx + hh * a1, vy + hh * b1, vz + hh * c1
    r2, p2, y2 = r + hh * d1, p + hh * e1, y + hh * f1
    wx2, wy2, wz2 = wx + hh * g1, wy + hh * h1, wz + hh * i1
    sr, cr, sp, cp, sy, cy = sin(r2), cos(r2), sin(p2), cos(p2), sin(y2), cos(y2)
    tp = sp / cp
    q = sr * wy2 + cr * wz2
    a2 = a * (sy * sr + cy * cr * sp) - k * vx2 + dx
    b2 = a * (-cy * sr + sy * cr * sp) - k * vy2 + dy
    c2 = a * (cr * cp) - k * vz2 - g
    d2 = wx2 + tp * q
    e2 = cr * wy2 - sr * wz2
    f2 = q / cp
    g2 = (u2 - dzy * wy2 * wz2) / ixx
    h2 = (u3 - dxz * wz2 * wx2) / iyy
    i2 = (u4 - dyx * wx2 * wy2) / izz
    # stage 3 at x + dt/2 k2
    vx3, vy3, vz3 = vx + hh * a2, vy + hh * b2, vz + hh * c2
    r3, p3, y3 = r + hh * d2, p + hh * e2, y + hh * f2
    wx3, wy3, wz3 = wx + hh * g2, wy + hh * h2, wz + hh * i2
    sr, cr, sp, cp, sy, cy = sin(r3), cos(r3), sin(p3), cos(p3), sin(y3), cos(y3)
    tp = sp / cp
    q = sr * wy3 + cr * wz3
    a3 = a * (sy * sr + cy * cr * sp) - k * vx3 + dx
    b3 = a * (-cy * sr + sy * cr * sp) - k * vy3 + dy
    c3 = a * (cr * cp) - k * vz3 - g
    d3 = wx3 + tp * q
    e3 = cr * wy3 - sr * wz3
    f3 = q / cp
    g3 = (u2 - dzy * wy3 * wz3) / ixx
    h3 = (u3 - dxz * wz3 * wx3) / iyy
    i3 = (u4 - dyx * wx3 * wy3) / izz
    # stage 4 at x + dt k3
    vx4, vy4, vz4 = vx + dt * a3, vy + dt * b3, vz + dt * c3
    r4, p4, y4 = r + dt * d3, p + dt * e3, y + dt * f3
    wx4, wy4, wz4 = wx + dt * g3, wy + dt * h3, wz + dt * i3
    sr, cr, sp, cp, sy, cy = sin(r4), cos(r4), sin(p4), cos(p4), sin(y4), cos(y4)
    tp = sp / cp
    q = sr * wy4 + cr * wz4
    a4 = a * (sy * sr + cy * cr * sp) - k * vx4 + dx
    b4 = a * (-cy * sr + sy * cr * sp) - k * vy4 + dy
    c4 = a * (cr * cp) - k * vz4 - g
    d4 = wx4 + tp * q
    e4 = cr * wy4 - sr * wz4
    f4 = q / cp
    g4 = (u2 - dzy * wy4 * wz4) / ixx
    h4 = (u3 - dxz * wz4 * wx4) / iyy
    i4 = (u4 - dyx * wx4 * wy4) / izz
    d6 = dt / 6.0
    x_next = [px + d6 * (vx + 2.0 * vx2 + 2.0 * vx3 + vx4),
              py + d6 * (vy + 2.0 * vy2 + 2.0 * vy3 + vy4),
              pz + d6 * (vz + 2.0 * vz2 + 2.0 * vz3 + vz4),
              vx + d6 * (a1 + 2.0 * a2 + 2.0 * a3 + a4),
              vy + d6 * (b1 + 2.0 * b2 + 2.0 * b3 + b4),
              vz + d6 * (c1 + 2.0 * c2 + 2.0 * c3 + c4),
              r + d6 * (d1 + 2.0 * d2 + 2.0 * d3 + d4),
              p + d6 * (e1 + 2.0 * e2 + 2.0 * e3 + e4),
              y + d6 * (f1 + 2.0 * f2 + 2.0 * f3 + f4),
              wx + d6 * (g1 + 2.0 * g2 + 2.0 * g3 + g4),
              wy + d6 * (h1 + 2.0 * h2 + 2.0 * h3 + h4),
              wz + d6 * (i1 + 2.0 * i2 + 2.0 * i3 + i4)]
    if not jacobian:
        return x_next, None
    # J (22) at the step's start, times dt (jacobian_f's entries, in _J_ROWS/_J_COLS order)
    sr, cr, sp, cp, sy, cy, tp, q = sr0, cr0, sp0, cp0, sy0, cy0, tp0, q0
    qd = cr * wy - sr * wz
    cp2 = cp * cp
    kdt = -k * dt
    vals = [dt, dt, dt, kdt, kdt, kdt,
            a * (sy * cr - cy * sr * sp) * dt, a * (cy * cr * cp) * dt, a * (cy * sr - sy * cr * sp) * dt,
            a * (-cy * cr - sy * sr * sp) * dt, a * (sy * cr * cp) * dt, a * (sy * sr + cy * cr * sp) * dt,
            -a * sr * cp * dt, -a * cr * sp * dt,
            tp * qd * dt, q / cp2 * dt, dt, sr * tp * dt, cr * tp * dt,
            -q * dt, cr * dt, -sr * dt,
            qd / cp * dt, q * sp / cp2 * dt, sr / cp * dt, cr / cp * dt,
            -dzy * wz / ixx * dt, -dzy * wy / ixx * dt,
            -dxz * wz / iyy * dt, -dxz * wx / iyy * dt,
            -dyx * wy / izz * dt, -dyx * wx / izz * dt]
    if u_col is not None:
        b = u_col / m
        vals += (b * (sy * sr + cy * cr * sp) * dt, b * (-cy * sr + sy * cr * sp) * dt, b * (cr * cp) * dt, dt, dt)
    return x_next, vals


def _transition(vals, n: int) -> np.ndarray:
    """F_d = I + A + A^2 / 2 from the entries of A (see _step)."""
    A = np.zeros((n, n))
    A.put(_J_FLAT[n], vals)
    AA = A.dot(A)   # ndarray.dot: the product @ makes, with less overhead per call
    AA *= 0.5
    F = _EYE[n] + A
    F += AA
    return F


# --------------------------------------------------------------------------- #
# The filter
# --------------------------------------------------------------------------- #
class _Node:
    """One history entry: time, input that led here, prior (x, P) here, accepted measurements,
    and the posterior (x, P) after them.

    The posterior is what re-applying the measurements to the prior gives (the same
    arithmetic on the same numbers), kept so that a delayed measurement fused here starts
    from it.  x and P are shared with the filter, never written in place (every step
    makes new ones); at a stale node (PositionEKF._current) they are out of date, or None."""

    __slots__ = ("t", "u", "x", "P", "meas", "post")

    def __init__(self, t, u, x, P):
        self.t = t
        self.u = u   # [u1, u2, u3, u4] as floats (None for the first node)
        self.x = x   # the filter's states as floats
        self.P = P
        self.meas: list[tuple] = []  # (kind, z, R, offset_s), in the order applied
        self.post = (x, P)


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

    Its 14th and 15th elements, d (DISTURBANCE), are a horizontal acceleration the model
    lacks, added to (1)'s: above all the wind's pull (the drag of the air speed, where the
    model has the ground speed's: 0.5 m/s^2 on the x250 in a 2 m/s wind), a random walk the
    camera's positions make observable. Without it a wind's pull built up between fixes until
    the gate refused them. With `position.wind_estimation` the position level feeds it
    forward as the law's disturbance (PX4's EKF2 estimates the wind for the same drag);
    without, its noise and initial variance are 0 and it stays 0. Its 16th and 17th, b
    (ACCEL_BIAS), are the accelerometer's bias on body x and y, which only the drag reading
    (update_drag) sees: without it a 0.026 m/s^2 bias read as a wind's pull in still air.

    One filter is for one thread: its steps share a scratch array.
    """

    def __init__(self, vehicle: Vehicle, params: PositionEKFParams | None = None, dt: float = 0.01):
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise PositionEKFError(f"dt must be a positive number (got {dt!r})")
        self.vehicle = vehicle
        self.params = params if params is not None else PositionEKFParams()
        self.dt = float(dt)
        self._qc = self.params.process_noise_density
        self._Qc = np.diag(self._qc)   # Q_d = _Qc dt
        self._Qd: dict[float, np.ndarray] = {}
        self._A = np.zeros((N_STATE, N_STATE))  # A = J dt (_propagate's scratch)
        # I - K H of an H selecting states from the first one, per first state (_correct's
        # scratch): (I - K H, its columns that K replaces, its transpose, those columns of I)
        self._ikh = {}
        for first, n in ((6, 6), (0, 3)):
            ikh = np.eye(N_STATE)
            self._ikh[first] = (ikh, ikh[:, first:first + n], ikh.T, _EYE_FULL[:, first:first + n].copy())
        p = self.params.gate_probability
        self._gate = {n: (math.inf if p >= 1.0 else _chi2_ppf(p, n)) for n in (2, 3, 6)}
        self._eps = 1e-6 * self.dt
        self._x: list | None = None  # the states as floats: the step's arithmetic is in floats
        self._P: np.ndarray | None = None
        # the first node of the history whose prior and posterior are out of date (None: none
        # is; then self._x, self._P are the newest node's posterior): see _current
        self._stale: int | None = None
        self._t: float | None = None
        self._hist: list[_Node] = []
        self._counts = {k: {"accepted": 0, **{r: 0 for r in _REASONS}} for k in _KINDS}
        self.last_nis = {k: math.nan for k in _KINDS}
        # the last camera fix's (innovation (3,), velocity at its time (3 floats), gain K (N_STATE x 3)
        # or None when gated), for the delay estimator (flight/estimation/camera_delay.py); None
        # when the fix was refused before its innovation was formed (invalid, too old, future)
        self.camera_fix: tuple | None = None
        self._K = None   # the gain of the last correction (_correct)

    @property
    def vehicle(self) -> Vehicle:
        return self._vehicle

    @vehicle.setter
    def vehicle(self, vehicle: Vehicle) -> None:
        if getattr(self, "_stale", None) is not None:
            self._current()   # the predictions made before run with the vehicle they were made with
        self._vehicle = vehicle
        self._C = _constants(vehicle)
        self._weight = vehicle.mass_kg * vehicle.gravity_m_s2
        self._drag_per_mass = vehicle.drag_n_per_m_s / vehicle.mass_kg

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
        self._current()
        return np.array(self._x)

    @property
    def P(self) -> np.ndarray:
        self._current()
        return self._P.copy()

    @property
    def position(self) -> np.ndarray:
        self._current()
        return np.array(self._x[POSITION])

    @property
    def velocity(self) -> np.ndarray:
        self._current()
        return np.array(self._x[VELOCITY])

    @property
    def euler(self) -> np.ndarray:
        self._current()
        return np.array(self._x[EULER])

    @property
    def rates(self) -> np.ndarray:
        self._current()
        return np.array(self._x[RATES])

    @property
    def thrust_scale(self) -> float:
        self._current()
        return self._x[THRUST_SCALE]

    @property
    def position_cov(self) -> np.ndarray:
        self._current()
        return self._P[POSITION, POSITION].copy()

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
        x[6] = wrap_angle_float(float(x[6]))
        x[8] = wrap_angle_float(float(x[8]))
        P = self.params.initial_covariance if P0 is None else np.array(P0, dtype=np.float64)
        if P.shape != (N_STATE, N_STATE) or not np.all(np.isfinite(P)):
            raise PositionEKFError(f"P0 must be a finite {N_STATE}x{N_STATE} matrix")
        self._t = float(t_s)
        self._x, self._P = x.tolist(), 0.5 * (P + P.T)
        self._hist = [_Node(self._t, None, self._x, self._P)]
        self._stale = None

    def reset_position(self, position, cov, velocity_std_m_s: float = 1.0, age_s: float = 0.0) -> None:
        """Restart the translational states at a camera fix, keeping the attitude:
        the way out when the gate has refused every fix for a while (the filter
        has lost the vehicle and would otherwise never take a fix again). age_s: how old
        the fix is (its exposure before the filter's time): the vehicle has moved since by
        up to velocity_std_m_s x age_s, so the position's variance grows by that (held at
        the camera's own, the next fixes of a moving vehicle were gated again: a loop of
        resets). The disturbance starts again from 0 (one learnt while losing the vehicle is
        suspect: kept, a turbulent take-off's crashed) with the variance it had (at its initial
        one the first fixes after a restart moved it wildly: the delay-step flight diverged)."""
        self._current()
        x, P = np.array(self._x), self._P.copy()
        x[POSITION] = _vec(position, 3, "position")
        x[DISTURBANCE] = 0.0
        P[:6, :] = 0.0
        P[:, :6] = 0.0
        P[:3, :3] = np.array(cov, dtype=np.float64).reshape(3, 3) + np.eye(3) * (velocity_std_m_s * max(age_s, 0.0))**2
        P[3:6, 3:6] = np.eye(3) * velocity_std_m_s**2
        self._x, self._P = x.tolist(), P
        self._hist = [_Node(self._t, None, self._x, P)]
        self._stale = None

    def predict(self, t_s: float, u) -> None:
        """Advance to t_s with u = [u1 (N), u2, u3, u4 (N m)] held; record the step."""
        self._need_init()
        u = _floats(u, 4, "u")
        if not all(map(math.isfinite, u)):
            raise PositionEKFError(f"u must be finite (got {np.array(u)})")
        t = float(t_s)
        h = t - self._t
        if not h > self._eps:
            raise PositionEKFError(f"predict: time must advance (t={self._t}, t_s={t_s})")
        if self._stale is not None:
            self._current()
        self._t = t
        hist = self._hist
        # the new node's prior is computed when something needs it (_current): in flight the
        # attitude state comes 5 ms late and is fused at the node before, which changes this
        # prior's starting point before anything reads it
        hist.append(_Node(t, u, None, None))
        new = len(hist) - 1
        # keep the newest node at or before (now - max_delay) and everything after it
        horizon = t - self.params.max_delay_s + self._eps
        drop = 0
        while drop + 1 < len(hist) and hist[drop + 1].t <= horizon:
            drop += 1
        if drop == new:   # only the new node stays: its prior needs its predecessor, now
            self._stale = new
            self._current()
        else:
            self._stale = new - drop
        if drop:
            del hist[:drop]

    def update_attitude(self, t_s: float, euler, rates, euler_var, rate_var) -> bool:
        """Rows 4..9 of (24): angles and body rates from the attitude level; gated, yaw wrapped.

        Normally t_s is the filter's time (the attitude level compensates its own
        delay with (15)); an older t_s within the history is fused there like the
        camera.  Returns whether it was accepted.
        """
        z = _floats(euler, 3, "euler") + _floats(rates, 3, "rates")
        var = _floats(euler_var, 3, "euler_var") + _floats(rate_var, 3, "rate_var")
        if any(v < 0 for v in var):
            raise PositionEKFError(f"attitude variances must be >= 0 (got {np.array(var)})")
        accepted, _ = self._fuse("attitude", float(t_s), z, None, var)
        return accepted

    def pin_attitude(self, t_s: float, euler, rates) -> bool:
        """Set the angle and rate states to the attitude level's (no Kalman update, no gate).

        For attitudes where the Euler linearisation and the attitude level's variances are
        not to be trusted (a flip, past ~60 deg of tilt): the translational states keep
        predicting with the model, thrust along the body z of these angles, and the
        attitude follows the gyro-carried estimate rather than the open-loop torque model.
        Stored in the history like a measurement, so a delayed camera replay re-applies it."""
        z = _floats(euler, 3, "euler") + _floats(rates, 3, "rates")
        accepted, _ = self._fuse("pin", float(t_s), z, None)
        return accepted

    def update_position(self, t_meas_s: float, position, cov) -> tuple[bool, float]:
        """Camera position of (24) taken at t_meas_s (<= now): fused there, re-predicted to now."""
        self.camera_fix = None
        z = _vec(position, 3, "position")
        R = np.array(cov, dtype=np.float64)
        if R.shape != (3, 3):
            raise PositionEKFError(f"cov must be 3x3 (got shape {R.shape})")
        return self._fuse("position", float(t_meas_s), z, 0.5 * (R + R.T))

    def update_drag(self, t_s: float, accel_xy, var) -> tuple[bool, float]:
        """The accelerometer's body x and y (m/s^2, averaged up to t_s) as a measurement of the
        air's force on the airframe: h = [R' (-(c / m) v + (d, 0))]_xy + b, b the accelerometer's
        bias (ACCEL_BIAS). The thrust is along body z and drops out, so this observes the wind's
        pull d where the camera sees only the position it moves, and before the first fix (a
        take-off in a gust); PX4's EKF2 fuses the same (multirotor drag fusion). var: per axis,
        m^2/s^4. Gated like a fix; returns (accepted, NIS)."""
        z = _floats(accel_xy, 2, "accel_xy")
        var = _floats(var, 2, "var")
        if any(v <= 0 for v in var):
            raise PositionEKFError(f"drag variances must be > 0 (got {np.array(var)})")
        return self._fuse("drag", float(t_s), z, np.diag(var))

    # ---------------------------------------------------------------- internals
    def _need_init(self):
        if self._x is None:
            raise RuntimeError("PositionEKF: call initialize() first")

    def _current(self, stop: int | None = None) -> None:
        """Bring the history's nodes up to (not including) index stop, all by default, up to
        date: re-run the predictions from the first stale node with the stored inputs and
        re-apply the stored measurements. A measurement fused in the past, or a prediction,
        only marks the nodes after it stale; this runs once whatever came in meanwhile, with
        the same arithmetic in the same order as running it at each (so the same numbers)."""
        if self._x is None:
            self._need_init()
        k = self._stale
        if k is None:
            return
        hist = self._hist
        if stop is None or stop >= len(hist):
            stop = len(hist)
        prev = hist[k - 1]
        x, P = prev.post
        t_prev = prev.t
        propagate, apply = self._propagate, self._apply
        for nk in hist[k:stop]:
            x, P = propagate(x, P, nk.u, nk.t - t_prev)
            t_prev = nk.t
            nk.x, nk.P = x, P
            for meas in nk.meas:
                x, P = apply(x, P, meas)
            nk.post = (x, P)
        if stop == len(hist):
            self._stale = None
            self._x, self._P = x, P
        else:
            self._stale = stop

    def _propagate(self, x, P, u, h):
        """(x, P) after h with u (4 floats) held: n RK4 steps of at most dt, F P F' + Q each."""
        v = h / self.dt - 1e-6
        n = 1 if v <= 1.0 else math.ceil(v)
        sub = h / n
        Qd = self._Qd.get(sub)  # Q_d = diag(q_c) dt; a replay meets its steps' dt again
        if Qd is None:
            if len(self._Qd) > 64:
                self._Qd.clear()
            Qd = self._Qd[sub] = self._Qc * sub
        xs = x
        u1, u2, u3, u4 = u
        s, dx, dy, bx, by = xs[THRUST_SCALE], xs[13], xs[14], xs[15], xs[16]
        u1s = u1 * s   # the model runs with s u1 (discretize)
        C = self._C
        for _ in range(n):
            xs, vals = _step(xs, u1s, u2, u3, u4, sub, C, u_col=u1)
            xs += (s, dx, dy, bx, by)
            A = self._A   # _transition, inline; the same entries are written every time
            A.put(_J_FLAT_FULL, vals)
            AA = A.dot(A)
            AA *= 0.5
            F = _EYE_FULL + A
            F += AA
            P = F.dot(P).dot(F.T)
            P += Qd
        Pt = P.T.copy()   # (P + P') / 2 as P' + P, the same sums: a contiguous P' adds faster
        Pt += P
        Pt *= 0.5
        xs[6] = wrap_angle_float(xs[6])
        xs[8] = wrap_angle_float(xs[8])
        if xs[2] <= 0.0:  # the floor: (1) alone would let a vehicle at idle thrust fall through it
            xs[2], xs[5] = 0.0, max(xs[5], 0.0)
            if u1 * s < self._weight:
                xs[3] = xs[4] = xs[5] = 0.0  # resting on it: no sliding either
        return xs, Pt

    def _correct(self, x, P, y, H, S_inv, R, frozen=None):
        """Joseph-form correction (18)-(20).  H is the first state selected (6: the attitude,
        0: the camera at a node's time) where it only selects states: then P H' is P's
        columns and I - K H the identity less K in them, exactly what the products with the
        0/1 matrix give (every other term of those sums is an exact zero), written into a
        scratch identity kept per first state; else a full H (a camera offset, the drag).
        frozen: the states this measurement must not move (a Schmidt "consider" update: their
        gain rows zeroed, the Joseph form keeps P right for any gain)."""
        if H.__class__ is int:
            IKH, cols, IKH_T, eye_cols = self._ikh[H]
            K = P[:, H:H + len(y)].dot(S_inv)
            np.subtract(eye_cols, K, out=cols)
        else:
            K = P.dot(H.T).dot(S_inv)
            if frozen is not None:
                K[frozen] = 0.0
            IKH = _EYE_FULL - K.dot(H)
            IKH_T = IKH.T
        self._K = K
        xs = [a + b for a, b in zip(x, K.dot(y).tolist())]
        xs[6] = wrap_angle_float(xs[6])
        xs[8] = wrap_angle_float(xs[8])
        s = xs[THRUST_SCALE]
        xs[THRUST_SCALE] = THRUST_SCALE_LIMITS[0] if s < THRUST_SCALE_LIMITS[0] else (
            THRUST_SCALE_LIMITS[1] if s > THRUST_SCALE_LIMITS[1] else s)
        P = IKH.dot(P).dot(IKH_T)
        P += K.dot(R).dot(K.T)
        Pt = P.T.copy()   # symmetric: (P + P') / 2, as in _propagate
        Pt += P
        Pt *= 0.5
        return xs, Pt

    def _innovate(self, kind, x, P, z, R, offset):
        """(y, H, S) of a measurement at a node (x: floats); H as _correct takes it."""
        if kind == "attitude":  # h = [angles, rates], the angle innovations wrapped
            z0, z1, z2, z3, z4, z5 = z
            y = np.array((wrap_angle_float(z0 - x[6]), wrap_angle_float(z1 - x[7]), wrap_angle_float(z2 - x[8]),
                          z3 - x[9], z4 - x[10], z5 - x[11]))
            return y, 6, P[6:12, 6:12] + R
        if kind == "drag":  # h = [R' a]_xy + b, a = -(c / m) v + (d, 0): body x and y are R's columns 0 and 1
            r, p, yw = x[6], x[7], x[8]
            sr, cr, sp, cp, sy, cy = math.sin(r), math.cos(r), math.sin(p), math.cos(p), math.sin(yw), math.cos(yw)
            bx = (cy * cp, sy * cp, -sp)
            by = (cy * sp * sr - sy * cr, sy * sp * sr + cy * cr, cp * sr)
            k = self._drag_per_mass
            a = (-k * x[3] + x[13], -k * x[4] + x[14], -k * x[5])
            H = np.zeros((2, N_STATE))
            H[0, 3:6] = [-k * c for c in bx]
            H[1, 3:6] = [-k * c for c in by]
            H[0, 13:15] = bx[:2]
            H[1, 13:15] = by[:2]
            H[0, 15] = H[1, 16] = 1.0
            y = np.array((z[0] - (bx[0] * a[0] + bx[1] * a[1] + bx[2] * a[2]) - x[15],
                          z[1] - (by[0] * a[0] + by[1] * a[1] + by[2] * a[2]) - x[16]))
            return y, H, H.dot(P).dot(H.T) + R
        if not offset:  # the camera, h = p
            return z - np.array(x[0:3]), 0, P[0:3, 0:3] + R
        # the camera offset from the node: h = p + d v
        H = _H_POSITION.copy()
        H[:, 3:6] = offset * np.eye(3)
        y = z - (np.array(x[POSITION]) + offset * np.array(x[VELOCITY]))
        return y, H, H.dot(P).dot(H.T) + R

    def _apply(self, x, P, meas):
        kind, z, R, offset = meas
        if kind == "pin":
            x = list(x)
            x[6:12] = z
            x[6] = wrap_angle_float(x[6])
            x[8] = wrap_angle_float(x[8])
            return x, P
        y, H, S = self._innovate(kind, x, P, z, R, offset)
        return self._correct(x, P, y, H, _inv(S), R, _DRAG_FROZEN if kind == "drag" else None)

    def _reject(self, kind, reason, nis=math.nan):
        self._counts[kind][reason] += 1
        self.last_nis[kind] = nis
        return False, nis

    def _fuse(self, kind, t_meas, z, R, var=None):
        """z (and var, the attitude's diagonal R) as floats; z and R as arrays for the camera."""
        if self._x is None:
            self._need_init()
        if kind == "position":
            finite = all(map(math.isfinite, z.tolist())) and all(map(math.isfinite, R.ravel().tolist()))
        elif kind == "drag":
            finite = all(map(math.isfinite, z)) and all(map(math.isfinite, R.ravel().tolist()))
        else:
            finite = all(map(math.isfinite, z)) and (var is None or all(map(math.isfinite, var)))
        if not (math.isfinite(t_meas) and finite):
            return self._reject(kind, "invalid")
        eps = self._eps
        if t_meas > self._t + eps:
            return self._reject(kind, "future")
        hist = self._hist
        if t_meas < self._t - self.params.max_delay_s - eps or t_meas < hist[0].t - eps:
            return self._reject(kind, "too_old")
        # node nearest not after t_meas
        j = len(hist) - 1
        while hist[j].t > t_meas + eps:
            j -= 1
        node = hist[j]
        offset = t_meas - node.t
        if offset <= eps:
            offset = 0.0
        if self._stale is not None and j >= self._stale:
            self._current(j + 1)
        x, P = node.post   # (self._x, self._P) at the newest node
        if kind == "pin":
            nis = math.nan
            meas = (kind, z, None, offset)
            x, P = self._apply(x, P, meas)
        else:
            if var is not None:  # R = diag(var)
                R = _ZERO66.copy()
                R.put(_DIAG6, var)
            y, H, S = self._innovate(kind, x, P, z, R, offset)
            try:
                S_inv = _inv(S)
                nis = float(y.dot(S_inv).dot(y))
            except np.linalg.LinAlgError:
                return self._reject(kind, "invalid")
            if not math.isfinite(nis) or nis < 0:
                return self._reject(kind, "invalid")
            if nis > self._gate[len(z)]:
                if kind == "position":
                    self.camera_fix = (y, x[3:6], None)
                return self._reject(kind, "gate", nis)
            x0 = x
            x, P = self._correct(x, P, y, H, S_inv, R, _DRAG_FROZEN if kind == "drag" else None)
            if kind == "position":
                self.camera_fix = (y, x0[3:6], self._K)
            meas = (kind, z, R, offset)
        node.meas.append(meas)
        node.post = (x, P)
        if j + 1 < len(hist):   # the predictions after it re-run when something needs them (_current)
            self._stale = j + 1
        else:
            self._x, self._P = x, P
        self._counts[kind]["accepted"] += 1
        self.last_nis[kind] = nis
        return True, nis


try:  # what np.linalg.inv runs, without its checks and conversions (a third of its time here)
    from numpy.linalg import _umath_linalg

    def _inv(S: np.ndarray) -> np.ndarray:
        S_inv = _umath_linalg.inv(S, signature="d->d")
        if S_inv.item(0) != S_inv.item(0):  # singular (NaN-filled): np.linalg.inv's LinAlgError
            return np.linalg.inv(S)
        return S_inv
except ImportError:  # pragma: no cover - a numpy without it
    _inv = np.linalg.inv


_H_POSITION = np.zeros((3, N_STATE))
_H_POSITION[:, 0:3] = np.eye(3)
_ZERO66 = np.zeros((6, 6))
# what the drag's horizontal force says nothing about: the vertical, the attitude and rates (the
# attitude level's), the thrust scale (along body z: it drops out; through the tilt's correlation a
# take-off's wind pull was read as 7 % more thrust and the vehicle sank while the estimate climbed)
_DRAG_FROZEN = np.array([2, 5, 6, 7, 8, 9, 10, 11, THRUST_SCALE])
_DIAG6 = np.arange(0, 36, 7)   # the diagonal of a 6x6, flat


def _vec(v, n: int, name: str) -> np.ndarray:
    a = np.array(v, dtype=np.float64).reshape(-1)
    if a.shape != (n,):
        raise PositionEKFError(f"{name} must have {n} elements (got {np.shape(v)})")
    return a


def _floats(v, n: int, name: str) -> list:
    """_vec(v, n, name) as a list of floats, without numpy for the usual inputs."""
    if isinstance(v, np.ndarray):
        if v.shape == (n,) and v.dtype == np.float64:
            return v.tolist()
    elif isinstance(v, (list, tuple)) and len(v) == n:
        try:
            return [float(a) for a in v]
        except TypeError:  # nested: let _vec decide
            pass
    return _vec(v, n, name).tolist()


@functools.lru_cache(maxsize=None)
def _chi2_ppf(p: float, dof: int) -> float:
    """The chi-square quantile scipy.stats.chi2.ppf(p, dof) gives (to ~1e-15), for an
    integer dof, without importing scipy.stats (~0.3 s in a 100 Hz service): bisection on
    the survival function in closed form, with y = x / 2,
    Q = e^-y sum_{i<dof/2} y^i / i!  (dof even),
    Q = erfc(sqrt y) + e^-y sum_{i=1}^{(dof-1)/2} y^(i-1/2) / Gamma(i+1/2)  (dof odd)."""
    if not (isinstance(dof, int) and dof >= 1 and 0.0 < p < 1.0):
        raise PositionEKFError(f"chi-square quantile: need an integer dof >= 1 and 0 < p < 1 (got {dof}, {p})")
    tail = 1.0 - p

    def sf(x):
        y = 0.5 * x
        if dof % 2 == 0:
            term = total = 1.0
            for i in range(1, dof // 2):
                term *= y / i
                total += term
            return math.exp(-y) * total
        term = math.sqrt(y) / math.gamma(1.5)
        total = 0.0
        for i in range(1, (dof + 1) // 2):
            total += term
            term *= y / (i + 0.5)
        return math.erfc(math.sqrt(y)) + math.exp(-y) * total

    lo, hi = 0.0, max(1.0, float(dof))
    while sf(hi) > tail:
        lo, hi = hi, 2.0 * hi
    while True:
        mid = 0.5 * (lo + hi)
        if not lo < mid < hi:
            return hi
        if sf(mid) > tail:
            lo = mid
        else:
            hi = mid


class LaggedMotorInput:
    """The EKF's input over a step: the mean rotor forces, through the motors' first-order
    lag, of the commands as they were sent (each held from its time stamp to the next).

    The motor driver commands at 400 Hz; the filter steps at 100 Hz. Taking only the latest
    command, lagged over the whole step, puts the force of the step's end on all of it:
    through a flip the rotor forces swing by ~6 N within 60 ms, ~0.5 N (0.6 m/s^2) off
    for half a step at a time. The mean of the lagged force over each held command is
    exact for a held command (flight/motor_model.py's motors, the rotor speed lagging:
    thrust_step_and_mean_floats, written out in mean_to for the four rotors, four segments
    a step)."""

    def __init__(self, time_constant_s: float):
        if not (math.isfinite(time_constant_s) and time_constant_s > 0):
            raise PositionEKFError(f"time_constant_s must be > 0 (got {time_constant_s!r})")
        self.tau = float(time_constant_s)
        self._forces = [0.0] * 4   # rotor forces at self.t
        self._command = [0.0] * 4  # the command held since self.t
        self.t: float | None = None
        self._pending: list[tuple[float, list]] = []  # commands stamped after self.t
        self._weights: dict[float, tuple] = {}   # motor_model.mean_weights by step

    @property
    def forces(self) -> np.ndarray:
        """Rotor forces (4,) at self.t."""
        return np.array(self._forces)

    @property
    def command(self) -> np.ndarray:
        """The command (4,) held since self.t."""
        return np.array(self._command)

    def add(self, t_s: float, command_n) -> None:
        """A command sent at t_s (held from then until the next). One older than the
        forces already integrated is taken to hold from their time (it cannot be undone)."""
        c = _floats(command_n, 4, "command_n")
        if self.t is None:
            self.t, self._forces, self._command = float(t_s), c, list(c)
        elif t_s <= self.t:
            self._command = c
        else:
            self._pending.append((float(t_s), c))

    def mean_to(self, t_s: float) -> np.ndarray:
        """Mean rotor forces (4,) over [self.t, t_s]; advances to t_s. Commands stamped at or
        after t_s wait for the next step (a command sent at t_s acts from t_s on)."""
        t = self.t
        if t is None or t_s <= t:
            return np.array(self._forces)
        pending = self._pending
        if len(pending) > 1:
            pending.sort(key=_stamp)
        # motor_model.thrust_step_and_mean_floats over the four rotors, written out (the same
        # expressions, so the same numbers): several segments a step, 400 Hz in all
        f0, f1, f2, f3 = self._forces
        sqrt = math.sqrt
        q0, q1, q2, q3 = [sqrt(c) if c > 0.0 else 0.0 for c in self._command]   # the command's rotor speeds (root)
        m0 = m1 = m2 = m3 = 0.0
        weights = self._weights
        start = t
        taken = 0
        while True:
            end = t_s
            if taken < len(pending) and pending[taken][0] < t_s:
                end = pending[taken][0]
            h = end - t
            if h > 0.0:
                w = weights.get(h)
                if w is None:   # the segments are mostly the commands' 2.5 ms: a handful of values
                    if len(weights) > 64:
                        weights.clear()
                    w = weights[h] = motor_model.mean_weights(h, self.tau)
                d, w1, w2 = w
                e = (sqrt(f0) if f0 > 0.0 else 0.0) - q0
                r = q0 + e * d
                f0 = r * r
                m0 = m0 + h * (q0 * q0 + 2.0 * q0 * e * w1 + e * e * w2)
                e = (sqrt(f1) if f1 > 0.0 else 0.0) - q1
                r = q1 + e * d
                f1 = r * r
                m1 = m1 + h * (q1 * q1 + 2.0 * q1 * e * w1 + e * e * w2)
                e = (sqrt(f2) if f2 > 0.0 else 0.0) - q2
                r = q2 + e * d
                f2 = r * r
                m2 = m2 + h * (q2 * q2 + 2.0 * q2 * e * w1 + e * e * w2)
                e = (sqrt(f3) if f3 > 0.0 else 0.0) - q3
                r = q3 + e * d
                f3 = r * r
                m3 = m3 + h * (q3 * q3 + 2.0 * q3 * e * w1 + e * e * w2)
                t = end
            if end >= t_s:
                break
            command = pending[taken][1]
            taken += 1
            q0, q1, q2, q3 = [sqrt(c) if c > 0.0 else 0.0 for c in command]
            self._command = command
        if taken:
            del pending[:taken]
        self.t = t
        self._forces = [f0, f1, f2, f3]
        span = t_s - start
        return np.array((m0 / span, m1 / span, m2 / span, m3 / span))


def _stamp(entry):
    return entry[0]
