"""The MAVLink bridge's logic, without Zenoh or sockets (testable with a byte buffer).

`Bridge` turns the stack's latest messages into MAVLink telemetry (NED/FRD
through flight/mavframes.py, the only place frames are converted) and runs the
MAVLink microservices a ground station (QGroundControl, MAVSDK) expects:
heartbeat/modes, commands (every COMMAND_LONG/COMMAND_INT gets a COMMAND_ACK),
parameters, missions, offboard targets, and the GCS-link failsafe. What the
stack must do is returned as actions: ("command", planner/command fields),
("mission", planner/mission fields) and ("param", param/set fields); the
service shell publishes them.

Modes: the vehicle calls itself MAV_AUTOPILOT_PX4 and uses PX4's custom-mode
numbering (custom_mode = main << 16 | sub << 24; DO_SET_MODE: param2 main, param3
sub), which MAVSDK and QGroundControl decode: hold = AUTO.LOITER, position =
POSCTL, mission = AUTO.MISSION, takeoff = AUTO.TAKEOFF, land = AUTO.LAND, return
= AUTO.RTL, offboard = OFFBOARD; the flip shows as ACRO and attitude steps as
STABILIZED (reported, not settable). The flip is the custom command
MAV_CMD_USER_1 (31010), as a command (flying) or a mission item, accepted only while
the planner says it can fly one (planner/flip_status: it has a flip controller, built
for its mission's flip items or its `flip_methods`, and the flip's prediction does not
refuse it); otherwise DENIED (an upload: MAV_MISSION_UNSUPPORTED) with the reason.

Missions (MISSION_INT): NAV_WAYPOINT, NAV_TAKEOFF, NAV_LAND, NAV_LOITER_TIME,
NAV_LOITER_UNLIM, NAV_DELAY (seconds), NAV_RETURN_TO_LAUNCH, MAV_CMD_USER_1 (flip); DO_CHANGE_SPEED
is accepted and ignored (the position level flies its own speed). Frames: global
(relative or AMSL altitude, around the configured home) and LOCAL_NED.
Takeoff altitudes in commands (MAV_CMD_NAV_TAKEOFF param7) are relative to
the take-off point (as ArduPilot reads them); NaN: the MIS_TAKEOFF_ALT parameter.
"""

from __future__ import annotations

import math
import os
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

from pymavlink.dialects.v20 import common as mavlink   # the MAVLink 2 messages and constants

from flight import mavframes as mf
# the services' parameter declarations only (no service, no transport): the table below
from services.params import tunable
from services.params.attitude import PARAMS as ATTITUDE_PARAMS
from services.params.mavlink import PARAMS as BRIDGE_PARAMS
from services.params.motors import PARAMS as MOTORS_PARAMS
from services.params.position import PARAMS as POSITION_PARAMS


def mavutil_v2():
    """pymavlink's mavutil speaking MAVLink 2 on the common dialect: it reads that choice from
    the environment when first imported, so a process sets it when it opens its first link,
    never on import."""
    os.environ.setdefault("MAVLINK20", "1")
    os.environ.setdefault("MAVLINK_DIALECT", "common")
    from pymavlink import mavutil
    return mavutil


def px4_mode(main: int, sub: int = 0) -> int:
    """PX4's custom_mode (px4_custom_mode.h): main mode in bits 16-23, sub mode in bits 24-31."""
    return (main << 16) | (sub << 24)


PX4_MANUAL, PX4_ALTCTL, PX4_POSCTL, PX4_AUTO, PX4_ACRO, PX4_OFFBOARD, PX4_STABILIZED = 1, 2, 3, 4, 5, 6, 7
PX4_AUTO_TAKEOFF, PX4_AUTO_LOITER, PX4_AUTO_MISSION, PX4_AUTO_RTL, PX4_AUTO_LAND = 2, 3, 4, 5, 6
MODES = {  # the project's modes -> PX4 custom mode
    "hold": px4_mode(PX4_AUTO, PX4_AUTO_LOITER), "position": px4_mode(PX4_POSCTL),
    "mission": px4_mode(PX4_AUTO, PX4_AUTO_MISSION), "takeoff": px4_mode(PX4_AUTO, PX4_AUTO_TAKEOFF),
    "land": px4_mode(PX4_AUTO, PX4_AUTO_LAND), "return": px4_mode(PX4_AUTO, PX4_AUTO_RTL),
    "offboard": px4_mode(PX4_OFFBOARD), "flip": px4_mode(PX4_ACRO), "attitude": px4_mode(PX4_STABILIZED),
}
MODE_BY_NUMBER = {number: name for name, number in MODES.items()}
SETTABLE_MODES = ("hold", "position", "mission", "takeoff", "land", "return", "offboard")
MAV_CMD_FLIP = mavlink.MAV_CMD_USER_1  # the project's flip (document 001), as a command or mission item
FORCE_DISARM = 21196  # MAVLink's magic number in param2 of ARM_DISARM: disarm even in the air
# commands that change what the vehicle does: only from a ground station (see _from_ground_station)
ACTION_COMMANDS = frozenset((mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_NAV_TAKEOFF,
                             mavlink.MAV_CMD_NAV_LAND, mavlink.MAV_CMD_NAV_LOITER_UNLIM,
                             mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH,
                             mavlink.MAV_CMD_MISSION_START, mavlink.MAV_CMD_DO_SET_MISSION_CURRENT,
                             MAV_CMD_FLIP))

# streams: message name -> (message id, default rate Hz). HIGHRES_IMU is off by default: its
# 400 Hz IMU input costs CPU; SET_MESSAGE_INTERVAL turns it on
STREAMS = {
    "HEARTBEAT": (0, 1.0), "SYS_STATUS": (1, 1.0), "SYSTEM_TIME": (2, 1.0), "ATTITUDE": (30, 25.0),
    "ATTITUDE_QUATERNION": (31, 10.0), "LOCAL_POSITION_NED": (32, 25.0), "GLOBAL_POSITION_INT": (33, 10.0),
    "MISSION_CURRENT": (42, 1.0), "HIGHRES_IMU": (105, 0.0), "BATTERY_STATUS": (147, 1.0),
    "HOME_POSITION": (242, 0.2), "EXTENDED_SYS_STATE": (245, 1.0), "AUTOPILOT_VERSION": (148, 0.0),
    "WIND_COV": (231, 1.0),
}
STREAM_BY_ID = {mid: name for name, (mid, _) in STREAMS.items()}

# Parameters over MAVLink (the one list), generated from the declarations that name a MAVLink
# parameter (services/params/): (service, key, MAVLink name pattern, axis letters or None, (min, max)),
# in this order of services (the parameter protocol's index). The values are the stack's: the stack
# file over each service's defaults (services/mavlink.py); the "mavlink" rows are the bridge's own.
_DECLARED = {"attitude": ATTITUDE_PARAMS, "position": POSITION_PARAMS, "motors": MOTORS_PARAMS,
             "mavlink": BRIDGE_PARAMS}
TUNABLE = tunable(_DECLARED)
TUNABLE_DEFAULTS = {(service, key): _DECLARED[service][key].value() for service, key, *_ in TUNABLE}
BRIDGE_PARAM_DEFAULTS = {key: value for (service, key), value in TUNABLE_DEFAULTS.items() if service == "mavlink"}

