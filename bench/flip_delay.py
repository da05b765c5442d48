"""The flip on the plant alone with a link's delays: what the planner's lead buys.

    .venv/bin/python bench/flip_delay.py [--cases UP_MS/DOWN_MS/MODE ...]

As bench/flip_sim.py (the project's iLQR flip from a hover on the simulator's plant, truth
state, no noise, the motor driver's law at 400 Hz), with a planner across a link: it sees
each state UP ms after it was measured, and its plans reach the driver DOWN ms after they
were made (held until then; the driver flies the newest plan that has started). MODE, how
the planner starts its plan:
  clock   at its own clock, from the state as it was measured (the stack's planner with
          plan_lead_s = 0 carries the state over its age at constant rates: between this and
          `stamp`)
  stamp   at the state's sample time, from that state (time-consistent, nothing predicted)
  lead    DOWN ms ahead of its clock, from the state flown forward on the iLQR's model under
          the plans sent (flight/control/lead.py: the planner's plan_lead_s = DOWN)
Deterministic; prints one line per case: completed, height lost, drift, overshoot, recovery.
"""
from __future__ import annotations

import argparse
import sys
import time
from collections import deque
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from flip_sim import PROJECT_SOLVE_RATE_HZ, SIM, FlipRun, _plant_command, _tick  # noqa: E402

from flight.control.flip import PROJECT_FLIP, FlipPhaseMachine, Phase  # noqa: E402
from flight.control.ilqr import PROJECT, ILQRSolver, feedback_control, warm_start  # noqa: E402
from flight.control.lead import PLANS, make_lead_predictor  # noqa: E402
from flight.motor_model import thrust_step  # noqa: E402
from flight.vehicle import load_vehicle  # noqa: E402
from simulator.plant import Plant  # noqa: E402

MODES = ("clock", "stamp", "lead")
DEFAULT_CASES = ("0/0/clock", "25/25/clock", "25/25/stamp", "25/25/lead", "30/45/clock", "30/45/stamp",
                 "30/45/lead", "50/60/stamp", "50/60/lead")


def simulate(vehicle, solver, lead_predict, up_s: float, down_s: float, mode: str,
             after_recovery_s: float = 1.0, max_time_s: float = 12.0) -> FlipRun:
    rate = SIM.tick_rate_hz
    up, down = round(up_s * rate), round(down_s * rate)
    per_solve = round(rate / PROJECT_SOLVE_RATE_HZ)
    kf = vehicle.thrust_coefficient_kf
    plant = Plant(vehicle)
    machine = FlipPhaseMachine(PROJECT_FLIP, solver.config.horizon, solver.config.dt_s)
    machine.start(0.0, plant.x[:13])
    run = FlipRun()
    forces = plant.motor_thrust_n     # the driver's (and planner's) estimate of the rotor forces
    seen = deque(maxlen=up + 1)       # the states, as the planner will see them up ticks later
    in_flight = deque()               # (tick it reaches the driver, plan, start)
    sent = deque(maxlen=PLANS)        # (start, plan): what the planner sent
    held, last = [], None
    for tick in range(int(max_time_s * rate)):
        t = tick / rate
        x = solver.full_state(plant.x[:13].copy(), forces)
        seen.append(x)
        if tick % per_solve == 0:
            x_seen, t_seen = seen[0], t - (len(seen) - 1) / rate
            if mode == "clock":
                x0, t0 = x_seen, t
            elif mode == "stamp":
                x0, t0 = x_seen, t_seen
            else:
                t0 = t + down / rate
                x0 = lead_predict(x_seen, [(start - t_seen, p) for start, p in sent], t0 - t_seen)
            phase = machine.update(t0, x0)
            if phase == Phase.DONE or (phase == Phase.LAND and t - machine.phase_start_s >= after_recovery_s):
                break
            targets = machine.settle_targets(t0, x0) if phase == Phase.LAND else machine.targets(t0, x0)
            plan = solver.solve(x0, targets, warm=None if last is None else warm_start(last[1], t0 - last[0]))
            run.solves += 1
            if plan.usable or last is None:
                last = (t0, plan)
                sent.append(last)
                in_flight.append((tick + down, plan, t0))
            else:
                run.failed_solves += 1
        while in_flight and in_flight[0][0] <= tick:
            held.append(in_flight.popleft()[1:])
        started = [(p, start) for p, start in held if start <= t + 1e-9]
        if started:
            plan, start = started[-1]
            u = feedback_control(plan, t - start, x, solver.u_max_rad_s)
        else:
            u = np.full(4, solver.u_hover_rad_s)
        run.record(t, plant, machine.phase)
        command = _plant_command(vehicle, kf * u * u)
        _tick(plant, SIM, command)
        forces = thrust_step(forces, command, 1.0 / rate, solver.motor_time_constant_s)
    return run.finish()


def parse_case(text: str) -> tuple[float, float, str]:
    try:
        up, down, mode = text.split("/")
        up_s, down_s = float(up) / 1e3, float(down) / 1e3
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected UP_MS/DOWN_MS/MODE, e.g. 30/45/lead") from None
    if mode not in MODES or up_s < 0 or down_s < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: delays >= 0 and MODE one of {', '.join(MODES)}")
    return up_s, down_s, mode


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", nargs="+", type=parse_case, default=[parse_case(c) for c in DEFAULT_CASES])
    args = p.parse_args(argv)
    print("$", " ".join(["python bench/flip_delay.py", *(argv if argv is not None else sys.argv[1:])]))
    vehicle = load_vehicle("q820")
    solver = ILQRSolver(vehicle, PROJECT)
    lead_predict = make_lead_predictor(vehicle)
    print("| up ms | down ms | mode | completed | loss m | drift m | overshoot deg | recovery s |")
    print("|---|---|---|---|---|---|---|---|")
    for up_s, down_s, mode in args.cases:
        start = time.perf_counter()
        m = simulate(vehicle, solver, lead_predict, up_s, down_s, mode).metrics
        print(f"| {up_s * 1e3:.0f} | {down_s * 1e3:.0f} | {mode} | {'yes' if m.completed else 'no'} | "
              f"{m.altitude_loss_m:.2f} | {m.xy_drift_m:.2f} | {m.overshoot_deg:.1f} | {m.recovery_s:.3f} |"
              f"  ({time.perf_counter() - start:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
