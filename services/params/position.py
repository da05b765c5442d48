"""The position level's parameters (services/position.py)."""

from __future__ import annotations

from flight.estimation.camera_delay import CameraDelayParams
from flight.estimation.position_ekf import PositionEKFParams
from services.params import Param

STATE_SOURCES = ("truth", "estimate")

PARAMS = {
    "state_source": Param("estimate", choices=STATE_SOURCES,
                          doc="what the laws steer on: the EKF's estimate, or the simulator's truth (ablation)"),
    "k": Param([4.0, 4.0, 4.0], "1/s", 0.05, 50.0, mavlink=("POS_K_{}", "XYZ"),
               doc="laws (10) position gain per axis (x, y, z)"),
    "alpha": Param([4.0, 4.0, 4.0], "1/s", 0.05, 50.0, mavlink=("POS_ALPHA_{}", "XYZ"),
                   doc="laws (10) velocity gain per axis (x, y, z)"),
    # law (8) saturates the x250's torque (~46 rad/s^2 about hover) for any attitude-reference
    # step over ~10 deg; at 35 deg the position and attitude loops lost their separation under
    # saturation when attitude steps handed back to position hold (a growing oscillation, the
    # mixer raising the collective); 20 deg held on every seed tried
    "max_tilt_deg": Param(20.0, "deg", 1.0, 80.0, mavlink="POS_MAX_TILT",
                          doc="the most tilt the laws may ask for; a vehicle file's max_tilt_deg lowers it "
                              "for that airframe (Vehicle.tilt_limit_rad)"),
    # a steady wind otherwise leaves an offset of a_wind / (alpha k); 8 puts the closed loop's
    # poles at -5.2, -2 and -0.76 rad/s with k = alpha = 4
    "hold_ki": Param(0.0, "1/s^3", 0.0,
                     doc="integral gain on the horizontal position error while the planner holds (phases "
                         "\"settle\" and \"hold\"); 0: laws (10) as 000 has them"),
    "hold_integral_limit_m_s2": Param(2.0, "m/s^2", 0.0, doc="the most acceleration the hold integral may ask for"),
    # the forward-Euler observer at the loop's 100 Hz is stable to 200 rad/s; the EKF's velocity is
    # not worth reading past a few rad/s: 3 in wind (docs/results.md, "The wind settings")
    "disturbance_bandwidth_rad_s": Param(0.0, "rad/s", 0.0, 50.0, doc="the horizontal disturbance observer's bandwidth "
                                         "(flight/control/laws.py DisturbanceObserver), its estimate fed forward in "
                                         "the position mode; 0: off"),
    # off by default as PX4's EKF2 has its wind estimate (EKF2_DRAG_CTRL): in still air it adds
    # ~0.3 deg of noise to the hold's attitude references, and an unstamped camera delay step is
    # absorbed worse (docs/results.md, "Hold in wind")
    "wind_estimation": Param(False, doc="the EKF learns the wind's pull (its horizontal disturbance states, "
                             "`ekf.q_disturbance_m2_s5`) and the position law feeds it forward; false: the "
                             "states held at 0"),
    "drag_fusion": Param(True, doc="with wind_estimation: the accelerometer's body x and y fused as the air's "
                         "force (the EKF's update_drag, PX4's drag fusion), which observes the wind's pull "
                         "between camera fixes and before the first"),
    "disturbance_limit_m_s2": Param(3.0, "m/s^2", 0.0, doc="the most acceleration the disturbance feed-forward may "
                                    "ask for"),
    "setpoint_timeout_s": Param(0.5, "s", 0.0, min_exclusive=True,
                                doc="a planner setpoint older than this: hold where we are"),
    "planner_loss_land_after_s": Param(5.0, "s", 0.0, doc="... and after holding this long, land there"),
    "land_speed_m_s": Param(0.5, "m/s", 0.0, min_exclusive=True,
                            doc="sink rate of a landing without the planner"),
    "vision_timeout_s": Param(3.0, "s", 0.0, min_exclusive=True,
                              doc="no camera fix fused this long in the air: the setpoint is withheld and the "
                                  "attitude level's descent lands"),
    "pose_timeout_s": Param(0.5, "s", 0.0, min_exclusive=True,
                            doc="a camera fix older than this (from its exposure) is not fused"),
    "attitude_timeout_s": Param(0.05, "s", 0.0, min_exclusive=True,
                                doc="an att/state older than this is not fused"),
    "home_position_m": Param([0.0, 0.0, 0.0], "m", doc="where the EKF starts: the take-off point (x, y, z)"),
    "position_reset_after": Param(5, "", 1, doc="camera fixes gated out in a row before the EKF restarts at one (too old, future or invalid ones do not count)"),
    "fuse_camera_at_exposure": Param(True, doc="fuse a camera fix at its exposure time; false (ablation): as if "
                                               "taken now"),
    # the attitude filter does not model the accelerometer's error in manoeuvres nor
    # unmodelled torques
    "attitude_var_floor": Param([3e-4, 3e-4, 3e-3], "rad^2", 0.0,
                                doc="floor on the attitude level's angle variances as the EKF fuses them"),
    "rate_var_floor": Param([2.5e-3, 2.5e-3, 2.5e-3], "rad^2/s^2", 0.0,
                            doc="floor on the attitude level's rate variances as the EKF fuses them"),
    # the solver's few-mm covariance ignores time-stamp and model errors of a fast climb
    "camera_var_floor": Param(1e-5, "m^2", 0.0, doc="added to a camera fix's position variance"),
    "attitude_pin_tilt_deg": Param(60.0, "deg", 0.0, 180.0,
                                   doc="past this tilt (a flip) the attitude level's angles are pinned into the "
                                       "EKF, not fused (PositionEKF.pin_attitude)"),
    "camera_delay": Param({}, table=CameraDelayParams,
                          doc="the camera delay's online estimate and correction (flight/estimation/camera_delay.py "
                              "CameraDelayParams)"),
    "ekf": Param({}, table=PositionEKFParams,
                 doc="the EKF's settings (flight/estimation/position_ekf.py PositionEKFParams)"),
}