# SYS_STATUS sensor bits and the services whose health they reflect
S = mavlink
SENSOR_BITS = (
    (S.MAV_SYS_STATUS_SENSOR_3D_GYRO | S.MAV_SYS_STATUS_SENSOR_3D_ACCEL, "sim"),
    (S.MAV_SYS_STATUS_SENSOR_3D_MAG | S.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE, "sim"),
    (S.MAV_SYS_STATUS_SENSOR_VISION_POSITION, "vision"),
    (S.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL | S.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION, "attitude"),
    (S.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL | S.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL, "position"),
    (S.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS, "motors"),
    (S.MAV_SYS_STATUS_LOGGING, "recorder"),
)
# healthy only while the estimate they stand for has converged (see Bridge.estimates_converged):
# AHRS the attitude estimate, GPS the position estimate (local, around the configured home)
ESTIMATOR_BITS = ((S.MAV_SYS_STATUS_AHRS, "attitude"), (S.MAV_SYS_STATUS_SENSOR_GPS, "position"))
PREARM_REPEAT_S = 10.0  # a pre-arm failure that lasts is said again in STATUSTEXT this often

# mission items the planner flies (see mission_to_planner)
MISSION_NAV = {mavlink.MAV_CMD_NAV_WAYPOINT, mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_NAV_LAND,
               mavlink.MAV_CMD_NAV_LOITER_TIME, mavlink.MAV_CMD_NAV_LOITER_UNLIM,
               mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, mavlink.MAV_CMD_NAV_DELAY, MAV_CMD_FLIP}
MISSION_IGNORED = {mavlink.MAV_CMD_DO_CHANGE_SPEED}
GLOBAL_FRAMES = {mavlink.MAV_FRAME_GLOBAL: False, mavlink.MAV_FRAME_GLOBAL_INT: False,
                 mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT: True, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: True}
MISSION_RETRY_S = 1.0   # an upload waiting for an item asks again after this long ...
MISSION_RETRIES = 5     # ... this many times, then gives up (MAV_MISSION_OPERATION_CANCELLED)
FOREVER_S = 1e9
ARM_PENDING_S = 3.0  # an accepted arm counts as armed this long before the planner shows it
MISSION_START_GRACE_S = 3.0  # the planner shows a sent mission within this (wall) time, or it refused it


LOOPBACK_HOSTS = ("127.", "localhost", "::1", "[::1]")


def is_loopback_endpoint(endpoint: str) -> bool:
    """A pymavlink connection string that stays on this machine (udp/tcp to or on a loopback
    address). Anything else (another host, every interface, a serial radio) is a link."""
    kind, sep, rest = endpoint.partition(":")
    if not sep or kind not in ("udp", "udpin", "udpout", "udpbcast", "tcp", "tcpin"):
        return False   # a serial device, or a string pymavlink would take for one
    host = rest.rsplit(":", 1)[0]
    return host.startswith(LOOPBACK_HOSTS)


EKF_HEALTH_TIMEOUT_S = 2.5   # pos/ekf_health comes at 1 Hz


@dataclass
class BridgeConfig:
    """The bridge's settings; defaults (and their meaning) as declared in services/params/mavlink.py."""
    system_id: int = BRIDGE_PARAMS["system_id"].default
    component_id: int = BRIDGE_PARAMS["component_id"].default
    home_lat_deg: float = BRIDGE_PARAMS["home_lat_deg"].default
    home_lon_deg: float = BRIDGE_PARAMS["home_lon_deg"].default
    home_alt_m: float = BRIDGE_PARAMS["home_alt_m"].default
    gcs_timeout_s: float = BRIDGE_PARAMS["gcs_timeout_s"].default
    failsafe_hold_s: float = BRIDGE_PARAMS["failsafe_hold_s"].default
    health_timeout_s: float = BRIDGE_PARAMS["health_timeout_s"].default
    state_timeout_s: float = 0.5      # att/pos state older than this -> no telemetry, no arming
    converged_position_std_m: float = BRIDGE_PARAMS["converged_position_std_m"].default
    converged_attitude_std_deg: float = BRIDGE_PARAMS["converged_attitude_std_deg"].default
    rates_hz: dict = field(default_factory=dict)  # stream name -> rate override
    # wind speed per m/s^2 of the EKF's disturbance (the vehicle's mass / linear drag): WIND_COV
    wind_per_accel_s: float = math.nan


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
    """MAVLink names <-> stack parameters (vector parameters split per axis), in TUNABLE's order
    (the index of the parameter protocol)."""

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

    def own(self, key: str) -> float:
        """The bridge's own parameter `key` (its value, or the default when not in the table)."""
        for r in self.rows:
            if r["service"] == "mavlink" and r["key"] == key:
                return r["value"]
        return BRIDGE_PARAM_DEFAULTS[key]


class MissionStore:
    """The vehicle's side of the mission protocol (MISSION_INT; plan, not fence or rally):
    the items as uploaded (sent back as they came), the current item, an upload in progress."""

    def __init__(self):
        self.items: list = []            # MISSION_ITEM_INT messages, by seq
        self.current = 0
        self.upload: dict | None = None  # {"peer": (sys, comp), "count", "items", "asked_wall", "tries"}
        self.reached = -1                # last seq reported with MISSION_ITEM_REACHED (this run)
        self.finished = False


