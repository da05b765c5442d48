"""Time of one run of the attitude service (services/attitude.py AttitudeLoop.step) and of its
filter (AttitudeFilter.update) on a real flight's inputs, against the former code.

    python bench/attitude_step.py [--log runs/X/flight.mcap] [--runs 2000] [--rounds 5]

The inputs are a lockstep flight's messages (the default mission, flown into
runs/bench-attitude unless --log names a flight.mcap): before each run at the time of an
att/state message, the IMU samples up to that run's newest (its att/command's imu_t_s), the
magnetometer, motors/pwm, pos/state and pos/setpoint before it and the vision poses 50 ms
old are queued; the inboxes hold them encoded and decode them on the first read, as the
service's Runtime does, and the publishers encode what is put. Rows:

  step:   AttitudeLoop.step, decoding its inputs and encoding its two outputs included;
  filter: the filter's update alone (update_floats where the loop calls that), on the
          arguments the step gave it.

Each figure is the best of --rounds rounds (mean per run within a round) over the same
--runs consecutive runs from mid-flight; "old" is bench/support/attitude_reference.py (the
code of zenpilot 6b2add1), run in the same process on the same inputs, the two alternating
round by round. The published messages of old and new are compared byte for byte.
"""
from __future__ import annotations

import argparse
import bisect
import copy
import gc
import shlex
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import schemas  # noqa: E402
from bench.support import attitude_reference as ref  # noqa: E402
from schemas.flightlog import read_log  # noqa: E402
from services import attitude as new  # noqa: E402
from services.runtime import ParamAccess  # noqa: E402
from services.stack import resolve_params  # noqa: E402

POSE_AGE_S = 0.05   # a pose is seen this long after its exposure (the camera's latency)
_SHARED = {id(m): m for m in vars(schemas).values() if isinstance(m, schemas.Message)}


def settle() -> None:
    """Collect, then freeze what is there: the replay's thousands of decoded messages would
    otherwise make the collector's passes, landing in whichever run allocates, most of the time."""
    gc.collect()
    gc.freeze()


def clone(obj):
    """A deep copy sharing the message definitions (a copied one would compile its codec again)."""
    return copy.deepcopy(obj, dict(_SHARED))


class Inbox:
    """Encoded messages queued by the replay, decoded once on the first read (as Runtime's Inbox)."""

    def __init__(self, message: schemas.Message):
        self.message, self.raw, self.items, self.taken = message, [], [], 0

    def _drain(self):
        if self.raw:
            decode = self.message.decode
            self.items.extend(decode(p) for p in self.raw)
            self.raw = []

    def take(self):
        self._drain()
        out, self.taken = self.items[self.taken:], len(self.items)
        return out

    def latest(self):
        self._drain()
        return self.items[-1] if self.items else None


class Publisher:
    def __init__(self, message: schemas.Message):
        self.message, self.sent = message, []

    def put(self, values, t_s=None, repeat=False):
        self.sent.append(self.message.encode(t_s, len(self.sent), "attitude", values))


class IO(ParamAccess):
    name, vehicle_name, rate_hz = "attitude", "x250", 200.0

    def __init__(self, declared: dict):
        self.declared = declared
        self.params = resolve_params(declared, {}, self.where())
        self.rejected, self.problems = {}, []
        self.inboxes, self.outputs, self._param_callbacks = {}, {}, {}

    def where(self):
        return "bench: [services.attitude.params]"

    def inbox(self, message, upstream, key=None, keep=4):
        return self.inboxes.setdefault(message.name, Inbox(message))

    def publisher(self, message, key=None):
        return self.outputs.setdefault(message.name, Publisher(message))

    def on_param(self, key, callback):
        self._param_callbacks.setdefault(key, []).append(callback)

    def problem(self, text):
        self.problems.append(text)


FEEDS = (("zp/0/sim/imu", schemas.IMU), ("zp/0/sim/mag", schemas.MAG), ("zp/0/motors/pwm", schemas.MOTOR_PWM),
         ("zp/0/pos/state", schemas.POSITION_STATE), ("zp/0/pos/setpoint", schemas.POSITION_SETPOINT),
         ("zp/0/vision/pose", schemas.VISION_POSE))


def schedule(log: dict) -> list[tuple[float, list[tuple[str, bytes]]]]:
    """[(run time, [(message name, payload) queued before the run])] over the whole flight."""
    imu_t = {round(m["header"]["t_s"], 9): m["imu_t_s"] for m in log["zp/0/att/command"]}
    runs = [m["header"]["t_s"] for m in log["zp/0/att/state"]]
    pending = []
    for key, message in FEEDS:
        for m in log.get(key, []):
            h = m["header"]
            payload = message.encode(h["t_s"], h["seq"], h["source"],
                                     {k: v for k, v in m.items() if k not in ("version", "header")})
            pending.append((h["t_s"], key, message.name, payload))
    out, cursor = [], {key: 0 for key, _ in FEEDS}
    by_key = {key: sorted((p for p in pending if p[1] == key), key=lambda p: p[0]) for key, _ in FEEDS}
    for t in runs:
        batch = []
        for key, _ in FEEDS:
            seq = by_key[key]
            if key == "zp/0/sim/imu":
                limit = imu_t.get(round(t, 9), t) + 1e-9
            elif key == "zp/0/vision/pose":
                limit = t - POSE_AGE_S + 1e-9
            elif key == "zp/0/sim/mag":
                limit = t + 1e-9
            else:
                limit = t - 1e-9
            j = bisect.bisect_right([p[0] for p in seq], limit, lo=cursor[key]) if seq else 0
            batch.extend((p[2], p[3]) for p in seq[cursor[key]:j])
            cursor[key] = max(cursor[key], j)
        out.append((t, batch))
    return out


