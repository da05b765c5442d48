"""The lockstep protocol (as PX4 SITL's lockstep), both halves in one module.

The simulator drives a clock; each participant (services.stack.LOCKSTEP_PARTICIPANTS) runs the work
due at a simulated tick once the outputs it depends on for that tick are in, and the
simulator steps the physics only when the outputs it applies (PWM, mission state) are in.
Same seed, same flight, bit for bit.

    zp/<v>/@lockstep/clock/<svc>   sim -> svc: "run tick k; the last run of each upstream due before k"
    zp/<v>/@lockstep/sync/<svc>    svc -> all: "done with tick k; my next tick, triggers, period"

A run that ends with its RUN_DONE message (schemas.RUN_DONE) stamped with the run's time sends
no sync: that message's arrival says "done" (it is tagged and queued first, so a reader woken
by it finds it). A participant whose liveliness token goes, or that owes a tick for
DROP_AFTER_S of wall time, is dropped from the clock: the rest fly on (the failsafes act).

- `Progress`: what a process knows of the others (fed on Zenoh's threads by the runtime).
- `follow_clock`: a service's loop on the clock.
- `Clock`: the simulator's half (the schedule, the clocks out, the wait for what it applies).
"""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import TYPE_CHECKING, Callable

import schemas
from services.local_bus import swap_owner

if TYPE_CHECKING:
    from services.runtime import Runtime

READY_RESEND_S = 0.2   # a participant says "ready" this often until its first clock
START_GRACE_S = 0.5    # the clock lets subscriptions propagate before tick 0
# Generous: a slow but live run of any service on a loaded 2-core machine stays far below it.
DROP_AFTER_S = 15.0
CPU_WINDOW_TICKS = 40   # one process: the inline runs' CPU is shared out this often (Clock.share_cpu)
perf_counter, thread_time = time.perf_counter, time.thread_time


class Upstream:
    """What a process knows of another participant's lockstep progress."""

    def __init__(self):
        self.last_done = -2  # -1: ready, nothing run yet
        self.next_tick = 0
        self.triggers: tuple[str, ...] = ()
        self.period_ticks = 0


class Progress:
    """The others' progress and the clocks received, as this process sees them. Written on
    Zenoh's threads (on_sync, on_run_done, on_clock, drop), read by the loop (wait_synced)."""

    def __init__(self, stop_event: threading.Event, report_drop: Callable[[str, str], None]):
        self.upstreams: dict[str, Upstream] = {}
        self.gone: set[str] = set()   # dropped from the clock (dead or frozen)
        self._gone_why: dict[str, str] = {}   # dropped, not reported yet
        self.event = threading.Event()        # set on any progress of an upstream
        self.sim_tick = -1                    # the newest clock tick received
        self.clocks: deque[dict] = deque()    # clocks for this service, not run yet
        self.clock_event = threading.Event()
        self._stop = stop_event
        self._report_drop = report_drop

    def follow(self, name: str) -> bool:
        """Start tracking `name`; False if already tracked."""
        if name in self.upstreams:
            return False
        self.upstreams[name] = Upstream()
        return True

    def on_sync(self, name: str, msg: dict) -> None:
        u = self.upstreams[name]
        u.next_tick, u.triggers, u.period_ticks = msg["next_tick"], tuple(msg["triggers"]), msg["period_ticks"]
        u.last_done = max(u.last_done, msg["tick"])
        self.event.set()

    def on_run_done(self, name: str, tick: int) -> None:
        """`name`'s RUN_DONE message for `tick` arrived: its run is done, as a sync would say."""
        u = self.upstreams[name]
        if tick > u.last_done:
            u.last_done = tick
            if not self.event.is_set():   # (set() takes a lock even when it is set already)
                self.event.set()

    def on_clock(self, msg: dict) -> None:
        self.sim_tick = msg["tick"]
        self.clocks.append(msg)
        self.clock_event.set()

    def last_done(self, name: str) -> int:
        u = self.upstreams.get(name)
        return u.last_done if u else -2

    def drop(self, name: str, why: str) -> None:
        """Stop waiting for `name`; reported when a wait skips it (report_gone): a service that
        merely stops after the flight is waited for by nobody, and the log stays the same."""
        if name not in self.gone:
            self._gone_why[name] = why
            self.gone.add(name)
            self.event.set()

    def report_gone(self, name: str) -> None:
        if name in self._gone_why:
            self._report_drop(name, self._gone_why.pop(name))

    def wait_ready(self, names: list[str]) -> bool:
        """Wait until each of `names` has said it is ready (False: stopped meanwhile)."""
        while not self._stop.is_set():
            if all(self.upstreams[n].last_done >= -1 for n in names):
                return True
            self.event.wait(0.2)
            self.event.clear()
        return False

    def wait_synced(self, ticks: dict[str, int], k: int, problem: Callable[[str], None]) -> bool:
        """Wait until each participant named has reported its run at the tick given done (False:
        stopped meanwhile); after 5 s, say who is missing at tick k. A participant dropped from
        the clock (or silent for DROP_AFTER_S) is not waited for."""
        if not self._stop.is_set():   # the common case, cheaply (in one process, always): all done
            upstreams = self.upstreams
            for n, t in ticks.items():
                if upstreams[n].last_done < t:
                    break
            else:
                return True
        warned = False
        start = time.monotonic()
        while not self._stop.is_set():
            self.event.clear()  # clear before checking, so a sync arriving now is not lost
            waiting = [n for n, t in ticks.items() if self.upstreams[n].last_done < t]
            if self.gone.intersection(waiting):
                for n in self.gone.intersection(waiting):
                    self.report_gone(n)
                waiting = [n for n in waiting if n not in self.gone]
            if not waiting:
                return True
            self.event.wait(0.5)
            waited = time.monotonic() - start
            if not warned and waited > 5.0:
                problem(f"lockstep: tick {k} still waiting for {', '.join(waiting)}")
                warned = True
            if waited > DROP_AFTER_S:
                for n in waiting:
                    self.drop(n, f"no sync for tick {k} in {DROP_AFTER_S:.0f} s")
                    self.report_gone(n)
        return False


