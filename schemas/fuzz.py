"""Invalid messages for a definition, for fuzz tests and benches (tests/, bench/fuzz.py).

Every payload `garbage` makes is invalid by construction: the strict decoder must reject
it. Kinds: random bytes, valid MessagePack of the wrong types, missing and extra fields,
NaN/inf, wrong version, out of range, huge arrays and deep nesting."""

from __future__ import annotations

import math
import random

import msgpack

from .core import HEADER_FIELDS, Field, Message

KINDS = ("random_bytes", "not_a_map", "wrong_type", "missing_field", "extra_field", "non_finite",
         "wrong_version", "out_of_range", "huge_array", "deep_nesting")
HUGE_ITEMS = 200_000   # a huge array: ~1.8 MB of floats, over every message's size bound
DEEP = (10, 100, 400, 1500, 100_000)   # nesting levels of deep payloads (msgpack refuses beyond 1023)


def _value(f: Field) -> object:
    kind = f.kind.rstrip("[]")
    if kind == "float":
        v = 0.0 if f.min is None or f.min <= 0.0 <= (f.max if f.max is not None else 1.0) else float(f.min)
    elif kind == "int":
        v = 0 if f.min is None or f.min <= 0 else int(f.min)
    elif kind == "bool":
        v = False
    elif kind == "str":
        v = f.choices[0] if f.choices else "x"
    elif kind == "bytes":
        return bytes(f.length or 0)
    else:   # counts
        return {}
    if f.kind.endswith("[]"):
        return [v] * (f.length or 0)
    return v


def valid_doc(m: Message, source: str = "fuzz") -> dict:
    """A map of `m` with in-range values (the check may still refuse it: callers mutate it anyway)."""
    doc = {"version": m.version, "header": {"t_s": 1.0, "seq": 0, "source": source}}
    doc.update({f.name: _value(f) for f in m.fields})
    # the cross-field checks of schemas/messages.py: array lengths that go together
    if m.name == "planner_plan":
        h, n = doc["horizon"], doc["state_dim"]
        doc.update(states=[0.0] * ((h + 1) * n), controls_rad_s=[0.0] * (4 * h), gains=[0.0] * (4 * h * n),
                   target_roll_rad=[0.0] * h)
    elif m.name == "camera_image":
        doc.update(width_px=2, height_px=1, pixels=b"\x00\xff")
    elif m.name == "planner_mission":
        doc.update(types=[doc["types"][0] if doc["types"] else "takeoff"], position_m=[0.0, 0.0, 1.0],
                   yaw_rad=[0.0], hold_s=[0.0], acceptance_m=[0.5])
    return doc


def _wrong(f: Field, rng: random.Random) -> object:
    """A value of the wrong type for `f`."""
    if f.kind.endswith("[]") or f.kind == "counts" or f.kind == "bytes":
        return rng.choice(["a string", 1.5, True])
    if f.kind == "str":
        return rng.choice([1, 2.5, [1, 2], {"a": 1}])
    if f.kind == "bool":
        return rng.choice(["true", 1.0, [True]])
    if f.kind == "int":
        return rng.choice(["1", 1.5, [1]])
    return rng.choice(["1.0", [1.0], {"x": 1.0}, None, True])


def garbage(m: Message, kind: str, rng: random.Random, huge_items: int = HUGE_ITEMS) -> bytes:
    """One invalid payload for `m` of the kind given (`huge_items`: the length of a huge array)."""
    if kind == "random_bytes":
        while True:   # random bytes that are a complete map of the right size are (nearly) impossible: make sure
            data = rng.randbytes(rng.randint(0, 64))
            if not data or data[0] not in range(0x80, 0x90):
                return data
    if kind == "not_a_map":
        return msgpack.packb(rng.choice([1, -3.5, "text", [1, 2, 3], None, True, b"\x00\x01"]))
    if kind == "huge_array":
        doc = valid_doc(m)
        doc[rng.choice([f.name for f in m.fields] + ["extra"])] = [0.0] * huge_items
        return msgpack.packb(doc)
    if kind == "deep_nesting":   # a field's value nested deep (or the whole payload)
        depth = rng.choice(DEEP)
        if rng.random() < 0.2:
            return b"\x91" * depth + b"\x00"
        return b"\x81\xa6header" + b"\x91" * depth + b"\x00"
    doc = valid_doc(m)
    fields = list(m.fields)
    if kind == "wrong_type":
        if rng.random() < 0.3 or not fields:
            f = rng.choice(HEADER_FIELDS)
            doc["header"][f.name] = _wrong(f, rng)
        else:
            f = rng.choice(fields)
            doc[f.name] = _wrong(f, rng)
    elif kind == "missing_field":
        name = rng.choice([f.name for f in fields] + ["version", "header"])
        del doc[name]
    elif kind == "extra_field":
        doc[rng.choice(["extra", "x", "pwm", "nan"])] = rng.choice([1, 0.5, "y", [1.0]])
    elif kind == "non_finite":
        bad = rng.choice([math.nan, math.inf, -math.inf])
        floats = [f for f in fields if f.kind.startswith("float")]
        if floats and rng.random() < 0.8:
            f = rng.choice(floats)
            doc[f.name] = [bad] * max(1, f.length or 1) if f.kind.endswith("[]") else bad
        else:
            doc["header"]["t_s"] = bad
    elif kind == "wrong_version":
        doc["version"] = m.version + rng.randint(1, 5)
    elif kind == "out_of_range":
        doc["header"]["seq"] = -rng.randint(1, 1000)
    else:
        raise ValueError(f"unknown garbage kind {kind!r}; one of {KINDS}")
    return msgpack.packb(doc)


class Garbage:
    """Invalid payloads for a message at a few microseconds each: a pool made once per kind
    (huge and deep payloads are costly to build), served at random."""

    def __init__(self, m: Message, seed: int = 0, pool: int = 64, kinds: tuple[str, ...] = KINDS,
                 huge_items: int = HUGE_ITEMS):
        rng = random.Random(seed)
        self.kinds = kinds
        self.pools = {k: [garbage(m, k, rng, huge_items)
                          for _ in range(2 if k == "huge_array" else 8 if k == "deep_nesting" else pool)]
                      for k in kinds}
        self._rng = random.Random(seed + 1)

    def next(self) -> tuple[str, bytes]:
        kind = self._rng.choice(self.kinds)
        return kind, self._rng.choice(self.pools[kind])
