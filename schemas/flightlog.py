"""The flight log: every message of a flight in one MCAP file.

Messages are stored as JSON (the decoded MessagePack map, header included)
with a JSON Schema per message, so Foxglove and the `mcap` CLI open the log
as it is. log_time and publish_time are the header's sample time in ns.

The recorder writes the log as the flight goes (FlightLogWriter): messages go
into compressed chunks, a chunk is handed to the OS at least every second, and
the summary (the index) is written at the end. A recorder killed before the end
leaves a file without summary whose written chunks are readable: read_log reads
them (LogScan says where the file was cut) and recover() copies them into a
complete, indexed file.
"""

from __future__ import annotations

import heapq
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator

from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Footer, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

import schemas
from schemas.mcap_writer import ZSTD_LEVEL, McapWriter

LOG_NAME = "flight.mcap"
# A chunk is closed when it reaches this many bytes (uncompressed) or when the writer is
# flushed (the recorder: every second), whichever comes first.
CHUNK_BYTES = 1 << 20
# zstd level of a log written as the flight goes: half level 3's time per chunk (2.5 against
# 4.9 ms for a second of a real-time hover's messages, 840 KB), and as small (4.8:1 against 4.6:1)
LIVE_ZSTD_LEVEL = 1

_JSON_TYPES = {"float": "number", "int": "integer", "bool": "boolean", "str": "string"}
# allow_nan=False: the codec never lets a NaN through; if one ever came, fail loudly, not write it
_to_json = json.JSONEncoder(separators=(",", ":"), check_circular=False, allow_nan=False).encode
try:
    import msgspec
    # ~5x the stdlib's speed on a real-time flight's messages (floats of 17 digits: their text is
    # most of the time); the same values, some numbers spelled otherwise (1e-7 for 1e-07)
    _fast_json = msgspec.json.Encoder().encode
except ImportError:   # an environment installed before it was a dependency
    _fast_json = None
FAST_JSON = _fast_json is not None   # exact_json=False writes faster than the stdlib


def _exact_json(msg: dict) -> bytes:
    return _to_json(msg).encode()


def json_schema(message: schemas.Message) -> dict:
    def prop(f: schemas.Field) -> dict:
        if f.kind == "counts":
            p = {"type": "object", "additionalProperties": {"type": "integer"}}
        elif f.kind == "bytes":   # not logged (camera_image's key is outside zp/<vehicle>/**); JSON has no bytes
            p = {"type": "string", "contentEncoding": "base64"}
        elif f.kind.endswith("[]"):
            p = {"type": "array", "items": {"type": _JSON_TYPES[f.kind[:-2]]}}
        else:
            p = {"type": _JSON_TYPES[f.kind]}
        p["description"] = f.doc + (f" [{f.unit}]" if f.unit else "")
        return p

    header = {"type": "object", "properties": {f.name: prop(f) for f in schemas.core.HEADER_FIELDS}}
    return {
        "title": message.name,
        "description": message.doc,
        "type": "object",
        "properties": {"version": {"type": "integer"}, "header": header, **{f.name: prop(f) for f in message.fields}},
    }


class FlightLogWriter:
    """An MCAP flight log written as the flight goes.

    write(key, msg) adds one decoded bus message on the channel of its key; flush() closes
    the chunk in progress and hands it to the OS (a process killed after it leaves that
    chunk readable); close() writes the summary, which makes the file complete and indexed.
    Other channels (another encoding, another schema) go through channel() and add()."""

    def __init__(self, path: str | Path, chunk_bytes: int = CHUNK_BYTES, zstd_level: int = ZSTD_LEVEL,
                 exact_json: bool = True):
        """zstd_level: the default gives mcap.writer.Writer's bytes (the lockstep log's); the
        recorder writes its live log faster (LIVE_ZSTD_LEVEL).
        exact_json: the bus messages' JSON as Python's json module writes it, which a lockstep
        log's bytes are; False: msgspec's (when installed), the same values, written faster
        (the real-time recorder: messages are validated, so never a NaN, which it would write
        as null)."""
        self.path = Path(path)
        self._json = _exact_json if exact_json or _fast_json is None else _fast_json
        self._fh = open(self.path, "wb")
        self._writer = McapWriter(self._fh, chunk_size=chunk_bytes, zstd_level=zstd_level)
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
        self._writer.add_message(cid, t_ns, self._json(msg), t_ns, header["seq"] & 0xFFFFFFFF)
        self.count += 1
        return True

    def flush(self) -> None:
        self._writer.flush()

    def close(self) -> None:
        """Write the summary and close the file."""
        self._writer.finish()
        self._fh.close()


