# The recorder's path per message as of zenpilot db0b64d, verbatim (services/recorder.py's
# FlightRecorder, schemas/flightlog.py's FlightLogWriter on mcap.writer.Writer, the methods of
# services/foxglove_map.py's FoxgloveMap that changed since): the baseline bench/recorder.py
# times the recorder against. Not used in flight.
from __future__ import annotations

import json
import time
from collections import deque
from pathlib import Path
from typing import Callable

from mcap.writer import CompressionType, Writer

import schemas
from schemas.flightlog import CHUNK_BYTES, json_schema
from services.foxglove_map import FoxgloveMap

NAME = "recorder"
FLUSH_S = 1.0
SKIP = object()
_UNSEEN = object()
MAX_KEYS = 4096
QUIET_STEPS = 3
DRAIN_MAX_S = 3.0

_to_json = json.JSONEncoder(separators=(",", ":"), check_circular=False, allow_nan=False).encode


class RefFoxgloveMap(FoxgloveMap):
    def convert(self, key: str, msg: dict) -> list[tuple[str, object]]:
        """(topic, well-known message) pairs for one decoded message; [] when it makes none."""
        if not key.startswith(self.prefix):
            return []
        handler = self._handlers.get(key[len(self.prefix):])
        t = msg["header"]["t_s"]
        out = self._static(t) if self._static_second != int(t) else []
        if handler is not None:
            handler(t, msg, out)
        return out

    def wants(self, key: str, t_s: float) -> bool:
        """Whether convert(key, msg) at sample time t_s can make anything: a reader of stored
        messages decodes only those."""
        handled = self._handled.get(key)
        if handled is None:
            handled = key.startswith(self.prefix) and key[len(self.prefix):] in self._handlers
            if len(self._handled) < 4096:   # keys come from the network: bound what is remembered
                self._handled[key] = handled
        return handled or self._static_second != int(t_s)


class RefFlightLogWriter:
    def __init__(self, path: str | Path, chunk_bytes: int = CHUNK_BYTES):
        self.path = Path(path)
        self._fh = open(self.path, "wb")
        self._writer = Writer(self._fh, chunk_size=chunk_bytes, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="zenpilot")
        self._fh.flush()   # from now on the file is an MCAP file, whatever happens to the writer
        self._schema_ids: dict[tuple[str, str, bytes], int] = {}
        self._channel_ids: dict[str, int] = {}   # topic -> channel id
        self.count = 0

    def channel(self, topic: str, schema_name: str, schema_data: bytes, message_encoding: str = "json",
                schema_encoding: str = "jsonschema", metadata: dict[str, str] | None = None) -> int:
        """The id of the channel `topic`, registered (with its schema) on first use."""
        cid = self._channel_ids.get(topic)
        if cid is None:
            skey = (schema_name, schema_encoding, schema_data)
            sid = self._schema_ids.get(skey)
            if sid is None:
                sid = self._schema_ids[skey] = self._writer.register_schema(schema_name, schema_encoding, schema_data)
            cid = self._channel_ids[topic] = self._writer.register_channel(topic, message_encoding, sid, metadata or {})
        return cid

    def add(self, channel_id: int, t_ns: int, data: bytes, sequence: int = 0, publish_ns: int | None = None) -> None:
        self._writer.add_message(channel_id, t_ns, data, t_ns if publish_ns is None else publish_ns, sequence)
        self.count += 1

    def write(self, key: str, msg: dict) -> bool:
        """One decoded message of the bus (header included) on its key's channel, as JSON.
        False (nothing written) for a key no message is defined for."""
        cid = self._channel_ids.get(key)
        if cid is None:
            definition = schemas.message_for_key(key)
            if definition is None:
                return False
            cid = self.channel(key, definition.name, json.dumps(json_schema(definition)).encode())
        header = msg["header"]
        t_ns = int(round(header["t_s"] * 1e9))
        self._writer.add_message(cid, t_ns, _to_json(msg).encode(), t_ns, header["seq"] & 0xFFFFFFFF)
        self.count += 1
        return True

    def flush(self) -> None:
        self._writer.flush()

    def close(self) -> None:
        """Write the summary and close the file."""
        self._writer.finish()
        self._fh.close()


class RefFlightRecorder:
    def __init__(self, io, path: Path, vehicle_id: int | str, foxglove: FoxgloveMap | None = None,
                 clock: Callable[[], float] = time.monotonic, flush_s: float = FLUSH_S):
        self.io = io
        self.path = Path(path)
        self.sorted_path = self.path.with_name(self.path.name + ".sorted")
        self.sorted_path.unlink(missing_ok=True)   # a rewrite a previous recorder did not finish
        self.log = RefFlightLogWriter(self.path)
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
            log.write(key, msg)
            if foxglove is not None and foxglove.wants(key, msg["header"]["t_s"]):
                t_ns = int(round(msg["header"]["t_s"] * 1e9))
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
