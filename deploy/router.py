"""zenpilot-router: a Zenoh router from the Python package (no zenohd binary needed).

    zenpilot-router --listen tcp/127.0.0.1:7447                  # a bare router (tests, benches)
    zenpilot-router --stack FILE --machine NAME                   # a machine's router, as the stack says

With --machine it listens exactly where the stack file says (the machine's `router`
endpoint and its `listen` endpoints), links to its `connect` routers and, with a [security]
table, requires TLS client certificates and the machine's users, and enforces the access
control of services/security.py.

A router that connects to another host by QUIC (`quic/...;rel=0` beside `tls/...`), or by several
endpoints (`tls/...?prio=0-6` and `tls/...?prio=7-7`; the open split's TCP + UDP + TCP), checks that
the link carries data both ways: Zenoh 1.10.2 may send the accepting router's first routing
declarations on either link, and when one is lost (QUIC's datagrams) or taken out of order (two
links) the routers stay linked and never learn each other's subscriptions (docs/reliability.md,
"A secured split over an unreliable link"). The link to the other host is then a session of its
own in this process (CheckedLink), which pings a key the other router echoes (echo_links) and
opens itself again when no echo came back within CHECK_S; the machine's router, where its
services connect, opens once the link echoed (or after GATE_S) and links to that session on
loopback. From then on the link is only watched, never re-opened, so no service is cut by it,
with one exception: a link lost for RELINK_S (no echo, and no health from any other machine's
service through the machine's router) is opened again with the machine's router, as at the start
(`relink`): after an outage longer than Zenoh's lease the routers' link may form again and route
nothing, ever (docs/reliability.md, "The link lost mid-flight"); the connecting machine's own
services are cut from their router for the few seconds it takes, when they have nothing of the
other host anyway.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import socket
import threading
import time

import zenoh

from services import security
from services.runtime import bound_drop_wait, bulk_downsampling, on_stop_signals, tie_to_parent
from services.stack import StackError, load_stack

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
MAX_LINKS = 8   # links per router pair: at most one per Zenoh priority
CLOSE_S = 3.0
CHECK_S = 2.0   # no echo for this long: the link to the other host is opened again (linked: ~1 s)
PING_S = 0.25
# the longest the machine's router waits for its link's first echo: three whole checks (2 + 4 + 8 s,
# each open ~0.3 s), so a link slow to carry gets its third try (deploy/launcher.py waits 5 s more)
GATE_S = 15.0
# no echo and nothing from the other machines' services for this long: the link and the machine's
# router open again. Past Zenoh's 10 s lease and the ~2 s its links took to come back by themselves
# after a 15 s outage (docs/reliability.md, "The link lost mid-flight")
RELINK_S = 20.0


def router_log(line: str) -> None:
    """A line of the router's log; the wall clock on each: a link lost mid-flight is matched with
    the outage's times."""
    print(f"zenpilot-router: {line} (at {time.time():.3f})", file=sys.stderr, flush=True)


def link_keys(vehicle_id: int, machine: str) -> tuple[str, str]:
    """The keys a connecting machine's link pings and its accepting router echoes (a verbatim
    chunk, @link: no service's wildcard subscription receives them)."""
    return f"zp/{vehicle_id}/@link/{machine}/ping", f"zp/{vehicle_id}/@link/{machine}/echo"


def _is_quic(endpoints) -> bool:
    return any(e.split("/", 1)[0] == "quic" for e in endpoints)


def _checked(stack, endpoints) -> bool:
    """Whether a link over these endpoints is checked: QUIC's, and any link of several endpoints
    (Zenoh 1.10.2 may send the first declarations on any of them, and two on two links arrive out
    of order: TLS prio 0-6 + TLS prio 7-7 linked nothing in 1 of 2 flights across lan, 3 of 110
    attempts across lan under load, 1 of 70 on loopback; the open split's TCP + UDP + TCP in 1 of
    2 flights and 3 of 40 attempts across bad; checked, none: docs/reliability.md)."""
    return _is_quic(endpoints) or len(endpoints) > 1


def checks_link(stack, machine: str) -> bool:
    """Whether `machine`'s router links to other hosts through a checked link session."""
    return _checked(stack, stack.machines[machine].connect)