class Bridge:
    def __init__(self, mav: mavlink.MAVLink, config: BridgeConfig, params: ParamTable,
                 services: tuple[str, ...], counts: dict[str, int], t_origin_s: float = 0.0,
                 problem: Callable[[str], None] = lambda text: None):
        self.mav, self.cfg, self.params = mav, config, params
        self.services = services
        self.counts = counts  # bad input by reason (the service's health "rejected")
        self.t_origin_s = t_origin_s  # stack time of boot: time_boot_ms = (t - origin) * 1000
        self.problem = problem
        self.inputs: dict[str, dict | None] = {}  # att, pos, imu, baro, mag, battery, setpoint, flip
        self.health: dict[str, tuple[float, dict]] = {}  # service -> (arrival wall time, message)
        self.health_on_stack_clock = False   # lockstep: health judged by its sample time (set by the shell)
        self._now_stack = 0.0
        self.failsafe = LinkFailsafe(config.gcs_timeout_s, config.failsafe_hold_s)
        self.ground_stations: set[int] = set()   # system ids heard sending a GCS heartbeat
        self.intervals_s: dict[str, float] = {}
        for name, (_, hz) in STREAMS.items():
            hz = float(config.rates_hz.get(name, hz))
            self.intervals_s[name] = 1.0 / hz if hz > 0 else 0.0
        self.next_due = {name: 0.0 for name in STREAMS}
        self.latency_s: dict[str, deque] = {n: deque(maxlen=5000) for n in ("ATTITUDE", "LOCAL_POSITION_NED",
                                                                             "HIGHRES_IMU")}
        self.imu_requested = False  # REQUEST_MESSAGE(HIGHRES_IMU): the shell subscribes to the IMU
        self.sent = 0
        # what the GCS asked for last (None: nothing yet; the planner flies its mission file)
        self.mode: str | None = None
        self.mission = MissionStore()
        self.flying_seq: list[int] = []     # planner item -> mission seq, for the mission being flown
        self.mission_sent_wall: float | None = None  # sent, not yet seen in the planner's setpoint
        self.mission_first_phases: tuple = ()
        self.mission_live = False          # the setpoint's `item` indexes flying_seq
        self.offboard: dict | None = None  # {"kind", "target", "velocity", "yaw", "wall", "sent"}
        self.last_stack_t: float | None = None
        self.takeoff_pending: dict | None = None  # a takeoff acked IN_PROGRESS: {"peer", "altitude", "wall"}
        self.prearm_said: tuple[str, float] = ("", -math.inf)
        self.arm_accepted_wall: float | None = None

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
        if got is None or got[1]["state"] != "running":
            return False
        if self.health_on_stack_clock:   # lockstep: 1 Hz of simulated time, however slow the machine runs it
            return self._now_stack - got[1]["header"]["t_s"] <= self.cfg.health_timeout_s
        return now_wall - got[0] <= self.cfg.health_timeout_s

    def statustext(self, text: str, severity: int = mavlink.MAV_SEVERITY_WARNING) -> None:
        self.send(self.mav.statustext_encode(severity, text[:50].encode()))

    # ------------------------------------------------------------------ vehicle state
    def armed(self) -> bool:
        sp = self.inputs.get("setpoint")
        return bool(sp and sp["armed"])

    def armed_or_arming(self, wall: float) -> bool:
        """Armed, or an accepted arm command the planner has not shown yet: a GCS may follow its
        arm with takeoff or mission start at once (after the ACK, PX4 is armed)."""
        return self.armed() or (self.arm_accepted_wall is not None and wall - self.arm_accepted_wall < ARM_PENDING_S)

    def mode_name(self) -> str:
        """The project's mode now: what the GCS asked for, as the planner's phase shows it."""
        sp = self.inputs.get("setpoint")
        if sp is None:
            return "hold"
        phase = sp["phase"]
        if phase.startswith("flip"):
            return "flip"
        if phase == "attitude":
            return "attitude"
        if self.mode is None:  # the planner flies its mission file
            return "mission" if sp["mission_state"] == "running" else "hold"
        if self.mode in ("mission", "return", "offboard", "hold", "position"):
            return self.mode
        if self.mode == "takeoff":
            return "takeoff" if phase == "takeoff" else "hold"
        return self.mode

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

    def position_enu(self) -> list[float] | None:
        pos = self.inputs.get("pos")
        return [float(v) for v in pos["position_m"]] if pos else None

    def yaw_enu(self) -> float:
        sp = self.inputs.get("setpoint")
        return float(sp["attitude_rad"][2]) if sp else 0.0

    def estimates_converged(self, service: str, now: float) -> bool:
        """The attitude or position estimate is fresh and its uncertainty small (truth: zeros)."""
        if service == "attitude":
            att = self.fresh("att", now)
            limit = math.radians(self.cfg.converged_attitude_std_deg) ** 2
            return att is not None and max(att.get("euler_var_rad2", (0.0,))) <= limit
        pos = self.fresh("pos", now)
        if pos is None:
            return False
        cov = pos.get("position_cov_m2", [0.0] * 9)
        return max(cov[0], cov[4], cov[8]) <= self.cfg.converged_position_std_m ** 2

    def resting_on_ground(self, wall: float) -> bool:
        """Disarmed, on the ground and at rest, vision running: the position estimator has no fix
        there (the camera sees no marker from the ground; its covariance grows) but the vehicle is
        where it stopped, and vision corrects the estimate once airborne. Arming is allowed; the GPS
        health bit (MAVSDK's is_local_position_ok) still says the estimate has not converged."""
        pos = self.inputs.get("pos")
        return (pos is not None and not self.armed() and self.landed_state() == mavlink.MAV_LANDED_STATE_ON_GROUND
                and math.hypot(*pos["velocity_m_s"]) < 0.1
                and ("vision" not in self.services or self.healthy("vision", wall)))

    # ------------------------------------------------------------------ one loop
    def cycle(self, now_stack: float, now_wall: float, incoming) -> list[tuple[str, dict]]:
        """One loop of the bridge: every message waiting (`incoming`), then the streams and the
        timers. Messages first: a bridge that ran late (a busy machine) judges a ground station's
        streams (offboard setpoints, heartbeats) by what reached its socket, not by its own delay."""
        actions = []
        for msg in incoming:
            actions += self.handle(msg, now_stack, now_wall)
        return actions + self.tick(now_stack, now_wall)

    # ------------------------------------------------------------------ outgoing
    def tick(self, now_stack: float, now_wall: float) -> list[tuple[str, dict]]:
        """Send the streams that are due; follow the mission, offboard and the failsafe. Returns actions."""
        self._now_stack = now_stack
        actions = self.follow_mission(now_wall) + self.follow_takeoff(now_wall)
        actions += self.follow_offboard(now_stack, now_wall)
        self.retry_upload(now_wall)
        self.say_prearm(now_stack, now_wall)
        for name, interval in self.intervals_s.items():
            if interval <= 0.0 or now_wall < self.next_due[name]:
                continue
            due = self.next_due[name]  # on its period; a stream behind by a period or more restarts from now
            self.next_due[name] = due + interval if now_wall - due < interval else now_wall + interval
            self.send_stream(name, now_stack, now_wall)
        action = self.failsafe.update(now_wall, self.flying())
        if action:
            self.problem(f"GCS heartbeat lost for > {self.cfg.gcs_timeout_s} s: {action}")
            self.statustext(f"failsafe: GCS link lost, {action}", mavlink.MAV_SEVERITY_CRITICAL)
            self.mode = "hold" if action == "hold" else "land"
            self.offboard = None
            actions.append(("command", self.command_fields(action, origin="failsafe")))
        self.last_stack_t = now_stack
        return actions

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
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        mode = self.mode_name()
        if mode in ("hold", "position", "offboard", "return", "takeoff", "land", "mission"):
            base |= mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED | mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
        if mode == "mission":
            base |= mavlink.MAV_MODE_FLAG_AUTO_ENABLED
        if self.armed():
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if self.inputs.get("setpoint") is None:
            status = mavlink.MAV_STATE_BOOT
        elif self.failsafe.state != "ok":
            status = mavlink.MAV_STATE_CRITICAL
        else:
            status = mavlink.MAV_STATE_ACTIVE if self.armed() else mavlink.MAV_STATE_STANDBY
        return self.mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base,
                                         MODES[mode], status)

    def sensor_bits(self, now_stack: float, now_wall: float) -> tuple[int, int]:
        """SYS_STATUS (present = enabled, healthy): services' health, estimates converged, pre-arm checks."""
        present = health = 0
        for bits, service in SENSOR_BITS:
            if service not in self.services:
                continue
            present |= bits
            if self.healthy(service, now_wall):
                health |= bits
        for bits, service in ESTIMATOR_BITS:
            if service not in self.services:
                continue
            present |= bits
            if self.healthy(service, now_wall) and self.estimates_converged(service, now_stack):
                health |= bits
        if "battery" in self.inputs:
            present |= mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
            health |= mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
        present |= mavlink.MAV_SYS_STATUS_PREARM_CHECK
        if self.armed() or not self.arming_blocker(now_stack, now_wall):
            health |= mavlink.MAV_SYS_STATUS_PREARM_CHECK
        return present, health

    def _msg_sys_status(self, now, wall):
        present, health = self.sensor_bits(now, wall)
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

    def _msg_wind_cov(self, now, wall):
        """The EKF's wind (its disturbance acceleration x mass / drag), as PX4 sends it; nothing
        without the wind estimation (the disturbance is then held at 0, not estimated)."""
        ekf = self.fresh("ekf", now, timeout_s=EKF_HEALTH_TIMEOUT_S)
        if ekf is None or not ekf["disturbance_estimated"] or not math.isfinite(self.cfg.wind_per_accel_s):
            return None
        east, north = (a * self.cfg.wind_per_accel_s for a in ekf["disturbance_m_s2"])   # ENU x, y
        return self.mav.wind_cov_encode(int(max(0.0, ekf["header"]["t_s"] - self.t_origin_s) * 1e6), north, east,
                                        math.nan, math.nan, math.nan, math.nan, 0.0, 0.0)

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

    def _msg_mission_current(self, now, wall):
        m = self.mission
        if not m.items:
            state = mavlink.MISSION_STATE_NO_MISSION
        elif m.finished:
            state = mavlink.MISSION_STATE_COMPLETE
        elif self.mode_name() == "mission":
            state = mavlink.MISSION_STATE_ACTIVE
        else:
            state = mavlink.MISSION_STATE_NOT_STARTED if m.reached < 0 else mavlink.MISSION_STATE_PAUSED
        seq = len(m.items) if m.finished else m.current
        return self.mav.mission_current_encode(seq, len(m.items), state, 0)

    def _msg_autopilot_version(self, now, wall):
        caps = (mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED)
        version = (0 << 24) | (1 << 16) | (0 << 8) | mavlink.FIRMWARE_VERSION_TYPE_DEV  # 0.1.0 dev
        return self.mav.autopilot_version_encode(caps, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8,
                                                 0, 0, 0x7A70_0000 + self.cfg.system_id)  # uid: "zp" + id

    # ------------------------------------------------------------------ incoming
    def handle(self, msg, now_stack: float, now_wall: float) -> list[tuple[str, dict]]:
        """One received message -> replies sent, actions returned. Bad input is counted."""
        self._now_stack = now_stack
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
        # x, y are integers (degrees * 1e7 or metres * 1e4): INT32_MAX is their "no value"
        p = [msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z]
        return self._command(msg, msg.command, p, now, wall)

    def _ack(self, msg, command: int, result: int, reason: str = "", progress: int = 0) -> None:
        self.send(self.mav.command_ack_encode(command, result, progress, 0, msg.get_srcSystem(),
                                              msg.get_srcComponent()))
        if reason:
            self.statustext(f"cmd {command}: {reason}")

    def command_fields(self, command: str, altitude_m: float = 0.0, position_m=(0.0, 0.0, 0.0),
                       yaw_rad: float = 0.0, origin: str = "mavlink") -> dict:
        return {"command": command, "altitude_m": float(altitude_m), "position_m": [float(v) for v in position_m],
                "yaw_rad": float(yaw_rad), "origin": origin}

    def _command(self, msg, command: int, p: list, now: float, wall: float) -> list:
        """One command. Unused parameters may be NaN ("no value", the command protocol); a
        parameter that is used must be finite: NaN means its default where it has one."""
        origin = f"mavlink:{msg.get_srcSystem()}/{msg.get_srcComponent()}"
        C, R = mavlink, mavlink
        if command in ACTION_COMMANDS and not self._from_ground_station(msg):
            return self._deny(msg, command, R.MAV_RESULT_DENIED,
                              f"system {msg.get_srcSystem()} has sent no GCS heartbeat")
        if command == C.MAV_CMD_COMPONENT_ARM_DISARM:
            if not _finite(p[0]):
                return self._deny(msg, command, R.MAV_RESULT_DENIED, "param1 (arm) must be 0 or 1")
            force = _finite(p[1]) and int(round(p[1])) == FORCE_DISARM
            if p[0] >= 0.5:
                if self.armed():
                    self._ack(msg, command, R.MAV_RESULT_ACCEPTED)
                    return []
                why = self.arming_blocker(now, wall)
                if why:
                    return self._deny(msg, command, R.MAV_RESULT_TEMPORARILY_REJECTED, f"Preflight Fail: {why}")
                self._ack(msg, command, R.MAV_RESULT_ACCEPTED)
                self.arm_accepted_wall = wall
                self.mode = self.mode if self.mode in ("hold", "position") else "hold"
                return [("command", self.command_fields("arm", origin=origin))]
            if self.flying() and not force:
                return self._deny(msg, command, R.MAV_RESULT_DENIED, "in the air: land first")
            self._ack(msg, command, R.MAV_RESULT_ACCEPTED)
            self.offboard, self.arm_accepted_wall = None, None
            return [("command", self.command_fields("disarm", origin=origin))]
        if command == C.MAV_CMD_NAV_TAKEOFF:
            alt = p[6] if _finite(p[6]) else self.params.own("takeoff_alt_m")
            return self._takeoff(msg, command, alt, origin, wall)
        if command == C.MAV_CMD_NAV_LAND:
            return self._switch(msg, command, "land", origin, now, wall)
        if command == C.MAV_CMD_NAV_LOITER_UNLIM:
            return self._switch(msg, command, "hold", origin, now, wall)
        if command == C.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self._switch(msg, command, "return", origin, now, wall)
        if command == C.MAV_CMD_MISSION_START:
            first = int(p[0]) if _finite(p[0]) and p[0] >= 0 else None
            if first is not None and first < len(self.mission.items):
                self.mission.current = first
            return self._switch(msg, command, "mission", origin, now, wall)
        if command == C.MAV_CMD_DO_SET_MISSION_CURRENT:
            if not _finite(p[0]) or not 0 <= int(p[0]) < len(self.mission.items):
                return self._deny(msg, command, R.MAV_RESULT_DENIED, f"no mission item {p[0]}")
            self._ack(msg, command, R.MAV_RESULT_ACCEPTED)
            return self.set_current(int(p[0]), origin, wall)
        if command == MAV_CMD_FLIP:
            result, why = self.flip_refusal(now)
            if why:   # never ACCEPTED for a flip the planner would refuse
                return self._deny(msg, command, result, why)
            if not self.flying():
                return self._deny(msg, command, R.MAV_RESULT_TEMPORARILY_REJECTED, "not flying")
            self._ack(msg, command, R.MAV_RESULT_ACCEPTED)
            self.mode = "hold"  # after the flip the planner holds
            return [("command", self.command_fields("flip", origin=origin))]
        if command == C.MAV_CMD_DO_SET_MODE:
            if not _finite(p[0]) or not int(p[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                return self._deny(msg, command, R.MAV_RESULT_DENIED, "only custom (PX4) modes")
            main = int(p[1]) if _finite(p[1]) else 0
            sub = int(p[2]) if _finite(p[2]) else 0
            return self._set_mode(msg, command, px4_mode(main, sub), origin, now, wall)
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
        self.problem(f"command {command} from {msg.get_srcSystem()}: {reason}")
        return []

    def flip_refusal(self, now: float) -> tuple[int, str]:
        """(MAV_RESULT, why) when the planner cannot fly a flip now, (ACCEPTED, "") when it can: from
        its planner/flip_status, sent once a second only while it has a flip controller (the
        texts fit a STATUSTEXT after "cmd 31010: ")."""
        status = self.inputs.get("flip")
        if status is None:   # never heard: no flip controller was built
            return mavlink.MAV_RESULT_DENIED, "no flip: set planner.flip_methods"
        if now - status["header"]["t_s"] > self.cfg.health_timeout_s:   # the planner stopped saying so
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED, "planner's flip status is stale"
        if status["refused"]:   # its prediction: the planner would not start it (its log says why)
            return mavlink.MAV_RESULT_DENIED, "flip predicted unsafe: see planner log"
        return mavlink.MAV_RESULT_ACCEPTED, ""

    def arming_blocker(self, now: float, wall: float) -> str:
        """Why arming is refused now ('' if it is not): the pre-arm checks."""
        for service in ("attitude", "position", "motors", "planner"):
            if service in self.services and not self.healthy(service, wall):
                return f"{service} not healthy"
        if self.fresh("pos", now) is None or self.fresh("att", now) is None:
            return "no fresh attitude/position estimate"
        if not self.estimates_converged("attitude", now):
            return "attitude estimate not converged"
        if not self.estimates_converged("position", now) and not self.resting_on_ground(wall):
            return "position estimate not converged"
        if self.failsafe.state != "ok":
            return "failsafe active"
        return ""

    def say_prearm(self, now: float, wall: float) -> None:
        """A pre-arm failure in STATUSTEXT when it changes (and again every PREARM_REPEAT_S), disarmed only."""
        if self.armed() or self.inputs.get("setpoint") is None:
            return
        why = self.arming_blocker(now, wall)
        said, at = self.prearm_said
        if why and (why != said or wall - at >= PREARM_REPEAT_S):
            self.statustext(f"Preflight Fail: {why}", mavlink.MAV_SEVERITY_CRITICAL)
            self.prearm_said = (why, wall)
        elif not why:
            self.prearm_said = ("", -math.inf)

    def _takeoff(self, msg, command: int, alt: float, origin: str, wall: float) -> list:
        """Acknowledged IN_PROGRESS, then ACCEPTED once at the altitude (FAILED if something else
        replaces it); a repeat while it climbs gets IN_PROGRESS again."""
        if not _finite(alt) or not 0.0 < alt <= 100.0:
            return self._deny(msg, command, mavlink.MAV_RESULT_DENIED, f"altitude {alt} outside (0, 100] m")
        if not self.armed_or_arming(wall):
            return self._deny(msg, command, mavlink.MAV_RESULT_TEMPORARILY_REJECTED, "not armed")
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        if self.takeoff_pending is not None:
            self._ack(msg, command, mavlink.MAV_RESULT_IN_PROGRESS, progress=self.takeoff_progress())
            return []
        self.takeoff_pending = {"peer": peer, "command": command, "altitude": float(alt), "wall": wall,
                                "said_wall": wall, "from": self.position_enu() or [0.0, 0.0, 0.0]}
        self._ack(msg, command, mavlink.MAV_RESULT_IN_PROGRESS, progress=0)
        self.mode, self.offboard = "takeoff", None
        return [("command", self.command_fields("takeoff", altitude_m=alt, origin=origin))]

    def takeoff_progress(self) -> int:
        pend, pos = self.takeoff_pending, self.position_enu()
        if pend is None or pos is None:
            return 0
        span = max(1e-3, pend["altitude"] - pend["from"][2])
        return int(max(0.0, min(99.0, 100.0 * (pos[2] - pend["from"][2]) / span)))

    def follow_takeoff(self, wall: float) -> list:
        pend = self.takeoff_pending
        if pend is None:
            return []
        sp = self.inputs.get("setpoint")
        sys_id, comp = pend["peer"]
        if self.mode != "takeoff" or (sp is not None and not sp["armed"] and not self.armed_or_arming(wall)):
            result = mavlink.MAV_RESULT_FAILED  # replaced by another command, or disarmed
        elif sp is not None and sp["phase"] in ("hold", "settle") and wall - pend["wall"] > 0.2:
            result = mavlink.MAV_RESULT_ACCEPTED  # the planner's takeoff item is done: at the altitude
        else:
            if wall - pend["said_wall"] >= 1.0:  # progress at 1 Hz keeps the GCS waiting
                pend["said_wall"] = wall
                self.send(self.mav.command_ack_encode(pend["command"], mavlink.MAV_RESULT_IN_PROGRESS,
                                                      self.takeoff_progress(), 0, sys_id, comp))
            return []
        self.send(self.mav.command_ack_encode(pend["command"], result, 100 if result == 0 else 0, 0, sys_id, comp))
        self.takeoff_pending = None
        return []

    def _switch(self, msg, command: int, mode: str, origin: str, now: float, wall: float) -> list:
        """Fly `mode` (one of SETTABLE_MODES) now, or refuse with the reason."""
        R = mavlink
        flying, armed = self.flying(), self.armed_or_arming(wall)
        actions: list = []
        if mode in ("hold", "position"):
            if flying:
                actions = [("command", self.command_fields("hold", origin=origin))]
        elif mode == "land":
            if not flying:
                return self._deny(msg, command, R.MAV_RESULT_TEMPORARILY_REJECTED, "not flying")
            actions = [("command", self.command_fields("land", origin=origin))]
        elif mode == "takeoff":
            return self._takeoff(msg, command, self.params.own("takeoff_alt_m"), origin, wall)
        elif mode == "return":
            if not flying:
                return self._deny(msg, command, R.MAV_RESULT_TEMPORARILY_REJECTED, "not flying")
            actions = [("mission", self.return_mission(origin))]
        elif mode == "mission":
            if not self.mission.items:
                return self._deny(msg, command, R.MAV_RESULT_DENIED, "no mission uploaded")
            if not armed:
                return self._deny(msg, command, R.MAV_RESULT_TEMPORARILY_REJECTED, "arm first")
            if self.mission.finished or self.mission.current >= len(self.mission.items):
                self.mission.current = 0
            try:
                actions = [("mission", self.start_mission(self.mission.current, origin, wall))]
            except ValueError as exc:
                return self._deny(msg, command, R.MAV_RESULT_DENIED, str(exc))
        elif mode == "offboard":
            off = self.offboard
            if off is None or wall - off["wall"] > self.params.own("offboard_timeout_s"):
                return self._deny(msg, command, R.MAV_RESULT_DENIED, "no offboard setpoint")
            if not armed:
                return self._deny(msg, command, R.MAV_RESULT_TEMPORARILY_REJECTED, "arm first")
            off["sent"] = None  # fly the current target from now
        self._ack(msg, command, R.MAV_RESULT_ACCEPTED)
        if mode != "offboard":
            self.offboard = None
        if mode != "mission":
            self.mission_live, self.mission_sent_wall = False, None
        self.mode = mode
        return actions

    def _set_mode(self, msg, command: int, custom: int, origin: str, now: float, wall: float) -> list:
        mode = MODE_BY_NUMBER.get(custom)
        if mode is None or mode not in SETTABLE_MODES:
            main, sub = (custom >> 16) & 0xFF, (custom >> 24) & 0xFF
            return self._deny(msg, command, mavlink.MAV_RESULT_DENIED,
                              f"mode {main}.{sub} not flown (hold, position, mission, land, return, offboard)")
        if mode == self.mode_name() and mode not in ("mission", "offboard"):
            self._ack(msg, command, mavlink.MAV_RESULT_ACCEPTED)
            return []
        return self._switch(msg, command, mode, origin, now, wall)

    def _on_set_mode(self, msg, now, wall):  # the deprecated message, still sent by some GCSs
        if msg.target_system in (0, self.cfg.system_id) and self._from_ground_station(msg):
            if not msg.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                return self._deny(msg, mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_RESULT_DENIED, "only custom modes")
            return self._set_mode(msg, mavlink.MAV_CMD_DO_SET_MODE, msg.custom_mode,
                                  f"mavlink:{msg.get_srcSystem()}", now, wall)
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

    # -- missions ------------------------------------------------------------------
    def return_mission(self, origin: str) -> dict:
        """Return: to above home at max(current altitude, RTL_RETURN_ALT), then land."""
        pos = self.position_enu() or [0.0, 0.0, 0.0]
        z = max(pos[2], self.params.own("return_alt_m"))
        return mission_fields([("goto", [0.0, 0.0, z], self.yaw_enu(), 0.0, self.params.own("acceptance_radius_m")),
                               ("land", [0.0, 0.0, 0.0], 0.0, 0.0, 1.0)], origin)

    def item_to_enu(self, item) -> list[float] | None:
        """A mission item's position, world ENU (None: the item has no position of its own)."""
        c = self.cfg
        if item.frame in GLOBAL_FRAMES:
            if item.x == 0 and item.y == 0:
                return None
            relative = GLOBAL_FRAMES[item.frame]
            lat, lon = (item.x, item.y) if isinstance(item.x, float) and item.get_type() == "MISSION_ITEM" \
                else (item.x * 1e-7, item.y * 1e-7)
            ned = mf.geodetic_to_ned(lat, lon, c.home_alt_m + item.z if relative else item.z,
                                     c.home_lat_deg, c.home_lon_deg, c.home_alt_m)
        elif item.frame == mavlink.MAV_FRAME_LOCAL_NED:
            scale = 1.0 if item.get_type() == "MISSION_ITEM" else 1e-4  # MISSION_ITEM_INT: metres * 1e4
            ned = [item.x * scale, item.y * scale, item.z]
        else:
            return None
        return [float(v) for v in mf.ned_to_enu(ned)]

    def check_item(self, item) -> int:
        """MAV_MISSION_ACCEPTED or the error for one uploaded item."""
        M = mavlink
        if item.command in MISSION_IGNORED:
            return M.MAV_MISSION_ACCEPTED
        if item.command not in MISSION_NAV:
            return M.MAV_MISSION_UNSUPPORTED
        needs_position = item.command in (M.MAV_CMD_NAV_WAYPOINT,)
        if item.frame not in GLOBAL_FRAMES and item.frame not in (M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_MISSION):
            return M.MAV_MISSION_UNSUPPORTED_FRAME
        if needs_position and self.item_to_enu(item) is None:
            return M.MAV_MISSION_INVALID_PARAM5_X
        if item.command in (M.MAV_CMD_NAV_WAYPOINT, M.MAV_CMD_NAV_TAKEOFF):
            if not _finite(item.z) or (item.command == M.MAV_CMD_NAV_TAKEOFF and item.frame in GLOBAL_FRAMES
                                       and GLOBAL_FRAMES[item.frame] and not 0.0 < item.z <= 100.0):
                return M.MAV_MISSION_INVALID_PARAM7
        if item.command in (M.MAV_CMD_NAV_LOITER_TIME, M.MAV_CMD_NAV_DELAY) and not (
                _finite(item.param1) and item.param1 >= 0):  # NAV_DELAY by time of day (param1 -1): not flown
            return M.MAV_MISSION_INVALID_PARAM1
        return M.MAV_MISSION_ACCEPTED

    def mission_to_planner(self, first: int) -> tuple[list, list[int]]:
        """The stored items from `first` -> planner items (type, position ENU, yaw, hold, acceptance)
        and the mission seq of each; a mission started on the ground takes off first."""
        M = mavlink
        pos = self.position_enu() or [0.0, 0.0, 0.0]
        yaw = self.yaw_enu()
        acc_default = self.params.own("acceptance_radius_m")
        out, seqs = [], []
        here = list(pos)
        for seq in range(first, len(self.mission.items)):
            it = self.mission.items[seq]
            target = self.item_to_enu(it)
            if it.command == M.MAV_CMD_NAV_WAYPOINT:
                yaw = mf.yaw_ned_to_enu(math.radians(it.param4)) if _finite(it.param4) else yaw
                hold = it.param1 if _finite(it.param1) and it.param1 > 0 else 0.0
                acc = it.param2 if _finite(it.param2) and it.param2 > 0 else acc_default
                out.append(("goto", target, yaw, hold, acc))
                here = target
            elif it.command == M.MAV_CMD_NAV_TAKEOFF:
                z = target[2] if target is not None else (it.z if _finite(it.z) else self.params.own("takeoff_alt_m"))
                out.append(("takeoff", [here[0], here[1], z], yaw, 0.0, acc_default))
                here = [here[0], here[1], z]
            elif it.command == M.MAV_CMD_NAV_DELAY:  # MAVSDK's loiter_time_s: wait where it is
                out.append(("hold", here, yaw, float(it.param1), acc_default))
            elif it.command in (M.MAV_CMD_NAV_LOITER_TIME, M.MAV_CMD_NAV_LOITER_UNLIM):
                if target is not None:
                    out.append(("goto", target, yaw, 0.0, acc_default))
                    seqs.append(seq)
                    here = target
                hold = it.param1 if it.command == M.MAV_CMD_NAV_LOITER_TIME else FOREVER_S
                out.append(("hold", here, yaw, hold, acc_default))
            elif it.command == M.MAV_CMD_NAV_LAND:
                if target is not None:
                    out.append(("goto", [target[0], target[1], here[2]], yaw, 0.0, acc_default))
                    seqs.append(seq)
                out.append(("land", here, yaw, 0.0, acc_default))
            elif it.command == M.MAV_CMD_NAV_RETURN_TO_LAUNCH:
                z = max(here[2], self.params.own("return_alt_m"))
                out.append(("goto", [0.0, 0.0, z], yaw, 0.0, acc_default))
                seqs.append(seq)
                out.append(("land", [0.0, 0.0, 0.0], yaw, 0.0, acc_default))
            elif it.command == MAV_CMD_FLIP:
                out.append(("flip", here, yaw, 0.0, acc_default))
            else:
                continue  # ignored items (DO_CHANGE_SPEED): reached along with the next one
            seqs.append(seq)
        if not out:
            raise ValueError("the mission has no item to fly")
        if not self.flying() and out[0][0] != "takeoff":
            z = next((i[1][2] for i in out if i[0] == "goto"), self.params.own("takeoff_alt_m"))
            out.insert(0, ("takeoff", [pos[0], pos[1], max(z, 0.2)], yaw, 0.0, acc_default))
            seqs.insert(0, first)
        return out, seqs

    def start_mission(self, first: int, origin: str, wall: float) -> dict:
        items, seqs = self.mission_to_planner(first)
        self.flying_seq = seqs
        self.mission.current, self.mission.finished = first, False
        self.mission.reached = first - 1
        self.mission_sent_wall, self.mission_live = wall, False
        self.mission_first_phases = {"takeoff": ("takeoff",), "goto": ("goto", "hold"), "hold": ("hold", "settle"),
                                     "land": ("land", "landed"), "flip": ("flip",)}[items[0][0]]
        return mission_fields(items, origin)

    def follow_mission(self, wall: float) -> list:
        """MISSION_CURRENT / MISSION_ITEM_REACHED from the planner's progress through the mission sent."""
        sp = self.inputs.get("setpoint")
        if self.mode != "mission" or sp is None or not self.flying_seq:
            return []
        if not self.mission_live:  # the planner's setpoint still shows what it flew before
            if sp["item"] == 0 and sp["mission_state"] == "running" and sp["phase"].startswith(self.mission_first_phases):
                self.mission_live = True
            elif self.mission_sent_wall is not None and wall - self.mission_sent_wall > MISSION_START_GRACE_S:
                self.statustext("mission: the planner did not take it", mavlink.MAV_SEVERITY_ERROR)
                self.mode, self.mission_sent_wall = "hold", None
                return []
            else:
                return []
        m = self.mission
        done = len(self.flying_seq) if sp["mission_state"] == "completed" else min(sp["item"], len(self.flying_seq))
        # every mission item before the one being flown is reached (ignored items with the next one)
        reached = self.flying_seq[done] - 1 if done < len(self.flying_seq) else len(m.items) - 1
        for seq in range(m.reached + 1, reached + 1):
            self.send(self.mav.mission_item_reached_encode(seq))
        if reached > m.reached:
            m.reached = reached
        current = self.flying_seq[done] if done < len(self.flying_seq) else len(m.items)
        if done >= len(self.flying_seq) and not m.finished:
            m.finished = True
            self.statustext("mission finished", mavlink.MAV_SEVERITY_INFO)
        if current != m.current:
            m.current = min(current, len(m.items))
            self.send(self._msg_mission_current(0.0, wall))
        return []

    def set_current(self, seq: int, origin: str, wall: float) -> list:
        """The mission goes on from `seq` (flown from there now if the mission is being flown)."""
        m = self.mission
        m.current, m.finished = seq, False
        m.reached = min(m.reached, seq - 1)
        actions = []
        if self.mode == "mission" and self.armed():
            actions = [("mission", self.start_mission(seq, origin, wall))]
        self.send(self._msg_mission_current(0.0, 0.0))
        return actions

    def _mission_ack(self, msg, result: int, mission_type: int = mavlink.MAV_MISSION_TYPE_MISSION) -> None:
        self.send(self.mav.mission_ack_encode(msg.get_srcSystem(), msg.get_srcComponent(), result, mission_type))

    def _plan_only(self, msg) -> bool:
        """Missions only: fence and rally points are not supported (answered so)."""
        mission_type = getattr(msg, "mission_type", 0)
        if mission_type == mavlink.MAV_MISSION_TYPE_MISSION:
            return True
        self._mission_ack(msg, mavlink.MAV_MISSION_UNSUPPORTED, mission_type)
        return False

    def _on_mission_count(self, msg, now, wall):
        if not self._for_us(msg) or not self._from_ground_station(msg) or not self._plan_only(msg):
            return []
        if self.mode_name() == "mission" and self.flying():
            self._mission_ack(msg, mavlink.MAV_MISSION_DENIED)  # not while it is being flown
            self.statustext("mission: switch to hold before uploading")
            return []
        if msg.count == 0:
            return self._clear(msg)
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        self.mission.upload = {"peer": peer, "count": msg.count, "items": [], "asked_wall": wall, "tries": 0}
        self.send(self.mav.mission_request_int_encode(*peer, 0, mavlink.MAV_MISSION_TYPE_MISSION))
        return []

    def _on_mission_item_int(self, msg, now, wall):
        up = self.mission.upload
        if not self._for_us(msg) or up is None or (msg.get_srcSystem(), msg.get_srcComponent()) != up["peer"]:
            return []
        if not self._plan_only(msg):
            return []
        expected = len(up["items"])
        if msg.seq != expected:  # a repeat of one we have, or out of order: ask for the right one
            if msg.seq > expected:
                self.send(self.mav.mission_request_int_encode(*up["peer"], expected, mavlink.MAV_MISSION_TYPE_MISSION))
            return []
        result, why = self.check_item(msg), ""
        if result == mavlink.MAV_MISSION_ACCEPTED and msg.command == MAV_CMD_FLIP:
            flip, why = self.flip_refusal(now)   # a flip the planner cannot fly is refused at upload
            if why:
                result = (mavlink.MAV_MISSION_ERROR if flip == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
                          else mavlink.MAV_MISSION_UNSUPPORTED)
        if result != mavlink.MAV_MISSION_ACCEPTED:
            self.mission.upload = None
            self._mission_ack(msg, result)
            why = (f"mission item {msg.seq}: {why}" if why else
                   f"mission item {msg.seq}: command {msg.command} frame {msg.frame} refused ({result})")
            self.statustext(why)
            self.problem(why)
            return []
        up["items"].append(msg)
        up["asked_wall"], up["tries"] = wall, 0
        if len(up["items"]) < up["count"]:
            self.send(self.mav.mission_request_int_encode(*up["peer"], len(up["items"]),
                                                          mavlink.MAV_MISSION_TYPE_MISSION))
            return []
        m = self.mission
        m.items, m.upload, m.current, m.reached, m.finished = up["items"], None, 0, -1, False
        self._mission_ack(msg, mavlink.MAV_MISSION_ACCEPTED)
        self.send(self._msg_mission_current(now, wall))
        return []

    _on_mission_item = _on_mission_item_int  # the float variant (deprecated): same fields

    def retry_upload(self, wall: float) -> None:
        up = self.mission.upload
        if up is None or wall - up["asked_wall"] < MISSION_RETRY_S:
            return
        if up["tries"] >= MISSION_RETRIES:
            self.mission.upload = None
            self.send(self.mav.mission_ack_encode(*up["peer"], mavlink.MAV_MISSION_OPERATION_CANCELLED,
                                                  mavlink.MAV_MISSION_TYPE_MISSION))
            self.count("mavlink_mission_upload_timeout")
            return
        up["tries"] += 1
        up["asked_wall"] = wall
        self.send(self.mav.mission_request_int_encode(*up["peer"], len(up["items"]), mavlink.MAV_MISSION_TYPE_MISSION))

    def _on_mission_request_list(self, msg, now, wall):
        if self._for_us(msg) and self._plan_only(msg):
            self.send(self.mav.mission_count_encode(msg.get_srcSystem(), msg.get_srcComponent(),
                                                    len(self.mission.items), mavlink.MAV_MISSION_TYPE_MISSION))
        return []

    def _on_mission_request_int(self, msg, now, wall):
        if not self._for_us(msg) or not self._plan_only(msg):
            return []
        if not 0 <= msg.seq < len(self.mission.items):
            self._mission_ack(msg, mavlink.MAV_MISSION_INVALID_SEQUENCE)
            return []
        it = self.mission.items[msg.seq]
        x, y = it.x, it.y
        if it.get_type() == "MISSION_ITEM":  # stored from the float variant: sent back as MISSION_ITEM_INT
            scale = 1e7 if it.frame in GLOBAL_FRAMES else 1e4
            x, y = int(round(x * scale)), int(round(y * scale))
        self.send(self.mav.mission_item_int_encode(
            msg.get_srcSystem(), msg.get_srcComponent(), msg.seq, it.frame, it.command,
            int(msg.seq == self.mission.current), it.autocontinue, it.param1, it.param2, it.param3, it.param4,
            x, y, it.z, mavlink.MAV_MISSION_TYPE_MISSION))
        return []

    _on_mission_request = _on_mission_request_int  # QGC's older request: answered with the INT item

    def _on_mission_ack(self, msg, now, wall):
        return []  # the end of a download: nothing to do

    def _clear(self, msg) -> list:
        m = self.mission
        m.items, m.upload, m.current, m.reached, m.finished = [], None, 0, -1, False
        self._mission_ack(msg, mavlink.MAV_MISSION_ACCEPTED)
        return []

    def _on_mission_clear_all(self, msg, now, wall):
        if not self._for_us(msg) or not self._from_ground_station(msg) or not self._plan_only(msg):
            return []
        actions = []
        if self.mode == "mission":
            self.mode, self.mission_live = "hold", False
            if self.flying():
                actions = [("command", self.command_fields("hold", origin=f"mavlink:{msg.get_srcSystem()}"))]
        self._clear(msg)
        return actions

    def _on_mission_set_current(self, msg, now, wall):
        if not self._for_us(msg) or not self._from_ground_station(msg):
            return []
        if not 0 <= msg.seq < len(self.mission.items):
            self.statustext(f"mission: no item {msg.seq}")
            return []
        return self.set_current(msg.seq, f"mavlink:{msg.get_srcSystem()}", wall)

    # -- offboard --------------------------------------------------------------
    def _on_set_position_target_local_ned(self, msg, now, wall):
        """Offboard targets (MAVSDK's offboard plugin): position or velocity, LOCAL_NED. Kept while
        streamed; flown in offboard mode; lost for COM_OF_LOSS_T: hold."""
        if not self._for_us(msg) or not self._from_ground_station(msg):
            return []
        if msg.coordinate_frame != mavlink.MAV_FRAME_LOCAL_NED:
            self.count("mavlink_target_unsupported")
            return []
        m = msg.type_mask
        use_position = not m & 0b111
        use_velocity = not use_position and not m & 0b111000
        if not use_position and not use_velocity:
            self.count("mavlink_target_unsupported")  # acceleration/thrust targets are not flown
            return []
        values = (msg.x, msg.y, msg.z) if use_position else (msg.vx, msg.vy, msg.vz)
        if not _finite(*values) or max(abs(v) for v in values) > (1e4 if use_position else 20.0):
            self.count("mavlink_bad_value")
            return []
        yaw_ignored = m & mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
        yaw = None if yaw_ignored or not _finite(msg.yaw) else mf.yaw_ned_to_enu(msg.yaw)
        enu = [float(v) for v in mf.ned_to_enu(values)]
        off = self.offboard or {"sent": None, "target": None}
        off.update(kind="position" if use_position else "velocity", wall=wall, yaw=yaw)
        if use_position:
            off["target"] = enu
        else:
            off["velocity"] = enu
            if off.get("target") is None or self.mode != "offboard":
                off["target"] = self.position_enu()
        self.offboard = off
        return []

    def follow_offboard(self, now: float, wall: float) -> list:
        off = self.offboard
        dt = 0.0 if self.last_stack_t is None else max(0.0, min(0.1, now - self.last_stack_t))
        if off is None or self.mode != "offboard":
            return []
        if wall - off["wall"] > self.params.own("offboard_timeout_s"):
            self.statustext("offboard: setpoints lost, hold", mavlink.MAV_SEVERITY_CRITICAL)
            self.problem(f"offboard setpoints lost (none for {wall - off['wall']:.2f} s): hold")
            self.mode, self.offboard = "hold", None
            return [("command", self.command_fields("hold", origin="offboard-timeout"))]
        if off["target"] is None:
            return []
        if off["kind"] == "velocity":  # the target moves at the velocity asked (the stack's clock)
            off["target"] = [p + v * dt for p, v in zip(off["target"], off["velocity"])]
        yaw = off["yaw"] if off["yaw"] is not None else self.yaw_enu()
        key = tuple(round(v, 3) for v in off["target"]) + (round(yaw, 3),)
        if key == off["sent"]:
            return []  # a stream of the same target: nothing new for the planner
        off["sent"] = key
        return [("command", self.command_fields("goto", position_m=off["target"], yaw_rad=yaw,
                                                origin="mavlink/offboard"))]

    # -- parameters --------------------------------------------------------------
    def _param_value(self, i: int) -> None:
        r = self.params.rows[i]
        self.send(self.mav.param_value_encode(r["name"].encode(), r["value"], mavlink.MAV_PARAM_TYPE_REAL32,
                                              len(self.params.rows), i))

    def _param_error(self, msg, param_id, index: int, error: int) -> None:
        name = param_id if isinstance(param_id, bytes) else str(param_id).encode()
        self.send(self.mav.param_error_encode(msg.get_srcSystem(), msg.get_srcComponent(), name[:16], index, error))

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
        if i is None:  # the parameter protocol's answer: PARAM_ERROR, at once (not a timeout)
            self.count("mavlink_unknown_param")
            self._param_error(msg, msg.param_id, msg.param_index, mavlink.MAV_PARAM_ERROR_DOES_NOT_EXIST)
            return []
        self._param_value(i)
        return []

    def _on_param_set(self, msg, now, wall):
        if not self._for_us(msg) or not self._from_ground_station(msg):
            return []
        i = self._param_index(msg.param_id, -1)
        if i is None:
            self.count("mavlink_unknown_param")
            self._param_error(msg, msg.param_id, -1, mavlink.MAV_PARAM_ERROR_DOES_NOT_EXIST)
            return []
        r = self.params.rows[i]
        lo, hi = r["bounds"]
        value = msg.param_value
        if not _finite(value) or not lo <= value <= hi:
            self.count("mavlink_bad_value")
            self.statustext(f"{r['name']}={value}: outside [{lo}, {hi}]")
            self._param_error(msg, msg.param_id, i, mavlink.MAV_PARAM_ERROR_VALUE_OUT_OF_RANGE)
            self._param_value(i)  # the older protocol's refusal: the unchanged value
            return []
        r["value"] = float(value)
        self._param_value(i)
        if r["service"] == "mavlink":
            return []  # the bridge's own: read where it is used
        value_list = self.params.vector(r["service"], r["key"]) if r["index"] is not None else [float(value)]
        return [("param", {"service": r["service"], "key": r["key"], "value": value_list})]


def mission_fields(items: list, origin: str) -> dict:
    """planner/mission fields from (type, position ENU, yaw, hold_s, acceptance_m) tuples."""
    return {"types": [i[0] for i in items], "position_m": [float(v) for i in items for v in i[1]],
            "yaw_rad": [float(math.remainder(i[2], 2 * math.pi)) for i in items],
            "hold_s": [float(min(i[3], FOREVER_S)) for i in items],
            "acceptance_m": [float(i[4]) for i in items], "origin": origin}


def latency_summary(bridge: Bridge) -> dict[str, tuple[float, float, int]]:
    """Per stream: (p50 ms, p99 ms, n) of sample time -> send."""
    out = {}
    for name, values in bridge.latency_s.items():
        if values:
            v = sorted(values)
            out[name] = (v[len(v) // 2] * 1e3, v[min(len(v) - 1, int(0.99 * len(v)))] * 1e3, len(v))
    return out
