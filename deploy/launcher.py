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
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from deploy.router import GATE_S
from schemas.flightlog import LOG_NAME
from services import security
from services.runtime import PARENT_ENV
from services.stack import SERVICE_MODULES, Stack, StackError, service_of

ROUTER_START_TIMEOUT_S = GATE_S + 5.0   # a machine's router opens once its link echoed, or after GATE_S
STOP_GRACE_S = 5.0        # a service's time to finish after SIGTERM before SIGKILL
# The recorder's: it writes what arrived last and the log's summary (the log is then complete),
# and in lockstep rewrites the log in sample-time order (~1.2 s per MB on 2 busy cores,
# docs/performance.md): 3 s per MB leaves a margin. Running out of time would cost that order,
# never the log.
RECORDER_GRACE_S = 30.0
RECORDER_GRACE_S_PER_MB = 3.0
ONE_PROCESS = "stack"   # a one-process lockstep's process (deploy/one_process.py): its log is logs/stack.log
ONE_PROCESS_FAILED = 3  # ... its exit status when a service other than the simulator failed
DELIVERY_S = 0.3   # after the services stop, for their last messages to reach the recorder
# One thread per Zenoh runtime pool: a 400 Hz service needs no more, and on a
# small computer (2 cores here, a Raspberry Pi on the vehicle) fewer threads
# means fewer context switches (docs/performance.md, "Lockstep").
ZENOH_RUNTIME = ("(app: (worker_threads: 1), acc: (worker_threads: 1), tx: (worker_threads: 1), "
                 "rx: (worker_threads: 1), net: (worker_threads: 1))")

# The services' linear algebra is small (3x3 .. 13x13, a PnP of a few hundred points): one BLAS
# thread. A second one only spin-waits, and beside real-time loops on 2 cores it takes CPU from
# the flip's planner (docs/performance.md).
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


def recorder_grace_s(log_paths) -> float:
    """The recorder's time to finish after SIGTERM, from the size of the log it writes."""
    size = sum(Path(p).stat().st_size for p in log_paths if Path(p).exists())
    return RECORDER_GRACE_S + RECORDER_GRACE_S_PER_MB * size / 1e6


