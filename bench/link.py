"""What a link between the vehicle and the ground costs: the link alone, then flights across it.

    python bench/link.py [--profiles none,lan,bad] [--missions hover,flip-short]
                         [--modes realtime,lockstep] [--placement ground] [--seed N] [--out DIR]
                         [--link-only] [--emulator auto|netem|forwarder] [--secure [tls|tls+quic]]

Two hosts as bench/two_hosts.py makes them (network namespaces "vehicle" and "ground"; an
impaired link is `tc netem` where the kernel has it, else bench/support/linkemu.py forwarding
between them in a third namespace). Profiles: none (a plain veth pair), lan (20 +- 5 ms, 1 %
loss each way), bad (50 +- 20 ms, 5 %), or DELAY_MS/JITTER_MS/LOSS_PCT.

1. The link alone, per impaired profile: 500 UDP round trips vehicle -> ground (one every 10 ms:
   the delay the link really gives, and its loss) and 5 s of one TCP stream (what TCP makes of
   it: Zenoh's links are TCP); the forwarder's CPU per frame.
2. For each mission and mode: the flight on one host (`zenpilot fly`, same stack), then across
   each profile (bench/two_hosts.py, placement `--placement`: by default the issue's, planner,
   recorder and MAVLink bridge on the ground, a router per host). One line per flight: completed,
   crashed, hold RMS, wall time per simulated second, messages lost vehicle -> ground (all keys),
   the latency of pos/state (vehicle -> ground) and planner/setpoint (ground -> vehicle), and in
   lockstep whether the flight is the one-host flight message for message. `--secure`: the
   two-host flights secured (bench/two_hosts.py --secure; the one-host flight stays open).

Each flight's own report (per key) is in <out>/<mission>-<mode>-<profile>/ground/metrics.json and
bench/two_hosts.py's printout above the summary. Namespaces and processes are removed after each
step, also on an error or Ctrl-C. Needs root; real time is skewed by other work on the machine
(the load average is printed).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import two_hosts  # noqa: E402
from bench.two_hosts import BenchError, TwoHosts, parse_profile  # noqa: E402
from flight.control.mission import MissionError  # noqa: E402


def measure_link(profile, emulator: str, out: Path, tcp_s: float = 5.0) -> dict:
    """UDP round trips and one TCP stream across the link alone; the forwarder's own account."""
    hosts = TwoHosts(f"{os.getpid()}", profile, emulator, 0, out)
    py = [sys.executable, "-m"]
    result: dict = {"profile": str(profile)}
    try:
        hosts.open()
        result["emulator"] = hosts.method
        server = subprocess.Popen(hosts.argv("ground", [*py, "bench.support.udpecho", "server", "--idle-s", "20"]),
                                  cwd=ROOT, stdout=subprocess.PIPE, text=True)
        server.stdout.readline()   # listening
        echo = two_hosts.run(hosts.argv("vehicle", [*py, "bench.support.udpecho", "client", two_hosts.GROUND_IP,
                                                    "-n", "500", "--gap-ms", "10"]), cwd=ROOT, timeout=120)
        result["udp"] = json.loads(echo.stdout.strip().splitlines()[-1])
        server.terminate()
        server.wait(10)
        sink = ("import socket,time\ns=socket.socket();s.setsockopt(socket.SOL_SOCKET,socket.SO_REUSEADDR,1)\n"
                "s.bind(('0.0.0.0',9998));s.listen(1);c,_=s.accept();n=0;t=time.monotonic()\n"
                "while (d:=c.recv(65536)):n+=len(d)\nprint(n,time.monotonic()-t)")
        source = (f"import socket,time\ns=socket.create_connection(('{two_hosts.GROUND_IP}',9998),timeout=10)\n"
                  f"t=time.monotonic();b=bytes(16384)\nwhile time.monotonic()-t<{tcp_s}:s.sendall(b)\ns.close()")
        rx = subprocess.Popen(hosts.argv("ground", [sys.executable, "-c", sink]), stdout=subprocess.PIPE, text=True)
        time.sleep(0.5)
        two_hosts.run(hosts.argv("vehicle", [sys.executable, "-c", source]), timeout=tcp_s + 60)
        n, took = rx.communicate(timeout=60)[0].split()
        result["tcp_mbit_s"] = round(8 * int(n) / 1e6 / float(took), 2)
    finally:
        hosts.close()
        result["forwarder"] = hosts.forwarder_stats
    return result


