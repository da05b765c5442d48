"""The flip known before it is flown: its predicted envelope over an uncertain vehicle (JAX).

Two steps, both pure (no I/O):

1. ``fly_nominal``: the flip item flown once on the planner's own model by the planner's own
   controller (flight/control/flip_runner.FlipController: phase machine, adaptive targets, iLQR
   re-solved at its rate), from a hover at the item's altitude. What the motor driver applies
   at each tick, u = u_plan + K (x - x_plan), is kept as a time-varying affine policy
   (u_plan, K, x_plan per tick). The same controller also flies the vehicles at the knots of
   each drawn parameter (``anchored_policy``: mass and inertia over the thrust scale, the
   motor lag; two knots a side, 20 flights for the default uncertainty).
2. ``predict``: N closed-loop rollouts at once (``jax.vmap`` over cases of a ``lax.scan`` over
   ticks), each on a vehicle drawn from ``Uncertainty``: mass, inertia, thrust coefficient
   and motor lag, a steady wind with gusts (first-order Gauss-Markov), a control delay, and an
   error in the state the flip starts from (the estimators'). Each case replays the policy the
   controller flies on its vehicle (the knots' tables interpolated per parameter),
   its planned positions moved with the start's position error (the phase machine's targets
   are where the flip starts). The controller models its motors from the commands it sent
   with the file's time constant, as the driver does; the plant has the drawn one.

In flight the planner re-plans from the state at 100 Hz: on a stronger or weaker vehicle it
flies another trajectory, which one set of gains about the nominal would pull back onto the
nominal's (the first version of this module did: flown flips fell outside its bands on the
stronger side, docs/flip-history.md). What is left to the gains is the noise: wind, gusts,
delay, the start's attitude and rates. The metrics are those of flight/control/flip.flip_metrics,
on the nominal phases' clock, and the loss from the turn's start (flight/control/flip.heights:
the height where the roll starts, less the lowest point after the peak).
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from flight import motor_model
from flight.control.flip import TURN_START_RAD
from flight.quat import quat_multiply, wrap_angle
from flight.vehicle import Vehicle

# the flip's metric thresholds (flight/control/flip.flip_metrics' defaults)
LEVEL_TOLERANCE_RAD = math.radians(5.0)
LEVEL_RATE_RAD_S = 0.5
HOLD_S = 0.2
LOST_TILT_RAD = math.radians(30.0)
LOST_RATE_RAD_S = 3.0
FIGURES = ("loss_from_turn_m", "loss_from_hover_m", "xy_drift_m", "overshoot_deg", "recovery_s")
TICK_RATE_HZ = 400.0      # the motor driver's rate: the policy is applied per tick
AFTER_RECOVERY_S = 1.0    # how long the nominal flight holds after recovery
MAX_TIME_S = 12.0


class PredictError(ValueError):
    """A prediction that cannot be made (a method without a plan, a bad uncertainty)."""


@dataclass(frozen=True)
class Uncertainty:
    """What is drawn per case: uniform +-fractions about the vehicle file's numbers (the mass
    about mass_scale times it); the wind
    uniform in direction, its speed uniform in [0, wind_m_s]; gusts of gust_m_s (1 sigma per
    axis) with gust_time_s correlation; the control delay uniform in [0, delay_max_s]; the
    start state's error normal with these sigmas (per axis; the attitude's about each axis)."""
    mass_scale: float = 1.0   # the centre of the mass's spread, times the file's (a payload)
    mass_frac: float = 0.10
    inertia_frac: float = 0.10
    thrust_coefficient_frac: float = 0.05
    motor_lag_frac: float = 0.25
    wind_m_s: float = 1.0
    gust_m_s: float = 0.3
    gust_time_s: float = 1.0
    delay_max_s: float = 0.005
    position_sigma_m: float = 0.02
    velocity_sigma_m_s: float = 0.03
    attitude_sigma_rad: float = math.radians(0.5)
    rate_sigma_rad_s: float = 0.02

    def __post_init__(self):
        for name, value in asdict(self).items():
            if not (math.isfinite(value) and value >= 0.0):
                raise PredictError(f"uncertainty {name} must be finite and >= 0 (got {value!r})")
        if self.mass_scale <= 0.0:
            raise PredictError(f"uncertainty mass_scale must be > 0 (got {self.mass_scale!r})")
        for name in ("mass_frac", "inertia_frac", "thrust_coefficient_frac", "motor_lag_frac"):
            if getattr(self, name) >= 0.9:
                raise PredictError(f"uncertainty {name} must be < 0.9 (got {getattr(self, name)!r})")
        if self.gust_time_s <= 0.0 and self.gust_m_s > 0.0:
            raise PredictError("uncertainty gust_time_s must be > 0 when gust_m_s > 0")

    @classmethod
    def none(cls) -> "Uncertainty":
        return cls(**{k: 0.0 for k in asdict(cls())} | {"gust_time_s": 1.0, "mass_scale": 1.0})


@dataclass
class NominalFlip:
    """The nominal flight and its policy, one row per tick."""
    vehicle: Vehicle
    method: str
    altitude_m: float
    tick_s: float
    x0: np.ndarray            # (state_dim,) the hover the flip starts from
    u_plan: np.ndarray        # (T, 4) rad/s
    gains: np.ndarray         # (T, 4, state_dim)
    x_plan: np.ndarray        # (T, state_dim)
    phases: list              # (T,) the nominal phase names
    flip_tick: int            # first tick of the flip phase
    motor_time_constant_s: float | None
    solves: int = 0
    failed_solves: int = 0
    states: np.ndarray = field(default=None, repr=False)  # (T, state_dim) the nominal flight
    controller: object = field(default=None, repr=False)  # the FlipController that flew it

    @property
    def ticks(self) -> int:
        return self.u_plan.shape[0]


@dataclass
class Prediction:
    """Per case (N,) figures and the summary; NaN where a case never turned or recovered."""
    n: int
    completed: np.ndarray      # turned and recovered (level and calm for HOLD_S) in the window
    crashed: np.ndarray        # hit the ground, never turned, or out of control at the end
    hit_ground: np.ndarray
    loss_from_turn_m: np.ndarray
    loss_from_hover_m: np.ndarray
    xy_drift_m: np.ndarray
    overshoot_deg: np.ndarray
    recovery_s: np.ndarray
    lowest_m: np.ndarray       # the lowest altitude of the whole rollout
    altitude_m: float
    rollout_s: float           # wall time of the N rollouts (compiled)
    compile_s: float           # the first call's extra time (compilation)
    nominal_s: float           # wall time of the nominal flight (its iLQR solves)
    anchor_flights: int = 0    # the controller's flights on the knots' vehicles (AnchoredPolicy)
    anchor_s: float = 0.0      # their wall time

    @property
    def crash_probability(self) -> float:
        return float(np.mean(self.crashed))

    @property
    def recovered_probability(self) -> float:
        return float(np.mean(self.completed))

    @property
    def ground_probability(self) -> float:
        return float(np.mean(self.hit_ground))

    def band(self, name: str, low: float = 5.0, high: float = 95.0) -> tuple[float, float, float]:
        """(p_low, median, p_high) of a figure over the cases where it is defined (NaN: none)."""
        v = np.asarray(getattr(self, name), dtype=np.float64)
        v = v[np.isfinite(v)]
        if v.size == 0:
            return (math.nan, math.nan, math.nan)
        return tuple(float(p) for p in np.percentile(v, [low, 50.0, high]))

    def refusal(self, clearance_m: float = 0.5) -> str | None:
        """Why the flip must not start from altitude_m (None: it may): the 95th percentile of
        the height lost from the hover leaves less than clearance_m above the ground, or more
        than 5 % of the cases crash."""
        p95 = self.band("loss_from_hover_m")[2]
        if not math.isfinite(p95) or self.crash_probability > 0.05:
            return (f"predicted P(crash) {self.crash_probability:.1%} over {self.n} rollouts "
                    f"(more than 5 %)")
        if p95 > self.altitude_m - clearance_m:
            return (f"predicted 95th-percentile altitude loss {p95:.2f} m exceeds the "
                    f"{self.altitude_m - clearance_m:.2f} m available above {clearance_m:g} m of clearance")
        return None

    def summary(self) -> dict:
        out = {"rollouts": self.n, "altitude_m": self.altitude_m,
               "p_crash": self.crash_probability, "p_ground": self.ground_probability,
               "p_recovered": self.recovered_probability,
               "rollout_s": self.rollout_s, "compile_s": self.compile_s, "nominal_s": self.nominal_s,
               "anchor_flights": self.anchor_flights, "anchor_s": self.anchor_s}
        for name in FIGURES:
            p5, p50, p95 = self.band(name)
            out[name] = {"p5": p5, "p50": p50, "p95": p95}
        return out


# --- the nominal flight ---------------------------------------------------------------------

def fly_nominal(vehicle: Vehicle, method: str = "ilqr-project", altitude_m: float = 5.0,
                settle_s: float = 1.0, controller=None, plant: dict | None = None) -> NominalFlip:
    """The flip item flown on the planner's model, no uncertainty: its policy per tick.
    controller: a built flight.control.flip_runner.FlipController for this vehicle and method (the
    planner service passes its own; built here otherwise, which compiles the iLQR).
    plant: another vehicle under the same controller (nominal_params' keys: mass, inertia,
    thrust_scale, tau); the controller still models its motors with the file's time constant."""
    from flight.control.flip import Phase
    from flight.control.flip_runner import FlipController
    from flight.control.ilqr import hover_state

    if method == "baseline":
        raise PredictError("the baseline flip has no plan to predict from (it is a fixed rate "
                           "sequence); predict flies the iLQR methods")
    c = controller if controller is not None else FlipController(vehicle, method)
    if c.method != method:
        raise PredictError(f"controller flies {c.method!r}, not {method!r}")
    tick_s = 1.0 / TICK_RATE_HZ
    ratio = max(1, round(TICK_RATE_HZ / c.solve_rate_hz))
    tau = c.motor_time_constant_s
    kf = vehicle.thrust_coefficient_kf
    u_max = float(vehicle.max_rotor_speed_rad_s)
    step = _plant_step(vehicle, tick_s)
    params = nominal_params(vehicle) if plant is None else plant

    body = hover_state(np.array([0.0, 0.0, altitude_m]))
    forces = np.full(4, vehicle.hover_thrust_per_motor_n)
    plant_forces = forces.copy()
    x_full = np.concatenate([body, forces]) if c.state_dim == 17 else body.copy()
    c.start(0.0, x_full, altitude_m)
    rows_u, rows_k, rows_x, phases, states = [], [], [], [], []
    flip_tick, land_tick = None, None
    for tick in range(int(MAX_TIME_S * TICK_RATE_HZ)):
        t = tick * tick_s
        x_ctrl = np.concatenate([body, forces]) if c.state_dim == 17 else body
        s = c.step(t, x_ctrl, settle_s, solve=tick % ratio == 0)
        phase = c.machine.phase
        if phase == Phase.FLIP and flip_tick is None:
            flip_tick = tick
        if phase in (Phase.LAND, Phase.DONE) and land_tick is None:
            land_tick = tick
        if s.done or (land_tick is not None and tick - land_tick >= AFTER_RECOVERY_S * TICK_RATE_HZ):
            break
        plan, elapsed = c.plan, t - c.plan_t_s
        h = plan.controls.shape[0]
        sk = min(max(elapsed / plan.dt_s, 0.0), h - 1e-9)
        k = int(sk)
        x_plan = (1 - (sk - k)) * plan.states[k] + (sk - k) * plan.states[k + 1]
        rows_u.append(plan.controls[k])
        rows_k.append(plan.gains[k])
        rows_x.append(x_plan)
        phases.append(phase.value)
        states.append(x_ctrl.copy())
        aligned = x_ctrl.copy()
        if np.dot(aligned[6:10], x_plan[6:10]) < 0:
            aligned[6:10] = -aligned[6:10]
        u = np.clip(plan.controls[k] + plan.gains[k] @ (aligned - x_plan), 0.0, u_max)
        command = kf * u * u
        if plant is None:
            # the nominal: the driver's model of its motors is the plant's, so one forces state serves both
            body, forces = (np.asarray(a, dtype=np.float64) for a in step(body, forces, command, params))
        else:
            body, rotors = (np.asarray(a, dtype=np.float64) for a in step(body, plant_forces, command, params))
            plant_forces = rotors
            forces = forces if tau is None else motor_model.thrust_step(forces, command, tick_s, tau)
    if flip_tick is None:
        raise PredictError(f"the nominal {method} flip from {altitude_m:g} m never started its turn")
    return NominalFlip(vehicle, method, float(altitude_m), tick_s, x_full,
                       np.array(rows_u), np.array(rows_k), np.array(rows_x), phases, flip_tick, tau,
                       c.solves, c.failed_solves, np.array(states), controller=c)


