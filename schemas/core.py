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

How it is fast: each `Message` compiles its definition once, at construction,
into specialised encode/decode/validate functions (`_compile`) that do only
the cheap exact checks a valid message needs. They decide nothing about a bad
message: whenever one of their checks fails they hand the message to the
reference path (`_validate_reference`, `_encode_reference`: the generic
validator walking the Field definitions), which finds the reason and the
detail text. So the compiled path may only ever accept what the reference
path accepts; every reason and message text comes from the reference path.

Decoding a payload in the project's own layout (as `encode` writes it) is one call to msgspec
with a typed definition of the message (`_typed_decoder`), which makes the same checks in C;
anything else is unpacked, then checked by the compiled Python checks. msgspec packs and
unpacks on the compiled path, msgpack everywhere else: a map the compiled checks pass holds
only plain types, which msgspec packs to msgpack's bytes (or refuses: msgpack packs it then), and a
payload msgspec unpacks into a map the checks pass, msgpack unpacks into the
same map. Anything else (msgspec refuses it, or a check fails) is decoded
again by msgpack, so the reasons and what is accepted do not
depend on it (tests/unit/schemas/test_codec_msgspec.py).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from typing import Annotated, Any, Callable, Literal, TypedDict, Union

import msgpack

import msgspec

# The same MessagePack as msgpack for the codec's plain maps, in a third of the time (pack)
# and half (unpack); Encoder/Decoder methods are thread safe since msgspec 0.16 (#402).
_fast_pack = msgspec.msgpack.Encoder().encode
_fast_unpack = msgspec.msgpack.Decoder().decode

REASONS = (
    "malformed",  # not MessagePack, or not a map
    "wrong_version",
    "missing_field",
    "unknown_field",
    "wrong_type",
    "wrong_length",
    "non_finite",
    "out_of_range",
    "too_large",  # over the definition's size bound: refused before decoding (Message.max_bytes)
    "flood",      # refused undiagnosed: its key had more than a flood's worth of rejects this second
)

# Size bounds (Message.max_bytes): a definition with only bounded fields gets the largest
# encoding of its fields, counting STR_MAX_BYTES for a string without choices; one with a
# field of unbounded size (a free-length array, a counts map) gets DEFAULT_MAX_BYTES unless
# it names its own bound. Generous: they exist to refuse huge garbage before decoding it.
STR_MAX_BYTES = 256
DEFAULT_MAX_BYTES = 64 * 1024

# A key's transport priority (services.runtime.zenoh_priority maps them to Zenoh's): "control",
# every message the stack's loops and lockstep handshake carry, all at one priority because their
# order on a link is part of the protocol (a plan before its setpoint, a run's outputs before its
# sync); "bulk", large messages that must never hold those up on a shared link (camera images).
PRIORITIES = ("control", "bulk")

# Field kinds. Arrays are MessagePack arrays; "counts" is a map str -> int >= 0.
KINDS = ("float", "int", "bool", "str", "float[]", "int[]", "str[]", "counts",  # counts: map str -> int >= min (0)
         "bytes")   # bytes: MessagePack bin (an image's pixels), of `length` bytes when given


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
        assert self.kind != "bytes" or (self.min is None and self.max is None and self.choices is None), self.name


