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

`--log FILE --log-key EXPR ...`: the messages on those key expressions also go, decoded, into a
flight log (schemas.flightlog) written at exit: the host's own record of what its router carried
(bench/two_hosts.py --outage: the vehicle's, while the ground's recorder is cut off from it).
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
    p.add_argument("--log", help="a flight log of the --log-key messages, written at exit")
    p.add_argument("--log-key", action="append", default=[], metavar="KEY_EXPR",
                   help="a key expression whose messages go into --log (repeatable)")
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

    kept: list[tuple[str, bytes]] = []

    def on_kept(sample) -> None:
        kept.append((str(sample.key_expr), sample.payload.to_bytes()))

    subs = [session.declare_subscriber(k, on_sample) for k in args.keys]
    subs += [session.declare_subscriber(k, on_kept) for k in (args.log_key if args.log else [])]
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
    if args.log:
        print(f"linkprobe: {write_kept(args.log, kept)} messages -> {args.log}", flush=True)
    return 0


def write_kept(path: str, kept: list[tuple[str, bytes]]) -> int:
    """The kept messages, decoded as the recorder decodes them (schemas), in their sample time's
    order, as a flight log; what does not decode is left out."""
    import schemas
    from schemas.flightlog import write_log
    records = []
    for key, payload in kept:
        definition = schemas.message_for_key(key)
        try:
            records.append((key, definition.decode(payload)))
        except Exception:   # no message for the key, or not one of ours
            continue
    records.sort(key=lambda r: r[1]["header"]["t_s"])
    return write_log(path, records)


if __name__ == "__main__":
    raise SystemExit(main())
