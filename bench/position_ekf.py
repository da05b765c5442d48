"""Time of the position level's 100 Hz run (services/position.py PositionLoop.step and its
PositionEKF), replaying a lockstep flight's inputs, against the filter as of 6b2add1.

    python bench/position_ekf.py [--log FLIGHT.mcap] [--rounds 5]

Without --log it first flies `fly --lockstep --mission hover` into a temporary folder (~30 s).
The log's attitude states, motor commands, planner setpoints and camera poses go to a
PositionLoop as its inboxes hand them over in a lockstep flight: each message at the first run
after its time stamp (the attitude state of time t comes after the position run of time t, so
every attitude update is 5 ms old and fused one node back), a camera pose `camera_latency_s`
after its exposure (as the simulator publishes the frame): 60 ms old, fused six nodes back and
the predictions re-run. The loop's
publishers only keep the values (no encoding). "old" is bench/support/position_ekf_reference.py
put in the loop instead of the filter; the two replay the whole log in turn, round after round;
each run's time is its least over the rounds (a run the machine's other work delayed in one round
counts with another round's), and a figure is their mean. The filter's share comes from rounds of
their own, its calls wrapped in timers. Both loops' published states are compared
value by value: the rewrite is meant to give the same numbers.
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import schemas  # noqa: E402
from bench.support.position_ekf_reference import PositionEKF as OldPositionEKF  # noqa: E402
from bench.support.position_ekf_reference import PositionEKFParams as OldParams  # noqa: E402
from schemas.flightlog import read_log  # noqa: E402
from services.position import PARAMS, PositionLoop  # noqa: E402
from services.runtime import ParamAccess  # noqa: E402
from services.stack import resolve_params  # noqa: E402
from simulator.config import SimConfig  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RATE_HZ = 100.0


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
    """The Runtime's face the loop sees: resolved default parameters, inboxes, publishers."""

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


def load_inputs(log: Path, latency_s: float) -> tuple[list[float], list[list[tuple[str, dict]]]]:
    """The run times (every 10 ms over the log) and, per run, the messages handed over before it."""
    msgs = read_log(log)
    topics = {schemas.ATTITUDE_STATE: "att/state", schemas.MOTOR_PWM: "motors/pwm",
              schemas.PLANNER_SETPOINT: "planner/setpoint", schemas.VISION_POSE: "vision/pose"}
    events = []
    for message, tail in topics.items():
        [key] = [k for k in msgs if k.endswith("/" + tail)]
        delay = latency_s if message is schemas.VISION_POSE else 0.0
        events += [(m["header"]["t_s"] + delay, i, message.name, m) for i, m in enumerate(msgs[key])]
    events.sort(key=lambda e: (e[0], e[2], e[1]))
    [pos_key] = [k for k in msgs if k.endswith("/pos/state")]
    t0, t1 = msgs[pos_key][0]["header"]["t_s"], msgs[pos_key][-1]["header"]["t_s"]
    times = [t0 + k / RATE_HZ for k in range(round((t1 - t0) * RATE_HZ) + 1)]
    due = [e[0] for e in events]
    per_run, start = [], 0
    for t in times:
        end = bisect.bisect_left(due, t - 1e-9)   # stamped before t: in lockstep a message stamped t comes after the run at t
        per_run.append([(e[2], e[3]) for e in events[start:end]])
        start = end
    return times, per_run


def make_loop(vehicle: str, old: bool) -> tuple[_IO, PositionLoop]:
    io = _IO(vehicle)
    loop = PositionLoop(io)
    if old:
        loop.ekf = OldPositionEKF(loop.vehicle, io.table("ekf", OldParams.from_dict), dt=loop.dt)
    return io, loop


class _Timed:
    """The filter with every use the loop makes of it timed: its calls, and its properties
    (reading the state brings the history up to date: the re-run predictions happen there)."""

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


