"""The flip of 001 through the whole stack: methods x scenarios x seeds, a table in docs/flip.md.

    .venv/bin/python bench/flip_stack.py [--seeds 3] [--methods ilqr-project,ilqr-thesis,baseline]
        [--scenarios nominal,mass+10%,wind-2m/s,camera-drop-20%] [--state estimate|truth]
        [--mission flip] [--jobs 1] [--out runs/flip-stack] [--doc docs/flip.md]

Every flight is `zenpilot fly --lockstep` (every service its own process) of the flip
mission, the method chosen with `--set planner.flip_method=...`; its metrics.json's
`flip` object (flight/flip.flip_metrics on the simulator truth) is tabulated as
median (worst) over the completed flights of the seeds. Scenarios: +10 % mass (the plant's only: sim.mass_scale,
the planner keeps the airframe file's 0.82 kg), a 2 m/s wind across the roll (world y),
20 % of camera frames lost. `--state estimate` (default): the stack's own estimators
(the attitude level's gyro carrier through the inversion, see
flight/attitude_filter.GyroCarrier), so the seeds change the sensor noise the
controllers read. `--state truth` (the ablation): the camera is not used by the
controllers and the seeds change only sensor noise nobody reads: flights repeat.
Lockstep: solve times are wall-clock measurements of this machine under its load.
"""
from __future__ import annotations

import argparse
import concurrent.futures
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

TRUTH_STATE = ["--set", "attitude.state_source=truth", "--set", "position.state_source=truth",
               "--set", "sim.truth_rate_hz=200"]
SCENARIOS = {
    "nominal": [],
    "mass+10%": ["--set", "sim.mass_scale=1.1"],
    "wind-2m/s": ["--set", "sim.wind_m_s=[0.0,2.0,0.0]"],
    "camera-drop-20%": ["--set", "sim.camera_drop_rate=0.2"],
}
METHODS = ("ilqr-project", "ilqr-thesis", "baseline")
TABLE_BEGIN, TABLE_END = "<!-- flip_stack table -->", "<!-- end of flip_stack table -->"
FIELDS = ("altitude_loss_m", "xy_drift_m", "overshoot_deg", "recovery_s", "duration_s")


def fly(mission: str, out: Path, seed: int, extra: list[str]) -> dict | None:
    argv = [sys.executable, "-m", "deploy.cli", "fly", "--mission", mission, "--lockstep",
            "--seed", str(seed), "--out", str(out), *extra]
    subprocess.run(argv, cwd=ROOT, capture_output=True, text=True)
    path = out / "metrics.json"
    return json.loads(path.read_text()) if path.exists() else None


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
    p.add_argument("--jobs", type=int, default=1, help="flights in parallel (solve times suffer)")
    p.add_argument("--reuse", action="store_true", help="take a flight's metrics.json from --out when there")
    p.add_argument("--tabulate-only", action="store_true",
                   help="fly nothing: tabulate the flights found in --out (missing ones are left out of n)")
    p.add_argument("--mission", default="flip")
    p.add_argument("--out", default="runs/flip-stack")
    p.add_argument("--doc", default="docs/flip.md")
    args = p.parse_args(argv)
    state = TRUTH_STATE if args.state == "truth" else []
    rows = []
    wall0 = time.monotonic()
    # seed-major: a run cut short still has every method and scenario at the first seeds
    cases = [(method, scenario, seed) for seed in range(args.seeds) for method in args.methods.split(",")
             for scenario in args.scenarios.split(",")]

    def one(case):
        method, scenario, seed = case
        out = ROOT / args.out / f"{method}-{scenario.replace('/', '_').replace('%', 'pct')}-seed{seed}"
        t0 = time.monotonic()
        done = out / "metrics.json"
        m = None
        if args.tabulate_only or (args.reuse and done.exists()):
            m = json.loads(done.read_text()) if done.exists() else None
            # a flight of another mission or state source (truth flights have no estimation figures)
            # is not reused
            if m is not None and ((m.get("estimation") is not None) != (args.state == "estimate")
                                  or m.get("mission") != Path(args.mission).stem):
                m = None
            if m is None and args.tabulate_only:
                return None
        if m is None:
            m = fly(args.mission, out, seed, [*state, "--set", f"planner.flip_method={method}", *SCENARIOS[scenario]])
        f = (m or {}).get("flip") or {}
        print(f"{method:13s} {scenario:16s} seed {seed:2d}: completed={f.get('completed')} "
              + " ".join(f"{k}={f.get(k) if f.get(k) is None else round(f[k], 3)}" for k in FIELDS)
              + f"  crashed={(m or {}).get('crashed')}  ({time.monotonic() - t0:.0f} s)", flush=True)
        return m, f

    with concurrent.futures.ThreadPoolExecutor(max(1, args.jobs)) as pool:
        results = dict(zip(cases, pool.map(one, cases)))
    for method in args.methods.split(","):
        for scenario in args.scenarios.split(","):
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
        "over the completed flights (flight.flip.flip_metrics on the simulator truth); a flight counts "
        "as completed when the flip recovered and the vehicle did not crash; missions completed: the "
        "whole mission too (the flip item handed back after its hold, the hold after it flown).\n\n"
        f"    {cmd}\n\n{table}\n\n"
        f"{sum(r['n'] for r in rows)} flights"
        + ("" if args.tabulate_only or args.reuse else f" in {time.monotonic() - wall0:.0f} s of wall time") + ".\n")
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