@dataclass(frozen=True)
class Message:
    name: str
    topic: str  # key expression below zp/<vehicle>/; "{service}" is filled per sender
    version: int
    doc: str
    fields: tuple[Field, ...]
    check: Callable[[dict], str | None] | None = None  # cross-field check -> error detail
    max_bytes: int | None = None  # bound on the encoded size; None: computed (_size_bound)
    priority: str = "control"  # one of PRIORITIES
    # True: every message counts (a command, a mission, a parameter): sent reliably in real time
    # too. False: a stream whose next sample replaces a lost one: best effort in real time, so
    # that no fresh sample waits behind a lost one's retransmission (services.runtime.Publisher).
    reliable: bool = False
    _by_name: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self):
        assert self.priority in PRIORITIES, (self.name, self.priority)
        self._by_name.update({f.name: f for f in self.fields})

    def __getattr__(self, name: str):
        """The compiled functions, made on first use (the definition is frozen: once): a service
        compiles only the messages it uses, and importing schemas stays cheap (a restart's start-up)."""
        if name not in _COMPILED:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        for key, value in _compile(self).items():
            object.__setattr__(self, key, value)
        return self.__dict__[name]

    def __getstate__(self):  # pickle/deepcopy: the definition, not its compiled functions
        return {k: v for k, v in self.__dict__.items() if k not in _COMPILED}

    def __setstate__(self, state):
        self.__dict__.update(state)

    @property
    def sent_reliably(self) -> bool:
        """In real time too: what must arrive, and bulk (Zenoh picks a link by reliability before
        priority: an image must not take the control keys' unreliable link)."""
        return self.reliable or self.priority == "bulk"

    @property
    def size_limit(self) -> int:
        """Largest payload a valid message can be: anything longer is refused undecoded."""
        return self._size_limit

    def key(self, vehicle: int | str = 0, service: str | None = None) -> str:
        topic = self.topic.format(service=service) if "{service}" in self.topic else self.topic
        return f"zp/{vehicle}/{topic}"

    # -- encoding -------------------------------------------------------
    def encode(self, t_s: float, seq: int, source: str, values: dict[str, Any]) -> bytes:
        """Validate `values` and pack them; invalid values raise SchemaError
        on the sender's side, so a NaN is never put on the wire."""
        return self._encode(t_s, seq, source, values)

    # -- decoding -------------------------------------------------------
    def decode(self, payload: bytes) -> dict:
        """Unpack and validate; returns the map (header included)."""
        return self._decode(payload)

    def validate(self, doc: Any) -> None:
        """Raise SchemaError unless `doc` (a decoded map) matches the definition."""
        self._validate(doc)

    def accept(self, payload: bytes) -> dict | None:
        """The decoded message, or None for an invalid one, without finding the reason (a few
        microseconds against tens for `decode`'s diagnosis of a bad message): for a receiver
        under a flood. Exact (accepts what `decode` accepts) where `fast_exact`; otherwise it
        falls back to `decode`."""
        return self._accept(payload)


HEADER_FIELDS = (
    Field("t_s", "float", "sample time of what the message describes", "s", min=0.0),
    Field("seq", "int", "sequence number per sender and key, from 0", min=0),
    Field("source", "str", "name of the sending service"),
)


# ---------------------------------------------------------------- reference path
# The generic validator: slow, but it is the definition of what is valid and of
# every reason and detail text. The compiled functions fall back to it.

def _validate_reference(m: Message, doc: Any) -> None:
    if not isinstance(doc, dict):
        raise SchemaError("malformed", m.name, f"expected a map, got {type(doc).__name__}")
    version = doc.get("version")
    if version is None:
        raise SchemaError("missing_field", m.name, "version")
    if version != m.version:
        raise SchemaError("wrong_version", m.name, f"got {version!r}, expected {m.version}")
    _check_header(m.name, doc.get("header"))
    for f in m.fields:
        if f.name not in doc:
            raise SchemaError("missing_field", m.name, f.name)
        _check_field(m.name, f, doc[f.name])
    if len(doc) != len(m.fields) + 2:
        extra = set(doc) - set(m._by_name) - {"version", "header"}
        raise SchemaError("unknown_field", m.name, ", ".join(sorted(map(str, extra))))
    if m.check is not None:
        problem = m.check(doc)
        if problem:
            raise SchemaError("wrong_length", m.name, problem)