def echoes_links(stack, machine: str) -> bool:
    """Whether `machine`'s router answers the checked links of the routers that connect to it."""
    return _checked(stack, stack.machines[machine].listen)


def _base_config(conf: zenoh.Config) -> None:
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    # No shared memory, as for the services (services.runtime.zenoh_config): two routers on one
    # machine (network namespaces standing for two hosts) would otherwise pass large payloads
    # through /dev/shm, not their link, as two real hosts never can
    conf.insert_json5("transport/shared_memory/enabled", "false")
    conf.insert_json5("transport/link/tx/queue/size/real_time", "16")
    # a bulk message that does not fit a saturated link's queue is dropped at once: the thread
    # that would wait for room routes every other link's messages too ...
    bound_drop_wait(conf)
    # ... and the bulk queue holds about a whole one (16 batches of 64 KB, Zenoh's most: a 1 MB image),
    # so that an image the link has room for goes whole, not cut after its first fragments (with
    # Zenoh's default 2 batches few of a flood's 1 MB images reached the ground: docs/reliability.md)
    conf.insert_json5("transport/link/tx/queue/size/background", "16")


def router_config(listen: list[str], stack_file: str | None = None, machine: str | None = None,
                  link_endpoint: str | None = None) -> tuple[zenoh.Config, list[str]]:
    """The router's configuration and the endpoints it listens on; `link_endpoint`: where its
    checked link's session listens (CheckedLink.endpoint)."""
    conf = zenoh.Config()
    _base_config(conf)
    connect: list[str] = []
    if machine:
        stack = load_stack(stack_file)
        if machine not in stack.machines:
            raise StackError(f"{stack.path}: no [machines.{machine}] (machines: {', '.join(stack.machines)})")
        m = stack.machines[machine]
        listen = list(dict.fromkeys([*(listen or [m.router]), *m.listen]))  # --listen stands for `router`
        # a checked link connects from its own session (link_config); this router to that session
        connect = ([link_endpoint] if link_endpoint else []) if checks_link(stack, machine) else list(m.connect)
        if stack.security is not None:
            security.apply_router(conf, stack, machine)
        if m.bulk_max_hz:
            conf.insert_json5("downsampling", json.dumps(bulk_downsampling(stack.vehicle_id, m.bulk_max_hz)))
    listen = listen or [DEFAULT_LISTEN]
    if any("prio=" in e for e in listen + connect):
        # endpoints that carry a priority range (`?prio=7-7`): one link per range to the same
        # router, so that bulk data never queues in front of control data in one TCP stream
        conf.insert_json5("transport/unicast/max_links", str(MAX_LINKS))
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    return conf, listen


def link_config(stack, machine: str, endpoint: str) -> zenoh.Config:
    """The checked link's session: a router that connects to the other hosts and listens only on
    `endpoint` (loopback), where the machine's router connects to it with the machine's login."""
    m = stack.machines[machine]
    conf = zenoh.Config()
    _base_config(conf)
    if stack.security is not None:
        security.apply_router(conf, stack, machine)   # no `listen` to other hosts: no access control here
    conf.insert_json5("transport/unicast/max_links", str(MAX_LINKS))
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    conf.insert_json5("connect/endpoints", json.dumps(list(m.connect)))
    return conf


def _loopback_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


