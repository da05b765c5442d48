"""Foxglove, live: `zenpilot fly --foxglove PORT` serves the flight over the Foxglove WebSocket
protocol while it flies. A client speaking that protocol (foxglove_client.py: the `websockets`
package, foxglove-sdk serves, it has no client) subscribes to every channel the server advertises
and counts what comes; the flight is conftest's hover_lockstep_live, which test_flights reads too."""

import base64
import json

import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

pytestmark = pytest.mark.integration


def protobuf_class(channel: dict):
    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


def test_live_view_during_a_lockstep_flight(hover_lockstep, hover_lockstep_live):
    tmp_path, proc, out, channels, received = hover_lockstep_live
    assert proc.returncode == 0, out
    by_topic = {channels[cid]["topic"]: msgs for cid, msgs in received.items()}
    assert len(by_topic) >= 10, sorted(by_topic)

    # every message of the flight came, at the services' rates in the flight's (simulated) time
    def rate(topic):
        times = [t for t, _ in by_topic[topic]]
        return (len(times) - 1) / ((times[-1] - times[0]) * 1e-9)

    nominal = {"zp/0/sim/imu": 400, "zp/0/motors/pwm": 400, "zp/0/att/state": 200, "zp/0/att/command": 200,
               "zp/0/pos/state": 100, "zp/0/sim/truth": 200, "zp/0/planner/setpoint": 50, "zp/0/sim/camera": 20,
               "zp/0/motors/health": 1, "foxglove/0/tf/truth": 200, "foxglove/0/tf/estimate": 100}
    for topic, hz in nominal.items():
        assert topic in by_topic, (topic, sorted(by_topic))
        assert rate(topic) == pytest.approx(hz, rel=0.05), topic
    flown_s = (by_topic["zp/0/sim/imu"][-1][0] - by_topic["zp/0/sim/imu"][0][0]) * 1e-9
    assert flown_s > 15.0   # take-off, the 10 s hold and the landing: the whole flight

    # the JSON channels carry the log's messages; the well-known ones decode with their schemas
    imu = json.loads(by_topic["zp/0/sim/imu"][-1][1])
    assert set(imu) >= {"header", "gyro_rad_s", "accel_m_s2"}
    tf_channel = next(c for c in channels.values() if c["topic"] == "foxglove/0/tf/truth")
    assert (tf_channel["encoding"], tf_channel["schemaName"]) == ("protobuf", "foxglove.FrameTransform")
    tf = protobuf_class(tf_channel).FromString(by_topic["foxglove/0/tf/truth"][len(by_topic["foxglove/0/tf/truth"]) // 2][1])
    assert (tf.parent_frame_id, tf.child_frame_id) == ("world", "base_link_truth")
    assert tf.translation.z == pytest.approx(1.0, abs=0.05)   # mid-flight: the 1 m hover
    assert any(c["schemaName"] == "foxglove.SceneUpdate" for c in channels.values())

    # a viewer only listens: the flight's log is the same, byte for byte, as without it
    fixture_out, _ = hover_lockstep
    assert (tmp_path / "flight.mcap").read_bytes() == (fixture_out / "flight.mcap").read_bytes()


# the log's (the live view also serves pose/truth and pose/estimate, which repeat the transforms)
WELL_KNOWN = {"tf/truth": "foxglove.FrameTransform", "tf/estimate": "foxglove.FrameTransform",
              "pose/setpoint": "foxglove.PoseInFrame", "pose/vision": "foxglove.PoseInFrame",
              "scene/markers": "foxglove.SceneUpdate", "scene/vehicle": "foxglove.SceneUpdate",
              "scene/seen": "foxglove.SceneUpdate"}


def check_log_for_foxglove(path, truth_hz):
    """flight.mcap opens with the `mcap` reader; its Foxglove channels have the well-known schemas
    and hold the flight (the truth's transform at the truth's times and positions)."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    from schemas.flightlog import read_log

    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        channels = {c.topic: c for c in summary.channels.values()}
        for name, schema_name in WELL_KNOWN.items():
            channel = channels[f"foxglove/0/{name}"]
            schema = summary.schemas[channel.schema_id]
            assert (schema.name, schema.encoding, channel.message_encoding) == (schema_name, "protobuf", "protobuf")
            assert summary.statistics.channel_message_counts[channel.id] > 0, name
        tfs = [(m.log_time, p) for _, _, m, p in reader.iter_decoded_messages(topics=["foxglove/0/tf/truth"])]
    truth = read_log(path)["zp/0/sim/truth"]   # the JSON bus channels read as before
    assert len(tfs) == len(truth) > 0
    if truth_hz:   # lockstep: every tick's truth, on simulated time
        assert (tfs[-1][0] - tfs[0][0]) * 1e-9 * truth_hz == pytest.approx(len(tfs) - 1, rel=0.01)
    for (t_ns, tf), msg in zip(tfs, truth):
        assert t_ns == round(msg["header"]["t_s"] * 1e9) and tf.translation.z == msg["position_m"][2]


def test_lockstep_log_has_the_well_known_channels(hover_lockstep):
    out, _ = hover_lockstep
    check_log_for_foxglove(out / "flight.mcap", truth_hz=200)


@pytest.mark.realtime
def test_real_time_log_has_the_well_known_channels(hover_real_time):
    out, (proc, m) = hover_real_time
    assert m["completed"], proc.stdout + proc.stderr
    check_log_for_foxglove(out / "flight.mcap", truth_hz=None)   # wall clock: no rate asserted
