"""zenpilot-recorder: writes every message of the vehicle to one MCAP flight log.

Subscribes to zp/<vehicle>/** and writes as the flight goes: Zenoh queues each message;
the recorder's loop (10 Hz) decodes each message strictly
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

What it does with each message is FlightRecorder's (no Zenoh: tests/unit/services/test_recorder.py);
run() only subscribes, keeps the loop and the signals, and prints what was written.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Callable

import zenoh

import schemas
from flight.vehicle import load_vehicle
from schemas.flightlog import FAST_JSON, LIVE_ZSTD_LEVEL, LOG_NAME, Derive, FlightLogWriter, sort_log
from services.foxglove_map import FoxgloveMap, MarkerGrid
from services.local_bus import read_frames
from services.runtime import Runtime, main_guard, on_stop_request, service_parser

NAME = "recorder"
PARAMS: dict = {}
FLUSH_S = 1.0  # at most this much wall time of messages is lost if the recorder is killed
SKIP = object()  # a key the recorder does not log (its own health, liveliness)
_UNSEEN = object()
RECEIVE_QUEUE = 1 << 16  # messages waiting for the loop: ~40 s of a flight's traffic
MAX_KEYS = 4096  # keys remembered by the per-key lookup; others are looked up per message
# Asked to stop, the recorder keeps receiving until nothing has come for QUIET_STEPS loop periods
# (the other services stop first: what they sent last may still be on its way, a busy machine
# delivering it late), at most DRAIN_MAX_S; then it closes the log.
QUIET_STEPS = 3
DRAIN_MAX_S = 3.0


class FlightRecorder:
    """The recorder's logic: each message received goes into the flight log, decoded strictly
    (a malformed one, or one on a key no message is defined for, is counted by `io.reject` and
    dropped), the log handed to the OS at least every `flush_s` of `clock` time and closed
    complete by `close`. `io` is the service's Runtime in flight, a fake in the unit tests; no
    Zenoh here. `receive` only queues (safe from another thread); the rest runs on one thread.

    foxglove: real time only, the Foxglove messages made from the bus messages as they come
    (lockstep makes them from the sorted stream instead: `sort`).
    exact_json: the JSON text of Python's json module, which the lockstep log's bytes are made
    of (`sort` copies it); real time writes it faster (FlightLogWriter's exact_json)."""

    def __init__(self, io, path: Path, vehicle_id: int | str, foxglove: FoxgloveMap | None = None,
                 clock: Callable[[], float] = time.monotonic, flush_s: float = FLUSH_S, exact_json: bool = True):
        self.io = io
        self.path = Path(path)
        self.sorted_path = self.path.with_name(self.path.name + ".sorted")
        self.sorted_path.unlink(missing_ok=True)   # a rewrite a previous recorder did not finish
        # the live log's chunks at a faster zstd level: lockstep's file is written again by `sort`
        # (at mcap's level: its bytes do not change), real time's reads back the same
        self.log = FlightLogWriter(self.path, zstd_level=LIVE_ZSTD_LEVEL, exact_json=exact_json)
        self.own_health = schemas.HEALTH.key(vehicle_id, NAME)
        self.foxglove = foxglove
        self.clock = clock
        self.flush_s = flush_s
        self.arrived: deque[tuple[str, bytes]] = deque()   # append/popleft are thread safe
        # per key, what to do with its messages: the message's decode, SKIP, or None (no
        # message defined); looked up once per key, not per message
        self.decoders: dict[str, Callable[[bytes], dict] | object | None] = {}
        self.stop_asked_at: float | None = None   # clock time of the stop request
        self.quiet_steps = 0                      # steps since then with nothing new
        self.next_flush = clock() + flush_s

    def receive(self, key: str, payload: bytes) -> None:
        self.arrived.append((key, payload))

    def _decoder_for(self, key: str):
        if key == self.own_health or "/alive/" in key:
            found = SKIP
        else:
            definition = schemas.message_for_key(key)
            found = None if definition is None else definition.decode
        if len(self.decoders) < MAX_KEYS:  # keys come from the network: bound the cache
            self.decoders[key] = found
        return found

    def write_arrived(self) -> int:
        """Log what has arrived; returns how many messages were taken (logged or not)."""
        arrived, decoders, log, foxglove = self.arrived, self.decoders, self.log, self.foxglove
        write = log.write
        n = len(arrived)
        for _ in range(n):
            key, payload = arrived.popleft()
            decode = decoders.get(key, _UNSEEN)
            if decode is _UNSEEN:
                decode = self._decoder_for(key)
            if decode is SKIP:
                continue
            if decode is None:
                self.io.reject(key, schemas.SchemaError("malformed", "?", f"no message is defined for key {key}"))
                continue
            try:
                msg = decode(payload)
            except schemas.SchemaError as exc:
                self.io.reject(key, exc)
                continue
            write(key, msg)
            if foxglove is not None:
                t_s = msg["header"]["t_s"]
                if foxglove.wants(key, t_s):
                    t_ns = int(round(t_s * 1e9))
                    for topic, name, schema_data, data in foxglove.encoded(key, msg):
                        log.add(log.channel(topic, name, schema_data, "protobuf", "protobuf"), t_ns, data)
        return n

    def ask_stop(self) -> None:
        """A stop was asked (SIGTERM/SIGINT): drain, then `step` says done."""
        if self.stop_asked_at is None:
            self.stop_asked_at = self.clock()

    def step(self) -> bool:
        """One loop period: log what arrived, flush when due. True once asked to stop and
        nothing came for QUIET_STEPS steps, or DRAIN_MAX_S after the request."""
        got = self.write_arrived()
        done = False
        if self.stop_asked_at is not None:
            self.quiet_steps = 0 if got else self.quiet_steps + 1
            done = self.quiet_steps >= QUIET_STEPS or self.clock() - self.stop_asked_at > DRAIN_MAX_S
        if self.clock() >= self.next_flush:
            self.log.flush()
            self.next_flush = self.clock() + self.flush_s
        return done

    def close(self) -> str:
        """Log the rest and write the summary: the log is complete. Returns what was done."""
        self.write_arrived()
        self.log.close()
        rejected = self.io.rejected
        return (f"wrote {self.log.count} messages to {self.path}; rejected {sum(rejected.values())} "
                f"{json.dumps(rejected, sort_keys=True)}")

    def sort(self, derive: Derive | None = None) -> int:
        """Lockstep, after close: rewrite the log in (sample time, key, sequence) order, each
        message once (schemas.flightlog.sort_log), through a temporary file that replaces it
        when done. Returns the messages kept."""
        n = sort_log(self.path, self.sorted_path, derive=derive)
        os.replace(self.sorted_path, self.path)
        return n


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS, announce=False)   # alive once it listens: the launcher waits for that
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    motors = load_vehicle(rt.vehicle_name).motor_positions_m
    live_foxglove = None if args.lockstep else FoxgloveMap(motors, rt.vehicle_id, MarkerGrid.for_stack(rt.stack),
                                                            poses=False)
    rec = FlightRecorder(rt, out_dir / LOG_NAME, rt.vehicle_id, live_foxglove, exact_json=args.lockstep)
    if not args.lockstep and not FAST_JSON:
        print("zenpilot-recorder: msgspec is not installed: the log's JSON by Python's json module, "
              "its largest cost in real time (pip install msgspec)", flush=True)

    if args.stdin:   # a one-process lockstep's messages, on this process's own core
        def read_input() -> None:
            for key, payload in read_frames(sys.stdin.buffer):
                rec.receive(key, payload)
            rec.ask_stop()   # the stream's end: the flight is over

        threading.Thread(target=read_input, name="input", daemon=True).start()

        def take_arrived() -> None:
            pass
    else:
        # Zenoh queues every message; the loop takes them. Its receiving thread then never waits
        # for the GIL (a callback per message did, ~1,500 a second); a full queue holds Zenoh
        # back, it does not drop.
        subscriber = rt.session.declare_subscriber(rt.key("**"), zenoh.handlers.FifoChannel(RECEIVE_QUEUE))
        channel = subscriber.handler

        def take_arrived() -> None:
            try:
                while (sample := channel.try_recv()) is not None:
                    rec.receive(str(sample.key_expr), sample.payload.to_bytes())
            except zenoh.ZError:   # the session closed and the queue is empty
                pass

    on_stop_request(rec.ask_stop)

    def step(_t: float) -> None:
        take_arrived()
        if rec.step():
            rt.stop_event.set()

    rt.announce_alive()
    rt.lockstep = False  # the recorder only listens: it keeps wall time for its own health
    rt.rate_hz = 10.0
    try:
        rt.run(step)   # returns on SIGTERM/SIGINT, its session closed
    finally:
        take_arrived()   # what came before the session closed
        print(f"zenpilot-recorder: {rec.close()}", flush=True)
    if args.lockstep:
        t0 = time.monotonic()
        sorted_foxglove = FoxgloveMap(motors, rt.vehicle_id, MarkerGrid.for_stack(rt.stack),
                                      poses=False)   # lockstep: from the sorted stream
        n = rec.sort(derive=sorted_foxglove.encoded_stored)
        print(f"zenpilot-recorder: sorted by sample time: {n} messages ({rec.log.count - n} repeats dropped) "
              f"in {time.monotonic() - t0:.1f} s", flush=True)


def main(argv=None) -> None:
    parser = service_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/latest", help="directory for flight.mcap")
    parser.add_argument("--stdin", action="store_true",
                        help="take the messages from standard input, framed as services/local_bus.py writes them "
                             "(a one-process lockstep's recorder), not from Zenoh; their end stops it")
    args = parser.parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
