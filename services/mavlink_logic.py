"""The MAVLink bridge's logic, without Zenoh or sockets (testable with a byte buffer).

`Bridge` turns the stack's latest messages into MAVLink telemetry (NED/FRD
through flight/mavframes.py, the only place frames are converted), answers
every COMMAND_LONG/COMMAND_INT with a COMMAND_ACK, runs the parameter
protocol over a small table of live-tunable parameters and the GCS-link
failsafe. What the stack must do is returned as actions:
("command", planner/command fields) and ("param", param/set fields); the
service shell publishes them.

Custom modes (HEARTBEAT.custom_mode; DO_SET_MODE accepts HOLD and LAND):
0 IDLE (waiting/disarmed/landed), 1 ARMED (on the ground), 2 TAKEOFF,
3 HOLD, 4 GOTO (offboard/position target), 5 LAND, 6 ATTITUDE, 7 FLIP.
"""

from __future__ import annotations

import math
import os
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink is imported: MAVLink 2 framing
os.environ.setdefault("MAVLINK_DIALECT", "common")
from pymavlink import mavutil  # noqa: E402,F401  (services/mavlink.py's, chosen after the env above)
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from flight import mavframes as mf  # noqa: E402

MODE_NUMBERS = {"IDLE": 0, "ARMED": 1, "TAKEOFF": 2, "HOLD": 3, "GOTO": 4, "LAND": 5, "ATTITUDE": 6, "FLIP": 7}
PHASE_MODES = {"waiting": "IDLE", "disarmed": "IDLE", "landed": "IDLE", "timeout": "IDLE", "arm": "ARMED",
               "takeoff": "TAKEOFF", "settle": "HOLD", "hold": "HOLD", "goto": "GOTO", "land": "LAND",
               "attitude": "ATTITUDE", "flip": "FLIP"}
FORCE_DISARM = 21196  # MAVLink's magic number in param2 of ARM_DISARM: disarm even in the air
# commands that change what the vehicle does: only from a ground station (see _from_ground_station)
ACTION_COMMANDS = frozenset((mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_NAV_TAKEOFF,
                             mavlink.MAV_CMD_NAV_LAND, mavlink.MAV_CMD_NAV_LOITER_UNLIM,
                             mavlink.MAV_CMD_DO_SET_MODE))

# streams: message name -> (message id, default rate Hz)
STREAMS = {
    "HEARTBEAT": (0, 1.0), "SYS_STATUS": (1, 1.0), "SYSTEM_TIME": (2, 1.0), "ATTITUDE": (30, 25.0),
    "ATTITUDE_QUATERNION": (31, 10.0), "LOCAL_POSITION_NED": (32, 25.0), "GLOBAL_POSITION_INT": (33, 10.0),
    "HIGHRES_IMU": (105, 0.0), "BATTERY_STATUS": (147, 1.0), "HOME_POSITION": (242, 0.2),
    "EXTENDED_SYS_STATE": (245, 1.0), "AUTOPILOT_VERSION": (148, 0.0),
}
# HIGHRES_IMU is off by default: its 400 Hz IMU input costs CPU; SET_MESSAGE_INTERVAL turns it on
STREAM_BY_ID = {mid: name for name, (mid, _) in STREAMS.items()}

# live-tunable parameters: (service, key, MAVLink name pattern, axis letters or None, (min, max))
TUNABLE = (
    ("attitude", "k", "ATT_K_{}", "RPY", (0.1, 200.0)),
    ("attitude", "alpha", "ATT_ALPHA_{}", "RPY", (0.1, 200.0)),
    ("position", "k", "POS_K_{}", "XYZ", (0.05, 50.0)),
    ("position", "alpha", "POS_ALPHA_{}", "XYZ", (0.05, 50.0)),
    ("position", "max_tilt_deg", "POS_MAX_TILT", None, (1.0, 80.0)),
    ("motors", "command_timeout_s", "MOT_CMD_TIMEOUT", None, (0.005, 1.0)),
)

