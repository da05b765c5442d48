"""A bulk publisher gone wild: valid, oversized camera images on a stack's bus at a fixed rate.

    python -m bench.support.flooder --connect tcp/127.0.0.1:7447 [--vehicle 0] [--bytes 1048576]
        [--hz 200] [--priority control|bulk] [--seconds 20]

A peer session beside the stack's services (as the camera's publisher would be), publishing
`zp/<vehicle>/sim/@image` at `--hz`: 1024-pixel-wide mono8 frames of about `--bytes`, a size
the vision service's intrinsics do not hold (it counts and drops them, after receiving each in
full). `--priority` is the key's priority class it declares (default: the camera key's own,
schemas.CAMERA_IMAGE's "bulk"; "control" puts the flood in the control keys' queue, as
without priorities). Prints how many it sent and how often it fell behind its rate.

`--sink`: subscribes to the same key instead (a ground tool showing the camera, on the other
host: what makes the flood cross a link) and prints what it received.
"""

from __future__ import annotations

import argparse
import json
import random
import signal
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import zenoh  # noqa: E402

import schemas  # noqa: E402
from services.runtime import bound_drop_wait, bulk_downsampling, zenoh_priority  # noqa: E402

WIDTH_PX = 1024


def flood_spec(text: str) -> tuple[int, float, str | None]:
    """A bench's --flood BYTES@HZ[:PRIORITY] -> (bytes, hz, priority or None)."""
    spec, _, priority = text.partition(":")
    size, _, hz = spec.partition("@")
    try:
        out = int(size), float(hz), priority or None
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected BYTES@HZ[:PRIORITY], e.g. 1048576@200") from None
    if out[0] < 1024 or out[1] <= 0 or (priority and priority not in schemas.core.PRIORITIES):
        raise argparse.ArgumentTypeError(f"{text!r}: BYTES >= 1024, HZ > 0, PRIORITY {' or '.join(schemas.core.PRIORITIES)}")
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--connect", required=True, help="the stack's router endpoint")
    ap.add_argument("--vehicle", default="0", help="vehicle id of the keys (default 0)")
    ap.add_argument("--bytes", type=int, default=1 << 20, help="about this many bytes a message (default 1 MiB)")
    ap.add_argument("--hz", type=float, default=200.0, help="messages per second (default 200: 10x the camera)")
    ap.add_argument("--priority", choices=schemas.core.PRIORITIES, default=None,
                    help="priority class (default: the camera key's own)")
    ap.add_argument("--seconds", type=float, default=1e9, help="stop after this long (default: on SIGTERM)")
    ap.add_argument("--max-hz", type=float, default=0.0,
                    help="its session caps the key at this rate, as a stack service's does on a machine with "
                         "bulk_max_hz (services.runtime.bulk_downsampling; default 0: no cap, a rogue publisher)")
    ap.add_argument("--sink", action="store_true", help="receive the flood instead (a client of --connect)")
    args = ap.parse_args(argv)
    if args.bytes < WIDTH_PX or args.hz <= 0:
        ap.error("--bytes must be >= 1024 and --hz > 0")
    message = schemas.CAMERA_IMAGE
    priority = zenoh_priority(args.priority or message.priority)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"' if args.sink else '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
    if not args.sink:
        conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/shared_memory/enabled", "false")
    if args.max_hz > 0 and not args.sink:   # configured as a stack service's session is (services.runtime)
        conf.insert_json5("downsampling", json.dumps(bulk_downsampling(int(args.vehicle), args.max_hz)))
        bound_drop_wait(conf)
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    if args.sink:
        sink(conf, message.key(args.vehicle), stop, args.seconds)
        return
    height = max(1, args.bytes // WIDTH_PX)
    pixels = random.Random(0).randbytes(WIDTH_PX * height)   # incompressible, as a camera's noise is
    with zenoh.open(conf) as session:
        pub = session.declare_publisher(message.key(args.vehicle), express=True, priority=priority,
                                        congestion_control=zenoh.CongestionControl.DROP)
        period = 1.0 / args.hz
        sent, late, seq = 0, 0, 0
        t0 = time.monotonic()
        nxt = t0
        while not stop and time.monotonic() - t0 < args.seconds:
            payload = message.encode(time.monotonic(), seq, "flooder",
                                     {"width_px": WIDTH_PX, "height_px": height, "encoding": "mono8",
                                      "exposure_s": 0.004, "pixels": pixels[:WIDTH_PX * height]})
            pub.put(payload)
            sent += 1
            seq += 1
            nxt += period
            wait = nxt - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            else:
                late += 1
                if wait < -0.5:   # far behind: no burst to catch up
                    nxt = time.monotonic()
        wall = time.monotonic() - t0
    print(json.dumps({"sent": sent, "seconds": round(wall, 2), "bytes_each": len(payload),
                      "rate_hz": round(sent / max(wall, 1e-9), 1), "behind": late}), flush=True)


def sink(conf: zenoh.Config, key: str, stop: list, seconds: float) -> None:
    got = {"n": 0, "bytes": 0}

    def on_sample(sample) -> None:
        got["n"] += 1
        got["bytes"] += len(sample.payload)

    with zenoh.open(conf) as session:
        session.declare_subscriber(key, on_sample)
        print("flooder: sink listening", flush=True)
        t0 = time.monotonic()
        while not stop and time.monotonic() - t0 < seconds:
            time.sleep(0.05)
        wall = time.monotonic() - t0
    print(json.dumps({"received": got["n"], "seconds": round(wall, 2),
                      "mb_per_s": round(got["bytes"] / max(wall, 1e-9) / 1e6, 1)}), flush=True)


if __name__ == "__main__":
    main()