class CheckedLink:
    """A session linking to other hosts that pings `ping` every PING_S and, until settle(), when no
    sample came back on `echo` for `check_s`, closes and opens again (a link down, or up but
    carrying nothing one way). After settle() it only says when the echo stops and comes back:
    replacing this session once the machine's router is linked to it left the two routers
    linked to it with no route through it (Zenoh 1.10.2, measured: docs/reliability.md), so the
    machine's router opens only once the link echoed, or GATE_S passed. `opens` counts the
    sessions opened; `echoed` is set once an echo came back; `endpoint`: where the session now
    open listens (a new port each: a session being closed aside is never the one linked to).
    Each re-opening waits twice as long for the echo as the one before (up to 4 x check_s): a
    starved machine whose link needs more than check_s would otherwise re-open forever.
    `make_config(endpoint)` gives a session's configuration."""

    def __init__(self, make_config, ping: str, echo: str, check_s: float = CHECK_S, log=None):
        self.make_config, self.ping, self.echo, self.check_s = make_config, ping, echo, check_s
        self.log = log or router_log
        self.opens = 0
        self.endpoint = ""
        self.echoed = threading.Event()
        self.last_echo = time.monotonic()   # or the session's opening, before the first echo
        self._changing = threading.Condition()
        self._settled = self._reopening = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="link", daemon=True)

    def start(self) -> "CheckedLink":
        self._thread.start()
        return self

    def settle(self) -> str:
        """No more re-opening; the endpoint of the session kept (one being re-opened: the new one's)."""
        with self._changing:
            self._settled = True
            self._changing.wait_for(lambda: not self._reopening, timeout=CLOSE_S + 2.0)
            return self.endpoint

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(CLOSE_S + 1.0)

    def _run(self) -> None:
        wait_s = self.check_s
        while not self._stop.is_set():
            endpoint = _loopback_endpoint()
            try:
                session = zenoh.open(self.make_config(endpoint))
            except zenoh.ZError as exc:
                session = None
                self.log(f"the link to the other host cannot open ({exc}); again in {self.check_s:g} s")
            with self._changing:
                self._reopening = False
                if session is not None:
                    self.opens += 1
                    self.endpoint = endpoint
                self._changing.notify_all()
            if session is None:
                self._stop.wait(self.check_s)
                continue
            last = [time.monotonic()]

            self.last_echo = last[0]

            def echoed(_sample) -> None:
                last[0] = self.last_echo = time.monotonic()
                self.echoed.set()
            session.declare_subscriber(self.echo, echoed)
            pub = session.declare_publisher(self.ping, priority=zenoh.Priority.DATA_HIGH, express=True)
            silent = False
            while not self._stop.wait(PING_S):
                pub.put(b"")
                quiet = time.monotonic() - last[0] >= (self.check_s if self.echoed.is_set() else wait_s)
                with self._changing:
                    self._reopening = quiet and not self._settled
                if self._reopening:
                    self.log(f"no echo over the link to the other host for {wait_s:g} s: opening it again")
                    wait_s = min(2.0 * wait_s, 4.0 * self.check_s)
                    break
                if quiet != silent:
                    silent = quiet
                    self.log(f"no echo over the link to the other host for {self.check_s:g} s" if quiet else
                             "the link to the other host echoes again")
            if self._stop.is_set():
                _close(session)
                return
            # closed aside: a link with a connection pending took 9.5 s to close
            threading.Thread(target=session.close, name="close", daemon=True).start()


def echo_links(session: zenoh.Session, vehicle_id: int, machines) -> list:
    """The accepting router's side of CheckedLink: each machine's ping answered on its echo key
    (one exact key each: the access control lets a machine see no wider subscription)."""
    def answer(echo: str):
        return lambda _sample: session.put(echo, b"", express=True)
    return [session.declare_subscriber(ping, answer(echo)) for ping, echo in (link_keys(vehicle_id, m) for m in machines)]


def _close(session: zenoh.Session) -> bool:
    """Close, given CLOSE_S (a router's close once took over 10 s under a loaded suite)."""
    closing = threading.Thread(target=session.close, name="close", daemon=True)
    closing.start()
    closing.join(CLOSE_S)
    return not closing.is_alive()


# a machine whose router carries these is never opened again: cut, they would lose each other
CONTROL_SERVICES = ("sim", "motors", "standby", "attitude", "position")


def health_keys(stack, machine: str) -> list[str]:
    """What `machine`'s router watches besides its link's echo before it opens them again: the
    health of every service not on `machine` (those of other machines on its host, as `vehicle`
    beside `vehicle-router`, keep coming while the link is down: such a router is never opened
    again); none, never opened again, where `machine` runs the vehicle's control services."""
    if any(s.machine == machine for n, s in stack.services.items() if n in CONTROL_SERVICES):
        return []
    return [f"zp/{stack.vehicle_id}/{n}/health" for n, s in stack.services.items() if s.machine not in ("", machine)]


