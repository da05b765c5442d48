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


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS)
    p = rt.params
    camera = Camera(p["camera_width_px"], p["camera_height_px"], p["camera_focal_px"])
    markers = MarkerMap.grid(p["marker_size_m"], p["marker_spacing_m"], p["marker_grid_half_extent_m"])
    frames = rt.inbox(schemas.CAMERA, "sim", keep=16)
    out = rt.publisher(schemas.VISION_POSE)
    last = {"pose": None}

    def step(t: float) -> None:
        for frame in frames.take():
            if not rt.lockstep:
                rt.count_run(t)  # lockstep counts the triggered run itself
            if not frame["marker_ids"]:
                rt.rejected["pose_no_markers"] = rt.rejected.get("pose_no_markers", 0) + 1
                continue
            sol = solve_pose(camera, markers, frame["marker_ids"], frame["corners_px"],
                             pixel_sigma_px=p["pixel_sigma_px"], max_reprojection_px=p["max_reprojection_px"],
                             prior=last["pose"])
            if not sol.ok:  # counted beside the message reasons, prefixed "pose_"
                rt.rejected["pose_" + sol.reason] = rt.rejected.get("pose_" + sol.reason, 0) + 1
                continue
            last["pose"] = (sol.position_m, sol.quaternion_wxyz)
            cov = np.asarray(sol.covariance)
            out.put({"position_m": sol.position_m, "quaternion_wxyz": sol.quaternion_wxyz,
                     "position_cov_m2": cov[:3, :3].reshape(-1), "attitude_var_rad2": np.diag(cov)[3:],
                     "reprojection_rms_px": float(sol.reprojection_rms_px),
                     "markers": int(sol.points_used // 4)}, t_s=frame["header"]["t_s"])

    rt.run(step, triggers=("camera",))


def main(argv=None) -> None:
    args = service_parser(NAME, __doc__.splitlines()[0]).parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
