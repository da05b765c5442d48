"""The motor driver's parameters (services/motors.py)."""

from __future__ import annotations

from flight.control.failsafe import DescentParams
from services.params import Param

OUTPUTS = ("sim", "mavlink")

PARAMS = {
    # armed and flying without a fresh command, the driver's own failsafe flies (level,
    # controlled descent, disarm on the ground; "failsafe_engaged")
    "command_timeout_s": Param(0.05, "s", 0.005, 1.0, mavlink="MOT_CMD_TIMEOUT",
                               doc="an attitude command older than this (its header, or the IMU sample "
                                   "behind it) is never mixed (\"stale_att_command\")"),
    # softer than the attitude level's: its rates are the raw gyro; yaw only held
    "failsafe_k": Param([8.0, 8.0, 2.0], "1/s", 0.0, doc="the failsafe's law (8) angle gain per axis "
                                                         "(roll, pitch, yaw)"),
    "failsafe_alpha": Param([8.0, 8.0, 2.0], "1/s", 0.0, doc="the failsafe's law (8) rate gain per axis "
                                                             "(roll, pitch, yaw)"),
    "failsafe_descent": Param({}, table=DescentParams,
                              doc="the failsafe descent's settings (flight/control/failsafe.py DescentParams)"),
    "output": Param("sim", choices=OUTPUTS,
                    doc="sim: motors/pwm only; mavlink: also the mixer's result to an external autopilot "
                        "(SET_ACTUATOR_CONTROL_TARGET) on mavlink_endpoint"),
    "mavlink_endpoint": Param("udpout:127.0.0.1:14560", doc="pymavlink connection string (output = \"mavlink\")"),
    # the hot standby ([services.motors] standby = true, real time; services/standby.py): well under the
    # vehicle's margin (its last PWM held, 20 deg of tilt in 0.45 s) and well over a late tick under load
    # (lateness max ~6 ms with a core kept busy, docs/performance.md)
    "standby_takeover_s": Param(0.025, "s", 0.005, 0.5,
                                doc="hot standby: the standby driver takes over when the active's output has "
                                    "been missing this long; an active driver whose own last output is older "
                                    "steps back to standby (it was stopped or starved)"),
    "mavlink_target_system": Param(1, "", 1, 255, doc="the external autopilot's MAVLink system id"),
}
