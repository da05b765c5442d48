"""Foxglove's view of the stack: decoded zenpilot messages as Foxglove well-known messages.

Pure (no I/O): `FoxgloveMap.convert(key, msg)` takes one decoded message (key
zp/<vehicle>/<topic>) and returns the well-known messages it makes, which the live view
(`zenpilot view`, deploy/view.py) serves over the Foxglove WebSocket protocol and the
recorder writes beside the raw channels of flight.mcap. The raw channels (JSON, one per
key) stay the plottable ones: setpoints, attitude, rates, motor outputs, each service's
health; this module adds what Foxglove's 3D panel needs.

Frames: the project's world is ENU (z up) and its body FLU, which are Foxglove's (ROS's)
conventions as they are: no axis change. Only the quaternion's order differs, [w, x, y, z]
here, (x, y, z, w) in Foxglove; `_quaternion` converts it, once, for every message.
Frames named: `world`, `base_link` (the estimate the vehicle flies on: position from
pos/state, attitude from att/state), `base_link_truth` (the simulator's truth).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

from foxglove.messages import (ArrowPrimitive, Color, CubePrimitive, CylinderPrimitive, FrameTransform, Pose,
                               PoseInFrame, Quaternion, SceneEntity, SceneUpdate, Timestamp, Vector3)

from flight.camera import DEFAULT_MARKERS
from flight.quat import quat_from_euler

WORLD = "world"
BODY = "base_link"
BODY_TRUTH = "base_link_truth"

# well-known channels: name -> message class; the topic is foxglove/<vehicle>/<name>
CHANNELS = {
    "tf/truth": FrameTransform,       # world -> base_link_truth
    "tf/estimate": FrameTransform,    # world -> base_link
    "pose/truth": PoseInFrame,        # live view only (poses=True): the transforms carry the same
    "pose/estimate": PoseInFrame,
    "pose/setpoint": PoseInFrame,     # the planner's position and attitude reference
    "pose/vision": PoseInFrame,       # each camera fix (vision/pose)
    "scene/markers": SceneUpdate,     # the floor's marker grid (static, repeated each second)
    "scene/vehicle": SceneUpdate,     # the airframe, locked to base_link and base_link_truth
    "scene/seen": SceneUpdate,        # the markers in the camera's last frame
}

_ESTIMATE_COLOR = Color(r=0.2, g=0.5, b=1.0, a=0.9)
_TRUTH_COLOR = Color(r=0.2, g=0.9, b=0.3, a=0.5)
_MARKER_COLOR = Color(r=0.25, g=0.25, b=0.25, a=1.0)
_SEEN_COLOR = Color(r=1.0, g=0.6, b=0.0, a=1.0)
_IDENTITY = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)


def topic(vehicle_id: int | str, name: str) -> str:
    return f"foxglove/{vehicle_id}/{name}"


def timestamp(t_s: float) -> Timestamp:
    sec = math.floor(t_s)   # split first: wall-clock seconds times 1e9 are past a double's 53 bits
    nsec = int(round((t_s - sec) * 1e9))
    if nsec >= 1_000_000_000:
        sec, nsec = sec + 1, nsec - 1_000_000_000
    return Timestamp(sec=int(sec), nsec=nsec)


_SCHEMAS: dict[type, tuple[str, bytes]] = {}


def schema_of(cls) -> tuple[str, bytes]:
    """(name, data) of a well-known message class's protobuf schema, e.g. foxglove.FrameTransform."""
    found = _SCHEMAS.get(cls)
    if found is None:
        schema = cls.get_schema()
        found = _SCHEMAS[cls] = (schema.name, bytes(schema.data))
    return found


def _quaternion(q_wxyz) -> Quaternion:
    """[w, x, y, z] (zenpilot) -> Foxglove's (x, y, z, w)."""
    return Quaternion(x=q_wxyz[1], y=q_wxyz[2], z=q_wxyz[3], w=q_wxyz[0])


def _vector(v) -> Vector3:
    return Vector3(x=v[0], y=v[1], z=v[2])


def _pose(position, q_wxyz) -> Pose:
    return Pose(position=_vector(position), orientation=_quaternion(q_wxyz))


