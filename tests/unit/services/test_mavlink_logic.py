"""The MAVLink bridge's logic against a pymavlink "ground station", over a byte buffer."""

import math
import random

import pytest

from flight.quat import quat_from_euler
from services.mavlink_logic import (
    MODES,
    STREAMS,
    Bridge,
    BRIDGE_PARAM_DEFAULTS,
    BridgeConfig,
    LinkFailsafe,
    ParamTable,
    mavlink,
)

NOW = 1000.0


class Wire:
    def __init__(self):
        self.buf = bytearray()

    def write(self, b):
        self.buf += b


def header(t=NOW):
    return {"t_s": t, "seq": 0, "source": "test"}


def setpoint(armed=False, phase="waiting", z=0.0):
    return {"header": header(), "mode": "position" if armed else "idle", "armed": armed,
            "position_m": [0.0, 0.0, z], "attitude_rad": [0.0, 0.0, 0.3], "item": 0, "phase": phase,
            "measure": False, "mission_state": "waiting" if phase == "waiting" else "running"}


def healthy(bridge, services=("sim", "attitude", "position", "motors", "planner", "vision")):
    for s in services:
        bridge.health[s] = (NOW, {"state": "running"})


@pytest.fixture
def link():
    wire = Wire()
    mav = mavlink.MAVLink(wire, srcSystem=1, srcComponent=1)
    counts = {}
    params = ParamTable({("attitude", "k"): [16.0, 16.0, 16.0], ("attitude", "alpha"): [16.0] * 3,
                         ("position", "k"): [4.0] * 3, ("position", "alpha"): [4.0] * 3,
                         ("position", "max_tilt_deg"): 35.0})
    bridge = Bridge(mav, BridgeConfig(gcs_timeout_s=2.0, failsafe_hold_s=1.0), params,
                    ("sim", "attitude", "position", "motors", "planner", "vision"), counts, t_origin_s=900.0)
    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    vehicle_parser = mavlink.MAVLink(None)

    def send(msg):
        """GCS -> bridge: pack with the GCS, parse as the vehicle would, handle."""
        parsed = vehicle_parser.parse_buffer(msg.pack(gcs))
        actions = []
        for m in parsed or []:
            actions += bridge.handle(m, NOW, NOW)
        return actions

    def received():
        msgs = gcs.parse_buffer(bytes(wire.buf)) or []
        wire.buf.clear()
        return msgs

    bridge.inputs["att"] = {"header": header(NOW - 0.005), "quaternion_wxyz": list(quat_from_euler(0.1, -0.2, 0.0)),
                            "rate_rad_s": [0.01, 0.02, 0.03]}
    bridge.inputs["pos"] = {"header": header(NOW - 0.01), "position_m": [1.0, 2.0, 0.0],
                            "velocity_m_s": [0.1, 0.2, 0.3]}
    bridge.inputs["setpoint"] = setpoint()
    bridge.ground_stations.add(255)   # as if its GCS heartbeat had been heard (without arming the failsafe)
    return bridge, gcs, send, received, counts


def test_actions_only_from_a_ground_station(link):
    bridge, _, _, received, counts = link
    stranger = mavlink.MAVLink(None, srcSystem=42, srcComponent=1)
    parser = mavlink.MAVLink(None)

    def send_from(sender, msg):
        return [a for m in parser.parse_buffer(msg.pack(sender)) or [] for a in bridge.handle(m, NOW, NOW)]

    arm = stranger.command_long_encode(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    assert send_from(stranger, arm) == [] and counts["mavlink_not_from_gcs"] == 1
    acks = [m for m in received() if m.get_type() == "COMMAND_ACK"]
    assert acks and acks[-1].result == mavlink.MAV_RESULT_DENIED      # answered, not obeyed
    unknown = stranger.command_long_encode(1, 1, 31000, 0, 0, 0, 0, 0, 0, 0, 0)
    send_from(stranger, unknown)
    assert [m for m in received() if m.get_type() == "COMMAND_ACK"][-1].result == mavlink.MAV_RESULT_UNSUPPORTED
    send_from(stranger, stranger.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0))
    send_from(stranger, arm)
    assert counts["mavlink_not_from_gcs"] == 1                         # now it is a ground station


def long(gcs, command, *params):
    p = list(params) + [0.0] * (7 - len(params))
    return gcs.command_long_encode(1, 1, command, 0, *p)


def acks(msgs):
    return [m for m in msgs if m.get_type() == "COMMAND_ACK"]


def test_streams_carry_ned_frd_telemetry(link):
    bridge, gcs, send, received, _ = link
    bridge.tick(NOW, NOW)
    got = {m.get_type(): m for m in received()}
    hb = got["HEARTBEAT"]
    assert hb.type == mavlink.MAV_TYPE_QUADROTOR and hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
    assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED and hb.custom_mode == MODES["hold"]
    assert hb.custom_mode == (4 << 16) | (3 << 24)  # PX4's AUTO.LOITER: MAVSDK's "Hold"
    att = got["ATTITUDE"]
    assert att.roll == pytest.approx(0.1) and att.pitch == pytest.approx(0.2)  # nose-up: + in FRD
    assert att.yaw == pytest.approx(math.pi / 2)  # ENU yaw 0 = east = 90 deg in NED
    assert att.pitchspeed == pytest.approx(-0.02) and att.yawspeed == pytest.approx(-0.03)
    assert att.time_boot_ms == 99995
    lp = got["LOCAL_POSITION_NED"]
    assert (lp.x, lp.y, lp.z) == pytest.approx((2.0, 1.0, -0.0)) and lp.vz == pytest.approx(-0.3)
    assert got["GLOBAL_POSITION_INT"].lat > 473977420 and got["GLOBAL_POSITION_INT"].hdg == 9000
    assert got["EXTENDED_SYS_STATE"].landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND
    assert "HOME_POSITION" in got and "SYS_STATUS" in got


