"""Message definitions and the strict MessagePack codec.

A message on the wire is one MessagePack map:

    {"version": int, "header": {"t_s": float, "seq": int, "source": str}, <fields>...}

`header.t_s` is the *sample* time of what the message describes (the IMU
sample, the camera exposure, the control computation), in the stack's clock:
wall time (Unix seconds) in real-time mode, simulated seconds in lockstep.
Delay compensation and latency metrics work from it, never from arrival time.

Decoding is strict: anything that does not match the definition raises one
`SchemaError` whose `reason` is one of `REASONS`, so receivers can count
rejected messages per reason and drop them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import msgpack

REASONS = (
    "malformed",  # not MessagePack, or not a map
    "wrong_version",
    "missing_field",
    "unknown_field",
    "wrong_type",
    "wrong_length",
    "non_finite",
    "out_of_range",
)

# Field kinds. Arrays are MessagePack arrays; "counts" is a map str -> int >= 0.
KINDS = ("float", "int", "bool", "str", "float[]", "int[]", "str[]", "counts")  # counts: map str -> int >= min (0)


class SchemaError(ValueError):
    """A message that does not match its definition."""

    def __init__(self, reason: str, message: str, detail: str):
        assert reason in REASONS, reason
        self.reason = reason
        self.message = message
        self.detail = detail
        super().__init__(f"{message}: {reason}: {detail}")


@dataclass(frozen=True)
class Field:
    name: str
    kind: str
    doc: str
    unit: str = ""
    length: int | None = None  # fixed length for arrays
    min: float | None = None
    max: float | None = None
    choices: tuple[str, ...] | None = None  # allowed values of a "str" field

    def __post_init__(self):
        assert self.kind in KINDS, self.kind


@dataclass(frozen=True)
class Message:
    name: str
    topic: str  # key expression below zp/<vehicle>/; "{service}" is filled per sender
    version: int
    doc: str
    fields: tuple[Field, ...]
    check: Callable[[dict], str | None] | None = None  # cross-field check -> error detail
    _by_name: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self):
        self._by_name.update({f.name: f for f in self.fields})

    def key(self, vehicle: int | str = 0, service: str | None = None) -> str:
        topic = self.topic.format(service=service) if "{service}" in self.topic else self.topic
        return f"zp/{vehicle}/{topic}"

    # -- encoding -------------------------------------------------------
    def encode(self, t_s: float, seq: int, source: str, values: dict[str, Any]) -> bytes:
        """Validate `values` and pack them; invalid values raise SchemaError
        on the sender's side, so a NaN is never put on the wire."""
        doc = {"version": self.version, "header": {"t_s": float(t_s), "seq": int(seq), "source": source}}
        for f in self.fields:
            if f.name not in values:
                raise SchemaError("missing_field", self.name, f.name)
            doc[f.name] = _plain(values[f.name])
        extra = set(values) - set(self._by_name)
        if extra:
            raise SchemaError("unknown_field", self.name, ", ".join(sorted(extra)))
        self.validate(doc)
        return msgpack.packb(doc, use_bin_type=True)

    # -- decoding -------------------------------------------------------
    def decode(self, payload: bytes) -> dict:
        """Unpack and validate; returns the map (header included)."""
        try:
            doc = msgpack.unpackb(payload, raw=False, strict_map_key=True)
        except Exception as exc:  # msgpack raises several unrelated types
            raise SchemaError("malformed", self.name, f"not MessagePack ({type(exc).__name__})") from None
        self.validate(doc)
        return doc

    def validate(self, doc: Any) -> None:
        if not isinstance(doc, dict):
            raise SchemaError("malformed", self.name, f"expected a map, got {type(doc).__name__}")
        version = doc.get("version")
        if version is None:
            raise SchemaError("missing_field", self.name, "version")
        if version != self.version:
            raise SchemaError("wrong_version", self.name, f"got {version!r}, expected {self.version}")
        _check_header(self.name, doc.get("header"))
        for f in self.fields:
            if f.name not in doc:
                raise SchemaError("missing_field", self.name, f.name)
            _check_field(self.name, f, doc[f.name])
        if len(doc) != len(self.fields) + 2:
            extra = set(doc) - set(self._by_name) - {"version", "header"}
            raise SchemaError("unknown_field", self.name, ", ".join(sorted(map(str, extra))))
        if self.check is not None:
            problem = self.check(doc)
            if problem:
                raise SchemaError("wrong_length", self.name, problem)


