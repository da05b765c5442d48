"""Start, watch and stop a stack's processes: the Zenoh router and the services.

Each service is its own OS process (`python -m services.<name>`), connected
in peer mode to the router of its machine; its output goes to
<run dir>/logs/<service>.log.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from deploy import security
from deploy.stack import SERVICE_MODULES, Stack, StackError

ROUTER_START_TIMEOUT_S = 10.0
# One thread per Zenoh runtime pool: a 400 Hz service needs no more, and on a
# small computer (2 cores here, a Raspberry Pi on the vehicle) fewer threads
# means fewer context switches (measured: lockstep 1.04x -> 1.25x real time).
ZENOH_RUNTIME = ("(app: (worker_threads: 1), acc: (worker_threads: 1), tx: (worker_threads: 1), "
                 "rx: (worker_threads: 1), net: (worker_threads: 1))")

# The services' linear algebra is small (3x3 .. 13x13, a PnP of a few hundred points): one BLAS
# thread. A second one only spin-waits, and beside real-time loops on 2 cores it took 40 % of a
# core from the flip's planner (measured: vision's PnP in a real-time flip).
SERVICE_THREADS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def endpoint_port(endpoint: str) -> tuple[str, int]:
    try:
        host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
        return host, int(port)
    except (IndexError, ValueError):
        raise StackError(f"router endpoint {endpoint!r}: expected tcp/HOST:PORT") from None


def wait_port(endpoint: str, timeout_s: float) -> bool:
    host, port = endpoint_port(endpoint)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with socket.create_connection((host, port), timeout=0.2):
                return True
        except OSError:
            time.sleep(0.05)
    return False


def client_session(endpoint: str, stack: Stack | None = None, machine: str | None = None) -> zenoh.Session:
    """A tool's session (status, start-up checks); with a [security] stack it presents the
    machine's login (default: the machine whose router is `endpoint`)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if stack is not None and stack.security is not None:
        security.apply_session(conf, stack.security, machine or security.machine_of(stack, endpoint))
    return zenoh.open(conf)


def alive_services(session: zenoh.Session, vehicle_id: int, timeout_s: float = 0.5) -> set[str]:
    replies = session.liveliness().get(f"zp/{vehicle_id}/alive/*", timeout=timeout_s)
    return {str(r.ok.key_expr).rsplit("/", 1)[1] for r in replies if r.ok is not None}


@dataclass
class Launcher:
    stack: Stack
    run_dir: Path
    router: str  # endpoint the services connect to
    lockstep: bool = False
    seed: int = 0
    vehicle: str | None = None
    mission: str | None = None
    params: dict[str, list[str]] = field(default_factory=dict)  # service -> ["k=v", ...]
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)
    machine: str | None = None  # the stack's machine whose router this starts (None: a bare router)

    def __post_init__(self):
        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)

    def _spawn(self, name: str, argv: list[str]) -> subprocess.Popen:
        log = open(self.run_dir / "logs" / f"{name}.log", "w")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)
        for key, value in SERVICE_THREADS.items():
            env.setdefault(key, value)
        proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, env=env,
                                start_new_session=True)  # Ctrl-C in a terminal reaches us only
        self.procs[name] = proc
        return proc

    def start_router(self) -> None:
        if self.stack.security is not None and self.machine is None:
            raise StackError(f"{self.stack.path}: a stack with [security] starts machine by machine "
                             f"(`zenpilot up --machine NAME`), each router as its machine says")
        machine = ["--stack", str(self.stack.path), "--machine", self.machine] if self.machine else []
        self._spawn("router", [sys.executable, "-m", "deploy.router", "--listen", self.router, *machine])
        if not wait_port(self.router, ROUTER_START_TIMEOUT_S):
            raise StackError(f"the Zenoh router did not open {self.router} "
                             f"(see {self.run_dir / 'logs' / 'router.log'})")

    def service_argv(self, name: str) -> list[str]:
        argv = [sys.executable, "-m", SERVICE_MODULES[name], "--stack", str(self.stack.path),
                "-e", self.router, "--seed", str(self.seed)]
        if self.lockstep:
            argv.append("--lockstep")
        if self.vehicle:
            argv += ["--vehicle", self.vehicle]
        if name == "planner" and self.mission:
            argv += ["--mission", self.mission]
        if name == "recorder":
            argv += ["--out", str(self.run_dir)]
        for item in self.params.get(name, []):
            argv += ["--param", item]
        return argv

    def start_services(self, names: list[str]) -> None:
        if self.stack.security is not None:   # another machine's login would have no way to its peers
            elsewhere = [n for n in names if self.stack.service(n).machine != self.machine]
            if elsewhere:
                raise StackError(f"{self.stack.path}: with [security] a machine starts only its own services "
                                 f"(`zenpilot up --machine NAME`); not here: {', '.join(elsewhere)}")
        # the recorder first so it sees everything; the simulator last, it drives the clock
        order = sorted(names, key=lambda n: (n != "recorder", n == "sim"))
        for name in order:
            proc = self._spawn(name, self.service_argv(name))
            if nice := self.stack.service(name).nice:
                try:
                    os.setpriority(os.PRIO_PROCESS, proc.pid, nice)
                except OSError as exc:  # it still runs, at the default priority: say so
                    print(f"zenpilot: {name}: could not set nice {nice}: {exc}", file=sys.stderr)

    def wait_alive(self, names: list[str], timeout_s: float = 30.0) -> set[str]:
        """Wait for every service's liveliness token; returns the ones still missing."""
        session = client_session(self.router, self.stack, self.machine)
        try:
            deadline = time.monotonic() + timeout_s
            missing = set(names)
            while missing and time.monotonic() < deadline:
                dead = [n for n in missing if self.procs[n].poll() is not None]
                if dead:
                    raise StackError("service(s) exited during start-up: " + ", ".join(
                        f"{n} (status {self.procs[n].returncode}, see {self.run_dir / 'logs' / (n + '.log')})"
                        for n in dead))
                missing -= alive_services(session, self.stack.vehicle_id)
                time.sleep(0.1)
            return missing
        finally:
            session.close()

    def stop(self, names: list[str] | None = None, grace_s: float = 5.0) -> None:
        names = [n for n in (names or list(self.procs)) if n in self.procs]
        for n in names:
            if self.procs[n].poll() is None:
                self.procs[n].send_signal(signal.SIGINT)
        deadline = time.monotonic() + grace_s
        for n in names:
            try:
                self.procs[n].wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.procs[n].kill()
                self.procs[n].wait()

    def failed(self) -> dict[str, int]:
        """Services that exited with an error status."""
        return {n: p.returncode for n, p in self.procs.items() if p.poll() not in (None, 0)}