def test_wind_cov_carries_the_ekf_wind_only_when_estimated(link):
    """WIND_COV (as PX4 sends it): the EKF's disturbance times mass / drag, ENU x, y -> NED east,
    north; nothing without the wind estimation (its disturbance is then held at 0) or its health."""
    bridge, gcs, send, received, _ = link
    assert not bridge.send_stream("WIND_COV", NOW, NOW)   # no pos/ekf_health yet
    bridge.cfg.wind_per_accel_s = 4.0                      # the x250: 0.4 kg / 0.1 N s/m
    ekf = {"header": header(NOW - 0.8), "disturbance_m_s2": [0.5, -0.1], "disturbance_estimated": False}
    bridge.inputs["ekf"] = ekf
    assert not bridge.send_stream("WIND_COV", NOW, NOW)
    ekf["disturbance_estimated"] = True
    assert bridge.send_stream("WIND_COV", NOW, NOW)
    (wind,) = [m for m in received() if m.get_type() == "WIND_COV"]
    assert (wind.wind_x, wind.wind_y) == pytest.approx((-0.4, 2.0)) and math.isnan(wind.wind_z)
    assert wind.time_usec == int((NOW - 0.8 - 900.0) * 1e6)
    ekf["header"] = header(NOW - 3.0)                      # its 1 Hz health lost: no wind
    assert not bridge.send_stream("WIND_COV", NOW, NOW)


def test_sys_status_health_bits_follow_service_health(link):
    bridge, gcs, send, received, _ = link
    healthy(bridge)
    bridge.health["attitude"] = (NOW - 10.0, {"state": "running"})  # stale estimator
    bridge.send_stream("SYS_STATUS", NOW, NOW)
    st = [m for m in received() if m.get_type() == "SYS_STATUS"][0]
    ahrs = mavlink.MAV_SYS_STATUS_AHRS
    assert st.onboard_control_sensors_present & ahrs and not st.onboard_control_sensors_health & ahrs
    gyro = mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
    assert st.onboard_control_sensors_health & gyro


def test_arm_takeoff_land_disarm_commands(link):
    bridge, gcs, send, received, _ = link
    # estimator unhealthy: arming refused with the reason
    assert send(long(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)) == []
    msgs = received()
    assert acks(msgs)[0].result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    assert any(m.get_type() == "STATUSTEXT" and b"not healthy" in m.text.encode() for m in msgs)
    healthy(bridge)
    # takeoff before arming: rejected
    send(long(gcs, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0))
    assert acks(received())[0].result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    # MAVSDK's arm: NaN in the unused param2 ("no value", the command protocol)
    actions = send(long(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0, math.nan, math.nan))
    assert acks(received())[0].result == mavlink.MAV_RESULT_ACCEPTED
    assert actions == [("command", {"command": "arm", "altitude_m": 0.0, "position_m": [0.0, 0.0, 0.0],
                                    "yaw_rad": 0.0, "origin": "mavlink:255/190"})]
    send(long(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, math.nan))  # the used param1: no default
    assert acks(received())[0].result == mavlink.MAV_RESULT_DENIED
    bridge.inputs["setpoint"] = setpoint(armed=True, phase="arm")
    # NaN altitude (MAVSDK with PX4): MIS_TAKEOFF_ALT; IN_PROGRESS until the planner's takeoff is done
    actions = send(long(gcs, mavlink.MAV_CMD_NAV_TAKEOFF, *[math.nan] * 7))
    ack = acks(received())[0]
    assert ack.result == mavlink.MAV_RESULT_IN_PROGRESS and ack.progress == 0
    assert actions[0][1]["command"] == "takeoff" and actions[0][1]["altitude_m"] == 2.0
    bridge.inputs["setpoint"] = setpoint(armed=True, phase="takeoff", z=1.0)
    bridge.inputs["pos"]["position_m"] = [0.0, 0.0, 1.0]
    assert send(long(gcs, mavlink.MAV_CMD_NAV_TAKEOFF, *[math.nan] * 7)) == []  # a repeat: still climbing
    ack = acks(received())[0]
    assert ack.result == mavlink.MAV_RESULT_IN_PROGRESS and ack.progress == 50
    hb = [m for m in (bridge.send_stream("HEARTBEAT", NOW, NOW), received())[1] if m.get_type() == "HEARTBEAT"][-1]
    assert hb.custom_mode == MODES["takeoff"]
    bridge.inputs["setpoint"] = setpoint(armed=True, phase="hold", z=2.0)
    bridge.inputs["pos"]["position_m"] = [0.0, 0.0, 2.0]
    bridge.tick(NOW + 1.0, NOW + 1.0)
    final = [a for a in acks(received()) if a.command == mavlink.MAV_CMD_NAV_TAKEOFF]
    assert [a.result for a in final] == [mavlink.MAV_RESULT_ACCEPTED] and final[0].target_system == 255
    # disarm in the air: denied unless forced
    send(long(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.0))
    assert acks(received())[0].result == mavlink.MAV_RESULT_DENIED
    assert send(long(gcs, mavlink.MAV_CMD_NAV_LOITER_UNLIM))[0][1]["command"] == "hold"
    assert send(long(gcs, mavlink.MAV_CMD_NAV_LAND))[0][1]["command"] == "land"
    bridge.mode = "hold"
    # DO_SET_MODE as MAVSDK sends it for PX4: param2 main mode (AUTO), param3 sub mode (LAND)
    assert send(long(gcs, mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                     4, 6, math.nan))[0][1]["command"] == "land"
    received()
    send(long(gcs, mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 1))  # MANUAL
    msgs = received()
    assert acks(msgs)[0].result == mavlink.MAV_RESULT_DENIED
    assert any(m.get_type() == "STATUSTEXT" and "not flown" in m.text for m in msgs)
    send(long(gcs, mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4, 4))  # MISSION
    msgs = received()
    assert acks(msgs)[0].result == mavlink.MAV_RESULT_DENIED
    assert any(m.get_type() == "STATUSTEXT" and "no mission" in m.text for m in msgs)
    rtl = send(long(gcs, mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH))
    assert rtl[0][0] == "mission" and rtl[0][1]["types"] == ["goto", "land"]
    assert rtl[0][1]["position_m"][:3] == [0.0, 0.0, 2.0] and bridge.mode_name() == "return"
    forced = send(long(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.0, 21196.0))
    assert forced[0][1]["command"] == "disarm"