# --- the plant of the rollouts ---------------------------------------------------------------

def nominal_params(vehicle: Vehicle) -> dict:
    """The rollout plant's numbers for the vehicle file (one case, no uncertainty)."""
    return {"mass": np.float32(vehicle.mass_kg), "inertia": np.asarray(vehicle.inertia_kg_m2, np.float32),
            "thrust_scale": np.float32(1.0), "tau": np.float32(vehicle.motor_time_constant_s),
            "wind": np.zeros(3, np.float32)}


def _jnp_root(x):
    import jax.numpy as jnp
    return jnp.sqrt(jnp.maximum(x, 0.0))


def _plant_step(vehicle: Vehicle, dt_s: float):
    """One tick of the plant: the rotor speeds lag the command with the case's time constant
    (flight/motor_model.py, exact over the tick), the rigid body by RK4 under the forces'
    mean over the tick (the iLQR's model, flight/control/ilqr.make_dynamics). Returns a jitted
    step(body, forces, command, params)."""
    import jax
    import jax.numpy as jnp
    from flight.control.ilqr import rigid_body_derivative

    allocation = jnp.asarray(vehicle.allocation, jnp.float32)
    drag = float(vehicle.drag_n_per_m_s)
    gravity = jnp.array([0.0, 0.0, vehicle.gravity_m_s2], jnp.float32)

    def step(body, forces, command, p):
        command = command * p["thrust_scale"]
        forces_next, mean = motor_model.thrust_step_and_mean(forces, command, dt_s, p["tau"], _jnp_root, jnp.exp)

        def f(x):
            return rigid_body_derivative(x, mean, p["mass"], p["inertia"], allocation, drag, gravity, p["wind"])
        k1 = f(body)
        k2 = f(body + 0.5 * dt_s * k1)
        k3 = f(body + 0.5 * dt_s * k2)
        k4 = f(body + dt_s * k3)
        x = body + dt_s / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        x = jnp.concatenate([x[:6], x[6:10] / jnp.linalg.norm(x[6:10]), x[10:]])
        return x, forces_next

    step.raw = step
    return jax.jit(step)


