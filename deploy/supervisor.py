"""The launcher's supervisor: every service process of this machine watched, restarted per its
stack file's policy, and what happened said in the log, on the bus and in metrics.json.

Per service (`[services.NAME]` in the stack file):

    restart = "on-failure"    # "always": also after a clean exit; "never": report only
    restart_limit = 3         # restarts at most, per flight (or per `zenpilot up`)
    hang_restart_s = 0.5      # stopped or stuck this long: a hang, killed and restarted

Detected, every POLL_S on the service's own host:
  * exited: the process ended (waitpid), with its status;
  * stopped: the process is stopped (SIGSTOP, a debugger: /proc state T), reported once per
    episode and again when it runs on;
  * stuck: its main loop sent no beat (`@beat/<name>`, every BEAT_PERIOD_S from the loop itself,
    services/runtime.py) for BEAT_SILENCE_S: a loop stuck inside a process that still runs, real
    time only, judged from the service's first beat on;
  * silent: before its first beat, no health message for HEALTH_SILENCE_S (a slow or stuck
    start-up: the planner's JAX compile takes seconds), real time only.
Services of other machines (`zenpilot up --machine NAME` on two hosts), real time only, are
watched by their beats across the link and reported, not acted on (their own host's supervisor
does that): stuck after REMOTE_BEAT_SILENCE_S without a beat (the link's delay on top of the
loop's), running again at the next beat.
A stopped or stuck service that stays so for its `hang_restart_s`, or a silent one for START_S,
has hung: it is killed (SIGKILL) and restarted as a failure. A restart waits a back-off
(none the first time: a vehicle without its motor driver tilts past 20 degrees in half a second;
then BACKOFF_S, doubled per restart of that service, at most BACKOFF_MAX_S) and starts the same
command line with `--restarted` (the service then takes control only once settled), in real time
in the launcher's warm spare (deploy/spare.py: its imports done, ~0.2 s to a first output instead
of ~0.5 s); its output is appended to the service's log.

With the motor driver's hot standby (`[services.motors] standby = true`, services/standby.py) its
second process `motors.b` is watched as a service of its own, with the driver's policy and bounds;
either, restarted, comes back as the standby (the other has taken over within ~25 ms).

A starved supervisor must not mistake its own stall for the services' (issue 22): under heavy
load a supervisor at normal priority beside SCHED_FIFO loops saw every loop's beat missing at once
and killed a healthy motor driver. So (real time) it watches from a thread of its own at a
real-time priority below every loop of its machine (`supervisor_priority`; reported where the OS
refuses it), Zenoh's receiving threads with it, and it discounts its own stalls from every beat
silence: a poll later than STALL_S past its due time (the supervisor starved), and a spell in
which no beat at all arrived while two or more of this machine's loops had been beating (its
reception starved: independent processes do not all stop at once); after a deaf spell of
DEAF_TRANSPORT_S or more (the router, not the supervisor: its link check re-opened it, or a link
was closing) the loops' sessions reconnect one by one, so RECONNECT_GRACE_S more is discounted.
A service is stuck only for beats it missed while the supervisor was demonstrably watching. Both are counted in
supervisor.json (`own`) and its health; one longer than POLL_S is an event. What no stall of the
supervisor explains is a silent loop whose thread has neither run nor waited to run for
LOOP_IDLE_S (its times in /proc/<pid>/schedstat unchanged: blocked, e.g. every loop of the machine
waiting on the same hung disk): that silence counts whole, so loops that all hang at once are
still killed, while a starved one (waiting to run) is not taken for hung.

Restarts happen in real time only. In lockstep a lost participant is dropped from the clock
(services/lockstep.py) and a new process cannot rejoin a clock already running, so there the
supervisor reports and the flight stops as it did without it. The simulator is never restarted
(a new world mid-flight), nor by default the recorder (it would begin a new log over the old one:
`restart = "never"` is its default; a cut log is made whole by `zenpilot log recover`).
"""
from __future__ import annotations

import json
import os
import threading
from collections import deque
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

from services.stack import DEFAULT_HANG_RESTART_S, NEVER_RESTARTED, service_of