def test_unknown_command_is_unsupported_and_others_not_for_us_ignored(link):
    bridge, gcs, send, received, _ = link
    send(long(gcs, 31337))
    ack = acks(received())[0]
    assert ack.command == 31337 and ack.result == mavlink.MAV_RESULT_UNSUPPORTED
    assert ack.target_system == 255 and ack.target_component == 190
    send(gcs.command_long_encode(7, 1, mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0))  # system 7
    assert acks(received()) == []
    # COMMAND_INT goes through the same table
    send(gcs.command_int_encode(1, 1, 0, 4242, 0, 0, 0, 0, 0, 0, 0, 0, 0.0))
    assert acks(received())[0].result == mavlink.MAV_RESULT_UNSUPPORTED


def test_message_interval_and_request_message(link):
    bridge, gcs, send, received, _ = link
    send(long(gcs, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 30, 100000))  # ATTITUDE at 10 Hz
    assert acks(received())[0].result == mavlink.MAV_RESULT_ACCEPTED
    assert bridge.intervals_s["ATTITUDE"] == pytest.approx(0.1)
    send(long(gcs, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 32, -1))  # LOCAL_POSITION_NED off
    received()
    bridge.next_due = {n: 0.0 for n in STREAMS}
    bridge.tick(NOW, NOW)
    assert "LOCAL_POSITION_NED" not in {m.get_type() for m in received()}
    send(long(gcs, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 9999, 1000))
    assert acks(received())[0].result == mavlink.MAV_RESULT_UNSUPPORTED
    send(long(gcs, mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION))
    msgs = received()
    assert acks(msgs)[0].result == mavlink.MAV_RESULT_ACCEPTED
    version = [m for m in msgs if m.get_type() == "AUTOPILOT_VERSION"][0]
    assert version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    send(long(gcs, mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_HOME_POSITION))
    assert "HOME_POSITION" in {m.get_type() for m in received()}


def test_parameter_protocol(link):
    bridge, gcs, send, received, counts = link
    send(gcs.param_request_list_encode(1, 1))
    values = [m for m in received() if m.get_type() == "PARAM_VALUE"]
    names = [v.param_id for v in values]
    assert len(values) == 13 and "ATT_K_R" in names and "POS_ALPHA_Z" in names and "POS_MAX_TILT" in names
    assert all(v.param_count == 13 for v in values) and [v.param_index for v in values] == list(range(13))
    send(gcs.param_request_read_encode(1, 1, b"POS_K_Y", -1))
    v = received()[0]
    assert v.param_id == "POS_K_Y" and v.param_value == 4.0
    actions = send(gcs.param_set_encode(1, 1, b"ATT_K_P", 12.0, mavlink.MAV_PARAM_TYPE_REAL32))
    assert actions == [("param", {"service": "attitude", "key": "k", "value": [16.0, 12.0, 16.0]})]
    v = received()[0]
    assert v.param_id == "ATT_K_P" and v.param_value == 12.0
    # out of bounds: refused (PARAM_ERROR), the old value echoed
    assert send(gcs.param_set_encode(1, 1, b"ATT_K_P", -5.0, mavlink.MAV_PARAM_TYPE_REAL32)) == []
    msgs = received()
    assert [m.param_value for m in msgs if m.get_type() == "PARAM_VALUE"] == [12.0]
    assert [m.error for m in msgs if m.get_type() == "PARAM_ERROR"] == [mavlink.MAV_PARAM_ERROR_VALUE_OUT_OF_RANGE]
    assert send(gcs.param_set_encode(1, 1, b"NO_SUCH", 1.0, mavlink.MAV_PARAM_TYPE_REAL32)) == []
    # an unknown name is answered at once: PARAM_ERROR (DOES_NOT_EXIST), to the asker
    send(gcs.param_request_read_encode(1, 1, b"NOT_THERE", -1))
    errors = [m for m in received() if m.get_type() == "PARAM_ERROR"]
    assert errors[-1].param_id == "NOT_THERE" and errors[-1].error == mavlink.MAV_PARAM_ERROR_DOES_NOT_EXIST
    assert errors[-1].target_system == 255
    send(gcs.param_request_read_encode(1, 1, b"", 99))  # by index, past the end
    assert [m.get_type() for m in received()] == ["PARAM_ERROR"]
    assert counts["mavlink_unknown_param"] == 3 and counts["mavlink_bad_value"] == 1


