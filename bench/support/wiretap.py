"""When each control message passed an interface, by the kernel's clock (bench/two_hosts.py --trace).

    python -m bench.support.wiretap IFACE --out FILE [--dscp 46]

Run inside a host's namespace on its end of the link: an AF_PACKET socket with a kernel filter
(classic BPF) that passes only IPv4 frames marked DSCP `--dscp` (the stack's control links:
EF, 46), both ways. Each frame keeps the kernel's timestamp (SO_TIMESTAMPNS:
taken when the frame was handed to the device going out, or when it came in), so how late this
process reads it changes nothing; the frames are kept raw and read at exit, so the loop costs
little. At SIGTERM/SIGINT, every message header found in a UDP frame's payload (the stack's
messages are MessagePack maps with a "header" map: t_s, seq, source) is written as JSON:
{"frames": N, "dropped_by_kernel": D, "out": [[t_wire, t_s, seq, source], ...], "in": [...]}.
The headers are matched to the link probes' rows by (source, seq, t_s): for a message that
crossed, where its time went (sender's host, the link, the receiver's host).
"""

from __future__ import annotations

import argparse
import ctypes
import json
import signal
import socket
import struct
import sys
import threading

import msgpack

ETH_P_ALL = 0x0003   # outgoing frames reach only ETH_P_ALL sockets (dev_queue_xmit_nit)
ETH_P_IP = 0x0800
SOL_PACKET = 263
PACKET_STATISTICS = 6
SO_TIMESTAMPNS = 35
SCM_TIMESTAMPNS = SO_TIMESTAMPNS
SO_ATTACH_FILTER = 26
PACKET_OUTGOING = 4
HEADER = b"\xa6header"


def dscp_filter(dscp: int) -> bytes:
    """struct sock_fprog for: IPv4 and (TOS & 0xfc) == dscp << 2, whole frame; else nothing."""
    insns = [(0x28, 0, 0, 12),           # ldh [12]        ethertype
             (0x15, 0, 4, ETH_P_IP),     # jeq #0x800      else drop
             (0x30, 0, 0, 15),           # ldb [15]        IP TOS
             (0x54, 0, 0, 0xFC),         # and #0xfc       DSCP << 2
             (0x15, 0, 1, dscp << 2),    # jeq             else drop
             (0x06, 0, 0, 0xFFFF),       # ret #65535      keep the frame
             (0x06, 0, 0, 0)]            # ret #0          drop
    buf = ctypes.create_string_buffer(b"".join(struct.pack("HBBI", *i) for i in insns))
    dscp_filter.keep = buf   # alive as long as the socket may read it (the kernel copies it; belt and braces)
    return struct.pack("HL", len(insns), ctypes.addressof(buf))


def headers(frame: bytes) -> list[tuple[float, int, str]]:
    """(t_s, seq, source) of every message header in an IPv4 UDP frame's payload."""
    if len(frame) < 34 or frame[23] != 17:   # not UDP (the TCP control link: segments, not read here)
        return []
    start = 14 + 4 * (frame[14] & 0x0F) + 8
    out, i = [], frame.find(HEADER, start)
    while i >= 0:
        try:
            u = msgpack.Unpacker()
            u.feed(frame[i + len(HEADER):i + len(HEADER) + 256])
            h = u.unpack()
            out.append((float(h["t_s"]), int(h["seq"]), str(h["source"])))
        except Exception:   # cut by the frame's end, or not one of ours
            pass
        i = frame.find(HEADER, i + len(HEADER))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("iface")
    p.add_argument("--out", required=True)
    p.add_argument("--dscp", type=int, default=46)
    args = p.parse_args(argv)
    s = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
    s.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, dscp_filter(args.dscp))
    s.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 << 20)
    s.bind((args.iface, ETH_P_ALL))
    s.settimeout(0.2)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    kept: list[tuple[float, int, bytes]] = []
    print(f"wiretap: {args.iface}, DSCP {args.dscp}", flush=True)
    while not stop.is_set():
        try:
            frame, anc, _, addr = s.recvmsg(2048, 64)
        except (socket.timeout, InterruptedError):
            continue
        t = None
        for level, kind, data in anc:
            if level == socket.SOL_SOCKET and kind == SCM_TIMESTAMPNS:
                sec, ns = struct.unpack("qq", data[:16])
                t = sec + ns * 1e-9
        if t is not None:
            kept.append((t, addr[2], frame))
    packets, drops = struct.unpack("II", s.getsockopt(SOL_PACKET, PACKET_STATISTICS, 8))
    out: dict = {"frames": len(kept), "dropped_by_kernel": drops, "out": [], "in": []}
    for t, kind, frame in kept:
        for h in headers(frame):
            out["out" if kind == PACKET_OUTGOING else "in"].append([t, *h])
    with open(args.out, "w") as f:
        json.dump(out, f)
    print(f"wiretap: {len(kept)} frames ({drops} dropped by the kernel), {len(out['out'])} headers out, "
          f"{len(out['in'])} in -> {args.out}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
