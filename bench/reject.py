"""Cost of rejecting malformed messages at a service's inbox, per message, old path beside new.

    PYTHONPATH=. python bench/reject.py [--n 2000] [--rounds 5] [--message imu]

For each kind of garbage (schemas/fuzz.py) and for valid messages, it times what one
message costs a service: the Zenoh callback (services.runtime.Inbox._on_sample, on Zenoh's
thread) and the reader's drain (decode, reject, count: on the service's thread), in
batches of 16 as a reader finds them. "old" is the Inbox before rejection was made early
(a verbatim copy below: every payload copied and queued, then fully decoded; the
rejection's reason found by the reference validator every time); "new" is
services.runtime.Inbox. Medians over --rounds rounds, microseconds per message.
Wall-clock figures depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import threading
import time
from collections import deque
from pathlib import Path
from types import SimpleNamespace

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import schemas  # noqa: E402
from schemas.fuzz import KINDS, Garbage, valid_doc  # noqa: E402
from services.runtime import Inbox  # noqa: E402

OLD_RAW_QUEUE_MAX = 256


class OldInbox:
    """services/runtime.py Inbox._on_sample and _drain before early rejection (verbatim)."""

    def __init__(self, runtime, message, key):
        self.runtime, self.message, self.key, self.upstream = runtime, message, key, "sim"
        self._raw, self._items = deque(), deque(maxlen=4)
        self._next_seq, self.arrived = {}, 0
        self.wakes, self._takes, self._superseded = False, False, False

    def _on_sample(self, sample) -> None:
        raw = self._raw
        rt = self.runtime
        raw.append((rt._sync_tick(self.upstream) if rt.lockstep else 0, sample.payload.to_bytes()))
        if len(raw) > OLD_RAW_QUEUE_MAX:   # not read for a while: the oldest goes
            raw.popleft()
            if self._takes:
                rt.count_dropped(self.key)
            else:
                self._superseded = True
        if self.wakes:
            rt._wake_t = time.time()
            rt._wake.set()
        elif rt.event_driven:
            rt._arrival.set()

    def _drain(self) -> None:
        raw, items, decode = self._raw, self._items, self.message.decode
        if self._superseded:
            self._superseded = False
            self._next_seq.clear()
        while raw:
            tag, payload = raw.popleft()
            self.arrived += 1
            try:
                msg = decode(payload)
            except schemas.SchemaError as exc:
                self.runtime.reject(self.key, exc)
                continue
            header = msg["header"]
            seq, source = header["seq"], header["source"]
            expected = self._next_seq.get(source)
            if expected is not None and seq > expected:
                self.runtime.count_dropped(self.key, seq - expected)
            if expected is None or seq >= expected - 1 or seq < expected - 1000:
                self._next_seq[source] = seq + 1
            items.append((tag, self.arrived, msg))


def old_decode_full(m):
    """The decode the old path ran: no size bound; the reason always diagnosed."""
    import msgpack

    def decode(payload):
        try:
            doc = msgpack.unpackb(payload, raw=False, strict_map_key=True)
        except Exception as exc:
            raise schemas.SchemaError("malformed", m.name, f"not MessagePack ({type(exc).__name__})") from None
        m.validate(doc)
        return doc
    return decode


class BenchRuntime:
    """The runtime as an Inbox sees it, with the real Runtime's reject counting."""

    def __init__(self):
        self.rejected, self.dropped, self._reported = {}, {}, set()
        self._arrival, self._wake, self._wake_t = threading.Event(), threading.Event(), 0.0
        self.lockstep, self.event_driven, self.detail = False, False, ""

    def _sync_tick(self, upstream):
        return 0

    def count_dropped(self, key, n=1):
        self.dropped[key] = self.dropped.get(key, 0) + n

    def reject(self, key, exc):   # services.runtime.Runtime.reject, less the one-line print
        self.rejected[exc.reason] = self.rejected.get(exc.reason, 0) + 1
        self._reported.add((key, exc.reason))

    def count_rejects(self, key, reason, n=1):
        self.rejected[reason] = self.rejected.get(reason, 0) + n


def sample(payload: bytes):
    import zenoh
    return SimpleNamespace(payload=zenoh.ZBytes(payload))


def per_message_us(box, samples, batch=16) -> float:
    t0 = time.perf_counter()
    for i in range(0, len(samples), batch):
        for s in samples[i:i + batch]:
            box._on_sample(s)
        box._drain()
    return (time.perf_counter() - t0) / len(samples) * 1e6


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=2000, help="messages per kind and round")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--message", default="imu", help="message name (schemas.BY_NAME)")
    args = p.parse_args(argv)
    m = schemas.BY_NAME[args.message]
    g = Garbage(m, seed=0)
    valid = [m.encode(1.0 + i, i, "sim", {k: v for k, v in valid_doc(m).items() if k not in ("version", "header")})
             for i in range(args.n)]
    cases = {"valid": valid}
    for kind in KINDS:
        pool = g.pools[kind]
        cases[kind] = [pool[i % len(pool)] for i in range(args.n if kind not in ("huge_array",) else args.n // 20)]
    print(f"{m.name}: microseconds per message (callback + drain), median of {args.rounds} rounds")
    print(f"{'kind':16s} {'bytes':>9s} {'old':>9s} {'new':>9s} {'old/new':>8s}")
    for kind, payloads in cases.items():
        samples = [sample(x) for x in payloads]
        old_t, new_t = [], []
        for r in range(args.rounds):   # old and new alternate which runs first (load drifts)
            for which in (("old", "new") if r % 2 == 0 else ("new", "old")):
                rt = BenchRuntime()
                if which == "old":
                    box = OldInbox(rt, m, "zp/0/x")
                    box.message = SimpleNamespace(decode=old_decode_full(m))
                    old_t.append(per_message_us(box, samples))
                    continue
                new_t.append(per_message_us(Inbox(rt, m, "zp/0/x", "sim", keep=4), samples))
                if kind != "valid":
                    assert sum(rt.rejected.values()) == len(samples), (kind, rt.rejected)
        o, n = statistics.median(old_t), statistics.median(new_t)
        size = statistics.median(len(x) for x in payloads)
        print(f"{kind:16s} {size:9.0f} {o:9.2f} {n:9.2f} {o / n:8.1f}")


if __name__ == "__main__":
    main()