class Participant:
    """A participant's half: say ready, then run `step` for each clock addressed to it."""

    def __init__(self, rt: "Runtime", step: Callable[[float], None], triggers: tuple[str, ...]):
        self.rt, self.step, self.triggers = rt, step, list(triggers)
        self.period = round(rt.tick_rate / rt.rate_hz) if rt.rate_hz > 0 else 0
        self.sync = rt.publisher(schemas.SYNC_DONE, schemas.SYNC_DONE.key(rt.vehicle_id, rt.name))
        self.sync.tracked = False
        done_message = schemas.RUN_DONE.get(rt.name)
        self.done_key = done_message.key(rt.vehicle_id) if done_message else None
        self.next_tick = 0 if self.period else -1
        self.ran = False
        rt.subscribe_run_done()
        rt.subscribe_clock()
        rt.watch_participants()

    def say_ready(self) -> None:
        self.sync.put({"tick": -1, "next_tick": self.next_tick, "triggers": self.triggers,
                       "period_ticks": self.period}, t_s=0.0, repeat=True)

    def started(self) -> None:
        """The first clock came (threaded), or is about to (inline): the runs' syncs count from 1."""
        self.sync.seq += 1
        self.rt.state = "running"
        self.rt.enter_loop()

    def run(self, clock: dict) -> bool:
        """Tick clock["tick"]: wait for the upstream runs it names, run the step on what they
        published, say done (a sync, unless the run ended with its RUN_DONE message). False:
        stopped while waiting."""
        rt, progress = self.rt, self.rt.progress
        self.ran = True
        k = clock["tick"]
        rt._t = t = k / rt.tick_rate
        done_before = clock["done"]
        start = time.perf_counter()
        # every upstream's run before k is done (and with it, over the same link, its outputs)
        ready = progress.wait_synced({n: done_before.get(n, -2) for n in progress.upstreams}, k, rt.problem)
        rt.wait_s += time.perf_counter() - start
        if not ready:
            return False
        for box in rt.inboxes:
            box.limit = k if box.clocked else done_before.get(box.upstream, -2)
        rt.count_run(t)
        rt._last_put = None
        rt._safe_step(self.step, t)
        rt.publish_health()
        if self.period:
            self.next_tick = k + self.period
        last = rt._last_put
        if last is None or last.key != self.done_key or last.last_t != t:   # else that message was its sync
            self.sync.put({"tick": k, "next_tick": self.next_tick, "triggers": self.triggers,
                           "period_ticks": self.period}, t_s=t)
        return True


def follow_clock(rt: "Runtime", step: Callable[[float], None], triggers: tuple[str, ...]) -> None:
    """A participant's loop: say ready until the first clock, then run each clock addressed to
    this service as it comes (Participant.run)."""
    me = Participant(rt, step, triggers)
    progress = rt.progress
    while not rt.stop_event.is_set() and not progress.clocks:
        me.say_ready()
        progress.clock_event.wait(READY_RESEND_S)
    me.started()
    while not rt.stop_event.is_set():
        progress.clock_event.clear()
        if not progress.clocks:
            progress.clock_event.wait(0.2)
            continue
        if not me.run(progress.clocks.popleft()):   # a clock for us: we are due at this tick
            break


def serve_inline(rt: "Runtime", step: Callable[[float], None], triggers: tuple[str, ...]) -> None:
    """One process (deploy/one_process.py): the simulator's thread runs this participant's clocks
    itself, in tick order, with no wake-up of this thread in between (rt.local_bus.participants);
    this thread only waits to be stopped. Every message is published as the threaded loop
    publishes it, so each service sees what it sees there."""
    me = Participant(rt, step, triggers)
    me.started()
    rt.local_bus.participants[rt.name] = me
    while not me.ran and not rt.stop_event.is_set():   # until the simulator, started last, has heard it
        me.say_ready()
        rt.stop_event.wait(READY_RESEND_S)
    rt.stop_event.wait()