def _encode_reference(m: Message, t_s: float, seq: int, source: str, values: dict[str, Any]) -> dict:
    """The map `encode` packs, built and validated the generic way (raises SchemaError)."""
    doc = {"version": m.version, "header": {"t_s": float(t_s), "seq": int(seq), "source": source}}
    for f in m.fields:
        if f.name not in values:
            raise SchemaError("missing_field", m.name, f.name)
        doc[f.name] = _plain(values[f.name])
    extra = set(values) - set(m._by_name)
    if extra:
        raise SchemaError("unknown_field", m.name, ", ".join(sorted(extra)))
    _validate_reference(m, doc)
    return doc


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
    elif kind == "bytes":
        if not isinstance(v, bytes):
            raise SchemaError("wrong_type", message, f"{where} must be bytes (MessagePack bin), got {type(v).__name__}")
        if f.length is not None and len(v) != f.length:
            raise SchemaError("wrong_length", message, f"{where} has {len(v)} bytes, expected {f.length}")
        return
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
    t = type(v)
    if t is float or t is int or t is str or t is bool:  # none of them has tolist/item
        return v
    if t is bytearray or t is memoryview:   # a memoryview's tolist would make a list of ints
        return bytes(v)
    if t is list:
        for x in v:
            if type(x) is not float and type(x) is not int:
                return [x.item() if hasattr(x, "item") else x for x in v]
        return v  # floats and ints only: nothing to convert
    tolist = getattr(v, "tolist", None)
    if tolist is not None:
        return tolist()
    if t is tuple:
        for x in v:
            if type(x) is not float and type(x) is not int:
                return [_plain(x) for x in v]
        return list(v)
    if isinstance(v, tuple):
        return [_plain(x) for x in v]
    if isinstance(v, list):
        return [x.item() if hasattr(x, "item") else x for x in v]
    return v


def _item_bytes(f: Field) -> int | None:
    """Largest MessagePack encoding of one value of `f`'s item kind (None: unbounded)."""
    kind = f.kind.rstrip("[]")
    if kind in ("float", "int"):
        return 9
    if kind == "bool":
        return 1
    if kind == "str":
        return 5 + (max(len(c.encode()) for c in f.choices) if f.choices else STR_MAX_BYTES)
    if kind == "bytes" and f.length is not None:
        return 5 + f.length
    return None   # counts, bytes of any length


def _size_bound(m: Message) -> int:
    if m.max_bytes is not None:
        return int(m.max_bytes)
    n = 5 + (1 + 7 + 9) + (1 + 6) + 5   # the map, "version" and its value, "header" and its map
    for f in HEADER_FIELDS + m.fields:
        item = _item_bytes(f)
        if item is None or (f.kind.endswith("[]") and f.length is None):
            return DEFAULT_MAX_BYTES
        n += 5 + len(f.name.encode()) + (5 + f.length * item if f.kind.endswith("[]") else item)
    return n


# ---------------------------------------------------------------- compiled path
class _Reject(Exception):
    """Raised inside compiled code: a check failed; the reference path decides."""


# One msgpack Packer per thread (a Packer is not thread safe), keyed by thread id: a
# threading.local does not survive between two Zenoh callbacks (each runs on a fresh Python
# thread state of the same OS thread), so it would build a Packer on every callback's encode.
_packers: dict[int, msgpack.Packer] = {}
_get_ident = threading.get_ident


def _new_packer() -> msgpack.Packer:
    if len(_packers) > 256:   # threads come and go: keep the table small
        _packers.clear()
    _packers[_get_ident()] = p = msgpack.Packer(use_bin_type=True)  # as msgpack.packb(use_bin_type=True)
    return p


def _finite_number(b: Any) -> bool:
    return type(b) in (int, float) and math.isfinite(b)


def _scalar_test(f: Field, x: str, consts: dict) -> str:
    """A Python expression that is true only if the value named `x` passes
    `_check_scalar` for `f` (it may be false for some valid values: those take the
    reference path). Float fields take ints, as the reference does, and float
    subclasses (numpy.float64: msgpack packs them as the float they are)."""
    kind = f.kind.rstrip("[]")
    if kind in ("float", "int"):
        if not all(b is None or _finite_number(b) for b in (f.min, f.max)):
            return "False"  # odd bounds: always the reference path
        if kind == "float":
            test = f"(type({x}) is float or type({x}) is int or isinstance({x}, float))"
            lo = "_NEG_INF < " if f.min is None else f"{f.min!r} <= "  # infinite bounds exclude NaN/Inf
            hi = " < _INF" if f.max is None else f" <= {f.max!r}"
            return f"{test} and {lo}{x}{hi}"
        test = f"type({x}) is int"
        if f.min is None and f.max is None:
            return test
        lo = "" if f.min is None else f"{f.min!r} <= "
        hi = "" if f.max is None else f" <= {f.max!r}"
        return f"{test} and {lo}{x}{hi}"
    if kind == "bool":
        return f"type({x}) is bool"
    if kind == "bytes":
        return f"type({x}) is bytes" + ("" if f.length is None else f" and len({x}) == {int(f.length)!r}")
    test = f"type({x}) is str"  # str
    if f.choices is not None:
        if not all(type(c) is str for c in f.choices):
            return "False"
        name = f"_C{len(consts)}"
        consts[name] = frozenset(f.choices)
        test += f" and {x} in {name}"
    return test


