"""The strict codec: every way a message can be wrong gives one typed reason."""

import math
import threading

import msgpack
import numpy as np
import pytest

import schemas
from schemas.core import HEADER_FIELDS, _encode_reference, _validate_reference
from schemas.reference import render

IMU_OK = {"gyro_rad_s": [0.0, 0.0, 0.1], "accel_m_s2": [0.0, 0.0, 9.81]}


def imu_doc(**changes):
    doc = {"version": 1, "header": {"t_s": 1.0, "seq": 3, "source": "sim"}, **IMU_OK}
    doc.update(changes)
    return msgpack.packb(doc)


def reason(payload, message=schemas.IMU):
    with pytest.raises(schemas.SchemaError) as err:
        message.decode(payload)
    return err.value.reason


def test_round_trip_keeps_header_and_fields():
    payload = schemas.IMU.encode(2.5, 7, "sim", IMU_OK)
    msg = schemas.IMU.decode(payload)
    assert msg["header"] == {"t_s": 2.5, "seq": 7, "source": "sim"}
    assert msg["gyro_rad_s"] == [0.0, 0.0, 0.1]


def test_plain_msgpack_client_can_read_it():
    doc = msgpack.unpackb(schemas.IMU.encode(2.5, 7, "sim", IMU_OK))
    assert doc["version"] == 1 and doc["accel_m_s2"][2] == 9.81


@pytest.mark.parametrize("payload, expected", [
    (b"\xc1garbage", "malformed"),
    (msgpack.packb([1, 2, 3]), "malformed"),
    (imu_doc(version=2), "wrong_version"),
    (msgpack.packb({"version": 1, "header": {"t_s": 1.0, "seq": 0, "source": "x"}, "gyro_rad_s": [0, 0, 0]}), "missing_field"),
    (imu_doc(extra=1), "unknown_field"),
    (imu_doc(gyro_rad_s="fast"), "wrong_type"),
    (imu_doc(gyro_rad_s=[0.0, True, 0.0]), "wrong_type"),
    (imu_doc(gyro_rad_s=[0.0, 0.0]), "wrong_length"),
    (imu_doc(gyro_rad_s=[0.0, math.nan, 0.0]), "non_finite"),
    (imu_doc(accel_m_s2=[0.0, 0.0, math.inf]), "non_finite"),
    (imu_doc(gyro_rad_s=[0.0, 0.0, 1e9]), "out_of_range"),
    (imu_doc(header={"t_s": 1.0, "seq": -1, "source": "sim"}), "out_of_range"),
    (imu_doc(header={"t_s": 1.0, "seq": 0}), "missing_field"),
])
def test_each_defect_has_its_reason(payload, expected):
    assert reason(payload) == expected


def test_cross_field_check_on_camera():
    bad = msgpack.packb({"version": 1, "header": {"t_s": 0.0, "seq": 0, "source": "sim"},
                         "marker_ids": [1, 2], "corners_px": [0.0] * 8})
    assert reason(bad, schemas.CAMERA) == "wrong_length"


def test_string_choices_are_enforced():
    values = {"attitude_ref_rad": [0, 0, 0], "thrust_n": 1.0}
    schemas.POSITION_SETPOINT.encode(0.0, 0, "position", values)
    bad = dict(mode="flying", armed=True, position_m=[0, 0, 1], attitude_rad=[0, 0, 0], item=0,
               phase="x", measure=False, mission_state="running")
    with pytest.raises(schemas.SchemaError) as err:
        schemas.PLANNER_SETPOINT.encode(0.0, 0, "planner", bad)
    assert err.value.reason == "out_of_range"


def test_sender_refuses_nan():
    with pytest.raises(schemas.SchemaError) as err:
        schemas.IMU.encode(0.0, 0, "sim", {"gyro_rad_s": [math.nan, 0, 0], "accel_m_s2": [0, 0, 9.8]})
    assert err.value.reason == "non_finite"


def test_key_expressions_map_back_to_messages():
    for m in schemas.ALL:
        key = m.key(0, "attitude")
        assert schemas.message_for_key(key) is m, key
    assert schemas.message_for_key("zp/0/nothing/here") is None


def test_reference_page_is_current():
    """docs/messages.md is generated; regenerate with `python -m schemas.reference > docs/messages.md`."""
    from pathlib import Path
    page = Path(__file__).resolve().parents[3] / "docs" / "messages.md"
    assert page.read_text() == render()