def open_router(args, stack, log) -> tuple:
    """The machine's router as main() runs it: its checked link first where it has one (opened until
    it echoes, or GATE_S), then its own session. Returns (session, listen, link or None)."""
    conf, listen = router_config(args.listen, args.stack, args.machine)
    link = None
    if stack is not None and checks_link(stack, args.machine):
        link = CheckedLink(lambda e: link_config(stack, args.machine, e), *link_keys(stack.vehicle_id, args.machine)).start()
        if not link.echoed.wait(GATE_S):
            log(f"no echo over the link to the other host within {GATE_S:g} s: the machine's router opens without "
                f"it (the link is watched from now on)")
        conf, listen = router_config(args.listen, args.stack, args.machine, link.settle())
    try:
        session = zenoh.open(conf)
    except BaseException:
        if link is not None:
            link.stop()
        raise
    return session, listen, link


def relink(args, stack, session, link, log, stop: threading.Event) -> tuple:
    """The link lost for RELINK_S: the machine's router and its link closed and opened again as at
    the start (open_router), the router's ports retried while the old session lets them go."""
    link.stop()
    if not _close(session):
        log(f"the machine's router did not close within {CLOSE_S:g} s")
    for attempt in range(30):
        try:
            return open_router(args, stack, log)
        except zenoh.ZError as exc:   # its ports not free yet
            if stop.wait(1.0):
                raise
            log(f"the machine's router cannot open again yet ({exc}); again in 1 s")
    return open_router(args, stack, log)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="zenpilot-router", description=__doc__.splitlines()[0])
    p.add_argument("-l", "--listen", action="append", default=[], metavar="ENDPOINT",
                   help=f"endpoint to listen on (default: the machine's, else {DEFAULT_LISTEN}; repeatable)")
    p.add_argument("--stack", help="stack file (default: deploy/stacks/default.toml)")
    p.add_argument("--machine", help="run this machine's router as the stack file describes it")
    args = p.parse_args(argv)
    tie_to_parent()
    if os.environ.get("RUST_LOG"):   # Zenoh's own log, when asked for (how its links come and go)
        zenoh.init_log_from_env_or("error")
    log = router_log
    stop = threading.Event()
    on_stop_signals(stop.set)
    try:
        stack = load_stack(args.stack) if args.machine else None
        session, listen, link = open_router(args, stack, log)
    except (StackError, ValueError) as exc:
        print(f"zenpilot-router: error: {exc}", file=sys.stderr)
        raise SystemExit(2)
    except zenoh.ZError as exc:
        print(f"zenpilot-router: error: cannot open the router on {args.listen or args.machine}: {exc}",
              file=sys.stderr)
        raise SystemExit(2)
    print(f"zenpilot-router: listening on {', '.join(listen)}", flush=True)
    watched = health_keys(stack, args.machine) if link is not None else []
    relink_s = RELINK_S
    while True:
        if stack is not None and echoes_links(stack, args.machine):
            echo_links(session, stack.vehicle_id, [m for m in stack.machines if m != args.machine])
        heard = [time.monotonic()]

        def on_health(_sample, heard=heard) -> None:
            heard[0] = time.monotonic()
        for key in watched:   # what the machine's services receive anyway (a recorder: everything)
            session.declare_subscriber(key, on_health)
        # a link with nothing of the other machines to watch is never opened again
        while not stop.wait(1.0):
            now = time.monotonic()
            if watched and now - link.last_echo >= relink_s and now - heard[0] >= relink_s:
                break
        if stop.is_set():
            break
        log(f"no echo and nothing from the other host's services for {relink_s:g} s: the link and the "
            f"machine's router open again")
        # the other host gone for long (switched off): its services' router is cut less and less often
        relink_s = RELINK_S if link.echoed.is_set() else min(2.0 * relink_s, 3.0 * RELINK_S)
        try:
            session, listen, link = relink(args, stack, session, link, log, stop)
        except zenoh.ZError as exc:
            if stop.is_set():   # asked to stop while its ports were not free yet: nothing left open
                return
            print(f"zenpilot-router: error: cannot open the router again on {args.machine}: {exc}",
                  file=sys.stderr, flush=True)
            raise SystemExit(2)
        log(f"listening again on {', '.join(listen)}")
    if link is not None:
        link.stop()
    # A router holds nothing to save: its close is given a few seconds, then the process ends
    # regardless (it once took over 10 s under a loaded suite, holding its caller's clean-up).
    if not _close(session):
        print(f"zenpilot-router: the session did not close within {CLOSE_S:g} s: exiting", file=sys.stderr, flush=True)
        os._exit(0)


if __name__ == "__main__":
    main()
