"""msgspec on the codec's compiled path: the wire stays msgpack's bytes, and decoding accepts and
rejects exactly what msgpack's decoding did, with the same reasons (schemas/core.py's doc)."""

import math

import msgpack
import pytest

import schemas
import schemas.core as core
from tests.unit.schemas.test_messages import (CODEC_CASES, EVERY_KIND, HEADER, outcome, reference_decode,
                                              valid_doc, valid_values)

# every boundary between two MessagePack integer widths, both sides, both signs
INT_EDGES = sorted({s * (b + d) for b in (0, 31, 32, 127, 128, 255, 256, 2**15, 2**16, 2**31, 2**32, 2**63)
                    for d in (-1, 0, 1) for s in (1, -1) if -2**63 <= s * (b + d) < 2**64} | {2**64 - 1})
FLOAT_EDGES = [0.0, -0.0, 1.0, -1.5, 5e-324, 2.2250738585072014e-308, 1.7976931348623157e308, 0.1, 1 / 3, 1e-7, 9.81]
# fixstr, str8, str16 and str32 sizes, ASCII and not
STRINGS = ["", "a", "x" * 31, "x" * 32, "é" * 20, "x" * 255, "x" * 256, "ü" * 40000, "x" * 65535, "x" * 65536, "𝄞\x00"]


def pack(doc):
    return msgpack.Packer(use_bin_type=True).pack(doc)


def test_msgspec_is_on_the_compiled_path():
    assert "_fast_unpack(payload)" in schemas.IMU._source and "_fast_pack(doc)" in schemas.IMU._source


@pytest.mark.parametrize("value", [*INT_EDGES, *FLOAT_EDGES, *STRINGS, True, False, [], {}, [[]], {"a": {}},
                                   list(range(15)), list(range(16)), list(range(65536)),
                                   {str(i): i for i in range(15)}, {str(i): i for i in range(16)},
                                   {str(i): i for i in range(65536)}, [math.inf, -math.inf]],
                         ids=lambda v: repr(v)[:40])
def test_msgspec_packs_plain_values_as_msgpack_does(value):
    assert core._fast_pack(value) == pack(value)
    assert core._fast_pack({"v": value, "l": [value]}) == pack({"v": value, "l": [value]})


@pytest.mark.parametrize("m", CODEC_CASES, ids=lambda m: m.name)
def test_every_message_encodes_to_msgpacks_bytes(m):
    values = valid_values(m)
    payload = m.encode(1.0, 3, "sim", values)
    assert payload == pack({"version": m.version, "header": dict(HEADER), **values})
    assert m.decode(payload) == msgpack.unpackb(payload, raw=False, strict_map_key=True)


def edge_values():
    """EVERY_KIND's values with each field set to the edges of its kind."""
    base = valid_values(EVERY_KIND)
    for i in INT_EDGES:
        yield {**base, "i": i, "f": i, "c": {"k": abs(i)}, "c_lo": {"": max(i, -1)}}
    for x in FLOAT_EDGES:
        yield {**base, "f": x, "fa": [x] * 3, "f_lo": abs(x)}   # fa: at most 3 (its check)
    for s in STRINGS:
        yield {**base, "s": s, "c": {s: 1}}
    yield {**base, "fa": [], "sa": [], "c": {}, "c_lo": {}}
    yield {**base, "sa": ["b"] * 70000}   # array32, and over the size bound on decode


def test_edge_values_encode_to_msgpacks_bytes_and_decode_back():
    for values in edge_values():
        for source in ("", "sim", "s" * 300):
            for seq in (0, 127, 128, 2**32, 2**64 - 1):
                payload = EVERY_KIND.encode(1.5, seq, source, values)
                doc = {"version": EVERY_KIND.version, "header": {"t_s": 1.5, "seq": seq, "source": source}, **values}
                assert payload == pack(doc)
                if len(payload) > EVERY_KIND.size_limit:   # refused before decoding (reference_decode has no bound)
                    assert outcome(EVERY_KIND.decode, payload)[1] == "too_large"
                else:
                    assert outcome(EVERY_KIND.decode, payload) == ("ok", doc)
                    assert EVERY_KIND.accept(payload) == doc


def test_a_float_subclass_msgspec_refuses_is_packed_by_msgpack():
    class Metres(float):   # no item() or tolist(): it reaches the packer as it is
        pass
    values = {"gyro_rad_s": [Metres(0.5), 0.0, 0.0], "accel_m_s2": [0.0, 0.0, Metres(9.81)]}
    with pytest.raises(TypeError):
        core._fast_pack(values)
    assert schemas.IMU.encode(1.0, 3, "sim", values) == pack(
        {"version": 1, "header": dict(HEADER), "gyro_rad_s": [0.5, 0.0, 0.0], "accel_m_s2": [0.0, 0.0, 9.81]})


