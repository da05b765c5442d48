"""Stack files: which services run, at what rates, with which parameters, on which machine.

A stack file is TOML:

    [stack]
    vehicle_id = 0            # the <vehicle> in zp/<vehicle>/...
    vehicle = "x250"          # airframe file in flight/vehicles/ (a mission may name another)
    tick_rate_hz = 400        # simulator tick; every service rate must divide it

    [machines.vehicle]        # one table per machine
    router = "tcp/127.0.0.1:7447"   # the Zenoh router its services connect to (the router listens there)
    runs_router = true        # `zenpilot up --machine vehicle` starts that router
    listen = ["tls/10.0.0.2:7448"]  # more endpoints its router listens on: a link to other hosts
    connect = []              # routers of other hosts its router links to
    services_listen = ["tcp/127.0.0.1:0"]  # where its services listen (default: loopback only)
    bulk_max_hz = 20.0        # its router forwards each bulk key (camera images) at most this often (0: any)

    [security]                # optional: TLS, passwords and access control (services/security.py)
    dir = "keys"              # made by `zenpilot certs keys --stack FILE`; relative to this file

    [services.attitude]
    machine = "vehicle"
    rate_hz = 200
    nice = 0                  # OS scheduling niceness (0..19): above 0 yields the CPU to the loops
    priority = 80             # real-time (SCHED_FIFO) priority 1..99 for a rate loop; 0: normal scheduling
    cpu = [1]                 # CPUs the process may run on (affinity); [] or absent: any
    restart = "on-failure"    # the supervisor restarts it when it dies (real time): on-failure | always | never
    restart_limit = 3         # ... at most this many times (deploy/supervisor.py)
    hang_restart_s = 0.5      # stopped or stuck this long: killed and restarted by its policy
    [services.attitude.params]
    state_source = "truth"
    [services.motors]
    standby = true            # real time: a second driver runs beside it, taking over (services/standby.py)

Every service checks its own parameters against its declarations (services/params/:
type, bounds, choices; `resolve_params`), so a typo is refused with the file, section and
key; so are settings of two services that cannot fly together (`check_compatible`). A
stack file gives only what differs from the declared defaults (docs/parameters.md).
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from services.params import Param
from services.security import Security, SecurityError, endpoint_host, is_loopback, parse_security

if TYPE_CHECKING:
    from flight.control.mission import Mission

# the deployment's files: services read them by path (never import deploy/)
STACKS_DIR = Path(__file__).resolve().parents[1] / "deploy" / "stacks"
MISSIONS_DIR = STACKS_DIR.parent / "missions"
# what the supervisor (deploy/supervisor.py) does when a service dies; a stack file may say otherwise
RESTART_POLICIES = ("on-failure", "always", "never")
DEFAULT_RESTART = {"sim": "never", "recorder": "never"}   # every other service: "on-failure"
DEFAULT_RESTART_LIMIT = 3
NEVER_RESTARTED = ("sim",)  # a new world mid-flight
# a hung level is no better than a dead one: killed and restarted while the failsafes still fly
DEFAULT_HANG_RESTART_S = 0.5
DEFAULT_STACK = STACKS_DIR / "default.toml"
# services with a hot standby (`standby = true`): a second process of the service, running beside it
STANDBY_SERVICES = ("motors",)
STANDBY_SUFFIX = ".b"   # the second process's name: "motors.b" (services/standby.py INSTANCES)


def service_of(process: str) -> str:
    """The service a process runs: "motors" for the standby driver "motors.b" too."""
    return process[:-len(STANDBY_SUFFIX)] if process.endswith(STANDBY_SUFFIX) else process


def standby_processes(stack: "Stack", names, real_time: bool) -> list[str]:
    """The standby processes to start beside `names` (real time only: lockstep runs one driver)."""
    return [n + STANDBY_SUFFIX for n in names if n in STANDBY_SERVICES and real_time and stack.services[n].standby]

# service name -> python module that runs it (console script zenpilot-<name>)
SERVICE_MODULES = {
    "sim": "services.sim",
    "motors": "services.motors",
    "attitude": "services.attitude",
    "position": "services.position",
    "planner": "services.planner",
    "vision": "services.vision",
    "recorder": "services.recorder",
    "mavlink": "services.mavlink",
}
# services that take part in lockstep (the recorder only listens; the MAVLink
# bridge is real time in every mode: a ground station lives on the wall clock)
LOCKSTEP_PARTICIPANTS = ("motors", "attitude", "position", "planner", "vision")
# Links to the outside world run on the wall clock whatever the mode; a lockstep run leaves them
# out, or its log would depend on the machine's speed (their health, their rates).
WALL_CLOCK_ONLY = ("mavlink",)


def lockstep_services(names) -> list[str]:
    """The services a lockstep run starts: all but the wall-clock links."""
    return [n for n in names if n not in WALL_CLOCK_ONLY]


class StackError(ValueError):
    """A stack file, mission or parameter that cannot be used; the message says where."""


@dataclass(frozen=True)
class ServiceSpec:
    name: str
    machine: str
    rate_hz: float  # 0: event driven
    params: dict[str, Any] = field(default_factory=dict)
    nice: int = 0  # OS niceness the launcher gives the process: >0 for work the flight must not wait for
    priority: int = 0  # SCHED_FIFO priority the service asks for (1..99), 0: normal scheduling
    cpu: tuple[int, ...] = ()  # CPU affinity the service asks for; (): any CPU
    restart: str = "on-failure"  # the supervisor's policy (deploy/supervisor.py): on-failure | always | never
    restart_limit: int = 3       # restarts at most, per run
    hang_restart_s: float = DEFAULT_HANG_RESTART_S  # stopped or stuck this long: a hang, killed and restarted
    standby: bool = False   # motors only: a hot-standby second driver (services/standby.py), real time


# Where a service listens unless its machine says otherwise: its own host only. A peer that
# listened on every interface could be reached from the network, past the router.
SERVICES_LISTEN = ("tcp/127.0.0.1:0",)


@dataclass(frozen=True)
class Machine:
    name: str
    router: str
    runs_router: bool
    listen: tuple[str, ...] = ()      # more endpoints its router listens on (a link to other hosts)
    connect: tuple[str, ...] = ()     # other hosts' routers its router links to
    services_listen: tuple[str, ...] = SERVICES_LISTEN
    bulk_max_hz: float = 0.0          # its router's cap per bulk key (schemas priority "bulk"); 0: none


@dataclass(frozen=True)
class Stack:
    path: Path
    vehicle_id: int
    vehicle: str
    tick_rate_hz: float
    machines: dict[str, Machine]
    services: dict[str, ServiceSpec]
    security: Security | None = None

    def service(self, name: str) -> ServiceSpec:
        if name not in self.services:
            raise StackError(f"{self.path}: no [services.{name}] section")
        return self.services[name]

    def period_ticks(self, name: str) -> int:
        return round(self.tick_rate_hz / self.service(name).rate_hz)


def _expect(value: Any, kind: type | tuple, where: str) -> Any:
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        name = kind.__name__ if isinstance(kind, type) else "/".join(k.__name__ for k in kind)
        raise StackError(f"{where}: expected {name}, got {value!r}")
    return value


def load_stack(path: str | Path | None = None) -> Stack:
    path = Path(path) if path else DEFAULT_STACK
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise StackError(f"{path}: stack file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise StackError(f"{path}: not valid TOML: {exc}") from None
    unknown = set(doc) - {"stack", "machines", "services", "security"}
    if unknown:
        raise StackError(f"{path}: unknown top-level table(s) {sorted(unknown)}")
    head = doc.get("stack", {})
    unknown = set(head) - {"vehicle_id", "vehicle", "tick_rate_hz", "name", "description"}
    if unknown:
        raise StackError(f"{path}: [stack]: unknown key(s) {sorted(unknown)}")
    tick_rate = _expect(head.get("tick_rate_hz", 400.0), float, f"{path}: [stack] tick_rate_hz")
    vehicle_id = _expect(head.get("vehicle_id", 0), int, f"{path}: [stack] vehicle_id")
    vehicle = _expect(head.get("vehicle", "x250"), str, f"{path}: [stack] vehicle")
    machines = {}
    for name, m in doc.get("machines", {}).items():
        where = f"{path}: [machines.{name}]"
        unknown = set(m) - {"router", "runs_router", "description", "listen", "connect", "services_listen",
                             "bulk_max_hz"}
        if unknown:
            raise StackError(f"{where}: unknown key(s) {sorted(unknown)}")
        machines[name] = Machine(
            name,
            _endpoint(m.get("router", "tcp/127.0.0.1:7447"), f"{where} router"),
            _expect(m.get("runs_router", False), bool, f"{where} runs_router"),
            _endpoints(m.get("listen", []), f"{where} listen"),
            _endpoints(m.get("connect", []), f"{where} connect"),
            _endpoints(m.get("services_listen", list(SERVICES_LISTEN)), f"{where} services_listen", empty=False),
            _expect(m.get("bulk_max_hz", 0.0), float, f"{where} bulk_max_hz"),
        )
        if not 0.0 <= machines[name].bulk_max_hz < float("inf"):
            raise StackError(f"{where} bulk_max_hz: must be >= 0 (0: no cap), got {machines[name].bulk_max_hz}")
    if not machines:
        raise StackError(f"{path}: no [machines.*] table")
    try:
        security = parse_security(doc["security"], path) if "security" in doc else None
    except SecurityError as exc:
        raise StackError(str(exc)) from None
    if security:
        _check_secure_links(path, machines)
    services = {}
    for name, s in doc.get("services", {}).items():
        where = f"{path}: [services.{name}]"
        if name not in SERVICE_MODULES:
            raise StackError(f"{where}: unknown service (known: {', '.join(SERVICE_MODULES)})")
        unknown = set(s) - {"machine", "rate_hz", "params", "nice", "priority", "cpu", "restart", "restart_limit",
                             "hang_restart_s", "standby"}
        if unknown:
            raise StackError(f"{where}: unknown key(s) {sorted(unknown)}")
        machine = _expect(s.get("machine", next(iter(machines))), str, f"{where} machine")
        if machine not in machines:
            raise StackError(f"{where}: machine {machine!r} is not defined under [machines]")
        rate = _expect(s.get("rate_hz", 0.0), float, f"{where} rate_hz")
        if rate < 0 or (rate > 0 and abs(tick_rate / rate - round(tick_rate / rate)) > 1e-9):
            raise StackError(f"{where}: rate_hz {rate} must divide the tick rate {tick_rate}")
        nice = _expect(s.get("nice", 0), int, f"{where} nice")
        if not 0 <= nice <= 19:  # raising a process's priority needs privileges; lowering it does not
            raise StackError(f"{where}: nice {nice} must be within 0..19")
        priority = _expect(s.get("priority", 0), int, f"{where} priority")
        if not 0 <= priority <= 99:
            raise StackError(f"{where}: priority {priority} must be within 0..99 (0: normal scheduling)")
        cpu = _expect(s.get("cpu", []), list, f"{where} cpu")
        if not all(isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in cpu):
            raise StackError(f"{where}: cpu {cpu!r} must be a list of CPU numbers (0, 1, ...)")
        restart = _expect(s.get("restart", DEFAULT_RESTART.get(name, "on-failure")), str, f"{where} restart")
        if restart not in RESTART_POLICIES:
            raise StackError(f"{where}: restart {restart!r} must be one of {', '.join(RESTART_POLICIES)}")
        if name in NEVER_RESTARTED and restart != "never":
            raise StackError(f"{where}: restart {restart!r}: the simulator is never restarted (a new world "
                             "mid-flight); say \"never\" or leave it out")
        restart_limit = _expect(s.get("restart_limit", DEFAULT_RESTART_LIMIT), int, f"{where} restart_limit")
        if not 0 <= restart_limit <= 100:
            raise StackError(f"{where}: restart_limit {restart_limit} must be within 0..100")
        hang_restart_s = _expect(s.get("hang_restart_s", DEFAULT_HANG_RESTART_S), float, f"{where} hang_restart_s")
        if not 0.1 <= hang_restart_s <= 60.0:
            raise StackError(f"{where}: hang_restart_s {hang_restart_s} must be within 0.1..60 s")
        standby = _expect(s.get("standby", False), bool, f"{where} standby")
        if standby and name not in STANDBY_SERVICES:
            raise StackError(f"{where}: standby: only {', '.join(STANDBY_SERVICES)} has a hot standby")
        services[name] = ServiceSpec(name, machine, rate, dict(_expect(s.get("params", {}), dict, f"{where} params")),
                                     nice, priority, tuple(cpu), restart, restart_limit, hang_restart_s, standby)
    for needed in ("sim", "motors", "attitude", "position", "planner"):
        if needed not in services:
            raise StackError(f"{path}: the stack needs a [services.{needed}] section")
    check_compatible(str(path), {name: spec.params for name, spec in services.items()})
    return Stack(
        path=path,
        vehicle_id=vehicle_id,
        vehicle=vehicle,
        tick_rate_hz=tick_rate,
        machines=machines,
        services=services,
        security=security,
    )


def _endpoint(value: Any, where: str) -> str:
    value = _expect(value, str, where)
    try:
        endpoint_host(value)
    except ValueError as exc:
        raise StackError(f"{where}: {exc}") from None
    return value


def _endpoints(value: Any, where: str, empty: bool = True) -> tuple[str, ...]:
    if isinstance(value, str):
        value = [value]
    value = _expect(value, list, where)
    if not value and not empty:
        raise StackError(f"{where}: at least one endpoint (default: {list(SERVICES_LISTEN)})")
    return tuple(_endpoint(v, f"{where}[{i}]") for i, v in enumerate(value))


def _check_secure_links(path: Path, machines: dict[str, "Machine"]) -> None:
    """With [security], the only door from another host is a router's TLS (or QUIC) endpoint: anything
    else reachable from the network would pass without a certificate or the access control."""
    for m in machines.values():
        where = f"{path}: [machines.{m.name}]"
        if not is_loopback(m.router):
            raise StackError(f"{where} router {m.router!r}: with [security] the services' router endpoint must "
                             f"be on loopback (tcp/127.0.0.1:PORT); other hosts link through `listen` (tls/...)")
        for key, endpoints in (("listen", m.listen), ("connect", m.connect)):
            for e in endpoints:   # quic: TLS 1.3 with the same certificates (its datagrams: best effort)
                if endpoint_host(e)[0] not in ("tls", "quic"):
                    raise StackError(f"{where} {key} {e!r}: with [security] a link between hosts must be "
                                     f"tls/HOST:PORT or quic/HOST:PORT")
        for e in m.services_listen:
            if not is_loopback(e):
                raise StackError(f"{where} services_listen {e!r}: with [security] services listen on loopback only "
                                 f"(other hosts reach them through the router, where access control is enforced)")
        if m.listen and m.connect:
            raise StackError(f"{where}: with [security] a router either accepts links (listen) or makes them "
                             f"(connect), not both: the accepting router is where access control is enforced")


def parse_overrides(items: list[str] | None) -> dict[str, Any]:
    """`--param key=value` pairs; values parsed as TOML (numbers, strings, arrays)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise StackError(f"--param {item!r}: expected KEY=VALUE")
        key, raw = item.split("=", 1)
        try:
            out[key.strip()] = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            out[key.strip()] = raw  # a bare word is a string
    return out


