"""A delay-and-loss link for kernels without `tc netem`: test and bench tooling, not flight code.

    python -m bench.support.linkemu IF_A IF_B --delay-ms 20 --jitter-ms 5 --loss-pct 1
                                    [--seed N] [--reorder] [--stats FILE]
                                    [--rate-mbit R [--priority-dscp D] [--queue-kb K]]

Run inside a third network namespace that holds IF_A and IF_B, the inner ends of two veth pairs
(host A <-> IF_A, IF_B <-> host B). Every Ethernet frame that arrives on one is sent out of the
other after a delay drawn per frame, uniform in [delay - jitter, delay + jitter] (netem's
distribution when it is given no table), or dropped with probability loss, the same profile in
each direction, each direction with its own seeded random stream.

Why frames (AF_PACKET) rather than routed IP: the two hosts stay on one subnet as with a plain veth
pair (ARP and all), nothing in the link namespace needs an address, a route or IP forwarding, and
the emulator sees what netem sees (the kernel's frames, GSO and checksum state included: each
frame is read and written with its virtio-net header, PACKET_VNET_HDR, so a frame whose checksum
the sender left to "hardware" keeps that state and TCP segments need no re-checksumming).

Order: by default each direction keeps its frames in order (a frame drawn a shorter delay than the
one before it leaves right after that one), as a radio link or a queue does; TCP then sees losses
but no reordering (a reordered segment costs it duplicate ACKs and, past its reordering threshold,
a spurious retransmission and a smaller window). netem's own default reorders (its queue is sorted
by send time): `--reorder` does that. Keeping the order at a high frame rate shifts the delay up
towards delay + jitter (a frame waits for the slowest of those just before it): the delay actually
given is measured and written to the stats.

Capacity (`--rate-mbit R`): the link then carries R Mbit/s each way; a frame waits in a
transmit queue (K KiB, tail drop) until the wire is free, takes len/R on it, then its delay. By
default the emulator's capacity is its own CPU's (~17 MB/s here). `--priority-dscp D` gives a
link that honours DSCP marks, as a WiFi access point's WMM queues or a router's priority qdisc
do: frames marked D or above (IP TOS >> 2; the stack marks its control links EF, 46) have a
transmit queue of their own, served first whenever the wire frees (strict priority; a frame
on the wire is not preempted).

On SIGTERM/SIGINT it writes its stats (per direction: frames in, dropped, sent, delay given p50/p99/max,
largest frame; process CPU seconds) as JSON to --stats and exits 0.
"""

from __future__ import annotations

import argparse
import heapq
import json
import os
import random
import resource
import select
import signal
import socket
import sys
import time
from collections import deque

ETH_P_ALL = 0x0003
SOL_PACKET = 263
PACKET_VNET_HDR = 15
PACKET_OUTGOING = 4   # sll_pkttype of a frame this host sent: not ours to forward
MAX_FRAME = 65536 + 64
VNET_HDR_LEN = 10     # struct virtio_net_hdr before each frame (PACKET_VNET_HDR)
HIGH, LOW = 0, 1      # transmit queues (--priority-dscp)


def dscp(frame: bytes) -> int:
    """The DSCP of an IPv4 or IPv6 frame (read with its virtio-net header); 0 for anything else."""
    eth = VNET_HDR_LEN
    if len(frame) < eth + 16:
        return 0
    kind = frame[eth + 12:eth + 14]
    if kind == b"\x08\x00":
        return frame[eth + 15] >> 2
    if kind == b"\x86\xdd":
        return (((frame[eth + 14] & 0x0F) << 4) | (frame[eth + 15] >> 4)) >> 2
    return 0


