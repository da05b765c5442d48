"""How fast lockstep runs, and where a tick's time goes.

    python bench/lockstep.py [--missions steps flip-short] [--seed 0]

For each mission and mode (the services as threads of one process, `fly --lockstep`'s
default, and a process per service, `--processes`): simulated seconds per wall second (the
simulator's own count, from its first tick to its last), and the per-tick cost split from
the services' totals: the simulator's own work, each service's step time, and with a
process per service the time the simulator waits, of which what the steps do not explain
is transport, wake-ups and the handshake. CPU seconds per simulated second come from each
service's log (per process; in one process, per thread).
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from bench.support import flying  # noqa: E402

TARGETS = {"steps": 5.0, "hover": 5.0, "flip-short": 3.0, "flip": 3.0}
FLIP_SHORT = "tests/integration/missions/flip-short.toml"
MODES = {"one process": [], "processes": ["--processes"]}   # `fly --lockstep` arguments


def fly(mission: str, seed: int, out: Path, extra: list[str]) -> float:
    t0 = time.monotonic()
    proc = flying.fly(["--lockstep", "--mission", mission, "--seed", str(seed), "--out", str(out), *extra],
                      f"{mission} seed {seed}")
    if proc.returncode:
        print(f"bench: {mission}: the flight ended with status {proc.returncode}: "
              f"{proc.stdout.strip().splitlines()[-1:]}")
    return time.monotonic() - t0


def run_totals(out: Path) -> dict[str, dict]:
    """Per service, from the line it logs when it stops: runs, step and waiting seconds."""
    totals = {}
    for log in (out / "logs").glob("*.log"):
        m = re.search(r"(\d+) runs, step ([0-9.]+) s, waited ([0-9.]+) s", log.read_text())
        if m:
            totals[log.stem] = {"runs": int(m.group(1)), "step": float(m.group(2)), "waited": float(m.group(3))}
    return totals


def report(mission: str, mode: str, out: Path, total_wall: float) -> float | None:
    """Print one flight's figures; returns its speed (simulated s per wall s)."""
    sim_log = out / "logs" / "sim.log"
    m = re.search(r"([0-9.]+) s simulated in ([0-9.]+) s of wall time", sim_log.read_text()) \
        if sim_log.exists() else None
    if m is None:
        print(f"bench: {mission} ({mode}): no simulator figures (see {out / 'logs'})")
        return None
    sim_s, wall_s = float(m.group(1)), float(m.group(2))
    totals = run_totals(out)
    sim = totals["sim"]
    ticks = max(sim["runs"], 1)
    target = TARGETS.get(mission)
    ratio = sim_s / wall_s
    print(f"\n{mission}, {mode}: {sim_s:.1f} simulated s in {wall_s:.1f} wall s = {ratio:.2f}x real time"
          + (f" (target >= {target:g}x: {'met' if ratio >= target else 'NOT met'})" if target else "")
          + f"; the whole command {total_wall:.1f} s (start-up and the log's sort included)")
    print(f"per tick ({ticks} ticks): {1e6 * wall_s / ticks:.0f} us of wall time")
    services = {n: h for n, h in sorted(totals.items()) if n not in ("sim", "recorder") and h["runs"]}
    steps = sum(1e6 * h["step"] / ticks for h in services.values())
    if mode == "one process":   # the simulator's thread runs the services' steps itself, in its tick
        own = 1e6 * (sim["step"] + sim["waited"]) / ticks - steps
        print(f"  {'simulator: physics, sensors, clock, bus':<44} {own:>7.0f} us")
    else:
        print(f"  {'simulator: physics and publishing':<44} {1e6 * sim['step'] / ticks:>7.0f} us")
        print(f"  {'simulator: waiting for the services due':<44} {1e6 * sim['waited'] / ticks:>7.0f} us")
    for name, h in services.items():
        print(f"    {name + ': step':<42} {1e6 * h['step'] / ticks:>7.0f} us per tick ({1e6 * h['step'] / h['runs']:.0f} "
              f"us per run, {h['runs']} runs; waiting for upstreams {1e6 * h['waited'] / ticks:.0f} us per tick)")
    if mode != "one process":
        waited = 1e6 * sim["waited"] / ticks
        print(f"  {'transport, wake-ups, handshake (wait - steps)':<44} {waited - steps:>7.0f} us "
              f"(steps overlap on {os.cpu_count()} CPUs, so this is a lower bound)")
    cpu = {}
    for log in (out / "logs").glob("*.log"):
        c = re.search(r"cpu ([0-9.]+) s", log.read_text())
        if c:
            cpu[log.stem] = float(c.group(1))
    print(f"CPU s per simulated s: {sum(cpu.values()) / sim_s:.2f} "
          f"({', '.join(f'{k} {v / sim_s:.2f}' for k, v in sorted(cpu.items(), key=lambda kv: -kv[1]))})"
          + ("; one process: each thread's own CPU, the services' steps on the simulator's" if mode == "one process"
             else ""))
    return ratio


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--missions", nargs="+", default=["steps", FLIP_SHORT],
                    help="mission names or files (default: steps and the flip-short mission)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="runs/bench-lockstep")
    ap.add_argument("--set", action="append", default=[], metavar="SERVICE.KEY=VALUE")
    ap.add_argument("--modes", nargs="+", choices=list(MODES), default=list(MODES),
                    help="one process (the default of `fly --lockstep`) and/or a process per service")
    args = ap.parse_args()
    print("$ python bench/lockstep.py " + " ".join(sys.argv[1:]))
    extra = [a for item in args.set for a in ("--set", item)]
    for mission in args.missions:
        name = Path(mission).stem
        speeds = {}
        for mode in args.modes:
            out = Path(args.out) / f"{name}-{mode.replace(' ', '-')}"
            speeds[mode] = report(name, mode, out, fly(mission, args.seed, out, extra + MODES[mode]))
        if len(speeds) == 2 and None not in speeds.values():
            print(f"\n{name}: one process {speeds['one process'] / speeds['processes']:.2f}x the speed of a "
                  f"process per service, same run")


if __name__ == "__main__":
    main()
