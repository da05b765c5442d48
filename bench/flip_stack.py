"""The flip of 001 through the whole stack: methods x scenarios x seeds, a table in docs/flip.md.

    .venv/bin/python bench/flip_stack.py [--seeds 3] [--methods ilqr-project,ilqr-thesis,baseline]
        [--scenarios nominal,mass+10%,wind-2m/s,camera-drop-20%] [--state estimate|truth]
        [--mission flip] [--workers 1] [--scheduler tcp://HOST:PORT] [--out runs/flip-stack] [--doc docs/flip.md]

The flights are a `zenpilot sweep` (deploy/sweep.py): every flight `zenpilot fly --lockstep`
(every service its own process) of the flip mission, the method swept as
`planner.flip_method`, as tasks on a Dask LocalCluster of --workers processes (or the cluster
of --scheduler); a flight already in --out from the same command is not flown again, and
--out/sweep.csv and sweep.parquet hold every flight's metrics. Each flight's metrics.json's
`flip` object (flight/control/flip.flip_metrics on the simulator truth) is tabulated as
median (worst) over the completed flights of the seeds. Scenarios (deploy/sweep.SCENARIOS):
+10 % mass (the plant's only: sim.mass_scale, the planner keeps the airframe file's 0.82 kg),
a 2 m/s wind across the roll (world y), 20 % of camera frames lost. `--state estimate`
(default): the stack's own estimators (the attitude level's gyro carrier through the
inversion, see flight/estimation/gyro_carrier.GyroCarrier), so the seeds change the sensor noise the
controllers read. `--state truth` (the ablation): the camera is not used by the
controllers and the seeds change only sensor noise nobody reads: flights repeat.
Lockstep: solve times are wall-clock measurements of this machine under its load (two
workers: each flight's solves with another flight beside it).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from deploy.sweep import SCENARIOS, expand_grid, run_sweep  # noqa: E402

TRUTH_STATE = ["attitude.state_source=truth", "position.state_source=truth", "sim.truth_rate_hz=200"]
METHODS = ("ilqr-project", "ilqr-thesis", "baseline")
TABLE_BEGIN, TABLE_END = "<!-- flip_stack table -->", "<!-- end of flip_stack table -->"
FIELDS = ("altitude_loss_m", "xy_drift_m", "overshoot_deg", "recovery_s", "duration_s")


def summary(values: list) -> str:
    """median (worst) of the values; larger is worse for every tabulated figure."""
    vals = [v for v in values if v is not None]
    if not vals:
        return "-"
    med = statistics.median(vals)
    if len(vals) == 1:
        return f"{med:.2f}"
    return f"{med:.2f} ({max(vals):.2f})"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--scenarios", default=",".join(SCENARIOS))
    p.add_argument("--state", choices=("estimate", "truth"), default="estimate")
    p.add_argument("--workers", "--jobs", type=int, default=1, dest="workers",
                   help="flights at a time on a Dask LocalCluster (solve times suffer)")
    p.add_argument("--scheduler", help="a Dask scheduler's address: fly on its cluster")
    p.add_argument("--tabulate-only", action="store_true",
                   help="fly nothing: tabulate the flights found in --out (missing ones are left out of n)")
    p.add_argument("--mission", default="flip")
    p.add_argument("--out", default="runs/flip-stack")
    p.add_argument("--doc", default="docs/flip.md")
    args = p.parse_args(argv)
    methods, scenarios = args.methods.split(","), args.scenarios.split(",")
    grid = expand_grid([args.mission], f"0-{args.seeds - 1}", [f"planner.flip_method={args.methods}"],
                       [args.scenarios], TRUTH_STATE if args.state == "truth" else None)
    out = ROOT / args.out
    wall0 = time.monotonic()
    flown = 0
    if not args.tabulate_only:
        sweep_rows = run_sweep(grid, out, workers=args.workers, scheduler=args.scheduler, metric="flip.altitude_loss_m")
        flown = sum(1 for r in sweep_rows if not r.get("resumed"))
    results = {}
    for f in grid.flights:
        path = out / f.id / "metrics.json"
        m = json.loads(path.read_text()) if path.exists() else None
        fl = (m or {}).get("flip") or {}
        results[(f.values()["planner.flip_method"], f.scenario, f.seed)] = None if m is None else (m, fl)
        if m is not None:
            print(f"{f.id:60s} completed={fl.get('completed')} "
                  + " ".join(f"{k}={fl.get(k) if fl.get(k) is None else round(fl[k], 3)}" for k in FIELDS)
                  + f"  crashed={m.get('crashed')}", flush=True)
    rows = []
    for method in methods:
        for scenario in scenarios:
            runs = [results[(method, scenario, seed)] for seed in range(args.seeds)
                    if results[(method, scenario, seed)] is not None]
            flips = [f for _, f in runs]
            ok = [f for (m, f) in runs if f.get("completed") and m and not m.get("crashed")]
            rows.append({
                "method": method, "scenario": scenario, "n": len(runs), "completed": len(ok),
                "missions": sum(1 for m, _ in runs if m and m.get("completed") and not m.get("crashed")),
                **{k: summary([f.get(k) for f in ok]) for k in FIELDS},
                "solve_ms_p50": summary([f.get("solve_ms_p50") for f in flips if f.get("method") != "baseline"]),
                "plan_rate_hz": summary([f.get("plan_rate_hz") for f in flips]),
                "failed_solves": sum(f.get("failed_solves") or 0 for f in flips),
                "fallbacks": sum(sum((f.get("motor_fallbacks") or {}).values()) for f in flips),
            })
    head = ("| method | scenario | completed | missions completed | altitude loss m | XY drift m | overshoot deg "
            "| recovery s "
            "| duration s | solve ms p50 | plans/s | failed solves | motor fallback ticks |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        lines.append(f"| {r['method']} | {r['scenario']} | {r['completed']}/{r['n']} | {r['missions']}/{r['n']} | "
                     + " | ".join(r[k] for k in FIELDS)
                     + f" | {r['solve_ms_p50']} | {r['plan_rate_hz']} | {r['failed_solves']} | {r['fallbacks']} |")
    table = "\n".join(lines)
    cmd = "$ .venv/bin/python bench/flip_stack.py " + " ".join(sys.argv[1:] if argv is None else argv)
    doc = ROOT / args.doc
    generated = (
        "Generated by `bench/flip_stack.py` (see its docstring). Lockstep, every service a process; "
        f"state: {args.state}; mission `{args.mission}` (q820, flip at 5 m). Figures: median (worst) "
        "over the completed flights (flight.control.flip.flip_metrics on the simulator truth); a flight counts "
        "as completed when the flip recovered and the vehicle did not crash; missions completed: the "
        "whole mission too (the flip item handed back after its hold, the hold after it flown).\n\n"
        f"    {cmd}\n\n{table}\n\n"
        f"{sum(r['n'] for r in rows)} flights"
        + (f" ({flown} flown in {time.monotonic() - wall0:.0f} s of wall time, {args.workers} at a time)"
           if flown else "") + f"; every flight's metrics in {args.out}/sweep.csv.\n")
    # the table goes between the markers; what the doc says around it is kept
    text = doc.read_text() if doc.exists() else ""
    if TABLE_BEGIN in text and TABLE_END in text:
        head, rest = text.split(TABLE_BEGIN, 1)
        text = head + TABLE_BEGIN + "\n" + generated + TABLE_END + rest.split(TABLE_END, 1)[1]
    else:
        text = f"# The flip of 001 through the stack\n\n{TABLE_BEGIN}\n{generated}{TABLE_END}\n" + text
    doc.write_text(text)
    print(table)
    print(f"wrote {doc}")


if __name__ == "__main__":
    main()
