"""Two routers linked as a secured split would link them, again and again: does the link come up?

    python bench/secure_link.py [-n 30] [--mode tls+quic|tls|quic|tcp+udp|tls+quic1-6|tls+tls7|tcp+tcp7]
                                [--log FILTER] [--timeout S] [--router]
    python bench/secure_link.py --across lan [--link tls|tls+quic|open] [--no-check] [-n 20] [--timeout S]

Per attempt, on loopback: a "vehicle" router listening on the mode's endpoints (mutual TLS with the
certificates of `zenpilot certs`, made here for a two-machine stack), a "ground" router connecting
to them (as deploy/router.py configures a machine's router: no shared memory, `max_links`), a
subscriber on the ground to a reliable and a best-effort key, and the vehicle publishing both
every 10 ms until each arrives or `--timeout` (10 s) passes. Printed per attempt: the time to each first arrival
(about 1 s for every mode when linked), or NOT LINKED; then the count. `--log` passes a Zenoh log
filter (e.g. "zenoh_transport=trace") to see why an attempt failed: docs/reliability.md ("A
secured split over an unreliable link").

`--router`: the machines' routers as deploy/router.py runs them (tls+quic only): the ground's
link from a session of its own, checked by its echo and opened again until it echoes, the
ground's router opened after it; a ground client session then waits for both keys.

Modes: tls+quic = `tls/...?prio=0-6` and `quic/...?prio=0-6;rel=0` (QUIC's datagrams for the
best-effort streams: the reverted link of 0a2d2d3); tls+quic1-6 = the same with QUIC at
priorities 1-6; tcp+udp = the unsecured split's control and UDP links; tls+tls7, tcp+tcp7 = a
link at priorities 0-6 and one at 7 (control and bulk); tls, quic = one link.

`--across PROFILE` (root): across an emulated link instead of loopback, as bench/two_hosts.py
makes it (two network namespaces, PROFILE as its --link), the secured ground placement's routers
as `zenpilot up` runs them (`python -m deploy.router --stack S --machine M`, the stack files and
keys of `two_hosts.py --secure LINK`); per attempt fresh namespaces (the forwarder's seed: the
attempt's number), the vehicle's router, then the
ground's, a vehicle client publishing a reliable and a best-effort key every 10 ms and a ground
client waiting for both (its time from the ground router's start). `--no-check`: the ground's
router links straight from its own session, as before deploy/router.py checked a secured link of
several endpoints (the race measured).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
import zenoh  # noqa: E402

from deploy.launcher import free_port  # noqa: E402
from deploy.router import MAX_LINKS  # noqa: E402
from services import security  # noqa: E402
from services.stack import load_stack  # noqa: E402

MODES = {
    "tls+quic": lambda a, b: [f"tls/127.0.0.1:{a}?prio=0-6", f"quic/127.0.0.1:{b}?prio=0-6;rel=0"],
    "tls+quic1-6": lambda a, b: [f"tls/127.0.0.1:{a}?prio=0-6", f"quic/127.0.0.1:{b}?prio=1-6;rel=0"],
    "tcp+udp": lambda a, b: [f"tcp/127.0.0.1:{a}?prio=0-6", f"udp/127.0.0.1:{b}?prio=0-6;rel=0"],
    "tls+tls7": lambda a, b: [f"tls/127.0.0.1:{a}?prio=0-6", f"tls/127.0.0.1:{b}?prio=7-7"],
    "tcp+tcp7": lambda a, b: [f"tcp/127.0.0.1:{a}?prio=0-6", f"tcp/127.0.0.1:{b}?prio=7-7"],
    "tls": lambda a, b: [f"tls/127.0.0.1:{a}"],
    "quic": lambda a, b: [f"quic/127.0.0.1:{b}"],
}
STACK = """
[stack]
vehicle_id = 0
[security]
dir = "keys"
[machines.vehicle]
router = "tcp/127.0.0.1:7001"
runs_router = true
listen = ["tls/127.0.0.1:7002"]
[machines.ground]
router = "tcp/127.0.0.1:7003"
runs_router = true
connect = ["tls/127.0.0.1:7002"]
""" + "".join(f'[services.{n}]\nmachine = "{m}"\nrate_hz = {r}\n' for n, m, r in (
    ("sim", "vehicle", 400.0), ("motors", "vehicle", 400.0), ("attitude", "vehicle", 200.0),
    ("position", "vehicle", 100.0), ("planner", "ground", 50.0), ("recorder", "ground", 10.0)))


def router(sec: security.Security, machine: str, listen: list[str], connect: list[str]) -> zenoh.Session:
    conf = zenoh.Config()
    for key, value in {"mode": "router", "scouting/multicast/enabled": False, "transport/shared_memory/enabled": False,
                       "transport/unicast/max_links": MAX_LINKS, "listen/endpoints": listen,
                       "connect/endpoints": connect, "transport/link/tls": security.tls_config(sec, machine)}.items():
        conf.insert_json5(key, json.dumps(value))
    return zenoh.open(conf)


def attempt(sec: security.Security, mode: str, timeout_s: float = 10.0) -> dict:
    links = MODES[mode](free_port(), free_port())
    t0 = time.monotonic()
    vehicle = router(sec, "vehicle", links, [])
    ground = router(sec, "ground", [], links)
    got: dict[str, float | None] = {"reliable": None, "best_effort": None}

    def seen(kind: str):
        def callback(_sample) -> None:
            if got[kind] is None:
                got[kind] = time.monotonic() - t0
        return callback
    try:
        subs = [ground.declare_subscriber(f"bench/{kind}", seen(kind)) for kind in got]  # noqa: F841 (kept alive)
        pubs = {kind: vehicle.declare_publisher(f"bench/{kind}", priority=zenoh.Priority.REAL_TIME, reliability=rel)
                for kind, rel in (("reliable", zenoh.Reliability.RELIABLE), ("best_effort", zenoh.Reliability.BEST_EFFORT))}
        while None in got.values() and time.monotonic() - t0 < timeout_s:
            for pub in pubs.values():
                pub.put(b"x")
            time.sleep(0.01)
    finally:
        ground.close()
        vehicle.close()
    return got | {"reopened": 0}


def attempt_router(folder: Path, timeout_s: float = 10.0) -> dict:
    """deploy/router.py's checked link (as tests/integration/test_security.py drives it)."""
    from deploy.launcher import client_session
    from deploy.router import GATE_S, CheckedLink, echo_links, link_config, link_keys, router_config
    links = MODES["tls+quic"](free_port(), free_port())
    path = folder / "stack.toml"
    path.write_text(STACK.replace('listen = ["tls/127.0.0.1:7002"]', f"listen = {json.dumps(links)}")
                    .replace('connect = ["tls/127.0.0.1:7002"]', f"connect = {json.dumps(links)}")
                    .replace("7001", str(free_port())).replace("7003", str(free_port())))
    stack = load_stack(path)
    t0 = time.monotonic()
    sessions = [zenoh.open(router_config([], str(path), "vehicle")[0])]
    vehicle = sessions[0]
    echo_links(vehicle, 0, ["ground"])
    link = CheckedLink(lambda e: link_config(stack, "ground", e), *link_keys(0, "ground"), log=lambda _l: None).start()
    got: dict = {"reliable": None, "best_effort": None}
    try:
        link.echoed.wait(GATE_S)
        sessions.append(zenoh.open(router_config([], str(path), "ground", link.settle())[0]))
        client = client_session(stack.machines["ground"].router, stack, "ground")
        sessions.append(client)

        def seen(kind: str):
            def callback(_sample) -> None:
                if got[kind] is None:
                    got[kind] = time.monotonic() - t0
            return callback
        subs = [client.declare_subscriber(f"zp/0/bench/{kind}", seen(kind)) for kind in got]  # noqa: F841
        pubs = [vehicle.declare_publisher(f"zp/0/bench/{kind}", priority=zenoh.Priority.REAL_TIME, reliability=rel)
                for kind, rel in (("reliable", zenoh.Reliability.RELIABLE), ("best_effort", zenoh.Reliability.BEST_EFFORT))]
        while None in got.values() and time.monotonic() - t0 < GATE_S + timeout_s:
            for pub in pubs:
                pub.put(b"x")
            time.sleep(0.01)
    finally:
        link.stop()
        for session in reversed(sessions):
            session.close()
    got["reopened"] = link.opens - 1
    return got


