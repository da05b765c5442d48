"""The motor driver's hot standby: which of two running drivers publishes (pure logic, no I/O).

With `[services.motors] standby = true` (real time) two motor-driver processes run the same loop
on the same inputs, each its state warm (plans, failsafe, command ages, the motors' model): one
active, whose motors/pwm the simulator (the ESCs) applies, and one standby, which computes every
tick and sends nothing while the active's output arrives. Per tick, before anything is sent:

* standby -> active: no output from another driver for `takeover_s` (by the newest sample time
  heard) and itself listening at least that long (START_GRACE_S for a driver started with the
  stack: the active's first output may come late in a loaded start-up);
* active -> standby, on its own clock: its previous output is older than `takeover_s` (it was
  stopped, frozen or starved that long: the standby will have taken over). Decided before it
  sends, so a driver resumed by SIGCONT never sends a tick, whether or not Zenoh has yet delivered
  the other's output (its receiving thread was stopped too: an epoch carried in the messages
  would be read only after that delivery). It then listens for REJOIN_S before it may take over
  again (the other dead as well): after a 2 s stop its first fresh message from the other took
  more than 28 ms to come (measured: the backlog of the stop first, then a pause), and silence
  read from a stale inbox had it take control back, on a failsafe started from 2 s-old state;
* silence is judged by both clocks: no output heard with a sample time within `takeover_s`, and
  nothing heard at all (however old: a backlog still arriving) for `takeover_s`;
* active -> standby, on hearing output sent after its own takeover by a driver of higher rank
  (INSTANCES order): two actives at once (a takeover raced an output delivered late) resolve to
  one within a message's delivery, always the same one: no livelock.

The rank is the header's `source` (the instance name), so no field is added to motors/pwm: the
message, the flight log and every subscriber stay as they are. Sample times are wall time on one
host (the drivers run on the vehicle's computer beside each other).
"""
from __future__ import annotations

import math

from services.stack import STANDBY_SUFFIX

INSTANCES = ("motors", "motors" + STANDBY_SUFFIX)   # the two drivers, highest rank first
START_GRACE_S = 1.0   # a standby started with the stack waits this long for the active's first output
REJOIN_S = 0.25       # a driver that stepped back on its own gap listens this long before it may take over


class Standby:
    """One driver's role. `heard(source, t_s)` for every motors/pwm message received;
    `may_publish(now)` once per tick, before sending: True only for the active driver."""

    def __init__(self, me: str, active: bool, now: float, takeover_s: float, grace_s: float = START_GRACE_S):
        if me not in INSTANCES:
            raise ValueError(f"motor driver instance {me!r}: expected one of {', '.join(INSTANCES)}")
        self.me, self.rank, self.takeover_s = me, INSTANCES.index(me), float(takeover_s)
        self.active = active
        self.since = now                    # the last change of role
        self.last_out = None                # this driver's last output (None: none yet, a start-up is no gap)
        self.other_t = -math.inf            # the newest output heard from another driver (sample time)
        self.other_arrived = -math.inf      # when the last one (of any age) was heard, on this driver's clock
        self.listen_until = now if active else now + grace_s
        self.takeovers = 0
        self.stepped_back = 0
        self.changed = ""                   # why the role last changed (for the log)

    @property
    def role(self) -> str:
        return "active" if self.active else "standby"

    def heard(self, source: str, t_s: float, now: float) -> None:
        """Output of `source` sampled at t_s, read at `now` (this driver's clock)."""
        if source == self.me or source not in INSTANCES:
            return
        self.other_arrived = now
        self.other_t = max(self.other_t, t_s)
        if self.active and t_s > self.since and INSTANCES.index(source) < self.rank:
            self._step_back(t_s, f"{source} (higher rank) is active too")

    def may_publish(self, now: float) -> bool:
        if self.active:
            gap = now - self.last_out if self.last_out is not None else 0.0
            if gap > self.takeover_s:
                self._step_back(now, f"own output {gap * 1e3:.0f} ms ago (stopped or starved)", REJOIN_S)
                return False
            self.last_out = now
            return True
        silent = now - self.other_t
        if silent > self.takeover_s and now - self.other_arrived > self.takeover_s and now >= self.listen_until:
            self.active, self.since, self.last_out = True, now, now
            self.takeovers += 1
            self.changed = (f"took over: no output from the other driver for {silent * 1e3:.0f} ms"
                            if math.isfinite(silent) else "took over: no other driver heard")
            return True
        return False

    def _step_back(self, now: float, why: str, listen_s: float | None = None) -> None:
        self.active, self.since = False, now
        self.listen_until = now + (self.takeover_s if listen_s is None else max(listen_s, self.takeover_s))
        self.stepped_back += 1
        self.changed = f"stepped back to standby: {why}"