POLL_S = 0.1
FIRST_BACKOFF_S = 0.0   # the warm spare (deploy/spare.py) is ready: at once
BACKOFF_S = 0.5
BACKOFF_MAX_S = 8.0
HEALTH_SILENCE_S = 3.0
START_S = 30.0   # a service silent this long before its first beat has hung in its start-up
BEAT_SILENCE_S = 0.3   # three beats missed (services/runtime.BEAT_PERIOD_S): seen within 0.4 s
REMOTE_BEAT_SILENCE_S = 0.5   # another host's service: its beats cross a link (jitter, a lost segment)
LOOP_IDLE_S = 0.2   # a loop's thread neither running nor waiting to this long is blocked (it beats every 0.1 s)
STALL_S = 0.05   # a poll this late past its due time: the supervisor was starved, not the services
DEAF_S = 0.15    # no beat from anyone this long, two or more loops beating: its reception was starved
BEATING_WITHIN_S = 1.0   # a source counts as beating when the quiet began if it beat this recently
KEPT_STALLS = 256   # the own stalls remembered (a silence longer than they reach counts them less)
# A deaf spell this long is the transport's (the machine's router re-opened by its link check, a
# link closing), not a starved thread: every session then reconnects to the router on its own,
# Zenoh retrying every 1 s and backing off to 4 s, so the loops are heard again one by one. The
# first beat back ends the spell; the others get RECONNECT_GRACE_S more before they count as stuck.
DEAF_TRANSPORT_S = 1.0
RECONNECT_GRACE_S = 5.0
PRIORITY_ENV = "ZENPILOT_SUPERVISOR_PRIORITY"   # an explicit priority (0: normal), e.g. a bench's comparison


def supervisor_priority(stack, names) -> int:
    """The supervisor's SCHED_FIFO priority: one below the lowest of the loops it watches (it must
    never take their CPU: its work is a poll and a few stores), 0 (normal) where none has one;
    PRIORITY_ENV overrides."""
    given = os.environ.get(PRIORITY_ENV)
    if given is not None:
        try:
            value = int(given)
        except ValueError:
            value = -1
        if not 0 <= value <= 99:
            raise ValueError(f"{PRIORITY_ENV}={given!r}: expected an integer 0..99 (0: normal scheduling)")
        return value
    loops = [p for p in (stack.service(service_of(n)).priority for n in names) if p > 0]
    return max(1, min(loops) - 1) if loops else 0


def apply_watch_scheduling(priority: int) -> str:
    """SCHED_FIFO at `priority` for the calling thread and every other thread of the process but
    the main one (Zenoh's, which deliver the beats; the main thread's screen and analysis stay
    normal), reset on fork (a process started from here, a restart, gets normal scheduling and
    asks for its own). Returns what holds, as services/runtime.apply_scheduling does."""
    if priority <= 0:
        return "normal"
    policy = os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0)
    try:
        os.sched_setscheduler(0, policy, os.sched_param(priority))
        try:
            threads = [int(t) for t in os.listdir("/proc/self/task")]
        except OSError:
            threads = []
        for tid in threads:
            if tid in (os.getpid(), threading.get_native_id()):
                continue
            try:
                os.sched_setscheduler(tid, policy, os.sched_param(priority))
            except ProcessLookupError:   # a thread that ended meanwhile
                pass
    except (OSError, AttributeError) as exc:
        return f"priority {priority} refused ({exc}); normal scheduling"
    return f"fifo {priority}"


def backoff_s(restarts: int) -> float:
    """The wait before a service's restart number `restarts` + 1."""
    return FIRST_BACKOFF_S if restarts == 0 else min(BACKOFF_MAX_S, BACKOFF_S * 2 ** (restarts - 1))


def loop_runnable_ns(pid: int) -> int | None:
    """How long the process's main thread (a service's loop) has run on a CPU or waited for one,
    in ns (/proc/<pid>/schedstat: on-CPU + run-queue time): constant only while it is blocked, a
    starved thread's grows too. None where unreadable."""
    try:
        with open(f"/proc/{pid}/schedstat") as fh:
            ran, waited, _ = fh.read().split()
        return int(ran) + int(waited)
    except (OSError, ValueError):
        return None


