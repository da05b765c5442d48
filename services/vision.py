"""zenpilot-vision: vehicle pose from the camera's marker corners (20 Hz, on each frame).

Runs on every sim/camera frame: a perspective-n-point solve against the
known marker map (flight/estimation/pnp.py) gives position, attitude and their
covariance, stamped with the frame's exposure time. Degenerate or
inconsistent solutions are counted by reason (health `rejected`) and not
published. Detection (pixels from an image) is not done here: the frame
already carries marker corners, as a real detector (e.g. ArUco) would give.
"""

from __future__ import annotations

import numpy as np

import schemas
from flight.camera import Camera
from flight.estimation.pnp import MarkerMap, solve_pose
from services.params.vision import PARAMS  # every parameter: default, unit, bounds, doc
from services.runtime import Runtime, main_guard, service_parser

NAME = "vision"


class VisionLoop:
    """The vision service's logic: a pose from each camera frame's marker corners. `io` is the
    service's Runtime in flight, a fake in the unit tests; no Zenoh here."""

    def __init__(self, io):
        self.io = io
        p = self.p = io.params
        self.camera = Camera(p["camera_width_px"], p["camera_height_px"], p["camera_focal_px"])
        self.markers = MarkerMap.grid(p["marker_size_m"], p["marker_spacing_m"], p["marker_grid_half_extent_m"])
        self.frames = io.inbox(schemas.CAMERA, "sim", keep=16)
        self.out = io.publisher(schemas.VISION_POSE)
        self.last_pose = None   # the previous solution: the next solve's starting point

    def count(self, reason: str) -> None:
        rejected = self.io.rejected
        rejected[reason] = rejected.get(reason, 0) + 1

    def step(self, t: float) -> None:
        """Every frame that arrived: its pose, stamped with the frame's exposure time."""
        io, p = self.io, self.p
        for frame in self.frames.take():
            if not io.lockstep:
                io.count_run(t)  # lockstep counts the triggered run itself
            if not frame["marker_ids"]:
                self.count("pose_no_markers")
                continue
            sol = solve_pose(self.camera, self.markers, frame["marker_ids"], frame["corners_px"],
                             pixel_sigma_px=p["pixel_sigma_px"], max_reprojection_px=p["max_reprojection_px"],
                             prior=self.last_pose)
            if not sol.ok:  # counted beside the message reasons, prefixed "pose_"
                self.count("pose_" + sol.reason)
                continue
            self.last_pose = (sol.position_m, sol.quaternion_wxyz)
            cov = np.asarray(sol.covariance)
            self.out.put({"position_m": sol.position_m, "quaternion_wxyz": sol.quaternion_wxyz,
                          "position_cov_m2": cov[:3, :3].reshape(-1), "attitude_var_rad2": np.diag(cov)[3:],
                          "reprojection_rms_px": float(sol.reprojection_rms_px),
                          "markers": int(sol.points_used // 4)}, t_s=frame["header"]["t_s"])


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS)
    rt.run(VisionLoop(rt).step, triggers=("camera",))


def main(argv=None) -> None:
    args = service_parser(NAME, __doc__.splitlines()[0]).parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