PUBLISH = """
import sys, time, zenoh
from deploy.launcher import client_session
from services.stack import load_stack
s = client_session("tcp/127.0.0.1:7447", load_stack(sys.argv[1]))
pubs = [s.declare_publisher("zp/0/bench/reliable", priority=zenoh.Priority.REAL_TIME),
        s.declare_publisher("zp/0/bench/best_effort", priority=zenoh.Priority.REAL_TIME,
                            reliability=zenoh.Reliability.BEST_EFFORT)]
while True:
    for p in pubs:
        p.put(b"x")
    time.sleep(0.01)
"""
WAIT = """
import json, os, sys, time, zenoh
from deploy.launcher import client_session, wait_port
from services.stack import load_stack
t0, timeout = float(sys.argv[2]), float(sys.argv[3])
wait_port("tcp/127.0.0.1:7447", timeout)
s = client_session("tcp/127.0.0.1:7447", load_stack(sys.argv[1]))
got = {}
subs = [s.declare_subscriber(f"zp/0/bench/{k}", lambda _s, k=k: got.setdefault(k, time.time() - t0))
        for k in ("reliable", "best_effort")]
while len(got) < 2 and time.time() - t0 < timeout:
    time.sleep(0.01)
print(json.dumps(got), flush=True)
os._exit(0)   # not waiting for the session's close: the answer is out
"""
NO_CHECK = ("import sys, deploy.router as r; r.checks_link = lambda stack, machine: False; "
            "r.main(sys.argv[1:])")


