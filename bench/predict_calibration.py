"""Is `zenpilot predict` calibrated? Flown flips against the predicted 5-95 % bands.

    .venv/bin/python bench/predict_calibration.py [--flights 20] [--rollouts 1000]
        [--rows nominal,mass+10%,wind-2m/s] [--replay] [--cases] [--oracle K]
        [--flight-seed 1000] [--cache DIR] [--fly-only]
        [--replan HZ [--replan-iterations 1] [--replan-horizon H] [--replan-hold-s 0.8]]

For each row: the prediction (flight/control/predict.py: per case, the controller's policy on its
vehicle, over --rollouts drawn cases; --replay: the nominal's plans and gains in every case, as
before 2026-12-05), then --flights other cases drawn from the same uncertainty, each
flown by the planner's full controller (flight/control/flip_runner.FlipController: the phase machine
and the iLQR re-solved at 100 Hz from the state) on the simulator's plant (simulator/plant.py:
RK4 at 2 kHz, its own motor lag and drag), with the case's mass, inertia, thrust, motor lag,
wind and gusts, control delay and start error, on the true state. Prints, per flip figure,
the fraction of flown flips inside the predicted band (target: >= 90 %), how many fell below
and above it, and the rollouts' own figure for the same cases beside the flown one (paired:
the mean |flown - rollout|; --cases: every case). With 20 flights a calibrated band holds
>= 18 in 68 % of figures (binomial, p = 0.9); the pooled count over all figures and rows is the
steadier check. --oracle K: the first K cases also replay the controller's flight on their own
vehicle (what the anchors interpolate), which splits flown - rollout into the interpolation's
part and the rest (plant, sampling, metrics: the flown controller against its policy replayed).
--flight-seed S: row r's flights are drawn with seed S + r (1000: the calibration set; another S,
flights the prediction was not tuned on). --cache DIR: each flown flight's figures kept in DIR
(one JSON file per row, seed and count; the flights are lockstep, so the same bytes every run),
a re-run flies only those missing; --fly-only: fill the cache, no prediction.
--replan HZ: the re-planning rollouts (flight/control/replan.py: each case re-plans from its
state at HZ, no anchors) instead of the replayed policies.

This calibrates the predictor against re-planning on the simulator's plant; the stack's
estimators and transport are not in these flights.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from flight import motor_model
from flight.control.flip import Phase, RollAccumulator, flip_metrics, heights
from flight.control.flip_runner import FlipController
from flight.control.predict import (TICK_RATE_HZ, Predictor, Uncertainty, draw_cases, fly_nominal,
                                    metrics_from_series)
from flight.control.replan import Replan
from flight.vehicle import load_vehicle
from simulator.config import SimConfig
from simulator.plant import Plant

ROWS = {
    "nominal": Uncertainty(),
    "mass+10%": dataclasses.replace(Uncertainty(), mass_scale=1.1, mass_frac=0.02),
    "wind-2m/s": dataclasses.replace(Uncertainty(), wind_m_s=2.0),
}
FIGURES = ("loss_from_turn_m", "loss_from_hover_m", "xy_drift_m", "overshoot_deg", "recovery_s")
SIM = SimConfig()


def fly_case(controller: FlipController, vehicle, cases: dict, i: int, ticks: int, uncertainty: Uncertainty,
             altitude_m: float = 5.0):
    """One flip of the full controller on the simulator's plant with case i's vehicle and air."""
    dt = 1.0 / TICK_RATE_HZ
    sub = SIM.physics_substeps if abs(SIM.tick_rate_hz - TICK_RATE_HZ) < 1e-9 else 5
    plant_vehicle = dataclasses.replace(
        vehicle, mass_kg=float(cases["mass"][i]), inertia_kg_m2=tuple(float(v) for v in cases["inertia"][i]),
        motor_time_constant_s=float(cases["tau"][i]))
    hover = np.full(4, vehicle.hover_thrust_per_motor_n)
    err = cases["start_error"][i].astype(np.float64)
    plant = Plant(plant_vehicle, position_m=(err[0], err[1], altitude_m + err[2]), motor_thrust_n=hover,
                  velocity_m_s=err[3:6], rate_rad_s=err[6:9])
    dq = cases["start_dq"][i].astype(np.float64)
    plant.x[6:10] = dq / np.linalg.norm(dq)
    kf, u_max = vehicle.thrust_coefficient_kf, float(vehicle.max_rotor_speed_rad_s)
    tau = controller.motor_time_constant_s
    ratio = max(1, round(TICK_RATE_HZ / controller.solve_rate_hz))
    delay = int(cases["delay_ticks"][i])
    est = hover.copy()
    x0 = np.concatenate([plant.x[:13], est]) if controller.state_dim == 17 else plant.x[:13].copy()
    controller.start(0.0, x0, altitude_m)
    buffer = [None] * (delay + 1)
    gust = np.zeros(3)
    gust_decay = np.exp(-dt / uncertainty.gust_time_s) if uncertainty.gust_m_s > 0 else 0.0
    gust_gain = uncertainty.gust_m_s * np.sqrt(1.0 - gust_decay ** 2)
    rows = {"t": [], "p": [], "q": [], "w": [], "phase": []}
    for tick in range(ticks):
        t = tick * dt
        x = np.concatenate([plant.x[:13], est]) if controller.state_dim == 17 else plant.x[:13].copy()
        s = controller.step(t, x, 0.5, solve=tick % ratio == 0)
        rows["t"].append(t)
        rows["p"].append(plant.position_m)
        rows["q"].append(plant.quaternion)
        rows["w"].append(plant.rate_rad_s)
        rows["phase"].append(controller.machine.phase.value)
        if s.done:
            break
        u = _feedback(controller, t, x, u_max)
        command = kf * u * u
        buffer = [command] + buffer[:-1]
        applied = next(c for c in buffer if c is not None) if buffer[delay] is None else buffer[delay]
        wind = cases["wind"][i] + gust
        for _ in range(sub):
            plant.step(dt / sub, applied * float(cases["thrust_scale"][i]), wind)
        if tau is not None:   # the motor driver's model of its motors (services/motors.py)
            est = motor_model.thrust_step(est, command, dt, tau)
        gust = gust * gust_decay + gust_gain * cases["gust_noise"][i, min(tick, cases["gust_noise"].shape[1] - 1)]
    m = flip_metrics(rows["t"], rows["p"], rows["q"], rows["w"], rows["phase"])
    p = np.asarray(rows["p"])
    start = rows["phase"].index(Phase.FLIP.value) if Phase.FLIP.value in rows["phase"] else 0
    turn_loss = hover_loss = float("nan")
    if m.completed:
        end = start + int(round(m.duration_s * TICK_RATE_HZ)) + 1
        roll = RollAccumulator()
        roll.reset(rows["q"][start])
        turn_loss = heights(p[start:end, 2] - p[start, 2], [roll.update(q) for q in rows["q"][start:end]])["turn_loss"]
        hover_loss = altitude_m - float(p[start:end, 2].min())
    return {"completed": m.completed, "loss_from_turn_m": turn_loss, "loss_from_hover_m": hover_loss,
            "xy_drift_m": m.xy_drift_m, "overshoot_deg": m.overshoot_deg, "recovery_s": m.recovery_s}


def oracle_figures(predictor, nominal, cases: dict, k: int, controller) -> dict:
    """The figures of the first k cases with each replaying the policy the controller flies on
    that case's own vehicle (flight/control/predict.fly_nominal on its mass, inertia, thrust
    and motor lag, no wind), with the case's wind, gusts, delay and start error: what the
    rollouts would give if the anchors' interpolation were exact."""
    from flight.control.predict import _tables
    tables = []
    for i in range(k):
        plant = {"mass": cases["mass"][i], "inertia": cases["inertia"][i].copy(), "tau": cases["tau"][i],
                 "thrust_scale": cases["thrust_scale"][i], "wind": np.zeros(3, np.float32)}
        flight = fly_nominal(nominal.vehicle, nominal.method, nominal.altitude_m, controller=controller, plant=plant)
        tables.append(_tables(flight, nominal.ticks))
    out = []
    for i, (u_plan, gains, x_plan) in enumerate(tables):
        one = {key: value[i:i + 1] for key, value in cases.items() if key != "weights"}
        one["weights"] = np.ones((1, 1), np.float32)
        out.append(np.asarray(predictor._rollouts(one, u_plan[None].astype(np.float32), gains[None].astype(np.float32),
                                                  x_plan[None].astype(np.float32),
                                                  nominal.x0.astype(np.float32)), dtype=np.float64))
    m = metrics_from_series(np.concatenate(out), nominal.flip_tick, nominal.tick_s, nominal.altitude_m)
    return {name: m[name] for name in FIGURES}


