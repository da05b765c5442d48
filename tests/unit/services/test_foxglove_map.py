"""services/foxglove_map.py: decoded zenpilot messages -> Foxglove well-known messages.

The messages are checked as Foxglove reads them: encoded by the SDK, decoded with
protobuf from the schema the SDK ships (not through the SDK's own objects)."""

import math

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from flight.camera import marker_grid
from flight.quat import quat_from_euler, rotate_vector
from flight.vehicle import load_vehicle
from services.foxglove_map import BODY, BODY_TRUTH, CHANNELS, WORLD, FoxgloveMap, MarkerGrid, timestamp

_classes = {}


def decode(msg):
    """The protobuf message Foxglove gets, decoded with the schema's own descriptors."""
    schema = type(msg).get_schema()
    assert schema.encoding == "protobuf" and schema.name.startswith("foxglove.")
    if schema.name not in _classes:
        pool = descriptor_pool.DescriptorPool()
        for fd in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
            pool.Add(fd)
        _classes[schema.name] = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
    return _classes[schema.name].FromString(msg.encode())


def header(t, source="sim"):
    return {"t_s": t, "seq": 0, "source": source}


@pytest.fixture
def fmap():
    return FoxgloveMap(load_vehicle("x250").motor_positions_m)


def by_topic(pairs):
    return {topic.split("/", 2)[2]: decode(m) for topic, m in pairs}


def test_truth_gives_transform_and_pose_with_xyzw_quaternion(fmap):
    q = quat_from_euler(0.1, -0.2, 0.7)   # [w, x, y, z]
    out = by_topic(fmap.convert("zp/0/sim/truth", {"header": header(12.345), "position_m": [1.0, -2.0, 3.5],
                                                   "quaternion_wxyz": list(q)}))
    tf = out["tf/truth"]
    assert (tf.parent_frame_id, tf.child_frame_id) == (WORLD, BODY_TRUTH)
    assert (tf.timestamp.seconds, tf.timestamp.nanos) == (12, 345_000_000)
    assert [tf.translation.x, tf.translation.y, tf.translation.z] == [1.0, -2.0, 3.5]
    r = tf.rotation
    assert [r.x, r.y, r.z, r.w] == pytest.approx([q[1], q[2], q[3], q[0]])
    pose = out["pose/truth"]
    assert pose.frame_id == WORLD and pose.pose.orientation.w == pytest.approx(q[0])
    assert pose.pose.position.z == 3.5


def test_rotation_means_the_same_in_foxglove(fmap):
    """A body-forward vector rotated with Foxglove's (x, y, z, w) equals the project's rotation."""
    q = quat_from_euler(0.3, 0.2, 1.1)
    r = by_topic(fmap.convert("zp/0/sim/truth", {"header": header(0.0), "position_m": [0, 0, 0],
                                                  "quaternion_wxyz": list(q)}))["tf/truth"].rotation
    x, y, z, w = r.x, r.y, r.z, r.w   # Hamilton product as Foxglove (three.js) applies it
    v = np.array([1.0, 0.0, 0.0])
    u = np.array([x, y, z])
    rotated = v + 2 * w * np.cross(u, v) + 2 * np.cross(u, np.cross(u, v))
    assert rotated == pytest.approx(rotate_vector(q, v))


def test_estimate_needs_an_attitude_then_combines_position_and_attitude(fmap):
    state = {"header": header(1.0, "position"), "position_m": [0.5, 0.25, 1.0]}
    assert "tf/estimate" not in by_topic(fmap.convert("zp/0/pos/state", state))
    q = quat_from_euler(0.0, 0.0, math.pi / 2)
    assert fmap.convert("zp/0/att/state", {"header": header(1.005, "attitude"), "quaternion_wxyz": list(q)}) == []
    out = by_topic(fmap.convert("zp/0/pos/state", {**state, "header": header(1.01, "position")}))
    tf = out["tf/estimate"]
    assert (tf.parent_frame_id, tf.child_frame_id) == (WORLD, BODY)
    assert [tf.translation.x, tf.translation.y, tf.translation.z] == [0.5, 0.25, 1.0]
    assert tf.rotation.z == pytest.approx(math.sin(math.pi / 4))
    assert out["pose/estimate"].pose.position.x == 0.5