def test_bridge_parameters_come_from_the_one_table():
    from services.mavlink import PARAMS
    table = ParamTable({("mavlink", k): PARAMS[k].default for k in BRIDGE_PARAM_DEFAULTS})
    assert [r["name"] for r in table.rows] == ["MIS_TAKEOFF_ALT", "RTL_RETURN_ALT", "NAV_ACC_RAD", "COM_OF_LOSS_T"]
    assert table.own("takeoff_alt_m") == PARAMS["takeoff_alt_m"].default


def test_offboard_position_and_velocity_targets_with_timeout(link):
    bridge, gcs, send, received, counts = link
    position = 0b110111111000   # MAVSDK's set_position_ned: position and yaw
    target = gcs.set_position_target_local_ned_encode(0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, position,
                                                      1.0, 2.0, -3.0, 0, 0, 0, 0, 0, 0, 0, 0)
    offboard = long(gcs, mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 6)
    send(offboard)  # no setpoint streamed yet: refused, as PX4 does
    assert acks(received())[0].result == mavlink.MAV_RESULT_DENIED
    bridge.inputs["setpoint"] = setpoint(armed=True, phase="hold", z=2.0)
    bridge.inputs["pos"]["position_m"] = [0.0, 0.0, 2.0]
    assert send(target) == []                  # kept, not flown: not in offboard mode
    assert bridge.tick(NOW, NOW) == []
    send(offboard)
    assert acks(received())[0].result == mavlink.MAV_RESULT_ACCEPTED
    (kind, cmd), = bridge.tick(NOW + 0.02, NOW + 0.02)
    assert kind == "command" and cmd["command"] == "goto"
    assert cmd["position_m"] == pytest.approx([2.0, 1.0, 3.0]) and cmd["yaw_rad"] == pytest.approx(0.3)
    send(target)
    assert bridge.tick(NOW + 0.04, NOW + 0.04) == []  # the same target again: nothing new
    hb = [m for m in (bridge.send_stream("HEARTBEAT", NOW, NOW), received())[1] if m.get_type() == "HEARTBEAT"][-1]
    assert hb.custom_mode == MODES["offboard"]
    # velocity (MAVSDK's set_velocity_ned): the target moves at it on the stack's clock
    velocity = 0b110111000111
    bridge.inputs["pos"]["position_m"] = [2.0, 1.0, 3.0]
    send(gcs.set_position_target_local_ned_encode(0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, velocity,
                                                  0, 0, 0, 1.0, 0.0, 0.0, 0, 0, 0, 0, 0))  # north 1 m/s
    (_, cmd), = bridge.tick(NOW + 0.14, NOW + 0.14)
    assert cmd["position_m"] == pytest.approx([2.0, 1.1, 3.0])
    # setpoints stop: after COM_OF_LOSS_T the vehicle holds
    actions = bridge.tick(NOW + 1.5, NOW + 1.5)
    assert actions[-1][1]["command"] == "hold" and bridge.mode_name() == "hold"
    nan = gcs.set_position_target_local_ned_encode(0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, 0, math.nan, 0, 0,
                                                   0, 0, 0, 0, 0, 0, 0, 0)
    assert send(nan) == [] and counts["mavlink_bad_value"] == 1


def test_a_bridge_that_ran_late_judges_the_streams_by_its_socket(link):
    """The bridge's loop stalled past COM_OF_LOSS_T and the GCS timeout (a busy machine) while
    MAVSDK kept streaming: the setpoint and heartbeat waiting on the socket are read before the
    timers judge, so neither offboard nor the link failsafe fires. A stream that really stopped does."""
    bridge, gcs, send, received, counts = link
    parser = mavlink.MAVLink(None)
    bridge.inputs["setpoint"] = setpoint(armed=True, phase="hold", z=2.0)
    bridge.inputs["pos"]["position_m"] = [0.0, 0.0, 2.0]
    position = 0b110111111000
    target = gcs.set_position_target_local_ned_encode(0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, position,
                                                      1.0, 0.0, -2.0, 0, 0, 0, 0, 0, 0, 0, 0)
    heartbeat = gcs.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    send(heartbeat)
    send(target)
    send(long(gcs, mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 6))
    assert bridge.cycle(NOW, NOW, [])[0][1]["command"] == "goto"
    late = NOW + 2.5   # past COM_OF_LOSS_T (1 s) and the GCS timeout (2 s)
    waiting = parser.parse_buffer(heartbeat.pack(gcs) + target.pack(gcs))
    actions = bridge.cycle(late, late, iter(waiting))
    assert all(a[1]["command"] not in ("hold", "land") for a in actions), actions
    assert bridge.mode_name() == "offboard" and bridge.failsafe.state == "ok"
    actions = bridge.cycle(late + 1.5, late + 1.5, iter([]))   # nothing came: lost
    assert [a[1]["command"] for a in actions] == ["hold"] and bridge.mode_name() == "hold"


