"""Cost of the Foxglove view per message (ground side: `zenpilot view`, the recorder's well-known channels).

    python bench/foxglove_view.py LOG [--repeat 3]

Replays the messages of a flight log (LOG: a flight.mcap) through each step the live view
(deploy/view.py) does for a message a client listens to, timed per message kind:

  decode     schemas' strict msgpack decode (the payload re-encoded from the log first)
  json       json.dumps of the decoded message (the raw JSON channel)
  convert    FoxgloveMap.convert (services/foxglove_map.py): the well-known messages it makes
  encode     .encode() of those well-known messages (protobuf, what the SDK sends)

and prints microseconds per message (median over --repeat passes) with each kind's rate in
the log, then the CPU share of one core the whole stream costs at those rates. Then the
lockstep recorder's end-of-flight rewrite (schemas.flightlog.sort_log) of the log's bus
channels, without and with the well-known channels made from them (FoxgloveMap.encoded_stored). Wall-clock
figures depend on the machine and its load (other processes on a shared machine inflate them).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import schemas  # noqa: E402
from flight.vehicle import load_vehicle  # noqa: E402
from schemas.flightlog import FlightLogWriter, LogScan, read_log, scan, sort_log  # noqa: E402
from services.foxglove_map import FoxgloveMap, MarkerGrid  # noqa: E402

SKIP = ("/sim/clock/", "/sync/")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("log", help="a flight.mcap")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--vehicle", default="x250")
    args = p.parse_args()
    log = {k: v for k, v in read_log(args.log).items() if not any(s in k for s in SKIP)}
    stream = sorted(((m["header"]["t_s"], k, m) for k, msgs in log.items() for m in msgs), key=lambda r: r[0])
    duration = stream[-1][0] - stream[0][0]
    kinds = sorted({_kind(k) for _, k, _ in stream})
    payloads = []
    for _, key, msg in stream:
        d = schemas.message_for_key(key)
        values = {f.name: msg[f.name] for f in d.fields}
        payloads.append((key, d, d.encode(msg["header"]["t_s"], msg["header"]["seq"], msg["header"]["source"], values)))
    motors = load_vehicle(args.vehicle).motor_positions_m
    per = {k: {"decode": [], "json": [], "convert": [], "encode": []} for k in kinds}
    for _ in range(args.repeat):
        totals = {k: {s: 0.0 for s in ("decode", "json", "convert", "encode")} for k in kinds}
        fmap = FoxgloveMap(motors, 0, MarkerGrid())
        clock = time.perf_counter
        for key, d, payload in payloads:
            kind = _kind(key)
            t0 = clock()
            msg = d.decode(payload)
            t1 = clock()
            json.dumps(msg, separators=(",", ":")).encode()
            t2 = clock()
            out = fmap.convert(key, msg)
            t3 = clock()
            for _, m in out:
                m.encode()
            t4 = clock()
            tot = totals[kind]
            tot["decode"] += t1 - t0
            tot["json"] += t2 - t1
            tot["convert"] += t3 - t2
            tot["encode"] += t4 - t3
        counts = {k: 0 for k in kinds}
        for key, _, _ in payloads:
            counts[_kind(key)] += 1
        for k in kinds:
            for s, v in totals[k].items():
                per[k][s].append(v / counts[k] * 1e6)
    print(f"{len(payloads)} messages over {duration:.1f} s of flight ({args.log}); us per message, "
          f"median of {args.repeat}")
    print(f"{'kind':<22} {'rate Hz':>8} {'decode':>8} {'json':>8} {'convert':>8} {'encode':>8} {'total':>8} {'cpu %':>6}")
    share = 0.0
    for k in kinds:
        rate = counts[k] / duration
        med = {s: statistics.median(v) for s, v in per[k].items()}
        total = sum(med.values())
        share += rate * total * 1e-6
        print(f"{k:<22} {rate:8.1f} {med['decode']:8.1f} {med['json']:8.1f} {med['convert']:8.1f} "
              f"{med['encode']:8.1f} {total:8.1f} {100 * rate * total * 1e-6:6.2f}")
    print(f"all messages: {100 * share:.1f} % of one core at the log's rates (target: ground side, < 25 %)")
    sort_cost(args.log, motors, args.repeat)


def sort_cost(log_path: str, motors, repeat: int) -> None:
    """sort_log of the bus channels alone, without and with the derived well-known channels."""
    with tempfile.TemporaryDirectory() as tmp:
        bus = Path(tmp) / "bus.mcap"
        found = LogScan(Path(log_path))
        out = FlightLogWriter(bus)
        for ch, m in scan(log_path, found):
            if ch.message_encoding == "json":
                s = found.schemas[ch.schema_id]
                out.add(out.channel(ch.topic, s.name, s.data, ch.message_encoding, s.encoding, ch.metadata),
                        m.log_time, m.data, m.sequence)
        out.close()
        times = {}
        for name in ("bus only", "with well-known"):
            runs = []
            for _ in range(repeat):
                derive = (FoxgloveMap(motors, 0, MarkerGrid(), poses=False).encoded_stored   # as the recorder
                          if name != "bus only" else None)
                t0 = time.perf_counter()
                sort_log(bus, Path(tmp) / "sorted.mcap", derive=derive)
                runs.append(time.perf_counter() - t0)
            times[name] = statistics.median(runs)
            size = (Path(tmp) / "sorted.mcap").stat().st_size
            print(f"sort_log, {name:<16}: {times[name]:.2f} s, {size / 1e6:.2f} MB")
        print(f"the well-known channels add {times['with well-known'] - times['bus only']:.2f} s to the rewrite")


def _kind(key: str) -> str:
    parts = key.split("/", 2)[2]
    return "*/health" if parts.endswith("/health") else parts


if __name__ == "__main__":
    main()