def process_state(pid: int) -> str | None:
    """The one-letter state of /proc/<pid>/stat (R, S, D, T, t, Z, ...); None where unreadable."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return None


@dataclass
class Watch:
    """What the supervisor knows of one service."""
    policy: str
    limit: int
    hang_s: float = DEFAULT_HANG_RESTART_S
    state: str = "running"     # running | stopped | stuck | silent | restarting | exited | gave-up
    exits: int = 0
    restarts: int = 0
    stops: int = 0
    silences: int = 0
    stucks: int = 0
    beats: int = 0
    hangs: int = 0
    last_status: int | None = None
    detail: str = ""
    restart_at: float | None = None
    last_health: float | None = None
    last_beat: float | None = None   # None: no beat since its (re)start
    since: float | None = None     # when the present stop or silence began
    ran_ns: int | None = None      # its loop's time running or waiting to (loop_runnable_ns), as last read
    ran_at: float | None = None    # when it was last seen to have grown
    ran_beat: float | None = None  # the beat after which it was last read
    idle: bool = False             # stuck with its loop's thread not running: no stall discounted


@dataclass
class RemoteWatch:
    """Another machine's service, as its beats show it here."""
    state: str = "unseen"   # unseen (no beat yet) | running | stuck
    beats: int = 0
    stucks: int = 0
    last_beat: float | None = None


