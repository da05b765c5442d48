"""zenpilot-vision: vehicle pose from the camera's markers (20 Hz, on each frame).

Runs on every camera frame. Image mode (sim/@image, mono8 frames): OpenCV's ArUco
detector finds the markers, their corners are undistorted with the camera's intrinsics
(flight/estimation/markers.py). Corner mode (sim/camera): the frame already carries the
corners, as a detector would give them. Either way a perspective-n-point solve against
the known marker map (flight/estimation/pnp.py) gives position, attitude and their
covariance, stamped with the frame's exposure time. Degenerate or inconsistent solutions
are counted by reason (health `rejected`) and not published; so are images whose size is
not the intrinsics'. Time per frame: health step_s / cycles in real time, and a line in
the log at exit (detect and solve, median and worst) in both modes.
"""

from __future__ import annotations

import time

import numpy as np

import schemas
from flight.camera import Camera, Intrinsics, load_intrinsics
from flight.estimation.pnp import MarkerMap, solve_pose
from services.params.vision import PARAMS  # every parameter: default, unit, bounds, doc
from services.runtime import Runtime, main_guard, service_parser

NAME = "vision"


class VisionLoop:
    """The vision service's logic: a pose from each camera frame's markers. `io` is the
    service's Runtime in flight, a fake in the unit tests; no Zenoh here. `intrinsics`: the
    image mode's camera (None: from the `camera_intrinsics` parameter, read on the first image)."""

    def __init__(self, io, intrinsics: Intrinsics | None = None):
        self.io = io
        p = self.p = io.params
        self.camera = Camera(p["camera_width_px"], p["camera_height_px"], p["camera_focal_px"])
        self.markers = MarkerMap.grid(p["marker_size_m"], p["marker_spacing_m"], p["marker_grid_half_extent_m"])
        self.frames = io.inbox(schemas.CAMERA, "sim", keep=16)
        # the newest two frames: a detector that falls behind in real time skips, never queues
        self.images = io.inbox(schemas.CAMERA_IMAGE, "sim", keep=2)
        self.out = io.publisher(schemas.VISION_POSE)
        self.last_pose = None   # the previous solution: the next solve's starting point
        self.intrinsics = intrinsics
        self.detector = None    # made on the first image (cv2 loaded only in the image mode)
        # per image: wall ms (detection, and detection + pose), and the thread's CPU ms: what a
        # core would spend on it alone (the wall time counts the other processes' turns)
        self.frame_ms: list[float] = []
        self.frame_cpu_ms: list[float] = []
        self.detect_ms: list[float] = []
        self.images_seen = self.images_detected = 0
        self.in_view = 0.0      # markers about in the whole of the previous image

    def count(self, reason: str) -> None:
        rejected = self.io.rejected
        rejected[reason] = rejected.get(reason, 0) + 1

    def step(self, t: float) -> None:
        """Every frame that arrived: its pose, stamped with the frame's exposure time."""
        io = self.io
        for frame in self.frames.take():
            if not io.lockstep:
                io.count_run(t)  # lockstep counts the triggered run itself
            if not frame["marker_ids"]:
                self.count("pose_no_markers")
                continue
            self.solve(frame["marker_ids"], frame["corners_px"], frame["header"]["t_s"], self.p["pixel_sigma_px"])
        for image in self.images.take():
            if not io.lockstep:
                io.count_run(t)
            self.image(image)

    def image(self, msg: dict) -> None:
        t0, c0 = time.perf_counter(), time.thread_time()
        if self.detector is None:
            self._make_detector()
        intr = self.intrinsics
        if (msg["width_px"], msg["height_px"]) != (intr.width_px, intr.height_px):
            # a frame of another size: the intrinsics do not hold for it (said once, counted always)
            if "image_wrong_size" not in self.io.rejected:
                self.io.problem(f"dropped a {msg['width_px']} x {msg['height_px']} image: the camera intrinsics "
                                f"are for {intr.width_px} x {intr.height_px}")
            self.count("image_wrong_size")
            return
        self.images_seen += 1
        img = np.frombuffer(msg["pixels"], dtype=np.uint8).reshape(msg["height_px"], msg["width_px"])
        # many markers in view (a high floor): the image's central part holds enough of them for less
        # time (bench/vision.py); too few there, the whole image after all
        window = self.p["crop_window"] if 0 < self.p["crop_above_markers"] < self.in_view else 1.0
        ids, corners = self.detector.detect(img, window=window)
        if window < 1.0 and len(ids) < self.p["crop_min_markers"]:
            ids, corners = self.detector.detect(img)
            window = 1.0
        self.in_view = len(ids) / (window * window)   # about as many in the whole image
        t1 = time.perf_counter()
        self.detect_ms.append(1e3 * (t1 - t0))
        if not ids:
            self.count("pose_no_markers")
        else:
            self.images_detected += 1
            self.solve(ids, corners, msg["header"]["t_s"], self.p["image_pixel_sigma_px"],
                       camera=self.detector.camera)
        self.frame_ms.append(1e3 * (time.perf_counter() - t0))
        self.frame_cpu_ms.append(1e3 * (time.thread_time() - c0))

    def _make_detector(self) -> None:
        import cv2

        from flight.estimation.markers import MarkerDetector

        # one thread, as the services' BLAS: the detector's parallel loops would take the core the
        # control loops need, for the same CPU time (bench/vision.py)
        cv2.setNumThreads(1)

        if self.intrinsics is None:
            self.intrinsics = (load_intrinsics(self.p["camera_intrinsics"]) if self.p["camera_intrinsics"]
                               else Intrinsics.of(self.camera))
        self.detector = MarkerDetector(self.intrinsics, len(self.markers))

    def solve(self, ids, corners, t_s: float, sigma_px: float, camera: Camera | None = None) -> None:
        sol = solve_pose(camera or self.camera, self.markers, ids, corners, pixel_sigma_px=sigma_px,
                         max_reprojection_px=self.p["max_reprojection_px"], prior=self.last_pose,
                         method=self.p["pnp"])
        if not sol.ok:  # counted beside the message reasons, prefixed "pose_"
            self.count("pose_" + sol.reason)
            return
        self.last_pose = (sol.position_m, sol.quaternion_wxyz)
        cov = np.asarray(sol.covariance)
        self.out.put({"position_m": sol.position_m, "quaternion_wxyz": sol.quaternion_wxyz,
                      "position_cov_m2": cov[:3, :3].reshape(-1), "attitude_var_rad2": np.diag(cov)[3:],
                      "reprojection_rms_px": float(sol.reprojection_rms_px),
                      "markers": int(sol.points_used // 4)}, t_s=t_s)

    def summary(self) -> str:
        """The image mode's figures for the log at exit ('' in the corner mode)."""
        if not self.images_seen:
            return ""
        ms, det, cpu = np.array(self.frame_ms), np.array(self.detect_ms), np.array(self.frame_cpu_ms)
        return (f"zenpilot-vision: {self.images_seen} images, markers found in {self.images_detected} "
                f"({100.0 * self.images_detected / self.images_seen:.1f} %); CPU ms per image: median "
                f"{np.median(cpu):.2f}, p95 {np.percentile(cpu, 95):.2f}, max {cpu.max():.2f}; wall ms per image: "
                f"median {np.median(ms):.2f}, p95 {np.percentile(ms, 95):.2f}, max {ms.max():.2f} "
                f"(detection median {np.median(det):.2f}, pose median {np.median(ms - det):.2f})")


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS)
    if rt.params["camera_intrinsics"]:   # relative to the stack file; a bad file refused before flying
        from flight.camera import IntrinsicsError
        from services.stack import intrinsics_path
        path = intrinsics_path(rt.stack.path, rt.params["camera_intrinsics"])
        try:
            intrinsics = load_intrinsics(path)
        except IntrinsicsError as exc:
            rt.close()
            raise ValueError(f"{rt.stack.path}: [services.vision.params] camera_intrinsics: {exc}") from None
    else:
        intrinsics = None
    loop = VisionLoop(rt, intrinsics)
    try:
        rt.run(loop.step, triggers=("camera", "camera_image"))
    finally:
        if loop.summary():
            print(loop.summary(), flush=True)


def main(argv=None) -> None:
    args = service_parser(NAME, __doc__.splitlines()[0]).parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