def upload(send, received, gcs, items):
    """The GCS side of a mission upload; returns the final MISSION_ACK."""
    send(gcs.mission_count_encode(1, 1, len(items), 0))
    while True:
        msgs = received()
        ack = [m for m in msgs if m.get_type() == "MISSION_ACK"]
        if ack:
            return ack[0]
        req = [m for m in msgs if m.get_type() == "MISSION_REQUEST_INT"]
        assert req, [m.get_type() for m in msgs]
        send(items[req[0].seq])


def waypoint(gcs, seq, north, east, up, command=16, frame=6, p1=0.0):
    from flight.mavframes import ned_to_geodetic
    lat, lon, _ = ned_to_geodetic([north, east, -up], 47.397742, 8.545594, 488.0)
    return gcs.mission_item_int_encode(1, 1, seq, frame, command, 0, 1, p1, math.nan, math.nan, math.nan,
                                       int(round(lat * 1e7)), int(round(lon * 1e7)), up, 0)


def test_mission_upload_download_fly_reached_clear(link):
    bridge, gcs, send, received, counts = link
    healthy(bridge)
    items = [waypoint(gcs, 0, 0.0, 0.0, 2.0), waypoint(gcs, 1, 2.0, 0.0, 2.0, p1=1.0),
             waypoint(gcs, 2, 2.0, 2.0, 2.0), gcs.mission_item_int_encode(1, 1, 3, 2, 178, 0, 1, 1, 1.5, -1, 0, 0, 0, 0, 0),
             gcs.mission_item_int_encode(1, 1, 4, 2, mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0)]
    assert upload(send, received, gcs, items).type == mavlink.MAV_MISSION_ACCEPTED
    # downloaded as uploaded
    send(gcs.mission_request_list_encode(1, 1, 0))
    assert [m.count for m in received() if m.get_type() == "MISSION_COUNT"] == [5]
    send(gcs.mission_request_int_encode(1, 1, 1, 0))
    item = [m for m in received() if m.get_type() == "MISSION_ITEM_INT"][0]
    assert (item.seq, item.x, item.y, item.z, item.param1) == (1, items[1].x, items[1].y, 2.0, 1.0)
    # start on the ground, armed: the planner gets a takeoff first, then the waypoints (ENU), RTL as goto + land
    bridge.inputs["setpoint"] = setpoint(armed=True, phase="arm")
    bridge.inputs["pos"]["position_m"] = [0.0, 0.0, 0.0]
    (kind, m), = send(long(gcs, mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4, 4))
    assert acks(received())[0].result == mavlink.MAV_RESULT_ACCEPTED
    assert kind == "mission" and m["types"] == ["takeoff", "goto", "goto", "goto", "goto", "land"]
    # lat/lon in 1e-7 degrees: ~1 cm
    assert m["position_m"][3:6] == pytest.approx([0.0, 0.0, 2.0], abs=0.01)
    assert m["position_m"][6:9] == pytest.approx([0.0, 2.0, 2.0], abs=0.01)    # 2 m north = ENU y
    assert m["hold_s"][2] == 1.0 and m["acceptance_m"][1] == 0.3
    assert bridge.flying_seq == [0, 0, 1, 2, 4, 4]

    def at(item, state="running", phase="goto"):
        sp = setpoint(armed=True, phase=phase, z=2.0)
        sp["item"], sp["mission_state"] = item, state
        bridge.inputs["setpoint"] = sp
        bridge.tick(NOW, NOW)
        return received()
    at(0, phase="arm")              # the planner has not taken it yet: nothing
    assert not bridge.mission_live
    msgs = at(0, phase="takeoff")
    assert bridge.mission_live and not [m for m in msgs if m.get_type() == "MISSION_ITEM_REACHED"]
    msgs = at(2)
    assert [m.seq for m in msgs if m.get_type() == "MISSION_ITEM_REACHED"] == [0]
    assert [m.seq for m in msgs if m.get_type() == "MISSION_CURRENT"][-1] == 1
    msgs = at(4)
    assert [m.seq for m in msgs if m.get_type() == "MISSION_ITEM_REACHED"] == [1, 2, 3]
    msgs = at(5, state="completed", phase="landed")
    assert [m.seq for m in msgs if m.get_type() == "MISSION_ITEM_REACHED"] == [4]
    current = [m for m in msgs if m.get_type() == "MISSION_CURRENT"][-1]
    assert current.seq == 5 and current.total == 5 and current.mission_state == mavlink.MISSION_STATE_COMPLETE
    # set current and clear
    send(gcs.mission_set_current_encode(1, 1, 2))
    assert [m.seq for m in received() if m.get_type() == "MISSION_CURRENT"] == [2]
    send(gcs.mission_clear_all_encode(1, 1, 0))
    assert [m.type for m in received() if m.get_type() == "MISSION_ACK"] == [mavlink.MAV_MISSION_ACCEPTED]
    send(gcs.mission_request_list_encode(1, 1, 0))
    assert [m.count for m in received() if m.get_type() == "MISSION_COUNT"] == [0]


