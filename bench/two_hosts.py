"""Fly a mission in real time over two hosts, and the same mission on one host, and compare.

    python bench/two_hosts.py [--mission hover|flip-short|FILE] [--seed N]
                              [--delay-ms D] [--loss-pct P] [--out DIR] [--no-one-host]

Two hosts are two network namespaces that this bench creates (root, `ip netns`): "vehicle"
and "ground", joined by a veth pair (vehicle 10.77.0.1/24, ground 10.77.0.2/24), loopback up
in each, nothing else: no route out, so nothing of the run can leave them. `--delay-ms` and
`--loss-pct` put `tc netem` on both ends of the link (each direction is delayed by D ms and
loses P % of its packets). The stack is tests/integration/stacks/two-hosts.toml (the default
stack's services; the vehicle's router as its own machine so that it starts first), run with
`zenpilot up -d` in each namespace, as on two computers:

    vehicle:  zenpilot up -d --machine vehicle-router --router tcp/10.77.0.1:7447
    ground:   zenpilot up -d --machine ground --router tcp/10.77.0.1:7447      (the recorder)
    vehicle:  zenpilot up -d --machine vehicle --router tcp/10.77.0.1:7447 --mission M
              --set sim.stop_after_mission=true                                 (the flight)

The simulator ends the run when the mission ends; the vehicle's `zenpilot down` then stops its
services and router, the ground's stops the recorder, which writes flight.mcap on the ground
side (<out>/ground/); the metrics (deploy.metrics, on the log up to the simulator's last
sample: the services still running while `down` stops them one by one are the stack winding
down, not the flight) go to <out>/ground/metrics.json (`zenpilot report <out>/ground` redraws
the plots, on the whole log). Both flights are measured the same way. Each host has its own run directory and
`zenpilot` state directory (the filesystem is shared, the hosts do not share it). The same
mission is then flown on one host with `zenpilot fly` (same stack, seed, real time) into
<out>/one-host/. Namespaces, the link and every process in them are removed at the end,
also on an error or Ctrl-C.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from deploy.metrics import compute_metrics  # noqa: E402
from flight.control.mission import MissionError  # noqa: E402
from schemas.flightlog import LOG_NAME, read_log  # noqa: E402
from services.stack import load_mission, load_stack  # noqa: E402

STACK = ROOT / "tests" / "integration" / "stacks" / "two-hosts.toml"
TEST_MISSIONS = ROOT / "tests" / "integration" / "missions"
VEHICLE_IP, GROUND_IP = "10.77.0.1", "10.77.0.2"
ROUTER = f"tcp/{VEHICLE_IP}:7447"
SCOUTING_GROUP = "224.0.0.224"  # Zenoh's multicast scouting group (port 7446)
SERVICES = ("sim", "motors", "attitude", "position", "vision", "planner", "mavlink")


class BenchError(Exception):
    pass


class Stop(BaseException):
    """SIGTERM, raised in the main thread so that the clean-up runs (as Ctrl-C does)."""


def _stop(signum, frame):
    raise Stop()


def run(argv: list[str], check: bool = True, **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run(argv, capture_output=True, text=True, **kw)
    if check and proc.returncode != 0:
        raise BenchError(f"`{shlex.join(argv)}` failed (status {proc.returncode}): "
                         f"{(proc.stderr or proc.stdout).strip()}")
    return proc


# ---------------------------------------------------------------- the two hosts
class TwoHosts:
    """Two network namespaces joined by a veth pair; `close` removes them and what runs in them."""

    def __init__(self, tag: str, delay_ms: float, loss_pct: float):
        self.ns = {"vehicle": f"zp{tag}-vehicle", "ground": f"zp{tag}-ground"}
        self.dev = {"vehicle": f"zp{tag}v", "ground": f"zp{tag}g"}  # interface names: 15 characters at most
        self.ip = {"vehicle": VEHICLE_IP, "ground": GROUND_IP}
        self.delay_ms, self.loss_pct = delay_ms, loss_pct
        self.created: list[str] = []

    def open(self) -> None:
        for host in ("vehicle", "ground"):
            try:
                run(["ip", "netns", "add", self.ns[host]])
            except BenchError as exc:
                raise BenchError(f"cannot create the two hosts (needs root and `ip netns`): {exc}") from None
            self.created.append(self.ns[host])
        v, g = self.ns["vehicle"], self.ns["ground"]
        run(["ip", "link", "add", self.dev["vehicle"], "netns", v, "type", "veth",
             "peer", "name", self.dev["ground"], "netns", g])
        for host in ("vehicle", "ground"):
            ns, dev = self.ns[host], self.dev[host]
            run(["ip", "-n", ns, "link", "set", "lo", "up"])
            run(["ip", "-n", ns, "addr", "add", f"{self.ip[host]}/24", "dev", dev])
            run(["ip", "-n", ns, "link", "set", dev, "up"])
            if self.delay_ms or self.loss_pct:
                netem = ["netem"] + (["delay", f"{self.delay_ms}ms"] if self.delay_ms else []) \
                    + (["loss", f"{self.loss_pct}%"] if self.loss_pct else [])
                proc = run(["tc", "-n", ns, "qdisc", "add", "dev", dev, "root", *netem], check=False)
                if proc.returncode != 0:
                    raise BenchError(f"tc netem on {dev}: {proc.stderr.strip()} (this kernel has no "
                                     f"sch_netem? run without --delay-ms/--loss-pct)")

    def argv(self, host: str, cmd: list[str]) -> list[str]:
        return ["ip", "netns", "exec", self.ns[host], *cmd]

    def pids(self, host: str) -> list[int]:
        proc = run(["ip", "netns", "pids", self.ns[host]], check=False)
        return [int(p) for p in proc.stdout.split()] if proc.returncode == 0 else []

    def link_stats(self) -> dict:
        """Bytes and packets the ground's end of the link received and sent."""
        proc = run(["ip", "-n", self.ns["ground"], "-s", "-j", "link", "show", "dev", self.dev["ground"]], check=False)
        try:
            s = json.loads(proc.stdout)[0]["stats64"]
            return {"rx_bytes": s["rx"]["bytes"], "rx_packets": s["rx"]["packets"],
                    "tx_bytes": s["tx"]["bytes"], "tx_packets": s["tx"]["packets"],
                    "rx_dropped": s["rx"]["dropped"], "tx_dropped": s["tx"]["dropped"]}
        except (ValueError, KeyError, IndexError):
            return {}

    def sockets(self) -> dict:
        """What crosses the link and whether anything listens for multicast scouting."""
        out = {}
        for host in ("vehicle", "ground"):
            ns = self.ns[host]
            tcp = run(["ip", "netns", "exec", ns, "ss", "-Htn", "state", "established"], check=False).stdout
            udp = run(["ip", "netns", "exec", ns, "ss", "-Huan"], check=False).stdout
            groups = run(["ip", "-n", ns, "maddr", "show"], check=False).stdout
            other = GROUND_IP if host == "vehicle" else VEHICLE_IP
            out[host] = {
                "tcp_across_link": sum(1 for line in tcp.splitlines() if other in line),
                "tcp_local": sum(1 for line in tcp.splitlines() if other not in line),
                "udp": [" -> ".join(line.split()[3:5]) for line in udp.splitlines()],
                "udp_7446": sum(1 for line in udp.splitlines() if line.split()[3].endswith(":7446")),
                "scouting_group_joined": SCOUTING_GROUP in groups,
            }
        return out

    def close(self) -> list[str]:
        """Stop whatever still runs in the namespaces (SIGINT, then SIGKILL), delete them (the
        veth pair goes with them). Returns what was left over (should be nothing)."""
        for sig, wait_s in ((signal.SIGINT, 10.0), (signal.SIGKILL, 5.0)):
            pids = [p for h in self.ns for p in self.pids(h)] if self.created else []
            if not pids:
                break
            for p in pids:
                try:
                    os.kill(p, sig)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + wait_s
            while time.monotonic() < deadline and any(_running(p) for p in pids):
                time.sleep(0.1)
        for ns in reversed(self.created):
            run(["ip", "netns", "del", ns], check=False)
        left = [ns for ns in self.created if ns in run(["ip", "netns", "list"], check=False).stdout.split()]
        links = run(["ip", "-o", "link", "show"], check=False).stdout
        left += [d for d in self.dev.values() if f" {d}@" in links or f" {d}:" in links]
        return left


