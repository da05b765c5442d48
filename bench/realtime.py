"""Fly a mission in real time and measure what the stack holds on this machine.

    python bench/realtime.py [--mission hover] [--seed 7] [--load N] [--set SERVICE.KEY=VALUE ...]

Per service: the achieved rate (median of the 1 s health windows) against the nominal one,
loop lateness against its own absolute deadline (p50, p99 and max; per 1 s window in the
health messages: the median window's p50, the worst window's p99 and max), deadlines
woken more than 5 ms late, CPU % of one core (from /proc, per process, over the flight
after start-up), messages lost before the service read them (sequence gaps, queue
overflow). For the stack: the imu->pwm latency (the IMU sample's time to the motor
output that used it) and the CPU of the vehicle's services together and of everything.

`--load N` keeps N busy processes (normal priority) beside the stack: `--load 1` takes one
of the two cores. `--flood BYTES@HZ[:PRIORITY]` floods the camera's image key from a peer beside
the stack's services for the whole flight (bench/support/flooder.py; e.g. `--flood 1048576@200`:
1 MiB at 10x the camera's rate; PRIORITY control|bulk, default the key's own; its session capped
as the stack's vehicle machine caps its services' bulk keys, `bulk_max_hz`, unless `--rogue`) and
reports what the control keys lost. Figures are printed beside their targets (docs/performance.md).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.support.flooder import flood_spec  # noqa: E402
from schemas.flightlog import read_log  # noqa: E402
from services.stack import load_stack  # noqa: E402

NOMINAL_HZ = {"sim": 400, "motors": 400, "attitude": 200, "position": 100, "vision": 20, "planner": 50}
VEHICLE = ("attitude", "position", "vision", "motors")
TICK = os.sysconf("SC_CLK_TCK")


def burn() -> None:
    while True:
        pass


def descendants(pid: int) -> dict[int, str]:
    """pid -> service name ('router', 'launcher', or the services.<name> module) of the run."""
    children: dict[int, list[int]] = {}
    names: dict[int, str] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
            with open(f"/proc/{entry}/cmdline", "rb") as fh:
                argv = fh.read().split(b"\0")
        except OSError:
            continue
        children.setdefault(ppid, []).append(int(entry))
        argv = [a.decode(errors="replace") for a in argv]
        if "-m" in argv:
            module = argv[argv.index("-m") + 1]
            names[int(entry)] = module.rsplit(".", 1)[-1]
    out, todo = {}, [pid]
    while todo:
        p = todo.pop()
        for c in children.get(p, []):
            out[c] = names.get(c, "other")
            todo.append(c)
    out[pid] = "launcher"
    return out


def cpu_ticks(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        return int(fields[11]) + int(fields[12])  # utime + stime
    except OSError:
        return None


def fly(args, out: Path) -> tuple[dict[str, float], float, int]:
    """Fly; returns CPU % of one core per process name, the measured seconds, the exit status."""
    argv = [sys.executable, "-m", "deploy.cli", "fly", "--mission", args.mission, "--seed", str(args.seed),
            "--out", str(out)]
    flooder = None
    if args.flood:
        from deploy.launcher import free_port
        port = free_port()
        argv += ["--port", str(port)]
    for item in args.set:
        argv += ["--set", item]
    if args.stack:
        argv += ["--stack", args.stack]
    proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120   # every service spawned (a loaded machine starts slowly) ...
    while proc.poll() is None and time.monotonic() < deadline:
        if {"sim", *VEHICLE} <= set(descendants(proc.pid).values()):
            break
        time.sleep(0.2)
    if args.flood:   # from the start: the whole flight flies through it
        size, hz, priority = args.flood
        stack = load_stack(args.stack)   # capped as the camera's machine (the simulator's) caps its services
        cap = [] if args.rogue else ["--max-hz", str(stack.machines[stack.service("sim").machine].bulk_max_hz)]
        flooder = subprocess.Popen([sys.executable, "-m", "bench.support.flooder", "--connect", f"tcp/127.0.0.1:{port}",
                                    "--bytes", str(size), "--hz", str(hz), *cap] + (["--priority", priority] if priority else []),
                                   cwd=ROOT, stdout=subprocess.PIPE, text=True)
    time.sleep(args.settle_s)   # ... then start-up (imports, compiles) is not what the loops cost
    pids = descendants(proc.pid)
    if flooder is not None:
        pids[flooder.pid] = "flooder"
    first = {p: cpu_ticks(p) for p in pids}
    t0 = time.monotonic()
    last = dict(first)
    t_last = t0
    sim = [p for p, name in pids.items() if name == "sim"]
    while proc.poll() is None and all(cpu_ticks(p) is not None for p in sim):   # the flight, not the analysis after it
        time.sleep(0.5)
        for p in pids:
            v = cpu_ticks(p)
            if v is not None:
                last[p] = v
        t_last = time.monotonic()
    proc.wait()
    if flooder is not None:
        flooder.terminate()
        print(f"flooder: {flooder.communicate(timeout=10)[0].strip()}")
    err = proc.stderr.read()
    if proc.returncode:
        print(f"bench: the flight ended with status {proc.returncode}: {err.strip().splitlines()[-1:] }")
    wall = max(t_last - t0, 1e-9)
    cpu: dict[str, float] = {}
    for p, name in pids.items():
        if first.get(p) is None or last.get(p) is None:
            continue
        cpu[name] = cpu.get(name, 0.0) + 100.0 * (last[p] - first[p]) / TICK / wall
    return cpu, wall, proc.returncode


def health_table(log: dict) -> dict[str, dict]:
    table = {}
    for key in sorted(log):
        if not key.endswith("/health"):
            continue
        service = key.split("/")[-2]
        hs = sorted(log[key], key=lambda h: h["header"]["t_s"])
        running = [h for h in hs if h["state"] == "running"][1:]   # the first window is partial
        if not running:
            continue
        windows = running[:-1] or running
        table[service] = {
            "rate": statistics.median(h["rate_hz"] for h in windows),
            "p50": statistics.median(h["lateness_p50_ms"] for h in windows),
            "p99": max(h["lateness_p99_ms"] for h in windows),
            "p99_median": statistics.median(h["lateness_p99_ms"] for h in windows),
            "max": max(h["lateness_max_ms"] for h in windows),
            "late": hs[-1]["late"], "cycles": hs[-1]["cycles"], "overruns": hs[-1]["overruns"],
            "dropped": sum(hs[-1]["dropped"].values()), "dropped_by_key": hs[-1]["dropped"],
            "rejected": hs[-1]["rejected"], "scheduling": hs[-1]["scheduling"],
        }
    return table


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mission", default="hover")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--stack", help="stack file (default: the default stack)")
    ap.add_argument("--set", action="append", default=[], metavar="SERVICE.KEY=VALUE")
    ap.add_argument("--load", type=int, default=0, help="busy processes beside the stack")
    ap.add_argument("--settle-s", type=float, default=4.0, help="start-up left out of the CPU figures")
    ap.add_argument("--flood", type=flood_spec, metavar="BYTES@HZ[:PRIORITY]",
                    help="flood the camera's image key beside the stack (e.g. 1048576@200)")
    ap.add_argument("--rogue", action="store_true",
                    help="the flood from outside the stack: no bulk_max_hz cap on its session (default: as the "
                         "stack's camera, capped as its vehicle machine says)")
    ap.add_argument("--out", default="runs/bench-realtime")
    args = ap.parse_args()
    if args.load < 0:
        ap.error("--load must be >= 0")
    print("$ python bench/realtime.py " + " ".join(sys.argv[1:]))
    import multiprocessing
    burners = [multiprocessing.Process(target=burn, daemon=True) for _ in range(args.load)]
    for b in burners:
        b.start()
    try:
        out = Path(args.out)
        cpu, wall, rc = fly(args, out)
    finally:
        for b in burners:
            b.terminate()
    metrics = json.loads((out / "metrics.json").read_text())
    health = health_table(read_log(out / "flight.mcap"))

    print(f"\nreal time, {args.mission} seed {args.seed}, {os.cpu_count()} CPUs, {args.load} busy process(es) beside; "
          f"completed {metrics['completed']}, crashed {metrics['crashed']}, hover RMS {metrics['position_rms_m']:.4f} m")
    print(f"{'service':<9} {'rate Hz':>8} {'nominal':>7} {'%':>6} {'late p50':>8} {'p99':>6} {'max ms':>7} "
          f"{'>5ms':>5} {'/1e4':>6} {'skipped':>7} {'dropped':>7} {'cpu %':>6}  scheduling")
    for s, h in sorted(health.items(), key=lambda kv: (kv[0] not in NOMINAL_HZ, kv[0])):
        nominal = NOMINAL_HZ.get(s)
        pct = f"{100 * h['rate'] / nominal:6.1f}" if nominal else f"{'-':>6}"
        per = 1e4 * h["late"] / max(h["cycles"], 1)
        print(f"{s:<9} {h['rate']:>8.1f} {nominal or '-':>7} {pct} {h['p50']:>8.2f} {h['p99']:>6.2f} {h['max']:>7.2f} "
              f"{h['late']:>5} {per:>6.1f} {h['overruns']:>7} {h['dropped']:>7} {cpu.get(s, 0.0):>6.1f}  {h['scheduling']}")
    lost = {f"{s}:{k}": n for s, h in health.items() for k, n in h["dropped_by_key"].items() if n}
    print("messages lost before their service read them: " + (", ".join(f"{k} {n}" for k, n in sorted(lost.items())) or "none"))
    if args.flood:
        print("rejected by reason: " + ", ".join(f"{s} {h['rejected']}" for s, h in health.items() if h["rejected"]))
    lat = metrics["latency_ms"]
    vehicle = sum(cpu.get(s, 0.0) for s in VEHICLE)
    total = sum(cpu.values())
    print(f"imu->pwm latency: p50 {lat['imu_to_pwm_p50']:.2f} ms, p99 {lat['imu_to_pwm_p99']:.2f} ms, "
          f"max {lat['imu_to_pwm_max']:.2f} ms ({lat['samples']} outputs)   target p99 <= 5 ms, max <= 10 ms")
    print(f"CPU over {wall:.1f} s: vehicle services ({' + '.join(VEHICLE)}) {vehicle:.0f} % of one core "
          f"(target <= 60 %); whole stack {total:.0f} % (target <= 100 %): "
          + ", ".join(f"{k} {v:.0f}" for k, v in sorted(cpu.items(), key=lambda kv: -kv[1])))
    if rc:
        raise SystemExit(rc)


if __name__ == "__main__":
    main()