# --- the controller's own answer to the vehicle drawn ----------------------------------------
#
# The flown controller re-plans from the state at 100 Hz with the file's model; on a vehicle
# that is stronger or weaker than the file it flies another trajectory (a lighter or more
# agile one turns ahead of the nominal's clock and recovers higher), which one set of gains
# about the nominal cannot follow: it pulls every case back onto the nominal's trajectory. So
# the rollouts replay, per case, the policy the controller flies on that case's vehicle: the
# nominal's tables plus, per parameter, the change measured by flying the controller on the
# vehicles at ANCHOR_KNOTS of the way to the extremes the draw allows (four flights a
# parameter), interpolated on each side (bench/predict_calibration.py measures how close that
# comes to flown flips).
# The parameters are the ones the rigid body sees: mass / thrust scale and inertia / thrust
# scale (the same accelerations up to the drag), and the motors' time constant.
ANCHOR_PARAMETERS = ("mass", "inertia_x", "inertia_y", "inertia_z", "motor_lag")
# the anchors' vehicles: these fractions of the way from the centre to each extreme (the
# response is far from linear: +7 % mass/thrust costs the flip 1.6 deg of overshoot, +15 % 6.7)
ANCHOR_KNOTS = (0.5, 1.0)


def anchor_extents(uncertainty: Uncertainty) -> dict[str, tuple[float, float]]:
    """Per parameter drawn with a spread: the log of its smallest and largest value the draw
    allows, about the centre (the file's vehicle, its mass times mass_scale)."""
    u = uncertainty
    fs = u.thrust_coefficient_frac
    out = {"mass": (math.log((1 - u.mass_frac) / (1 + fs)), math.log((1 + u.mass_frac) / (1 - fs)))}
    for axis in "xyz":
        out["inertia_" + axis] = (math.log((1 - u.inertia_frac) / (1 + fs)), math.log((1 + u.inertia_frac) / (1 - fs)))
    out["motor_lag"] = (math.log(1 - u.motor_lag_frac), math.log(1 + u.motor_lag_frac))
    return {k: v for k, v in out.items() if v[1] - v[0] > 1e-9}


