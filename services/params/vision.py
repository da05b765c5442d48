"""The vision service's parameters (services/vision.py): a real deployment sets the camera and
the marker map from its calibration. The image mode (frames from sim/@image) reads the camera
from `camera_intrinsics`; the corner mode (sim/camera) from camera_*."""

from __future__ import annotations

from flight.camera import DEFAULT_CAMERA, DEFAULT_MARKERS, DEFAULT_PIXEL_NOISE_PX
from services.params import Param

PARAMS = {
    "camera_width_px": Param(DEFAULT_CAMERA.width_px, "px", 1, doc="image width"),
    "camera_height_px": Param(DEFAULT_CAMERA.height_px, "px", 1, doc="image height"),
    "camera_focal_px": Param(DEFAULT_CAMERA.focal_px, "px", 0.0, min_exclusive=True, doc="focal length"),
    "marker_size_m": Param(DEFAULT_MARKERS.size_m, "m", 0.0, min_exclusive=True, doc="a marker's side"),
    "marker_spacing_m": Param(DEFAULT_MARKERS.spacing_m, "m", 0.0, min_exclusive=True,
                              doc="distance between marker centres on the grid"),
    "marker_grid_half_extent_m": Param(DEFAULT_MARKERS.half_extent_m, "m", 0.0,
                                       doc="the marker grid spans this far from the origin in x and y"),
    "pixel_sigma_px": Param(DEFAULT_PIXEL_NOISE_PX, "px", 0.0, min_exclusive=True,
                            doc="the corners' pixel noise (std) the pose covariance assumes"),
    "camera_intrinsics": Param("", doc="image mode: the intrinsics file (`zenpilot calibrate-camera` writes it; "
                               "relative to the stack file); \"\": camera_* with flight.camera.DEFAULT_DISTORTION, "
                               "as the simulator's default"),
    "image_pixel_sigma_px": Param(0.3, "px", 0.0, min_exclusive=True,
                                  doc="image mode: the detected corners' noise (std) the pose covariance assumes"),
    "crop_above_markers": Param(60, "", 0, doc="image mode: when the previous frame had more markers in view "
                                "than this, look in the image's central crop_window only (less detection time for "
                                "enough markers); 0: always the whole image"),
    "crop_window": Param(0.67, "", 0.2, 1.0, doc="image mode: the central part searched then, as a fraction of the "
                         "image's width and height"),
    "crop_min_markers": Param(12, "", 1, doc="image mode: a search of the central part that finds fewer markers "
                              "than this is done again on the whole image"),
    "pnp": Param("hand", choices=("hand", "opencv"),
                 doc="the pose solver: \"hand\" (flight/estimation/pnp.py) or \"opencv\" (cv2.solvePnP, IPPE "
                     "then Levenberg-Marquardt; docs/vision.md compares them)"),
    "max_reprojection_px": Param(3.0, "px", 0.0, min_exclusive=True,
                                 doc="a pose whose RMS reprojection error is above this is refused"),
}
