"""Each service killed or frozen mid-hover in real time, as `zenpilot fly` supervises it (issue 22).

Per (service, fault), a real-time hover on the estimates (the default stack); 5 s after the
simulator's first tick the fault: `kill` (SIGKILL), `stop2` (SIGSTOP, SIGCONT 2 s later) or
`freeze` (SIGSTOP, never continued); with `--standby`, `kill2` (the active driver killed, and 3 s
later the driver that took over: the restarted one, now the standby, must take over in turn);
`stutter15` / `stutter40` (stopped 15 / 40 ms every 200 ms, ten times: under and over the
standby's 25 ms bound); `supstop600`: not a service but the supervisor (`zenpilot fly`'s process)
stopped 0.6 s, every service healthy (the service named is only the row's label); `freezeall1000`:
every service of the flight (the simulator too) frozen at once for 1 s by the cgroup freezer, then
thawed: their loops blocked, not stopped (/proc state D, not T), no beat from anyone, which a
supervisor could take for its own deafness, as on a vehicle whose every loop hangs;
`freezeloops1000`: the same but the simulator (the world goes on, and its beats with it). The
service named is only the row's label; both need a writable /sys/fs/cgroup/freezer (cgroup v1,
as root).
Printed per flight: when the supervisor saw it (after the fault), what it did (its events), the
failsafes the services counted, and the flight's outcome
on the simulator's truth (completed, crashed, touchdown speed).

`--standby`: the default stack with the motor driver's hot standby (`[services.motors] standby =
true`, services/standby.py); the fault goes to the active driver, and per flight the output gap
(the longest pause between motors/pwm sample times in the flight log after the fault), which
drivers sent it, and each driver's CPU (% of one core, from /proc, over the seconds before the
fault). `--load N`: N busy-loop processes (normal priority) beside each flight, from before its
start to its end: the heavy load under which the warm spare started too late.
Also printed: what the supervisor judged of the services not faulted (stuck, silent, hung: a
starved supervisor's mistakes), its scheduling and its own stalls (deploy/supervisor.py).
`--supervisor-priority P`: the supervisor's priority (0: normal, as before the watch thread).

    python bench/supervised_faults.py [--services attitude position ...] [--faults kill stop2 freeze]
    python bench/supervised_faults.py --services motors --standby --load 3
"""
from __future__ import annotations

import argparse
import json
import math
import re
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from flight.quat import quat_tilt  # noqa: E402
from schemas.flightlog import LogError, read_log  # noqa: E402
SERVICES = ("attitude", "position", "motors", "planner", "vision")
FAULTS = ("kill", "stop2", "freeze")
KILL2 = "kill2"   # --standby: the active driver killed, then 3 s later the one that took over (a second failure)
# a stuttering process: stopped for MS milliseconds every 200 ms, ten times (a loop starved in bursts):
# under the standby's 25 ms bound nothing must change hands; over it, one hand-over and no flapping
STUTTERS = {"stutter15": 0.015, "stutter40": 0.040}
# the supervisor itself starved: its `zenpilot fly` process stopped this long (no poll, no beat
# received), every service healthy: nothing must be judged stuck, nothing killed
SUPSTOP = {"supstop600": 0.6}
# every loop of the machine blocked at once (a hung disk, a frozen cgroup) this long, then thawed;
# the simulator with them or not
FREEZE_ALL = {"freezeall1000": (1.0, True), "freezeloops1000": (1.0, False)}
FREEZER = Path("/sys/fs/cgroup/freezer")


def cmdline(pid: int) -> list[bytes]:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return fh.read().split(b"\0")
    except OSError:
        return []


def service_pid(out: Path, service: str, instance: str | None = None) -> int:
    """The flight's service process: the one started with the recorder's router endpoint (with a
    hot standby, `instance` names which driver: None, the one without --instance)."""
    procs = [int(p) for p in os.listdir("/proc") if p.isdigit()]
    recorder = next(p for p in procs if b"services.recorder" in cmdline(p) and str(out).encode() in b" ".join(cmdline(p)))
    argv = cmdline(recorder)
    endpoint = argv[argv.index(b"-e") + 1]
    found = [p for p in procs if endpoint in cmdline(p) and f"services.{service}".encode() in cmdline(p)
             and (instance.encode() in cmdline(p) if instance else b"--instance" not in cmdline(p))]
    if len(found) != 1:
        raise SystemExit(f"bench: expected one {service} process of {out}, found {found}")
    return found[0]


