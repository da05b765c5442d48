"""The recorder's CPU per message, by stage, against the recorder before it was made cheaper.

    python bench/recorder.py [--log runs/bench-realtime/flight.mcap] [--seconds 10] [--rounds 5]

The messages are a flight's: every bus message of --log (its first --seconds), in the log's
order (a real-time log's is the order they arrived in, a lockstep log's sample time), encoded
again with the schemas' encoders into the payloads the bus carried. A real-time log (`python
bench/realtime.py` leaves one in runs/bench-realtime) gives the real-time costs: its times are
wall-clock seconds (JSON of more digits than a lockstep log's) and its order has messages a
little late around each second's start. Each figure is the median over --rounds rounds of
microseconds per message (of all messages, whatever the stage does with each), "old"
(bench/support/recorder_reference.py: the code of zenpilot db0b64d) and "new" (services/recorder.py)
alternating in the same run:

  recorder   FlightRecorder as run() builds it in real time (the live FoxgloveMap, poses=False;
             the fast JSON): receive for each message, step() every 0.1 s of sample time (its
             loop's period), close(); flushed every second of sample time
  lockstep   the same as run() builds it in lockstep (no Foxglove, the exact JSON)
  decode     the strict decode (the same code both ways: its ratio shows the noise)
  json       the JSON text of each decoded message (new: as in real time)
  log        FlightLogWriter.write of each decoded message (JSON, MCAP records, zstd chunks), as
             the real-time recorder's
  foxglove   FoxgloveMap.wants, encoded where it wants, and the records of what it made

The two real-time recorders' logs are compared: the same bus messages (read_log), the same
Foxglove messages (topic, time, bytes) but the static scene's (the new one sends it once per
second where the old one sent it again for each message a little late). Wall-clock figures
depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import schemas  # noqa: E402
from bench.support import recorder_reference as ref  # noqa: E402
from flight.vehicle import load_vehicle  # noqa: E402
from schemas import flightlog  # noqa: E402
from schemas.flightlog import read_log, scan  # noqa: E402
from services import recorder  # noqa: E402
from services.foxglove_map import FoxgloveMap, MarkerGrid  # noqa: E402
from services.stack import load_stack  # noqa: E402

DEFAULT_LOG = "runs/bench-realtime/flight.mcap"
PERIOD_S = 0.1   # the recorder's loop


class BenchIO:
    def __init__(self):
        self.rejected: dict[str, int] = {}

    def reject(self, key: str, exc: schemas.SchemaError) -> None:
        self.rejected[exc.reason] = self.rejected.get(exc.reason, 0) + 1


def flight_messages(path: Path, seconds: float) -> list[tuple[float, str, bytes]]:
    """(sample time, key, payload) of the log's bus messages in the log's order, up to the first
    whose sample time is `seconds` past the first's."""
    rows = []
    for channel, message in scan(path):
        definition = schemas.message_for_key(channel.topic)
        if channel.message_encoding != "json" or definition is None:
            continue
        m = json.loads(message.data)
        h = m["header"]
        if rows and h["t_s"] >= rows[0][0] + seconds:
            break
        values = {k: v for k, v in m.items() if k not in ("version", "header")}
        rows.append((h["t_s"], channel.topic, definition.encode(h["t_s"], h["seq"], h["source"], values)))
    return rows


def batches(rows):
    """The messages in loop periods of sample time (a period ends at the first message past it):
    (period's end, [(key, payload)])."""
    out, end = [], rows[0][0] + PERIOD_S
    current = []
    for t, key, payload in rows:
        while t >= end:
            out.append((end, current))
            current, end = [], end + PERIOD_S
        current.append((key, payload))
    out.append((end, current))
    return out