UNROLL_MAX = 16   # fixed-length arrays up to this long are checked item by item, without a loop


def _field_checks(f: Field, v: str, consts: dict, indent: str) -> list[str]:
    """Lines that raise _Reject unless the value named `v` passes `_check_field`."""
    if f.kind.endswith("[]"):
        if f.length is not None and 0 < f.length <= UNROLL_MAX:   # unpacked: no loop, and a wrong length raises
            xs = [f"_x{i}" for i in range(int(f.length))]
            return [f"{indent}if type({v}) is not list:", f"{indent}    raise _Reject",
                    f"{indent}{', '.join(xs)}, = {v}",
                    f"{indent}if not ({' and '.join(f'({_scalar_test(f, x, consts)})' for x in xs)}):",
                    f"{indent}    raise _Reject"]
        cond = f"type({v}) is not list"
        if f.length is not None:
            cond += f" or len({v}) != {int(f.length)!r}"
        return [f"{indent}if {cond}:", f"{indent}    raise _Reject",
                f"{indent}for x in {v}:",
                f"{indent}    if not ({_scalar_test(f, 'x', consts)}):", f"{indent}        raise _Reject"]
    if f.kind == "counts":
        lo = 0 if f.min is None else f.min
        if not _finite_number(lo):
            return [f"{indent}raise _Reject"]
        return [f"{indent}if type({v}) is not dict:", f"{indent}    raise _Reject",
                f"{indent}for k, n in {v}.items():",
                f"{indent}    if type(k) is not str or type(n) is not int or n < {lo!r}:",
                f"{indent}        raise _Reject"]
    return [f"{indent}if not ({_scalar_test(f, v, consts)}):", f"{indent}    raise _Reject"]


# The project's own layout of a message: a map of the header and the fields, "version" then a
# 3-key "header" first (as `encode` writes it). A payload that starts so can be checked whole by
# msgspec against a typed definition (_typed_decoder): the entry counts in these bytes and the
# definition's required keys leave no room for a missing, unknown or repeated key.
def _layout_prefix(m: Message) -> bytes:
    packer = msgpack.Packer(use_bin_type=True)
    return (packer.pack_map_header(len(m.fields) + 2) + packer.pack("version") + packer.pack(m.version)
            + packer.pack("header") + packer.pack_map_header(len(HEADER_FIELDS)))


_FLOAT_MAX = 1.7976931348623157e308   # the largest finite float: a bound that refuses NaN and +-inf


def _typed_value(f: Field, name: str) -> Any:
    """The msgspec type that accepts exactly what `_scalar_test` accepts for one item of `f`,
    or None where the compiled checks hand values to the reference path (odd bounds, choices)."""
    kind = f.kind.rstrip("[]")
    if kind in ("float", "int"):
        if not all(b is None or _finite_number(b) for b in (f.min, f.max)):
            return None
        ints = {"ge": None if f.min is None else math.ceil(f.min), "le": None if f.max is None else math.floor(f.max)}
        integer = Annotated[int, msgspec.Meta(**{k: v for k, v in ints.items() if v is not None})]
        if kind == "int":
            return integer
        real = Annotated[float, msgspec.Meta(ge=-_FLOAT_MAX if f.min is None else float(f.min),
                                             le=_FLOAT_MAX if f.max is None else float(f.max))]
        return Union[integer, real]   # a float field takes ints, and keeps them ints (as msgpack decodes them)
    if kind == "bool":
        return bool
    if kind == "bytes":
        return bytes if f.length is None else Annotated[bytes, msgspec.Meta(min_length=f.length, max_length=f.length)]
    if f.choices is None:
        return str
    if not f.choices or not all(type(c) is str for c in f.choices):
        return None
    return Literal[tuple(f.choices)]


