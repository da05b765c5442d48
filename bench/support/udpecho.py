"""A UDP echo and its client, to measure what a link gives (bench/link.py): round trips and losses.

    python -m bench.support.udpecho server [--port 9999] [--idle-s 30]
    python -m bench.support.udpecho client HOST [--port 9999] [-n 500] [--gap-ms 10]

The client sends n numbered datagrams of 64 bytes, one every gap, each answered or lost (no answer
within 1 s), and prints one JSON line: sent, lost, round trip p1/p50/p99/max/mean in ms.
"""

from __future__ import annotations

import argparse
import json
import socket
import time


def server(port: int, idle_s: float) -> None:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("0.0.0.0", port))
    s.settimeout(idle_s)
    print(f"udpecho: listening on {port}", flush=True)
    try:
        while True:
            data, addr = s.recvfrom(2048)
            s.sendto(data, addr)
    except socket.timeout:   # nothing for idle_s: done
        pass


def client(host: str, port: int, n: int, gap_s: float) -> dict:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.settimeout(1.0)
    rtts, lost = [], 0
    for i in range(n):
        t0 = time.monotonic()
        s.sendto(i.to_bytes(4, "big") + bytes(60), (host, port))
        try:
            while int.from_bytes(s.recvfrom(2048)[0][:4], "big") != i:   # a late answer to an earlier one
                pass
            rtts.append(1e3 * (time.monotonic() - t0))
        except socket.timeout:
            lost += 1
        time.sleep(max(0.0, gap_s - (time.monotonic() - t0)))
    rtts.sort()

    def q(f):
        return round(rtts[min(len(rtts) - 1, int(f * len(rtts)))], 3) if rtts else None

    return {"sent": n, "lost": lost, "rtt_ms": {"p1": q(0.01), "p50": q(0.5), "p99": q(0.99), "max": q(1.0),
                                                "mean": round(sum(rtts) / len(rtts), 3) if rtts else None}}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("role", choices=("server", "client"))
    p.add_argument("host", nargs="?")
    p.add_argument("--port", type=int, default=9999)
    p.add_argument("-n", type=int, default=500)
    p.add_argument("--gap-ms", type=float, default=10.0)
    p.add_argument("--idle-s", type=float, default=30.0)
    args = p.parse_args(argv)
    if args.role == "server":
        server(args.port, args.idle_s)
    elif not args.host:
        p.error("client: HOST is needed")
    else:
        print(json.dumps(client(args.host, args.port, args.n, args.gap_ms / 1e3)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
