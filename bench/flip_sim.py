"""Closed-loop flip on the simulator plant (truth state, no noise), pure: no services.

    .venv/bin/python bench/flip_sim.py [--which thesis,project,baseline] [--project-rate-hz 100]
        [--climb-m 1.5] [--windup-s 0.3]

The plant runs RK4 at 2 kHz (SimConfig: 400 Hz ticks x 5 substeps) with its 20 ms
motor lag and drag. The MPC re-solves from the true state at solve_rate_hz; at
every 400 Hz tick the rotor speeds u_plan(t) + K(t)(x - x_plan(t)), clipped to the
rotor limits, become thrust kf u^2, PWM through the vehicle's motor map and the
plant's thrust command. When the planner models the motors (PROJECT), its rotor-force
states are estimated from the commands sent (motor_forces_update), not read from the
plant. The baseline's climb to its flip altitude is reported as take-off: its flip (and
the metrics) start with the roll, where Appendix И resets its accumulated roll. A solve that is not usable (non-finite, or neither
converged nor better than its warm start) is counted and the previous plan kept.
The solve is taken as instantaneous (its compute time is reported, not simulated).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from flight.control.flip import heights
from flight.control.flip import (
    PROJECT_FLIP,
    THESIS_BASELINE,
    THESIS_FLIP,
    BaselineConfig,
    BaselineFlip,
    FlipConfig,
    FlipMetrics,
    FlipPhaseMachine,
    Phase,
    RollAccumulator,
    flip_metrics,
)
from flight.control.ilqr import (
    PROJECT,
    THESIS,
    ILQRConfig,
    ILQRSolver,
    feedback_control,
    warm_start,
)
from flight.motor_model import pwm_to_thrust, thrust_to_pwm
from flight.motor_model import thrust_step as motor_forces_update
from flight.vehicle import Vehicle, load_vehicle
from simulator.config import SimConfig
from simulator.plant import Plant

THESIS_SOLVE_RATE_HZ = 20.0    # the thesis's MPC timer (50 ms)
PROJECT_SOLVE_RATE_HZ = 100.0
SIM = SimConfig()
BASELINE = BaselineConfig()


@dataclass
class FlipRun:
    t_s: list = field(default_factory=list)
    position_m: list = field(default_factory=list)
    quaternion: list = field(default_factory=list)
    rate_rad_s: list = field(default_factory=list)
    phase: list = field(default_factory=list)
    solves: int = 0
    failed_solves: int = 0
    solve_s: list = field(default_factory=list)
    metrics: FlipMetrics | None = None

    def record(self, t_s: float, plant: Plant, phase: Phase) -> None:
        self.t_s.append(t_s)
        self.position_m.append(plant.position_m)
        self.quaternion.append(plant.quaternion)
        self.rate_rad_s.append(plant.rate_rad_s)
        self.phase.append(phase)

    def finish(self) -> FlipRun:
        self.metrics = flip_metrics(self.t_s, self.position_m, self.quaternion, self.rate_rad_s, self.phase)
        return self


def _plant_command(vehicle: Vehicle, forces_n) -> np.ndarray:
    """Rotor forces -> PWM (the motors service's map) -> the plant's thrust command."""
    return pwm_to_thrust(vehicle, thrust_to_pwm(vehicle, forces_n))


def _tick(plant: Plant, sim: SimConfig, cmd) -> None:
    """One tick with the plant's thrust command (after _plant_command)."""
    dt_s = 1.0 / sim.tick_rate_hz / sim.physics_substeps
    for _ in range(sim.physics_substeps):
        plant.step(dt_s, cmd, np.zeros(3))


def simulate_mpc(vehicle: Vehicle, planner: ILQRSolver, flip: FlipConfig, solve_rate_hz: float,
                 after_recovery_s: float = 1.0, max_time_s: float = 12.0,
                 sim: SimConfig = SIM) -> FlipRun:
    """Take off from the ground, flip, recover; stop after_recovery_s into the hold that
    follows (the phase machine's land: as the planner service (flight/control/flip_runner.py), a
    hover where it recovered, at the flip's altitude)."""
    ticks_per_solve = round(sim.tick_rate_hz / solve_rate_hz)
    kf = vehicle.thrust_coefficient_kf
    plant = Plant(vehicle)
    machine = FlipPhaseMachine(flip, planner.config.horizon, planner.config.dt_s)
    machine.start(0.0, plant.x[:13])
    run = FlipRun()
    plan, plan_t_s = None, 0.0
    tau = planner.motor_time_constant_s
    forces_est = plant.motor_thrust_n  # the plan's motor states: estimated from the commands
    for tick in range(int(max_time_s * sim.tick_rate_hz)):
        t_s = tick / sim.tick_rate_hz
        x = planner.full_state(plant.x[:13].copy(), forces_est)
        if tick % ticks_per_solve == 0:
            phase = machine.update(t_s, x)
            if phase in (Phase.DONE,) or (phase == Phase.LAND and t_s - machine.phase_start_s >= after_recovery_s):
                break
            if phase == Phase.LAND:  # as the planner service: the hold after recovery
                targets = machine.settle_targets(t_s, x)
            else:
                targets = machine.targets(t_s, x)
            warm = None if plan is None else warm_start(plan, t_s - plan_t_s)
            start = time.perf_counter()
            candidate = planner.solve(x, targets, warm=warm)
            run.solve_s.append(time.perf_counter() - start)
            run.solves += 1
            if candidate.usable or plan is None:
                plan, plan_t_s = candidate, t_s
            else:
                run.failed_solves += 1
        u = feedback_control(plan, t_s - plan_t_s, x, planner.u_max_rad_s)
        run.record(t_s, plant, machine.phase)
        command = _plant_command(vehicle, kf * u * u)
        _tick(plant, sim, command)
        if tau is not None:
            forces_est = motor_forces_update(forces_est, command, 1.0 / sim.tick_rate_hz, tau)
    return run.finish()


def simulate_baseline(vehicle: Vehicle, config: BaselineConfig = BASELINE,
                      after_recovery_s: float = 3.0, max_time_s: float = 15.0,
                      sim: SimConfig = SIM) -> FlipRun:
    plant = Plant(vehicle)
    controller = BaselineFlip(vehicle, config)
    run = FlipRun()
    land_t_s = None
    for tick in range(int(max_time_s * sim.tick_rate_hz)):
        t_s = tick / sim.tick_rate_hz
        forces = controller.command(t_s, plant.x[:13])
        if controller.phase == Phase.LAND:
            land_t_s = t_s if land_t_s is None else land_t_s
            if t_s - land_t_s >= after_recovery_s:
                break
        run.record(t_s, plant, controller.reported_phase)
        _tick(plant, sim, _plant_command(vehicle, forces))
    return run.finish()


def _report(name: str, run: FlipRun) -> str:
    m = run.metrics
    line = (f"{name:9s} completed={m.completed!s:5s} altitude_loss_m={m.altitude_loss_m:6.3f} "
            f"xy_drift_m={m.xy_drift_m:6.3f} overshoot_deg={m.overshoot_deg:6.1f} "
            f"recovery_s={m.recovery_s:6.3f} duration_s={m.duration_s:6.3f}")
    if m.completed:  # heights about the flip's start: its peak, the lowest point after it
        phases = [Phase(p) for p in run.phase]
        start = phases.index(Phase.FLIP)
        end = start + int(round(m.duration_s * SIM.tick_rate_hz))
        z = np.asarray(run.position_m)[start:end + 1, 2] - run.position_m[start][2]
        roll = RollAccumulator()
        roll.reset(run.quaternion[start])
        h = heights(z, [roll.update(q) for q in run.quaternion[start:end + 1]])
        line += f" peak_m={h['peak']:+.2f} lowest_after_peak_m={h['lowest']:+.2f}"
    if run.solves:
        line += (f"  solves={run.solves} failed={run.failed_solves} "
                 f"solve_ms_median={1e3 * np.median(run.solve_s):.1f} max={1e3 * np.max(run.solve_s):.1f}")
    return line


def run_mpc(vehicle: Vehicle, config: ILQRConfig, flip: FlipConfig, rate_hz: float) -> FlipRun:
    return simulate_mpc(vehicle, ILQRSolver(vehicle, config), flip, rate_hz)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--which", default="thesis,project,baseline")
    parser.add_argument("--project-rate-hz", type=float, default=PROJECT_SOLVE_RATE_HZ)
    parser.add_argument("--climb-m", type=float, default=PROJECT_FLIP.climb_m,
                        help="the project flip's climb before the turn (FlipConfig.climb_m)")
    parser.add_argument("--windup-s", type=float, default=PROJECT_FLIP.windup_s,
                        help="... and the time it leaves for it (FlipConfig.windup_s)")
    args = parser.parse_args(argv)
    if args.climb_m < 0 or args.windup_s < 0 or args.project_rate_hz <= 0:
        parser.error("--climb-m and --windup-s must be >= 0, --project-rate-hz > 0")
    project_flip = dataclasses.replace(PROJECT_FLIP, climb_m=args.climb_m, windup_s=args.windup_s)
    vehicle = load_vehicle("q820")
    print("$ .venv/bin/python bench/flip_sim.py " + " ".join(sys.argv[1:] if argv is None else argv))
    which = args.which.split(",")
    if "thesis" in which:
        print(_report(f"thesis@{THESIS_SOLVE_RATE_HZ:g}Hz", run_mpc(vehicle, THESIS, THESIS_FLIP, THESIS_SOLVE_RATE_HZ)))
    if "project" in which:
        print(_report(f"project@{args.project_rate_hz:g}Hz", run_mpc(vehicle, PROJECT, project_flip, args.project_rate_hz)))
    if "baseline" in which:
        print(_report("baseline", simulate_baseline(vehicle)))
        print(_report("baseline@17rad/s", simulate_baseline(vehicle, THESIS_BASELINE)))


if __name__ == "__main__":
    main()