def _typed_field(f: Field) -> Any:
    if f.kind == "counts":
        lo = 0 if f.min is None else f.min
        return dict[str, Annotated[int, msgspec.Meta(ge=math.ceil(lo))]] if _finite_number(lo) else None
    item = _typed_value(f, f.name)
    if item is None or not f.kind.endswith("[]"):
        return item
    return list[item] if f.length is None else Annotated[list[item], msgspec.Meta(min_length=f.length,
                                                                                  max_length=f.length)]


def _typed_decoder(m: Message) -> Callable[[bytes], dict] | None:
    """msgspec's decoder of `m` checking every field in C (the same checks as `_field_checks`), or
    None where one of them cannot be said so. It takes only payloads of the project's layout
    (_layout_prefix): a TypedDict ignores unknown keys, which that layout's entry counts exclude."""
    if type(m.version) is not int:
        return None
    header = {f.name: _typed_field(f) for f in HEADER_FIELDS}
    fields = {f.name: _typed_field(f) for f in m.fields}
    if any(t is None for t in (*header.values(), *fields.values())) or {"version", "header"} & set(fields):
        return None
    definition = TypedDict(f"{m.name}_typed", {"version": Literal[m.version],
                                               "header": TypedDict(f"{m.name}_header", header), **fields})
    return msgspec.msgpack.Decoder(definition).decode


# what `encode` leaves as it is (anything else goes through _plain first)
_AS_IS = {"float": ("float", "int"), "int": ("int",), "bool": ("bool",), "str": ("str",), "counts": ("dict",),
          "bytes": ("bytes",)}


