"""Cost of the message codec per encode and per decode, beside plain msgpack.

    python bench/codec.py [--rounds 7] [--round-s 0.05] [--messages imu,motor_pwm,...]

For a few representative messages (valid values built from the definitions in
schemas/messages.py) it times, in the same run:

  packb / unpackb   msgpack.packb / msgpack.unpackb of the same map (no checks): msgpack's
                    time; the codec packs and unpacks with msgspec where it is installed
                    (schemas/core.py), faster than msgpack, so new/packb can be near 1
  old               the generic validator the codec used before it was compiled
                    (a verbatim copy below: Field walking per message)
  new               schemas' Message.encode / Message.decode

Figures are medians over --rounds rounds of about --round-s seconds each, in
microseconds per call, with ratios to the baseline and to the old codec.
"encode (numpy)" passes the arrays as numpy float64 arrays, as the services do.
The encoded bytes of old and new are compared (they must be identical).
Wall-clock figures depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import timeit
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import msgpack  # noqa: E402
import numpy as np  # noqa: E402

import schemas  # noqa: E402
from schemas.core import HEADER_FIELDS, Field, Message, SchemaError  # noqa: E402

DEFAULT_MESSAGES = ("imu", "motor_pwm", "attitude_state", "position_state", "health")


# ------------------------------------------------------------------ the old codec
# Verbatim (as functions of the Message) from schemas/core.py before compilation.
def old_encode(m: Message, t_s: float, seq: int, source: str, values: dict[str, Any]) -> bytes:
    doc = {"version": m.version, "header": {"t_s": float(t_s), "seq": int(seq), "source": source}}
    for f in m.fields:
        if f.name not in values:
            raise SchemaError("missing_field", m.name, f.name)
        doc[f.name] = _old_plain(values[f.name])
    extra = set(values) - set(m._by_name)
    if extra:
        raise SchemaError("unknown_field", m.name, ", ".join(sorted(extra)))
    old_validate(m, doc)
    return msgpack.packb(doc, use_bin_type=True)


def old_decode(m: Message, payload: bytes) -> dict:
    try:
        doc = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except Exception as exc:
        raise SchemaError("malformed", m.name, f"not MessagePack ({type(exc).__name__})") from None
    old_validate(m, doc)
    return doc


def old_validate(m: Message, doc: Any) -> None:
    if not isinstance(doc, dict):
        raise SchemaError("malformed", m.name, f"expected a map, got {type(doc).__name__}")
    version = doc.get("version")
    if version is None:
        raise SchemaError("missing_field", m.name, "version")
    if version != m.version:
        raise SchemaError("wrong_version", m.name, f"got {version!r}, expected {m.version}")
    _old_check_header(m.name, doc.get("header"))
    for f in m.fields:
        if f.name not in doc:
            raise SchemaError("missing_field", m.name, f.name)
        _old_check_field(m.name, f, doc[f.name])
    if len(doc) != len(m.fields) + 2:
        extra = set(doc) - set(m._by_name) - {"version", "header"}
        raise SchemaError("unknown_field", m.name, ", ".join(sorted(map(str, extra))))
    if m.check is not None:
        problem = m.check(doc)
        if problem:
            raise SchemaError("wrong_length", m.name, problem)


def _old_check_header(message: str, header: Any) -> None:
    if header is None:
        raise SchemaError("missing_field", message, "header")
    if not isinstance(header, dict):
        raise SchemaError("wrong_type", message, "header is not a map")
    for f in HEADER_FIELDS:
        if f.name not in header:
            raise SchemaError("missing_field", message, f"header.{f.name}")
        _old_check_field(message, f, header[f.name], prefix="header.")
    if len(header) != len(HEADER_FIELDS):
        raise SchemaError("unknown_field", message, "header has extra keys")


def _old_is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _old_check_scalar(message: str, f: Field, v: Any, where: str) -> None:
    kind = f.kind.rstrip("[]")
    if kind == "float":
        if not _old_is_number(v):
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


def _old_check_field(message: str, f: Field, v: Any, prefix: str = "") -> None:
    where = prefix + f.name
    if f.kind.endswith("[]"):
        if not isinstance(v, list):
            raise SchemaError("wrong_type", message, f"{where} must be an array, got {type(v).__name__}")
        if f.length is not None and len(v) != f.length:
            raise SchemaError("wrong_length", message, f"{where} has {len(v)} items, expected {f.length}")
        for i, item in enumerate(v):
            _old_check_scalar(message, f, item, f"{where}[{i}]")
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
        _old_check_scalar(message, f, v, where)


def _old_plain(v: Any) -> Any:
    if hasattr(v, "tolist"):
        return v.tolist()
    if isinstance(v, tuple):
        return [_old_plain(x) for x in v]
    if isinstance(v, list):
        return [x.item() if hasattr(x, "item") else x for x in v]
    return v


# ------------------------------------------------------------------ inputs
def sample_values(m: Message) -> dict[str, Any]:
    """Valid, non-round values for every field of `m`, from its definition only
    (so fields added to a message are benchmarked too)."""
    out: dict[str, Any] = {}
    for i, f in enumerate(m.fields):
        def number(j: int) -> float:
            lo = -10.0 if f.min is None else f.min
            hi = lo + 20.0 if f.max is None else f.max
            return lo + (hi - lo) * (0.31 + 0.037 * ((i + j) % 11))
        if f.kind == "float":
            out[f.name] = number(0)
        elif f.kind == "int":
            out[f.name] = int(max(number(0), 0 if f.min is None else f.min))
        elif f.kind == "bool":
            out[f.name] = i % 2 == 0
        elif f.kind == "str":
            out[f.name] = f.choices[1 % len(f.choices)] if f.choices else "attitude: imu late 3 ms"
        elif f.kind == "counts":
            out[f.name] = {"malformed": 2, "out_of_range": 17}
        else:  # arrays
            n = f.length or 3
            if f.kind == "float[]":
                out[f.name] = [number(j) for j in range(n)]
            elif f.kind == "int[]":
                out[f.name] = list(range(n))
            else:
                out[f.name] = [f"item{j}" for j in range(n)]
    if m is schemas.CAMERA:  # sizes its cross-field check wants: 8 corners per marker
        out["corners_px"] = [100.0 + j for j in range(8 * len(out["marker_ids"]))]
    if m is schemas.PLANNER_PLAN:  # a 50-step plan of the 13-state model
        h, n = 50, 13
        out.update(horizon=h, state_dim=n, states=[0.01 * j for j in range((h + 1) * n)],
                   controls_rad_s=[900.0 + j for j in range(4 * h)], gains=[-0.001 * j for j in range(4 * h * n)],
                   target_roll_rad=[0.06 * j for j in range(h)])
    return out


def as_numpy(values: dict[str, Any]) -> dict[str, Any]:
    return {k: np.asarray(v, dtype=np.float64) if isinstance(v, list) and v and isinstance(v[0], float) else v
            for k, v in values.items()}


# ------------------------------------------------------------------ timing
def per_call_us(fn, rounds: int, round_s: float) -> float:
    fn()
    timer = timeit.Timer(fn)
    n, t = 1, 0.0
    while t < round_s / 4:  # calls per round: about round_s
        n *= 4
        t = timer.timeit(n)
    n = max(1, int(n * round_s / t))
    return statistics.median(timer.timeit(n) / n for _ in range(rounds)) * 1e6


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--round-s", type=float, default=0.05, help="seconds per round and figure")
    ap.add_argument("--messages", default=",".join(DEFAULT_MESSAGES),
                    help=f"comma-separated message names (of {', '.join(schemas.BY_NAME)})")
    args = ap.parse_args(argv)
    print("$ python " + " ".join([Path(sys.argv[0]).as_posix()] + sys.argv[1:]) if argv is None
          else "$ python bench/codec.py " + " ".join(argv))
    print(f"python {sys.version.split()[0]}, msgpack {'.'.join(map(str, msgpack.version))}, "
          f"{args.rounds} rounds of ~{args.round_s} s, medians in us per call")

    def run(fn):
        return per_call_us(fn, args.rounds, args.round_s)

    enc_rows, dec_rows = [], []
    for name in args.messages.split(","):
        m = schemas.BY_NAME[name.strip()]
        values = sample_values(m)
        arrays = as_numpy(values)
        header = (1712345678.125, 4711, "attitude")
        doc = {"version": m.version, "header": dict(zip(("t_s", "seq", "source"), header)), **values}
        payload = m.encode(*header, values)
        same = (payload == old_encode(m, *header, values) == msgpack.packb(doc)
                == m.encode(*header, arrays) == old_encode(m, *header, arrays))
        assert m.decode(payload) == old_decode(m, payload) == doc, name
        base_e = run(lambda: msgpack.packb(doc))
        old_e = run(lambda: old_encode(m, *header, values))
        new_e = run(lambda: m.encode(*header, values))
        old_n = run(lambda: old_encode(m, *header, arrays))
        new_n = run(lambda: m.encode(*header, arrays))
        base_d = run(lambda: msgpack.unpackb(payload))
        old_d = run(lambda: old_decode(m, payload))
        new_d = run(lambda: m.decode(payload))
        enc_rows.append((m.name, len(payload), base_e, old_e, new_e, old_n, new_n, "yes" if same else "NO"))
        dec_rows.append((m.name, len(payload), base_d, old_d, new_d))

    print("\nencode (us per call; numpy: arrays as np.float64 arrays)")
    print(f"{'message':16s} {'bytes':>5s} {'packb':>7s} {'old':>7s} {'new':>7s} {'new/packb':>9s} {'new/old':>7s}"
          f" {'old np':>7s} {'new np':>7s} {'new/old':>7s}  identical bytes")
    for name, size, base, old, new, old_n, new_n, same in enc_rows:
        print(f"{name:16s} {size:5d} {base:7.2f} {old:7.2f} {new:7.2f} {new / base:9.2f} {new / old:7.2f}"
              f" {old_n:7.2f} {new_n:7.2f} {new_n / old_n:7.2f}  {same}")
    print("\ndecode (us per call)")
    print(f"{'message':16s} {'bytes':>5s} {'unpackb':>7s} {'old':>7s} {'new':>7s} {'new/unpackb':>11s} {'new/old':>7s}")
    for name, size, base, old, new in dec_rows:
        print(f"{name:16s} {size:5d} {base:7.2f} {old:7.2f} {new:7.2f} {new / base:11.2f} {new / old:7.2f}")


if __name__ == "__main__":
    main()