class Direction:
    """One way of the link: frames read on `src`, sent on `dst` at their departure time."""

    def __init__(self, name: str, src: socket.socket, dst: socket.socket, delay_s: float, jitter_s: float,
                 loss: float, seed: int, reorder: bool, rate_bit_s: float = 0.0, priority_dscp: int | None = None,
                 queue_bytes: int = 256 << 10):
        self.name, self.src, self.dst = name, src, dst
        self.delay_s, self.jitter_s, self.loss, self.reorder = delay_s, jitter_s, loss, reorder
        # the wire (rate_bit_s > 0): transmit queues, HIGH for frames marked priority_dscp or above
        self.rate_bit_s, self.priority_dscp, self.queue_bytes = rate_bit_s, priority_dscp, queue_bytes
        self.tx: tuple[deque, deque] = (deque(), deque())   # (arrival, frame)
        self.tx_bytes = [0, 0]
        self.tx_dropped = [0, 0]
        self.tx_frames = [0, 0]
        self.tx_delays: tuple[list, list] = ([], [])   # per queue: arrival to the end of its delay, s
        self.wire_free_at = 0.0
        self.rng = random.Random(seed)
        self.queue: deque = deque()   # (departure, arrival, frame), departures non-decreasing
        self.heap: list = []          # the same with --reorder: by departure time
        self.n = 0
        self.last_departure = 0.0
        self.received = self.dropped = self.sent = self.send_errors = self.recv_errors = 0
        self.largest = 0
        self.delays: list[float] = []  # given, s (bounded below)

    def take(self, now: float) -> None:
        """Read every frame waiting on `src`; queue each kept one for its departure."""
        while True:
            try:
                frame, addr = self.src.recvfrom(MAX_FRAME)
            except BlockingIOError:
                return
            except OSError:   # its interface set down (an outage: bench/two_hosts.py --outage): ENETDOWN once
                self.recv_errors += 1
                return
            if addr[2] == PACKET_OUTGOING:
                continue
            self.received += 1
            self.largest = max(self.largest, len(frame))
            if self.loss and self.rng.random() < self.loss:
                self.dropped += 1
                continue
            if not self.rate_bit_s:
                self._propagate(now, now, frame)
                continue
            c = HIGH if self.priority_dscp is not None and dscp(frame) >= self.priority_dscp else LOW
            if self.tx_bytes[c] + len(frame) > self.queue_bytes:   # the queue is full: tail drop
                self.tx_dropped[c] += 1
                continue
            self.tx[c].append((now, frame))
            self.tx_bytes[c] += len(frame)
            self.tx_frames[c] += 1

    def _propagate(self, t: float, arrival: float, frame: bytes) -> float:
        """The frame leaves the wire (or arrives, without one) at t: queue it for t + its delay
        (returned)."""
        d = self.delay_s + (self.rng.uniform(-self.jitter_s, self.jitter_s) if self.jitter_s else 0.0)
        departure = t + max(d, 0.0)
        if self.reorder:
            self.n += 1
            heapq.heappush(self.heap, (departure, self.n, arrival, frame))
        else:
            departure = max(departure, self.last_departure)
            self.last_departure = departure
            self.queue.append((departure, arrival, frame))
        return departure

    def serialise(self, now: float) -> None:
        """Put frames on the wire while it is free by `now`, the HIGH queue first."""
        tx = self.tx
        while (tx[HIGH] or tx[LOW]) and self.wire_free_at <= now:
            c = HIGH if tx[HIGH] else LOW
            arrival, frame = tx[c].popleft()
            self.tx_bytes[c] -= len(frame)
            done = max(self.wire_free_at, arrival) + 8 * len(frame) / self.rate_bit_s
            self.wire_free_at = done
            departure = self._propagate(done, arrival, frame)
            if len(self.tx_delays[c]) < 1_000_000:
                self.tx_delays[c].append(departure - arrival)

    def next_event(self) -> float | None:
        """When this direction next has something to do: a departure, or the wire freeing."""
        due = self.next_departure()
        if self.tx[HIGH] or self.tx[LOW]:
            due = self.wire_free_at if due is None else min(due, self.wire_free_at)
        return due

    def next_departure(self) -> float | None:
        if self.reorder:
            return self.heap[0][0] if self.heap else None
        return self.queue[0][0] if self.queue else None

    def send_due(self, now: float) -> None:
        while (due := self.next_departure()) is not None and due <= now:
            if self.reorder:
                _, _, arrival, frame = heapq.heappop(self.heap)
            else:
                _, arrival, frame = self.queue.popleft()
            try:
                self.dst.send(frame)
                self.sent += 1
            except OSError:   # the other end gone (the namespaces being removed), or a full queue
                self.send_errors += 1
            if len(self.delays) < 1_000_000:
                self.delays.append(now - arrival)

    def stats(self) -> dict:
        d = sorted(self.delays)

        def q(f: float, d=d) -> float | None:
            return round(1e3 * d[min(len(d) - 1, int(f * len(d)))], 3) if d else None

        def spread(delays: list) -> dict:
            s = sorted(delays)
            return {"p50": q(0.5, s), "p99": q(0.99, s), "max": q(1.0, s)}

        wire = {}
        if self.rate_bit_s:
            wire = {"wire": {"rate_mbit": self.rate_bit_s / 1e6, "priority_dscp": self.priority_dscp,
                             "frames": {"high": self.tx_frames[HIGH], "low": self.tx_frames[LOW]},
                             "delay_ms": {"high": spread(self.tx_delays[HIGH]), "low": spread(self.tx_delays[LOW])},
                             "queue_full_dropped": {"high": self.tx_dropped[HIGH], "low": self.tx_dropped[LOW]}}}
        return {**wire, "received": self.received, "dropped": self.dropped, "sent": self.sent,
                "send_errors": self.send_errors, "recv_errors": self.recv_errors, "queued_at_exit": len(self.queue) + len(self.heap),
                "largest_frame": self.largest, "delay_ms": {"p1": q(0.01), "p50": q(0.5), "p99": q(0.99),
                                                             "max": q(1.0),
                                                             "mean": round(1e3 * sum(d) / len(d), 3) if d else None}}


