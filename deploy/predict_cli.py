"""`zenpilot predict`: a mission's flips predicted before they are flown (flight/control/predict.py).

For each flip item of the mission: the flip flown once on the planner's model by the
planner's own controller, and by the same controller on the vehicles at the knots of each drawn
parameter (20 flights for the default uncertainty), then N closed-loop rollouts on vehicles
drawn from the uncertainty (mass, inertia, thrust coefficient, motor lag, wind and gusts,
control delay, the start state's error), batched in JAX, each replaying the plans and feedback
gains the controller flies on its vehicle (interpolated between the knots). Prints the predicted
distribution of each flip figure (5th / 50th / 95th percentile), the probabilities of a crash
and of touching the ground, and whether the planner would refuse the item (its predicted
95th-percentile loss from the hover leaves less than the clearance). Exit 1 when an item
would be refused.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

FIGURES = (("loss_from_turn_m", "altitude loss from the turn's start", "m"),
           ("loss_from_hover_m", "altitude loss from the hover height", "m"),
           ("xy_drift_m", "XY drift", "m"),
           ("overshoot_deg", "overshoot", "deg"),
           ("recovery_s", "recovery time", "s"))


def add_parser(sub) -> None:
    from flight.control.predict import Uncertainty
    d = Uncertainty()
    p = sub.add_parser("predict", help="predict a mission's flips before flying them (batched JAX rollouts)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mission", default="flip", help="mission name or file (default: flip)")
    p.add_argument("--rollouts", "-n", type=int, default=1000, help="cases drawn per flip (default 1000)")
    p.add_argument("--seed", type=int, default=0, help="seed of the draws (default 0)")
    p.add_argument("--clearance-m", type=float, default=0.5,
                   help="height to keep above the ground at the 95th percentile (default 0.5)")
    p.add_argument("--mass-scale", type=float, default=d.mass_scale,
                   help="the mass's centre, times the vehicle file's (default 1; 1.1: a 10 %% payload)")
    p.add_argument("--mass-frac", type=float, default=d.mass_frac, help=f"mass +- fraction (default {d.mass_frac:g})")
    p.add_argument("--inertia-frac", type=float, default=d.inertia_frac,
                   help=f"inertia +- fraction per axis (default {d.inertia_frac:g})")
    p.add_argument("--thrust-frac", type=float, default=d.thrust_coefficient_frac,
                   help=f"thrust coefficient +- fraction (default {d.thrust_coefficient_frac:g})")
    p.add_argument("--motor-lag-frac", type=float, default=d.motor_lag_frac,
                   help=f"motor time constant +- fraction (default {d.motor_lag_frac:g})")
    p.add_argument("--wind-m-s", type=float, default=d.wind_m_s, help=f"steady wind up to, m/s (default {d.wind_m_s:g})")
    p.add_argument("--gust-m-s", type=float, default=d.gust_m_s, help=f"gusts, 1 sigma per axis, m/s (default {d.gust_m_s:g})")
    p.add_argument("--delay-ms", type=float, default=d.delay_max_s * 1e3,
                   help=f"control delay up to, ms (default {d.delay_max_s * 1e3:g})")
    p.add_argument("--replay", action="store_true",
                   help="every case replays the nominal's plans and gains: no flights on the knots (faster), "
                        "pessimistic on a stronger vehicle (the planner's flip_predict_adapt=false)")
    p.add_argument("--replan", action="store_true",
                   help="every case re-plans as flown: the planner's own iLQR solve from the case's state at the "
                        "controller's rate inside the rollouts (flight/control/replan.py; no flights on the knots). "
                        "The closest model of the flown flips, and slow: ~40 min for 1000 on a 2-core CPU, for a GPU "
                        "(docs/flip-history.md)")
    p.add_argument("--json", metavar="FILE", help="also write the summary per flip item as JSON")
    p.add_argument("--compile-cache-dir", metavar="DIR", default="",
                   help="keep the compiled solver and rollouts in DIR (JAX's persistent cache, as the planner's "
                        "compile_cache_dir, e.g. ~/.cache/zenpilot/jax): a later run loads them instead of "
                        "compiling (default: compile every run)")
    p.set_defaults(func=cmd_predict)


def cmd_predict(args) -> int:
    from flight.control.predict import PredictError, Uncertainty, build_predictor
    from flight.control.replan import Replan
    from flight.vehicle import load_vehicle
    from services.stack import load_mission

    if args.rollouts < 1:
        raise ValueError(f"predict: --rollouts must be >= 1 (got {args.rollouts})")
    if not (math.isfinite(args.clearance_m) and args.clearance_m >= 0):
        raise ValueError(f"predict: --clearance-m must be >= 0 (got {args.clearance_m!r})")
    try:
        uncertainty = Uncertainty(mass_scale=args.mass_scale, mass_frac=args.mass_frac, inertia_frac=args.inertia_frac,
                                  thrust_coefficient_frac=args.thrust_frac, motor_lag_frac=args.motor_lag_frac,
                                  wind_m_s=args.wind_m_s, gust_m_s=args.gust_m_s, delay_max_s=args.delay_ms / 1e3)
    except PredictError as exc:
        raise ValueError(f"predict: {exc}") from None
    if args.replan and args.replay:
        raise ValueError("predict: --replan and --replay are two models: ask for one")
    mission = load_mission(args.mission)
    vehicle = load_vehicle(mission.vehicle)
    flips = [(i, item) for i, item in enumerate(mission.items) if item["type"] == "flip"]
    if not flips:
        raise ValueError(f"predict: mission {mission.name!r} has no flip item")
    if args.compile_cache_dir:
        from flight.control.ilqr import use_compile_cache
        try:
            use_compile_cache(args.compile_cache_dir)
        except OSError as exc:
            raise ValueError(f"predict: --compile-cache-dir: {exc}") from None
    import jax
    device = jax.devices()[0]
    print(f"$ zenpilot predict {' '.join(sys.argv[2:])}".rstrip())
    print(f"mission {mission.name} on {vehicle.name}: {len(flips)} flip(s), {args.rollouts} rollouts each, "
          f"JAX on {device.platform} ({device.device_kind})")
    refused, out = 0, []
    for index, item in flips:
        try:
            kwargs = {"replan": Replan(100.0, linearise="solver")} if args.replan else {}
            predictor = build_predictor(vehicle, item["method"], item["altitude_m"], uncertainty,
                                        adapt=not args.replay, **kwargs)
        except PredictError as exc:
            print(f"item {index} ({item['method']}): cannot predict: {exc}")
            out.append({"item": index, "method": item["method"], "error": str(exc)})
            continue
        result = predictor.predict(args.rollouts, args.seed)
        reason = result.refusal(args.clearance_m)
        refused += reason is not None
        print(f"\nitem {index}: {item['method']} flip from {item['altitude_m']:g} m "
              f"(nominal flight {predictor.nominal_s:.1f} s, solver compile and {predictor.nominal.solves} iLQR solves; "
              + ("each case re-planning as flown; " if args.replan else
                 f"{result.anchor_flights} flights on the knots' vehicles in {result.anchor_s:.1f} s; ") +
              f"rollouts compiled in {result.compile_s:.2f} s, "
              f"{args.rollouts} rollouts in {result.rollout_s:.2f} s)")
        print(f"  {'figure':<38} {'p5':>8} {'median':>8} {'p95':>8}")
        for name, label, unit in FIGURES:
            p5, p50, p95 = result.band(name)
            print(f"  {label + ' (' + unit + ')':<38} {p5:8.3f} {p50:8.3f} {p95:8.3f}")
        print(f"  P(crash) {result.crash_probability:.3f}   P(touches the ground) {result.ground_probability:.3f}   "
              f"P(recovered and level within the window) {result.recovered_probability:.3f}")
        print(f"  verdict: {'REFUSED: ' + reason if reason else 'may fly'}")
        out.append({"item": index, "method": item["method"], **result.summary(), "refused": reason})
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"mission": mission.name, "vehicle": vehicle.name,
                                               "seed": args.seed, "items": out}, indent=2))
    return 1 if refused else 0