def replay(vehicle: str, old: bool, times, per_run, ekf_share: bool = False) -> tuple[list, list, float, _IO]:
    """(seconds of each PositionLoop.step, of each the filter's calls (with ekf_share: the
    timing wrappers add their own cost to the step), the thread's CPU seconds over the whole
    replay (the steps and handing the messages over), io)."""
    io, loop = make_loop(vehicle, old)
    ekf_s = [0.0]
    if ekf_share:
        loop.ekf = _Timed(loop.ekf, ekf_s)
    inboxes = io.inboxes
    step = loop.step
    clock = time.perf_counter
    steps, ekfs = [], []
    cpu0 = time.thread_time()
    for t, msgs in zip(times, per_run):
        for name, m in msgs:
            inboxes[name].push(m)
        ekf_s[0] = 0.0
        t0 = clock()
        step(t)
        steps.append(clock() - t0)
        ekfs.append(ekf_s[0])
    return steps, ekfs, time.thread_time() - cpu0, io


def compare(a: _IO, b: _IO) -> str:
    sa, sb = a.outputs[schemas.POSITION_STATE.name].sent, b.outputs[schemas.POSITION_STATE.name].sent
    if len(sa) != len(sb):
        return f"DIFFERENT: {len(sa)} vs {len(sb)} states published"
    worst, first = 0.0, None
    for (ta, va), (tb, vb) in zip(sa, sb):
        for key in ("position_m", "velocity_m_s", "position_cov_m2", "thrust_scale"):
            xa, xb = va[key], vb[key]
            xa, xb = (list(map(float, xa)), list(map(float, xb))) if hasattr(xa, "__len__") else ([xa], [xb])
            d = max(abs(p - q) for p, q in zip(xa, xb))
            if d > worst:
                worst = d
                first = first if first is not None else ta
    if worst == 0.0 and a.rejected == b.rejected:
        return f"identical ({len(sa)} states, every number equal; rejected {a.rejected})"
    return (f"DIFFERENT: largest difference {worst:.3g} (first at t={first}); "
            f"rejected {a.rejected} vs {b.rejected}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log", type=Path, help="a lockstep flight's flight.mcap (default: fly a hover first)")
    ap.add_argument("--vehicle", default="x250")
    ap.add_argument("--rounds", type=int, default=5)
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
        times, per_run = load_inputs(log, SimConfig().camera_latency_s)
    n = len(times)
    print(f"{log}: {n} runs at {RATE_HZ:.0f} Hz, {sum(len(m) for m in per_run)} messages handed over")
    # per run, its least time over the rounds: a run the machine's other work delayed in one
    # round counts with its time from another (the rounds replay the same inputs)
    best = {old: [[float("inf")] * n for _ in range(3)] for old in (False, True)}
    ios, cpu = {}, {False: float("inf"), True: float("inf")}
    for r in range(args.rounds + max(1, args.rounds // 2)):
        share = r >= args.rounds   # the filter's share, in rounds of their own (its calls wrapped)
        for old in (True, False):
            steps, ekfs, cpu_s, io = replay(args.vehicle, old, times, per_run, ekf_share=share)
            ios.setdefault(old, io)
            if not share:
                cpu[old] = min(cpu[old], cpu_s)
            rows = best[old][1:] if share else best[old][:1]
            cols = (ekfs, [a - b for a, b in zip(steps, ekfs)]) if share else (steps,)
            for row, col in zip(rows, cols):
                row[:] = map(min, row, col)
    print(f"{'per run (each at its least)':<34} {'old':>9} {'new':>9} {'old/new':>8}")
    for i, what in enumerate(("PositionLoop.step", "  the PositionEKF calls in it", "  the rest of the step")):
        o, w = sum(best[True][i]) / n * 1e6, sum(best[False][i]) / n * 1e6
        print(f"{what:<34} {o:>6.1f} us {w:>6.1f} us {o / w:>7.2f}x")
    o, w = cpu[True] / n * 1e6, cpu[False] / n * 1e6
    print(f"{'CPU per run, best round (+ handover)':<34} {o:>6.1f} us {w:>6.1f} us {o / w:>7.2f}x")
    o, w = sum(best[True][0]) / n, sum(best[False][0]) / n
    print(f"the loop at {RATE_HZ:.0f} Hz: {w * RATE_HZ * 100:.2f} % of a core (old {o * RATE_HZ * 100:.2f} %)")
    print("published states, new vs old: " + compare(ios[False], ios[True]))


if __name__ == "__main__":
    main()