def open_socket(ifname: str) -> socket.socket:
    s = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
    s.setsockopt(SOL_PACKET, PACKET_VNET_HDR, 1)   # frames with their GSO/checksum header, kept as they are
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    s.bind((ifname, ETH_P_ALL))
    s.setblocking(False)
    return s


class Stop(Exception):
    pass


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("a", help="interface towards host A")
    p.add_argument("b", help="interface towards host B")
    p.add_argument("--delay-ms", type=float, default=0.0, help="mean one-way delay added, each direction")
    p.add_argument("--jitter-ms", type=float, default=0.0, help="delay drawn uniformly within +- this")
    p.add_argument("--loss-pct", type=float, default=0.0, help="frames dropped at random, each direction, %%")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--reorder", action="store_true", help="let a shorter draw overtake (netem's default)")
    p.add_argument("--stats", help="write the stats here (JSON) on exit")
    p.add_argument("--rate-mbit", type=float, default=0.0, help="the link's capacity each way (0: the emulator's)")
    p.add_argument("--priority-dscp", type=int, help="with --rate-mbit: frames marked this DSCP or above first")
    p.add_argument("--queue-kb", type=int, default=256, help="with --rate-mbit: each transmit queue's size, KiB")
    args = p.parse_args(argv)
    if args.delay_ms < 0 or args.jitter_ms < 0 or not 0 <= args.loss_pct <= 100:
        p.error("delay and jitter must be >= 0, loss within 0..100")
    if args.rate_mbit < 0 or args.queue_kb < 1 or (args.priority_dscp is not None and not 0 <= args.priority_dscp <= 63):
        p.error("--rate-mbit must be >= 0, --queue-kb >= 1, --priority-dscp within 0..63")
    if args.priority_dscp is not None and not args.rate_mbit:
        p.error("--priority-dscp needs --rate-mbit (priority orders the wire's queue)")
    try:
        sa, sb = open_socket(args.a), open_socket(args.b)
    except OSError as exc:
        print(f"linkemu: error: cannot open raw sockets on {args.a}/{args.b} (root, in their namespace?): {exc}",
              file=sys.stderr)
        return 2
    common = dict(delay_s=args.delay_ms / 1e3, jitter_s=args.jitter_ms / 1e3, loss=args.loss_pct / 100,
                  reorder=args.reorder, rate_bit_s=args.rate_mbit * 1e6, priority_dscp=args.priority_dscp,
                  queue_bytes=args.queue_kb << 10)
    dirs = {sa.fileno(): Direction(f"{args.a}->{args.b}", sa, sb, seed=2 * args.seed, **common),
            sb.fileno(): Direction(f"{args.b}->{args.a}", sb, sa, seed=2 * args.seed + 1, **common)}

    def stop(*_):
        raise Stop()

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    t0 = time.monotonic()
    print(f"linkemu: {args.a} <-> {args.b}: {args.delay_ms:g} +- {args.jitter_ms:g} ms, loss {args.loss_pct:g} %, "
          f"seed {args.seed}, {'reordering' if args.reorder else 'in order'}"
          + (f", {args.rate_mbit:g} Mbit/s, queues {args.queue_kb} KiB"
             + (f", DSCP >= {args.priority_dscp} first" if args.priority_dscp is not None else "")
             if args.rate_mbit else "") + f"; pid {os.getpid()}", flush=True)
    readers = [sa, sb]
    try:
        while True:
            now = time.monotonic()
            due = [t for d in dirs.values() if (t := d.next_event()) is not None]
            timeout = max(0.0, min(due) - now) if due else 0.5
            ready, _, _ = select.select(readers, [], [], timeout)
            now = time.monotonic()
            for s in ready:
                dirs[s.fileno()].take(now)
            for d in dirs.values():
                if d.rate_bit_s:
                    d.serialise(now)
                d.send_due(now)
    except Stop:
        pass
    ru = resource.getrusage(resource.RUSAGE_SELF)
    stats = {"profile": {"delay_ms": args.delay_ms, "jitter_ms": args.jitter_ms, "loss_pct": args.loss_pct,
                         "seed": args.seed, "reorder": args.reorder, "rate_mbit": args.rate_mbit,
                         "priority_dscp": args.priority_dscp, "queue_kb": args.queue_kb},
             "wall_s": round(time.monotonic() - t0, 3), "cpu_s": round(ru.ru_utime + ru.ru_stime, 3),
             "directions": {d.name: d.stats() for d in dirs.values()}}
    frames = sum(d.received for d in dirs.values())
    stats["cpu_us_per_frame"] = round(1e6 * stats["cpu_s"] / frames, 2) if frames else None
    if args.stats:
        with open(args.stats, "w") as f:
            json.dump(stats, f, indent=2)
    print("linkemu: " + json.dumps(stats), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