# ---------------------------------------------------------------- the compiled codec
# Each Message compiles its definition into fast encode/decode/validate functions
# that fall back to the generic reference validator whenever a check fails. These
# tests hold the compiled path to the reference: same accepted maps, same bytes,
# same reason and detail text for every kind of bad input.
HEADER = {"t_s": 1.0, "seq": 3, "source": "sim"}


def valid_values(m):
    """Valid values for every field of `m`, from its definition (floats, not ints)."""
    out = {}
    for i, f in enumerate(m.fields):
        lo = -10.0 if f.min is None else float(f.min)
        hi = lo + 20.0 if f.max is None else float(f.max)
        x = lo + (hi - lo) * (0.25 + 0.01 * i)
        if f.kind == "float":
            out[f.name] = x
        elif f.kind == "int":
            out[f.name] = int(max(x, 0 if f.min is None else f.min))
        elif f.kind == "bool":
            out[f.name] = bool(i % 2)
        elif f.kind == "str":
            out[f.name] = f.choices[-1] if f.choices else "text"
        elif f.kind == "counts":
            out[f.name] = {"malformed": 2, "wrong_type": 0}
        elif f.kind == "float[]":
            out[f.name] = [x + (hi - lo) * 0.01 * j for j in range(f.length or 2)]
        elif f.kind == "int[]":
            out[f.name] = [int(max(x, 0 if f.min is None else f.min))] * (f.length or 2)
        elif f.kind == "bytes":
            out[f.name] = bytes(range(f.length or 5))
        else:
            out[f.name] = [f.choices[0] if f.choices else "a"] * (f.length or 2)
    if m is schemas.CAMERA:
        out["corners_px"] = [100.0] * (8 * len(out["marker_ids"]))
    if m is schemas.CAMERA_IMAGE:  # one byte per pixel
        out.update(width_px=3, height_px=2, pixels=bytes([0, 1, 2, 253, 254, 255]))
    if m is schemas.PLANNER_PLAN:  # sizes that satisfy its cross-field check
        h, n = 2, 13
        out.update(horizon=h, state_dim=n, states=[0.0] * ((h + 1) * n), controls_rad_s=[1.0] * (4 * h), gains=[0.0] * (4 * h * n),
                   target_roll_rad=[0.0] * h)
    if m is schemas.PLANNER_MISSION:  # two items: 3 positions each
        out.update(position_m=[1.0] * 6)
    if m is schemas.PLANNER_FLIP_PREDICTION:  # bands of three percentiles
        out.update({k: [0.1, 0.2, 0.3] for k in ("loss_from_turn_m", "loss_from_hover_m", "xy_drift_m",
                                                  "overshoot_deg", "recovery_s")})
    return out


def valid_doc(m):
    return {"version": m.version, "header": dict(HEADER), **valid_values(m)}


def outcome(fn, *args):
    """('ok', result) or ('error', reason, str) - what a receiver can observe."""
    try:
        return ("ok", fn(*args))
    except schemas.SchemaError as exc:
        return ("error", exc.reason, str(exc))


def reference_decode(m, payload):
    try:
        doc = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except Exception as exc:
        raise schemas.SchemaError("malformed", m.name, f"not MessagePack ({type(exc).__name__})") from None
    _validate_reference(m, doc)
    return doc


def reference_encode(m, t_s, seq, source, values):
    return msgpack.packb(_encode_reference(m, t_s, seq, source, values), use_bin_type=True)


# values that are wrong (or right) for some kind of field
PROBES = [None, True, False, 0, 1, -1, 7, 2**40, 0.0, 1.5, -1.5, 1e9, -1e9, math.nan, math.inf, -math.inf,
          "", "x", "running", "estimate", "truth", b"bytes", [], [0.0], [0.0, 0.0, 0.0], [0, 0, 0], [0.0] * 4,
          [0.0] * 9, [1] * 4, [True, 0.0, 0.0], [0.0, math.nan, 0.0], [0.0, 0.0, math.inf], [0.0, 0.0, 1e9],
          [0.0, "x", 0.0], [None], ["a", "b"], [["nested"]], {}, {"k": 1}, {"k": -1}, {"k": -2}, {"k": True},
          {"k": 1.5}, {"k": "v"}, {1: 1}, {b"k": 1}]