def centre_plant(vehicle: Vehicle, uncertainty: Uncertainty) -> dict:
    """The plant at the draw's centre (nominal_params with the mass times mass_scale)."""
    return nominal_params(vehicle) | {"mass": np.float32(vehicle.mass_kg * uncertainty.mass_scale)}


def anchor_plant(vehicle: Vehicle, uncertainty: Uncertainty, name: str, log_value: float) -> dict:
    """The centre's plant with one parameter at exp(log_value) times the centre's."""
    p = centre_plant(vehicle, uncertainty)
    scale = np.float32(math.exp(log_value))
    if name == "mass":
        p["mass"] = np.float32(p["mass"] * scale)
    elif name.startswith("inertia_"):
        axis = "xyz".index(name[-1])
        p["inertia"] = p["inertia"].copy()
        p["inertia"][axis] *= scale
    elif name == "motor_lag":
        p["tau"] = np.float32(p["tau"] * scale)
    else:
        raise PredictError(f"no anchor parameter {name!r}")
    return p


def case_parameters(vehicle: Vehicle, uncertainty: Uncertainty, cases: dict) -> dict[str, np.ndarray]:
    """Per case (N,), the log of each ANCHOR_PARAMETERS about the centre."""
    s = cases["thrust_scale"].astype(np.float64)
    inertia = np.asarray(vehicle.inertia_kg_m2, dtype=np.float64)
    out = {"mass": np.log(cases["mass"] / s / (vehicle.mass_kg * uncertainty.mass_scale)),
           "motor_lag": np.log(cases["tau"] / np.float64(vehicle.motor_time_constant_s))}
    for i, axis in enumerate("xyz"):
        out["inertia_" + axis] = np.log(cases["inertia"][:, i] / s / inertia[i])
    return out


