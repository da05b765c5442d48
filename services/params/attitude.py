"""The attitude level's parameters (services/attitude.py)."""

from __future__ import annotations

from flight.control.failsafe import DescentParams
from flight.control.laws import STOPPING_ACCEL_FRACTION
from flight.estimation.attitude_filter import AttitudeFilterParams
from flight.estimation.camera_level import CameraLevelParams
from flight.estimation.gyro_carrier import GyroCarrierParams
from services.params import Param

STATE_SOURCES = ("truth", "estimate")
COMPENSATIONS = ("window", "slope")
ESTIMATORS = ("kalman-000", "gyro-vertical")
GV_COMPENSATIONS = ("file", "window", "none")

PARAMS = {
    "state_source": Param("estimate", choices=STATE_SOURCES,
                          doc="what the law steers on: the filter's estimate, or the simulator's truth (ablation)"),
    "k": Param([16.0, 16.0, 16.0], "1/s", 0.1, 200.0, mavlink=("ATT_K_{}", "RPY"),
               doc="law (8) angle gain per axis (roll, pitch, yaw)"),
    "alpha": Param([16.0, 16.0, 16.0], "1/s", 0.1, 200.0, mavlink=("ATT_ALPHA_{}", "RPY"),
                   doc="law (8) rate gain per axis (roll, pitch, yaw)"),
    # beyond a few degrees of error on a heavy frame the linear law saturates the rotors,
    # overshoots and can limit-cycle; errors below (fraction a_max) / (alpha k / (alpha + k))^2
    # see law (8) exactly
    "stopping_accel_fraction": Param(STOPPING_ACCEL_FRACTION, "", 0.0, 1.0,
                                     doc="law (8)'s angle loop asks at most for the rate this fraction of the "
                                         "airframe's angular acceleration can stop (flight/control/laws.py "
                                         "stopping_rate); 0: law (8) as printed"),
    "setpoint_timeout_s": Param(0.1, "s", 0.0, min_exclusive=True,
                                doc="a position setpoint older than this is not used: in the air, level and "
                                    "a controlled descent (failsafe); on the ground, idle"),
    "state_timeout_s": Param(0.05, "s", 0.0, min_exclusive=True,
                             doc="newest IMU sample (or truth) older than this: no command"),
    "restart_settle_s": Param(0.3, "s", 0.0, 10.0,
                              doc="restarted mid-flight by the supervisor: no command for this long after the "
                                  "first sample, while the filter settles (the motor driver's failsafe flies)"),
    "failsafe_descent": Param({}, table=DescentParams,
                              doc="the failsafe descent's settings (flight/control/failsafe.py DescentParams)"),
    "filter": Param({}, table=AttitudeFilterParams,
                    doc="the attitude filter's settings (flight/estimation/attitude_filter.py AttitudeFilterParams)"),
    # a multirotor's accelerometer reads "level" whenever it tilts to accelerate, so 000's plain
    # accelerometer angles pull the estimate toward level in every manoeuvre
    "compensate_acceleration": Param(True, doc="subtract the position level's acceleration from the accelerometer "
                                               "before deriving roll and pitch (004's observation (5)); false: 000 "
                                               "as printed"),
    # "window" has no lag between the two velocity changes, so a tilt step is not read as a pull
    # towards level; the published acceleration is the velocity's slope, ~50 ms late
    "acceleration_compensation": Param("window", choices=COMPENSATIONS,
                                       doc="window: the position level's velocity change over accel_window_s "
                                           "against the accelerometer's at the filter's attitude; slope: subtract "
                                           "the position level's published acceleration"),
    "accel_window_s": Param(0.1, "s", 0.0, 0.5, min_exclusive=True,
                            doc="the window of acceleration_compensation = \"window\""),
    # kalman-000 is the default because it flies better in this stack (docs/gyrovertical.md)
    "estimator": Param("kalman-000", choices=ESTIMATORS,
                       doc="the filter's angle measurement: kalman-000, the accelerometer angles of 000; "
                           "gyro-vertical, the adaptive gyro-vertical of 004 (raw IMU, its own accelerometer "
                           "trust; compensate_acceleration does not apply, gyrovertical_compensation does)"),
    "gyrovertical_params": Param("", doc="the gyro-vertical's trained parameter file (`zenpilot "
                                         "train-gyrovertical`); \"\": the one the vehicle file names (its "
                                         "gyrovertical_params), else the shipped x250 file"),
    # a filter trained without it trusts the accelerometer as a manoeuvre leaves it; one trained with it,
    # as the compensated one (docs/gyrovertical.md): so by default the file decides
    "gyrovertical_compensation": Param("file", choices=GV_COMPENSATIONS,
                                       doc="the gyro-vertical's acceleration compensation: window, the position "
                                           "level's velocity change over accel_window_s against the IMU's "
                                           "specific force at the gyro-vertical's attitude (its gravity the "
                                           "observation); none: the accelerometer (004); file: as the parameter "
                                           "file was trained (its [meta] compensation, none if absent)"),
    "imu_rate_hz": Param(400.0, "Hz", 0.0, min_exclusive=True,
                         doc="the gyro-vertical's sample rate (its variances are per sample)"),
    "camera_level": Param(True, doc="remove the accelerometer bias's tilt with the camera's attitude (vision/pose, "
                                    "low-passed: camera_level.py CameraLevel); false: no camera at this "
                                    "level (000)"),
    "camera_level_settings": Param({}, table=CameraLevelParams,
                                   doc="CameraLevel's settings (flight/estimation/camera_level.py CameraLevelParams)"),
    # the 000 filter (Euler axes, body rate as Euler rate) cannot follow a flip (001)
    "carrier": Param({}, table=GyroCarrierParams,
                     doc="past these tilts and rates a gyro-integrated quaternion carries the estimate, the filter "
                         "restarts from it near level (flight/estimation/gyro_carrier.py GyroCarrierParams)"),
}