def summary_line(label: str, m: dict | None) -> str:
    if m is None:
        return f"{label:<34} (no flight)"
    th = m.get("two_hosts", {})
    keys = th.get("keys", {})
    up = [r for r in keys.values() if r["to"] == "ground" and r.get("expected")]
    lost = sum(r["lost"] for r in up)
    exp = sum(r["expected"] for r in up)

    def lat(key: str) -> str:
        r = keys.get(f"zp/0/{key}", {}).get("latency_ms") or {}
        return "-" if r.get("p50") is None else f"{r['p50']:.0f}/{r['p99']:.0f}"

    same = th.get("same_as_one_host")
    ident = "-" if same is None else ("yes" if not same["differ"] else "NO")
    wall = th.get("wall_per_sim_s")
    return (f"{label:<34} {two_hosts._fmt(m.get('completed')):>4} {two_hosts._fmt(m.get('crashed')):>5} "
            f"{two_hosts._fmt(m.get('position_rms_m')):>9} {'-' if wall is None else f'{wall:.2f}':>6} "
            f"{'-' if not exp else f'{100 * lost / exp:.1f}':>6} {lat('pos/state'):>10} {lat('planner/setpoint'):>10} "
            f"{ident:>6}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--profiles", default="none,lan,bad")
    p.add_argument("--missions", default="hover,flip-short")
    p.add_argument("--modes", default="realtime,lockstep")
    p.add_argument("--placement", choices=tuple(two_hosts.STACKS), default="ground")
    p.add_argument("--emulator", choices=("auto", "netem", "forwarder"), default="auto")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=str(ROOT / "runs" / "link"))
    p.add_argument("--link-only", action="store_true", help="only step 1: the link alone")
    p.add_argument("--no-link", action="store_true", help="skip step 1")
    p.add_argument("--secure", nargs="?", const="tls", choices=tuple(two_hosts.SECURE_LINKS), metavar="LINK",
                   help="the two-host flights secured (bench/two_hosts.py --secure): tls (default) or tls+quic")
    args = p.parse_args(argv)
    try:
        profiles = [parse_profile(x) for x in args.profiles.split(",")]
        missions = [two_hosts.resolve_mission(x) for x in args.missions.split(",")]
    except (argparse.ArgumentTypeError, MissionError) as exc:
        print(f"link: error: {exc}", file=sys.stderr)
        return 2
    modes = args.modes.split(",")
    if set(modes) - {"realtime", "lockstep"}:
        print(f"link: error: --modes {args.modes!r}: realtime and/or lockstep", file=sys.stderr)
        return 2
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    print(f"link: load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs", flush=True)
    if not args.no_link:
        for prof in profiles:
            if not prof.impaired:
                continue
            try:
                r = measure_link(prof, args.emulator, out / f"link-{prof.name.replace('/', '_')}")
            except (BenchError, subprocess.SubprocessError, ValueError) as exc:
                print(f"link: {prof}: error: {exc}", file=sys.stderr)
                return 2
            f = r.get("forwarder") or {}
            dirs = "; ".join(f"{k}: delay given p50 {d['delay_ms']['p50']} p99 {d['delay_ms']['p99']} ms, "
                             f"{d['dropped']}/{d['received']} frames dropped" for k, d in f.get("directions", {}).items())
            u = r["udp"]
            print(f"link: {prof} by {r['emulator']}: UDP round trip p1 {u['rtt_ms']['p1']} p50 {u['rtt_ms']['p50']} "
                  f"p99 {u['rtt_ms']['p99']} max {u['rtt_ms']['max']} ms, {u['lost']}/{u['sent']} lost; one TCP stream "
                  f"{r['tcp_mbit_s']} Mbit/s" + (f"; forwarder {f.get('cpu_us_per_frame')} us CPU per frame; {dirs}"
                                                 if f else ""), flush=True)
            (out / f"link-{prof.name.replace('/', '_')}" / "link.json").write_text(json.dumps(r, indent=2) + "\n")
    if args.link_only:
        return 0
    rows = []
    code = 0
    for mission in missions:
        for mode in modes:
            lock = ["--lockstep"] if mode == "lockstep" else []
            one = None
            ns = argparse.Namespace(placement=args.placement, seed=args.seed, lockstep=mode == "lockstep")
            print(f"link: {mission.name} {mode} on one host (load average {os.getloadavg()[0]:.1f})", flush=True)
            try:
                one, _ = two_hosts.fly_one_host(mission, ns, out / f"{mission.name}-{mode}-one-host")
            except subprocess.TimeoutExpired:
                print("link: the one-host flight timed out", file=sys.stderr)
            rows.append((f"{mission.name} {mode} one host", one and {**one, "two_hosts": {}}))
            for prof in profiles:
                run_out = out / f"{mission.name}-{mode}-{prof.name.replace('/', '_')}"
                print(f"link: {mission.name} {mode} across {prof} (load average {os.getloadavg()[0]:.1f})", flush=True)
                rc = two_hosts.main(["--mission", mission.path, "--seed", str(args.seed), "--link", prof.name,
                                     "--emulator", args.emulator, "--placement", args.placement, "--no-one-host",
                                     "--out", str(run_out), *lock,
                                     *(["--secure", args.secure] if args.secure else [])])
                if rc in (2, 130):
                    code = code or rc
                if rc == 130:
                    break
                try:
                    m = json.loads((run_out / "ground" / "metrics.json").read_text())
                except (OSError, ValueError):
                    m = None
                if m is not None and mode == "lockstep" and one is not None:
                    m["two_hosts"]["same_as_one_host"] = two_hosts.same_flight(
                        run_out / "ground" / two_hosts.LOG_NAME, out / f"{mission.name}-{mode}-one-host" / two_hosts.LOG_NAME)
                rows.append((f"{mission.name} {mode} {prof.name}", m))
    print()
    print(f"placement {args.placement}; latency p50/p99 ms = arrival - header time on the receiving host "
          f"(real time); lost = sequence gaps vehicle -> ground")
    print(f"{'flight':<34} {'done':>4} {'crash':>5} {'RMS m':>9} {'wall/s':>6} {'lost%':>6} {'pos/state':>10} "
          f"{'setpoint':>10} {'same':>6}")
    for label, m in rows:
        print(summary_line(label, m))
    (out / "summary.json").write_text(json.dumps({k: m for k, m in rows}, indent=1, default=str) + "\n")
    return code


if __name__ == "__main__":
    raise SystemExit(main())