@dataclass
class AnchoredPolicy:
    """The policy tables the rollouts replay: row 0 the centre's flight, then per (parameter,
    knot) the change of the flight on that knot's vehicle; weights() gives a case its row
    weights (1 on row 0)."""
    u_plan: np.ndarray       # (A, T, 4)
    gains: np.ndarray        # (A, T, 4, state_dim)
    x_plan: np.ndarray       # (A, T, state_dim)
    columns: list            # per row after the first: (parameter, its knot: log value about the centre)
    flights: int = 0         # flights flown to build it (the centre's when not the nominal, anchors)
    flight_s: float = 0.0    # their wall time

    def weights(self, vehicle: Vehicle, uncertainty: Uncertainty, cases: dict) -> np.ndarray:
        """(N, A): per case, the rows' weights of the polynomial through the centre (the knot at
        0) and the knots of each parameter's side it is on (Lagrange's basis: with two knots a
        side a parabola, which follows the response's curvature where a broken line through
        the knots overshoots it: +7 % of mass / thrust costs 1.6 deg of overshoot, +15 % 6.7)."""
        n = cases["mass"].shape[0]
        params = case_parameters(vehicle, uncertainty, cases) if self.columns else {}
        w = np.zeros((n, 1 + len(self.columns)), dtype=np.float64)
        w[:, 0] = 1.0
        for j, (name, knot) in enumerate(self.columns):
            e = params[name]
            nodes = [0.0] + [k for other, k in self.columns if other == name and k * knot > 0]
            basis = np.ones_like(e)
            for node in nodes:
                if node != knot:
                    basis = basis * (e - node) / (knot - node)
            w[:, 1 + j] = np.where(e * knot > 0, basis, 0.0)   # the other side's knots carry none
        return w.astype(np.float32)