def mutations(m):
    """Every single-defect variant of a valid map of `m` (and some valid ones)."""
    base = valid_doc(m)
    yield "valid", base
    for f in m.fields:
        doc = dict(base)
        del doc[f.name]
        yield f"missing {f.name}", doc
        for i, probe in enumerate(PROBES):
            yield f"{f.name}={probe!r}", {**base, f.name: probe}
    for probe in PROBES:
        yield f"version={probe!r}", {**base, "version": probe}
        yield f"header={probe!r}", {**base, "header": probe}
        for f in HEADER_FIELDS:
            yield f"header.{f.name}={probe!r}", {**base, "header": {**HEADER, f.name: probe}}
    yield "extra field", {**base, "extra": 1}
    yield "no version", {k: v for k, v in base.items() if k != "version"}
    yield "no header", {k: v for k, v in base.items() if k != "header"}
    yield "header extra key", {**base, "header": {**HEADER, "extra": 1}}
    for f in HEADER_FIELDS:
        yield f"header without {f.name}", {**base, "header": {k: v for k, v in HEADER.items() if k != f.name}}
    yield "version 1.0", {**base, "version": float(m.version)}
    yield "not a map", [base]


# every kind of field, with and without bounds, length and choices (the real messages do not use all)
EVERY_KIND = schemas.Message("every_kind", "test/every_kind", 3, "a test message", (
    schemas.Field("f", "float", ""),
    schemas.Field("f_lo", "float", "", min=-1),
    schemas.Field("f_hi", "float", "", max=2.5),
    schemas.Field("i", "int", ""),
    schemas.Field("i_hi", "int", "", max=7),
    schemas.Field("i_lo_float", "int", "", min=-1.5, max=1e9),
    schemas.Field("b", "bool", ""),
    schemas.Field("s", "str", ""),
    schemas.Field("s_choice", "str", "", choices=("running", "x")),
    schemas.Field("fa", "float[]", ""),
    schemas.Field("ia", "int[]", "", length=3, max=5),
    schemas.Field("sa", "str[]", "", choices=("a", "b")),
    schemas.Field("c", "counts", ""),
    schemas.Field("c_lo", "counts", "", min=-1),
    schemas.Field("by", "bytes", ""),
    schemas.Field("by4", "bytes", "", length=4),
), check=lambda doc: "fa and ia differ" if len(doc["fa"]) > 3 else None)
CODEC_CASES = (*schemas.ALL, EVERY_KIND)


@pytest.mark.parametrize("m", CODEC_CASES, ids=lambda m: m.name)
def test_compiled_decode_matches_reference_for_every_defect(m):
    for what, doc in mutations(m):
        payload = msgpack.packb(doc, use_bin_type=True)
        assert outcome(m.decode, payload) == outcome(reference_decode, m, payload), what


@pytest.mark.parametrize("m", CODEC_CASES, ids=lambda m: m.name)
def test_compiled_validate_matches_reference_for_every_defect(m):
    for what, doc in mutations(m):
        assert outcome(m.validate, doc) == outcome(_validate_reference, m, doc), what


@pytest.mark.parametrize("m", CODEC_CASES, ids=lambda m: m.name)
def test_compiled_encode_matches_reference_for_every_defect(m):
    for what, doc in mutations(m):
        if not isinstance(doc, dict) or not isinstance(doc.get("header"), dict) or set(doc["header"]) != set(HEADER):
            continue  # the sender does not choose these
        h = doc["header"]
        values = {k: v for k, v in doc.items() if k not in ("version", "header")}
        args = (h["t_s"], h["seq"], h["source"], values)
        try:
            expected = outcome(reference_encode, m, *args)
        except (TypeError, ValueError, OverflowError) as exc:  # not SchemaError: float(None), packing 2**70...
            with pytest.raises(type(exc)):
                m.encode(*args)
            continue
        assert outcome(m.encode, *args) == expected, what


@pytest.mark.parametrize("m", CODEC_CASES, ids=lambda m: m.name)
def test_encoding_is_byte_identical_to_packb_of_the_map(m):
    """The wire format is the plain msgpack map it always was, whatever the values' Python types."""
    values = valid_values(m)
    expected = msgpack.packb({"version": m.version, "header": dict(HEADER), **values}, use_bin_type=True)
    assert m.encode(1.0, 3, "sim", values) == expected
    as_numpy = {k: np.asarray(v) if isinstance(v, list) and v and not isinstance(v[0], str) else v
                for k, v in values.items()}
    assert m.encode(np.float64(1.0), np.int64(3), "sim", as_numpy) == expected
    as_tuples = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
    assert m.encode(1.0, 3, "sim", as_tuples) == expected
    scalars = {k: (np.float64(v) if type(v) is float else np.int64(v) if type(v) is int else
                   np.bool_(v) if type(v) is bool else [np.float64(x) for x in v] if isinstance(v, list)
                   and v and type(v[0]) is float else v) for k, v in values.items()}
    assert m.encode(1.0, 3, "sim", scalars) == expected
    assert m.decode(expected) == msgpack.unpackb(expected)


