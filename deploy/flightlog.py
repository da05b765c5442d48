"""The flight log: every message of a flight in one MCAP file.

Messages are stored as JSON (the decoded MessagePack map, header included)
with a JSON Schema per message, so Foxglove and the `mcap` CLI open the log
as it is. log_time and publish_time are the header's sample time in ns.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

import schemas

LOG_NAME = "flight.mcap"

_JSON_TYPES = {"float": "number", "int": "integer", "bool": "boolean", "str": "string"}


def json_schema(message: schemas.Message) -> dict:
    def prop(f: schemas.Field) -> dict:
        if f.kind == "counts":
            p = {"type": "object", "additionalProperties": {"type": "integer"}}
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


def write_log(path: str | Path, records: Iterable[tuple[str, dict]]) -> int:
    """Write (key, decoded message) records in the given order; returns the count."""
    n = 0
    with open(path, "wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD)
        writer.start(profile="", library="zenpilot")
        schema_ids: dict[str, int] = {}
        channel_ids: dict[str, int] = {}
        for key, msg in records:
            definition = schemas.message_for_key(key)
            if definition is None:
                continue
            if key not in channel_ids:
                if definition.name not in schema_ids:
                    schema_ids[definition.name] = writer.register_schema(
                        definition.name, "jsonschema", json.dumps(json_schema(definition)).encode())
                channel_ids[key] = writer.register_channel(key, "json", schema_ids[definition.name])
            t_ns = int(round(msg["header"]["t_s"] * 1e9))
            data = json.dumps(msg, separators=(",", ":")).encode()
            writer.add_message(channel_ids[key], t_ns, data, t_ns, msg["header"]["seq"] & 0xFFFFFFFF)
            n += 1
        writer.finish()
    return n


def read_log(path: str | Path) -> dict[str, list[dict]]:
    """All messages by key expression, in file order."""
    out: dict[str, list[dict]] = {}
    with open(path, "rb") as fh:
        for _schema, channel, message in make_reader(fh).iter_messages(log_time_order=False):
            out.setdefault(channel.topic, []).append(json.loads(message.data))
    return out