class LogError(ValueError):
    """A file that is not a flight log that cannot be used as asked (no MCAP magic, empty; cut where a summary is needed)."""


def write_log(path: str | Path, records: Iterable[tuple[str, dict]]) -> int:
    """Write (key, decoded message) records in the given order; returns the count."""
    log = FlightLogWriter(path)
    for key, msg in records:
        log.write(key, msg)
    log.close()
    return log.count


Derive = Callable[[str, int, bytes], Iterable[tuple[str, str, bytes, bytes]]]


def sort_log(src: str | Path, dst: str | Path, derive: Derive | None = None) -> int:
    """Copy a complete log in (sample time, key, sequence) order, each message once; returns
    how many were copied.

    derive(topic, log_time_ns, data), if given, is called for each message copied, in that
    order, and what it returns, (topic, schema name, schema data, message) as protobuf, is
    written beside it at the same time (the recorder's Foxglove well-known channels: made
    from the sorted stream, they are as deterministic as it is).

    The recorder's lockstep logs: arrival order across senders depends on the machine, sample
    time does not; a message sent again until answered (the lockstep "ready") is kept once.
    A merge through the chunk index: chunks are read in order of their first sample time and a
    message is written once no chunk still unread can hold an earlier one, so only the chunks
    that overlap in time are in memory at once."""
    out = FlightLogWriter(dst)
    with open(src, "rb") as fh:
        try:
            summary = make_reader(fh).get_summary()
        except Exception:   # a cut file: the footer's place holds whatever was being written
            summary = None
        if summary is None:
            raise LogError(f"{src}: no summary (a cut log: `zenpilot log recover` it first)")
        out_ids: dict[int, int] = {}   # the source's channel id -> ours, in order of first use

        def out_channel(cid: int) -> int:
            if cid not in out_ids:
                channel = summary.channels[cid]
                schema = summary.schemas.get(channel.schema_id)
                out_ids[cid] = out.channel(channel.topic, schema.name if schema else "",
                                           schema.data if schema else b"", channel.message_encoding,
                                           schema.encoding if schema else "", channel.metadata)
            return out_ids[cid]

        # (t, topic, seq, data, publish time, channel): a total order on what is written
        heap: list[tuple[int, str, int, bytes, int, int]] = []
        previous = None
        copied = [0]

        def emit_before(t_ns: float) -> None:
            nonlocal previous
            while heap and heap[0][0] < t_ns:
                row = heapq.heappop(heap)
                if row[:4] != previous:   # a repeat: same sample time, key, sequence and bytes
                    previous = row[:4]
                    out.add(out_channel(row[5]), row[0], row[3], row[2], row[4])
                    copied[0] += 1
                    if derive is not None:
                        for topic, name, schema_data, data in derive(row[1], row[0], row[3]):
                            out.add(out.channel(topic, name, schema_data, "protobuf", "protobuf"), row[0], data)

        for index in sorted(summary.chunk_indexes, key=lambda c: (c.message_start_time, c.chunk_start_offset)):
            emit_before(index.message_start_time)
            fh.seek(index.chunk_start_offset + 1 + 8)   # past the record's opcode and length
            for record in breakup_chunk(Chunk.read(ReadDataStream(fh)), validate_crc=True):
                if isinstance(record, Message):
                    topic = summary.channels[record.channel_id].topic
                    heapq.heappush(heap, (record.log_time, topic, record.sequence, record.data,
                                          record.publish_time, record.channel_id))
        emit_before(float("inf"))
    out.close()
    return copied[0]


