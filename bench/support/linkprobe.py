"""Arrival times of a host's incoming keys, for the link's latency per key (bench/two_hosts.py).

    python -m bench.support.linkprobe -e ENDPOINT [--stack FILE] --out FILE KEY_EXPR [KEY_EXPR ...]

A Zenoh client of the host's router (as the host's services are) subscribes to the key
expressions (the keys the other host's services publish) and notes, for every message, the wall
clock when Zenoh handed it over (time.time(), the clock real-time headers are stamped with) and
its header's time and sequence number. On SIGTERM/SIGINT it writes them as JSON:
{key: [[t_arrival, t_s, seq, source], ...]}. The callback only notes the bytes and the time (the
header is decoded at exit), so the probe costs its host little and is late by little more than
the router hop every service takes. Latency = arrival - header time: on two real hosts that needs
their clocks in step (chrony/PTP), the namespaces share one.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time

import msgpack
import zenoh


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-e", "--connect", required=True, help="the host's router endpoint")
    p.add_argument("--stack", help="a stack file with [security]: the probe presents its host's machine's login "
                                   "(deploy.launcher.client_session)")
    p.add_argument("--out", required=True)
    p.add_argument("keys", nargs="+")
    args = p.parse_args(argv)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    try:
        if args.stack:   # as a tool of the host's machine: its login and certificate
            from deploy.launcher import client_session
            from services.stack import load_stack
            session = client_session(args.connect, load_stack(args.stack))
        else:
            session = zenoh.open(conf)
    except zenoh.ZError as exc:
        print(f"linkprobe: error: cannot reach {args.connect}: {exc}", file=sys.stderr)
        return 2
    seen: list[tuple[float, str, bytes]] = []
    now = time.time

    def on_sample(sample) -> None:
        seen.append((now(), str(sample.key_expr), sample.payload.to_bytes()))

    subs = [session.declare_subscriber(k, on_sample) for k in args.keys]
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print(f"linkprobe: listening on {' '.join(args.keys)} via {args.connect}", flush=True)
    stop.wait()
    for s in subs:
        s.undeclare()
    session.close()
    out: dict[str, list] = {}
    bad = 0
    for t, key, payload in list(seen):
        try:
            h = msgpack.unpackb(payload)["header"]
            out.setdefault(key, []).append([t, float(h["t_s"]), int(h["seq"]), str(h["source"])])
        except Exception:   # not one of ours: counted, not fatal
            bad += 1
    with open(args.out, "w") as f:
        json.dump(out, f)
    print(f"linkprobe: {len(seen)} messages on {len(out)} keys ({bad} unreadable) -> {args.out}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