class Clock:
    """The simulator's half. Every participant's runs are fixed by the schedule (the period it
    announced when ready, or the simulator topics that trigger it), so the clock can say, before
    anything has run, which run of each upstream a service must wait for (the last one due before
    its tick). The simulator waits only for the services whose outputs it applies (`applied`)
    before stepping the physics; the others run beside it, each waiting for its own upstreams.
    Every service sees exactly what the unpipelined handshake showed it."""

    def __init__(self, rt: "Runtime", participants: list[str], applied: set[str]):
        self.rt, self.progress = rt, rt.progress
        self.participants, self.applied = participants, applied
        self.clocks = {p: rt.publisher(schemas.CLOCK, schemas.CLOCK.key(rt.vehicle_id, p)) for p in participants}
        for p in participants:
            rt.follow(p)
        rt.subscribe_run_done()
        rt.watch_participants()
        self.period: dict[str, int] = {}
        self.next_due: dict[str, int] = {}
        self.triggers: dict[str, set[str]] = {}
        self.last_due = {p: -1 for p in participants}   # the last tick each was due at (-1: none yet)
        # one process: the participants whose runs this thread makes itself (serve_inline)
        self.inline: dict[str, Participant] = rt.local_bus.participants if rt.local_bus is not None else {}
        self._window_wall: dict[str, float] = {}   # inline runs' wall time since the last share_cpu
        self._window_cpu, self._window_start, self._window_end = thread_time(), perf_counter(), 0

    def start(self) -> bool:
        """Wait for every participant's "ready" and read the schedule it announced with it (the
        planner runs faster for a flip); False if stopped meanwhile."""
        if not self.progress.wait_ready(self.participants):
            return False
        time.sleep(START_GRACE_S)
        self._window_cpu, self._window_start = thread_time(), perf_counter()
        for p in self.participants:
            u = self.progress.upstreams[p]
            self.period[p], self.next_due[p], self.triggers[p] = u.period_ticks, u.next_tick, set(u.triggers)
        return True

    def tick(self, k: int, t: float, published: list[str]) -> list[str]:
        """Send tick k's clocks to the participants due at it; returns them."""
        progress = self.progress
        if progress.gone:   # dropped from the clock (killed or frozen): no more clocks for them
            for p in progress.gone.intersection(self.participants):
                progress.report_gone(p)
        next_due, triggers, gone = self.next_due, self.triggers, progress.gone
        due = [p for p in self.participants if p not in gone
               and (next_due[p] == k or (next_due[p] < 0 and triggers[p].intersection(published)))]
        # one clock for all: its "done" is the runs before k (nobody changes it)
        clock = {"tick": k, "tick_rate_hz": self.rt.tick_rate, "published": published, "done": dict(self.last_due)}
        inline, last_due, period = self.inline, self.last_due, self.period
        for p in due:
            if p in inline:   # one process: run it here, now (each run sees only runs before k)
                w0 = perf_counter()
                previous = swap_owner(p)
                try:
                    inline[p].run(clock)
                finally:
                    swap_owner(previous)
                self._window_wall[p] = self._window_wall.get(p, 0.0) + (perf_counter() - w0)
            else:
                self.clocks[p].put(clock, t_s=t)
            last_due[p] = k
            if period[p]:
                next_due[p] = k + period[p]
        if inline and k >= self._window_end:
            self.share_cpu()
            self._window_end = k + CPU_WINDOW_TICKS
        return due

    def share_cpu(self) -> None:
        """One process: the simulator's thread's CPU since the last call, split among the inline
        runs of that window by their wall time (the rest is the simulator's own). A CPU clock read
        costs ~4 us here (a system call), twice per run was ~2 % of a tick; once per window, with
        the thread's CPU/wall ratio of the window, is an estimate of each share, the total exact."""
        cpu, wall = thread_time(), perf_counter()
        ratio = (cpu - self._window_cpu) / (wall - self._window_start) if wall > self._window_start else 0.0
        for p, w in self._window_wall.items():
            share = w * ratio
            self.inline[p].rt.cpu_inline_s += share   # the participant's CPU, not the simulator's
            self.rt.cpu_inline_s -= share
        self._window_wall.clear()
        self._window_cpu, self._window_start = cpu, wall

    def wait_applied(self, due: list[str], k: int) -> bool:
        """Wait for the runs at tick k whose outputs the physics applies (False: stopped)."""
        return self.progress.wait_synced({p: k for p in due if p in self.applied}, k, self.rt.problem)

    def finish(self, k: int) -> None:
        """The runs still going finish before the simulator says it is done: the log holds them all."""
        self.progress.wait_synced({p: t for p, t in self.last_due.items() if t >= 0}, k, self.rt.problem)

    def close(self) -> None:
        """The loop is over (finished or stopped): the last window's CPU shared out."""
        if self.inline:
            self.share_cpu()