class Paths:
    """What both recorders need, built once."""

    def __init__(self, rows, tmp: Path):
        stack = load_stack()
        self.rows = rows
        self.tmp = tmp
        self.batches = batches(rows)
        self.motors = load_vehicle(stack.vehicle).motor_positions_m
        self.markers = MarkerGrid.for_stack(stack)
        self.vehicle_id = stack.vehicle_id
        self.decode = {key: schemas.message_for_key(key).decode for _, key, _ in rows}
        self.decoded = [(key, self.decode[key](payload)) for _, key, payload in rows]

    def foxglove(self, which: str) -> FoxgloveMap:
        cls = ref.RefFoxgloveMap if which == "old" else FoxgloveMap
        return cls(self.motors, self.vehicle_id, self.markers, poses=False)

    # -- stages: each returns seconds ------------------------------------------
    def recorder(self, which: str, lockstep: bool = False) -> float:
        now = [self.batches[0][0]]
        path = self.tmp / f"{which}{'-lockstep' if lockstep else ''}.mcap"
        foxglove = None if lockstep else self.foxglove(which)
        if which == "old":
            rec = ref.RefFlightRecorder(BenchIO(), path, self.vehicle_id, foxglove, clock=lambda: now[0])
        else:
            rec = recorder.FlightRecorder(BenchIO(), path, self.vehicle_id, foxglove, clock=lambda: now[0],
                                          exact_json=lockstep)
        t0 = time.perf_counter()
        for end, batch in self.batches:
            now[0] = end
            for key, payload in batch:
                rec.receive(key, payload)
            rec.step()
        rec.close()
        return time.perf_counter() - t0

    def lockstep(self, which: str) -> float:
        return self.recorder(which, lockstep=True)

    def decode_all(self, which: str) -> float:
        decode = self.decode
        t0 = time.perf_counter()
        for _, key, payload in self.rows:
            decode[key](payload)
        return time.perf_counter() - t0

    def json(self, which: str) -> float:
        to_json = ref._to_json if which == "old" else flightlog._to_json
        fast = flightlog._fast_json if which == "new" else None
        t0 = time.perf_counter()
        if fast is not None:
            for _, msg in self.decoded:
                fast(msg)
        else:
            for _, msg in self.decoded:
                to_json(msg).encode()
        return time.perf_counter() - t0

    def _writer(self, which: str, name: str):
        path = self.tmp / f"{name}-{which}.mcap"
        if which == "old":
            return ref.RefFlightLogWriter(path)
        return flightlog.FlightLogWriter(path, zstd_level=flightlog.LIVE_ZSTD_LEVEL, exact_json=False)

    def log(self, which: str) -> float:
        log = self._writer(which, "log")
        t0 = time.perf_counter()
        next_flush = self.decoded[0][1]["header"]["t_s"] + 1.0
        for key, msg in self.decoded:
            log.write(key, msg)
            if msg["header"]["t_s"] >= next_flush:
                log.flush()
                next_flush += 1.0
        log.close()
        return time.perf_counter() - t0

    def foxglove_all(self, which: str) -> float:
        log = self._writer(which, "foxglove")
        fox = self.foxglove(which)
        t0 = time.perf_counter()
        for key, msg in self.decoded:
            t = msg["header"]["t_s"]
            if fox.wants(key, t):
                t_ns = int(round(t * 1e9))
                for topic, name, schema_data, data in fox.encoded(key, msg):
                    log.add(log.channel(topic, name, schema_data, "protobuf", "protobuf"), t_ns, data)
        dt = time.perf_counter() - t0
        log.close()
        return dt


STATIC = ("scene/markers", "scene/vehicle")


def foxglove_records(path: Path) -> tuple[list[tuple[str, int, bytes]], int]:
    """The Foxglove messages (topic, time, bytes) but the static scene's, and how many of those."""
    records = [(c.topic, m.log_time, m.data) for c, m in scan(path) if c.message_encoding == "protobuf"]
    return [r for r in records if not r[0].endswith(STATIC)], sum(r[0].endswith(STATIC) for r in records)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--log", default=DEFAULT_LOG, help=f"a flight log (default {DEFAULT_LOG})")
    ap.add_argument("--seconds", type=float, default=10.0, help="of the flight, from its first message")
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    if args.rounds < 1 or args.seconds <= 0:
        ap.error("--rounds must be >= 1 and --seconds > 0")
    path = Path(args.log)
    if not path.is_file():
        raise SystemExit(f"bench: no flight log at {path}: fly one (python bench/realtime.py leaves "
                         f"{DEFAULT_LOG}; or zenpilot fly --no-plots --out DIR) and pass --log DIR/flight.mcap")
    print("$ python bench/recorder.py " + shlex.join(sys.argv[1:]))
    rows = flight_messages(path, args.seconds)
    span = rows[-1][0] - rows[0][0]
    print(f"{len(rows)} messages over {span:.1f} s of {path} ({len(rows) / max(span, 1e-9):.0f} a second), "
          f"{len({k for _, k, _ in rows})} keys")
    with tempfile.TemporaryDirectory() as tmp:
        paths = Paths(rows, Path(tmp))
        stages = {"recorder": paths.recorder, "lockstep": paths.lockstep, "decode": paths.decode_all,
                  "json": paths.json, "log": paths.log, "foxglove": paths.foxglove_all}
        times = {(s, w): [] for s in stages for w in ("old", "new")}
        for r in range(args.rounds):
            for name, stage in stages.items():
                for which in (("old", "new") if r % 2 == 0 else ("new", "old")):
                    times[name, which].append(stage(which) / len(rows) * 1e6)
        old_log, new_log = Path(tmp) / "old.mcap", Path(tmp) / "new.mcap"
        same_bus = read_log(old_log) == read_log(new_log)
        (old_fox, old_static), (new_fox, new_static) = foxglove_records(old_log), foxglove_records(new_log)
        same_foxglove = old_fox == new_fox
        sizes = old_log.stat().st_size, new_log.stat().st_size
    print(f"\n{'us per message':<16} {'old':>8} {'new':>8} {'new/old':>8}   (median of {args.rounds} rounds)")
    for name in stages:
        old, new = statistics.median(times[name, "old"]), statistics.median(times[name, "new"])
        print(f"{name:<16} {old:>8.2f} {new:>8.2f} {new / old:>8.2f}")
    print(f"\nreal-time logs: the same bus messages: {same_bus}; the same Foxglove messages but the static "
          f"scene's: {same_foxglove}; static scene {old_static // 2} times old, {new_static // 2} new; "
          f"{sizes[0] / 1e6:.2f} MB old, {sizes[1] / 1e6:.2f} MB new")
    print(f"JSON: {'msgspec' if flightlog._fast_json else 'json (msgspec is not installed)'} in real time")
    if not (same_bus and same_foxglove):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