HEADER_FIELDS = (
    Field("t_s", "float", "sample time of what the message describes", "s", min=0.0),
    Field("seq", "int", "sequence number per sender and key, from 0", min=0),
    Field("source", "str", "name of the sending service"),
)


def _check_header(message: str, header: Any) -> None:
    if header is None:
        raise SchemaError("missing_field", message, "header")
    if not isinstance(header, dict):
        raise SchemaError("wrong_type", message, "header is not a map")
    for f in HEADER_FIELDS:
        if f.name not in header:
            raise SchemaError("missing_field", message, f"header.{f.name}")
        _check_field(message, f, header[f.name], prefix="header.")
    if len(header) != len(HEADER_FIELDS):
        raise SchemaError("unknown_field", message, "header has extra keys")


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _check_scalar(message: str, f: Field, v: Any, where: str) -> None:
    kind = f.kind.rstrip("[]")
    if kind == "float":
        if not _is_number(v):
            raise SchemaError("wrong_type", message, f"{where} must be a number, got {type(v).__name__}")
        if isinstance(v, float) and not math.isfinite(v):
            raise SchemaError("non_finite", message, f"{where} is {v}")
    elif kind == "int":
        if not isinstance(v, int) or isinstance(v, bool):
            raise SchemaError("wrong_type", message, f"{where} must be an integer, got {type(v).__name__}")
    elif kind == "bool":
        if not isinstance(v, bool):
            raise SchemaError("wrong_type", message, f"{where} must be a boolean, got {type(v).__name__}")
    elif kind == "str":
        if not isinstance(v, str):
            raise SchemaError("wrong_type", message, f"{where} must be a string, got {type(v).__name__}")
        if f.choices is not None and v not in f.choices:
            raise SchemaError("out_of_range", message, f"{where}={v!r} not one of {list(f.choices)}")
        return
    if kind in ("float", "int"):
        if (f.min is not None and v < f.min) or (f.max is not None and v > f.max):
            raise SchemaError("out_of_range", message, f"{where}={v} outside [{f.min}, {f.max}]")


def _check_field(message: str, f: Field, v: Any, prefix: str = "") -> None:
    where = prefix + f.name
    if f.kind.endswith("[]"):
        if not isinstance(v, list):
            raise SchemaError("wrong_type", message, f"{where} must be an array, got {type(v).__name__}")
        if f.length is not None and len(v) != f.length:
            raise SchemaError("wrong_length", message, f"{where} has {len(v)} items, expected {f.length}")
        for i, item in enumerate(v):
            _check_scalar(message, f, item, f"{where}[{i}]")
    elif f.kind == "counts":
        if not isinstance(v, dict):
            raise SchemaError("wrong_type", message, f"{where} must be a map")
        lo = 0 if f.min is None else f.min
        for k, n in v.items():
            if not isinstance(k, str) or not isinstance(n, int) or isinstance(n, bool):
                raise SchemaError("wrong_type", message, f"{where} must map strings to integers")
            if n < lo:
                raise SchemaError("out_of_range", message, f"{where}[{k!r}]={n} below {lo}")
    else:
        _check_scalar(message, f, v, where)


def _plain(v: Any) -> Any:
    """numpy scalars/arrays -> plain Python values that msgpack packs."""
    if hasattr(v, "tolist"):
        return v.tolist()
    if isinstance(v, tuple):
        return [_plain(x) for x in v]
    if isinstance(v, list):
        return [x.item() if hasattr(x, "item") else x for x in v]
    return v