@dataclass(frozen=True)
class MarkerGrid:
    """The floor's marker grid as flight.camera.marker_grid lays it (ids row-major from
    (-extent, -extent)); defaults: flight.camera.DEFAULT_MARKERS."""
    size_m: float = DEFAULT_MARKERS.size_m
    spacing_m: float = DEFAULT_MARKERS.spacing_m
    half_extent_m: float = DEFAULT_MARKERS.half_extent_m

    @property
    def per_row(self) -> int:
        return int(math.floor(2 * self.half_extent_m / self.spacing_m + 1e-9)) + 1

    @classmethod
    def for_stack(cls, stack) -> "MarkerGrid":
        """The grid a stack's vision service uses: its parameters over the defaults."""
        spec = stack.services.get("vision")
        params = spec.params if spec else {}
        return cls(float(params.get("marker_size_m", DEFAULT_MARKERS.size_m)),
                   float(params.get("marker_spacing_m", DEFAULT_MARKERS.spacing_m)),
                   float(params.get("marker_grid_half_extent_m", DEFAULT_MARKERS.half_extent_m)))

    def centre(self, marker_id: int) -> tuple[float, float] | None:
        n = self.per_row
        if not 0 <= marker_id < n * n:
            return None
        return (-self.half_extent_m + self.spacing_m * (marker_id % n),
                -self.half_extent_m + self.spacing_m * (marker_id // n))


class FoxgloveMap:
    """Converts decoded messages of one vehicle to well-known Foxglove messages.

    Keeps the little state the conversion needs: the newest estimated attitude (the
    estimate's transform is published with each pos/state, attitude from the newest
    att/state) and the second the static scene was last sent in (markers and airframe go
    out once per second of message time, so a viewer that joins late or seeks sees them:
    when a message's second is later than that one, or more than a second earlier; a
    message a little late from one sender, after the next second began, does not send it
    again, as it did ~4 times a second in real time, 47 KB each)."""

    def __init__(self, motor_positions_m, vehicle_id: int | str = 0, markers: MarkerGrid = MarkerGrid(),
                 poses: bool = True):
        """motor_positions_m: the airframe's (flight.vehicle.Vehicle.motor_positions_m), to draw it.
        poses: also PoseInFrame of the truth and the estimate, which repeat their transforms
        (the live view serves them to whoever asks; the flight log leaves them out: a quarter
        more messages for the recorder to write, for nothing the layout shows)."""
        self.poses = poses
        self.vehicle_id = vehicle_id
        self.prefix = f"zp/{vehicle_id}/"
        self.topics = {name: topic(vehicle_id, name) for name in CHANNELS}
        self.markers = markers
        self._attitude: list[float] | None = None
        self._static_second: int | None = None
        self._motors = tuple((float(x), float(y)) for x, y in motor_positions_m)
        self._handled: dict[str, bool] = {}   # per key: whether a handler converts it
        self._handlers = {
            "sim/truth": self._truth,
            "pos/state": self._position_state,
            "att/state": self._attitude_state,
            "planner/setpoint": self._setpoint,
            "vision/pose": self._vision,
            "sim/camera": self._camera,
        }
        size = markers.size_m
        self._marker_cubes = [
            CubePrimitive(pose=Pose(position=Vector3(x=x, y=y, z=0.0), orientation=_IDENTITY),
                          size=Vector3(x=size, y=size, z=0.002), color=_MARKER_COLOR)
            for x, y in (markers.centre(i) for i in range(markers.per_row ** 2))]

    def convert(self, key: str, msg: dict) -> list[tuple[str, object]]:
        """(topic, well-known message) pairs for one decoded message; [] when it makes none."""
        if not key.startswith(self.prefix):
            return []
        handler = self._handlers.get(key[len(self.prefix):])
        t = msg["header"]["t_s"]
        out = self._static(t) if self._static_due(t) else []
        if handler is not None:
            handler(t, msg, out)
        return out

    def wants(self, key: str, t_s: float) -> bool:
        """Whether convert(key, msg) at sample time t_s can make anything: a reader of stored
        messages decodes only those."""
        handled = self._handled.get(key)
        if handled is None:
            handled = key.startswith(self.prefix) and key[len(self.prefix):] in self._handlers
            if len(self._handled) < 4096:   # keys come from the network: bound what is remembered
                self._handled[key] = handled
        return handled or self._static_due(t_s)

    def _static_due(self, t_s: float) -> bool:
        second, last = int(t_s), self._static_second
        return last is None or second > last or second < last - 1

    def encoded(self, key: str, msg: dict) -> list[tuple[str, str, bytes, bytes]]:
        """convert(), encoded for a log: (topic, schema name, schema data, message bytes), the
        schema a protobuf FileDescriptorSet as the SDK ships it (message encoding `protobuf`)."""
        return [(topic_, *schema_of(type(m)), m.encode()) for topic_, m in self.convert(key, msg)]

    def encoded_stored(self, key: str, t_ns: int, data: bytes) -> list[tuple[str, str, bytes, bytes]]:
        """encoded() for a message stored as JSON (a flight log's bus channel), decoding only
        the messages the conversion uses (schemas.flightlog.sort_log's `derive`)."""
        if not self.wants(key, t_ns * 1e-9):
            return []
        return self.encoded(key, json.loads(data))

    # -- per message -----------------------------------------------------------
    def _truth(self, t, msg, out):
        stamp = timestamp(t)
        p, q = msg["position_m"], msg["quaternion_wxyz"]
        out.append((self.topics["tf/truth"], FrameTransform(
            timestamp=stamp, parent_frame_id=WORLD, child_frame_id=BODY_TRUTH,
            translation=_vector(p), rotation=_quaternion(q))))
        if self.poses:
            out.append((self.topics["pose/truth"], PoseInFrame(timestamp=stamp, frame_id=WORLD, pose=_pose(p, q))))

    def _attitude_state(self, t, msg, out):
        self._attitude = msg["quaternion_wxyz"]

    def _position_state(self, t, msg, out):
        if self._attitude is None:   # no attitude estimate yet: no pose to show
            return
        stamp = timestamp(t)
        p, q = msg["position_m"], self._attitude
        out.append((self.topics["tf/estimate"], FrameTransform(
            timestamp=stamp, parent_frame_id=WORLD, child_frame_id=BODY,
            translation=_vector(p), rotation=_quaternion(q))))
        if self.poses:
            out.append((self.topics["pose/estimate"], PoseInFrame(timestamp=stamp, frame_id=WORLD, pose=_pose(p, q))))

    def _setpoint(self, t, msg, out):
        roll, pitch, yaw = msg["attitude_rad"]
        q = quat_from_euler(roll, pitch, yaw)
        out.append((self.topics["pose/setpoint"], PoseInFrame(
            timestamp=timestamp(t), frame_id=WORLD, pose=_pose(msg["position_m"], q))))

    def _vision(self, t, msg, out):
        out.append((self.topics["pose/vision"], PoseInFrame(
            timestamp=timestamp(t), frame_id=WORLD, pose=_pose(msg["position_m"], msg["quaternion_wxyz"]))))

    def _camera(self, t, msg, out):
        size = self.markers.size_m
        cubes = []
        for marker_id in msg["marker_ids"]:
            c = self.markers.centre(marker_id)
            if c is not None:   # an id off the grid: nothing to draw
                cubes.append(CubePrimitive(pose=Pose(position=Vector3(x=c[0], y=c[1], z=0.005), orientation=_IDENTITY),
                                           size=Vector3(x=size, y=size, z=0.01), color=_SEEN_COLOR))
        out.append((self.topics["scene/seen"], SceneUpdate(entities=[SceneEntity(
            timestamp=timestamp(t), frame_id=WORLD, id="seen", cubes=cubes)])))

    # -- the static scene ------------------------------------------------------
    def _static(self, t) -> list[tuple[str, object]]:
        self._static_second = int(t)
        stamp = timestamp(t)
        markers = SceneUpdate(entities=[SceneEntity(timestamp=stamp, frame_id=WORLD, id="markers",
                                                    cubes=self._marker_cubes)])
        vehicle = SceneUpdate(entities=[self._airframe(stamp, BODY, "vehicle/estimate", _ESTIMATE_COLOR),
                                        self._airframe(stamp, BODY_TRUTH, "vehicle/truth", _TRUTH_COLOR)])
        return [(self.topics["scene/markers"], markers), (self.topics["scene/vehicle"], vehicle)]

    def _airframe(self, stamp, frame, entity_id, color) -> SceneEntity:
        """Arms to each motor, a rotor disc per motor and an arrow forward (body +x)."""
        arm_len = max(math.hypot(x, y) for x, y in self._motors)
        rotor = 1.2 * arm_len
        cubes = [CubePrimitive(
            pose=Pose(position=Vector3(x=x / 2, y=y / 2, z=0.0),
                      orientation=_quaternion(quat_from_euler(0.0, 0.0, math.atan2(y, x)))),
            size=Vector3(x=math.hypot(x, y), y=0.012, z=0.012), color=color) for x, y in self._motors]
        cylinders = [CylinderPrimitive(
            pose=Pose(position=Vector3(x=x, y=y, z=0.02), orientation=_IDENTITY),
            size=Vector3(x=rotor, y=rotor, z=0.005), bottom_scale=1.0, top_scale=1.0, color=color)
            for x, y in self._motors]
        arrows = [ArrowPrimitive(pose=Pose(position=Vector3(x=0.0, y=0.0, z=0.03), orientation=_IDENTITY),
                                 shaft_length=arm_len, shaft_diameter=0.01, head_length=0.3 * arm_len,
                                 head_diameter=0.03, color=color)]
        return SceneEntity(timestamp=stamp, frame_id=frame, id=entity_id, frame_locked=True,
                           cubes=cubes, cylinders=cylinders, arrows=arrows)