class Replay:
    """A loop (new or old module) fed the schedule; `warm` runs first, then `n` timed ones."""

    def __init__(self, module, sched, start: int):
        self.io = IO(module.PARAMS)
        self.loop = module.AttitudeLoop(self.io)
        self.sched, self.start = sched, start
        self.calls = []   # the filter's update() arguments of the timed runs, captured once
        for t, batch in sched[:start]:
            self.feed(batch)
            self.loop.step(t)

    def feed(self, batch):
        boxes = self.io.inboxes
        for name, payload in batch:
            box = boxes.get(name)
            if box is not None:
                box.raw.append(payload)

    def snapshot(self):
        """The loop's state before the timed runs, restored before each round (same inputs)."""
        for p in self.io.outputs.values():
            p.sent = []
        return clone((self.loop, self.io))

    def run(self, n: int, state) -> float:
        self.loop, self.io = clone(state)
        settle()
        sched, feed, step = self.sched[self.start:self.start + n], self.feed, self.loop.step
        pc, total = time.perf_counter, 0.0
        for t, batch in sched:
            feed(batch)
            t0 = pc()
            step(t)
            total += pc() - t0
        return total / n * 1e6

    def published(self):
        return {name: p.sent for name, p in self.io.outputs.items()}


def capture_filter_calls(replay: Replay, state, n: int):
    """A copy of the filter before the timed runs, and the update() arguments they gave it."""
    loop, io = clone(state)
    calls, first = [], clone(loop.filt)
    name = "update_floats" if hasattr(loop.filt, "update_floats") else "update"   # what the loop calls
    orig = getattr(loop.filt, name)

    def spy(*args, **kw):
        calls.append(clone((args, kw)))
        return orig(*args, **kw)
    setattr(loop.filt, name, spy)
    for t, batch in replay.sched[replay.start:replay.start + n]:
        for name, payload in batch:
            box = io.inboxes.get(name)
            if box is not None:
                box.raw.append(payload)
        loop.step(t)
    return first, calls


def time_filter(filt, calls) -> float:
    f = clone(filt)
    settle()
    update, pc, total = getattr(f, "update_floats", f.update), time.perf_counter, 0.0
    for args, kw in calls:
        t0 = pc()
        update(*args, **kw)
        total += pc() - t0
    return total / len(calls) * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log", help="a lockstep flight's flight.mcap (default: fly the default mission)")
    ap.add_argument("--runs", type=int, default=2000, help="timed runs per round (default 2000 = 10 s of flight)")
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    print("$ python " + " ".join(shlex.quote(a) for a in sys.argv))
    path = Path(args.log) if args.log else ROOT / "runs/bench-attitude/flight.mcap"
    if not path.exists():
        if args.log:
            sys.exit(f"bench: {path}: no such file")
        print(f"bench: flying the default mission into {path.parent} (once)")
        subprocess.run([sys.executable, "-m", "deploy.cli", "fly", "--lockstep", "--no-plots", "--out",
                        str(path.parent)], cwd=ROOT, check=True, capture_output=True)
    try:
        sched = schedule(read_log(path))
    except (KeyError, ValueError) as exc:
        sys.exit(f"bench: {path}: not a flight log with the attitude service's messages ({exc})")
    n = min(args.runs, len(sched) // 2)
    start = (len(sched) - n) // 2
    if n < 10:
        sys.exit(f"bench: {path}: {len(sched)} attitude runs, too few")
    reps = {"new": Replay(new, sched, start), "old": Replay(ref, sched, start)}
    states = {k: r.snapshot() for k, r in reps.items()}
    best = {"new": float("inf"), "old": float("inf")}
    for _ in range(args.rounds):
        for k in ("new", "old"):
            best[k] = min(best[k], reps[k].run(n, states[k]))
    same = reps["new"].published() == reps["old"].published()
    fbest = {"new": float("inf"), "old": float("inf")}
    filt = {k: capture_filter_calls(reps[k], states[k], n) for k in ("new", "old")}
    for _ in range(args.rounds):
        for k in ("new", "old"):
            fbest[k] = min(fbest[k], time_filter(*filt[k]))
    print(f"{path}: runs {start}..{start + n} of {len(sched)} (t = {sched[start][0]:.2f}..{sched[start + n - 1][0]:.2f} s), "
          f"best of {args.rounds} rounds; period 5 ms (200 Hz)")
    print(f"{'':44}  {'new us':>8}  {'old us':>8}  {'old/new':>7}")
    for name, b in (("step (decode inputs, encode outputs)", best), ("filter update (as the step calls it)", fbest)):
        print(f"{name:44}  {b['new']:8.1f}  {b['old']:8.1f}  {b['old'] / b['new']:6.2f}x")
    print("published messages: " + ("identical, byte for byte" if same else "DIFFER between old and new"))


if __name__ == "__main__":
    main()
