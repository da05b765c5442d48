"""The strict codec: every way a message can be wrong gives one typed reason."""

import math

import msgpack
import pytest

import schemas
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
    page = Path(__file__).resolve().parents[2] / "docs" / "messages.md"
    assert page.read_text() == render()