def test_setpoint_and_vision_poses(fmap):
    out = by_topic(fmap.convert("zp/0/planner/setpoint", {"header": header(2.0, "planner"), "position_m": [1, 2, 3],
                                                          "attitude_rad": [0.0, 0.0, math.pi]}))
    sp = out["pose/setpoint"].pose
    assert [sp.position.x, sp.position.y, sp.position.z] == [1, 2, 3]
    assert abs(sp.orientation.z) == pytest.approx(1.0)
    out = by_topic(fmap.convert("zp/0/vision/pose", {"header": header(2.05, "vision"), "position_m": [0.1, 0.2, 0.9],
                                                     "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0]}))
    assert out["pose/vision"].pose.position.z == pytest.approx(0.9)


def test_seen_markers_at_their_grid_centres(fmap):
    ids, corners = marker_grid(0.2, 0.5, 5.0)
    seen = [0, 7, 220, 440]
    out = by_topic(fmap.convert("zp/0/sim/camera", {"header": header(3.0), "marker_ids": seen + [99999],
                                                    "corners_px": []}))
    entity = out["scene/seen"].entities[0]
    assert entity.frame_id == WORLD and len(entity.cubes) == len(seen)   # the id off the grid is skipped
    for cube, marker_id in zip(entity.cubes, seen):
        centre = corners[marker_id].mean(axis=0)
        assert [cube.pose.position.x, cube.pose.position.y] == pytest.approx(centre[:2])


def test_static_scene_once_per_second_of_message_time(fmap):
    truth = {"position_m": [0, 0, 0], "quaternion_wxyz": [1, 0, 0, 0]}
    first = by_topic(fmap.convert("zp/0/sim/truth", {**truth, "header": header(0.0)}))
    assert len(first["scene/markers"].entities[0].cubes) == MarkerGrid().per_row ** 2 == 441
    frames = {e.frame_id for e in first["scene/vehicle"].entities}
    assert frames == {BODY, BODY_TRUTH} and all(e.frame_locked for e in first["scene/vehicle"].entities)
    assert len(first["scene/vehicle"].entities[0].cylinders) == 4   # one rotor per motor of the x250
    assert "scene/markers" not in by_topic(fmap.convert("zp/0/sim/truth", {**truth, "header": header(0.99)}))
    assert "scene/markers" in by_topic(fmap.convert("zp/0/sim/truth", {**truth, "header": header(1.0)}))


def test_static_scene_not_again_for_a_message_a_little_late(fmap):
    """Real time: messages arrive out of sample-time order around a second's start; only a jump
    back of more than a second (another clock) sends the scene again."""
    truth = {"position_m": [0, 0, 0], "quaternion_wxyz": [1, 0, 0, 0]}

    def sends(t):
        return "scene/markers" in by_topic(fmap.convert("zp/0/sim/truth", {**truth, "header": header(t)}))

    assert [sends(t) for t in (10.98, 11.01, 10.99, 11.02, 10.97, 12.0, 11.5, 9.9, 12.1)] == \
        [True, True, False, False, False, True, False, True, True]


def test_other_vehicles_and_keys_make_nothing(fmap):
    truth = {"header": header(0.0), "position_m": [0, 0, 0], "quaternion_wxyz": [1, 0, 0, 0]}
    assert fmap.convert("zp/1/sim/truth", truth) == []
    fmap.convert("zp/0/sim/truth", truth)
    assert fmap.convert("zp/0/motors/pwm", {"header": header(0.5, "motors")}) == []


def test_every_channel_is_a_well_known_schema(fmap):
    for name, cls in CHANNELS.items():
        assert cls.get_schema().name == f"foxglove.{cls.__name__}", name


def test_timestamp_rounds_to_the_nanosecond():
    t = timestamp(1.9999999999)
    assert (t.sec, t.nsec) == (2, 0)
    t = timestamp(1712345678.25)
    assert (t.sec, t.nsec) == (1712345678, 250_000_000)


def test_shipped_layout_is_the_generated_one_and_its_plots_name_real_fields():
    import json
    import re

    import schemas
    from deploy.foxglove_layout import LAYOUT_PATH, layout_json

    assert LAYOUT_PATH.read_text() == layout_json(0), "regenerate: python -m deploy.foxglove_layout"
    values = re.findall(r'"value": "([^"]+)"', LAYOUT_PATH.read_text())
    assert len(values) >= 20
    for value in values:
        m = re.fullmatch(r"(zp/0/[a-z_/]+)\.([a-z_0-9]+)(?:\[(\d)\])?", value)
        assert m, value
        definition = schemas.message_for_key(m.group(1))
        assert definition is not None, value
        f = {f.name: f for f in definition.fields}.get(m.group(2))
        assert f is not None, value
        assert (m.group(3) is None) == (f.length is None) and (f.length is None or int(m.group(3)) < f.length), value
    topics = json.loads(LAYOUT_PATH.read_text())["content"]["items"][0]["content"]["config"]["topics"]
    assert set(topics) <= {f"foxglove/0/{name}" for name in CHANNELS}


def test_wants_says_which_stored_messages_to_decode(fmap):
    assert fmap.wants("zp/0/motors/pwm", 0.0)          # nothing sent yet: the static scene is due
    fmap.convert("zp/0/sim/imu", {"header": header(0.0)})
    assert not fmap.wants("zp/0/motors/pwm", 0.5) and not fmap.wants("zp/0/sim/imu", 0.9)
    assert fmap.wants("zp/0/sim/truth", 0.5) and fmap.wants("zp/0/att/state", 0.5)
    assert fmap.wants("zp/0/motors/pwm", 1.0)          # a new second: the static scene again


def test_marker_grid_follows_the_stack_vision_parameters():
    from services.stack import load_stack
    from simulator.config import SimConfig

    grid = MarkerGrid.for_stack(load_stack())
    c = SimConfig()
    assert (grid.size_m, grid.spacing_m, grid.half_extent_m) == (
        c.marker_size_m, c.marker_spacing_m, c.marker_grid_half_extent_m)


def test_poses_can_be_left_to_the_transforms():
    fmap = FoxgloveMap(load_vehicle("x250").motor_positions_m, poses=False)
    out = by_topic(fmap.convert("zp/0/sim/truth", {"header": header(0.5), "position_m": [0, 0, 1],
                                                   "quaternion_wxyz": [1, 0, 0, 0]}))
    assert "tf/truth" in out and "pose/truth" not in out
