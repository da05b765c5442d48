"""What one message costs an inbox on its way to the reader, warm and cache-cold, in one process.

    python bench/inbox_cost.py [--n 200000] [--cold 3000] [--rounds 2] [--baseline DIR]

For an IMU message (132 B, as the simulator sends it): `Inbox._on_sample` (the Zenoh callback's
part) then `Inbox.latest()` (the reader's: decode, checks, sequence, the newest), timed

  warm   in a tight loop, --n messages: the interpreter's best case
  cold   one message at a time after a 16 MiB copy that flushes the CPU's caches (medians over
         --cold messages): closer to what a callback that follows a wait pays, where each
         Python step costs several times its warm price (docs/performance.md, "One hop")

beside the same for the decode alone (the compiled codec) and, raw zenoh-python's part, the
payload's `to_bytes()`. `--baseline DIR` adds DIR/services/runtime.py's Inbox with DIR/schemas/
core.py's codec (another checkout, e.g. `git archive main | tar -x -C DIR`), alternated with this tree's in every round. The
runtime is a stand-in with the attributes an Inbox reads (real time: untagged, not woken).
Wall-clock figures depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import zenoh  # noqa: E402

import schemas  # noqa: E402
from bench.support.baseline_tree import baseline_message, load_module  # noqa: E402
from services.runtime import Inbox  # noqa: E402

VALUES = {"gyro_rad_s": [0.01, -0.02, 0.1], "accel_m_s2": [0.1, 0.2, 9.81]}


class StandIn:
    """The runtime as an Inbox sees it in real time (nothing rejected in this bench)."""

    def __init__(self):
        self.rejected, self.dropped = {}, {}
        self._arrival, self._wake, self._wake_t = threading.Event(), threading.Event(), 0.0
        self.lockstep, self.event_driven = False, False

    def _sync_tick(self, upstream):
        return 0

    def reject(self, key, exc):
        raise AssertionError(f"a valid message was rejected: {exc}")

    def count_rejects(self, key, reason, n=1):
        raise AssertionError(f"a valid message was rejected: {reason}")

    def count_dropped(self, key, n=1):
        self.dropped[key] = self.dropped.get(key, 0) + n


def baseline_inbox(tree: str):
    return load_module(tree, "services/runtime.py", "inbox_cost_baseline").Inbox


def samples(n: int) -> list:
    return [SimpleNamespace(payload=zenoh.ZBytes(schemas.IMU.encode(1.0 + i * 0.0025, i, "sim", VALUES)))
            for i in range(n)]


def warm(box_class, message, msgs: list) -> float:
    box = box_class(StandIn(), message, "zp/0/sim/imu", "sim", keep=4)
    on, latest = box._on_sample, box.latest
    t0 = time.perf_counter()
    for s in msgs:
        on(s)
        latest()
    return (time.perf_counter() - t0) / len(msgs)


def cold(box_class, message, msgs: list) -> dict[str, float]:
    box = box_class(StandIn(), message, "zp/0/sim/imu", "sim", keep=4)
    on, latest, decode = box._on_sample, box.latest, message._decode
    src, dst = bytearray(16 << 20), bytearray(16 << 20)
    clock = time.perf_counter
    t_on, t_latest, t_decode, t_raw = [], [], [], []
    for s in msgs:
        dst[:] = src
        t0 = clock()
        on(s)
        t1 = clock()
        latest()
        t2 = clock()
        t_on.append(t1 - t0)
        t_latest.append(t2 - t1)
        dst[:] = src
        t0 = clock()
        data = s.payload.to_bytes()
        t1 = clock()
        t_raw.append(t1 - t0)
        dst[:] = src
        t0 = clock()
        decode(data)
        t_decode.append(clock() - t0)
    med = statistics.median
    return {"_on_sample": med(t_on), "latest": med(t_latest), "decode alone": med(t_decode), "to_bytes": med(t_raw)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200_000, help="messages per warm loop (default 200000)")
    ap.add_argument("--cold", type=int, default=3000, help="messages timed cache-cold (default 3000)")
    ap.add_argument("--rounds", type=int, default=2, help="alternations (default 2)")
    ap.add_argument("--baseline", metavar="DIR", help="also time DIR/services/runtime.py's Inbox and DIR/schemas' codec")
    args = ap.parse_args()
    trees = {"this tree": (Inbox, schemas.IMU)}
    if args.baseline:
        trees["baseline"] = (baseline_inbox(args.baseline), baseline_message(args.baseline, schemas.IMU))
    print("command:", " ".join([Path(sys.executable).name, *sys.argv]))
    warm_msgs, cold_msgs = samples(args.n), samples(args.cold)
    for r in range(args.rounds):
        order = list(trees.items())
        for name, (box_class, message) in order if r % 2 == 0 else order[::-1]:   # each goes first in turn
            w = warm(box_class, message, warm_msgs)
            c = cold(box_class, message, cold_msgs)
            parts = "  ".join(f"{k} {v * 1e6:5.2f}" for k, v in c.items())
            print(f"round {r + 1} {name:<9}  warm _on_sample+latest {w * 1e6:5.2f} us | cold (us): "
                  f"_on_sample+latest {(c['_on_sample'] + c['latest']) * 1e6:5.2f}  {parts}", flush=True)


if __name__ == "__main__":
    main()
