"""zenpilot-router: a Zenoh router from the Python package (no zenohd binary needed).

    zenpilot-router --listen tcp/127.0.0.1:7447                  # a bare router (tests, benches)
    zenpilot-router --stack FILE --machine NAME                   # a machine's router, as the stack says

With --machine it listens exactly where the stack file says (the machine's `router`
endpoint and its `listen` endpoints), links to its `connect` routers and, with a [security]
table, requires TLS client certificates and the machine's users, and enforces the access
control of services/security.py.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading

import zenoh

from services import security
from services.runtime import bulk_downsampling, on_stop_signals, tie_to_parent
from services.stack import StackError, load_stack

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
MAX_LINKS = 8   # links per router pair: at most one per Zenoh priority
CLOSE_S = 3.0


def router_config(listen: list[str], stack_file: str | None = None, machine: str | None = None) -> tuple[zenoh.Config, list[str]]:
    """The router's configuration and the endpoints it listens on."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    # No shared memory, as for the services (services.runtime.zenoh_config): two routers on one
    # machine (network namespaces standing for two hosts) would otherwise pass large payloads
    # through /dev/shm, not their link, as two real hosts never can
    conf.insert_json5("transport/shared_memory/enabled", "false")
    conf.insert_json5("transport/link/tx/queue/size/real_time", "16")
    connect: list[str] = []
    if machine:
        stack = load_stack(stack_file)
        if machine not in stack.machines:
            raise StackError(f"{stack.path}: no [machines.{machine}] (machines: {', '.join(stack.machines)})")
        m = stack.machines[machine]
        listen = list(dict.fromkeys([*(listen or [m.router]), *m.listen]))  # --listen stands for `router`
        connect = list(m.connect)
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


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="zenpilot-router", description=__doc__.splitlines()[0])
    p.add_argument("-l", "--listen", action="append", default=[], metavar="ENDPOINT",
                   help=f"endpoint to listen on (default: the machine's, else {DEFAULT_LISTEN}; repeatable)")
    p.add_argument("--stack", help="stack file (default: deploy/stacks/default.toml)")
    p.add_argument("--machine", help="run this machine's router as the stack file describes it")
    args = p.parse_args(argv)
    tie_to_parent()
    try:
        conf, listen = router_config(args.listen, args.stack, args.machine)
        session = zenoh.open(conf)
    except (StackError, ValueError) as exc:
        print(f"zenpilot-router: error: {exc}", file=sys.stderr)
        raise SystemExit(2)
    except zenoh.ZError as exc:
        print(f"zenpilot-router: error: cannot open the router on {args.listen or args.machine}: {exc}",
              file=sys.stderr)
        raise SystemExit(2)
    stop = threading.Event()
    on_stop_signals(stop.set)
    print(f"zenpilot-router: listening on {', '.join(listen)}", flush=True)
    stop.wait()
    # A router holds nothing to save: its close is given a few seconds (it once took over 10 s
    # under a loaded suite, holding its caller's clean-up), then the process ends regardless.
    closing = threading.Thread(target=session.close, name="close", daemon=True)
    closing.start()
    closing.join(CLOSE_S)
    if closing.is_alive():
        print(f"zenpilot-router: the session did not close within {CLOSE_S:g} s: exiting", file=sys.stderr, flush=True)
        os._exit(0)


if __name__ == "__main__":
    main()
