"""Time of the position level's 100 Hz run (services/position.py PositionLoop.step with its
PositionEKF), replaying a lockstep flight's inputs, against the filter as of 6b2add1.

    python bench/position_ekf.py [--log FLIGHT.mcap] [--rounds 8]

Without --log it first flies `fly --lockstep --mission hover` into a temporary folder (~30 s).
The log's attitude states, motor commands, planner setpoints and camera poses go to a
PositionLoop as its inboxes hand them over in a lockstep flight: each message at the first run
after its time stamp (the attitude state of time t comes after the position run of time t, so
every attitude update is 5 ms old and fused one node back), a camera pose `camera_latency_s`
after its exposure (as the simulator publishes the frame): 60 ms old, fused six nodes back and
the predictions after it re-run. Replayed so, the loop publishes the flight's own position
states, number for number (checked below against the log). The loop's publishers only keep
the values (no encoding, no bus).

"old" is bench/support/position_ekf_reference.py's filter and motor lag (the filter's input)
put in the loop instead of this module's. The two replay the whole log in turn, round after
round; each run's time is its least over the rounds (a run that the machine's other work
delayed in one round counts with another round's time) and a figure is their mean. The filter's share comes from rounds of their own, with
every use the loop makes of the filter timed (the timers' own cost lands in "the rest").
"""
from __future__ import annotations

import argparse
import bisect
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import schemas  # noqa: E402
from bench.support.position_ekf_reference import LaggedMotorInput as OldLaggedMotorInput  # noqa: E402
from bench.support.position_ekf_reference import PositionEKF as OldPositionEKF  # noqa: E402
from bench.support.position_ekf_reference import PositionEKFParams as OldParams  # noqa: E402
from schemas.flightlog import LogError, read_log  # noqa: E402
from services.position import PARAMS, PositionLoop  # noqa: E402
from services.runtime import ParamAccess  # noqa: E402
from services.stack import resolve_params  # noqa: E402
from simulator.config import SimConfig  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RATE_HZ = 100.0
INPUTS = {schemas.ATTITUDE_STATE: "/att/state", schemas.MOTOR_PWM: "/motors/pwm",
          schemas.PLANNER_SETPOINT: "/planner/setpoint", schemas.VISION_POSE: "/vision/pose"}
STATES = "/pos/state"
COMPARED = ("position_m", "velocity_m_s", "position_cov_m2", "thrust_scale")


class _Inbox:
    def __init__(self):
        self.queue: list[dict] = []
        self.newest: dict | None = None

    def push(self, msg: dict) -> None:
        self.queue.append(msg)
        self.newest = msg

    def take(self) -> list[dict]:
        out, self.queue = self.queue, []
        return out

    def latest(self) -> dict | None:
        return self.newest


class _Publisher:
    def __init__(self):
        self.sent: list[tuple[float, dict]] = []

    def put(self, values: dict, t_s: float | None = None, repeat: bool = False) -> None:
        self.sent.append((t_s, values))


class _IO(ParamAccess):
    """The Runtime as the loop sees it: the default parameters (the default stack's), inboxes
    the replay fills, publishers that keep what was put."""

    name = "position"

    def __init__(self, vehicle: str):
        self.declared = PARAMS
        self.params = resolve_params(PARAMS, {}, self.where())
        self.vehicle_name = vehicle
        self.rate_hz = RATE_HZ
        self.lockstep = True
        self.rejected: dict[str, int] = {}
        self.problems: list[str] = []
        self.inboxes: dict[str, _Inbox] = {}
        self.outputs: dict[str, _Publisher] = {}
        self._param_callbacks: dict = {}

    def where(self) -> str:
        return "bench: [services.position.params]"

    def inbox(self, message, upstream, key=None, keep=4):
        return self.inboxes.setdefault(message.name, _Inbox())

    def publisher(self, message, key=None):
        return self.outputs.setdefault(message.name, _Publisher())

    def on_param(self, key, callback) -> None:
        self._param_callbacks.setdefault(key, []).append(callback)

    def problem(self, text: str) -> None:
        self.problems.append(text)