def tricky_payloads(m):
    """Payloads where msgspec's untyped decoding and msgpack's (raw=False, strict_map_key=True) differ,
    or might: each must decode (or fail, with its reason) as msgpack's decoding did."""
    good = pack(valid_doc(m))
    yield "valid", good
    yield "trailing byte", good + b"\x00"
    yield "truncated", good[:-1]
    yield "empty", b""
    yield "reserved byte", b"\xc1"
    doc = valid_doc(m)
    name = m.fields[0].name
    for key in (1, -1, None, True, 1.5, b"version", b"header"):
        yield f"top-level key {key!r}", pack({**doc, key: 1})
        yield f"header key {key!r}", pack({**doc, "header": {**HEADER, key: 1}})
        yield f"top-level key {key!r} for a field", pack({**{k: v for k, v in doc.items() if k != name}, key: doc[name]})
    yield "bin key for the header", pack({**{k: v for k, v in doc.items() if k != "header"}, b"header": HEADER})
    yield "bin source", pack({**doc, "header": {**HEADER, "source": b"sim"}})
    yield "tuple key", b"\x81\x91\x01\x01"
    for ext in (msgpack.ExtType(5, b"xx"), msgpack.Timestamp(1, 0)):
        yield f"ext {ext!r} as t_s", pack({**doc, "header": {**HEADER, "t_s": ext}})
        yield f"ext {ext!r} as a field", pack({**doc, name: ext})
    def sub(old, new):
        assert old in good, old   # else the case tests nothing
        return good.replace(old, new, 1)
    src = b"\xa3sim"
    for bad in (b"\xa3\xed\xa0\x80", b"\xa2\xc0\x80", b"\xa4\xf4\x90\x80\x80", b"\xa2\xe2\x82"):  # not UTF-8
        yield f"source {bad!r}", sub(src, bad)
    yield "str32 source", sub(src, b"\xdb\x00\x00\x00\x03sim")
    yield "uint64 seq", sub(b"\xa3seq\x03", b"\xa3seq\xcf" + (3).to_bytes(8, "big"))
    yield "float32 t_s", sub(b"\xa3t_s" + pack(1.0), b"\xa3t_s\xca\x3f\x80\x00\x00")
    yield "map32 header", sub(pack(HEADER)[:1], b"\xdf\x00\x00\x00\x03")
    # a key twice: the last one counts in both; a valid value first and an invalid one last, and back
    for first, last in ((HEADER["seq"], -1), (-1, HEADER["seq"])):
        yield f"seq {first} then {last}", sub(pack(HEADER), b"\x84" + pack({**HEADER, "seq": first})[1:]
                                              + pack("seq") + pack(last))
    yield "deep nesting", b"\x91" * 5000 + b"\x00"   # over the small messages' size bound
    yield "nested 1000 deep", b"\x91" * 1000 + b"\x00"   # msgspec refuses it (RecursionError), msgpack not
    yield "nested in a field", pack({**doc, name: [[[[{}]]]]})


@pytest.mark.parametrize("m", CODEC_CASES, ids=lambda m: m.name)
def test_decoding_accepts_and_rejects_as_msgpack_did(m):
    for what, payload in tricky_payloads(m):
        if len(payload) > m.size_limit:   # refused before decoding (reference_decode has no bound)
            assert outcome(m.decode, payload)[1] == "too_large" and m.accept(payload) is None, what
            continue
        expected = outcome(reference_decode, m, payload)
        assert outcome(m.decode, payload) == expected, what
        if m.fast_exact:
            assert m.accept(payload) == (expected[1] if expected[0] == "ok" else None), what


@pytest.mark.parametrize("m", schemas.ALL, ids=lambda m: m.name)
def test_every_message_is_checked_whole_by_msgspec_on_the_projects_layout(m):
    """Every definition's checks can be said as msgspec types (a new field kind or bound that cannot
    falls back to the slower Python checks: make it expressible, or drop it from this test)."""
    assert core._typed_decoder(m) is not None
    assert m.encode(1.0, 3, "sim", valid_values(m)).startswith(core._layout_prefix(m))


@pytest.mark.parametrize("m", CODEC_CASES, ids=lambda m: m.name)
def test_the_projects_layout_with_a_key_too_many_or_a_key_twice_is_rejected_as_msgpack_did(m):
    """msgspec's typed maps ignore unknown keys; the layout's entry counts are what refuses them."""
    doc = valid_doc(m)
    name = m.fields[0].name
    cases = {   # (a key overridden in a dict keeps its place: "version", "header" stay first)
        "unknown header key": pack({**doc, "header": {**HEADER, "extra": 1}}),
        "unknown key": pack({**doc, "extra": 1}),
        "header key twice, one missing": pack({**doc, "header": HEADER})
        .replace(pack("source"), pack("seq"), 1),
    }
    if len(m.fields) > 1:
        cases["field twice, one missing"] = pack(doc).replace(pack(m.fields[1].name), pack(name), 1)
    for what, payload in cases.items():
        expected = outcome(reference_decode, m, payload)
        assert expected[0] == "error", what
        assert outcome(m.decode, payload) == expected, what
        assert m.accept(payload) is None, what
