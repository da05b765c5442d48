"""The launcher's supervisor: every service process of this machine watched, restarted per its
stack file's policy, and what happened said in the log, on the bus and in metrics.json.

Per service (`[services.NAME]` in the stack file):

    restart = "on-failure"    # "always": also after a clean exit; "never": report only
    restart_limit = 3         # restarts at most, per flight (or per `zenpilot up`)

Detected, every POLL_S on the service's own host:
  * exited: the process ended (waitpid), with its status;
  * stopped: the process is stopped (SIGSTOP, a debugger: /proc state T), reported once per
    episode and again when it runs on;
  * silent: no health message for HEALTH_SILENCE_S (a loop stuck inside a service that still
    runs; health is sent at 1 Hz), real time only.
A restart waits a back-off (BACKOFF_S, doubled per restart of that service, at most
BACKOFF_MAX_S) and starts the same command line; its output is appended to the service's log.

Restarts happen in real time only. In lockstep a lost participant is dropped from the clock
(services/lockstep.py) and a new process cannot rejoin a clock already running, so there the
supervisor reports and the flight stops as it did without it. The simulator is never restarted
(a new world mid-flight), nor by default the recorder (it would begin a new log over the old one:
`restart = "never"` is its default; a cut log is made whole by `zenpilot log recover`).
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

from services.stack import NEVER_RESTARTED

POLL_S = 0.1
BACKOFF_S = 0.5
BACKOFF_MAX_S = 8.0
HEALTH_SILENCE_S = 3.0


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
    state: str = "running"     # running | stopped | silent | restarting | exited | gave-up
    exits: int = 0
    restarts: int = 0
    stops: int = 0
    silences: int = 0
    last_status: int | None = None
    detail: str = ""
    restart_at: float | None = None
    last_health: float | None = None


class Supervisor:
    """poll() once per POLL_S from the launcher's loop; it returns the services that ended and
    will not be restarted (the caller decides what that means for the flight)."""

    def __init__(self, launcher, names: list[str], real_time: bool,
                 say: Callable[[str], None] = print, clock: Callable[[], float] = time.monotonic,
                 publish: Callable[[dict], None] | None = None):
        """publish(health): called with health_message() once a second from poll() (None: not)."""
        self.launcher = launcher
        self.publish = publish
        self._published = None
        self.real_time = real_time
        self.say = say
        self.clock = clock
        self.t0 = clock()
        stack = launcher.stack
        self.watches = {n: Watch(stack.service(n).restart, stack.service(n).restart_limit) for n in names}
        self.events: list[dict] = []
        self.path = Path(launcher.run_dir) / "supervisor.json"
        self._write()

    # -- inputs -----------------------------------------------------------------------
    def health_seen(self, service: str) -> None:
        """A health message from `service` arrived (called from a Zenoh callback: one store)."""
        w = self.watches.get(service)
        if w is not None:
            w.last_health = self.clock()

    # -- the pass ---------------------------------------------------------------------
    def poll(self) -> list[str]:
        now = self.clock()
        lost = []
        if self.publish is not None and (self._published is None or now - self._published >= 1.0):
            self._published = now
            self.publish(self.health_message())
        for name, w in self.watches.items():
            if w.state in ("gave-up", "exited"):   # reported once, when it happened
                continue
            if w.state == "restarting":
                if now >= w.restart_at:
                    self.launcher.restart(name)
                    w.restarts += 1
                    w.state, w.restart_at, w.last_health = "running", None, now   # silence counts from here
                    self._event(name, "restarted", f"restart {w.restarts} of {w.limit}")
                continue
            proc = self.launcher.procs[name]
            status = proc.poll()
            if status is not None:
                w.exits += 1
                w.last_status = status
                why = f"exited with status {status}" if status >= 0 else f"killed by signal {-status}"
                if self._restarts(name, w, status):
                    delay = min(BACKOFF_MAX_S, BACKOFF_S * 2 ** w.restarts)
                    w.state, w.restart_at = "restarting", now + delay
                    self._event(name, "exited", f"{why}; restarting in {delay:.1f} s")
                elif status == 0 and w.policy != "always":
                    w.state = "gave-up"
                    self._event(name, "exited", f"{why} (a clean exit: not restarted)")
                else:
                    w.state = "exited"
                    reason = ("lockstep: a new process cannot rejoin the clock" if not self.real_time
                              else f"policy {w.policy}" if w.policy == "never" or name in NEVER_RESTARTED
                              else f"restart limit {w.limit} reached")
                    self._event(name, "exited", f"{why}; not restarted ({reason})")
                    lost.append(name)
                continue
            stopped = process_state(proc.pid) in ("T", "t")
            if stopped and w.state != "stopped":
                w.state, w.stops = "stopped", w.stops + 1
                self._event(name, "stopped", "the process is stopped (SIGSTOP or a debugger)")
            elif not stopped and w.state == "stopped":
                w.state = "running"
                self._event(name, "running", "the process runs again")
            if self.real_time and not stopped:
                since = w.last_health if w.last_health is not None else self.t0
                silent = now - since > HEALTH_SILENCE_S
                if silent and w.state == "running":
                    w.state, w.silences = "silent", w.silences + 1
                    self._event(name, "silent", f"no health message for {now - since:.1f} s")
                elif not silent and w.state == "silent":
                    w.state = "running"
                    self._event(name, "running", "health messages again")
        return lost

    def _restarts(self, name: str, w: Watch, status: int) -> bool:
        if not self.real_time or name in NEVER_RESTARTED or w.policy == "never" or w.restarts >= w.limit:
            return False
        return status != 0 or w.policy == "always"

    # -- reporting --------------------------------------------------------------------
    def _event(self, name: str, kind: str, detail: str) -> None:
        w = self.watches[name]
        w.detail = detail
        t = self.clock() - self.t0
        self.events.append({"t_s": round(t, 3), "service": name, "event": kind, "detail": detail})
        self.say(f"zenpilot: supervisor: {name} {detail} (+{t:.2f} s)")
        self._write()

    def summary(self) -> dict:
        return {"real_time": self.real_time,
                "services": {n: {k: v for k, v in asdict(w).items() if k not in ("restart_at", "last_health")}
                             for n, w in self.watches.items()},
                "events": self.events}

    def _write(self) -> None:
        """supervisor.json beside the flight log, rewritten whole on every change (metrics.json
        and `zenpilot status` read it)."""
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.summary(), indent=1) + "\n")
        tmp.replace(self.path)

    def health_message(self) -> dict:
        """The supervisor's own planner-independent health (HEALTH fields): 'degraded' while a
        service is not running, with counts per service and event kind."""
        counts = {}
        for n, w in self.watches.items():
            for kind, value in (("exited", w.exits), ("restarted", w.restarts), ("stopped", w.stops),
                                ("silent", w.silences)):
                if value:
                    counts[f"{kind}_{n}"] = value
        bad = [f"{n} {w.state}" for n, w in self.watches.items() if w.state != "running"]
        return {"state": "degraded" if bad else "running", "rate_hz": 1.0 / POLL_S, "target_rate_hz": 1.0 / POLL_S,
                "overruns": 0, "jitter_p99_ms": 0.0, "lateness_p50_ms": 0.0, "lateness_p99_ms": 0.0,
                "lateness_max_ms": 0.0, "late": 0, "cycles": 0, "step_s": 0.0, "wait_s": 0.0,
                "rejected": counts, "dropped": {}, "scheduling": "normal",
                "detail": "; ".join(bad) or (self.events[-1]["detail"] if self.events else "")}
