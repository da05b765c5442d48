"""Progress of a flight as `zenpilot fly` waits for it: simulated time, wall time, the speed
factor, and the mission's progress (a bar: items done, and inside a timed item its time).

It listens to the planner's setpoint (50 Hz; its header carries the simulated time, the item
and the phase): the callback only keeps the newest payload, decoded when the line is drawn.
On a terminal one line is redrawn in place; otherwise a plain line every PLAIN_EVERY_S.
"""

from __future__ import annotations

import sys
import time

import schemas

PLAIN_EVERY_S = 10.0
TTY_EVERY_S = 0.25
BAR = 24


def _timed_s(item: dict) -> float | None:
    """How long an item lasts when its length is fixed (holds, attitude references); None: it
    lasts until its goal is reached (take-off, go-to, land, flip)."""
    if item["type"] == "hold":
        return item.get("settle_s", 0.0) + item.get("duration_s", 0.0)
    if item["type"] == "attitude":
        return item.get("duration_s")
    return None


class FlightProgress:
    def __init__(self, session, vehicle_id: int, items: tuple[dict, ...], out=None, real_time: bool = False):
        self.items = items
        self.out = out or sys.stdout
        self.tty = self.out.isatty()
        self._latest: bytes | None = None
        self._sub = session.declare_subscriber(schemas.PLANNER_SETPOINT.key(vehicle_id), self._on_setpoint)
        self._wall0: float | None = None   # when the first setpoint came: the flight's start
        self._item, self._item_t0 = -1, 0.0
        # simulated time counts from 0 in lockstep; in real time headers carry the wall clock's
        # epoch seconds, so the flight's time counts from its first setpoint
        self._t0: float | None = None if real_time else 0.0
        self._next_plain = time.monotonic() + (0.0 if self.tty else PLAIN_EVERY_S)
        self._drawn = False

    def _on_setpoint(self, sample) -> None:
        self._latest = sample.payload.to_bytes()   # callbacks only keep: decoded when drawn
        if self._wall0 is None:
            self._wall0 = time.monotonic()

    def _update(self) -> dict | None:
        """The newest setpoint, decoded; notes when a new item began (called every poll, so the
        item's start is known to the poll's resolution, not the display's)."""
        payload = self._latest
        if payload is None or self._wall0 is None:
            return None
        try:
            sp = schemas.PLANNER_SETPOINT.decode(payload)
        except schemas.SchemaError:
            return None
        if self._t0 is None:
            self._t0 = sp["header"]["t_s"]
        if sp["item"] != self._item:
            self._item, self._item_t0 = sp["item"], sp["header"]["t_s"]
        return sp

    def line(self) -> str | None:
        sp = self._update()
        if sp is None:
            return None
        sim_t = sp["header"]["t_s"] - self._t0
        wall = time.monotonic() - self._wall0
        n = len(self.items)
        text = f"sim {sim_t:6.1f} s  wall {wall:6.1f} s  {sim_t / wall if wall > 0 else 0.0:4.2f}x"
        if n and sp["mission_state"] in ("running", "completed", "failed"):
            index = min(sp["item"], n - 1)
            within = 0.0
            length = _timed_s(self.items[index])
            if length:
                within = min(max((sp["header"]["t_s"] - self._item_t0) / length, 0.0), 0.99)
            done = 1.0 if sp["mission_state"] == "completed" else (index + within) / n
            filled = int(round(done * BAR))
            text += (f"  [{'#' * filled}{'-' * (BAR - filled)}] {100 * done:3.0f} %  item {index + 1}/{n} "
                     f"{self.items[index]['type']} ({sp['phase']})")
            if sp["mission_state"] != "running":
                text += f", mission {sp['mission_state']}"
        else:
            text += f"  mission {sp['mission_state']}"
        return text

    def show(self) -> None:
        """Call often (the flight's poll): draws in place on a terminal every TTY_EVERY_S, a plain
        line every PLAIN_EVERY_S otherwise."""
        now = time.monotonic()
        if now < self._next_plain:
            self._update()
            return
        text = self.line()
        if text is None:
            return
        if self.tty:
            self.out.write("\r\033[K" + text)
            self._drawn = True
            self._next_plain = now + TTY_EVERY_S
        else:
            self.out.write(text + "\n")
            self._next_plain = now + PLAIN_EVERY_S
        self.out.flush()

    def close(self) -> None:
        if self._drawn:
            self.out.write("\n")
            self.out.flush()
        try:
            self._sub.undeclare()
        except Exception:   # the session is closing already
            pass
