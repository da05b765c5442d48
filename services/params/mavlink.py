"""The MAVLink bridge's parameters (services/mavlink.py, services/mavlink_logic.py)."""

from __future__ import annotations

from services.params import Param

PARAMS = {
    "endpoint": Param("udpout:127.0.0.1:14550", doc="pymavlink connection string: QGroundControl's port by default"),
    "system_id": Param(1, "", 1, 255, doc="the vehicle's MAVLink system id"),
    "component_id": Param(1, "", 1, 255, doc="the autopilot's MAVLink component id"),
    # PX4 SITL's home, so ground station maps look familiar
    "home_lat_deg": Param(47.397742, "deg", -90.0, 90.0,
                          doc="latitude of the local frame's origin (GLOBAL_POSITION_INT, HOME_POSITION, missions)"),
    "home_lon_deg": Param(8.545594, "deg", -180.0, 180.0, doc="longitude of the local frame's origin"),
    "home_alt_m": Param(488.0, "m", doc="altitude (AMSL) of the local frame's origin"),
    "gcs_timeout_s": Param(5.0, "s", 0.0, min_exclusive=True,
                           doc="no GCS heartbeat this long while flying: hold ..."),
    "failsafe_hold_s": Param(3.0, "s", 0.0, doc="... then land after holding this long"),
    "health_timeout_s": Param(3.0, "s", 0.0, min_exclusive=True,
                              doc="a service's 1 Hz health older than this: unhealthy (SYS_STATUS)"),
    "signing_key_file": Param("", doc="MAVLink 2 signing key (32 bytes, 64 hex digits or a passphrase); \"\": "
                                      "unsigned"),
    # unsigned, anyone on the link could command the vehicle
    "allow_unsigned_link": Param(False, doc="allow an endpoint off this machine (a radio, another host) without "
                                            "signing, knowingly"),
    "rates_hz": Param({}, doc="per-stream rate overrides, e.g. {ATTITUDE = 50.0} (streams: services/mavlink_logic.py "
                              "STREAMS)"),
    "max_messages_per_step": Param(200, "", 1, doc="incoming messages handled per loop at most (bounded work "
                                                   "under a flood)"),
    "converged_position_std_m": Param(0.1, "m", 0.0, min_exclusive=True,
                                      doc="position estimate converged (SYS_STATUS GPS healthy, arming allowed): "
                                          "each axis' std below this"),
    "converged_attitude_std_deg": Param(3.0, "deg", 0.0, min_exclusive=True,
                                        doc="attitude estimate converged (SYS_STATUS AHRS healthy): each angle's "
                                            "std below this"),
    # PX4's names: MAVSDK reads and sets them
    "takeoff_alt_m": Param(2.0, "m", 0.2, 100.0, mavlink="MIS_TAKEOFF_ALT",
                           doc="take-off altitude above the take-off point when a command gives none"),
    "return_alt_m": Param(0.0, "m", 0.0, 100.0, mavlink="RTL_RETURN_ALT",
                          doc="return to launch flies home at the higher of this and the current altitude, then lands"),
    "acceptance_radius_m": Param(0.3, "m", 0.05, 10.0, mavlink="NAV_ACC_RAD",
                                 doc="a mission waypoint is reached within this distance"),
    "offboard_timeout_s": Param(1.0, "s", 0.1, 10.0, mavlink="COM_OF_LOSS_T",
                                doc="offboard targets older than this: the vehicle holds"),
}