def _topic(msgs: dict, tail: str, log: Path) -> list[dict]:
    found = [k for k in msgs if k.endswith(tail)]
    if len(found) != 1:
        sys.exit(f"bench: {log} has {len(found)} channels ending in {tail} (one expected)")
    return msgs[found[0]]


def load_inputs(log: Path, latency_s: float) -> tuple[list[float], list[list[tuple[str, dict]]], list[dict]]:
    """The run times (every 10 ms from the flight's first position state to its last), per
    run the messages handed over before it, and the position states the flight published."""
    try:
        msgs = read_log(log)
    except LogError as exc:
        sys.exit(f"bench: {exc}")
    events = []
    for message, tail in INPUTS.items():
        delay = latency_s if message is schemas.VISION_POSE else 0.0
        events += [(m["header"]["t_s"] + delay, i, message.name, m) for i, m in enumerate(_topic(msgs, tail, log))]
    events.sort(key=lambda e: (e[0], e[2], e[1]))
    flown = _topic(msgs, STATES, log)
    if not flown:
        sys.exit(f"bench: {log} has no position states: not a flight on the estimate")
    t0, t1 = flown[0]["header"]["t_s"], flown[-1]["header"]["t_s"]
    times = [t0 + k / RATE_HZ for k in range(round((t1 - t0) * RATE_HZ) + 1)]
    due = [e[0] for e in events]
    per_run, start = [], 0
    for t in times:
        end = bisect.bisect_left(due, t - 1e-9)   # stamped before t: the one stamped t comes after the run at t
        per_run.append([(e[2], e[3]) for e in events[start:end]])
        start = end
    return times, per_run, flown


class _Timed:
    """The filter with every use the loop makes of it timed: its calls and its properties
    (reading the state is where the predictions after a fused measurement run)."""

    def __init__(self, ekf, total: list):
        self._ekf, self._total = ekf, total

    def __getattr__(self, name):
        total, clock = self._total, time.perf_counter
        t0 = clock()
        value = getattr(self._ekf, name)
        total[0] += clock() - t0
        if not callable(value):
            return value

        def timed(*a, **k):
            t1 = clock()
            try:
                return value(*a, **k)
            finally:
                total[0] += clock() - t1
        return timed


class _OldWithoutDisturbance(OldPositionEKF):
    """The former filter as the loop reads a filter today: its state with the disturbance
    states it does not have, none (the feed-forward of zeros changes no number)."""

    @property
    def x(self) -> np.ndarray:
        return np.r_[super().x, 0.0, 0.0]


def replay(vehicle: str, old: bool, times, per_run, ekf_share: bool = False) -> tuple[list, list, _IO]:
    """(seconds of each PositionLoop.step, of each the filter's part (with ekf_share), io)."""
    io = _IO(vehicle)
    loop = PositionLoop(io)
    if old:
        known = OldParams.__dataclass_fields__
        loop.ekf = _OldWithoutDisturbance(loop.vehicle, io.table(
            "ekf", lambda d: OldParams.from_dict({k: v for k, v in d.items() if k in known})), dt=loop.dt)
        loop.ekf.camera_fix = None   # it has no hook for the camera delay's fit: that part is not run
        loop.rotor_forces = OldLaggedMotorInput(loop.vehicle.motor_time_constant_s)
    ekf_s = [0.0]
    if ekf_share:
        loop.ekf = _Timed(loop.ekf, ekf_s)
    inboxes, step, clock = io.inboxes, loop.step, time.perf_counter
    steps, ekfs = [], []
    for t, msgs in zip(times, per_run):
        for name, m in msgs:
            inboxes[name].push(m)
        ekf_s[0] = 0.0
        t0 = clock()
        step(t)
        steps.append(clock() - t0)
        ekfs.append(ekf_s[0])
    return steps, ekfs, io