def _tables(flight: NominalFlip, ticks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A flight's (u_plan, gains, x_plan) over `ticks` rows: its last row held, or cut."""
    def fit(a):
        if a.shape[0] >= ticks:
            return a[:ticks]
        return np.concatenate([a, np.repeat(a[-1:], ticks - a.shape[0], axis=0)])
    return fit(flight.u_plan), fit(flight.gains), fit(flight.x_plan)


def anchored_policy(nominal: NominalFlip, uncertainty: Uncertainty, controller=None,
                    adapt: bool = True) -> AnchoredPolicy:
    """The nominal's tables and, for each parameter drawn with a spread, the flights of the
    controller on the vehicles at ANCHOR_KNOTS of the way to its extremes (anchor_extents), as
    changes from the centre's. adapt=False: the nominal's tables alone (no flight; every case
    replays the nominal's policy, the centre's mass or not)."""
    start = time.perf_counter()
    extents = anchor_extents(uncertainty) if adapt else {}
    c = controller if controller is not None else nominal.controller
    flights = 0
    fly = None
    moved = adapt and uncertainty.mass_scale != 1.0
    if extents or moved:
        if c is None:
            from flight.control.flip_runner import FlipController
            c = FlipController(nominal.vehicle, nominal.method)

        def fly(plant):
            return fly_nominal(nominal.vehicle, nominal.method, nominal.altitude_m, controller=c, plant=plant)
    ticks = nominal.ticks
    if moved:
        centre = _tables(fly(centre_plant(nominal.vehicle, uncertainty)), ticks)
        flights += 1
    else:
        centre = _tables(nominal, ticks)
    rows, columns = [centre], []
    for name, (low, high) in extents.items():
        for extent in [f * low for f in ANCHOR_KNOTS] + [f * high for f in ANCHOR_KNOTS]:
            if abs(extent) < 1e-9:
                continue
            anchor = _tables(fly(anchor_plant(nominal.vehicle, uncertainty, name, extent)), ticks)
            flights += 1
            x = anchor[2].copy()
            flip = np.sum(x[:, 6:10] * centre[2][:, 6:10], axis=1) < 0   # q and -q: the centre's sign
            x[flip, 6:10] *= -1
            rows.append((anchor[0] - centre[0], anchor[1] - centre[1], x - centre[2]))
            columns.append((name, extent))
    stack = [np.stack([r[i] for r in rows]).astype(np.float32) for i in range(3)]
    return AnchoredPolicy(*stack, columns, flights, time.perf_counter() - start if flights else 0.0)


# --- the rollouts ---------------------------------------------------------------------------

def draw_cases(vehicle: Vehicle, nominal: NominalFlip, n: int, uncertainty: Uncertainty, seed: int) -> dict:
    """N cases (numpy, float32): the plant's numbers, the start error, the delay in ticks and
    the gust noise."""
    rng = np.random.default_rng(seed)
    u = uncertainty

    def spread(frac, shape=(n,)):
        return 1.0 + rng.uniform(-frac, frac, shape)

    tau0 = vehicle.motor_time_constant_s
    heading = rng.uniform(0.0, 2.0 * math.pi, n)
    speed = rng.uniform(0.0, u.wind_m_s, n)
    wind = np.stack([speed * np.cos(heading), speed * np.sin(heading), np.zeros(n)], axis=1)
    small = rng.normal(0.0, u.attitude_sigma_rad, (n, 3))
    angle = np.linalg.norm(small, axis=1, keepdims=True)
    axis = np.divide(small, angle, out=np.zeros_like(small), where=angle > 0)
    dq = np.concatenate([np.cos(angle / 2), np.sin(angle / 2) * axis], axis=1)
    max_delay = int(round(u.delay_max_s * TICK_RATE_HZ))
    return {
        "mass": (vehicle.mass_kg * u.mass_scale * spread(u.mass_frac)).astype(np.float32),
        "inertia": (np.asarray(vehicle.inertia_kg_m2)[None] * spread(u.inertia_frac, (n, 3))).astype(np.float32),
        "thrust_scale": spread(u.thrust_coefficient_frac).astype(np.float32),
        "tau": (tau0 * spread(u.motor_lag_frac)).astype(np.float32),
        "wind": wind.astype(np.float32),
        "start_error": np.concatenate([rng.normal(0.0, u.position_sigma_m, (n, 3)),
                                       rng.normal(0.0, u.velocity_sigma_m_s, (n, 3)),
                                       rng.normal(0.0, u.rate_sigma_rad_s, (n, 3))], axis=1).astype(np.float32),
        "start_dq": dq.astype(np.float32),
        "delay_ticks": rng.integers(0, max_delay + 1, n).astype(np.int32),
        "gust_noise": rng.standard_normal((n, nominal.ticks, 3)).astype(np.float32),
    }, max_delay


def euler_roll(q, jnp):
    """The roll angle of quaternion q (w, x, y, z), in JAX."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))


def start_body(case, x0, jnp):
    """A case's rigid-body start (13 states) and attitude: the nominal start x0 with the case's
    drawn estimator error (start_dq, start_error) applied, in JAX."""
    body0 = x0[:13]
    q0 = quat_multiply(body0[6:10], case["start_dq"], jnp)
    err = case["start_error"]
    return jnp.concatenate([body0[0:3] + err[0:3], body0[3:6] + err[3:6], q0, body0[10:13] + err[6:9]]), q0


def make_rollouts(nominal: NominalFlip, uncertainty: Uncertainty, max_delay_ticks: int):
    """A jitted rollouts(cases, u_plan, gains, x_plan, x0) -> per tick (N, T, 6): z, x, y,
    accumulated roll, tilt, body-rate norm. The tables are an AnchoredPolicy's (A, T, ...),
    cases["weights"] (N, A) its weights."""
    import jax
    import jax.numpy as jnp

    vehicle = nominal.vehicle
    dt_s = nominal.tick_s
    kf = float(vehicle.thrust_coefficient_kf)
    u_max = float(vehicle.max_rotor_speed_rad_s)
    ctrl_tau = nominal.motor_time_constant_s
    ctrl_decay = None if ctrl_tau is None else motor_model.decay(dt_s, ctrl_tau)
    step = _plant_step(vehicle, dt_s).raw
    gust_decay = float(np.exp(-dt_s / uncertainty.gust_time_s)) if uncertainty.gust_m_s > 0 else 0.0
    gust_gain = uncertainty.gust_m_s * math.sqrt(1.0 - gust_decay ** 2)
    hover_f = float(vehicle.hover_thrust_per_motor_n)

    def one(case, u_plan, gains, x_plan, x0):
        w = case["weights"]
        body0, q0 = start_body(case, x0, jnp)
        err = case["start_error"]
        forces0 = jnp.full(4, hover_f, jnp.float32)
        params = {k: case[k] for k in ("mass", "inertia", "thrust_scale", "tau")}
        buffer0 = jnp.tile((kf * (w @ u_plan[:, 0]) ** 2)[None], (max_delay_ticks + 1, 1))
        # the phase machine's targets move with where the flip starts (its flip point, the
        # recovery's coast, the hold's stop): the plan's positions move with the start's error
        shift = jnp.concatenate([err[0:3], jnp.zeros(x0.shape[0] - 3, jnp.float32)])

        def tick(carry, inputs):
            body, forces, est, buffer, gust, roll, last = carry
            u_rows, k_rows, x_rows, noise = inputs
            u_bar = w @ u_rows
            k = jnp.tensordot(w, k_rows, axes=1)
            xp = w @ x_rows + shift
            x_ctrl = jnp.concatenate([body, est]) if ctrl_tau is not None else body
            sign = jnp.where(jnp.sum(x_ctrl[6:10] * xp[6:10]) < 0, -1.0, 1.0)
            x_ctrl = x_ctrl.at[6:10].multiply(sign)
            u = jnp.clip(u_bar + k @ (x_ctrl - xp), 0.0, u_max)
            command = kf * u * u
            buffer = jnp.concatenate([command[None], buffer[:-1]])
            applied = buffer[case["delay_ticks"]]
            wind = case["wind"] + gust
            body_next, forces_next = step(body, forces, applied, params | {"wind": wind})
            est_next = est if ctrl_tau is None else motor_model.root_step(_jnp_root(est), _jnp_root(command),
                                                                          ctrl_decay) ** 2
            gust_next = gust * gust_decay + gust_gain * noise * jnp.array([1.0, 1.0, 1.0])
            r = euler_roll(body[6:10], jnp)
            roll_next = roll + wrap_angle(r - last, jnp)
            q = body[6:10]
            tilt = jnp.arccos(jnp.clip((q[0] ** 2 - q[1] ** 2 - q[2] ** 2 + q[3] ** 2) / jnp.sum(q * q), -1.0, 1.0))
            out = jnp.stack([body[2], body[0], body[1], roll_next, tilt, jnp.linalg.norm(body[10:13])])
            return (body_next, forces_next, est_next, buffer, gust_next, roll_next, r), out

        carry0 = (body0, forces0, forces0, buffer0, jnp.zeros(3, jnp.float32), jnp.float32(0.0), euler_roll(q0, jnp))
        tables = (jnp.swapaxes(u_plan, 0, 1), jnp.swapaxes(gains, 0, 1), jnp.swapaxes(x_plan, 0, 1))
        _, outs = jax.lax.scan(tick, carry0, tables + (case["gust_noise"],))
        return outs

    batched = jax.vmap(one, in_axes=(0, None, None, None, None))
    return jax.jit(batched)


def metrics_from_series(series: np.ndarray, flip_tick: int, tick_s: float, altitude_m: float) -> dict:
    """Flip metrics (flight/control/flip.flip_metrics' definitions) of N series (N, T, 6), vectorised.
    The accumulated roll is taken relative to the flip's first tick."""
    z, xy = series[:, :, 0], series[:, :, 1:3]
    roll = series[:, :, 3] - series[:, flip_tick:flip_tick + 1, 3]
    n, t_len = z.shape
    ticks = np.arange(t_len)
    after = ticks[None, :] >= flip_tick
    turned = after & (roll >= 2 * math.pi - LEVEL_TOLERANCE_RAD)
    has_turn = turned.any(axis=1)
    turn = np.where(has_turn, turned.argmax(axis=1), t_len)
    calm = (series[:, :, 4] <= LEVEL_TOLERANCE_RAD) & (series[:, :, 5] < LEVEL_RATE_RAD_S)
    hold = int(round(HOLD_S / tick_s))
    # calm over [i, i + hold] (clipped at the end): a running count of calm ticks
    counts = np.concatenate([np.zeros((n, 1)), np.cumsum(calm, axis=1)], axis=1)
    upto = np.minimum(ticks + hold + 1, t_len)
    calm_window = (counts[:, upto] - counts[:, ticks]) == (upto - ticks)[None, :]
    candidates = calm_window & (ticks[None, :] >= turn[:, None])
    has_recovery = candidates.any(axis=1)
    recovered = np.where(has_recovery, candidates.argmax(axis=1), t_len - 1)
    completed = has_turn & has_recovery
    end = np.where(completed, recovered, t_len - 1)
    in_span = after & (ticks[None, :] <= end[:, None])
    z_span = np.where(in_span, z, np.inf)
    lowest_span = z_span.min(axis=1)
    # from the turn's start (flight/control/flip.heights' turn_loss): the height where the roll passes
    # TURN_START_RAD, less the lowest point after the peak (a climb before the turn is not a gain)
    turn_start = np.argmax(after & (roll > TURN_START_RAD), axis=1)
    peak = np.argmax(np.where(in_span, z, -np.inf), axis=1)
    lowest_after_peak = np.where(in_span & (ticks[None, :] >= peak[:, None]), z, np.inf).min(axis=1)
    rows = np.arange(n)
    drift = np.where(in_span, np.linalg.norm(xy - xy[:, flip_tick:flip_tick + 1], axis=2), 0.0).max(axis=1)
    overshoot = np.maximum(0.0, np.degrees(np.where(in_span, roll, -np.inf).max(axis=1)) - 360.0)
    nan = np.full(n, np.nan)
    hit_ground = z.min(axis=1) <= 0.0
    # the end of the window: still tilted past LOST_TILT_RAD or spinning (a steady lean into the
    # wind, a few degrees, is not calm by the flip's criterion but is not lost either)
    lost = (series[:, -1, 4] > LOST_TILT_RAD) | (series[:, -1, 5] > LOST_RATE_RAD_S)
    return {
        "completed": completed,
        "crashed": hit_ground | ~has_turn | lost,
        "hit_ground": hit_ground,
        "lowest_m": z.min(axis=1),
        "loss_from_turn_m": z[rows, turn_start] - lowest_after_peak,
        "loss_from_hover_m": altitude_m - lowest_span,
        "xy_drift_m": drift,
        "overshoot_deg": np.where(has_turn, overshoot, nan),
        "recovery_s": np.where(completed, (recovered - turn) * tick_s, nan),
    }


class Predictor:
    """A nominal flip and its compiled rollouts; predict() draws and flies N cases."""

    def __init__(self, nominal: NominalFlip, uncertainty: Uncertainty = Uncertainty(), nominal_s: float = 0.0,
                 controller=None, adapt: bool = True, replan=None):
        """controller: the FlipController that flies the anchors (default: the nominal's);
        adapt: False replays the nominal's policy in every case (anchored_policy);
        replan: a flight/control/replan.Replan: each case re-plans instead (no anchor flights)."""
        self.nominal = nominal
        self.uncertainty = uncertainty
        self.nominal_s = nominal_s
        self.replan = replan
        self.max_delay = int(round(uncertainty.delay_max_s * TICK_RATE_HZ))
        if replan is None:
            self.policy = anchored_policy(nominal, uncertainty, controller, adapt)
            self._rollouts = make_rollouts(nominal, uncertainty, self.max_delay)
        else:   # built by the flight/control/replan.Replan given (this module does not import it)
            self.policy = anchored_policy(nominal, uncertainty, controller, adapt=False)   # no flights
            self._rollouts, self._initial = replan.rollouts(nominal, uncertainty, self.max_delay)
        self._compiled_for = set()

    def series(self, n: int, seed: int = 0) -> tuple[np.ndarray, float, float]:
        """(series (N, T, 6), rollout seconds, compile seconds) for N drawn cases."""
        import jax
        nom = self.nominal
        cases, _ = draw_cases(nom.vehicle, nom, n, self.uncertainty, seed)
        tables = self.tables()
        cases["weights"] = self.policy.weights(nom.vehicle, self.uncertainty, cases)
        compile_s = 0.0
        if n not in self._compiled_for:
            start = time.perf_counter()
            self._rollouts.lower(cases, *tables).compile()
            compile_s = time.perf_counter() - start
            self._compiled_for.add(n)
        start = time.perf_counter()
        out = np.asarray(jax.block_until_ready(self._rollouts(cases, *tables)), dtype=np.float64)
        return out, time.perf_counter() - start, compile_s

    def tables(self) -> tuple:
        """The rollouts' arguments after the cases: the policy's (u_plan, gains, x_plan) and the
        start state; re-planning: the start state and the controller's first plan."""
        if self.replan is not None:
            return (self.nominal.x0.astype(np.float32), *self._initial)
        p = self.policy
        return p.u_plan, p.gains, p.x_plan, self.nominal.x0.astype(np.float32)

    def predict(self, n: int = 1000, seed: int = 0) -> Prediction:
        if n < 1:
            raise PredictError(f"rollouts must be >= 1 (got {n})")
        series, rollout_s, compile_s = self.series(n, seed)
        m = metrics_from_series(series, self.nominal.flip_tick, self.nominal.tick_s, self.nominal.altitude_m)
        return Prediction(n=n, altitude_m=self.nominal.altitude_m, rollout_s=rollout_s, compile_s=compile_s,
                          nominal_s=self.nominal_s, anchor_flights=self.policy.flights,
                          anchor_s=self.policy.flight_s, **m)


def build_predictor(vehicle: Vehicle, method: str = "ilqr-project", altitude_m: float = 5.0,
                    uncertainty: Uncertainty = Uncertainty(), controller=None, adapt: bool = True,
                    replan=None) -> Predictor:
    start = time.perf_counter()
    nominal = fly_nominal(vehicle, method, altitude_m, controller=controller)
    return Predictor(nominal, uncertainty, time.perf_counter() - start, adapt=adapt, replan=replan)