def flight_services(out: Path, sim: bool) -> list[int]:
    """Every service process of the flight (those started with the recorder's router endpoint),
    the simulator's with them or not."""
    recorder = service_pid(out, "recorder")
    endpoint = cmdline(recorder)[cmdline(recorder).index(b"-e") + 1]
    return [int(p) for p in os.listdir("/proc") if p.isdigit() and endpoint in cmdline(int(p))
            and b"services." in b" ".join(cmdline(int(p))) and (sim or b"services.sim" not in cmdline(int(p)))]


def freeze_all(pids: list[int], seconds: float) -> float:
    """Freeze `pids` together in a cgroup of their own for `seconds`, thaw, put them back; the time
    they were frozen."""
    group = FREEZER / f"zenpilot-bench-{os.getpid()}"
    group.mkdir()
    try:
        for pid in pids:
            (group / "cgroup.procs").write_text(str(pid))
        (group / "freezer.state").write_text("FROZEN")
        t0 = time.monotonic()
        time.sleep(seconds)
        (group / "freezer.state").write_text("THAWED")
        return time.monotonic() - t0
    finally:
        (group / "freezer.state").write_text("THAWED")
        for pid in (group / "cgroup.procs").read_text().split():
            try:
                (FREEZER / "cgroup.procs").write_text(pid)
            except OSError:   # gone meanwhile (killed by the supervisor)
                pass
        group.rmdir()


