"""zenpilot-recorder: writes every message of the vehicle to one MCAP flight log.

Subscribes to zp/<vehicle>/** and writes as the flight goes: the Zenoh callback only
queues (key, payload); the recorder's loop (10 Hz) decodes each message strictly
(malformed ones are counted, not logged) and adds it to the log, and at least every
FLUSH_S of wall time hands the chunk in progress to the OS, so a recorder killed at any
time leaves the chunks written before readable (`zenpilot log recover`). On a stop
(SIGTERM/SIGINT) it writes the rest and the summary: a complete, indexed log.

In lockstep the log is then rewritten in (sample time, key, sequence) order, each
message once, so the same seed gives the same file: arrival order across senders
depends on the machine. The rewrite goes to a temporary file that replaces the log
when done, so the log is complete at every moment of it.

Beside the bus messages (JSON, one channel per key) the log holds Foxglove's well-known
messages made from them (services/foxglove_map.py: transforms, poses, the 3D scene), so
Foxglove shows the flight without configuration: written as the messages come in real time,
made from the sorted stream in lockstep (the conversion keeps state, e.g. the newest
attitude: it must see the messages in a deterministic order).
"""

from __future__ import annotations

import json
import os
import signal
import time
from collections import deque
from pathlib import Path
from typing import Callable

import zenoh

import schemas
from flight.vehicle import load_vehicle
from schemas.flightlog import LOG_NAME, FlightLogWriter, sort_log
from services.foxglove_map import FoxgloveMap, MarkerGrid
from services.runtime import Runtime, main_guard, service_parser

NAME = "recorder"
PARAMS: dict = {}
FLUSH_S = 1.0  # at most this much wall time of messages is lost if the recorder is killed
SKIP = object()  # a key the recorder does not log (its own health, liveliness)
_UNSEEN = object()
MAX_KEYS = 4096  # keys remembered by the per-key lookup; others are looked up per message
# Asked to stop, the recorder keeps receiving until nothing has come for QUIET_STEPS loop periods
# (the other services stop first: what they sent last may still be on its way, a busy machine
# delivering it late), at most DRAIN_MAX_S; then it closes the log.
QUIET_STEPS = 3
DRAIN_MAX_S = 3.0


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS, announce=False)   # alive once it listens: the launcher waits for that
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / LOG_NAME
    sorted_path = path.with_name(path.name + ".sorted")
    sorted_path.unlink(missing_ok=True)   # a rewrite a previous recorder did not finish
    log = FlightLogWriter(path)
    own_health = schemas.HEALTH.key(rt.vehicle_id, NAME)
    live_foxglove = FoxgloveMap(load_vehicle(rt.vehicle_name).motor_positions_m, rt.vehicle_id,
                                MarkerGrid.for_stack(rt.stack), poses=False)   # real time: as messages come
    arrived: deque[tuple[str, bytes]] = deque()   # append/popleft are thread safe
    # per key, what to do with its messages: the message's decode, SKIP, or None (no
    # message defined); looked up once per key, not per message
    decoders: dict[str, Callable[[bytes], dict] | object | None] = {}

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
        arrived.append((str(sample.key_expr), sample.payload.to_bytes()))

    def write_arrived() -> int:
        n = len(arrived)
        for _ in range(n):
            key, payload = arrived.popleft()
            decode = decoders.get(key, _UNSEEN)
            if decode is _UNSEEN:
                decode = decoder_for(key)
            if decode is SKIP:
                continue
            if decode is None:
                rt.reject(key, schemas.SchemaError("malformed", "?", f"no message is defined for key {key}"))
                continue
            try:
                msg = decode(payload)
            except schemas.SchemaError as exc:
                rt.reject(key, exc)
                continue
            log.write(key, msg)
            if not args.lockstep and live_foxglove.wants(key, msg["header"]["t_s"]):
                t_ns = int(round(msg["header"]["t_s"] * 1e9))
                for topic, name, schema_data, data in live_foxglove.encoded(key, msg):
                    log.add(log.channel(topic, name, schema_data, "protobuf", "protobuf"), t_ns, data)
        return n

    stop_asked = [0.0, 0]   # when the stop was asked (monotonic), loop periods since with nothing new

    def ask_stop(*_) -> None:
        if not stop_asked[0]:
            stop_asked[0] = time.monotonic()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, ask_stop)
    next_flush = time.monotonic() + FLUSH_S

    def step(_t: float) -> None:
        nonlocal next_flush
        got = write_arrived()
        if stop_asked[0]:
            stop_asked[1] = 0 if got else stop_asked[1] + 1
            if stop_asked[1] >= QUIET_STEPS or time.monotonic() - stop_asked[0] > DRAIN_MAX_S:
                rt.stop_event.set()
        if time.monotonic() >= next_flush:
            log.flush()
            next_flush = time.monotonic() + FLUSH_S

    rt.subscribe(rt.key("**"), on_sample)
    rt.announce_alive()
    rt.lockstep = False  # the recorder only listens: it keeps wall time for its own health
    rt.rate_hz = 10.0
    try:
        rt.run(step)   # returns on SIGTERM/SIGINT, its session closed
    finally:
        write_arrived()
        log.close()
        summary = (f"wrote {log.count} messages to {path}; rejected {sum(rt.rejected.values())} "
                   f"{json.dumps(rt.rejected, sort_keys=True)}")
        print(f"zenpilot-recorder: {summary}", flush=True)
    if args.lockstep:
        t0 = time.monotonic()
        sorted_foxglove = FoxgloveMap(load_vehicle(rt.vehicle_name).motor_positions_m, rt.vehicle_id,
                                      MarkerGrid.for_stack(rt.stack), poses=False)   # lockstep: from the sorted stream
        n = sort_log(path, sorted_path, derive=sorted_foxglove.encoded_stored)
        os.replace(sorted_path, path)
        print(f"zenpilot-recorder: sorted by sample time: {n} messages ({log.count - n} repeats dropped) "
              f"in {time.monotonic() - t0:.1f} s", flush=True)


def main(argv=None) -> None:
    parser = service_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/latest", help="directory for flight.mcap")
    args = parser.parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
