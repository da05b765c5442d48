"""Benchmark the whole stack on this machine: real-time rates, period jitter,
imu->pwm latency and CPU; lockstep speed as simulated seconds per wall second.

    python bench/stack.py [--mission hover] [--out runs/bench]

Each figure is printed beside its target. Wall-clock figures depend on the
machine and its load; run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from deploy.flightlog import read_log  # noqa: E402

SERVICES = ("sim", "motors", "attitude", "position", "planner", "vision")


TRUTH_STATE = ["--set", "attitude.state_source=truth", "--set", "position.state_source=truth",
               "--set", "sim.truth_rate_hz=200"]


def fly(mission: str, out: Path, lockstep: bool, extra: list[str]) -> tuple[dict, float]:
    argv = [sys.executable, "-m", "deploy.cli", "fly", "--mission", mission, "--out", str(out), *extra]
    if lockstep:
        argv.append("--lockstep")
    t0 = time.monotonic()
    proc = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True)
    if proc.returncode != 0:
        print(f"bench: the flight did not complete (rc {proc.returncode}); figures below are what it measured")
    return json.loads((out / "metrics.json").read_text()), time.monotonic() - t0


def cpu_seconds(out: Path) -> dict[str, float]:
    cpu = {}
    for log in (out / "logs").glob("*.log"):
        m = re.search(r"cpu ([0-9.]+) s", log.read_text())
        if m:
            cpu[log.stem] = float(m.group(1))
    return cpu


def sim_speed(out: Path) -> tuple[float, float]:
    m = re.search(r"([0-9.]+) s simulated in ([0-9.]+) s of wall time", (out / "logs" / "sim.log").read_text())
    return float(m.group(1)), float(m.group(2))


def jitter_p99_ms(out: Path) -> dict[str, float]:
    log = read_log(out / "flight.mcap")
    result = {}
    for s in SERVICES:
        values = [h["jitter_p99_ms"] for h in log.get(f"zp/0/{s}/health", [])[1:-1] if h["state"] == "running"]
        result[s] = statistics.median(values) if values else float("nan")
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mission", default="hover")
    ap.add_argument("--out", default="runs/bench")
    ap.add_argument("--truth-state", action="store_true",
                    help="fly the control laws on the simulator's truth (no estimators)")
    args = ap.parse_args()
    out = Path(args.out)
    extra = TRUTH_STATE if args.truth_state else []
    print(f"$ python bench/stack.py --mission {args.mission}{' --truth-state' if args.truth_state else ''}")

    m_rt, _ = fly(args.mission, out / "realtime", lockstep=False, extra=extra)
    sim_s, wall_s = sim_speed(out / "realtime")
    cpu = cpu_seconds(out / "realtime")
    jitter = jitter_p99_ms(out / "realtime")
    targets = {"sim": 400, "motors": 400, "attitude": 200, "position": 100, "planner": 50, "vision": 20}
    print("\nreal time, whole stack on this machine (6 services + router)")
    print(f"{'service':<10} {'rate Hz':>8} {'target':>7} {'error %':>8} {'<=1%':>5} {'p99 jitter ms':>14} {'<=1ms':>6} {'cpu %':>6}")
    for s, target in targets.items():
        rate = m_rt["rates_hz"].get(s) or 0.0
        err = 100 * abs(rate - target) / target
        print(f"{s:<10} {rate:>8.1f} {target:>7} {err:>8.2f} {'yes' if err <= 1 else 'NO':>5} "
              f"{jitter[s]:>14.2f} {'yes' if jitter[s] <= 1 else 'NO':>6} {100 * cpu.get(s, 0) / wall_s:>6.1f}")
    lat = m_rt["latency_ms"]
    print(f"imu->pwm latency p50 {lat['imu_to_pwm_p50']:.2f} ms, p99 {lat['imu_to_pwm_p99']:.2f} ms "
          f"(target p99 <= 5 ms: {'met' if lat['imu_to_pwm_p99'] <= 5 else 'NOT met'})")
    total_cpu = sum(cpu.values())
    print(f"stack CPU: {total_cpu:.1f} s over {wall_s:.1f} s = {100 * total_cpu / wall_s:.0f}% of one core "
          f"({', '.join(f'{k} {v:.1f}' for k, v in sorted(cpu.items()))})")

    fly(args.mission, out / "lockstep", lockstep=True, extra=extra)
    sim_s, wall_s = sim_speed(out / "lockstep")
    ratio = sim_s / wall_s
    print(f"\nlockstep: {sim_s:.1f} simulated s in {wall_s:.1f} wall s = {ratio:.2f}x real time "
          f"(target >= 2x: {'met' if ratio >= 2 else 'NOT met'})")
    cpu = cpu_seconds(out / "lockstep")
    print(f"lockstep CPU per simulated second: {sum(cpu.values()) / sim_s:.2f} s "
          f"({', '.join(f'{k} {v / sim_s:.2f}' for k, v in sorted(cpu.items()))})")


if __name__ == "__main__":
    main()