def _compile(m: Message) -> dict:
    """Specialised encode/decode/validate functions for one message definition."""
    consts: dict[str, Any] = {}
    n_doc = len(m.fields) + 2
    version = repr(m.version) if type(m.version) is int else "_VERSION"
    check = ["        if _check(doc):", "            raise _Reject"] if m.check is not None else []

    def doc_checks(indent: str) -> list[str]:
        lines = [f"{indent}if type(doc) is not dict or len(doc) != {n_doc} or doc['version'] != {version}:",
                 f"{indent}    raise _Reject",
                 f"{indent}h = doc['header']",
                 f"{indent}if type(h) is not dict or len(h) != {len(HEADER_FIELDS)}:",
                 f"{indent}    raise _Reject"]
        for i, f in enumerate(HEADER_FIELDS):
            lines.append(f"{indent}v = h[{f.name!r}]")
            lines += _field_checks(f, "v", consts, indent)
        for f in m.fields:
            lines.append(f"{indent}v = doc[{f.name!r}]")
            lines += _field_checks(f, "v", consts, indent)
        return lines

    size = _size_bound(m)
    src = ["def _decode_msgpack(payload):",
           f"    if len(payload) > {size}:",
           f"        raise _SchemaError('too_large', _NAME, f'{{len(payload)}} bytes, at most {size}')",
           "    try:",
           "        doc = _unpackb(payload, raw=False, strict_map_key=True)",
           "    except Exception as exc:  # msgpack raises several unrelated types",
           "        raise _SchemaError('malformed', _NAME, f'not MessagePack ({type(exc).__name__})') from None",
           "    try:",
           *doc_checks("        "), *check,
           "        return doc",
           "    except Exception:",
           "        pass",
           "    _validate_reference(_M, doc)",
           "    return doc",
           "",
           "def _accept_msgpack(payload):",
           f"    if len(payload) > {size}:",
           "        return None",
           "    try:",
           "        doc = _unpackb(payload, raw=False, strict_map_key=True)",
           *doc_checks("        "), *check,
           "        return doc",
           "    except Exception:",
           "        pass",
           "    return None",
           ""]
    typed = _typed_decoder(m)
    for name in ("_decode", "_accept"):   # msgspec first; anything it refuses or a check fails on: msgpack's decide
        src += [f"def {name}_untyped(payload):",
                f"    if len(payload) <= {size}:",
                "        try:",
                "            doc = _fast_unpack(payload)",
                *doc_checks("            "), *["    " + line for line in check],
                "            return doc",
                "        except Exception:",
                "            pass",
                f"    return {name}_msgpack(payload)",
                ""]
        if typed is None:
            src += [f"{name} = {name}_untyped", ""]
            continue
        # the project's layout: checked whole in C; another layout: unpacked, then checked in Python
        src += [f"def {name}(payload):",
                f"    if len(payload) <= {size}:",
                "        try:",
                "            if payload.startswith(_LAYOUT):",
                "                doc = _typed_unpack(payload)",
                *["        " + line for line in check],
                "                return doc",
                "        except Exception:",
                f"            return {name}_msgpack(payload)",
                f"        return {name}_untyped(payload)",
                f"    return {name}_msgpack(payload)",
                ""]
    src += [
           "def _validate(doc):",
           "    try:",
           *doc_checks("        "), *check,
           "        return",
           "    except Exception:",
           "        pass",
           "    _validate_reference(_M, doc)",
           "",
           "def _encode(t_s, seq, source, values):",
           "    try:",
           "        if type(values) is not dict:",
           "            raise _Reject",
           "        _t = float(t_s)",
           "        _s = int(seq)"]
    header_vars = {"t_s": "_t", "seq": "_s", "source": "source"}
    for f in HEADER_FIELDS:
        src += _field_checks(f, header_vars[f.name], consts, "        ")
    names = []
    for i, f in enumerate(m.fields):
        v = f"v{i}"
        names.append((f.name, v))
        as_is = _AS_IS.get(f.kind, ("list",))
        src += [f"        {v} = values[{f.name!r}]",
                f"        if {' and '.join(f'type({v}) is not {t}' for t in as_is)}:",
                f"            {v} = _plain({v})"]
        src += _field_checks(f, v, consts, "        ")
    src += [f"        if len(values) != {len(m.fields)}:",
            "            raise _Reject",
            f"        doc = {{'version': {version}, 'header': {{'t_s': _t, 'seq': _s, 'source': source}}, "
            + "".join(f"{name!r}: {v}, " for name, v in names) + "}",
            *check,
            "    except Exception:",
            "        doc = None",
            "    if doc is None:",
            "        doc = _encode_reference(_M, t_s, seq, source, values)",
            *(["    else:",   # checked plain types: msgspec's bytes are msgpack's, or it refuses
               "        try:",
               "            return _fast_pack(doc)",
               "        except Exception:   # e.g. a float subclass (numpy.float64) in a list: msgpack packs it",
               "            pass"] if type(m.version) is int else []),
            "    packer = _packers.get(_get_ident())",
            "    if packer is None:",
            "        packer = _new_packer()",
            "    return packer.pack(doc)",
            ""]
    source = "\n".join(src)
    namespace = {
        "_M": m, "_NAME": m.name, "_VERSION": m.version, "_check": m.check, "_Reject": _Reject,
        "_SchemaError": SchemaError, "_unpackb": msgpack.unpackb, "_validate_reference": _validate_reference,
        "_encode_reference": _encode_reference, "_plain": _plain, "_packers": _packers, "_get_ident": _get_ident,
        "_new_packer": _new_packer, "_fast_pack": _fast_pack, "_fast_unpack": _fast_unpack,
        "_typed_unpack": typed, "_LAYOUT": _layout_prefix(m),
        "_INF": math.inf, "_NEG_INF": -math.inf, **consts,
    }
    exec(compile(source, f"<schemas codec {m.name}>", "exec"), namespace)
    # The compiled checks decide alone only where none of them hands valid values to the reference
    # path ("False": odd bounds or choices); elsewhere `accept` must diagnose like `decode`.
    fast_exact = "False" not in [_scalar_test(f, "x", {}) for f in HEADER_FIELDS + m.fields if f.kind != "counts"]
    accept = namespace["_accept"] if fast_exact else _diagnosing_accept(namespace["_decode"])
    return {"_encode": namespace["_encode"], "_decode": namespace["_decode"], "_accept": accept,
            "_validate": namespace["_validate"], "_source": source, "_size_limit": size, "fast_exact": fast_exact}


def _diagnosing_accept(decode: Callable[[bytes], dict]) -> Callable[[bytes], dict | None]:
    def accept(payload: bytes) -> dict | None:
        try:
            return decode(payload)
        except SchemaError:
            return None
    return accept


_COMPILED = ("_encode", "_decode", "_accept", "_validate", "_source", "_size_limit", "fast_exact")  # what _compile adds to a Message