def cpu_s(pid: int) -> float:
    """CPU seconds (user + system) a process has used so far."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


def standby_stack(out: Path, hang_s: float | None = None) -> Path:
    """The default stack with the motor driver's hot standby on (and its hang bound hang_s),
    written beside the flight."""
    text = (ROOT / "deploy" / "stacks" / "default.toml").read_text()
    head = "[services.motors]\n"
    assert head in text, "deploy/stacks/default.toml: no [services.motors] table"
    if hang_s is not None:
        text = re.sub(r"(\[services\.motors\][^\[]*?)hang_restart_s = [0-9.]+", rf"\g<1>hang_restart_s = {hang_s}", text)
    path = out.parent / f"{out.name}-stack.toml"
    path.write_text(text.replace(head, head + "standby = true\n", 1))
    return path


def fly_with(out: Path, service: str, fault: str, at_s: float, seed: int, standby: bool = False,
             hang_s: float | None = None) -> dict:
    argv = [sys.executable, "-m", "deploy.cli", "fly", "--mission", "hover", "--seed", str(seed),
            "--out", str(out), "--no-plots"]
    if standby:
        out.parent.mkdir(parents=True, exist_ok=True)
        argv += ["--stack", str(standby_stack(out, hang_s))]
    proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    cpu = {}
    try:
        deadline = time.monotonic() + 120
        sim_log = out / "logs" / "sim.log"
        while not (sim_log.exists() and "first tick" in sim_log.read_text(errors="replace")):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"bench: the flight did not start:\n{proc.stdout.read()}")
            time.sleep(0.05)
        drivers = {}
        if service == "motors":   # each driver's CPU over the seconds before the fault
            drivers = {"motors": service_pid(out, "motors")}
            if standby:
                drivers["motors.b"] = service_pid(out, "motors", "motors.b")
            time.sleep(1.0)
            c0, w0 = {n: cpu_s(p) for n, p in drivers.items()}, time.monotonic()
            time.sleep(max(0.0, at_s - 1.0))
            cpu = {n: 100.0 * (cpu_s(p) - c0[n]) / (time.monotonic() - w0) for n, p in drivers.items()}
        else:
            time.sleep(at_s)
        pid = service_pid(out, service)
        injected = time.time()
        if fault in FREEZE_ALL:
            seconds, with_sim = FREEZE_ALL[fault]
            pids = flight_services(out, with_sim)
            frozen = freeze_all(pids, seconds)
            print(f"bench: {fault}: {len(pids)} services frozen {1e3 * frozen:.0f} ms", flush=True)
        elif fault in SUPSTOP:   # the launcher, not the service: timed as the stutters are
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(95))
            except OSError:
                pass
            os.kill(proc.pid, signal.SIGSTOP)
            t0 = time.monotonic()
            time.sleep(SUPSTOP[fault])
            os.kill(proc.pid, signal.SIGCONT)
            stopped = time.monotonic() - t0
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            print(f"bench: {fault}: the supervisor stopped {1e3 * stopped:.0f} ms", flush=True)
        elif fault in STUTTERS:   # timed at real-time priority where allowed: a starved bench would stop it longer
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(95))
            except OSError:
                pass
            stopped = []
            for _ in range(10):
                os.kill(pid, signal.SIGSTOP)
                t0 = time.monotonic()
                time.sleep(STUTTERS[fault])
                os.kill(pid, signal.SIGCONT)
                stopped.append(time.monotonic() - t0)
                time.sleep(0.2 - STUTTERS[fault])
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            print(f"bench: {fault}: stopped {1e3 * min(stopped):.1f}..{1e3 * max(stopped):.1f} ms", flush=True)
        else:
            os.kill(pid, signal.SIGKILL if fault in ("kill", KILL2) else signal.SIGSTOP)
        if fault == KILL2:   # the restarted driver is the standby now: the new active fails too
            time.sleep(3.0)
            os.kill(service_pid(out, service, "motors.b"), signal.SIGKILL)
        if fault == "stop2":
            time.sleep(2.0)
            try:
                os.kill(pid, signal.SIGCONT)
            except ProcessLookupError:   # the supervisor killed it first
                pass
        said, _ = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    record = json.loads((out / "supervisor.json").read_text())
    events = [e for e in record["events"] if e["service"] in (service, service + ".b")   # a standby's too
              or fault in FREEZE_ALL]
    # the fault's own detection (not an earlier event, e.g. a start-up's under load)
    seen = [e for e in events if e["service"] == service and record["started_unix"] + e["t_s"] >= injected - 0.05]
    metrics = json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").exists() else {}
    # what it judged of the others (a healthy loop taken for hung: a starved supervisor), and its own stalls
    faulted = (() if fault in SUPSTOP   # supstop: every service is healthy; freezeall: every one faulted
               else tuple(record["services"]) if fault in FREEZE_ALL else (service, service + ".b"))
    others = [e for e in record["events"] if e["service"] not in (*faulted, "supervisor")
              and e["event"] in ("stuck", "silent", "hung")]
    return {"rc": proc.returncode, "events": events, "after": after_fault(out, injected), "cpu": cpu, "others": others,
            "own": record.get("own"), "scheduling": record.get("scheduling", "normal (before the watch thread)"),
            "seen_ms": (record["started_unix"] + seen[0]["t_s"] - injected) * 1e3 if seen else None,
            "metrics": metrics, "said": said}


def after_fault(out: Path, injected: float, window_s: float = 5.0) -> dict:
    """On the simulator's truth, the window_s after the fault: lowest and highest height, most tilt."""
    try:
        log = read_log(out / "flight.mcap")
        truth = log["zp/0/sim/truth"]
    except (OSError, KeyError, LogError) as exc:   # a log the flight left unreadable is a result too
        return {"error": str(exc)}
    seen = [m for m in truth if injected <= m["header"]["t_s"] <= injected + window_s]
    if not seen:
        return {}
    z = [m["position_m"][2] for m in seen]
    got = {"z_min": min(z), "z_max": max(z), "tilt_max_deg": max(math.degrees(quat_tilt(m["quaternion_wxyz"])) for m in seen)}
    # the motors' output: the longest pause between sample times from just before the fault on
    # (the simulator holds the last PWM meanwhile), and which drivers sent it
    pwm = sorted((m["header"]["t_s"], m["header"]["source"]) for m in log.get("zp/0/motors/pwm", [])
                 if injected - 0.1 <= m["header"]["t_s"] <= injected + window_s)
    gaps = [b[0] - a[0] for a, b in zip(pwm, pwm[1:])]
    got["gap_ms"] = 1e3 * max(gaps) if gaps else None
    got["sources"] = sorted({src for _, src in pwm})
    # hand-overs: 1 for a clean takeover; more where a resumed driver sent again
    got["switches"] = sum(1 for a, b in zip(pwm, pwm[1:]) if a[1] != b[1])
    return got


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--services", nargs="+", default=list(SERVICES), choices=SERVICES)
    ap.add_argument("--faults", nargs="+", default=list(FAULTS),
                    choices=(*FAULTS, KILL2, *STUTTERS, *SUPSTOP, *FREEZE_ALL))
    ap.add_argument("--at", type=float, default=5.0, help="wall seconds after the first tick")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="runs/bench-supervised-faults")
    ap.add_argument("--standby", action="store_true", help="the motor driver's hot standby on")
    ap.add_argument("--load", type=int, default=0, metavar="N", help="N busy-loop processes beside each flight")
    ap.add_argument("--supervisor-priority", type=int, metavar="P",
                    help="the supervisor's SCHED_FIFO priority (0: normal scheduling); default: the stack's")
    ap.add_argument("--hang-restart-s", type=float, metavar="S",
                    help="with --standby: the motor driver's hang bound (e.g. 10: a stop2's driver is "
                         "continued, not killed, and must step back)")
    args = ap.parse_args()
    if args.load < 0:
        ap.error("--load: expected N >= 0")
    if set(FREEZE_ALL) & set(args.faults) and not os.access(FREEZER, os.W_OK):
        ap.error(f"--faults {' '.join(FREEZE_ALL)}: needs a writable {FREEZER} (cgroup v1's freezer, as root)")
    if KILL2 in args.faults and not (args.standby and args.services == ["motors"]):
        ap.error(f"--faults {KILL2}: with --standby --services motors")
    if args.hang_restart_s is not None and not (args.standby and 0.1 <= args.hang_restart_s <= 60.0):
        ap.error("--hang-restart-s: with --standby, 0.1..60 s")
    if args.supervisor_priority is not None:   # the flights' `zenpilot fly` read it (deploy/supervisor.py)
        if not 0 <= args.supervisor_priority <= 99:
            ap.error("--supervisor-priority: 0..99")
        os.environ["ZENPILOT_SUPERVISOR_PRIORITY"] = str(args.supervisor_priority)
    print("$ python bench/supervised_faults.py " + " ".join(sys.argv[1:]), flush=True)
    rows, misjudged = [], 0
    for service in args.services:
        for fault in args.faults:
            out = Path(args.out) / f"{service}-{fault}{'-standby' if args.standby else ''}"
            hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.load)]
            try:
                load = os.getloadavg()[0]
                r = fly_with(out.resolve(), service, fault, args.at, args.seed, args.standby, args.hang_restart_s)
                load = max(load, os.getloadavg()[0])
            finally:
                for h in hogs:
                    h.kill()
                    h.wait()
            m = r["metrics"]
            misjudged += bool(r["others"])
            did = "; ".join(f"+{e['t_s']:.2f} {'' if e['service'] == service else e['service'] + ' '}{e['event']}"
                            for e in r["events"]) or "nothing"
            fs = ", ".join(f"{k}" for svc in (m.get("failsafes") or {}).values() for k in svc) or "-"
            seen = f"{r['seen_ms']:.0f}" if r["seen_ms"] is not None else "-"
            rows.append((service, fault, seen, did, fs, m.get("completed"), m.get("crashed"),
                         m.get("touchdown_speed_m_s"), load))
            a = r["after"]
            fig = (f"z {a['z_min']:.2f}..{a['z_max']:.2f} m, tilt <= {a['tilt_max_deg']:.0f} deg" if "z_min" in a
                   else a.get("error", "no truth"))
            if a.get("gap_ms") is not None:
                fig += f", pwm gap {a['gap_ms']:.0f} ms from {'+'.join(a['sources'])} ({a['switches']} hand-overs)"
            if r["cpu"]:
                fig += ", cpu " + " ".join(f"{n} {c:.1f}%" for n, c in r["cpu"].items())
            others = "; ".join(f"+{e['t_s']:.2f} {e['service']} {e['event']}" for e in r["others"]) or "none"
            own = r["own"]
            own = (f"late {own['late']} (max {1e3 * own['late_max_s']:.0f} ms), deaf {own['deaf']} "
                   f"(max {1e3 * own['deaf_max_s']:.0f} ms)" if own else "not measured")
            fig += f" | others judged: {others} | supervisor {r['scheduling']}, own stalls: {own}"
            print(f"{service:9} {fault:6} seen after {seen:>5} ms | {did} | failsafes: {fs} | 5 s after: {fig} | "
                  f"completed {m.get('completed')} crashed {m.get('crashed')} {m.get('crash_reason') or ''} "
                  f"| load {load:.1f} | {out}", flush=True)
    bad = [r for r in rows if r[6] is not False]
    print(f"\n{len(rows) - len(bad)} of {len(rows)} flights not crashed; {misjudged} with a service not faulted "
          f"judged stuck, silent or hung")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