def resolve_params(declared: dict[str, Any], given: dict[str, Any], where: str) -> dict[str, Any]:
    """`given` over the declared defaults (name -> services.params.Param, or a bare default), as plain
    values; an unknown key, a wrong type, a value out of bounds or not among the choices is refused
    with `where` and the key, a nested table's keys too (`Param.check`, flight/param.py)."""
    out = {}
    for key, d in declared.items():
        out[key] = d.value() if isinstance(d, Param) else d
    for key, value in given.items():
        out[key] = check_param(declared, key, value, where)
    return out


def check_param(declared: dict[str, Any], key: str, value: Any, where: str) -> Any:
    """One value given for `key`, checked against its declaration (Param.check) as resolve_params
    checks each (start-up, a sweep's grid, param/set in flight): returned as the service holds it
    (an int for a float parameter becomes a float), or refused with `where`.key and what is wrong."""
    if key not in declared:
        raise StackError(f"{where}: unknown parameter {key!r} (known: {', '.join(sorted(declared))})")
    decl = declared[key] if isinstance(declared[key], Param) else Param(declared[key])
    try:
        return decl.check(value, f"{where}.{key}")
    except ValueError as exc:   # ParamError, or a nested table's owner's error: each names where
        raise StackError(str(exc)) from None


def check_compatible(where: str, params: dict[str, dict[str, Any]]) -> None:
    """Settings of two services that cannot fly together, refused before anything flies.
    `params`: service -> the parameters it is given (the stack file's, with any --param)."""
    sim, ekf = params.get("sim", {}), params.get("position", {}).get("ekf", {})
    ekf = ekf if isinstance(ekf, dict) else {}   # not a table: the position service says so
    if "camera_latency_s" not in sim and "camera_latency_step_at_s" not in sim and "max_delay_s" not in ekf:
        return   # the defaults fit (tests/unit/services/test_params.py); the simulator and the EKF stay unloaded
    from flight.estimation.position_ekf import PositionEKFParams
    from services.params.sim import PARAMS as SIM

    key, latency = "camera_latency_s", sim.get("camera_latency_s", SIM["camera_latency_s"].default)
    step_at = sim.get("camera_latency_step_at_s", -1.0)
    stepped = sim.get("camera_latency_step_s", SIM["camera_latency_step_s"].default)
    # a delay step whose stamps follow reaches the EKF as the new delay (one whose stamps do not, as the old)
    if _is_number(step_at) and step_at >= 0 and sim.get("camera_latency_step_stamped", True) is True \
            and _is_number(stepped) and _is_number(latency) and stepped > latency:
        key, latency = "camera_latency_step_s", stepped
    max_delay = ekf.get("max_delay_s", PositionEKFParams.max_delay_s)
    # wrong types are the owners' to report, with their own words
    if _is_number(latency) and _is_number(max_delay) and latency >= max_delay:
        raise StackError(f"{where}: [services.sim.params] {key} = {latency:g} s is not below "
                         f"[services.position.params] ekf.max_delay_s = {max_delay:g} s: the position EKF keeps "
                         f"no history that old and would drop every camera fix")


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def intrinsics_path(stack_path: str | Path, name: str) -> Path:
    """A camera intrinsics file named in a stack's parameters: relative to the stack file's folder."""
    p = Path(name).expanduser()
    return p if p.is_absolute() else Path(stack_path).resolve().parent / p


def mission_path(name_or_path: str) -> Path:
    """A shipped mission's file by name (deploy/missions/NAME.toml), or a .toml path as given."""
    p = Path(name_or_path)
    if p.suffix == ".toml":
        return p
    return MISSIONS_DIR / f"{name_or_path}.toml"


def available_missions() -> list[str]:
    return sorted(p.stem for p in MISSIONS_DIR.glob("*.toml"))


def load_mission(name_or_path: str) -> Mission:
    """Read and check a mission file (by shipped name or path); MissionError names the file."""
    from flight.control.mission import MissionError, parse_mission  # only where missions are read

    path = mission_path(name_or_path)
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise MissionError(f"mission {name_or_path!r}: no file {path} "
                           f"(shipped: {', '.join(available_missions())})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MissionError(f"{path}: cannot read: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise MissionError(f"{path}: not valid TOML: {exc}") from None
    return parse_mission(doc, str(path))