@pytest.mark.parametrize("m", CODEC_CASES, ids=lambda m: m.name)
def test_valid_messages_take_the_compiled_path(m, monkeypatch):
    """Valid values in the forms the services send never reach the (slow) reference path."""
    import schemas.core as core

    def reference_path(*args):
        raise AssertionError("reference path taken")

    monkeypatch.setattr(core, "_validate_reference", reference_path)
    monkeypatch.setattr(core, "_encode_reference", reference_path)
    fast = schemas.Message(m.name, m.topic, m.version, m.doc, m.fields, m.check)  # compiled with the patch
    values = valid_values(m)
    as_numpy = {k: np.asarray(v) if isinstance(v, list) and v and not isinstance(v[0], str) else v
                for k, v in values.items()}
    mixed = {k: (np.float64(v) if type(v) is float else tuple(v) if isinstance(v, list) else v)
             for k, v in values.items()}
    float64s = {k: [np.float64(x) for x in v] if isinstance(v, list) and v and type(v[0]) is float else v
                for k, v in values.items()}
    for vals in (values, as_numpy, mixed, float64s):
        payload = fast.encode(np.float64(1.0), 3, "sim", vals)
        fast.validate(fast.decode(payload))


def test_numpy_values_are_checked_like_plain_ones():
    values = {"gyro_rad_s": np.array([0.0, np.nan, 0.0]), "accel_m_s2": np.zeros(3)}
    assert outcome(schemas.IMU.encode, 0.0, 0, "sim", values)[1] == "non_finite"
    values = {"gyro_rad_s": [np.float32(0.0), np.float64(200.0), 0], "accel_m_s2": (0, 0, 9.8)}
    assert outcome(schemas.IMU.encode, 0.0, 0, "sim", values)[1] == "out_of_range"
    values = {"gyro_rad_s": np.zeros((3, 1)), "accel_m_s2": np.zeros(3)}
    assert outcome(schemas.IMU.encode, 0.0, 0, "sim", values)[1] == "wrong_type"
    values = {"gyro_rad_s": np.zeros(4), "accel_m_s2": np.zeros(3)}
    assert outcome(schemas.IMU.encode, 0.0, 0, "sim", values)[1] == "wrong_length"


def doc_with(**changes):
    doc = {"version": 1, "header": dict(HEADER), **IMU_OK}
    doc.update(changes)
    return doc


@pytest.mark.parametrize("doc, expected, detail", [
    ("not a map", "malformed", "expected a map, got str"),
    (doc_with(version=None), "missing_field", "version"),
    ({k: v for k, v in doc_with().items() if k != "version"}, "missing_field", "version"),
    (doc_with(version=2), "wrong_version", "got 2, expected 1"),
    ({k: v for k, v in doc_with().items() if k != "header"}, "missing_field", "header"),
    (doc_with(header=[1.0, 0, "sim"]), "wrong_type", "header is not a map"),
    (doc_with(header={"t_s": 1.0, "seq": 0}), "missing_field", "header.source"),
    (doc_with(header={**HEADER, "x": 1}), "unknown_field", "header has extra keys"),
    (doc_with(header={**HEADER, "t_s": math.nan}), "non_finite", "header.t_s is nan"),
    (doc_with(header={**HEADER, "t_s": -1.0}), "out_of_range", "header.t_s=-1.0 outside [0.0, None]"),
    (doc_with(header={**HEADER, "seq": True}), "wrong_type", "header.seq must be an integer, got bool"),
    (doc_with(header={**HEADER, "seq": 1.0}), "wrong_type", "header.seq must be an integer, got float"),
    (doc_with(header={**HEADER, "source": 7}), "wrong_type", "header.source must be a string, got int"),
    ({"version": 1, "header": HEADER, "gyro_rad_s": [0.0] * 3}, "missing_field", "accel_m_s2"),
    (doc_with(extra=1, other=2), "unknown_field", "extra, other"),
    (doc_with(gyro_rad_s={"x": 0.0}), "wrong_type", "gyro_rad_s must be an array, got dict"),
    (doc_with(gyro_rad_s=[0.0, True, 0.0]), "wrong_type", "gyro_rad_s[1] must be a number, got bool"),
    (doc_with(gyro_rad_s=[0.0, "1", 0.0]), "wrong_type", "gyro_rad_s[1] must be a number, got str"),
    (doc_with(gyro_rad_s=[0.0] * 4), "wrong_length", "gyro_rad_s has 4 items, expected 3"),
    (doc_with(gyro_rad_s=[0.0, 0.0, -math.inf]), "non_finite", "gyro_rad_s[2] is -inf"),
    (doc_with(gyro_rad_s=[0.0, 0.0, 100.5]), "out_of_range", "gyro_rad_s[2]=100.5 outside [-100.0, 100.0]"),
    (doc_with(gyro_rad_s=[0.0, 0.0, -101]), "out_of_range", "gyro_rad_s[2]=-101 outside [-100.0, 100.0]"),
])
def test_each_defect_has_its_reason_and_detail(doc, expected, detail):
    payload = msgpack.packb(doc)
    for check in (lambda: schemas.IMU.decode(payload), lambda: schemas.IMU.validate(doc)):
        with pytest.raises(schemas.SchemaError) as err:
            check()
        assert (err.value.reason, err.value.detail) == (expected, detail)


