"""zenpilot-recorder: writes every message of the vehicle to one MCAP flight log.

Subscribes to zp/<vehicle>/** and decodes each message strictly (malformed
ones are counted, not logged). In lockstep the log is sorted by sample time,
key and sequence number before writing, so the same seed gives the same file.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Callable

import zenoh

import schemas
from deploy.flightlog import LOG_NAME, write_log
from services.runtime import Runtime, main_guard, service_parser

NAME = "recorder"
PARAMS: dict = {}
SKIP = object()  # a key the recorder does not log (its own health, liveliness)
_UNSEEN = object()
MAX_KEYS = 4096  # keys remembered by the per-key lookup; others are looked up per message


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    own_health = schemas.HEALTH.key(rt.vehicle_id, NAME)
    records: list[tuple[str, dict]] = []
    lock = threading.Lock()
    # per key, what to do with its messages: the message's decode, SKIP, or None (no
    # message defined); looked up once per key, not per message
    decoders: dict[str, Callable[[bytes], dict] | object | None] = {}  # thread safe: single dict ops

    def decoder_for(key: str):
        if key == own_health or "/alive/" in key:
            found = SKIP
        else:
            definition = schemas.message_for_key(key)
            found = None if definition is None else definition.decode
        if len(decoders) < MAX_KEYS:  # keys come from the network: bound the cache
            decoders[key] = found
        return found

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        decode = decoders.get(key, _UNSEEN)
        if decode is _UNSEEN:
            decode = decoder_for(key)
        if decode is SKIP:
            return
        if decode is None:
            rt.reject(key, schemas.SchemaError("malformed", "?", f"no message is defined for key {key}"))
            return
        try:
            msg = decode(sample.payload.to_bytes())
        except schemas.SchemaError as exc:
            rt.reject(key, exc)
            return
        with lock:
            records.append((key, msg))

    rt.subscribe(rt.key("**"), on_sample)
    rt.lockstep = False  # the recorder only listens: it keeps wall time for its own health
    rt.rate_hz = 10.0
    try:
        rt.run(lambda t: None)
    finally:
        with lock:
            rows = list(records)
        if args.lockstep:  # arrival order across senders is not deterministic; sample time is
            rows.sort(key=lambda r: (r[1]["header"]["t_s"], r[0], r[1]["header"]["seq"]))
            # a message repeated until answered (the lockstep "ready") is logged once
            rows = [r for i, r in enumerate(rows) if i == 0 or (r[0], r[1]["header"]["seq"])
                    != (rows[i - 1][0], rows[i - 1][1]["header"]["seq"])]
        n = write_log(out_dir / LOG_NAME, rows)
        print(f"zenpilot-recorder: wrote {n} messages to {out_dir / LOG_NAME}; "
              f"rejected {sum(rt.rejected.values())} {json.dumps(rt.rejected, sort_keys=True)}", flush=True)


def main(argv=None) -> None:
    parser = service_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/latest", help="directory for flight.mcap")
    args = parser.parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
