"""What securing the stack costs per message: one hop's round trip on each path, open and secured.

    python bench/security.py [--rounds 5] [--pings 500] [--out FILE.json]

A sends a 100-byte message, B answers it from its subscriber callback, A times the round trip
(perf_counter; one message in flight). A and B are two Zenoh sessions of one process, in the
project's configuration (services.runtime.zenoh_config: loopback listeners, and with
[security] the machine's login and certificates); routers are deploy.router processes built
from a stack file (--stack --machine), keys from `zenpilot certs`. Paths:

  local           A, B peers of one vehicle router, no [security]: the services' 400 Hz path
                  (peer to peer on loopback)
  local-secure    the same with [security] (the vehicle's login; TLS and access control are on
                  the router, which these messages never cross): what the 400 Hz path pays
  split-open      B (ground) a peer linked straight to A's listener (the open split: today's
                  two-host stack, flight services listening on the link)
  split-tcp       B a peer of the ground router, the ground router linked to the vehicle router
                  over plain TCP, A a peer of the vehicle router: the routed path, no security
  split-tls       the same over TLS with client certificates and user/password, no access control
  split-secure    the secured split as shipped: split-tls plus the vehicle router's access control
                  (B puts planner/setpoint, allowed; A answers on att/state)

So split-tls - split-tcp is what TLS costs a round trip, split-secure - split-tls what the access
control costs (its check runs on the vehicle router's ingress and egress of the link), and
split-tcp - split-open what the two router hops cost. Blocks are interleaved, every round runs
every path in a rotated order; figures: p50 and p99 of all round trips, and the median of the
per-round p50 differences. Everything runs on loopback: the link's own delay is not included.
Real-time figures are only valid on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import zenoh  # noqa: E402

from deploy.launcher import ZENOH_RUNTIME, free_port, wait_port  # noqa: E402
from services import security  # noqa: E402
from services.runtime import service_parser, zenoh_config  # noqa: E402
from services.stack import load_stack  # noqa: E402

PATHS = ("local", "local-secure", "split-open", "split-tcp", "split-tls", "split-secure")
SERVICES = "\n".join(f'[services.{n}]\nmachine = "{m}"\nrate_hz = {r}\n' for n, m, r in (
    ("sim", "vehicle", 400.0), ("motors", "vehicle", 400.0), ("attitude", "vehicle", 200.0),
    ("position", "vehicle", 100.0), ("planner", "ground", 50.0), ("recorder", "ground", 10.0)))


def write_stack(folder: Path, name: str, link: str | None, secure: bool) -> Path:
    v, g = free_port(), free_port()
    text = "[stack]\nvehicle_id = 0\n"
    if secure:
        text += '[security]\ndir = "../keys"\n'
    text += f'[machines.vehicle]\nrouter = "tcp/127.0.0.1:{v}"\nruns_router = true\n'
    if link:
        text += f'listen = ["{link}"]\n'
    text += f'[machines.ground]\nrouter = "tcp/127.0.0.1:{g}"\nruns_router = true\n'
    if link:
        text += f'connect = ["{link}"]\n'
    (folder / name).mkdir()
    path = folder / name / "stack.toml"
    path.write_text(text + SERVICES)
    return path


def session(stack_path: Path | None, machine: str, connect: list[str], listen: list[str] | None = None) -> zenoh.Session:
    argv = sum((["-e", e] for e in connect), []) + sum((["-l", e] for e in listen or []), [])
    args = service_parser("bench", "").parse_args(argv)
    stack = load_stack(stack_path) if stack_path else None
    return zenoh.open(zenoh_config(args, stack, machine if stack else None))


class Procs(list):
    def start(self, argv: list[str]) -> subprocess.Popen:
        env = dict(os.environ, ZENOH_RUNTIME=ZENOH_RUNTIME)
        self.append(subprocess.Popen([sys.executable, *argv], cwd=ROOT, env=env,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT))
        return self[-1]

    def stop(self) -> None:
        for p in self:
            p.terminate()
        for p in self:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def router(procs: Procs, stack: Path, machine: str, no_acl: bool = False) -> subprocess.Popen:
    argv = ["-m", "deploy.router", "--stack", str(stack), "--machine", machine]
    if no_acl:
        argv = [str(Path(__file__)), "--router-without-acl", str(stack), machine]
    proc = procs.start(argv)
    m = load_stack(stack).machines[machine]
    for e in (m.router, *m.listen):
        if not wait_port(e, 15):
            raise SystemExit(f"security bench: router {machine} did not open {e}")
    return proc


def build(folder: Path, procs: Procs, routers: dict[str, int]) -> dict[str, tuple[zenoh.Session, zenoh.Session, str, str]]:
    """Every path's (A, B, key B sends on, key A answers on); `routers` gets each split's
    vehicle router's pid."""
    keys = ("zp/0/planner/setpoint", "zp/0/att/state")
    stacks = {"local": write_stack(folder, "local", None, False),
              "local-secure": write_stack(folder, "local-secure", None, True)}
    for name, proto, secure in (("split-tcp", "tcp", False), ("split-tls", "tls", True), ("split-secure", "tls", True)):
        stacks[name] = write_stack(folder, name, f"{proto}/127.0.0.1:{free_port()}", secure)
    # one set of keys for the secured paths (the vehicle's router accepts the ground's link)
    security.make_keys(folder / "keys", load_stack(stacks["split-secure"]))
    out = {}
    for name in ("local", "local-secure"):
        router(procs, stacks[name], "vehicle")
        r = load_stack(stacks[name]).machines["vehicle"].router
        out[name] = (session(stacks[name], "vehicle", [r]), session(stacks[name], "vehicle", [r]), *keys)
    port = free_port()
    a = session(None, "vehicle", [], [f"tcp/127.0.0.1:{port}"])
    out["split-open"] = (a, session(None, "ground", [f"tcp/127.0.0.1:{port}"]), *keys)
    for name in ("split-tcp", "split-tls", "split-secure"):
        routers[name] = router(procs, stacks[name], "vehicle", no_acl=name == "split-tls").pid
        router(procs, stacks[name], "ground")
        ms = load_stack(stacks[name]).machines
        out[name] = (session(stacks[name], "vehicle", [ms["vehicle"].router]),
                     session(stacks[name], "ground", [ms["ground"].router]), *keys)
    return out