# SYS_STATUS sensor bits and the services whose health they reflect
S = mavlink
SENSOR_BITS = (
    (S.MAV_SYS_STATUS_SENSOR_3D_GYRO | S.MAV_SYS_STATUS_SENSOR_3D_ACCEL, "sim"),
    (S.MAV_SYS_STATUS_SENSOR_3D_MAG | S.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE, "sim"),
    (S.MAV_SYS_STATUS_SENSOR_VISION_POSITION, "vision"),
    (S.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL | S.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
     | S.MAV_SYS_STATUS_AHRS, "attitude"),
    (S.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL | S.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL, "position"),
    (S.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS, "motors"),
    (S.MAV_SYS_STATUS_LOGGING, "recorder"),
)


@dataclass
class BridgeConfig:
    system_id: int = 1
    component_id: int = 1
    home_lat_deg: float = 47.397742   # PX4 SITL's home (Zurich), so GCS maps look familiar
    home_lon_deg: float = 8.545594
    home_alt_m: float = 488.0
    gcs_timeout_s: float = 5.0        # no GCS heartbeat for this long while flying -> hold
    failsafe_hold_s: float = 3.0      # ... then land after holding this long
    health_timeout_s: float = 3.0     # a service's 1 Hz health older than this -> unhealthy
    state_timeout_s: float = 0.5      # att/pos state older than this -> no telemetry, no arming
    rates_hz: dict = field(default_factory=dict)  # stream name -> rate override


def _finite(*values) -> bool:
    return all(isinstance(v, (int, float)) and math.isfinite(v) for v in values)


class LinkFailsafe:
    """GCS heartbeat lost while flying: hold, then land after hold_s. Armed only once a
    GCS has been heard (a stack flying a mission with no GCS is not in failsafe)."""

    def __init__(self, timeout_s: float, hold_s: float):
        self.timeout_s, self.hold_s = timeout_s, hold_s
        self.last_heartbeat: float | None = None
        self.state = "ok"  # ok | hold | land
        self.since = 0.0

    def heartbeat(self, now: float) -> None:
        self.last_heartbeat = now
        self.state = "ok"  # the link is back; the vehicle keeps its failsafe action until commanded

    def update(self, now: float, flying: bool) -> str | None:
        """The action to take now ("hold" or "land"), once per transition."""
        if self.last_heartbeat is None or now - self.last_heartbeat <= self.timeout_s:
            return None
        if self.state == "ok":
            if not flying:
                return None
            self.state, self.since = "hold", now
            return "hold"
        if self.state == "hold" and now - self.since >= self.hold_s:
            self.state = "land"
            return "land"
        return None


class ParamTable:
    """MAVLink names <-> stack parameters (vector parameters split per axis)."""

    def __init__(self, current: dict[tuple[str, str], Any]):
        self.rows: list[dict] = []  # name, service, key, index, value, bounds
        for service, key, pattern, axes, bounds in TUNABLE:
            if (service, key) not in current:
                continue
            value = current[(service, key)]
            if axes:
                for i, axis in enumerate(axes):
                    self.rows.append({"name": pattern.format(axis), "service": service, "key": key,
                                      "index": i, "value": float(value[i]), "bounds": bounds})
            else:
                self.rows.append({"name": pattern, "service": service, "key": key, "index": None,
                                  "value": float(value), "bounds": bounds})
        self.by_name = {r["name"]: i for i, r in enumerate(self.rows)}

    def vector(self, service: str, key: str) -> list[float]:
        return [r["value"] for r in self.rows if r["service"] == service and r["key"] == key]


