"""A lockstep flight's services as threads of one process, on an in-process bus.

`zenpilot fly --lockstep` runs here by default: the same service modules, each `main(argv)`
with the command line the launcher would give its process, its Runtime on a
services.local_bus.LocalBus instead of Zenoh, its output in <run>/logs/<service>.log. The
lockstep protocol and every message are unchanged, so the flight log is the one the
multi-process lockstep writes, byte for byte (`zenpilot fly --lockstep --processes` flies
that one; tests/integration/test_flights.py compares them); what goes is the cost of carrying
each message between processes. The recorder alone has a process of its own (`--stdin`): the
bus's messages reach it through a pipe in batches, and its decoding, JSON and compression
run on the other core instead of taking turns with the flight under this process's lock.
Real time always runs a process per service.

Started by deploy.launcher.Launcher.start_one_process; on SIGTERM/SIGINT, or when the
simulator ends the flight, it stops the clock, the services, then the recorder (it closes
and sorts the log), as the launcher stops processes. Exit status 0 when the simulator ended
the flight, ONE_PROCESS_FAILED (its last line says which service, and where its log is) when
a service failed, at start-up or in flight.
"""

from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys
import threading
import time
import traceback
from pathlib import Path
from typing import TextIO

import zenoh

from deploy.launcher import ONE_PROCESS_FAILED, STOP_GRACE_S, recorder_grace_s
from schemas.flightlog import LOG_NAME
from services import local_bus, runtime
from services.stack import LOCKSTEP_PARTICIPANTS

FORWARD_S = 0.02   # how often the bus's messages go to the recorder's process


class ThreadOutput:
    """sys.stdout/sys.stderr for a process of services: each line goes to the log of the
    service whose thread (or whose subscriber callback, on another's thread) writes it."""

    def __init__(self, files: dict[str, TextIO], default: TextIO):
        self.files, self.default = files, default

    def _file(self) -> TextIO:
        owner = local_bus.delivering_to() or threading.current_thread().name
        return self.files.get(owner, self.default)

    def write(self, text: str) -> int:
        f = self._file()
        try:
            n = f.write(text)
            f.flush()
        except ValueError:   # a service still talking after its log was closed (the process ending)
            n = self.default.write(text)
        return n

    def flush(self) -> None:
        self._file().flush()

    def isatty(self) -> bool:
        return False