def test_mission_upload_refuses_what_it_cannot_fly(link):
    bridge, gcs, send, received, _ = link
    bad = [waypoint(gcs, 0, 1.0, 0.0, 2.0), waypoint(gcs, 1, 0.0, 0.0, 2.0, command=mavlink.MAV_CMD_DO_DIGICAM_CONTROL)]
    assert upload(send, received, gcs, bad).type == mavlink.MAV_MISSION_UNSUPPORTED
    frame = [waypoint(gcs, 0, 1.0, 0.0, 2.0, frame=mavlink.MAV_FRAME_BODY_FRD)]
    assert upload(send, received, gcs, frame).type == mavlink.MAV_MISSION_UNSUPPORTED_FRAME
    send(gcs.mission_count_encode(1, 1, 1, mavlink.MAV_MISSION_TYPE_FENCE))  # fences: not supported
    assert [m.type for m in received() if m.get_type() == "MISSION_ACK"] == [mavlink.MAV_MISSION_UNSUPPORTED]
    # local NED items (MISSION_ITEM_INT: metres * 1e4)
    local = [gcs.mission_item_int_encode(1, 1, 0, mavlink.MAV_FRAME_LOCAL_NED, 16, 0, 1, 0, 0, 0, math.nan,
                                         10000, 20000, -3.0, 0)]
    assert upload(send, received, gcs, local).type == mavlink.MAV_MISSION_ACCEPTED
    assert bridge.item_to_enu(bridge.mission.items[0]) == pytest.approx([2.0, 1.0, 3.0])
    # an upload that stops: asked again, then cancelled
    send(gcs.mission_count_encode(1, 1, 3, 0))
    received()
    for k in range(1, 7):
        bridge.retry_upload(NOW + 1.01 * k)
    msgs = received()
    assert len([m for m in msgs if m.get_type() == "MISSION_REQUEST_INT"]) == 5
    assert [m.type for m in msgs if m.get_type() == "MISSION_ACK"] == [mavlink.MAV_MISSION_OPERATION_CANCELLED]
    assert len(bridge.mission.items) == 1  # the mission before the failed upload is kept


def flip_status(t=NOW, refused=False):
    """planner/flip_status as the planner sends it once a second while it has a flip controller."""
    return {"header": header(t), "methods": ["ilqr-project"], "method": "ilqr-project", "altitude_m": 5.0,
            "refused": refused, "reason": "predicted 95th-percentile altitude loss ..." if refused else ""}


def texts(msgs):
    return [m.text for m in msgs if m.get_type() == "STATUSTEXT"]


def test_a_flip_is_accepted_only_when_the_planner_can_fly_it(link):
    """MAV_CMD_USER_1 (the flip): DENIED, with how to enable it, while the planner has said nothing
    of flips (no flip controller: its flip_methods); DENIED when its prediction refuses the flip;
    TEMPORARILY_REJECTED when what it said is stale; ACCEPTED (flying) only with a fresh status."""
    bridge, gcs, send, received, _ = link
    bridge.inputs["setpoint"] = setpoint(armed=True, phase="hold", z=5.0)
    bridge.inputs["pos"]["position_m"] = [0.0, 0.0, 5.0]
    assert bridge.flying()
    flip = long(gcs, mavlink.MAV_CMD_USER_1)
    assert send(flip) == []
    msgs = received()
    assert acks(msgs)[0].result == mavlink.MAV_RESULT_DENIED
    assert texts(msgs) == ["cmd 31010: no flip: set planner.flip_methods"]
    bridge.inputs["flip"] = flip_status(refused=True)
    assert send(flip) == []
    msgs = received()
    assert acks(msgs)[0].result == mavlink.MAV_RESULT_DENIED and "predicted unsafe" in texts(msgs)[0]
    bridge.inputs["flip"] = flip_status(t=NOW - 10.0)   # the planner stopped saying it (3 s: health_timeout_s)
    assert send(flip) == []
    assert acks(received())[0].result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    bridge.inputs["flip"] = flip_status(t=NOW - 1.0)
    assert send(flip) == [("command", {"command": "flip", "altitude_m": 0.0, "position_m": [0.0, 0.0, 0.0],
                                       "yaw_rad": 0.0, "origin": "mavlink:255/190"})]
    assert acks(received())[0].result == mavlink.MAV_RESULT_ACCEPTED and bridge.mode == "hold"
    bridge.inputs["setpoint"] = setpoint(armed=True, phase="arm")   # on the ground: not now
    bridge.inputs["pos"]["position_m"] = [0.0, 0.0, 0.0]
    assert send(flip) == []
    assert acks(received())[0].result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED


def test_a_mission_with_a_flip_the_planner_cannot_fly_is_refused_at_upload(link):
    bridge, gcs, send, received, _ = link
    items = [waypoint(gcs, 0, 0.0, 0.0, 5.0),
             gcs.mission_item_int_encode(1, 1, 1, mavlink.MAV_FRAME_MISSION, mavlink.MAV_CMD_USER_1, 0, 1,
                                         0, 0, 0, 0, 0, 0, 0, 0)]
    send(gcs.mission_count_encode(1, 1, 2, 0))
    send(items[0])
    received()
    send(items[1])   # refused as it arrives, with the reason and how to enable it
    msgs = received()
    assert [m.type for m in msgs if m.get_type() == "MISSION_ACK"] == [mavlink.MAV_MISSION_UNSUPPORTED]
    assert texts(msgs) == ["mission item 1: no flip: set planner.flip_methods"]
    assert bridge.mission.items == [] and bridge.mission.upload is None
    bridge.inputs["flip"] = flip_status()
    assert upload(send, received, gcs, items).type == mavlink.MAV_MISSION_ACCEPTED
    assert len(bridge.mission.items) == 2
    bridge.inputs["flip"] = flip_status(refused=True)
    assert upload(send, received, gcs, items).type == mavlink.MAV_MISSION_UNSUPPORTED
    assert len(bridge.mission.items) == 2   # the mission before the refused upload is kept


def test_is_armable_follows_estimates_and_checks(link):
    """SYS_STATUS's PREARM_CHECK bit (MAVSDK's health.is_armable): services healthy, estimates fresh and
    converged; a failure is said in STATUSTEXT."""
    bridge, gcs, send, received, _ = link

    def status():
        bridge.send_stream("SYS_STATUS", NOW, NOW)
        st = [m for m in received() if m.get_type() == "SYS_STATUS"][0]
        bit = mavlink.MAV_SYS_STATUS_PREARM_CHECK
        assert st.onboard_control_sensors_present & bit and st.onboard_control_sensors_enabled & bit
        return st
    assert not status().onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK
    bridge.tick(NOW, NOW)
    assert any(m.get_type() == "STATUSTEXT" and m.text.startswith("Preflight Fail") for m in received())
    healthy(bridge)
    st = status()
    assert st.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK
    assert st.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_SENSOR_GPS
    bridge.inputs["pos"]["position_cov_m2"] = [0.25, 0, 0, 0, 0.25, 0, 0, 0, 0.25]  # 0.5 m std: not converged
    bridge.inputs["pos"]["velocity_m_s"] = [0.0, 0.0, 0.0]
    st = status()   # at rest on the ground, vision running: armable, the estimate not yet converged
    assert st.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK
    assert not st.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_SENSOR_GPS
    bridge.health["vision"] = (NOW - 10.0, {"state": "running"})   # and without vision: not armable
    st = status()
    assert not st.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK
    assert not st.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_SENSOR_GPS
    assert bridge.arming_blocker(NOW, NOW) == "position estimate not converged"


def test_link_failsafe_holds_then_lands():
    fs = LinkFailsafe(timeout_s=2.0, hold_s=1.0)
    assert fs.update(0.0, flying=True) is None  # no GCS ever heard: no failsafe
    fs.heartbeat(10.0)
    assert fs.update(11.9, flying=True) is None
    assert fs.update(12.1, flying=True) == "hold"
    assert fs.update(12.5, flying=True) is None
    assert fs.update(13.2, flying=True) == "land"
    assert fs.update(20.0, flying=True) is None  # once
    fs.heartbeat(21.0)
    assert fs.state == "ok" and fs.update(21.5, flying=True) is None
    assert fs.update(30.0, flying=False) is None  # on the ground: nothing to do


def test_bridge_failsafe_sends_hold_then_land(link):
    bridge, gcs, send, received, _ = link
    bridge.inputs["setpoint"] = setpoint(armed=True, phase="hold", z=2.0)
    bridge.inputs["pos"]["position_m"] = [0.0, 0.0, 2.0]
    bridge.failsafe.heartbeat(NOW - 2.5)
    actions = bridge.tick(NOW, NOW)
    assert actions[0][1]["command"] == "hold" and actions[0][1]["origin"] == "failsafe"
    assert bridge.tick(NOW + 1.1, NOW + 1.1)[0][1]["command"] == "land"


def test_garbage_and_random_crc_valid_messages_never_crash(link):
    """Random bytes and random (CRC-valid) messages of every type: counted, never raised."""
    bridge, gcs, send, received, counts = link
    rng = random.Random(0)
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    for _ in range(200):
        for m in parser.parse_buffer(bytes(rng.getrandbits(8) for _ in range(64))) or []:
            bridge.handle(m, NOW, NOW)
    ids = list(mavlink.mavlink_map)
    for _ in range(3000):
        cls = mavlink.mavlink_map[rng.choice(ids)]
        payload = bytes(rng.getrandbits(8) for _ in range(cls.unpacker.size))
        for m in parser.parse_buffer(_crc_valid_frame(cls, payload, rng)) or []:
            bridge.handle(m, NOW, NOW)
    # commands addressed to us with random numbers (NaN, inf, huge) in every parameter
    for _ in range(500):
        import struct
        params = [struct.unpack("<f", struct.pack("<I", rng.getrandbits(32)))[0] for _ in range(7)]
        cmd = rng.choice([400, 22, 21, 17, 176, 511, 512, 510, 520, rng.randrange(65536)])
        for m in parser.parse_buffer(gcs.command_long_encode(1, 1, cmd, 0, *params).pack(gcs)) or []:
            bridge.handle(m, NOW, NOW)
    bridge.tick(NOW, NOW)
    assert counts.get("mavlink_bad_data", 0) > 0
    assert counts.get("mavlink_handler_error", 0) == 0, counts
    assert len(acks(received())) >= 500  # every command answered