# ---------------------------------------------------------------- reading, also cut files
@dataclass
class LogScan:
    """What reading a log found: complete (it has its summary) or cut after `readable_bytes`
    of `size_bytes` (the rest, a chunk being written when the writer stopped, is unreadable)."""
    path: Path
    complete: bool = False
    size_bytes: int = 0
    readable_bytes: int = 0
    chunks: int = 0
    messages: int = 0
    problem: str = ""
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)

    def describe(self) -> str:
        if self.complete:
            return f"{self.path}: complete, {self.messages} messages in {self.chunks} chunks"
        lost = self.size_bytes - self.readable_bytes
        return (f"{self.path}: cut (no summary: the writer did not finish it); {self.messages} messages "
                f"in {self.chunks} readable chunks, " + (f"{lost} bytes at the end unreadable ({self.problem})"
                                                         if lost else "nothing after them"))


def scan(path: str | Path, scan_result: LogScan | None = None) -> Iterator[tuple[Channel, Message]]:
    """Every readable message of an MCAP file in file order, complete or cut: the records are
    read one by one with the mcap library's stream reader, each chunk whole (its CRC checked)
    or not at all; reading stops at the first record that cannot be read. `scan_result` (a
    LogScan) is filled in as it goes."""
    path = Path(path)
    found = scan_result if scan_result is not None else LogScan(path)
    found.size_bytes = path.stat().st_size
    with open(path, "rb") as fh:
        if fh.read(8) != b"\x89MCAP0\r\n":
            raise LogError(f"{path}: not an MCAP file ({found.size_bytes} bytes"
                           f"{', empty' if found.size_bytes == 0 else ''})")
        fh.seek(0)
        records = StreamReader(fh, emit_chunks=True, validate_crcs=False,
                               record_size_limit=max(found.size_bytes, 1)).records
        found.readable_bytes = 8
        while True:
            try:
                record = next(records)
                inner = breakup_chunk(record, validate_crc=True) if isinstance(record, Chunk) else [record]
            except StopIteration:
                break
            except Exception as exc:  # the cut: EndOfFile, a bad length, a short chunk (CRC, zstd)
                found.problem = f"{type(exc).__name__}: {exc}"[:200]
                break
            found.readable_bytes = fh.tell()
            if isinstance(record, Chunk):
                found.chunks += 1
            for r in inner:
                if isinstance(r, Schema):
                    found.schemas[r.id] = r
                elif isinstance(r, Channel):
                    found.channels[r.id] = r
                elif isinstance(r, Message) and r.channel_id in found.channels:
                    found.messages += 1
                    yield found.channels[r.channel_id], r
            if isinstance(record, Footer):
                found.complete = True   # the summary is there too: the file is indexed
    if found.complete:
        found.readable_bytes = found.size_bytes
        found.problem = ""


def read_log(path: str | Path, scan_result: LogScan | None = None) -> dict[str, list[dict]]:
    """All bus messages (the JSON channels) by key expression, in file order. A cut file gives
    the messages of its readable chunks (pass a LogScan to learn whether it was cut). The
    Foxglove well-known channels (protobuf, derived from these) are left out."""
    out: dict[str, list[dict]] = {}
    for channel, message in scan(path, scan_result):
        if channel.message_encoding == "json":
            out.setdefault(channel.topic, []).append(json.loads(message.data))
    return out


def recover(src: str | Path, dst: str | Path) -> LogScan:
    """Copy the readable chunks of a (cut) log into a complete, indexed log at `dst`."""
    found = LogScan(Path(src))
    out = FlightLogWriter(Path(str(dst) + ".part"))
    try:
        for channel, message in scan(src, found):
            schema = found.schemas.get(channel.schema_id)
            cid = out.channel(channel.topic, schema.name if schema else "", schema.data if schema else b"",
                              channel.message_encoding, schema.encoding if schema else "", channel.metadata)
            out.add(cid, message.log_time, message.data, message.sequence, message.publish_time)
        out.close()
    except BaseException:
        out._fh.close()
        os.unlink(out.path)
        raise
    os.replace(out.path, dst)
    return found


def log_is_complete(path: str | Path) -> bool:
    """The file ends with its summary (read from the footer, not the whole file)."""
    try:
        with open(path, "rb") as fh:
            return make_reader(fh).get_summary() is not None
    except Exception:   # a cut file: the footer's place holds whatever was being written
        return False
