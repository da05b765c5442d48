"""zenpilot-router: a Zenoh router from the Python package (no zenohd binary needed)."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading

import zenoh


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="zenpilot-router", description=__doc__)
    p.add_argument("-l", "--listen", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on (default tcp/127.0.0.1:7447; repeatable)")
    args = p.parse_args(argv)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps(args.listen or ["tcp/127.0.0.1:7447"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        print(f"zenpilot-router: error: cannot listen on {args.listen}: {exc}", file=sys.stderr)
        raise SystemExit(2)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print(f"zenpilot-router: listening on {', '.join(args.listen or ['tcp/127.0.0.1:7447'])}", flush=True)
    stop.wait()
    session.close()


if __name__ == "__main__":
    main()