def attempt_across(profile, stacks: dict, folder: Path, check: bool, timeout_s: float, link_seed: int) -> dict:
    """One attempt across the emulated link (module docstring, --across); `link_seed`: the
    forwarder's (which frames it drops, the delays it draws: another each attempt)."""
    import os
    import subprocess
    from bench.two_hosts import TwoHosts
    hosts = TwoHosts(str(os.getpid()), profile, link_seed=link_seed, out=folder)
    procs = []
    py = sys.executable

    def start(host: str, argv: list[str], log: str) -> subprocess.Popen:
        procs.append(subprocess.Popen(hosts.argv(host, argv), cwd=ROOT, stdout=subprocess.PIPE if log == "-" else
                                      open(folder / log, "w"), stderr=subprocess.STDOUT, text=True))
        return procs[-1]
    try:
        hosts.open()
        start("vehicle", [py, "-m", "deploy.router", "--stack", str(stacks["vehicle"]), "--machine", "vehicle-router"],
              "vehicle-router.log")
        probe = subprocess.run(hosts.argv("vehicle", [py, "-c", "import sys; from deploy.launcher import wait_port; "
                                                      "sys.exit(0 if wait_port('tcp/127.0.0.1:7447', 10) else 1)"]),
                               cwd=ROOT)
        if probe.returncode != 0:
            raise RuntimeError("the vehicle's router did not open (see vehicle-router.log)")
        start("vehicle", [py, "-c", PUBLISH, str(stacks["vehicle"])], "publish.log")
        t0 = time.time()
        ground = [py, "-m", "deploy.router"] if check else [py, "-c", NO_CHECK]
        start("ground", ground + ["--stack", str(stacks["ground"]), "--machine", "ground"], "ground-router.log")
        waiter = start("ground", [py, "-c", WAIT, str(stacks["ground"]), str(t0), str(timeout_s)], "-")
        out, _ = waiter.communicate(timeout=timeout_s + 30)
        got = json.loads(out.strip().splitlines()[-1]) if out.strip() else {}
        reopened = (folder / "ground-router.log").read_text().count("opening it again")
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        left = hosts.close()
        if left:
            raise RuntimeError(f"left behind: {left}")
    return {"reliable": got.get("reliable"), "best_effort": got.get("best_effort"), "reopened": reopened}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-n", type=int, default=30, help="attempts (default 30)")
    ap.add_argument("--mode", default="tls+quic", choices=list(MODES))
    ap.add_argument("--log", help="a Zenoh log filter, e.g. zenoh_transport=trace")
    ap.add_argument("--timeout", type=float, default=10.0, help="seconds an attempt waits (default 10)")
    ap.add_argument("--router", action="store_true", help="deploy/router.py's checked link (tls+quic)")
    ap.add_argument("--across", metavar="PROFILE",
                    help="across an emulated link (bench/two_hosts.py's --link: lan, bad, D/J/L), the machines' routers "
                         "in two network namespaces (root)")
    ap.add_argument("--link", default="tls", choices=("tls", "tls+quic", "open"),
                    help="--across: the secured link (default tls), or the open split's (two-hosts-ground.toml as it is)")
    ap.add_argument("--no-check", action="store_true", help="--across: the ground's router without the link check")
    args = ap.parse_args()
    if args.n < 1 or not args.timeout > 0:
        ap.error("-n: at least 1; --timeout: > 0")
    if args.log:
        zenoh.init_log_from_env_or(args.log)
    print("$ python bench/secure_link.py " + " ".join(sys.argv[1:]), flush=True)
    if args.across:
        return main_across(args)
    with tempfile.TemporaryDirectory(prefix="secure-link-") as tmp:
        (Path(tmp) / "stack.toml").write_text(STACK)
        security.make_keys(Path(tmp) / "keys", load_stack(Path(tmp) / "stack.toml"))
        sec = security.Security(Path(tmp) / "keys")
        linked = reopens = 0
        for i in range(args.n):
            got = attempt_router(Path(tmp), args.timeout) if args.router else attempt(sec, args.mode, args.timeout)
            reopens += got["reopened"]
            ok = got["reliable"] is not None and got["best_effort"] is not None
            linked += ok
            print(f"attempt {i}: " + (f"linked: reliable after {got['reliable']:.2f} s, best effort after "
                                      f"{got['best_effort']:.2f} s" + (f" ({got['reopened']} re-opened)" if got["reopened"] else "") if ok else
                                      f"NOT LINKED within {args.timeout:g} s (reliable {got['reliable']}, best effort {got['best_effort']})"),
                  flush=True)
    print(f"{linked} of {args.n} linked ({args.mode}" + (f", deploy/router.py's checked link: {reopens} re-opened)"
                                                           if args.router else ")"))
    return 0 if linked == args.n else 1