def flown_figures(controller, vehicle, cases: dict, flights: int, ticks: int, uncertainty: Uncertainty,
                  cache: Path | None, row: str, seed: int) -> list[dict]:
    """The flights of the row's cases, from the cache where flown before (lockstep: the same
    figures every time), each new one written at once (an interrupted run keeps what it flew)."""
    path = None if cache is None else cache / f"{row.replace('/', '_')}-seed{seed}-n{flights}.json"
    done = json.loads(path.read_text()) if path is not None and path.exists() else {}
    out = []
    for i in range(flights):
        if str(i) not in done:
            f = fly_case(controller, vehicle, cases, i, ticks, uncertainty)
            done[str(i)] = {k: bool(v) if k == "completed" else float(v) for k, v in f.items()}
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(json.dumps(done))
        out.append(done[str(i)])
    return out


def _feedback(controller, t, x, u_max):
    from flight.control.ilqr import feedback_control
    return feedback_control(controller.plan, t - controller.plan_t_s, x, u_max)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--flights", type=int, default=20)
    parser.add_argument("--rollouts", type=int, default=1000)
    parser.add_argument("--rows", default=",".join(ROWS))
    parser.add_argument("--replay", action="store_true", help="the nominal's policy in every case (no anchors)")
    parser.add_argument("--cases", action="store_true", help="print every case's flown and rollout figures")
    parser.add_argument("--oracle", type=int, default=0, metavar="K",
                        help="also fly the controller on the first K cases' own vehicles (no wind) and "
                             "replay that policy with the case's noise: splits flown - rollout into "
                             "the anchors' interpolation (oracle - rollout) and the rest (flown - oracle)")
    parser.add_argument("--flight-seed", type=int, default=1000,
                        help="row r's flights drawn with this seed + r (default 1000, the calibration set)")
    parser.add_argument("--cache", type=Path, help="keep the flown flights' figures here; fly only the missing")
    parser.add_argument("--fly-only", action="store_true", help="fly (and cache) the flights, no prediction")
    parser.add_argument("--replan", type=float, default=0.0, metavar="HZ",
                        help="re-planning rollouts at this rate (flight/control/replan.py; 0: the replayed policies)")
    parser.add_argument("--replan-iterations", type=int, default=1)
    parser.add_argument("--replan-horizon", type=int, default=None)
    parser.add_argument("--replan-hold-s", type=float, default=0.8)
    parser.add_argument("--replan-linearise", choices=("case", "nominal", "solver"), default="case")
    parser.add_argument("--replan-alphas", default="1,0.5,0.25")
    args = parser.parse_args(argv)
    rows = args.rows.split(",")
    unknown = [r for r in rows if r not in ROWS]
    if unknown or args.flights < 1 or args.rollouts < 1 or not 0 <= args.oracle <= args.flights:
        parser.error(f"--rows from {', '.join(ROWS)}; --flights, --rollouts >= 1; 0 <= --oracle <= --flights "
                     f"(got {unknown or ''})")
    print("$ .venv/bin/python bench/predict_calibration.py " + " ".join(sys.argv[1:] if argv is None else argv))
    vehicle = load_vehicle("q820")
    controller = FlipController(vehicle, "ilqr-project")
    nominal = fly_nominal(vehicle, "ilqr-project", 5.0, controller=controller)
    print(f"\n| row | figure | predicted p5 / p50 / p95 | flown min / median / max | flown inside the band "
          f"(below, above) | mean abs(flown - rollout), same cases |")
    print("|---|---|---|---|---|---|")
    pooled, total, details, oracles = 0, 0, [], []
    for r, row in enumerate(rows):
        uncertainty = ROWS[row]
        r = list(ROWS).index(row)   # the row's seed whichever rows are asked for
        cases, _ = draw_cases(vehicle, nominal, args.flights, uncertainty, seed=args.flight_seed + r)
        start = time.perf_counter()
        flown = flown_figures(controller, vehicle, cases, args.flights, nominal.ticks, uncertainty, args.cache,
                              row, args.flight_seed + r)
        wall = time.perf_counter() - start
        if args.fly_only:
            print(f"| {row} | flown | {args.flights} flights in {wall:.0f} s | | | |")
            continue
        replan = None if not args.replan else Replan(
            args.replan, args.replan_iterations, args.replan_horizon, args.replan_hold_s,
            tuple(float(a) for a in args.replan_alphas.split(",")), args.replan_linearise)
        predictor = Predictor(nominal, uncertainty, controller=controller, adapt=not args.replay, replan=replan)
        prediction = predictor.predict(args.rollouts, seed=0)
        # the rollouts of the very cases flown: where the model departs from the flights
        cases["weights"] = predictor.policy.weights(vehicle, uncertainty, cases)
        paired = metrics_from_series(np.asarray(predictor._rollouts(cases, *predictor.tables()), dtype=np.float64),
                                     nominal.flip_tick, nominal.tick_s, nominal.altitude_m)
        if args.oracle:
            oracles.append((row, flown[:args.oracle], {k: v[:args.oracle] for k, v in paired.items()},
                            oracle_figures(predictor, nominal, cases, args.oracle, controller)))
        for name in FIGURES:
            low, mid, high = prediction.band(name)
            values = np.array([f[name] for f in flown], dtype=np.float64)
            below, above = int(np.sum(values < low - 1e-3)), int(np.sum(values > high + 1e-3))
            inside = len(values) - below - above
            pooled, total = pooled + inside, total + len(values)
            print(f"| {row} | {name} | {low:.3f} / {mid:.3f} / {high:.3f} | "
                  f"{np.nanmin(values):.3f} / {np.nanmedian(values):.3f} / {np.nanmax(values):.3f} | "
                  f"{inside}/{len(values)} ({below}, {above}) | {np.nanmean(np.abs(values - paired[name])):.3f} |")
            details.append((row, name, values, paired[name], low, high))
        completed = sum(f["completed"] for f in flown)
        print(f"| {row} | completed | P(recovered) {prediction.recovered_probability:.2f}, "
              f"P(crash) {prediction.crash_probability:.3f} | {completed}/{len(flown)} flown completed "
              f"({wall:.0f} s) | | |")
        print(f"| {row} | timing | {args.rollouts} rollouts in {prediction.rollout_s:.2f} s after a "
              f"{prediction.compile_s:.1f} s compile; {prediction.anchor_flights} anchor flights in "
              f"{prediction.anchor_s:.1f} s | | | |")
    if args.fly_only:
        return
    print(f"\npooled: {pooled}/{total} flown figures inside their band ({pooled / total:.1%})")
    if oracles:
        print(f"\n| row | figure | cases | mean flown - rollout | mean oracle - rollout (the anchors) | "
              f"mean flown - oracle (the rest) |")
        print("|---|---|---|---|---|---|")
        for row, flown, paired, oracle in oracles:
            for name in FIGURES:
                f = np.array([x[name] for x in flown], dtype=np.float64)
                print(f"| {row} | {name} | {len(f)} | {np.nanmean(f - paired[name]):+.3f} | "
                      f"{np.nanmean(oracle[name] - paired[name]):+.3f} | {np.nanmean(f - oracle[name]):+.3f} |")
    if args.cases:
        for row, name, values, paired_values, low, high in details:
            print(f"\n{row} {name} band {low:.3f} .. {high:.3f}")
            print("  flown   " + " ".join(f"{v:7.3f}" for v in values))
            print("  rollout " + " ".join(f"{v:7.3f}" for v in paired_values))
            print("  outside " + " ".join("  below" if v < low - 1e-3 else "  above" if v > high + 1e-3 else "       "
                                          for v in values))


if __name__ == "__main__":
    main()