def cpu_s(pid: int) -> float:
    f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


class Burst:
    """B sends `n` messages as fast as the link takes them (congestion control: block, so none
    is lost); the vehicle router's CPU time over the burst, per message A received."""

    def __init__(self, a: zenoh.Session, b: zenoh.Session, key: str = "zp/0/planner/plan"):
        self.received = 0
        self.lost = 0
        self.done = threading.Event()
        self.expected = 0

        def count(_sample) -> None:
            self.received += 1
            if self.received >= self.expected:
                self.done.set()
        a.declare_subscriber(key, zenoh.handlers.Callback(count, indirect=False))
        self.pub = b.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        self.body = bytes(100)

    def run(self, n: int, router_pid: int) -> float:
        self.received, self.expected = 0, n
        self.done.clear()
        c0 = cpu_s(router_pid)
        for _ in range(n):
            self.pub.put(self.body)
        last = -1
        while not self.done.wait(0.5) and self.received != last:   # all in, or nothing more coming
            last = self.received
        self.lost += n - self.received
        return (cpu_s(router_pid) - c0) / max(1, self.received)


class Pinger:
    def __init__(self, a: zenoh.Session, b: zenoh.Session, ping_key: str, pong_key: str):
        self.body = bytes(100)   # the size of a control message (att/command packs to ~90 bytes)
        self.pong = threading.Event()
        answer = a.declare_publisher(pong_key, express=True)
        a.declare_subscriber(ping_key, zenoh.handlers.Callback(lambda s: answer.put(s.payload.to_bytes()), indirect=False))
        b.declare_subscriber(pong_key, zenoh.handlers.Callback(lambda s: self.pong.set(), indirect=False))
        self.ping = b.declare_publisher(ping_key, express=True)

    def round_trip(self, timeout: float = 1.0) -> float | None:
        self.pong.clear()
        t0 = time.perf_counter()
        self.ping.put(self.body)
        if not self.pong.wait(timeout):
            return None
        return time.perf_counter() - t0


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--pings", type=int, default=500)
    p.add_argument("--warm", type=int, default=100)
    p.add_argument("--burst", type=int, default=20000, help="messages per burst (router CPU per message)")
    p.add_argument("--out", help="write the figures as JSON")
    p.add_argument("--router-without-acl", nargs=2, metavar=("STACK", "MACHINE"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.router_without_acl:   # split-tls's vehicle router: TLS and passwords, no access control
        from deploy.router import router_config
        conf, _ = router_config([], *args.router_without_acl)
        conf.insert_json5("access_control/enabled", "false")
        s = zenoh.open(conf)
        threading.Event().wait()
        s.close()
        return
    procs = Procs()
    with tempfile.TemporaryDirectory() as tmp:
        try:
            routers: dict[str, int] = {}
            paths = build(Path(tmp), procs, routers)
            time.sleep(2.0)   # gossip and the routers' links settle
            pingers = {name: Pinger(*v) for name, v in paths.items()}
            links = {}
            for name, (a, b, *_k) in paths.items():   # what A is linked to: the path really taken
                links[name] = f"A: {len(a.info.peers_zid())} peer(s), {len(a.info.routers_zid())} router(s)"
                print(f"{name:<14} {links[name]}", flush=True)
            for name, pg in pingers.items():
                lost = sum(pg.round_trip() is None for _ in range(args.warm))
                if lost == args.warm:
                    raise SystemExit(f"security bench: {name}: no answer in {args.warm} pings")
            rtts: dict[str, list[float]] = {n: [] for n in PATHS}
            medians: dict[str, list[float]] = {n: [] for n in PATHS}
            for rnd in range(args.rounds):
                order = PATHS[rnd % len(PATHS):] + PATHS[:rnd % len(PATHS)]
                for name in order:
                    block = [x for x in (pingers[name].round_trip() for _ in range(args.pings)) if x is not None]
                    rtts[name] += block
                    medians[name].append(statistics.median(block))
            bursts = {name: Burst(*paths[name][:2]) for name in routers}
            cpu: dict[str, list[float]] = {n: [] for n in routers}
            for rnd in range(args.rounds):
                for name in list(routers)[rnd % 3:] + list(routers)[:rnd % 3]:
                    cpu[name].append(bursts[name].run(args.burst, routers[name]))
        finally:
            procs.stop()
    result = {"load_average": os.getloadavg()[0], "pings": args.pings, "rounds": args.rounds, "paths": {},
              "links": links}
    print(f"round trip, 100-byte message (load average {os.getloadavg()[0]:.1f}: real-time figures are only "
          f"valid on an idle machine)")
    print(f"{'path':<14} {'p50 us':>8} {'p99 us':>8} {'n':>6}")
    for name in PATHS:
        v = sorted(rtts[name])
        p50, p99 = 1e6 * v[len(v) // 2], 1e6 * v[min(len(v) - 1, int(0.99 * len(v)))]
        result["paths"][name] = {"p50_us": round(p50, 1), "p99_us": round(p99, 1), "n": len(v)}
        print(f"{name:<14} {p50:8.1f} {p99:8.1f} {len(v):6d}")
    diffs = {}
    for label, a, b in (("security on the 400 Hz path (local-secure - local)", "local-secure", "local"),
                        ("two router hops (split-tcp - split-open)", "split-tcp", "split-open"),
                        ("TLS + passwords (split-tls - split-tcp)", "split-tls", "split-tcp"),
                        ("access control (split-secure - split-tls)", "split-secure", "split-tls")):
        d = statistics.median(1e6 * (x - y) for x, y in zip(medians[a], medians[b]))
        diffs[label] = round(d, 1)
        print(f"{label:<55} {d:+8.1f} us per round trip (median of per-round p50 differences)")
    result["differences_us"] = diffs
    print(f"vehicle router CPU per message, bursts of {args.burst} (median of {args.rounds}):")
    result["router_cpu_us_per_message"] = {}
    for name in cpu:
        v = 1e6 * statistics.median(cpu[name])
        result["router_cpu_us_per_message"][name] = round(v, 2)
        print(f"  {name:<14} {v:6.2f} us  (rounds: {', '.join(f'{1e6 * x:.2f}' for x in cpu[name])}; "
              f"{bursts[name].lost} of {args.rounds * args.burst} not received)")
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
