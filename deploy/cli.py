"""zenpilot: fly missions and run the stack's services.

  zenpilot fly [--mission M] [--lockstep] [--seed N] [--out DIR]   fly a whole mission, then report
  zenpilot up [--machine NAME] [-d]     start the router and a machine's services, show live status
  zenpilot status                        liveliness and health of a running stack
  zenpilot down [--router R | --all]     stop what `zenpilot up -d` started
  zenpilot sweep [--param S.K=V1,V2] [--seeds 0-99] [--workers N | --scheduler ADDR]
                                         fly a grid of lockstep flights on Dask, one table
  zenpilot predict [--mission M]         predict a mission's flips before flying them
  zenpilot report DIR                    redraw a flight's plots, print its metrics, write report.html
  zenpilot view [--port 8765]            live Foxglove view of a running stack (WebSocket)
  zenpilot log info|recover RUN_OR_FILE  what a flight log holds; recover a cut one
  zenpilot missions                      list the shipped missions
  zenpilot certs DIR [--stack FILE]      make the TLS certificates and logins of a stack's machines
  zenpilot train-gyrovertical [--seed N] train the adaptive gyro-vertical (004) on simulator flights
  zenpilot calibrate-camera DIR --out F  camera intrinsics from checkerboard images (OpenCV)
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

import schemas
from deploy import gyrovertical_training, predict_cli, sweep
from deploy.launcher import (DELIVERY_S, ONE_PROCESS, ONE_PROCESS_FAILED, STOP_GRACE_S, Launcher, alive_services,
                             client_session, free_port, recorder_grace_s, stop_groups, wait_port)
from deploy.progress import FlightProgress
from deploy.report import REPORT_NAME, RUN_FILES, write_report
from deploy.supervisor import POLL_S, Supervisor, supervisor_priority
from flight.control.mission import MissionError
from schemas.flightlog import LOG_NAME, LogError, LogScan, log_is_complete, read_log, recover, scan
from services.runtime import on_stop_signals, tie_to_parent
from services.stack import (StackError, available_missions, load_mission, load_stack, lockstep_services,
                            STANDBY_SERVICES, service_of, standby_processes)

DEFAULT_MISSION = "steps"
STATE_DIR = Path(os.environ.get("ZENPILOT_STATE_DIR", Path.home() / ".zenpilot"))


def _param_overrides(items: list[str] | None, stack) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for item in items or []:
        service, sep, rest = item.partition(".")
        if not sep or "=" not in rest:
            raise StackError(f"--set {item!r}: expected SERVICE.KEY=VALUE, e.g. attitude.k=[12,12,12]")
        if service not in stack.services:   # a typo must not be dropped without a word
            raise StackError(f"--set {item!r}: no service {service!r} in {stack.path} "
                             f"(services: {', '.join(stack.services)})")
        out.setdefault(service, []).append(rest)
    return out


# ---------------------------------------------------------------- fly
def cmd_fly(args) -> int:
    stack = load_stack(args.stack)
    mission = load_mission(args.mission or DEFAULT_MISSION)
    out = Path(args.out or f"runs/{mission.name}-{'lockstep' if args.lockstep else 'realtime'}-seed{args.seed}")
    out.mkdir(parents=True, exist_ok=True)
    # what flew, beside its log: report.html shows them
    for source, name in ((mission.path, RUN_FILES["mission"]), (stack.path, RUN_FILES["stack"])):
        try:
            shutil.copyfile(source, out / name)
        except shutil.SameFileError:   # flown from the copy itself
            pass
    (out / RUN_FILES["command"]).write_text("zenpilot " + shlex.join(sys.argv[1:]) + "\n")
    router = f"tcp/127.0.0.1:{args.port or free_port()}"
    if args.foxglove is not None and not 0 < args.foxglove < 65536:
        raise StackError(f"--foxglove {args.foxglove}: expected a port number 1..65535")
    # a simulated flight belongs to this command: killed, it takes the stack with it (its log written)
    launcher = Launcher(stack, out, router, lockstep=args.lockstep, seed=args.seed,
                        vehicle=mission.vehicle, mission=mission.path, params=_param_overrides(args.set, stack),
                        die_with_parent=True)
    names = lockstep_services(stack.services) if args.lockstep else list(stack.services)
    names += _standbys(stack, names, not args.lockstep)
    # lockstep in one process unless asked otherwise, or the bus is wanted (a live view, a router's port)
    one_process = args.lockstep and not args.processes and args.foxglove is None and args.port is None
    print(f"zenpilot: flying {mission.name} ({mission.vehicle}, "
          f"{'lockstep' if args.lockstep else 'real time'}{', one process' if one_process else ''}, "
          f"seed {args.seed}) -> {out}", flush=True)
    wall0 = time.monotonic()
    started = time.time()
    completed_run = False
    try:
        if one_process:
            completed_run = _fly_one_process(launcher, names, mission.timeout_s * 20.0 + 30.0)
        else:
            completed_run = _fly_processes(launcher, names, args, mission, out)
    finally:
        launcher.stop_all()
    wall = time.monotonic() - wall0
    report_startup(out, started)
    if not completed_run:
        print(f"zenpilot: the simulator stopped with an error (see {out / 'logs' / 'sim.log'})", file=sys.stderr)
    metrics = analyse(out, {"mission": mission.name, "mode": "lockstep" if args.lockstep else "realtime",
                            "seed": args.seed, "vehicle": mission.vehicle}, plots=not args.no_plots)
    flown = f"{metrics['duration_s']:.1f} s" if metrics.get("duration_s") is not None else "nothing"
    print(f"zenpilot: {flown} flown in {wall:.1f} s of wall time; "
          f"log{'' if args.no_plots else ', plots, report.html'} and metrics.json in {out}")
    if metrics.get("crashed"):
        print("zenpilot: the vehicle crashed (truth on the ground mid-mission, or tilted past 60 deg)", file=sys.stderr)
    return 0 if metrics.get("completed") and not metrics.get("crashed") else 1


def _standbys(stack, names: list[str], real_time: bool) -> list[str]:
    """The hot-standby processes to start beside `names` (services/standby.py); in lockstep, said
    to be off: one driver keeps the flight deterministic."""
    if not real_time and any(stack.services[n].standby for n in names):
        print("zenpilot: [services.motors] standby = true: the hot standby runs in real time only; "
              "this lockstep flight flies one motor driver", file=sys.stderr, flush=True)
    return standby_processes(stack, names, real_time)


def _fly_processes(launcher: Launcher, names: list[str], args, mission, out: Path) -> bool:
    """A flight with a process per service over the router; True if the simulator ended it."""
    stack = launcher.stack
    progress = session = supervisor = None
    try:
        launcher.start_router()
        if args.foxglove is not None:   # the live view, ground side: it only listens
            start_view(launcher, launcher.router, args.foxglove, mission.vehicle, out)
        launcher.start_services(names)
        missing = launcher.wait_alive(names)
        if missing:
            raise StackError(f"no liveliness token from {', '.join(sorted(missing))} after 30 s "
                             f"(logs in {out / 'logs'})")
        limit = mission.timeout_s * (20.0 if args.lockstep else 1.5) + 30.0
        deadline = time.monotonic() + limit
        session = client_session(launcher.router)
        progress = FlightProgress(session, stack.vehicle_id, mission.items, real_time=not args.lockstep)
        supervisor = watch_services(launcher, [n for n in names if n != "sim"], session, not args.lockstep)
        while launcher.procs["sim"].poll() is None:
            progress.show()
            lost = supervisor.take_lost()
            bad = {n: launcher.procs[n].returncode for n in lost if launcher.procs[n].returncode != 0}
            if bad:
                raise StackError("service(s) failed during the flight: " + ", ".join(
                    f"{n} (status {c}, see {out / 'logs' / (n + '.log')})" for n, c in bad.items())
                    + (f"; the flight log holds the chunks the recorder wrote before: `zenpilot log recover {out}`"
                       if "recorder" in bad else ""))
            if time.monotonic() > deadline:
                raise StackError(f"the flight did not finish within {limit:.0f} s of wall time")
            time.sleep(POLL_S)
        return launcher.procs["sim"].returncode == 0
    finally:
        if supervisor is not None:
            supervisor.stop()   # before the services stop: their ends are no failures
        if progress is not None:
            progress.close()
        if session is not None:
            session.close()


def _fly_one_process(launcher: Launcher, names: list[str], limit_s: float) -> bool:
    """A lockstep flight in one process (deploy/one_process.py); True if the simulator ended it."""
    proc = launcher.start_one_process(names)
    deadline = time.monotonic() + limit_s
    while proc.poll() is None:
        if time.monotonic() > deadline:
            raise StackError(f"the flight did not finish within {limit_s:.0f} s of wall time")
        time.sleep(POLL_S)
    if proc.returncode == ONE_PROCESS_FAILED:
        said = _read(launcher.run_dir / "logs" / f"{ONE_PROCESS}.log").strip().splitlines()
        raise StackError(said[-1] if said else "a service failed during the flight")
    if proc.returncode < 0:   # killed: the recorder with the rest
        raise StackError(f"the stack's process was killed (signal {-proc.returncode}); the flight log holds the "
                         f"chunks the recorder wrote before: `zenpilot log recover {launcher.run_dir}`")
    return proc.returncode == 0


VIEW_NICE = 10   # the live view yields the CPU to the flight's loops (as the MAVLink bridge does)


def start_view(launcher: Launcher, router: str, port: int, vehicle: str, out: Path) -> None:
    argv = [sys.executable, "-m", "deploy.cli", "view", "--router", router, "--port", str(port),
            "--stack", str(launcher.stack.path), "--vehicle", vehicle]
    proc = launcher._spawn("view", argv)
    try:
        os.setpriority(os.PRIO_PROCESS, proc.pid, VIEW_NICE)
    except OSError:
        pass   # it runs at the default priority, on the ground side of the link
    if not wait_port(f"tcp/127.0.0.1:{port}", 15.0) or proc.poll() is not None:
        raise StackError(f"--foxglove {port}: the live view did not start (see {out / 'logs' / 'view.log'})")
    print(f"zenpilot: live Foxglove view on ws://127.0.0.1:{port}", flush=True)


def report_startup(out: Path, started: float) -> None:
    """How long `zenpilot fly` took to the simulator's first tick (the planner's JAX compile apart)."""
    logs = out / "logs"
    first = re.search(r"first tick at ([0-9.]+)", _read(logs / "sim.log"))
    if not first:
        return
    built = sum(float(x) for x in re.findall(r"built \(JAX compile and warm-up\) in ([0-9.]+) s",
                                             _read(logs / "planner.log")))
    print(f"zenpilot: start-up {float(first.group(1)) - started:.1f} s to the first tick"
          + (f" (the planner's JAX compile and warm-up {built:.1f} s of it)" if built else ""), flush=True)


def _read(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""


def watch_services(launcher: Launcher, names: list[str], session, real_time: bool) -> Supervisor:
    """The supervisor of `names` (deploy/supervisor.py), told of every health message and, in
    real time, of every loop's beat (the other machines' services' too, which it reports); there
    it also publishes its own health (supervisor/health) once a second."""
    publish = None
    vehicle = launcher.stack.vehicle_id
    if real_time:   # in lockstep a wall-clock message would make the log depend on the machine
        publisher = session.declare_publisher(schemas.HEALTH.key(vehicle, "supervisor"))
        seq = iter(range(1 << 62))

        def publish(health: dict) -> None:
            publisher.put(schemas.HEALTH.encode(time.time(), next(seq), "supervisor", health))
    # the stack's services this launcher did not start run on other machines: watched by their beats
    remote = [n for n in launcher.stack.services if n not in launcher.procs]
    supervisor = Supervisor(launcher, names, real_time, publish=publish, remote=remote,
                            say=lambda text: print(text, file=sys.stderr, flush=True))
    prefix = f"zp/{vehicle}/"
    supervisor.subscription = session.declare_subscriber(
        f"{prefix}*/health", lambda sample: supervisor.health_seen(str(sample.key_expr)[len(prefix):-len("/health")]))
    if real_time:
        launcher.start_spare()   # the next restart's process, its imports done
        beats = schemas.BEAT.key(vehicle, "")
        supervisor.beats = session.declare_subscriber(
            f"{beats}*", lambda sample: supervisor.beat_seen(str(sample.key_expr)[len(beats):]))
    # its own thread, in real time at a priority below the loops (with Zenoh's threads, which bring
    # the beats): a starved supervisor took every loop for hung (deploy/supervisor.py)
    supervisor.start(supervisor_priority(launcher.stack, names) if real_time else 0)
    return supervisor


def analyse(out: Path, info: dict, plots: bool = True, keep: dict | None = None) -> dict:
    """The flight's metrics (metrics.json, the table; the plots and report with `plots`).
    keep: a dict that receives the log read ("log"), for a caller that reads it too (one read
    less: ~0.8 s for a 20 s hover)."""
    from deploy.metrics import compute_metrics, format_table

    found = LogScan(out / LOG_NAME)
    try:
        log = read_log(out / LOG_NAME, found)
    except (LogError, OSError) as exc:
        raise StackError(f"cannot read the flight log: {exc}") from None
    if keep is not None:
        keep["log"] = log
    if not found.complete:
        print(f"zenpilot: {found.describe()}; the report covers what it holds "
              f"(`zenpilot log recover {out}` makes it a complete file)", file=sys.stderr)
    if not log:
        raise StackError(f"{out / LOG_NAME}: no message to report on")
    try:
        metrics = compute_metrics(log, info)
    except Exception as exc:  # a log cut early lacks what a metric needs: say so, not a traceback
        raise StackError(f"{out / LOG_NAME}: the metrics cannot be computed from this log "
                         f"({type(exc).__name__}: {exc})") from None
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, sort_keys=True) + "\n")
    table = format_table(metrics)
    if plots:
        from deploy.plots import make_plots
        paths = make_plots(log, out, vehicle=info.get("vehicle"))
        write_report(out, metrics, table, paths, "" if found.complete else found.describe())
    print(table)
    return metrics


def cmd_report(args) -> int:
    out = Path(args.dir)
    if not (out / LOG_NAME).exists():
        raise StackError(f"{out}: no {LOG_NAME} here (give the --out directory of a flight)")
    info = {}
    try:
        old = json.loads((out / "metrics.json").read_text())
        info = {k: old.get(k) for k in ("mission", "mode", "seed", "vehicle")}
    except (OSError, ValueError, AttributeError):
        pass   # none yet (a flight stopped early), or unreadable: the report makes a new one
    analyse(out, info)
    print(f"zenpilot: report in {out / REPORT_NAME}")
    return 0


# ---------------------------------------------------------------- log
def _log_path(given: str) -> Path:
    path = Path(given)
    if path.is_dir():
        path = path / LOG_NAME
    if not path.is_file():
        raise StackError(f"{given}: no flight log there (give a flight's directory or an .mcap file)")
    return path


def cmd_log_info(args) -> int:
    path = _log_path(args.log)
    found = LogScan(path)
    counts: dict[str, int] = {}
    try:
        for channel, _message in scan(path, found):
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    except LogError as exc:
        raise StackError(str(exc)) from None
    print(found.describe())
    for topic in sorted(counts):
        print(f"  {counts[topic]:>8}  {topic}")
    return 0 if found.complete else 1


def cmd_log_recover(args) -> int:
    src = _log_path(args.log)
    if args.output:
        dst = Path(args.output)
        if dst.resolve() == src.resolve():
            raise StackError(f"--output {dst}: the log itself; give another file")
    else:
        if log_is_complete(src):
            print(f"zenpilot: {src} is complete and indexed; nothing to recover")
            return 0
        dst = src   # the run's flight.mcap becomes whole again; the cut file is kept beside it
    try:
        found = recover(src, Path(str(dst) + ".recovered"))
    except LogError as exc:
        raise StackError(str(exc)) from None
    if dst == src:
        kept = src.with_name(src.stem + ".cut" + src.suffix)
        os.replace(src, kept)
        os.replace(Path(str(dst) + ".recovered"), dst)
        print(f"zenpilot: the cut file is kept as {kept}")
    else:
        os.replace(Path(str(dst) + ".recovered"), dst)
    print(f"zenpilot: {found.describe()}")
    print(f"zenpilot: wrote {dst}: {found.messages} messages, complete and indexed")
    return 0


# ---------------------------------------------------------------- up / status / down
def _machine_services(stack, machine: str | None) -> tuple[str, list[str], bool]:
    if machine is None:
        machine = next((m.name for m in stack.machines.values() if m.runs_router), next(iter(stack.machines)))
        names = list(stack.services)  # no --machine: the whole stack here
        return machine, names, True
    if machine not in stack.machines:
        raise StackError(f"{stack.path}: no machine {machine!r} (machines: {', '.join(stack.machines)})")
    names = [n for n, s in stack.services.items() if s.machine == machine]
    return machine, names, stack.machines[machine].runs_router


def _status_lines(session, stack) -> list[str]:
    alive = alive_services(session, stack.vehicle_id)
    # a hot standby's drivers: the active one holds zp/<v>/motors/active/<instance> (services/motors.py)
    standbys = standby_processes(stack, stack.services, True)
    active = {str(r.ok.key_expr).rsplit("/", 1)[1] for r in session.liveliness().get(
        f"zp/{stack.vehicle_id}/motors/active/*", timeout=0.5) if r.ok is not None} if standbys else set()
    lines = [f"{'service':<10} {'alive':<6} {'state':<9} {'rate Hz':>8} {'target':>7} {'overruns':>8}  rejected"]
    replies = {}

    def on_health(sample):
        try:
            msg = schemas.HEALTH.decode(sample.payload.to_bytes())
            replies[msg["header"]["source"]] = msg
        except schemas.SchemaError:
            pass

    sub = session.declare_subscriber(f"zp/{stack.vehicle_id}/*/health", on_health)
    deadline = time.monotonic() + 3.0  # health is published at 1 Hz
    while time.monotonic() < deadline and not alive <= set(replies):
        time.sleep(0.1)
    sub.undeclare()
    for name in [*stack.services, *standbys, *(["supervisor"] if "supervisor" in replies else [])]:
        h = replies.get(name)
        if h:
            rej = ", ".join(f"{k}={v}" for k, v in h["rejected"].items()) or "-"
            if standbys and service_of(name) in STANDBY_SERVICES:
                rej = f"[{'active' if name in active else 'standby'}] " + rej
            live = "yes" if name in alive else "-" if name == "supervisor" else "NO"  # it has no token
            lines.append(f"{name:<10} {live:<6} {h['state']:<9} "
                         f"{h['rate_hz']:>8.1f} {h['target_rate_hz']:>7.0f} {h['overruns']:>8}  {rej}")
        else:
            lines.append(f"{name:<10} {'yes' if name in alive else 'NO':<6} {'-':<9}")
    return lines


def cmd_status(args) -> int:
    stack = load_stack(args.stack)
    up = [st for st in _stacks() if st.live]
    router = args.router or (up[0].router if len(up) == 1 else None) or next(iter(stack.machines.values())).router
    session = client_session(router, stack)
    try:
        print("\n".join(_status_lines(session, stack)))
    finally:
        session.close()
    return 0


# `up -d` keeps what it started in STATE_DIR/<stack>/up-<machine>.json, one folder per stack
# (a stack: the router its services meet on), so `down` stops one stack and no other.
def _stack_dir(router: str) -> Path:
    return STATE_DIR / re.sub(r"[^A-Za-z0-9.]+", "-", router).strip("-")


@dataclass
class _UpStack:
    router: str
    pids: dict[str, int] = field(default_factory=dict)
    run_dirs: list[str] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)
    # `up -d`'s background `up` of each machine: (pid, the services it started)
    supervisors: list[tuple[int, set[str]]] = field(default_factory=list)

    @property
    def live(self) -> dict[str, int]:
        """Its processes still running: the pid alive and its command line naming this stack's
        router (a pid reused by another process since is not ours)."""
        return {n: pid for n, pid in self.pids.items() if _running(pid) and _names_router(pid, self.router)}


def _stacks() -> list[_UpStack]:
    """What `up -d` started, per stack (its machines merged)."""
    found: dict[tuple[Path, str], _UpStack] = {}
    # STATE_DIR/up-*.json: left by a zenpilot before stacks had their own folders
    for f in sorted([*STATE_DIR.glob("*/up-*.json"), *STATE_DIR.glob("up-*.json")]):
        try:
            state = json.loads(f.read_text())
            st = found.setdefault((f.parent, state["router"]), _UpStack(state["router"]))
            st.pids.update({n: int(p) for n, p in state["pids"].items()})
            st.files.append(f)
            if state.get("run_dir"):
                st.run_dirs.append(state["run_dir"])
            if state.get("supervisor"):
                st.supervisors.append((int(state["supervisor"]), set(state["pids"])))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            print(f"zenpilot: {f}: unreadable state file, ignored ({exc})", file=sys.stderr)
    return list(found.values())


DETACH_START_TIMEOUT_S = 120.0   # `up -d`: for the background `up` to report its stack up


def _up_detached(args, stack, machine: str, router: str, run_dir: Path) -> int:
    """`up -d`: the same `zenpilot up` in the background, in its own session (it outlives this
    command and supervises the services, deploy/supervisor.py); returns once it has written the
    state file that `status` and `down` read, or says why it did not start."""
    folder = _stack_dir(router)
    folder.mkdir(parents=True, exist_ok=True)
    state = folder / f"up-{machine}.json"
    state.unlink(missing_ok=True)
    (run_dir / "logs").mkdir(parents=True, exist_ok=True)
    argv = [sys.executable, "-m", "deploy.cli", "up", "--router", router, "--out", str(run_dir),
            "--seed", str(args.seed), "--machine", machine, "--state-file", str(state)]
    argv += ["--stack", str(stack.path)] + (["--mission", args.mission] if args.mission is not None else [])
    argv += (["--lockstep"] if args.lockstep else []) + [a for s in args.set or [] for a in ("--set", s)]
    log = run_dir / "logs" / "up.log"
    with open(log, "w") as out:
        child = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                 start_new_session=True)
    deadline = time.monotonic() + DETACH_START_TIMEOUT_S
    while not state.exists():
        if child.poll() is not None:
            said = log.read_text().strip().splitlines()
            raise StackError(f"the stack did not start: {said[-1] if said else f'status {child.returncode}'} "
                             f"(see {log})")
        if time.monotonic() > deadline:
            os.kill(child.pid, signal.SIGTERM)   # it stops what it started
            raise StackError(f"the stack was not up within {DETACH_START_TIMEOUT_S:.0f} s (see {log})")
        time.sleep(0.1)
    print(f"zenpilot: machine {machine!r} up: router {router}; supervised by pid {child.pid}; logs in {run_dir / 'logs'}")
    return 0


def _write_state(path: Path, stack, router: str, run_dir: Path, launcher) -> dict:
    state = {"router": router, "stack": str(stack.path), "run_dir": str(run_dir),
             "pids": {n: p.pid for n, p in launcher.procs.items()}, "supervisor": os.getpid()}
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(state))
    tmp.replace(path)
    return state["pids"]


def cmd_up(args) -> int:
    stack = load_stack(args.stack)
    machine, names, runs_router = _machine_services(stack, args.machine)
    names += _standbys(stack, names, not args.lockstep)
    # `up --lockstep` keeps the MAVLink bridge (unlike `fly`): a ground station is why one runs
    # `up`, and the bridge lives on the wall clock whatever the clock of the rest
    router = args.router or stack.machines[machine].router
    run_dir = Path(args.out or _stack_dir(router) / f"run-{machine}")
    if args.detach:
        return _up_detached(args, stack, machine, router, run_dir)
    background = args.state_file is not None
    params = _param_overrides(args.set, stack)
    # `up` runs until `down`, unless `--set sim.stop_after_mission=true` (given later, it wins)
    params["sim"] = ["stop_after_mission=false", *params.get("sim", [])]
    # the airframe the mission names, as `fly` flies it (without a mission: the stack's)
    vehicle = load_mission(args.mission).vehicle if args.mission not in (None, "", "none") else None
    launcher = Launcher(stack, run_dir, router, lockstep=args.lockstep, seed=args.seed,
                        vehicle=vehicle, mission=args.mission, params=params, machine=machine)
    try:
        if runs_router:
            launcher.start_router()
        launcher.start_services(names)
        missing = launcher.wait_alive(names)
        if missing:
            raise StackError(f"no liveliness token from {', '.join(sorted(missing))} (logs in {run_dir / 'logs'})")
    except BaseException:
        launcher.stop_all()   # what did start stops again, the recorder's log complete
        raise
    print(f"zenpilot: machine {machine!r} up: router {router}, services {', '.join(names)}; logs in {run_dir / 'logs'}",
          flush=True)
    stop = threading.Event()
    on_stop_signals(stop.set)
    session = client_session(router, stack, machine)
    supervisor = watch_services(launcher, names, session, not args.lockstep)
    recorded = _write_state(Path(args.state_file), stack, router, run_dir, launcher) if background else None
    try:
        drawn = 0.0
        while not stop.is_set():
            supervisor.take_lost()   # `up` flies on whatever is lost (the supervisor said it)
            if background:   # no screen: the state file follows the restarts (`down` stops the new pids)
                if recorded != {n: p.pid for n, p in launcher.procs.items()}:
                    recorded = _write_state(Path(args.state_file), stack, router, run_dir, launcher)
            elif time.monotonic() - drawn >= 1.0:
                drawn = time.monotonic()
                lines = _status_lines(session, stack)
                print("\033[2J\033[H" + f"zenpilot up ({machine}) - Ctrl-C stops\n" + "\n".join(lines), flush=True)
                for n, code in launcher.failed().items():
                    print(f"  {n} exited with status {code} (see {run_dir / 'logs' / (n + '.log')})")
                for event in supervisor.events[-5:]:
                    print(f"  supervisor +{event['t_s']:.1f} s: {event['service']} {event['detail']}")
            stop.wait(POLL_S)
    finally:
        supervisor.stop()
        session.close()
        launcher.stop_all()
        if background:
            Path(args.state_file).unlink(missing_ok=True)
    _say_log(run_dir / LOG_NAME)
    return 0


def _running(pid: int) -> bool:
    """The process exists and has not exited (a zombie waiting for its parent has: `up -d`'s
    services are reaped by init, on some systems a second later)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        return True