def main_across(args) -> int:
    from bench.two_hosts import STACKS, parse_profile, secure_stacks
    import argparse
    try:
        profile = parse_profile(args.across)
    except argparse.ArgumentTypeError as exc:
        print(f"secure_link: error: --across {exc}", file=sys.stderr)
        return 2
    linked = reopens = 0
    with tempfile.TemporaryDirectory(prefix="secure-link-across-") as tmp:
        stacks = (dict.fromkeys(("vehicle", "ground"), STACKS["ground"]) if args.link == "open"
                  else secure_stacks("ground", Path(tmp), args.link))
        for i in range(args.n):
            got = attempt_across(profile, stacks, Path(tmp), not args.no_check, args.timeout, i)
            ok = got["reliable"] is not None and got["best_effort"] is not None
            linked += ok
            reopens += got["reopened"]
            print(f"attempt {i}: " + (f"linked: reliable after {got['reliable']:.2f} s, best effort after "
                                      f"{got['best_effort']:.2f} s from the ground router's start"
                                      + (f" ({got['reopened']} re-opened)" if got["reopened"] else "") if ok else
                                      f"NOT LINKED within {args.timeout:g} s (reliable {got['reliable']}, best effort "
                                      f"{got['best_effort']})"), flush=True)
        from deploy.router import checks_link
        checked = not args.no_check and checks_link(load_stack(stacks["ground"]), "ground")
    print(f"{linked} of {args.n} linked (across {profile}, {args.link}, "
          + ("the link checked" if checked else "no link check") + f"; {reopens} re-opened)")
    return 0 if linked == args.n else 1


if __name__ == "__main__":
    sys.exit(main())