def stop_groups(names: list[str], log_paths=()) -> list[tuple[list[str], float]]:
    """The order a stack stops in, as (names, grace in s): services that produce messages
    first, then the recorder that logs them (to `log_paths`), then the router that carries them."""
    services = [n for n in names if n not in ("recorder", "router", ONE_PROCESS)]
    return [(g, grace) for g, grace in (([ONE_PROCESS] if ONE_PROCESS in names else [],   # its services, then its recorder
                                         STOP_GRACE_S + recorder_grace_s(log_paths)),
                                        (services, STOP_GRACE_S),
                                        (["recorder"] if "recorder" in names else [], recorder_grace_s(log_paths)),
                                        (["router"] if "router" in names else [], STOP_GRACE_S)) if g]


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
    spare: subprocess.Popen | None = None   # the supervisor's warm spare (start_spare), real time
    die_with_parent: bool = False   # its processes end when this one does (services.runtime.tie_to_parent)
    dying: list[subprocess.Popen] = field(default_factory=list)   # killed, not reaped yet (kill)

    def __post_init__(self):
        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)

    def _spawn(self, name: str, argv: list[str], append: bool = False) -> subprocess.Popen:
        log = open(self.run_dir / "logs" / f"{name}.log", "a" if append else "w")
        if append:
            log.write(f"--- zenpilot: {name} restarted at {time.strftime('%H:%M:%S')} ---\n")
            log.flush()
        proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, env=self._service_env(),
                                start_new_session=True)  # Ctrl-C in a terminal reaches us only
        self.procs[name] = proc
        return proc

    def _service_env(self) -> dict[str, str]:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.pop(PARENT_ENV, None)
        if self.die_with_parent:
            env[PARENT_ENV] = str(os.getpid())
        env.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)
        for key, value in SERVICE_THREADS.items():
            env.setdefault(key, value)
        return env

    def _check_machine_by_machine(self) -> None:
        if self.stack.security is not None and self.machine is None:
            raise StackError(f"{self.stack.path}: a stack with [security] starts machine by machine "
                             f"(`zenpilot up --machine NAME`), each router as its machine says")

    def start_router(self) -> None:
        self._check_machine_by_machine()
        machine = ["--stack", str(self.stack.path), "--machine", self.machine] if self.machine else []
        self._spawn("router", [sys.executable, "-m", "deploy.router", "--listen", self.router, *machine])
        if not wait_port(self.router, ROUTER_START_TIMEOUT_S):
            raise StackError(f"the Zenoh router did not open {self.router} "
                             f"(see {self.run_dir / 'logs' / 'router.log'})")

    def service_argv(self, name: str) -> list[str]:
        """The command line of process `name`: a service, or a hot standby's second process
        ("motors.b": the service's module with --instance)."""
        service = service_of(name)
        argv = [sys.executable, "-m", SERVICE_MODULES[service], "--stack", str(self.stack.path),
                "-e", self.router, "--seed", str(self.seed)]
        if service != name:
            argv += ["--instance", name]
        if self.lockstep:
            argv.append("--lockstep")
        if self.vehicle:
            argv += ["--vehicle", self.vehicle]
        if name == "planner" and self.mission:
            argv += ["--mission", self.mission]
        if name == "recorder":
            argv += ["--out", str(self.run_dir)]
        for item in self.params.get(service, []):
            argv += ["--param", item]
        return argv

    def start_services(self, names: list[str]) -> None:
        if self.stack.security is not None:   # another machine's login would have no way to its peers
            elsewhere = [n for n in names if self.stack.service(service_of(n)).machine != self.machine]
            if elsewhere:
                raise StackError(f"{self.stack.path}: with [security] a machine starts only its own services "
                                 f"(`zenpilot up --machine NAME`); not here: {', '.join(elsewhere)}")
        # the recorder first so it sees everything; the simulator last, it drives the clock
        order = sorted(names, key=lambda n: (n != "recorder", n == "sim"))
        for name in order:
            self._start_service(name)
            if name == "recorder":   # its token means it listens: nothing the others send is missed
                self.wait_alive(["recorder"])   # one still missing is reported with the others

    def start_one_process(self, names: list[str]) -> subprocess.Popen:
        """A lockstep flight's services as threads of one process (deploy/one_process.py), each
        with the command line its own process would have; no router. Registered as ONE_PROCESS."""
        if not self.lockstep:
            raise StackError("one process runs lockstep only: real time runs a process per service")
        self._check_machine_by_machine()   # as with a process per service: the stack file's word stands
        order = sorted(names, key=lambda n: (n != "recorder", n == "sim"))
        services = [(n, SERVICE_MODULES[n], self.service_argv(n)[3:]) for n in order]   # past python -m module
        return self._spawn(ONE_PROCESS, [sys.executable, "-m", "deploy.one_process", "--logs",
                                         str(self.run_dir / "logs"), "--vehicle-id", str(self.stack.vehicle_id),
                                         json.dumps(services)])

    def _start_service(self, name: str, append: bool = False, restarted: bool = False) -> None:
        proc = self._spawn(name, self.service_argv(name) + (["--restarted"] if restarted else []), append)
        self._set_nice(name, proc.pid)

    def _set_nice(self, name: str, pid: int) -> None:
        if nice := self.stack.service(service_of(name)).nice:
            try:
                os.setpriority(os.PRIO_PROCESS, pid, nice)
            except OSError as exc:  # it still runs, at the default priority: say so
                print(f"zenpilot: {name}: could not set nice {nice}: {exc}", file=sys.stderr)

    def restart(self, name: str) -> None:
        """Start a service again with the same command line and `--restarted` (the supervisor's
        restart), in the warm spare when one waits (deploy/spare.py); its output is appended to
        its log. A new spare is started for the next restart."""
        argv = self.service_argv(name) + ["--restarted"]
        spare, self.spare = self.spare, None
        if spare is None or spare.poll() is not None:
            self._start_service(name, append=True, restarted=True)
            return
        log = self.run_dir / "logs" / f"{name}.log"
        with open(log, "a") as fh:
            fh.write(f"--- zenpilot: {name} restarted at {time.strftime('%H:%M:%S')} (warm spare) ---\n")
        try:
            spare.stdin.write(json.dumps({"module": argv[2], "argv": argv[3:], "log": str(log)}) + "\n")
            spare.stdin.close()
        except OSError:   # the spare died meanwhile: a cold start
            self._start_service(name, append=True, restarted=True)
            return
        self.procs[name] = spare
        self._set_nice(name, spare.pid)
        self.start_spare()

    def start_spare(self) -> None:
        """A process with the services' imports done, waiting to become the next one restarted."""
        if self.spare is None or self.spare.poll() is not None:
            log = open(self.run_dir / "logs" / "spare.log", "a")
            self.spare = subprocess.Popen([sys.executable, "-m", "deploy.spare"], stdin=subprocess.PIPE,
                                          stdout=log, stderr=subprocess.STDOUT, env=self._service_env(),
                                          text=True, start_new_session=True)
            log.close()

    def stop_spare(self) -> None:
        if self.spare is not None and self.spare.poll() is None:
            self.spare.kill()
            self.spare.wait()
        self.spare = None

    def kill(self, name: str) -> None:
        """SIGKILL a service (the supervisor's answer to a hang), not waiting for it to end: one
        blocked in the kernel (a hung disk, a frozen cgroup) dies only when it wakes, without
        running again, and the supervisor must not wait with it (it did: 0.3-0.4 s, and forever
        for a disk that never answers). Reaped at a later kill or at the stop."""
        proc = self.procs[name]
        if proc.poll() is None:
            proc.kill()
            self.dying.append(proc)
        self.dying = [p for p in self.dying if p.poll() is None]

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

    def stop(self, names: list[str] | None = None, grace_s: float = STOP_GRACE_S) -> list[str]:
        """SIGTERM to each service named (all by default), then up to `grace_s` for them to
        finish; SIGKILL to those still running, reported. Returns the ones killed."""
        names = [n for n in (names or list(self.procs)) if n in self.procs]
        for n in names:
            if self.procs[n].poll() is None:
                self.procs[n].send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        killed = []
        for n in names:
            try:
                self.procs[n].wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.procs[n].kill()
                self.procs[n].wait()
                killed.append(n)
                print(f"zenpilot: {n} did not stop within {grace_s:.0f} s of SIGTERM; killed "
                      f"(see {self.run_dir / 'logs' / (n + '.log')})", file=sys.stderr, flush=True)
        return killed

    def stop_all(self) -> None:
        """Stop everything started, in the order that keeps the flight log whole: the services,
        then the recorder (it writes what they sent last, then the log's summary), then the
        router. A second Ctrl-C or SIGTERM meanwhile is answered, not obeyed."""
        def still_stopping(*_):
            print("zenpilot: stopping; the recorder is finishing the flight log", file=sys.stderr, flush=True)
        main = threading.current_thread() is threading.main_thread()   # only it may set handlers
        previous = {sig: signal.signal(sig, still_stopping) for sig in (signal.SIGINT, signal.SIGTERM)} if main else {}
        try:
            self.stop_spare()
            for group, grace_s in stop_groups(list(self.procs), [self.run_dir / LOG_NAME]):
                if group == ["recorder"]:
                    time.sleep(DELIVERY_S)
                self.stop(group, grace_s)
            self._reap_dying(STOP_GRACE_S)
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)

    def _reap_dying(self, timeout_s: float) -> None:
        """Wait up to `timeout_s` for the processes killed in flight; say which never ended."""
        deadline = time.monotonic() + timeout_s
        for proc in self.dying:
            try:
                proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                print(f"zenpilot: process {proc.pid}, killed as hung, has not ended (blocked in the kernel)",
                      file=sys.stderr, flush=True)
        self.dying = [p for p in self.dying if p.poll() is None]

    def failed(self) -> dict[str, int]:
        """Services that exited with an error status."""
        return {n: p.returncode for n, p in self.procs.items() if p.poll() not in (None, 0)}