class Bridge:
    def __init__(self, mav: mavlink.MAVLink, config: BridgeConfig, params: ParamTable,
                 services: tuple[str, ...], counts: dict[str, int], t_origin_s: float = 0.0,
                 problem: Callable[[str], None] = lambda text: None):
        self.mav, self.cfg, self.params = mav, config, params
        self.services = services
        self.counts = counts  # bad input by reason (the service's health "rejected")
        self.t_origin_s = t_origin_s  # stack time of boot: time_boot_ms = (t - origin) * 1000
        self.problem = problem
        self.inputs: dict[str, dict | None] = {}  # att, pos, imu, baro, mag, battery, setpoint
        self.health: dict[str, tuple[float, dict]] = {}  # service -> (arrival wall time, message)
        self.failsafe = LinkFailsafe(config.gcs_timeout_s, config.failsafe_hold_s)
        self.ground_stations: set[int] = set()   # system ids heard sending a GCS heartbeat
        self.intervals_s: dict[str, float] = {}
        for name, (_, hz) in STREAMS.items():
            hz = float(config.rates_hz.get(name, hz))
            self.intervals_s[name] = 1.0 / hz if hz > 0 else 0.0
        self.next_due = {name: 0.0 for name in STREAMS}
        self.latency_s: dict[str, deque] = {n: deque(maxlen=5000) for n in ("ATTITUDE", "LOCAL_POSITION_NED",
                                                                             "HIGHRES_IMU")}
        self.last_target: tuple | None = None
        self.imu_requested = False  # REQUEST_MESSAGE(HIGHRES_IMU): the shell subscribes to the IMU
        self.sent = 0

    # ------------------------------------------------------------------ helpers
    def count(self, reason: str) -> None:
        self.counts[reason] = self.counts.get(reason, 0) + 1

    def send(self, msg) -> None:
        self.mav.send(msg)
        self.sent += 1

    def boot_ms(self, t_s: float) -> int:
        return int(min(max(0.0, (t_s - self.t_origin_s) * 1000.0), 2 ** 32 - 1))

    def fresh(self, name: str, now: float, timeout_s: float | None = None) -> dict | None:
        """The newest `name` input if its sample time is recent (stack clock)."""
        msg = self.inputs.get(name)
        if msg is None:
            return None
        if now - msg["header"]["t_s"] > (timeout_s or self.cfg.state_timeout_s):
            return None
        return msg

    def healthy(self, service: str, now_wall: float) -> bool:
        got = self.health.get(service)
        return (got is not None and now_wall - got[0] <= self.cfg.health_timeout_s
                and got[1]["state"] == "running")

    def statustext(self, text: str, severity: int = mavlink.MAV_SEVERITY_WARNING) -> None:
        self.send(self.mav.statustext_encode(severity, text[:50].encode()))

    # ------------------------------------------------------------------ vehicle state
    def armed(self) -> bool:
        sp = self.inputs.get("setpoint")
        return bool(sp and sp["armed"])

    def mode_name(self) -> str:
        sp = self.inputs.get("setpoint")
        return PHASE_MODES.get(sp["phase"], "HOLD") if sp else "IDLE"

    def landed_state(self) -> int:
        sp, pos = self.inputs.get("setpoint"), self.inputs.get("pos")
        if sp is None:
            return mavlink.MAV_LANDED_STATE_UNDEFINED
        if not sp["armed"] or sp["phase"] in ("arm", "landed", "waiting", "disarmed"):
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        if sp["phase"] == "takeoff":
            return mavlink.MAV_LANDED_STATE_TAKEOFF
        if sp["phase"] == "land":
            return mavlink.MAV_LANDED_STATE_LANDING
        if pos is not None and pos["position_m"][2] < 0.05 and sp["position_m"][2] <= 0.05:
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        return mavlink.MAV_LANDED_STATE_IN_AIR

    def flying(self) -> bool:
        return self.armed() and self.landed_state() != mavlink.MAV_LANDED_STATE_ON_GROUND

    # ------------------------------------------------------------------ outgoing
    def tick(self, now_stack: float, now_wall: float) -> list[tuple[str, dict]]:
        """Send the streams that are due; run the failsafe. Returns actions."""
        for name, interval in self.intervals_s.items():
            if interval <= 0.0 or now_wall < self.next_due[name]:
                continue
            self.next_due[name] = max(self.next_due[name] + interval, now_wall - interval)
            self.send_stream(name, now_stack, now_wall)
        action = self.failsafe.update(now_wall, self.flying())
        if action:
            self.problem(f"GCS heartbeat lost for > {self.cfg.gcs_timeout_s} s: {action}")
            self.statustext(f"failsafe: GCS link lost, {action}", mavlink.MAV_SEVERITY_CRITICAL)
            return [("command", self.command_fields(action, origin="failsafe"))]
        return []

    def send_stream(self, name: str, now_stack: float, now_wall: float) -> bool:
        """Build and send one message of a stream; False if there is no data for it."""
        msg = getattr(self, "_msg_" + name.lower())(now_stack, now_wall)
        if msg is None:
            return False
        self.send(msg)
        return True

    def _record_latency(self, name: str, sample_t_s: float, now_stack: float) -> None:
        self.latency_s[name].append(now_stack - sample_t_s)

    def _msg_heartbeat(self, now, wall):
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_GUIDED_ENABLED \
            | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
        if self.armed():
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if self.inputs.get("setpoint") is None:
            status = mavlink.MAV_STATE_BOOT
        elif self.failsafe.state != "ok":
            status = mavlink.MAV_STATE_CRITICAL
        else:
            status = mavlink.MAV_STATE_ACTIVE if self.armed() else mavlink.MAV_STATE_STANDBY
        return self.mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_GENERIC, base,
                                         MODE_NUMBERS[self.mode_name()], status)

    def sensor_bits(self, now_wall: float) -> tuple[int, int]:
        present = health = 0
        for bits, service in SENSOR_BITS:
            if service not in self.services:
                continue
            present |= bits
            if self.healthy(service, now_wall):
                health |= bits
        if "battery" in self.inputs:
            present |= mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
            health |= mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
        return present, health

    def _msg_sys_status(self, now, wall):
        present, health = self.sensor_bits(wall)
        bat = self.inputs.get("battery")
        volt = int(bat["voltage_v"] * 1000) if bat else 65535
        cur = int(bat["current_a"] * 100) if bat else -1
        rem = int(round(bat["remaining"] * 100)) if bat else -1
        errors = min(65535, sum(v for k, v in self.counts.items() if k.startswith("mavlink_")))
        return self.mav.sys_status_encode(present, present, health, 0, min(volt, 65535), min(cur, 32767), rem,
                                          0, errors, 0, 0, 0, 0)

    def _msg_system_time(self, now, wall):
        return self.mav.system_time_encode(int(wall * 1e6), self.boot_ms(now))

    def _attitude_ned(self, now):
        att = self.fresh("att", now)
        if att is None:
            return None
        q = mf.quat_enu_flu_to_ned_frd(att["quaternion_wxyz"])
        rates = mf.flu_to_frd(att["rate_rad_s"])
        return att, q, mf.euler_from_quat_ned(q), rates

    def _msg_attitude(self, now, wall):
        got = self._attitude_ned(now)
        if got is None:
            return None
        att, _, (roll, pitch, yaw), w = got
        self._record_latency("ATTITUDE", att["header"]["t_s"], now)
        return self.mav.attitude_encode(self.boot_ms(att["header"]["t_s"]), roll, pitch, yaw, *map(float, w))

    def _msg_attitude_quaternion(self, now, wall):
        got = self._attitude_ned(now)
        if got is None:
            return None
        att, q, _, w = got
        return self.mav.attitude_quaternion_encode(self.boot_ms(att["header"]["t_s"]), *map(float, q), *map(float, w))

    def _msg_local_position_ned(self, now, wall):
        pos = self.fresh("pos", now)
        if pos is None:
            return None
        p, v = mf.enu_to_ned(pos["position_m"]), mf.enu_to_ned(pos["velocity_m_s"])
        self._record_latency("LOCAL_POSITION_NED", pos["header"]["t_s"], now)
        return self.mav.local_position_ned_encode(self.boot_ms(pos["header"]["t_s"]), *map(float, p), *map(float, v))

    def _msg_global_position_int(self, now, wall):
        pos = self.fresh("pos", now)
        if pos is None:
            return None
        p, v = mf.enu_to_ned(pos["position_m"]), mf.enu_to_ned(pos["velocity_m_s"])
        lat, lon, alt = mf.ned_to_geodetic(p, self.cfg.home_lat_deg, self.cfg.home_lon_deg, self.cfg.home_alt_m)
        got = self._attitude_ned(now)
        hdg = int(round(math.degrees(got[2][2]) % 360 * 100)) % 36000 if got else 65535

        def cm(x):
            return int(max(-32767, min(32767, round(x * 100))))
        return self.mav.global_position_int_encode(
            self.boot_ms(pos["header"]["t_s"]), int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
            int(round(-p[2] * 1000)), cm(v[0]), cm(v[1]), cm(v[2]), hdg)

    def _msg_home_position(self, now, wall):
        c = self.cfg
        return self.mav.home_position_encode(int(round(c.home_lat_deg * 1e7)), int(round(c.home_lon_deg * 1e7)),
                                             int(round(c.home_alt_m * 1000)), 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0],
                                             0.0, 0.0, 0.0, int(now * 1e6) if now > 0 else 0)

    def _msg_extended_sys_state(self, now, wall):
        return self.mav.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED, self.landed_state())

    def _msg_battery_status(self, now, wall):
        bat = self.inputs.get("battery")
        if bat is None:
            return None
        cell_mv = round(bat["voltage_v"] / bat["cells"] * 1000)
        cells = [cell_mv] * min(bat["cells"], 10) + [65535] * (10 - min(bat["cells"], 10))
        return self.mav.battery_status_encode(
            0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LIPO, 32767, cells,
            min(32767, int(bat["current_a"] * 100)), int(bat["consumed_mah"]), -1, int(round(bat["remaining"] * 100)))

    def _msg_highres_imu(self, now, wall):
        imu = self.fresh("imu", now)
        if imu is None:
            return None
        acc, gyro = mf.flu_to_frd(imu["accel_m_s2"]), mf.flu_to_frd(imu["gyro_rad_s"])
        mag, baro = self.inputs.get("mag"), self.inputs.get("baro")
        fields = 0b111111
        m = mf.flu_to_frd(mag["field_ut"]) / 100.0 if mag else [0.0, 0.0, 0.0]  # uT -> gauss
        if mag:
            fields |= 0b111000000
        pressure_hpa = temp_c = alt = 0.0
        if baro:
            pressure_hpa = baro["pressure_pa"] / 100.0
            temp_c = baro["temperature_k"] - 273.15
            alt = 44330.0 * (1.0 - (baro["pressure_pa"] / 101325.0) ** 0.1903)
            fields |= 0b1101000000000
        self._record_latency("HIGHRES_IMU", imu["header"]["t_s"], now)
        t_us = int(max(0.0, imu["header"]["t_s"] - self.t_origin_s) * 1e6)
        return self.mav.highres_imu_encode(t_us, *map(float, acc), *map(float, gyro), *map(float, m),
                                           pressure_hpa, 0.0, alt, temp_c, fields)

    def _msg_autopilot_version(self, now, wall):
        caps = (mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED)
        return self.mav.autopilot_version_encode(caps, 0x00010000 | 0xFF, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8,
                                                 0, 0, self.cfg.system_id)

    # ------------------------------------------------------------------ incoming
    def handle(self, msg, now_stack: float, now_wall: float) -> list[tuple[str, dict]]:
        """One received message -> replies sent, actions returned. Bad input is counted."""
        kind = msg.get_type()
        if kind == "BAD_DATA":
            if "signature" not in getattr(msg, "reason", ""):  # signing failures: pymavlink counts them
                self.count("mavlink_bad_data")
            return []
        if kind.startswith("UNKNOWN"):
            self.count("mavlink_unknown_message")
            return []
        if msg.get_srcSystem() == self.cfg.system_id:
            return []  # our own echo, or another vehicle with our id
        handler = getattr(self, "_on_" + kind.lower(), None)
        if handler is None:
            return []  # a message we do not act on (e.g. other vehicles' telemetry)
        try:
            return handler(msg, now_stack, now_wall) or []
        except Exception as exc:  # a random CRC-valid message must never take the bridge down
            self.count("mavlink_handler_error")
            self.problem(f"{kind}: {type(exc).__name__}: {exc}")
            return []

    def _for_us(self, msg) -> bool:
        return (msg.target_system in (0, self.cfg.system_id)
                and msg.target_component in (0, self.cfg.component_id))

    def _on_heartbeat(self, msg, now, wall):
        if msg.type == mavlink.MAV_TYPE_GCS:
            self.failsafe.heartbeat(wall)
            self.ground_stations.add(msg.get_srcSystem())

    def _from_ground_station(self, msg) -> bool:
        """Commands that move the vehicle are taken only from a system that announced itself
        with a GCS heartbeat (QGroundControl and MAVSDK do): a stray or random CRC-valid message
        from anyone else on the link must not land, arm or steer it."""
        if msg.get_srcSystem() in self.ground_stations:
            return True
        self.count("mavlink_not_from_gcs")
        return False

    # -- commands ------------------------------------------------------------
    def _on_command_long(self, msg, now, wall):
        if not self._for_us(msg):
            return []
        p = [msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7]
        return self._command(msg, msg.command, p, now, wall)

    def _on_command_int(self, msg, now, wall):
        if not self._for_us(msg):
            return []
        p = [msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z]
        return self._command(msg, msg.command, p, now, wall)

    def _ack(self, msg, command: int, result: int, reason: str = "") -> None:
        self.send(self.mav.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))
        if reason:
            self.statustext(f"cmd {command}: {reason}")

    def command_fields(self, command: str, altitude_m: float = 0.0, position_m=(0.0, 0.0, 0.0),
                       yaw_rad: float = 0.0, origin: str = "mavlink") -> dict:
        return {"command": command, "altitude_m": float(altitude_m), "position_m": [float(v) for v in position_m],
                "yaw_rad": float(yaw_rad), "origin": origin}

    def _command(self, msg, command: int, p: list, now: float, wall: float) -> list:
        origin = f"mavlink:{msg.get_srcSystem()}/{msg.get_srcComponent()}"
        C, R = mavlink, mavlink
        if command in ACTION_COMMANDS and not self._from_ground_station(msg):
            return self._deny(msg, command, R.MAV_RESULT_DENIED,
                              f"system {msg.get_srcSystem()} has sent no GCS heartbeat")
        if command == C.MAV_CMD_COMPONENT_ARM_DISARM:
            if not _finite(p[0], p[1]):
                return self._deny(msg, command, R.MAV_RESULT_DENIED, "non-finite parameter")
            if p[0] >= 0.5:
                if self.armed():
                    self._ack(msg, command, R.MAV_RESULT_ACCEPTED)
                    return []
                why = self.arming_blocker(now, wall)
                if why:
                    return self._deny(msg, command, R.MAV_RESULT_TEMPORARILY_REJECTED, why)
                self._ack(msg, command, R.MAV_RESULT_ACCEPTED)
                return [("command", self.command_fields("arm", origin=origin))]
            if self.flying() and int(round(p[1])) != FORCE_DISARM:
                return self._deny(msg, command, R.MAV_RESULT_DENIED, "in the air: land first")
            self._ack(msg, command, R.MAV_RESULT_ACCEPTED)
            return [("command", self.command_fields("disarm", origin=origin))]
        if command == C.MAV_CMD_NAV_TAKEOFF:
            alt = p[6]
            if not _finite(alt) or not 0.0 < alt <= 100.0:
                return self._deny(msg, command, R.MAV_RESULT_DENIED, f"altitude {alt} outside (0, 100] m")
            if not self.armed():
                return self._deny(msg, command, R.MAV_RESULT_TEMPORARILY_REJECTED, "not armed")
            self._ack(msg, command, R.MAV_RESULT_ACCEPTED)
            return [("command", self.command_fields("takeoff", altitude_m=alt, origin=origin))]
        if command == C.MAV_CMD_NAV_LAND:
            return self._airborne(msg, command, "land", origin)
        if command == C.MAV_CMD_NAV_LOITER_UNLIM:
            return self._airborne(msg, command, "hold", origin)
        if command == C.MAV_CMD_DO_SET_MODE:
            if not _finite(p[0], p[1]):
                return self._deny(msg, command, R.MAV_RESULT_DENIED, "non-finite parameter")
            return self._set_mode(msg, command, int(p[0]), int(p[1]), origin)
        if command == C.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(msg, command, p[0], p[1])
        if command == C.MAV_CMD_GET_MESSAGE_INTERVAL:
            name = STREAM_BY_ID.get(int(p[0])) if _finite(p[0]) else None
            if name is None:
                return self._deny(msg, command, R.MAV_RESULT_UNSUPPORTED, "message not streamed")
            interval = self.intervals_s[name]
            self._ack(msg, command, R.MAV_RESULT_ACCEPTED)
            self.send(self.mav.message_interval_encode(STREAMS[name][0], int(interval * 1e6) if interval else -1))
            return []
        if command in (C.MAV_CMD_REQUEST_MESSAGE, C.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES):
            mid = mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION if command != C.MAV_CMD_REQUEST_MESSAGE else p[0]
            name = STREAM_BY_ID.get(int(mid)) if _finite(mid) else None
            if name is None:
                return self._deny(msg, command, R.MAV_RESULT_UNSUPPORTED, f"cannot send message {mid}")
            self._ack(msg, command, R.MAV_RESULT_ACCEPTED)  # ack first, then the message, as PX4 does
            if not self.send_stream(name, now, wall):
                self.imu_requested |= name == "HIGHRES_IMU"
                self.statustext(f"{name}: no data yet, ask again")
            return []
        self._ack(msg, command, R.MAV_RESULT_UNSUPPORTED)
        return []

    def _deny(self, msg, command: int, result: int, reason: str) -> list:
        self._ack(msg, command, result, reason)
        return []

    def arming_blocker(self, now: float, wall: float) -> str:
        """Why arming is refused now ('' if it is not)."""
        for service in ("attitude", "position", "motors", "planner"):
            if service in self.services and not self.healthy(service, wall):
                return f"{service} not healthy"
        if self.fresh("pos", now) is None or self.fresh("att", now) is None:
            return "no fresh attitude/position estimate"
        if self.failsafe.state != "ok":
            return "failsafe active"
        return ""

    def _airborne(self, msg, command: int, action: str, origin: str) -> list:
        if not self.flying():
            return self._deny(msg, command, mavlink.MAV_RESULT_TEMPORARILY_REJECTED, "not flying")
        self._ack(msg, command, mavlink.MAV_RESULT_ACCEPTED)
        return [("command", self.command_fields(action, origin=origin))]

    def _set_mode(self, msg, command: int, base: int, custom: int, origin: str) -> list:
        if not base & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return self._deny(msg, command, mavlink.MAV_RESULT_DENIED, "only custom modes")
        if custom == MODE_NUMBERS["HOLD"]:
            return self._airborne(msg, command, "hold", origin)
        if custom == MODE_NUMBERS["LAND"]:
            return self._airborne(msg, command, "land", origin)
        if custom == MODE_NUMBERS[self.mode_name()]:
            self._ack(msg, command, mavlink.MAV_RESULT_ACCEPTED)
            return []
        return self._deny(msg, command, mavlink.MAV_RESULT_DENIED, f"mode {custom} cannot be set (HOLD=3, LAND=5)")

    def _on_set_mode(self, msg, now, wall):  # the deprecated message, still sent by some GCSs
        if msg.target_system in (0, self.cfg.system_id) and self._from_ground_station(msg):
            return self._set_mode(msg, mavlink.MAV_CMD_DO_SET_MODE, msg.base_mode, msg.custom_mode,
                                  f"mavlink:{msg.get_srcSystem()}")
        return []

    def _set_interval(self, msg, command: int, mid, interval_us) -> list:
        name = STREAM_BY_ID.get(int(mid)) if _finite(mid) else None
        if name is None:
            return self._deny(msg, command, mavlink.MAV_RESULT_UNSUPPORTED, f"message {mid} not streamed")
        if not _finite(interval_us) or interval_us > 1e9:
            return self._deny(msg, command, mavlink.MAV_RESULT_DENIED, f"interval {interval_us} us not in [-1, 1e9]")
        if interval_us < 0:
            self.intervals_s[name] = 0.0
        elif interval_us == 0:
            hz = float(self.cfg.rates_hz.get(name, STREAMS[name][1]))
            self.intervals_s[name] = 1.0 / hz if hz > 0 else 0.0
        else:
            self.intervals_s[name] = max(interval_us * 1e-6, 1e-3)
        self.next_due[name] = 0.0
        self._ack(msg, command, mavlink.MAV_RESULT_ACCEPTED)
        return []

    # -- offboard --------------------------------------------------------------
    def _on_set_position_target_local_ned(self, msg, now, wall):
        if not self._for_us(msg) or not self._from_ground_station(msg):
            return []
        position_ignored = msg.type_mask & 0b111
        if msg.coordinate_frame != mavlink.MAV_FRAME_LOCAL_NED or position_ignored:
            self.count("mavlink_target_unsupported")  # velocity/acceleration targets are not flown
            return []
        if not _finite(msg.x, msg.y, msg.z) or max(abs(msg.x), abs(msg.y), abs(msg.z)) > 1e4:
            self.count("mavlink_bad_value")
            return []
        if not self.flying():
            self.count("mavlink_target_not_flying")
            return []
        yaw_ignored = msg.type_mask & mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
        if yaw_ignored or not _finite(msg.yaw):
            sp = self.inputs.get("setpoint")
            yaw_enu = sp["attitude_rad"][2] if sp else 0.0
        else:
            yaw_enu = mf.yaw_ned_to_enu(msg.yaw)
        target = mf.ned_to_enu([msg.x, msg.y, msg.z])
        key = (round(float(target[0]), 3), round(float(target[1]), 3), round(float(target[2]), 3), round(yaw_enu, 3))
        if key == self.last_target and self.mode_name() in ("GOTO", "HOLD"):
            return []  # a stream of the same target: nothing new for the planner
        self.last_target = key
        return [("command", self.command_fields("goto", position_m=target, yaw_rad=yaw_enu,
                                                origin=f"mavlink:{msg.get_srcSystem()}/offboard"))]

    # -- parameters --------------------------------------------------------------
    def _param_value(self, i: int) -> None:
        r = self.params.rows[i]
        self.send(self.mav.param_value_encode(r["name"].encode(), r["value"], mavlink.MAV_PARAM_TYPE_REAL32,
                                              len(self.params.rows), i))

    def _on_param_request_list(self, msg, now, wall):
        if not self._for_us(msg):
            return []
        for i in range(len(self.params.rows)):
            self._param_value(i)
        return []

    def _param_index(self, param_id, index: int) -> int | None:
        if index >= 0:
            return index if index < len(self.params.rows) else None
        name = param_id.decode(errors="replace") if isinstance(param_id, bytes) else str(param_id)
        return self.params.by_name.get(name.rstrip("\x00"))

    def _on_param_request_read(self, msg, now, wall):
        if not self._for_us(msg):
            return []
        i = self._param_index(msg.param_id, msg.param_index)
        if i is None:
            self.count("mavlink_unknown_param")
            return []
        self._param_value(i)
        return []

    def _on_param_set(self, msg, now, wall):
        if not self._for_us(msg) or not self._from_ground_station(msg):
            return []
        i = self._param_index(msg.param_id, -1)
        if i is None:
            self.count("mavlink_unknown_param")
            return []
        r = self.params.rows[i]
        lo, hi = r["bounds"]
        value = msg.param_value
        if not _finite(value) or not lo <= value <= hi:
            self.count("mavlink_bad_value")
            self.statustext(f"{r['name']}={value}: outside [{lo}, {hi}]")
            self._param_value(i)  # the protocol's refusal: the unchanged value
            return []
        r["value"] = float(value)
        self._param_value(i)
        value_list = self.params.vector(r["service"], r["key"]) if r["index"] is not None else [float(value)]
        return [("param", {"service": r["service"], "key": r["key"], "value": value_list})]


def latency_summary(bridge: Bridge) -> dict[str, tuple[float, float, int]]:
    """Per stream: (p50 ms, p99 ms, n) of sample time -> send."""
    out = {}
    for name, values in bridge.latency_s.items():
        if values:
            v = sorted(values)
            out[name] = (v[len(v) // 2] * 1e3, v[min(len(v) - 1, int(0.99 * len(v)))] * 1e3, len(v))
    return out
