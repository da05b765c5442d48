"""The flip of document 001 as the planner service flies it (pure: no Zenoh, no msgpack).

FlipController is one mission `flip` item's controller for one method:

* "ilqr-project" / "ilqr-thesis": the feedback phase machine of flight/control/flip.py
  (take-off -> flip -> recovery; transitions on the state estimate only) with its
  adaptive roll targets, and the iLQR of flight/control/ilqr.py re-solved from the latest
  estimate every 1 / solve_rate_hz (model-predictive control). The solver is
  compiled when the controller is built (at service start-up, never in flight).
  A solve that is not usable (non-finite, or neither converged nor better than its
  warm start) is counted and no plan is sent: the motor driver keeps the previous
  plan while it lasts, then falls back to the cascaded hover laws.
* "baseline": Appendix И's model-free flip (flight/control/flip.BaselineFlip), its rotor
  commands sent as a plan of horizon 1 with zero gains.

After recovery (the phase machine's "land") the controller holds hover at the
flip's altitude, where it recovered, for at least the item's settle_s and until the
vehicle is calm there (HANDOVER_*), and then hands back to the mission (done).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np

from flight.control.flip import (
    PROJECT_FLIP,
    THESIS_FLIP,
    BASELINE_CLIMB_M,
    BaselineConfig,
    BaselineFlip,
    FlipPhaseMachine,
    Phase,
    tilt_rad,
)
from flight.quat import quat_to_euler, roll_floats, wrap_angle_float
from flight.vehicle import Vehicle

METHODS = ("ilqr-project", "ilqr-thesis", "baseline")
# re-solve rates: the thesis's 20 Hz MPC timer; the project's solve (~2-9 ms) allows 100 Hz;
# the baseline is a 200 Hz rate loop (the attitude level's rate)
DEFAULT_RATE_HZ = {"ilqr-project": 100.0, "ilqr-thesis": 20.0, "baseline": 200.0}

# the hand-over back to the mission's laws after the settle: level, slow, at the hold point
HANDOVER_TILT_RAD = math.radians(3.0)
HANDOVER_RATE_RAD_S = 0.2
HANDOVER_SPEED_M_S = 0.15
HANDOVER_DISTANCE_M = 0.1

_PHASE_NAMES = {Phase.IDLE: "takeoff", Phase.TAKEOFF: "takeoff", Phase.FLIP: "flip",
                Phase.RECOVERY: "recovery", Phase.LAND: "settle", Phase.DONE: "settle"}


@dataclass
class Step:
    """What one controller step gives the planner service."""
    phase: str                 # takeoff | flip | recovery | settle
    done: bool
    failed: bool
    position_ref_m: np.ndarray  # the fallback laws' position reference
    plan: dict | None          # planner/plan fields to publish (None: nothing new)


class FlipController:
    def __init__(self, vehicle: Vehicle, method: str, solve_rate_hz: float | None = None):
        if method not in METHODS:
            raise ValueError(f"flip method {method!r} not one of {', '.join(METHODS)}")
        self.vehicle = vehicle
        self.method = method
        self.solve_rate_hz = float(solve_rate_hz or DEFAULT_RATE_HZ[method])
        self.planner = None
        if method != "baseline":
            from flight.control.ilqr import PROJECT, THESIS, ILQRSolver  # JAX: only when an iLQR flies
            self.ilqr_config = PROJECT if method == "ilqr-project" else THESIS
            self.flip_config = PROJECT_FLIP if method == "ilqr-project" else THESIS_FLIP
            self.planner = ILQRSolver(vehicle, self.ilqr_config)  # compiles and warms up here
            self.state_dim = self.planner.state_dim
            self.motor_time_constant_s = self.planner.motor_time_constant_s
        else:
            self.state_dim = 13
            self.motor_time_constant_s = None
        self._reset()

    def _reset(self) -> None:
        self.started_s = None
        self.machine = None
        self.baseline = None
        self.plan = None
        self.plan_t_s = 0.0
        self.settle_start_s = None
        self.hold_point_m = None
        self.solves = self.failed_solves = self.overrun_solves = 0

    # -- the item ----------------------------------------------------------------
    def start(self, t_s: float, x, altitude_m: float, baseline_climb_m: float = BASELINE_CLIMB_M) -> None:
        """baseline_climb_m: the baseline's full-thrust climb above altitude_m before its roll."""
        self._reset()
        self.started_s = t_s
        x = np.asarray(x, dtype=np.float64)
        self.altitude_m = float(altitude_m)
        self.start_point_m = np.array([x[0], x[1], altitude_m])
        if self.method == "baseline":
            self.baseline = BaselineFlip(self.vehicle, BaselineConfig(hover_altitude_m=altitude_m,
                                                                      flip_altitude_m=altitude_m + baseline_climb_m))
        else:
            config = replace(self.flip_config, flip_altitude_m=altitude_m)
            self.machine = FlipPhaseMachine(config, self.ilqr_config.horizon, self.ilqr_config.dt_s)
            self.machine.start(t_s, x[:13])

    def step(self, t_s: float, x, settle_s: float, solve: bool) -> Step:
        """x: the body state (13,) or, when the solver models the motors, (17,) with the
        rotor forces. `solve`: a re-solve is due now (the service's schedule)."""
        x = np.asarray(x, dtype=np.float64)
        if self.method == "baseline":
            return self._baseline_step(t_s, x, settle_s)
        return self._ilqr_step(t_s, x, settle_s, solve)

    def _settling(self, t_s: float, x, settle_s: float) -> bool:
        """Entered the hold after recovery; True once it has lasted settle_s and the vehicle
        is calm at the hold point (the cascaded laws of 000 take over without a transient:
        on the q820 their torque saturates easily and a handover in motion can limit-cycle)."""
        if self.settle_start_s is None:
            self.settle_start_s = t_s
        # every step: the baseline's hold and the phase machine's stop both move on
        self.hold_point_m = self._settle_point(t_s, x)
        calm = (tilt_rad(x[6:10]) < HANDOVER_TILT_RAD and np.linalg.norm(x[10:13]) < HANDOVER_RATE_RAD_S
                and np.linalg.norm(x[3:6]) < HANDOVER_SPEED_M_S
                and np.linalg.norm(x[0:3] - self.hold_point_m) < HANDOVER_DISTANCE_M)
        return t_s - self.settle_start_s >= settle_s and calm

    def _settle_point(self, t_s: float, x) -> np.ndarray:
        """Where the vehicle must be calm before handing back. The baseline holds the altitude it
        recovered at (it climbed 1 m to roll) and only damps its horizontal speed, so it stops
        where it stops; the iLQR holds at the flip's altitude, where the phase machine's hold
        after recovery puts it (FlipPhaseMachine.settle_hold_point)."""
        if self.machine is not None and self.machine.phase in (Phase.LAND, Phase.DONE):
            return self.machine.settle_hold_point(t_s, x)
        if self.baseline is not None and self.baseline.hold_point_m is not None:
            z = self.baseline.hold_point_m[2]
        else:
            z = self.altitude_m
        return np.array([x[0], x[1], float(z)])

    def _ilqr_step(self, t_s, x, settle_s, solve) -> Step:
        from flight.control.ilqr import warm_start
        phase = self.machine.update(t_s, x[:13])
        done = False
        if phase in (Phase.LAND, Phase.DONE):
            done = self._settling(t_s, x, settle_s)
        ref = (self.hold_point_m if self.hold_point_m is not None
               else self.machine.flip_point_m if phase in (Phase.FLIP, Phase.RECOVERY) else self.start_point_m)
        step = Step(_PHASE_NAMES[phase], done, False, np.array(ref), None)
        if not solve or done:
            return step
        h = self.ilqr_config.horizon
        if self.hold_point_m is not None:
            targets = self.machine.settle_targets(t_s, x[:13])
        else:
            targets = self.machine.targets(t_s, x[:13])
        warm = None if self.plan is None else warm_start(self.plan, t_s - self.plan_t_s)
        start = time.perf_counter()
        candidate = self.planner.solve(x, targets, warm=warm)
        solve_ms = (time.perf_counter() - start) * 1e3
        self.solves += 1
        if solve_ms > 1e3 / self.solve_rate_hz:
            self.overrun_solves += 1
        if not (candidate.usable or (self.plan is None and _finite(candidate))):
            self.failed_solves += 1
            return step
        self.plan, self.plan_t_s = candidate, t_s
        roll_now, euler_roll = self.machine.roll.roll_rad, quat_to_euler(x[6:10])[0]
        # the rolls from the targets' rows as floats (roll_floats: quat_to_euler's roll, the same bits)
        target_roll = [roll_now + wrap_angle_float(roll_floats(*q) - euler_roll) for q in targets[:h, 6:10].tolist()]
        step.plan = {
            "method": self.method, "phase": step.phase, "t0_s": t_s, "dt_s": candidate.dt_s,
            "horizon": h, "state_dim": candidate.states.shape[1],
            "states": candidate.states.reshape(-1), "controls_rad_s": candidate.controls.reshape(-1),
            "gains": candidate.gains.reshape(-1), "roll_rad": float(roll_now), "target_roll_rad": target_roll,
            "solve_ms": solve_ms, "iterations": candidate.iterations, "cost": max(0.0, candidate.cost),
            "converged": candidate.converged, **self.counters(),
        }
        return step

    def _baseline_step(self, t_s, x, settle_s) -> Step:
        b = self.baseline
        start = time.perf_counter()
        forces = b.command(t_s, x[:13])
        compute_ms = (time.perf_counter() - start) * 1e3
        phase = b.reported_phase
        done = False
        if phase in (Phase.LAND, Phase.DONE):
            done = self._settling(t_s, x, settle_s)
        ref = self.hold_point_m if self.hold_point_m is not None else self.start_point_m
        step = Step(_PHASE_NAMES[phase], done, False, np.array(ref), None)
        if done:
            return step
        self.solves += 1
        kf = self.vehicle.thrust_coefficient_kf
        speeds = np.sqrt(np.maximum(np.asarray(forces, dtype=np.float64), 0.0) / kf)
        dt_s = 2.0 / self.solve_rate_hz  # valid for two periods: the next command replaces it
        step.plan = {
            "method": self.method, "phase": step.phase, "t0_s": t_s, "dt_s": dt_s, "horizon": 1,
            "state_dim": 13, "states": np.concatenate([x[:13], x[:13]]), "controls_rad_s": speeds,
            "gains": np.zeros(4 * 13), "roll_rad": float(b.roll.roll_rad), "target_roll_rad": [float(b.roll.roll_rad)],
            "solve_ms": compute_ms, "iterations": 0, "cost": 0.0, "converged": True, **self.counters(),
        }
        return step

    def counters(self) -> dict:
        return {"solves": self.solves, "failed_solves": self.failed_solves, "overrun_solves": self.overrun_solves}


def _finite(plan) -> bool:
    return bool(np.isfinite(plan.cost) and np.all(np.isfinite(plan.controls)) and np.all(np.isfinite(plan.gains)))


def loop_rate_hz(stack_rate_hz: float, tick_rate_hz: float, solve_rates_hz) -> float:
    """The planner's loop rate for a mission with flips: the smallest rate at least the
    stack's that divides the tick rate and that every solve rate divides."""
    for n in range(int(tick_rate_hz), 0, -1):
        rate = tick_rate_hz / n
        if rate + 1e-9 < stack_rate_hz:
            continue
        if all(abs(rate / r - round(rate / r)) < 1e-9 and r <= rate + 1e-9 for r in solve_rates_hz):
            return rate
    raise ValueError(f"no planner rate divides the tick rate {tick_rate_hz:g} Hz and is a multiple of "
                     f"the solve rates {sorted(solve_rates_hz)} Hz")
