"""A minimal MAVLink ground station over UDP (pymavlink) for the MAVLink tests and benches:
heartbeats, commands with retransmission, take-off and landing as QGroundControl does them."""

import os
import socket
import time

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink is imported: MAVLink 2 framing
os.environ.setdefault("MAVLINK_DIALECT", "common")
from pymavlink import mavutil  # noqa: E402

mavlink = mavutil.mavlink


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Gcs:
    """A minimal ground station: heartbeats at 2 Hz while it waits for anything."""

    def __init__(self, port: int):
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190)
        self.next_hb = 0.0
        self.latest: dict = {}
        self.heartbeat_times: list[float] = []

    def pump(self):
        now = time.monotonic()
        if now >= self.next_hb and self.conn.clients:
            self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            self.next_hb = now + 0.5
        m = self.conn.recv_match(blocking=True, timeout=0.05)
        if m is not None and m.get_srcSystem() == 1:
            self.latest[m.get_type()] = m
            if m.get_type() == "HEARTBEAT":
                self.heartbeat_times.append(time.monotonic())
        return m

    def wait(self, kind: str, cond=lambda m: True, timeout: float = 10.0):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            m = self.pump()
            if m is not None and m.get_type() == kind and m.get_srcSystem() == 1 and cond(m):
                return m
        shown = {k: str(v) for k, v in self.latest.items() if k in ("HEARTBEAT", "LOCAL_POSITION_NED", "STATUSTEXT")}
        raise AssertionError(f"no {kind} matching within {timeout} s; latest: {shown}")

    def command(self, command: int, *params, timeout: float = 5.0, confirmation: int = 0):
        p = list(params) + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(1, 1, command, confirmation, *p)
        return self.wait("COMMAND_ACK", lambda m: m.command == command, timeout)

    def command_retransmitted(self, command: int, *params, every_s: float = 3.0, timeout: float = 45.0):
        """The MAVLink command protocol: a command without an ACK is sent again (confirmation
        counting up), as QGroundControl and MAVSDK do; UDP may drop a datagram."""
        deadline = time.monotonic() + timeout
        confirmation = 0
        while True:
            try:
                return self.command(command, *params, timeout=every_s, confirmation=min(confirmation, 255))
            except AssertionError:
                if time.monotonic() > deadline:
                    raise
                confirmation += 1

    def command_until_accepted(self, command: int, *params, timeout: float = 20.0):
        deadline = time.monotonic() + timeout
        while True:
            ack = self.command(command, *params)
            if ack.result == mavlink.MAV_RESULT_ACCEPTED or time.monotonic() > deadline:
                return ack
            self.wait("HEARTBEAT", timeout=3.0)  # health arrives at 1 Hz


def takeoff(gcs, altitude_m):
    gcs.wait("HEARTBEAT", timeout=20.0)  # the UDP peer is known only once the bridge has spoken
    ack = gcs.command_until_accepted(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED, ack
    gcs.wait("HEARTBEAT", lambda m: m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
    ack = gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, altitude_m)
    assert ack.result == mavlink.MAV_RESULT_IN_PROGRESS, ack   # a long command: progress, then the result
    ack = gcs.wait("COMMAND_ACK", lambda m: m.command == mavlink.MAV_CMD_NAV_TAKEOFF
                   and m.result != mavlink.MAV_RESULT_IN_PROGRESS, timeout=40.0)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED, ack
    gcs.wait("LOCAL_POSITION_NED", lambda m: abs(m.z + altitude_m) < 0.08, timeout=40.0)


def land(gcs):
    # after a minute of flood a command datagram may be lost: retransmit until acknowledged
    ack = gcs.command_retransmitted(mavlink.MAV_CMD_NAV_LAND)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED, ack
    gcs.wait("HEARTBEAT", lambda m: not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED, timeout=30.0)
    gcs.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND)
