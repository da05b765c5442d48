"""The flight log's Foxglove well-known channels: made from the sorted stream (lockstep's
rewrite, schemas.flightlog.sort_log with FoxgloveMap.encoded_stored), read back with the `mcap`
reader and mcap-protobuf-support's decoder, beside the bus channels every reader keeps using."""

import random

from foxglove.messages import FrameTransform, SceneUpdate
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from flight.quat import quat_from_euler
from flight.vehicle import load_vehicle
from schemas.flightlog import FlightLogWriter, read_log, sort_log
from services.foxglove_map import FoxgloveMap


def stream():
    """A second and a half of a vehicle: truth and attitude at 200 Hz, position at 100 Hz,
    camera at 20 Hz, IMU at 400 Hz (sample times on a 400 Hz tick)."""
    rows, seq = [], {}

    def add(key, t, **fields):
        seq[key] = seq.get(key, -1) + 1
        rows.append((key, {"version": 1, "header": {"t_s": t, "seq": seq[key], "source": key.split("/")[2]},
                           **fields}))

    for k in range(600):
        t = k / 400
        add("zp/0/sim/imu", t, gyro_rad_s=[0.0, 0.0, 0.01 * k], accel_m_s2=[0.0, 0.0, 9.81])
        if k % 2 == 0:
            yaw = 0.001 * k
            add("zp/0/sim/truth", t, position_m=[0.01 * k, 0.0, 1.0], quaternion_wxyz=list(quat_from_euler(0, 0, yaw)))
            add("zp/0/att/state", t, quaternion_wxyz=list(quat_from_euler(0, 0, yaw + 0.01)))
        if k % 4 == 0:
            add("zp/0/pos/state", t, position_m=[0.01 * k + 0.002, 0.0, 1.0])
        if k % 20 == 0:
            add("zp/0/sim/camera", t, marker_ids=[220, 221], corners_px=[0.0] * 16)
    return rows


def write(path, rows):
    log = FlightLogWriter(path)
    for key, msg in rows:
        log.write(key, msg)
    log.close()


def sorted_with_foxglove(tmp_path, rows, name):
    write(tmp_path / f"{name}.raw.mcap", rows)
    fmap = FoxgloveMap(load_vehicle("x250").motor_positions_m, poses=False)   # as the recorder makes them
    n = sort_log(tmp_path / f"{name}.raw.mcap", tmp_path / f"{name}.mcap", derive=fmap.encoded_stored)
    assert n == len(rows)   # the count is of the bus messages copied
    return tmp_path / f"{name}.mcap"


def test_well_known_channels_are_deterministic_whatever_the_arrival_order(tmp_path):
    rows = stream()
    shuffled = rows[:]
    random.Random(3).shuffle(shuffled)   # another machine, another arrival order
    a = sorted_with_foxglove(tmp_path, rows, "a")
    b = sorted_with_foxglove(tmp_path, shuffled, "b")
    assert a.read_bytes() == b.read_bytes()


def test_log_opens_with_the_mcap_reader_with_well_known_schemas(tmp_path):
    rows = stream()
    path = sorted_with_foxglove(tmp_path, rows, "log")
    expected = {"foxglove/0/tf/truth": FrameTransform, "foxglove/0/tf/estimate": FrameTransform,
                "foxglove/0/scene/markers": SceneUpdate, "foxglove/0/scene/vehicle": SceneUpdate,
                "foxglove/0/scene/seen": SceneUpdate}
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        channels = {c.topic: c for c in summary.channels.values()}
        assert "foxglove/0/pose/truth" not in channels   # the transforms carry it
        for topic, cls in expected.items():
            channel = channels[topic]
            schema = summary.schemas[channel.schema_id]
            assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
            assert schema.name == cls.get_schema().name and schema.data == cls.get_schema().data, topic
        for topic, channel in channels.items():   # the bus channels are unchanged: JSON, JSON Schema
            if topic.startswith("zp/"):
                assert channel.message_encoding == "json"
                assert summary.schemas[channel.schema_id].encoding == "jsonschema"
        decoded = {}
        for _schema, channel, message, proto in reader.iter_decoded_messages(
                topics=list(expected), log_time_order=True):
            decoded.setdefault(channel.topic, []).append((message.log_time, proto))
    truth = {round(m["header"]["t_s"] * 1e9): m for k, m in rows if k == "zp/0/sim/truth"}
    assert len(decoded["foxglove/0/tf/truth"]) == len(truth) == 300
    for t_ns, tf in decoded["foxglove/0/tf/truth"]:
        q = truth[t_ns]["quaternion_wxyz"]
        assert (tf.timestamp.ToNanoseconds(), tf.child_frame_id) == (t_ns, "base_link_truth")
        assert [tf.translation.x, tf.rotation.w, tf.rotation.z] == [truth[t_ns]["position_m"][0], q[0], q[3]]
    # the estimate: each position with the attitude sorted before it (same tick: key order, att < pos)
    att = {round(m["header"]["t_s"] * 1e9): m["quaternion_wxyz"] for k, m in rows if k == "zp/0/att/state"}
    for t_ns, tf in decoded["foxglove/0/tf/estimate"]:
        assert tf.rotation.z == att[t_ns][3] and tf.child_frame_id == "base_link"
    assert len(decoded["foxglove/0/scene/markers"]) == 2   # once per second of flight: 0 s and 1 s
    assert len(decoded["foxglove/0/scene/seen"][0][1].entities[0].cubes) == 2


def test_read_log_keeps_to_the_bus_messages(tmp_path):
    rows = stream()
    log = read_log(sorted_with_foxglove(tmp_path, rows, "log"))
    assert set(log) == {k for k, _ in rows}
    assert sum(len(v) for v in log.values()) == len(rows)
