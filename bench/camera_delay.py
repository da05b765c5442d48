"""The camera's delay stepping mid-flight (50 -> 120 ms), seen and compensated online.

    python bench/camera_delay.py [--mission steps] [--seed 0] [--at 12] [--to 0.12] [--out runs/bench-camera-delay]

Flies the mission in lockstep on the stack's estimates four times: no fault; the camera's delay
stepping to `--to` for the frames exposed from `--at` s on with the stamps following (honest:
the delay shows in arrival - stamp, and the EKF fuses each fix at its stamp anyway); the same
step with stamps that still say 50 ms (dishonest: only the innovations can show it), once with
the correction off (`position.camera_delay={correct=false}`: estimated and reported, not
applied) and once with it on (the default). The default `steps` mission moves (1 m steps on each
axis), which is what a wrong delay costs on: with the vehicle at rest nothing is learnt and
nothing is lost.

Per flight: when the step was detected ((a) arrival - stamp for the honest stamps, (b) the
innovations for the dishonest ones; from the position service's log), the offset estimated and
the correction applied at the end of the last window, and the position errors over a window
before the step and windows after it: the estimate against the truth (what flying on estimates
holds to), and the flown path against the no-fault flight's (what the fault did to the flight),
from flight.mcap (pos/state, sim/truth, pos/ekf_health).
"""

from __future__ import annotations

import argparse
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from schemas.flightlog import read_log  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
EVENT = re.compile(r"(camera delay now|camera fixes) .* at t=([0-9.]+)")


def fly(out: Path, mission: str, seed: int, settings: list[str]) -> list[str]:
    cmd = [sys.executable, "-m", "deploy.cli", "fly", "--lockstep", "--mission", mission, "--seed", str(seed),
           "--out", str(out), "--no-plots"]
    for s in settings:
        cmd += ["--set", s]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if proc.returncode != 0 or not (out / "flight.mcap").exists():
        sys.exit(f"bench/camera_delay.py: the flight failed ({shlex.join(cmd)}):\n{proc.stdout[-2000:]}"
                 f"{proc.stderr[-2000:]}")
    return cmd


def tracks(out: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(times, estimated positions, true positions) of the position level's runs (100 Hz)."""
    log = read_log(out / "flight.mcap")
    truth, states = log["zp/0/sim/truth"], log["zp/0/pos/state"]
    tt = np.array([m["header"]["t_s"] for m in truth])
    tp = np.array([m["position_m"] for m in truth])
    st = np.array([m["header"]["t_s"] for m in states])
    i = np.clip(np.searchsorted(tt, st), 0, len(tt) - 1)   # truth at 100 Hz, at the states' times
    return st, np.array([m["position_m"] for m in states]), tp[i]


def rms(t: np.ndarray, err: np.ndarray, t0: float, t1: float) -> float:
    m = (t >= t0) & (t < t1)
    return float(np.sqrt(np.mean(np.sum(err[m] ** 2, axis=1))))


def events(out: Path, after: float) -> dict[str, float]:
    """The first (a) step and (b) detection the position service logged at or after `after`."""
    found: dict[str, float] = {}
    log = out / "logs" / "position.log"
    for line in log.read_text().splitlines() if log.exists() else []:
        m = EVENT.search(line)
        if m and float(m.group(2)) >= after:
            found.setdefault("a" if m.group(1).startswith("camera delay") else "b", float(m.group(2)))
    return found


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mission", default="steps")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--at", type=float, default=12.0, help="the step, s of flight (default 12: before the y step)")
    ap.add_argument("--to", type=float, default=0.12, help="the camera's delay after it, s (from 0.05)")
    ap.add_argument("--window", type=float, default=6.0, help="the windows' length, s")
    ap.add_argument("--out", default="runs/bench-camera-delay")
    args = ap.parse_args(argv)
    print("$ python bench/camera_delay.py " + shlex.join(argv if argv is not None else sys.argv[1:]))
    step = [f"sim.camera_latency_step_at_s={args.at}", f"sim.camera_latency_step_s={args.to}"]
    flights = [
        ("no fault", []),
        ("step, stamps follow", step),
        ("step, stamps do not, not corrected", step + ["sim.camera_latency_step_stamped=false",
                                                       "position.camera_delay={correct=false}"]),
        ("step, stamps do not, corrected", step + ["sim.camera_latency_step_stamped=false"]),
    ]
    w = args.window
    windows = [(args.at - w, args.at), (args.at, args.at + w), (args.at + w, args.at + 3 * w)]
    names = [f"[{a:g}, {b:g}) s" for a, b in windows]
    print(f"mission {args.mission}, seed {args.seed}, lockstep; the camera's delay 50 -> {args.to * 1e3:.0f} ms "
          f"for frames exposed from {args.at:g} s\n")
    print("RMS of |estimate - truth| (the hold error on estimates), and of the flown path's distance from the "
          "no-fault flight's, mm:\n")
    print("| flight | " + " | ".join(names) + " | path " + " | path ".join(names)
          + " | detected after the step | offset est. | correction |")
    print("|---|" + "---|" * (2 * len(names)) + "---|---|---|")
    commands, nominal = [], None
    t_end = windows[-1][1]
    for i, (label, settings) in enumerate(flights):
        out = Path(args.out) / f"flight{i}"
        commands.append(shlex.join(fly(out, args.mission, args.seed, settings)[1:]))
        t, est, truth = tracks(out)
        if nominal is None:
            nominal = (t, truth)
        n = min(len(t), len(nominal[0]))   # lockstep: the same run times, as long as both flew
        est_rms = [rms(t, est - truth, a, b) for a, b in windows]
        path_rms = [rms(t[:n], truth[:n] - nominal[1][:n], a, b) for a, b in windows]
        ev = events(out, args.at)
        health = [m for m in read_log(out / "flight.mcap").get("zp/0/pos/ekf_health", [])
                  if m["header"]["t_s"] <= t_end]
        last = health[-1] if health else {}
        seen = "; ".join(f"({k}) {ev[k] - args.at:.2f} s" for k in sorted(ev)) or "-"
        print(f"| {label} | " + " | ".join(f"{x * 1e3:.1f}" for x in est_rms + path_rms)
              + f" | {seen} | {last.get('camera_offset_s', float('nan')) * 1e3:.1f} "
              f"+- {last.get('camera_offset_std_s', float('nan')) * 1e3:.1f} ms "
              f"| {last.get('camera_offset_correction_s', float('nan')) * 1e3:.1f} ms |")
    print(f"\n(a): arrival - stamp, running median (position service); (b): the innovations' offset fit. "
          f"offset est. and correction: pos/ekf_health at {t_end:g} s (the std of a vehicle that has not moved "
          f"for a while grows: the fit forgets)")
    print("flights:")
    for c in commands:
        print("  python " + c)


if __name__ == "__main__":
    main()