def test_validate_wants_lists_not_tuples():
    with pytest.raises(schemas.SchemaError) as err:
        schemas.IMU.validate(doc_with(gyro_rad_s=(0.0, 0.0, 0.0)))
    assert (err.value.reason, err.value.detail) == ("wrong_type", "gyro_rad_s must be an array, got tuple")


def test_ints_are_numbers_but_bools_are_not():
    ints = msgpack.packb(doc_with(gyro_rad_s=[0, 0, 1], accel_m_s2=[0, 0, 10]))
    assert schemas.IMU.decode(ints)["gyro_rad_s"] == [0, 0, 1]  # kept as sent
    cam = {"marker_ids": [True], "corners_px": [0.0] * 8}
    assert outcome(schemas.CAMERA.encode, 0.0, 0, "sim", cam)[1:] == (
        "wrong_type", "camera: wrong_type: marker_ids[0] must be an integer, got bool")
    cam = {"marker_ids": [1.0], "corners_px": [0.0] * 8}
    assert outcome(schemas.CAMERA.encode, 0.0, 0, "sim", cam)[1] == "wrong_type"
    values = {"attitude_ref_rad": [0.0] * 3, "thrust_n": True}
    assert outcome(schemas.POSITION_SETPOINT.encode, 0.0, 0, "position", values)[1:] == (
        "wrong_type", "position_setpoint: wrong_type: thrust_n must be a number, got bool")


def test_choices_and_counts():
    doc = {**valid_doc(schemas.POSITION_STATE), "state_source": "guess"}
    with pytest.raises(schemas.SchemaError) as err:
        schemas.POSITION_STATE.decode(msgpack.packb(doc))
    assert (err.value.reason, err.value.detail) == ("out_of_range", "state_source='guess' not one of ['truth', 'estimate']")
    clock = {"tick": 3, "tick_rate_hz": 400.0, "published": ["imu"], "done": {"attitude": -1, "motors": 2}}
    assert schemas.CLOCK.decode(schemas.CLOCK.encode(0.0, 0, "sim", clock))["done"] == clock["done"]
    for done, reason, detail in [({"attitude": -2}, "out_of_range", "done['attitude']=-2 below -1"),
                                 ({"attitude": True}, "wrong_type", "done must map strings to integers"),
                                 ({"attitude": 1.0}, "wrong_type", "done must map strings to integers"),
                                 ([1], "wrong_type", "done must be a map")]:
        doc = {"version": 1, "header": HEADER, **clock, "done": done}
        with pytest.raises(schemas.SchemaError) as err:
            schemas.CLOCK.decode(msgpack.packb(doc))
        assert (err.value.reason, err.value.detail) == (reason, detail)
    with pytest.raises(schemas.SchemaError) as err:
        schemas.CLOCK.decode(msgpack.packb({"version": 1, "header": HEADER, **clock, "done": {1: 1}}))
    assert err.value.reason == "malformed"  # non-string map keys are not MessagePack this codec reads


