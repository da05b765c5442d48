"""A fuzzing publisher for flights (tests/integration/test_fuzz.py, bench/fuzz.py): invalid
messages (schemas/fuzz.py) at a steady rate, round-robin over every key a service of the
stack subscribes to: each message's key, the lockstep clock and sync keys of every
participant, param/set and a health key (the MAVLink bridge reads */health)."""

from __future__ import annotations

import threading
import time

import zenoh

import schemas
from deploy.launcher import alive_services, client_session
from schemas.fuzz import Garbage
from services.stack import LOCKSTEP_PARTICIPANTS

# a huge array in a flight: ~180 KB, over every bound but the plan's, mission's and camera's
# (those get 1.8 MB arrays in tests/unit/services/test_fuzz_inputs.py); 1.8 MB at 60/s to every
# subscriber would measure the loopback network, not the services
HUGE_ITEMS = 20_000
LINGER_S = 3.0


def fuzz_keys(vehicle_id: int = 0) -> list[tuple[str, schemas.Message]]:
    keys = [(m.key(vehicle_id), m) for m in schemas.ALL if "{service}" not in m.topic]
    for p in LOCKSTEP_PARTICIPANTS:
        keys += [(schemas.SYNC_DONE.key(vehicle_id, p), schemas.SYNC_DONE),
                 (schemas.CLOCK.key(vehicle_id, p), schemas.CLOCK)]
    keys.append((schemas.HEALTH.key(vehicle_id, "intruder"), schemas.HEALTH))
    return keys


class Fuzzer(threading.Thread):
    """Publishes `total` invalid messages at `rate_hz` once every service in `receivers` is
    alive (and `settle_s` later, for their subscriptions); `sent` counts them per key."""

    def __init__(self, endpoint: str, total: int, rate_hz: float, receivers: set[str],
                 vehicle_id: int = 0, settle_s: float = 2.0, seed: int = 0, huge_items: int = HUGE_ITEMS):
        super().__init__(daemon=True)
        self.endpoint, self.total, self.rate_hz, self.receivers = endpoint, total, rate_hz, receivers
        self.vehicle_id, self.settle_s = vehicle_id, settle_s
        self.keys = fuzz_keys(vehicle_id)
        self.pools = {m.name: Garbage(m, seed=seed + i, huge_items=huge_items) for i, m in enumerate(schemas.ALL)}
        self.stop = threading.Event()
        self.sent: dict[str, int] = {}
        self.kinds: dict[str, int] = {}
        self.started_at = self.finished_at = None
        self.error = ""

    def run(self) -> None:
        try:
            self._run()
        except Exception as exc:   # reported by the caller, never a silent thread death
            self.error = f"{type(exc).__name__}: {exc}"

    def _run(self) -> None:
        deadline = time.monotonic() + 120
        while True:
            try:
                session = client_session(self.endpoint)
                break
            except Exception:
                if self.stop.is_set() or time.monotonic() > deadline:
                    self.error = "no session"
                    return
                time.sleep(0.2)
        try:
            while not self.stop.is_set() and not alive_services(session, self.vehicle_id) >= self.receivers:
                time.sleep(0.2)
            time.sleep(self.settle_s)
            # BLOCK: every message sent reaches every subscriber (Zenoh's default drops under
            # congestion), so that the counts can be checked message for message
            pubs = [(key, session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK),
                     self.pools[m.name]) for key, m in self.keys]
            period = 1.0 / self.rate_hz
            self.started_at = t_next = time.monotonic()
            for n in range(self.total):
                if self.stop.is_set():
                    break
                key, pub, pool = pubs[n % len(pubs)]
                kind, payload = pool.next()
                pub.put(payload)
                self.sent[key] = self.sent.get(key, 0) + 1
                self.kinds[kind] = self.kinds.get(kind, 0) + 1
                t_next += period
                delay = t_next - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            self.finished_at = time.monotonic()
            self.stop.wait(LINGER_S)   # what is still queued in the session goes out before it closes
        finally:
            session.close()

    @property
    def count(self) -> int:
        return sum(self.sent.values())

    @property
    def achieved_hz(self) -> float:
        if self.started_at is None or self.finished_at is None:
            return 0.0
        return self.count / max(self.finished_at - self.started_at, 1e-9)