def _crc_valid_frame(cls, payload: bytes, rng) -> bytes:
    """A MAVLink 2 frame with a random payload for message `cls` and a correct CRC."""
    import struct

    from pymavlink.generator.mavcrc import x25crc
    hdr = struct.pack("<BBBBBBBHB", 0xFD, len(payload), 0, 0, rng.randrange(256), 255, 190,
                      cls.id & 0xFFFF, cls.id >> 16)
    crc = x25crc(hdr[1:] + payload)
    crc.accumulate(bytes([cls.crc_extra]))
    return hdr + payload + struct.pack("<H", crc.crc)


def test_highres_imu_and_battery_in_frd_and_si(link):
    bridge, gcs, send, received, _ = link
    assert bridge.send_stream("HIGHRES_IMU", NOW, NOW) is False  # off and no IMU yet
    send(long(gcs, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 105, 50000))
    assert bridge.intervals_s["HIGHRES_IMU"] == pytest.approx(0.05)
    bridge.inputs["imu"] = {"header": header(NOW - 0.002), "gyro_rad_s": [0.1, 0.2, 0.3],
                            "accel_m_s2": [0.0, 0.0, 9.81]}
    bridge.inputs["baro"] = {"header": header(), "pressure_pa": 100000.0, "temperature_k": 293.15}
    bridge.inputs["battery"] = {"header": header(), "voltage_v": 11.1, "current_a": 8.0, "consumed_mah": 100.0,
                                "remaining": 0.9, "cells": 3}
    received()
    assert bridge.send_stream("HIGHRES_IMU", NOW, NOW) and bridge.send_stream("BATTERY_STATUS", NOW, NOW)
    imu, bat = received()
    assert imu.zacc == pytest.approx(-9.81) and imu.ygyro == pytest.approx(-0.2) and imu.abs_pressure == 1000.0
    assert imu.time_usec == 99998000
    assert bat.voltages[:4] == [3700, 3700, 3700, 65535] and bat.current_battery == 800 and bat.battery_remaining == 90


def test_arm_then_mission_start_at_once_with_mavsdk_items(link):
    """MAVSDK's mission example: arm, then start at once (the planner has not shown the arm yet);
    its items carry DO_CHANGE_SPEED and NAV_DELAY (loiter_time_s)."""
    bridge, gcs, send, received, _ = link
    healthy(bridge)
    items = [waypoint(gcs, 0, 0.0, 0.0, 2.0),
             gcs.mission_item_int_encode(1, 1, 1, 2, mavlink.MAV_CMD_DO_CHANGE_SPEED, 0, 1, 1, 1.0, -1, 0, 0, 0, 0, 0),
             gcs.mission_item_int_encode(1, 1, 2, 2, mavlink.MAV_CMD_NAV_DELAY, 0, 1, 0.5, -1, -1, -1, 0, 0, 0, 0),
             waypoint(gcs, 3, 2.0, 0.0, 2.0)]
    assert upload(send, received, gcs, items).type == mavlink.MAV_MISSION_ACCEPTED
    assert send(long(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0, math.nan))[0][1]["command"] == "arm"
    assert bridge.inputs["setpoint"]["armed"] is False        # not shown by the planner yet
    (kind, m), = send(long(gcs, mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4, 4))
    assert acks(received())[-1].result == mavlink.MAV_RESULT_ACCEPTED
    assert m["types"] == ["takeoff", "goto", "hold", "goto"] and m["hold_s"][2] == 0.5
    assert bridge.flying_seq == [0, 0, 2, 3] and bridge.mode_name() == "mission"
    # set current while flying it: the planner flies from there; the new mission is followed, not timed out
    sp = setpoint(armed=True, phase="goto", z=2.0)
    sp["item"] = 1
    bridge.inputs["setpoint"] = sp
    bridge.inputs["pos"]["position_m"] = [0.0, 0.0, 2.0]
    bridge.mission_sent_wall = NOW - 100.0   # the first start, long ago
    (kind, m), = send(gcs.mission_set_current_encode(1, 1, 3))
    assert kind == "mission" and m["types"] == ["goto"] and bridge.flying_seq == [3]
    bridge.tick(NOW + 1.0, NOW + 1.0)
    assert bridge.mode_name() == "mission"
    # SET_MODE (the older message) to PX4's hold: accepted on the ground
    send(gcs.set_mode_encode(1, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MODES["hold"]))
    assert bridge.mode_name() == "hold"


def test_an_endpoint_off_this_machine_is_a_link():
    from services.mavlink_logic import is_loopback_endpoint
    for local in ("udpout:127.0.0.1:14550", "udpin:127.0.0.1:14540", "tcp:localhost:5760", "udp:[::1]:14550"):
        assert is_loopback_endpoint(local), local
    for link in ("udpin:0.0.0.0:14550", "udpout:192.168.1.10:14550", "tcpin:0.0.0.0:5760", "/dev/ttyUSB0",
                 "udpbcast:10.0.0.255:14550", "nonsense"):
        assert not is_loopback_endpoint(link), link


def test_an_unsigned_link_off_this_machine_is_refused_at_start():
    import subprocess
    import sys
    from pathlib import Path
    root = Path(__file__).resolve().parents[3]
    proc = subprocess.run([sys.executable, "-m", "services.mavlink", "--endpoint", "udpin:0.0.0.0:14599"],
                          cwd=root, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "signing_key_file" in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