class Supervisor:
    """poll() once per POLL_S from the launcher's loop; it returns the services that ended and
    will not be restarted (the caller decides what that means for the flight)."""

    def __init__(self, launcher, names: list[str], real_time: bool,
                 say: Callable[[str], None] = print, clock: Callable[[], float] = time.monotonic,
                 publish: Callable[[dict], None] | None = None, remote: list[str] = (),
                 loop_runnable: Callable[[int], int | None] = loop_runnable_ns):
        """publish(health): called with health_message() once a second from poll() (None: not).
        remote: other machines' services, watched by their beats (real time) and reported only.
        loop_runnable(pid): how long a service's loop thread has run or waited to, in ns (None: unknown)."""
        self.loop_runnable = loop_runnable
        self.launcher = launcher
        self.publish = publish
        self._published = None
        self.real_time = real_time
        self.say = say
        self.clock = clock
        self.t0 = clock()
        self.started_unix = time.time()   # events' t_s count from here (to match other logs)
        stack = launcher.stack
        specs = {n: stack.service(service_of(n)) for n in names}   # a hot standby's process: its service's policy
        self.watches = {n: Watch(s.restart, s.restart_limit, s.hang_restart_s) for n, s in specs.items()}
        self.remote = {n: RemoteWatch() for n in remote if n not in self.watches} if real_time else {}
        self.events: list[dict] = []
        # its own stalls (real time): spans discounted from every beat silence (see the docstring)
        self.stalls: list[tuple[float, float]] = []   # (from, to), closed, oldest first
        self.own = {"late": 0, "late_s": 0.0, "late_max_s": 0.0, "deaf": 0, "deaf_s": 0.0, "deaf_max_s": 0.0}
        self.scheduling = "normal"
        self._last_poll: float | None = None
        self._heard: float | None = None   # the newest beat's arrival, from any source
        self._beat_at: dict[str, float] = {}   # each source's newest beat's arrival
        self._deaf_from: float | None = None   # an open spell without any beat
        self._thread: threading.Thread | None = None
        self._lost: deque[str] = deque()   # the watch thread appends, the caller takes (thread-safe ends)
        self._failure: BaseException | None = None
        self._write_failed = False
        self.path = Path(launcher.run_dir) / "supervisor.json"
        self._write()

    # -- inputs -----------------------------------------------------------------------
    def health_seen(self, service: str) -> None:
        """A health message from `service` arrived (called from a Zenoh callback: one store)."""
        w = self.watches.get(service)
        if w is not None:
            w.last_health = self.clock()

    def beat_seen(self, service: str) -> None:
        """A beat of `service`'s main loop arrived (a Zenoh callback: a few stores)."""
        self._heard = self._beat_at[service] = self.clock()
        w = self.watches.get(service)
        if w is not None and w.state != "restarting":   # a late beat of the killed process is not the new one's
            w.last_beat = self.clock()
            w.beats += 1
        elif (r := self.remote.get(service)) is not None:
            r.last_beat = self.clock()
            r.beats += 1

    # -- the pass ---------------------------------------------------------------------
    def poll(self) -> list[str]:
        now = self.clock()
        lost = []
        if self.real_time:
            self._own_stalls(now)
        if self.publish is not None and (self._published is None or now - self._published >= 1.0):
            self._published = now
            self.publish(self.health_message())
            self._write()   # the beats counted so far
        for name, w in self.watches.items():
            if w.state in ("gave-up", "exited"):   # reported once, when it happened
                continue
            if w.state == "restarting":
                if now >= w.restart_at:
                    self.launcher.restart(name)
                    w.restarts += 1
                    w.state, w.restart_at, w.last_health = "running", None, now   # silence counts from here
                    w.last_beat = None   # judged by its beats again from its first one
                    self._event(name, "restarted", f"restart {w.restarts} of {w.limit}")
                continue
            proc = self.launcher.procs[name]
            status = proc.poll()
            if status is not None:
                w.exits += 1
                w.last_status = status
                why = f"exited with status {status}" if status >= 0 else f"killed by signal {-status}"
                if self._restarts(name, w, status):
                    self._restart_later(name, w, now, why)
                elif status == 0 and w.policy != "always":
                    w.state = "gave-up"
                    self._event(name, "exited", f"{why} (a clean exit: not restarted)")
                else:
                    w.state = "exited"
                    self._event(name, "exited", f"{why}; not restarted ({self._why_not(name, w)})")
                    lost.append(name)
                continue
            state = self._state(w, now, proc.pid)
            if state != w.state:
                if state == "stopped":
                    w.stops += 1
                    self._event(name, "stopped", "the process is stopped (SIGSTOP or a debugger)")
                elif state == "stuck":
                    w.stucks += 1
                    own = 0.0 if w.idle else self.discounted(w.last_beat, now)
                    self._event(name, "stuck", f"its loop sent no beat for {now - w.last_beat - own:.2f} s"
                                + (f" (and {own:.2f} s of the supervisor's own stalls, not counted)" if own else "")
                                + (f" and its thread has been blocked for {now - w.ran_at:.2f} s" if w.idle else ""))
                elif state == "silent":
                    w.silences += 1
                    self._event(name, "silent", f"no health message for {now - self._health_since(w):.1f} s")
                else:
                    self._event(name, "running", "the process runs again" if w.state == "stopped"
                                else "its loop beats again" if w.state == "stuck"
                                else "health messages again")
                w.state, w.since = state, (now if state != "running" else None)
            bound = w.hang_s if state != "silent" else START_S   # silent: not beating yet, maybe starting
            # stuck: judged by beats, so only while the supervisor was watching (a stop is /proc's)
            own = self.discounted(w.since, now) if state == "stuck" and not w.idle else 0.0
            lasted = None if w.since is None else now - w.since - own
            if lasted is not None and lasted >= bound and self._restarts(name, w, -1):
                self.launcher.kill(name)   # a stopped process dies of SIGKILL too
                w.hangs += 1
                self._restart_later(name, w, now, f"hung ({state} for {lasted:.1f} s): killed")
        for name, r in self.remote.items():
            if r.last_beat is None:
                continue
            silence = now - r.last_beat - self.discounted(r.last_beat, now)
            state = "stuck" if silence > REMOTE_BEAT_SILENCE_S else "running"
            if state != r.state:
                if state == "stuck":
                    r.stucks += 1
                    self._event(name, "stuck", f"no beat from its host for {silence:.2f} s (another "
                                               f"machine's service: reported, its own supervisor acts)")
                elif r.state == "stuck":
                    self._event(name, "running", "its loop beats again (another machine's service)")
                r.state = state
        return lost

    def _state(self, w: Watch, now: float, pid: int) -> str:
        """running, stopped, stuck or silent, as seen now."""
        if process_state(pid) in ("T", "t"):
            return "stopped"
        if not self.real_time:
            return "running"
        if w.last_beat is not None:
            heard = now - w.last_beat
            w.idle = self._loop_idle(w, pid, now, silent=heard > BEAT_SILENCE_S)
            if w.idle:
                return "stuck"
            return "stuck" if heard - self.discounted(w.last_beat, now) > BEAT_SILENCE_S else "running"
        return "silent" if now - self._health_since(w) > HEALTH_SILENCE_S else "running"

    def _loop_idle(self, w: Watch, pid: int, now: float, silent: bool) -> bool:
        """True if the `silent` loop's thread has neither run nor waited to for LOOP_IDLE_S (/proc is read at
        the first poll after each beat, and at every poll while silent)."""
        if not silent and w.ran_beat == w.last_beat:
            return False
        w.ran_beat = w.last_beat
        ran = self.loop_runnable(pid)
        if ran is None or ran != w.ran_ns:
            w.ran_ns, w.ran_at = ran, now
            return False
        return silent and now - w.ran_at > LOOP_IDLE_S

    # -- its own stalls -----------------------------------------------------------------
    def _own_stalls(self, now: float) -> None:
        """Note the spans in which this supervisor could not have seen a beat: its poll woke late
        (starved), or no beat arrived from anyone while two or more local loops were beating
        (its reception starved)."""
        if self._last_poll is not None:
            late = now - (self._last_poll + POLL_S)
            if late > STALL_S:
                self._stalled("late", now - late, now)
        self._last_poll = now
        heard = self._heard
        if self._deaf_from is not None:
            if heard is not None and heard > self._deaf_from:   # beats again
                start, self._deaf_from = self._deaf_from, None
                self._stalled("deaf", start, heard)
                if heard - start >= DEAF_TRANSPORT_S:   # (a span ending later: discounted as it passes)
                    self.stalls.append((heard, heard + RECONNECT_GRACE_S))
        elif heard is not None and now - heard - self.discounted(heard, now) > DEAF_S:   # not a late wake-up's
            local = [t for src, t in self._beat_at.items() if src not in self.remote and t >= heard - BEATING_WITHIN_S]
            if len(local) >= 2:
                self._deaf_from = heard

    def _stalled(self, kind: str, start: float, end: float) -> None:
        span = end - start
        self.stalls.append((start, end))
        del self.stalls[:-KEPT_STALLS]
        self.own[kind] += 1
        self.own[f"{kind}_s"] = round(self.own[f"{kind}_s"] + span, 4)
        self.own[f"{kind}_max_s"] = round(max(self.own[f"{kind}_max_s"], span), 4)
        if span > POLL_S:
            self._event("supervisor", "stalled", f"{'woke' if kind == 'late' else 'heard no beat from any loop for'} "
                        f"{span:.2f} s{' late' if kind == 'late' else ''}: its own stall, not counted against "
                        f"the services' beats")

    def discounted(self, start: float, end: float) -> float:
        """The time within (start, end) the supervisor was stalled (itself or its reception)."""
        spans = self.stalls if self._deaf_from is None else [*self.stalls, (self._deaf_from, end)]
        total, reached = 0.0, start   # their union: a late wake-up and a deaf spell often overlap
        for a, b in sorted((max(a, start), min(b, end)) for a, b in spans if b > start and a < end):
            if b > reached:
                total += b - max(a, reached)
                reached = b
        return total

    # -- a thread of its own ----------------------------------------------------------
    def start(self, priority: int = 0) -> None:
        """Poll from a thread of its own every POLL_S (absolute deadlines), at SCHED_FIFO
        `priority` with Zenoh's threads (apply_watch_scheduling): the caller's loop (a progress
        line, a status screen) never delays it. take_lost() gives what poll() returned."""
        ready = threading.Event()

        def watch() -> None:
            try:
                self.scheduling = apply_watch_scheduling(priority)
                ready.set()
                due = self.clock()
                while not self._stopping.is_set():
                    self._lost.extend(self.poll())
                    due += POLL_S
                    now = self.clock()
                    if due < now:   # starved past a poll: no burst of polls to catch up
                        due = now
                    self._stopping.wait(due - now)
            except BaseException as exc:   # said by take_lost(): a supervisor gone must not go unnoticed
                self._failure = exc
            finally:
                ready.set()

        self._stopping = threading.Event()
        self._thread = threading.Thread(target=watch, name="zenpilot-supervisor", daemon=True)
        self._thread.start()
        ready.wait(5.0)
        if "refused" in self.scheduling:
            self.say(f"zenpilot: supervisor: scheduling: {self.scheduling} (its own stalls are still discounted)")

    def take_lost(self) -> list[str]:
        """The services lost since the last call (the watch thread's poll() results); raises what
        ended the watch thread, if anything did."""
        if self._failure is not None:
            raise RuntimeError(f"the supervisor's watch failed: {self._failure!r}") from self._failure
        lost = []
        while self._lost:
            lost.append(self._lost.popleft())
        return lost

    def stop(self) -> None:
        """End the watch thread (before the services are stopped: their ends are no failures)."""
        if self._thread is not None:
            self._stopping.set()
            self._thread.join(timeout=5.0)
            self._thread = None

    def _health_since(self, w: Watch) -> float:
        return w.last_health if w.last_health is not None else self.t0

    def _restart_later(self, name: str, w: Watch, now: float, why: str) -> None:
        delay = backoff_s(w.restarts)
        w.state, w.restart_at, w.since = "restarting", now + delay, None
        self._event(name, "hung" if why.startswith("hung") else "exited", f"{why}; restarting in {delay:.1f} s")

    def _why_not(self, name: str, w: Watch) -> str:
        return ("lockstep: a new process cannot rejoin the clock" if not self.real_time
                else f"policy {w.policy}" if w.policy == "never" or name in NEVER_RESTARTED
                else f"restart limit {w.limit} reached")

    def _restarts(self, name: str, w: Watch, status: int) -> bool:
        if not self.real_time or name in NEVER_RESTARTED or w.policy == "never" or w.restarts >= w.limit:
            return False
        return status != 0 or w.policy == "always"

    # -- reporting --------------------------------------------------------------------
    def _event(self, name: str, kind: str, detail: str) -> None:
        if name in self.watches:
            self.watches[name].detail = detail
        t = self.clock() - self.t0
        self.events.append({"t_s": round(t, 3), "service": name, "event": kind, "detail": detail})
        self.say(f"zenpilot: supervisor: {name} {detail} (+{t:.2f} s)")
        self._write()

    def summary(self) -> dict:
        return {"real_time": self.real_time, "started_unix": self.started_unix,
                "services": {n: {k: v for k, v in asdict(w).items() if k not in ("restart_at", "last_health", "last_beat", "since")}
                             for n, w in self.watches.items()},
                "remote": {n: {k: v for k, v in asdict(r).items() if k != "last_beat"} for n, r in self.remote.items()},
                "scheduling": self.scheduling, "own": self.own, "events": self.events}

    def _write(self) -> None:
        """supervisor.json beside the flight log, rewritten whole on every change (metrics.json
        and `zenpilot status` read it)."""
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")   # two machines' supervisors may share a folder
        try:
            tmp.write_text(json.dumps(self.summary(), indent=1) + "\n")
            tmp.replace(self.path)
        except OSError as exc:   # the record is lost, not the supervision
            if not self._write_failed:
                self._write_failed = True
                self.say(f"zenpilot: supervisor: cannot write {self.path}: {exc}")

    def health_message(self) -> dict:
        """The supervisor's own planner-independent health (HEALTH fields): 'degraded' while a
        service is not running, with counts per service and event kind."""
        counts = {}
        for n, w in self.watches.items():
            for kind, value in (("exited", w.exits), ("restarted", w.restarts), ("stopped", w.stops),
                                ("stuck", w.stucks), ("silent", w.silences), ("hung", w.hangs)):
                if value:
                    counts[f"{kind}_{n}"] = value
        for n, r in self.remote.items():
            if r.stucks:
                counts[f"stuck_remote_{n}"] = r.stucks
        for kind in ("late", "deaf"):   # its own stalls, discounted (the count; max in supervisor.json)
            if self.own[kind]:
                counts[f"supervisor_{kind}"] = self.own[kind]
        bad = [f"{n} {w.state}" for n, w in self.watches.items() if w.state != "running"]
        bad += [f"{n} stuck (remote)" for n, r in self.remote.items() if r.state == "stuck"]
        return {"state": "degraded" if bad else "running", "rate_hz": 1.0 / POLL_S, "target_rate_hz": 1.0 / POLL_S,
                "overruns": 0, "jitter_p99_ms": 0.0, "lateness_p50_ms": 0.0, "lateness_p99_ms": 0.0,
                "lateness_max_ms": 0.0, "late": 0, "cycles": 0, "step_s": 0.0, "wait_s": 0.0,
                "rejected": counts, "dropped": {}, "scheduling": self.scheduling,
                "detail": "; ".join(bad) or (self.events[-1]["detail"] if self.events else "")}