def _running(pid: int) -> bool:
    """Alive and not a zombie (a process `zenpilot up -d` left is not our child: we cannot reap it)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except (OSError, IndexError):
        return False


# ---------------------------------------------------------------- the flights
def flight_metrics(log_path: Path, info: dict, vehicle_id: int) -> tuple[dict, int]:
    """deploy.metrics on the log up to the simulator's last IMU sample. What the services publish
    after it is the stack winding down, not the flight: the motors re-sending their last command
    (the output age grows by seconds), the EKF predicting without IMU (its error grows by metres);
    one `zenpilot down` stops them one by one. Returns the metrics and how many messages were left out."""
    log = read_log(log_path)
    imu = log.get(f"zp/{vehicle_id}/sim/imu") or []
    t_end = max((x["header"]["t_s"] for x in imu), default=float("inf"))
    trimmed = {k: [x for x in v if x["header"]["t_s"] <= t_end] for k, v in log.items()}
    left_out = sum(len(v) for v in log.values()) - sum(len(v) for v in trimmed.values())
    m = compute_metrics(trimmed, info, vehicle_id)
    m["left_out_after_sim"] = left_out
    return m, left_out


def zenpilot(hosts: TwoHosts, host: str, out: Path, *args: str, timeout: float = 120) -> tuple[str, float]:
    env = dict(os.environ, ZENPILOT_STATE_DIR=str(out / host / "state"))
    argv = hosts.argv(host, [sys.executable, "-m", "deploy.cli", *args])
    t0 = time.monotonic()
    proc = run(argv, check=False, cwd=ROOT, env=env, timeout=timeout)
    took = time.monotonic() - t0
    if proc.returncode != 0:
        raise BenchError(f"{host}: `zenpilot {shlex.join(args)}` failed (status {proc.returncode}): "
                         f"{(proc.stderr or proc.stdout).strip()}")
    return proc.stdout.strip(), took


def fly_two_hosts(hosts: TwoHosts, mission, args, out: Path) -> dict:
    timing, stack = {}, str(STACK)
    for host in ("vehicle", "ground"):
        (out / host).mkdir(parents=True, exist_ok=True)
        # a previous run's results and `up -d` state (its pids) must not be taken for this run's
        shutil.rmtree(out / host / "state", ignore_errors=True)
        for name in (LOG_NAME, "metrics.json"):
            (out / host / name).unlink(missing_ok=True)
    _, timing["up vehicle-router s"] = zenpilot(hosts, "vehicle", out, "up", "-d", "--stack", stack,
                                                "--machine", "vehicle-router", "--router", ROUTER,
                                                "--out", str(out / "vehicle"))
    _, timing["up ground s"] = zenpilot(hosts, "ground", out, "up", "-d", "--stack", stack, "--machine", "ground",
                                        "--router", ROUTER, "--out", str(out / "ground"))
    t_fly = time.monotonic()
    _, timing["up vehicle s"] = zenpilot(hosts, "vehicle", out, "up", "-d", "--stack", stack, "--machine", "vehicle",
                                         "--router", ROUTER, "--out", str(out / "vehicle"), "--seed", str(args.seed),
                                         "--mission", str(mission.path), "--set", "sim.stop_after_mission=true",
                                         timeout=300)
    pids = {}
    for host, machine in (("vehicle", "vehicle"), ("ground", "ground")):
        state, = (out / host / "state").glob(f"*/up-{machine}.json")   # one folder per stack (its router)
        pids.update(json.loads(state.read_text())["pids"])
    limit = mission.timeout_s * 1.5 + 60.0
    deadline, sampled, status = time.monotonic() + limit, None, ""
    while _running(pids["sim"]):
        dead = [n for n in pids if n != "sim" and not _running(pids[n])]
        if dead:
            raise BenchError(f"service(s) stopped during the flight: {', '.join(dead)} "
                             f"(logs in {out / 'vehicle' / 'logs'} and {out / 'ground' / 'logs'})")
        if time.monotonic() > deadline:
            raise BenchError(f"the flight did not end within {limit:.0f} s")
        if sampled is None and time.monotonic() - t_fly > 5.0:
            sampled = hosts.sockets()  # mid-flight: every service linked
            # liveliness and health of every service as the ground sees them across the link
            try:
                status, _ = zenpilot(hosts, "ground", out, "status", "--stack", stack, timeout=60)
            except (BenchError, subprocess.TimeoutExpired) as exc:
                status = f"(zenpilot status failed: {exc})"
        time.sleep(0.1)
    timing["flight wall s"] = time.monotonic() - t_fly
    if sampled is None:
        sampled = hosts.sockets()
    time.sleep(0.3)
    # as `zenpilot fly` stops them: the vehicle's services first (stopped later, the recorder would
    # log the motors re-sending their last command after the simulator ended), then the ground,
    # whose recorder writes the flight log when stopped
    _, timing["down vehicle s"] = zenpilot(hosts, "vehicle", out, "down", timeout=120)
    _, timing["down ground s"] = zenpilot(hosts, "ground", out, "down", timeout=120)
    link = hosts.link_stats()
    log_path = out / "ground" / LOG_NAME
    if not log_path.exists():
        raise BenchError(f"no flight log on the ground side ({log_path}); see {out / 'ground' / 'logs' / 'recorder.log'}")
    t0 = time.monotonic()
    metrics, _ = flight_metrics(log_path, {"mission": mission.name, "mode": "realtime", "seed": args.seed,
                                           "vehicle": mission.vehicle}, load_stack(STACK).vehicle_id)
    timing["metrics s"] = time.monotonic() - t0
    metrics["two_hosts"] = {"link": link, "sockets": sampled, "timing": timing, "status": status,
                            "netem": {"delay_ms": args.delay_ms, "loss_pct": args.loss_pct},
                            "log_on_vehicle_side": (out / "vehicle" / LOG_NAME).exists(),
                            "log_bytes": log_path.stat().st_size}
    (out / "ground" / "metrics.json").write_text(json.dumps(metrics, indent=2, sort_keys=True) + "\n")
    return metrics


def fly_one_host(mission, args, out: Path) -> tuple[dict | None, float]:
    out.mkdir(parents=True, exist_ok=True)
    for name in (LOG_NAME, "metrics.json"):
        (out / name).unlink(missing_ok=True)
    argv = [sys.executable, "-m", "deploy.cli", "fly", "--stack", str(STACK), "--mission", str(mission.path),
            "--seed", str(args.seed), "--out", str(out)]
    t0 = time.monotonic()
    with open(out / "fly.out", "w") as f:
        proc = subprocess.Popen(argv, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT)
        try:
            proc.wait(timeout=mission.timeout_s * 1.5 + 180)
        except BaseException:  # Ctrl-C reaches it too; SIGTERM or a timeout: tell it, it stops its services
            proc.send_signal(signal.SIGTERM)
            proc.wait(60)
            raise
    took = time.monotonic() - t0
    if not (out / LOG_NAME).exists():
        print(f"two_hosts: the one-host flight wrote no log (status {proc.returncode}, see {out / 'fly.out'})",
              file=sys.stderr)
        return None, took
    # as the two-host flight's: up to the simulator's end (metrics.json is `zenpilot fly`'s own, whole log)
    info = {"mission": mission.name, "mode": "realtime", "seed": args.seed, "vehicle": mission.vehicle}
    return flight_metrics(out / LOG_NAME, info, load_stack(STACK).vehicle_id)[0], took


# ---------------------------------------------------------------- report
def _fmt(v, unit: str = "") -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.4g}{unit}"
    return f"{v}{unit}"


def planner_build_s(logs: Path) -> float | None:
    """The planner's JAX compile and warm-up before it flies (kept in a cache: the next run is quicker)."""
    try:
        text = (logs / "planner.log").read_text(errors="replace")
    except OSError:
        return None
    built = re.findall(r"built \(JAX compile and warm-up\) in ([0-9.]+) s", text)
    return sum(float(x) for x in built) if built else None


