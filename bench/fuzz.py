"""Fuzz every input during a long hover: 10^6 invalid messages at >= 600/s.

    PYTHONPATH=. python bench/fuzz.py [--messages 1000000] [--rate 600] [--realtime] [--estimators]

Flies a hover whose hold outlasts the fuzz (a mission written to the output folder; lockstep's
speed varies with the machine, so the hold is planned for `--sim-speed` simulated seconds per
wall second, and the flight is stopped as Ctrl-C stops it once the fuzz is done and has been
delivered: "stopped after the fuzz" then stands for "completed")
while bench/support/fuzzer.py publishes invalid messages (schemas/fuzz.py) round-robin to
every key a service subscribes to, lockstep clock and sync keys included. Reports: messages
sent and the rate achieved, whether the flight completed and crashed, the rejections each
service counted (the recorder's total must equal the messages it is sent), non-finite motor
outputs in the log, and the largest distance of the simulator's truth from the hold's
setpoint. Exits 1 if any of: a crash, a service not completing, a rejection not counted, a
NaN at the motors, an error over 0.1 m. Default lockstep (deterministic: the truth state
hover; --estimators for the full estimator stack); --realtime flies on the wall clock
(figures valid only on an unloaded machine). Not run in CI: 10^6 at 600/s is ~28 minutes.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from bench.support.fuzzer import LINGER_S, Fuzzer  # noqa: E402
from deploy.launcher import free_port  # noqa: E402
from schemas import REASONS  # noqa: E402
from schemas.flightlog import read_log  # noqa: E402

TRUTH_STATE = ("--set", "attitude.state_source=truth", "--set", "position.state_source=truth",
               "--set", "sim.truth_rate_hz=200")
LOCKSTEP_RECEIVERS = {"sim", "attitude", "position", "motors", "planner", "vision", "recorder"}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--messages", type=int, default=1_000_000)
    p.add_argument("--rate", type=float, default=600.0, help="messages per second (wall clock)")
    p.add_argument("--realtime", action="store_true", help="fly on the wall clock (default: lockstep)")
    p.add_argument("--estimators", action="store_true", help="the full estimator stack (default: truth state)")
    p.add_argument("--sim-speed", type=float, default=8.0,
                   help="lockstep: simulated seconds per wall second to plan the hold's length for (at most)")
    p.add_argument("--out", default="runs/bench-fuzz")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    wall_s = args.messages / args.rate
    hold_s = wall_s * (1.0 if args.realtime else args.sim_speed) + 15.0
    mission = out / "fuzz-hover.toml"
    mission.write_text(
        '[mission]\nname = "fuzz-hover"\nvehicle = "x250"\n'
        f'description = "Hover while fuzzed (bench/fuzz.py)."\ntimeout_s = {hold_s + 60.0:.0f}\n\n'
        '[[items]]\ntype = "takeoff"\naltitude_m = 1.0\n\n'
        f'[[items]]\ntype = "hold"\nsettle_s = 2.0\nduration_s = {hold_s:.0f}\n\n[[items]]\ntype = "land"\n')
    port = free_port()
    receivers = LOCKSTEP_RECEIVERS | ({"mavlink"} if args.realtime else set())
    fuzzer = Fuzzer(f"tcp/127.0.0.1:{port}", args.messages, args.rate, receivers)
    argv_fly = [sys.executable, "-m", "deploy.cli", "fly", "--mission", str(mission), "--out", str(out),
                "--port", str(port), "--no-plots", "--set", f"sim.max_duration_s={hold_s + 120.0:.0f}",
                *(() if args.estimators else TRUTH_STATE)]
    if not args.realtime:
        argv_fly.append("--lockstep")
    t0 = time.monotonic()
    fuzzer.start()
    stopped_after_fuzz = False
    try:
        # SIGINT reaches it as from a terminal, also where this bench runs in the background (a
        # background job inherits SIGINT ignored, and Python keeps an inherited SIG_IGN)
        proc = subprocess.Popen(argv_fly, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        while proc.poll() is None:
            if fuzzer.finished_at is not None and time.monotonic() - fuzzer.finished_at > LINGER_S + 2.0:
                proc.send_signal(signal.SIGINT)   # as Ctrl-C: the services stop, the log is written whole
                stopped_after_fuzz = True
                break
            time.sleep(0.5)
        said, _ = proc.communicate()
    finally:
        fuzzer.stop.set()
        fuzzer.join()
    wall = time.monotonic() - t0
    (out / "fly.log").write_text(said)
    problems = []
    if fuzzer.error:
        problems.append(f"fuzzer: {fuzzer.error}")
    if fuzzer.count < args.messages:
        problems.append(f"only {fuzzer.count} of {args.messages} sent before the flight ended: plan a longer hold")
    metrics_path = out / "metrics.json"
    if stopped_after_fuzz:   # stopped as Ctrl-C stops it: the metrics from its (complete) log
        subprocess.run([sys.executable, "-m", "deploy.cli", "report", str(out)], cwd=ROOT, capture_output=True)
    if not metrics_path.exists():
        print(said[-3000:])
        print("no metrics.json: the flight did not finish")
        return 1
    m = json.loads(metrics_path.read_text())
    rejected = {s: sum(n for r, n in c.items() if r in REASONS) for s, c in m["rejected_messages"].items()}
    recorder = (out / "logs" / "recorder.log").read_text()
    # the recorder sees each message once (param/set twice: its runtime's handler is a second
    # subscriber), the keys under a verbatim chunk aside (@lockstep, @image): zp/0/** never matches them
    expected = (fuzzer.count - sum(n for key, n in fuzzer.sent.items() if "/@" in key)
                + fuzzer.sent.get("zp/0/param/set", 0))
    recorder_counted = f"rejected {expected} " in recorder
    log = read_log(out / "flight.mcap")
    pwm = log.get("zp/0/motors/pwm", [])
    non_finite = sum(1 for msg in pwm for v in msg["pwm_us"] + msg["thrust_n"] if not math.isfinite(v))
    holding = [s for s in log.get("zp/0/planner/setpoint", []) if s["phase"] == "hold"]
    err_max = math.inf
    if holding:
        t_a, t_b = holding[0]["header"]["t_s"], holding[-1]["header"]["t_s"]
        pos = np.array([t["position_m"] for t in log["zp/0/sim/truth"] if t_a <= t["header"]["t_s"] <= t_b])
        if len(pos):
            err_max = float(np.linalg.norm(pos - np.array(holding[0]["position_m"]), axis=1).max())
    print(f"bench/fuzz.py: {'real time' if args.realtime else 'lockstep'}, "
          f"{'estimators' if args.estimators else 'truth state'}; wall {wall:.0f} s")
    print(f"  sent {fuzzer.count} invalid messages to {len(fuzzer.keys)} keys at {fuzzer.achieved_hz:.0f}/s "
          f"(kinds: {json.dumps(fuzzer.kinds, sort_keys=True)})")
    print(f"  flight: completed {m['completed']}, stopped after the fuzz {stopped_after_fuzz}, crashed {m['crashed']}, "
          f"exit {proc.returncode}")
    print(f"  rejected per service: {json.dumps(rejected, sort_keys=True)}; recorder counted all: {recorder_counted}")
    print(f"  non-finite motor outputs: {non_finite} of {len(pwm)} messages; "
          f"hold: max distance from setpoint {err_max:.4f} m over {len(holding)} setpoints")
    if m["crashed"] or not (m["completed"] and proc.returncode == 0 or stopped_after_fuzz and proc.returncode in (130, 143)):
        problems.append("the flight did not complete (or last until the fuzz was done), or crashed")
    if not recorder_counted:
        problems.append("the recorder's rejected count is not the messages sent")
    if non_finite:
        problems.append("non-finite motor outputs")
    if not err_max < 0.1:
        problems.append(f"hover error {err_max:.3f} m >= 0.1 m")
    for line in problems:
        print(f"  FAILED: {line}")
    return 1 if problems else 0


if __name__ == "__main__":
    raise SystemExit(main())