def _names_router(pid: int, router: str) -> bool:
    """The process's command line names `router` (every process `up` starts has it: -e or
    --listen); True where /proc cannot tell."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return router.encode() in fh.read().split(b"\0")
    except FileNotFoundError:
        return False
    except OSError:
        return True


def _say_log(path: Path) -> None:
    if path.exists():
        print(f"zenpilot: flight log {path}: "
              + ("complete" if log_is_complete(path) else "NOT complete (`zenpilot log recover` reads what it holds)"))


def cmd_down(args) -> int:
    stacks = _stacks()
    if args.router:
        chosen = [st for st in stacks if st.router == args.router]
        if not chosen:
            print(f"zenpilot: nothing to stop on {args.router} (no stack started there with `zenpilot up -d`)")
            return 0
    else:
        live = [st for st in stacks if st.live]
        if len(live) > 1 and not args.all:
            raise StackError("several stacks are up: " + "; ".join(
                f"{st.router} ({', '.join(sorted(st.live))})" for st in live)
                + ". Say which: `zenpilot down --router ENDPOINT`, or `zenpilot down --all`")
        chosen = stacks   # the live one(s), and the state of stacks already gone
    if not any(st.live for st in chosen):
        print("zenpilot: nothing to stop (no stack started with `zenpilot up -d` is running)")
    for st in chosen:
        pids = st.live
        logs = [Path(d) / LOG_NAME for d in st.run_dirs]
        supervisors = [(pid, names) for pid, names in st.supervisors if _running(pid) and _names_router(pid, st.router)]
        if not pids and not supervisors:   # a stack gone already (stopped otherwise, the machine restarted)
            for f in st.files:
                f.unlink(missing_ok=True)
            continue
        stopped = list(pids)
        # `up -d`'s background `up`s stop their own services in order; the machine with the
        # recorder last, so that it logs what the others sent until they stopped
        for group in ([p for p, names in supervisors if "recorder" not in names],
                      [p for p, names in supervisors if "recorder" in names]):
            for pid in group:
                try:
                    os.kill(pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + 2 * STOP_GRACE_S + recorder_grace_s(logs) + 5.0
            while time.monotonic() < deadline and any(_running(pid) for pid in group):
                time.sleep(0.05)
        pids = st.live   # what they left running (nothing, normally; all of it without them) is stopped here
        for names, grace_s in stop_groups(list(pids), logs):
            if names == ["recorder"]:
                time.sleep(DELIVERY_S)
            stopped += [n for n in names if n not in stopped]
            for n in names:
                try:
                    os.kill(pids[n], signal.SIGTERM)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + grace_s
            while time.monotonic() < deadline and any(_running(pids[n]) for n in names):
                time.sleep(0.05)
            for n in names:
                if _running(pids[n]):
                    try:
                        os.kill(pids[n], signal.SIGKILL)
                    except ProcessLookupError:   # it ended just now
                        continue
                    print(f"zenpilot: {n} did not stop within {grace_s:.0f} s of SIGTERM; killed", file=sys.stderr)
        for f in st.files:
            f.unlink(missing_ok=True)
        print(f"zenpilot: stopped {', '.join(stopped)} ({st.router})")
        for run_dir in st.run_dirs:
            _say_log(Path(run_dir) / LOG_NAME)
    return 0


def cmd_certs(args) -> int:
    from services.security import make_keys
    stack = load_stack(args.stack)
    made = make_keys(Path(args.dir), stack, days=args.days)
    print(f"zenpilot: keys for machines {', '.join(stack.machines)} in {args.dir} ({len(made)} files; "
          f"*.key, *.login, *.users are secret). Copy ca.pem and NAME.* to each machine NAME; keep ca.key "
          f"off the vehicle. Point the stack's [security] dir at the folder (docs/security.md).")
    return 0


def cmd_view(args) -> int:
    from deploy.view import serve
    from flight.vehicle import load_vehicle
    from services.foxglove_map import MarkerGrid

    stack = load_stack(args.stack)
    if not 0 <= args.port < 65536:
        raise StackError(f"--port {args.port}: expected a port number 0..65535 (0: any free one)")
    up = [st for st in _stacks() if st.live]
    router = args.router or (up[0].router if len(up) == 1 else None) or next(iter(stack.machines.values())).router
    vehicle = load_vehicle(args.vehicle or stack.vehicle)
    stop = threading.Event()
    on_stop_signals(stop.set)
    serve(router, stack.vehicle_id, vehicle.motor_positions_m, MarkerGrid.for_stack(stack), args.host, args.port, stop)
    return 0


def cmd_missions(args) -> int:
    for name in available_missions():
        m = load_mission(name)
        print(f"{name:<16} {m.vehicle:<6} {m.description}")
    return 0


def cmd_calibrate_camera(args) -> int:
    from deploy.calibrate import calibrate_folder, parse_pattern, write_calibration

    cal = calibrate_folder(args.folder, parse_pattern(args.pattern), args.square)
    write_calibration(cal, args.out, args.folder)
    i = cal.intrinsics
    print(f"zenpilot: {len(cal.used)} of {len(cal.used) + len(cal.skipped)} images used, RMS reprojection error "
          f"{cal.rms_px:.3f} px: fx {i.fx_px:.2f}, fy {i.fy_px:.2f}, cx {i.cx_px:.2f}, cy {i.cy_px:.2f} px, "
          f"distortion {[round(x, 5) for x in i.distortion]} -> {args.out}")
    for skipped in cal.skipped:
        print(f"zenpilot: skipped {skipped}", file=sys.stderr)
    out = Path(args.out).resolve()   # a relative path in a stack's parameters is the stack file's
    print(f"zenpilot: fly with it: --set sim.camera_intrinsics={out} --set vision.camera_intrinsics={out}")
    return 0


# ---------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="zenpilot", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp):
        sp.add_argument("--stack", help="stack file (default: deploy/stacks/default.toml)")
        sp.add_argument("--set", action="append", metavar="SERVICE.KEY=VALUE",
                        help="override a service parameter, e.g. sim.camera_drop_rate=0.2 (repeatable)")
        sp.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
        sp.add_argument("--lockstep", action="store_true", help="deterministic: services run on the simulator's clock")

    fly = sub.add_parser("fly", help="fly a whole mission from start to finish, then report")
    common(fly)
    fly.add_argument("--mission", help=f"mission name or file (default: {DEFAULT_MISSION}; see `zenpilot missions`)")
    fly.add_argument("--out", help="output directory (default: runs/<mission>-<mode>-seed<N>)")
    fly.add_argument("--port", type=int, help="router port (default: a free one); in lockstep it implies --processes")
    fly.add_argument("--no-plots", action="store_true",
                     help="metrics only (sweeps, tests); `zenpilot report DIR` draws the plots later")
    fly.add_argument("--processes", action="store_true",
                     help="lockstep: a process per service over a Zenoh router, as real time runs "
                          "(default: the services as threads of one process, no router; the same flight log)")
    fly.add_argument("--foxglove", type=int, nargs="?", const=8765, metavar="PORT",
                     help="serve a live Foxglove view of the flight on ws://127.0.0.1:PORT (default 8765)")
    fly.set_defaults(func=cmd_fly)

    up = sub.add_parser("up", help="start the router and a machine's services; show live status")
    common(up)
    up.add_argument("--machine", help="start only this machine's services (connect to its router)")
    up.add_argument("--router", help="router endpoint to connect to (default: the stack's)")
    up.add_argument("--mission", help="mission for the planner")
    up.add_argument("--out", help="run directory for logs and the flight log")
    up.add_argument("-d", "--detach", action="store_true",
                    help="return once everything is up (a background `zenpilot up` supervises it); `zenpilot down` stops it")
    up.add_argument("--state-file", help=argparse.SUPPRESS)   # `up -d`'s background supervisor: where it reports
    up.set_defaults(func=cmd_up)

    st = sub.add_parser("status", help="liveliness and health of a running stack")
    st.add_argument("--stack")
    st.add_argument("--router", help="router endpoint (default: the one `up -d` started, else the stack's)")
    st.set_defaults(func=cmd_status)

    down = sub.add_parser("down", help="stop what `zenpilot up -d` started (one stack: its router)")
    down.add_argument("--router", help="the stack to stop, by its router endpoint (needed when several are up)")
    down.add_argument("--all", action="store_true", help="stop every stack `up -d` started")
    down.set_defaults(func=cmd_down)

    rep = sub.add_parser("report", help="redraw a flight's plots, print its metrics, write report.html")
    rep.add_argument("dir", help="a flight's output directory")
    rep.set_defaults(func=cmd_report)

    view = sub.add_parser("view", help="live Foxglove view of a running stack (Foxglove WebSocket protocol)")
    view.add_argument("--stack")
    view.add_argument("--router", help="router endpoint (default: the one `up -d` started, else the stack's)")
    view.add_argument("--vehicle", help="airframe drawn in the 3D scene (default: the stack's)")
    view.add_argument("--host", default="127.0.0.1", help="address to serve on (default: loopback only)")
    view.add_argument("--port", type=int, default=8765, help="WebSocket port (default 8765; 0: any free one)")
    view.set_defaults(func=cmd_view)

    log = sub.add_parser("log", help="flight logs: what a log holds, recover a cut one")
    log_sub = log.add_subparsers(dest="log_command", required=True)
    info = log_sub.add_parser("info", help="complete or cut, and the messages per key (exit 1 if cut)")
    info.add_argument("log", help="a flight's directory or an .mcap file")
    info.set_defaults(func=cmd_log_info)
    rec = log_sub.add_parser("recover", help="copy the readable chunks of a cut log into a complete, indexed one")
    rec.add_argument("log", help="a flight's directory or an .mcap file")
    rec.add_argument("-o", "--output", help="write here (default: in place; the cut file is kept as <name>.cut.mcap)")
    rec.set_defaults(func=cmd_log_recover)

    certs = sub.add_parser("certs", help="make the TLS certificates and logins of a stack's machines")
    certs.add_argument("dir", help="folder to write them to (the stack's [security] dir)")
    certs.add_argument("--stack", help="stack file whose machines get keys (default: deploy/stacks/default.toml)")
    certs.add_argument("--days", type=int, default=825, help="certificate validity (default 825 days)")
    certs.set_defaults(func=cmd_certs)

    mis = sub.add_parser("missions", help="list the shipped missions")
    mis.set_defaults(func=cmd_missions)

    cal = sub.add_parser("calibrate-camera", help="camera intrinsics from checkerboard images (OpenCV)")
    cal.add_argument("folder", help="folder of images of a checkerboard (10 or more views, tilted, all over the image)")
    cal.add_argument("--out", required=True, help="intrinsics file to write (TOML; the vision service's "
                                                  "and the simulator's camera_intrinsics)")
    cal.add_argument("--pattern", default="9x6", help="inner corners per row x per column (default 9x6)")
    cal.add_argument("--square", type=float, default=0.025, help="a square's side in metres (default 0.025)")
    cal.set_defaults(func=cmd_calibrate_camera)

    sweep.add_parser(sub)
    gyrovertical_training.add_parser(sub)
    predict_cli.add_parser(sub)
    return p


class Terminated(Exception):
    """SIGTERM: raised in the main thread so that every command's finally blocks stop the
    services it started (Python's default SIGTERM ends the process and leaves them running)."""


def _raise_terminated(signum, frame):
    raise Terminated()


def main(argv=None) -> None:
    args = build_parser().parse_args(argv)
    tie_to_parent()   # the live view a `fly` started
    signal.signal(signal.SIGTERM, _raise_terminated)  # `up` installs its own
    try:
        code = args.func(args)
    except (StackError, MissionError, ValueError) as exc:
        print(f"zenpilot: error: {exc}", file=sys.stderr)
        code = 2
    except zenoh.ZError as exc:  # e.g. no router where the stack says
        print(f"zenpilot: error: Zenoh: {str(exc).split(' at ')[0]}", file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        code = 130
    except BrokenPipeError:   # output piped into a reader that stopped early (`| head`)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        code = 0
    except Terminated:
        print("zenpilot: terminated; services stopped", file=sys.stderr)
        code = 143
    raise SystemExit(code)


if __name__ == "__main__":
    main()