def table(two: dict, one: dict | None) -> str:
    def g(m, *path):
        for p in path:
            if not isinstance(m, dict):
                return None
            m = m.get(p)
        return m

    rows = [("completed", ("completed",)), ("crashed", ("crashed",)), ("mission state", ("mission_state",)),
            ("flown s", ("duration_s",)), ("hover position RMS m", ("position_rms_m",)),
            ("max position error m", ("max_position_error_m",)), ("max tilt deg (outside flips)", ("max_tilt_deg",)),
            ("estimate position RMS m", ("estimation", "position_rms_m")),
            ("estimate attitude RMS deg", ("estimation", "attitude_rms_deg")),
            ("imu->pwm p50 ms", ("latency_ms", "imu_to_pwm_p50")), ("imu->pwm p99 ms", ("latency_ms", "imu_to_pwm_p99")),
            ("imu->pwm max ms", ("latency_ms", "imu_to_pwm_max")),
            ("output age p99 ms", ("latency_ms", "output_age_p99")),
            ("rejected messages", ("rejected_total",)), ("planner JAX build s", ("planner_build_s",)),
            ("msgs after the sim's end (left out)", ("left_out_after_sim",))]
    rows += [(f"rate {s} Hz", ("rates_hz", s)) for s in SERVICES]
    if two.get("flip") or (one or {}).get("flip"):
        rows += [(f"flip {k}", ("flip", k)) for k in
                 ("completed", "aborted", "altitude_loss_m", "xy_drift_m", "recovery_s", "overshoot_deg",
                  "duration_s", "min_altitude_m", "hit_ground", "solves", "failed_solves", "solve_ms_p99")]
    lines = [f"{'':<36} {'two hosts':>12} {'one host':>12}"]
    for label, path in rows:
        lines.append(f"{label:<36} {_fmt(g(two, *path)):>12} {_fmt(g(one, *path)) if one else 'not flown':>12}")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mission", default="hover",
                   help="mission name (deploy/missions, then tests/integration/missions) or file (default hover)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--delay-ms", type=float, default=0.0, help="tc netem delay on each direction of the link")
    p.add_argument("--loss-pct", type=float, default=0.0, help="tc netem loss on each direction of the link")
    p.add_argument("--out", help="output directory (default runs/two-hosts-<mission>-seed<N>)")
    p.add_argument("--no-one-host", action="store_true", help="skip the one-host comparison flight")
    args = p.parse_args(argv)
    print("two_hosts: " + shlex.join([sys.executable, *sys.argv]), flush=True)

    name = args.mission
    if not name.endswith(".toml") and not (ROOT / "deploy" / "missions" / f"{name}.toml").exists() \
            and (TEST_MISSIONS / f"{name}.toml").exists():
        name = str(TEST_MISSIONS / f"{name}.toml")
    try:
        mission = load_mission(name)
    except MissionError as exc:
        print(f"two_hosts: error: {exc}", file=sys.stderr)
        return 2
    mission = dataclasses.replace(mission, path=str(Path(mission.path).resolve()))
    out = Path(args.out or ROOT / "runs" / f"two-hosts-{mission.name}-seed{args.seed}").resolve()
    out.mkdir(parents=True, exist_ok=True)
    default, split = load_stack(), load_stack(STACK)
    drift = [n for n in set(default.services) | set(split.services)
             if n not in default.services or n not in split.services
             or dataclasses.replace(default.services[n], machine="") != dataclasses.replace(split.services[n], machine="")]
    if drift:
        print(f"two_hosts: warning: {STACK.name} no longer matches the default stack for: {', '.join(sorted(drift))}",
              file=sys.stderr)

    hosts = TwoHosts(str(os.getpid()), args.delay_ms, args.loss_pct)
    signal.signal(signal.SIGTERM, _stop)
    two = one = None
    code = 0
    try:
        hosts.open()
        netem = (f"netem delay {args.delay_ms:g} ms, loss {args.loss_pct:g} % each way"
                 if args.delay_ms or args.loss_pct else "no netem")
        print(f"two_hosts: {mission.name} ({mission.vehicle}, real time, seed {args.seed}); vehicle netns "
              f"{hosts.ns['vehicle']} {VEHICLE_IP} <-veth-> ground netns {hosts.ns['ground']} {GROUND_IP}; {netem}; "
              f"router {ROUTER} -> {out}; load average {os.getloadavg()[0]:.1f} "
              f"(other work on these {os.cpu_count()} CPUs skews a real-time flight)", flush=True)
        two = fly_two_hosts(hosts, mission, args, out)
    except (BenchError, subprocess.TimeoutExpired) as exc:
        print(f"two_hosts: error: {exc}", file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, Stop):
        print("two_hosts: interrupted; removing the namespaces", file=sys.stderr)
        code = 130
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # the clean-up is not to be interrupted
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        if hosts.created:
            for host in ("vehicle", "ground"):  # a graceful stop first: the recorder writes what it has
                if (out / host / "state").is_dir() and any((out / host / "state").glob("*/up-*.json")):
                    try:
                        zenpilot(hosts, host, out, "down", timeout=120)
                    except (BenchError, subprocess.TimeoutExpired) as exc:
                        print(f"two_hosts: clean-up: {exc}", file=sys.stderr)
        left = hosts.close()
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, _stop)
        if left:
            print(f"two_hosts: error: left behind: {', '.join(left)}", file=sys.stderr)
            code = 2
        elif hosts.created:
            print(f"two_hosts: removed {', '.join(hosts.created)} (and the veth pair); no process left in them",
                  flush=True)
    if two is None:
        return code or 2

    one_took = None
    if not args.no_one_host:
        print(f"two_hosts: the same flight on one host: zenpilot fly ... (load average {os.getloadavg()[0]:.1f})",
              flush=True)
        try:
            one, one_took = fly_one_host(mission, args, out / "one-host")
        except (KeyboardInterrupt, Stop, subprocess.TimeoutExpired):
            print("two_hosts: one-host flight interrupted", file=sys.stderr)
    two["planner_build_s"] = planner_build_s(out / "vehicle" / "logs")
    if one is not None:
        one["planner_build_s"] = planner_build_s(out / "one-host" / "logs")
    th = two["two_hosts"]
    print()
    print(table(two, one))
    print()
    t = th["timing"]
    if th["status"]:
        print("`zenpilot status` on the ground, mid-flight (the recorder does not log its own health):")
        print("  " + th["status"].replace("\n", "\n  "))
    print("two hosts, wall s: " + ", ".join(f"{k[:-2]} {v:.1f}" for k, v in t.items())
          + (f"; one host: `zenpilot fly` {one_took:.1f}" if one_took else ""))
    link, flight_s = th["link"], t["flight wall s"]
    if link:
        print(f"link (ground end): received {link['rx_bytes'] / 1e6:.1f} MB in {link['rx_packets']} packets, "
              f"sent {link['tx_bytes'] / 1e6:.1f} MB in {link['tx_packets']} packets "
              f"(~{8 * link['rx_bytes'] / 1e6 / max(flight_s, 1e-9):.1f} Mbit/s to the ground over the flight)")
    for host, s in th["sockets"].items():
        print(f"{host}: {s['tcp_across_link']} TCP connections across the link, {s['tcp_local']} on its loopback; "
              f"UDP sockets {s['udp'] or 'none'}; on port 7446: {s['udp_7446']}; "
              f"scouting group {SCOUTING_GROUP} joined: {'yes' if s['scouting_group_joined'] else 'no'}")
    print(f"flight log: {out / 'ground' / LOG_NAME} ({th['log_bytes'] / 1e6:.1f} MB, on the ground side; "
          f"on the vehicle side: {'yes' if th['log_on_vehicle_side'] else 'none'}); metrics: "
          f"{out / 'ground' / 'metrics.json'} (plots: zenpilot report {out / 'ground'})")
    return code or (0 if two.get("completed") and not two.get("crashed") else 1)


if __name__ == "__main__":
    raise SystemExit(main())