def compare(sent: list[tuple[float, dict]], other: list[tuple[float, dict]]) -> str:
    """How two lists of published position states compare (COMPARED, number for number)."""
    if len(sent) != len(other):
        return f"DIFFERENT: {len(sent)} vs {len(other)} states"
    differing, worst, first = 0, 0.0, None
    for (t, a), (_, b) in zip(sent, other):
        for key in COMPARED:
            xa, xb = a[key], b[key]
            xa, xb = (list(map(float, xa)), list(map(float, xb))) if hasattr(xa, "__len__") else ([xa], [xb])
            for p, q in zip(xa, xb):
                if p != q and not (p != p and q != q):   # NaN against NaN counts as the same
                    differing += 1
                    worst = max(worst, abs(p - q))
                    first = t if first is None else first
    if not differing:
        return f"identical ({len(sent)} states, every number equal)"
    return f"DIFFERENT: {differing} numbers, by up to {worst:.3g}, the first at t={first}"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log", type=Path, help="a lockstep flight's flight.mcap (default: fly a hover first)")
    ap.add_argument("--vehicle", default="x250", help="the flight's vehicle")
    ap.add_argument("--rounds", type=int, default=8, help="rounds of the step timing (and half as many of the share)")
    args = ap.parse_args(argv)
    if args.rounds < 1:
        ap.error("--rounds must be >= 1")
    print("$ python bench/position_ekf.py " + shlex.join(argv if argv is not None else sys.argv[1:]))
    with tempfile.TemporaryDirectory() as tmp:
        log = args.log
        if log is None:
            out = Path(tmp) / "hover"
            print(f"flying a lockstep hover into {out} ...", flush=True)
            proc = subprocess.run([sys.executable, "-m", "deploy.cli", "fly", "--lockstep", "--mission", "hover",
                                   "--no-plots", "--out", str(out)], cwd=ROOT, capture_output=True, text=True)
            if proc.returncode:
                sys.exit(f"bench: the hover flight failed ({proc.returncode}): {proc.stderr.strip()[-500:]}")
            log = out / "flight.mcap"
        if not log.is_file():
            sys.exit(f"bench: no flight log at {log}")
        times, per_run, flown = load_inputs(log, SimConfig().camera_latency_s)
    n = len(times)
    print(f"{log}: {n} runs at {RATE_HZ:.0f} Hz, {sum(len(m) for m in per_run)} messages handed over")
    best = {old: [[float("inf")] * n for _ in range(3)] for old in (False, True)}
    ios = {}
    for r in range(args.rounds + max(1, args.rounds // 2)):
        share = r >= args.rounds
        for old in (True, False):
            steps, ekfs, io = replay(args.vehicle, old, times, per_run, ekf_share=share)
            ios.setdefault(old, io)
            rows = best[old][1:] if share else best[old][:1]
            cols = (ekfs, [a - b for a, b in zip(steps, ekfs)]) if share else (steps,)
            for row, col in zip(rows, cols):
                row[:] = map(min, row, col)
    print(f"{'per run (each at its least)':<32} {'old':>9} {'new':>9} {'old/new':>8}")
    for i, what in enumerate(("PositionLoop.step", "  of it the filter", "  the rest")):
        o, w = sum(best[True][i]) / n * 1e6, sum(best[False][i]) / n * 1e6
        print(f"{what:<32} {o:>6.1f} us {w:>6.1f} us {o / w:>7.2f}x")
    o, w = sum(best[True][0]) / n, sum(best[False][0]) / n
    print(f"the loop at {RATE_HZ:.0f} Hz: {w * RATE_HZ * 100:.2f} % of a core (old {o * RATE_HZ * 100:.2f} %)")
    new_states = ios[False].outputs[schemas.POSITION_STATE.name].sent
    print("published states, new vs old: " + compare(new_states, ios[True].outputs[schemas.POSITION_STATE.name].sent)
          + (f"; counted {ios[False].rejected} vs {ios[True].rejected}" if ios[False].rejected != ios[True].rejected
             else ""))
    # a log flown with these numbers (this code's, or the same arithmetic's) is given back exactly
    print("published states, new vs the log's: " + compare(new_states, [(m["header"]["t_s"], m) for m in flown]))


if __name__ == "__main__":
    main()
