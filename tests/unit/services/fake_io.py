"""A stand-in for the service Runtime in the services' unit tests: parameters resolved as the
runtime resolves them, inboxes fed by the test, publishers that keep what was put. No Zenoh:
every message still goes through its schema (encoded and decoded) as on the bus."""

from __future__ import annotations

from typing import Any, Callable

import schemas
from services.runtime import ParamAccess
from services.stack import resolve_params


class FakeInbox:
    def __init__(self, message: schemas.Message):
        self.message = message
        self.queue: list[dict] = []
        self.newest: dict | None = None
        self.seq = 0

    def push(self, t_s: float, values: dict, source: str = "test") -> dict:
        """A message as the service would receive it (validated by its schema)."""
        msg = self.message.decode(self.message.encode(t_s, self.seq, source, values))
        self.seq += 1
        self.queue.append(msg)
        self.newest = msg
        return msg

    def take(self) -> list[dict]:
        out, self.queue = self.queue, []
        return out

    def latest(self) -> dict | None:
        return self.newest

    def fresh(self) -> bool:
        return bool(self.queue)

    def idle(self) -> None:
        self.queue = []


class FakePublisher:
    def __init__(self, message: schemas.Message):
        self.message = message
        self.sent: list[tuple[float | None, dict]] = []

    def put(self, values: dict[str, Any], t_s: float | None = None, repeat: bool = False) -> None:
        self.message.encode(t_s or 0.0, len(self.sent), "test", values)   # what the bus would refuse, refused here
        self.sent.append((t_s, values))


class FakeIO(ParamAccess):
    def __init__(self, name: str, defaults: dict, params: dict | None = None, vehicle: str = "x250",
                 rate_hz: float = 200.0, lockstep: bool = True, restarted: bool = False):
        self.name = name
        self.restarted = restarted
        self.declared = defaults
        self.params = resolve_params(defaults, params or {}, self.where())
        self.vehicle_name = vehicle
        self.rate_hz = rate_hz
        self.lockstep = lockstep
        self.rejected: dict[str, int] = {}
        self.problems: list[str] = []
        self.inboxes: dict[tuple[str, str], FakeInbox] = {}
        self.outputs: dict[str, FakePublisher] = {}
        self._param_callbacks: dict[str, list[Callable[[Any], None]]] = {}

    def where(self) -> str:
        return f"test: [services.{self.name}.params]"

    def inbox(self, message: schemas.Message, upstream: str, key: str | None = None, keep: int = 4,
              others_only: bool = False) -> FakeInbox:
        return self.inboxes.setdefault((message.name, upstream), FakeInbox(message))

    def publisher(self, message: schemas.Message, key: str | None = None) -> FakePublisher:
        return self.outputs.setdefault(message.name, FakePublisher(message))

    def on_param(self, key: str, callback: Callable[[Any], None]) -> None:
        self._param_callbacks.setdefault(key, []).append(callback)

    def problem(self, text: str) -> None:
        self.problems.append(text)

    def reject(self, key: str, exc: schemas.SchemaError) -> None:
        """As the Runtime counts a dropped message: by reason."""
        self.rejected[exc.reason] = self.rejected.get(exc.reason, 0) + 1
        self.problems.append(f"dropped a message on {key}: {exc}")

    def count_run(self, t: float) -> None:
        pass

    def received(self, message: schemas.Message, upstream: str) -> FakeInbox:
        return self.inboxes[(message.name, upstream)]

    def sent(self, message: schemas.Message) -> list[tuple[float | None, dict]]:
        return self.outputs[message.name].sent if message.name in self.outputs else []


def defaults(declared: dict) -> dict:
    """A service's declared defaults as plain values (what rt.params holds with nothing set)."""
    return resolve_params(declared, {}, "defaults")