class Host:
    def __init__(self, services: list[tuple[str, str, list[str]]], logs: Path, vehicle_id: int):
        self.services, self.logs, self.vehicle_id = services, logs, vehicle_id
        self.bus = local_bus.LocalBus()
        self.threads: dict[str, threading.Thread] = {}
        self.status: dict[str, int] = {}
        self.stop = threading.Event()
        self.recorder: subprocess.Popen | None = None
        self.to_record = None   # the bus's messages not yet forwarded to the recorder

    def _run(self, name: str, module: str, argv: list[str]) -> None:
        try:
            importlib.import_module(module).main(argv)
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except BaseException:   # a service's bug: its traceback in its own log, the flight stopped
            traceback.print_exc()
            code = 1
        self.status[name] = code

    def start(self, name: str, module: str, argv: list[str]) -> None:
        t = threading.Thread(target=self._run, args=(name, module, argv), name=name, daemon=True)
        self.threads[name] = t
        t.start()

    def start_recorder(self, argv: list[str], log: TextIO) -> None:
        """The recorder in a process of its own (its decoding, JSON and compression on the other
        core, not under this process's lock), fed every message of the bus through its stdin.
        The bus is listened to before anything is said: nothing is missed while it starts."""
        self.to_record = self.bus.open().declare_subscriber(f"zp/{self.vehicle_id}/**",
                                                            zenoh.handlers.FifoChannel(1)).handler
        no_router = [a for i, a in enumerate(argv) if a != "-e" and (i == 0 or argv[i - 1] != "-e")]
        self.recorder = subprocess.Popen([sys.executable, "-m", "services.recorder", *no_router, "--stdin"],
                                         stdin=subprocess.PIPE, stdout=log, stderr=subprocess.STDOUT)

    def forward(self) -> None:
        """What the bus carried since the last call, to the recorder."""
        if self.recorder is None or self.recorder.stdin.closed:
            return
        batch = []
        while (sample := self.to_record.try_recv()) is not None:
            batch.append((sample.key_expr, sample.payload))
        if not batch:
            return
        try:
            self.recorder.stdin.write(local_bus.frames(batch))
            self.recorder.stdin.flush()
        except (BrokenPipeError, ValueError):   # it died: its status says how
            self.recorder.stdin.close()

    def failed(self) -> dict[str, int]:
        if self.recorder is not None and self.recorder.poll() not in (None, 0):
            self.status["recorder"] = self.recorder.returncode
        return {n: c for n, c in self.status.items() if c != 0}

    def fly(self, log_files: dict[str, TextIO]) -> int:
        for name, module, argv in self.services:   # the recorder first, listening before anything is said
            if name == "recorder":
                self.start_recorder(argv, log_files[name])
            else:
                self.start(name, module, argv)
        sim = self.threads.get("sim")
        while not self.stop.is_set() and sim is not None and sim.is_alive() and not self.failed():
            self.forward()
            self.stop.wait(FORWARD_S)
        failed = self.failed()
        # start-up is over once every clocked service has reached its loop (services.lockstep.serve_inline)
        flying = set(self.bus.participants) >= set(self.threads) & set(LOCKSTEP_PARTICIPANTS)
        self.shut_down()
        if failed:
            print(f"service(s) {'failed during the flight' if flying else 'exited during start-up'}: "
                  + ", ".join(f"{n} (status {c}, see {self.logs / (n + '.log')})" for n, c in failed.items()),
                  file=sys.__stderr__, flush=True)
            return ONE_PROCESS_FAILED
        return 0 if "sim" in self.status else 1

    def shut_down(self) -> None:
        """The clock first, then the services, then the recorder (it logs what they sent last and
        closes the log complete), as the launcher stops processes."""
        names = list(self.threads)
        for group, grace_s in ((["sim"] if "sim" in names else [], STOP_GRACE_S),
                               ([n for n in names if n != "sim"], STOP_GRACE_S)):
            deadline = time.monotonic() + grace_s
            asked = set()
            while time.monotonic() < deadline:
                alive = [n for n in group if self.threads[n].is_alive()]
                if not alive:
                    break
                for n in alive:
                    if n not in asked and self.bus.request_stop(n):
                        asked.add(n)
                self.threads[alive[0]].join(0.05)
            for n in group:
                if self.threads[n].is_alive():
                    print(f"{n} did not stop within {grace_s:.0f} s", file=sys.__stderr__, flush=True)
        if self.recorder is not None:   # the rest of the messages, then their end: it closes the log
            self.forward()
            if not self.recorder.stdin.closed:
                self.recorder.stdin.close()
            grace_s = recorder_grace_s([self.logs.parent / LOG_NAME])
            try:
                self.recorder.wait(grace_s)
            except subprocess.TimeoutExpired:
                self.recorder.kill()
                self.recorder.wait()
                print(f"recorder did not stop within {grace_s:.0f} s; killed (`zenpilot log recover`)",
                      file=sys.__stderr__, flush=True)
            if self.recorder.returncode != 0:
                self.status["recorder"] = self.recorder.returncode


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m deploy.one_process", description=__doc__.splitlines()[0])
    p.add_argument("--logs", required=True, type=Path, help="folder for <service>.log")
    p.add_argument("--vehicle-id", required=True, type=int)
    p.add_argument("services", help='JSON: [[name, module, [argument, ...]], ...] in start order')
    args = p.parse_args(argv)
    runtime.tie_to_parent()
    services = [(n, m, list(a)) for n, m, a in json.loads(args.services)]
    args.logs.mkdir(parents=True, exist_ok=True)
    files = {name: open(args.logs / f"{name}.log", "w") for name, _, _ in services}
    host = Host(services, args.logs, args.vehicle_id)
    runtime.LOCAL_BUS = host.bus
    runtime.on_stop_signals(host.stop.set)
    sys.stdout = ThreadOutput(files, sys.__stdout__)
    sys.stderr = ThreadOutput(files, sys.__stderr__)
    try:
        return host.fly(files)
    finally:
        sys.stdout.flush()
        for f in files.values():
            f.close()
        sys.stdout, sys.stderr = sys.__stdout__, sys.__stderr__


if __name__ == "__main__":
    sys.exit(main())