def test_sender_side_missing_and_unknown_fields():
    with pytest.raises(schemas.SchemaError) as err:
        schemas.IMU.encode(0.0, 0, "sim", {"gyro_rad_s": [0.0] * 3})
    assert (err.value.reason, err.value.detail) == ("missing_field", "accel_m_s2")
    with pytest.raises(schemas.SchemaError) as err:
        schemas.IMU.encode(0.0, 0, "sim", {**IMU_OK, "z": 1, "a": 2})
    assert (err.value.reason, err.value.detail) == ("unknown_field", "a, z")
    with pytest.raises(schemas.SchemaError) as err:  # missing is reported before unknown, as before
        schemas.IMU.encode(0.0, 0, "sim", {"gyro_rad_s": [0.0] * 3, "z": 1})
    assert err.value.reason == "missing_field"
    with pytest.raises(schemas.SchemaError) as err:
        schemas.IMU.encode(-1.0, 0, "sim", IMU_OK)
    assert err.value.reason == "out_of_range"


def test_malformed_payloads():
    good = schemas.IMU.encode(0.0, 0, "sim", IMU_OK)
    for payload in (b"", b"\xc1", good + b"\x00", good[:-1], msgpack.packb(1.0)):
        assert reason(payload) == "malformed", payload
    with pytest.raises(schemas.SchemaError) as err:
        schemas.IMU.decode(good + b"\x00")
    assert err.value.detail == "not MessagePack (ExtraData)"


def test_a_failed_pack_leaves_the_packer_usable():
    with pytest.raises(OverflowError):  # as msgpack.packb raised it before
        schemas.IMU.encode(0.0, 2**70, "sim", IMU_OK)
    assert schemas.IMU.encode(2.5, 7, "sim", IMU_OK) == msgpack.packb(
        {"version": 1, "header": {"t_s": 2.5, "seq": 7, "source": "sim"}, **IMU_OK})


def test_encode_is_safe_from_many_threads():
    expected = {i: msgpack.packb({"version": 1, "header": {"t_s": float(i), "seq": i, "source": "t"},
                                  "gyro_rad_s": [float(i)] * 3, "accel_m_s2": [0.0, 0.0, 9.81]})
                for i in range(50)}
    errors = []

    def work():
        for _ in range(40):
            for i, payload in expected.items():
                values = {"gyro_rad_s": [float(i)] * 3, "accel_m_s2": [0.0, 0.0, 9.81]}
                if schemas.IMU.encode(float(i), i, "t", values) != payload:
                    errors.append(i)

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors


def test_definitions_copy_and_pickle_with_their_codec():
    import copy
    import pickle
    payload = schemas.IMU.encode(2.5, 7, "sim", IMU_OK)
    for m in (pickle.loads(pickle.dumps(schemas.IMU)), copy.deepcopy(schemas.IMU)):
        assert m == schemas.IMU and m.decode(payload) == schemas.IMU.decode(payload)
        assert reason(imu_doc(version=2), m) == "wrong_version"


def test_the_lockstep_handshake_is_outside_every_vehicle_wide_subscription():
    # the recorder and the tools subscribe to zp/<vehicle>/**: the clock and sync keys sit under a
    # verbatim chunk so that they are not sent thousands of handshake messages a second
    import zenoh
    everything = zenoh.KeyExpr("zp/0/**")
    for message in (schemas.CLOCK, schemas.SYNC_DONE):
        key = zenoh.KeyExpr(message.key(0, "motors"))
        assert not everything.intersects(key)
        assert zenoh.KeyExpr(message.key(0, "*")).intersects(key)
        assert schemas.message_for_key(str(key)) is message
    assert everything.intersects(zenoh.KeyExpr(schemas.IMU.key(0)))


def test_camera_images_are_outside_every_wildcard_subscription():
    """The recorder and the ground tools subscribe to zp/<vehicle>/**: the pixels (~6 MB/s) are not sent to them."""
    import zenoh
    key = zenoh.KeyExpr(schemas.CAMERA_IMAGE.key(0))
    assert not zenoh.KeyExpr("zp/0/**").intersects(key)
    assert zenoh.KeyExpr("zp/0/sim/@image").intersects(key)
    doc = valid_doc(schemas.CAMERA_IMAGE)
    assert outcome(schemas.CAMERA_IMAGE.validate, {**doc, "pixels": b"\x00" * 5})[1] == "wrong_length"
