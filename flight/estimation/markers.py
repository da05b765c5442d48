"""Marker corners from a camera image: OpenCV's ArUco detector, then the lens undone.

An image (mono8, H x W) in; the ids of the markers found and their four corners out, in
the pixels of the undistorted pinhole `Camera` that flight/estimation/pnp.py solves with
(corner order of flight.camera.marker_grid: ArUco's own). Sub-pixel corner refinement is
on (CORNER_REFINE_SUBPIX: ~0.13 px RMS against the true corners on a sharp render, 0.5 px
without). Ids beyond the layout cannot come out: the dictionary is cut to the layout's ids
(flight.camera.aruco_dictionary). Pure: no I/O; cv2 and numpy.
"""
from __future__ import annotations

import cv2
import numpy as np

from flight.camera import UNDISTORT_CRITERIA, Camera, Intrinsics, aruco_dictionary


ADAPTIVE_WINDOW_MAX_PX = 13


def pinhole_of(intr: Intrinsics) -> Camera:
    """The undistorted camera the corners are given in: the intrinsics' size, the mean focal
    length, the principal point at the image centre (flight.camera.Camera's)."""
    return Camera(intr.width_px, intr.height_px, 0.5 * (intr.fx_px + intr.fy_px))


class MarkerDetector:
    def __init__(self, intrinsics: Intrinsics, n_markers: int):
        self.intr = intrinsics
        self.camera = cam = pinhole_of(intrinsics)
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        # thresholding windows of 3 and 13 px (OpenCV's default adds 23): 30 % less time for the
        # same markers, sharp or blurred at hover; at 5 m under the flip's blur it finds 3/4 of them
        params.adaptiveThreshWinSizeMax = ADAPTIVE_WINDOW_MAX_PX
        self.detector = cv2.aruco.ArucoDetector(aruco_dictionary(n_markers), params)
        cx, cy = cam.principal_point_px
        self._p = np.array([[cam.focal_px, 0.0, cx], [0.0, cam.focal_px, cy], [0.0, 0.0, 1.0]])
        self._k = intrinsics.matrix
        self._d = intrinsics.dist_coeffs

    def detect(self, image: np.ndarray, window: float = 1.0) -> tuple[list[int], np.ndarray]:
        """(ids, corners (M, 4, 2) in the pinhole camera's pixels) of the markers found in `image`;
        `window` < 1: only in the central part of that fraction of its width and height."""
        x0 = y0 = 0
        if window < 1.0:
            h, w = image.shape
            cw, ch = max(1, int(round(w * window))), max(1, int(round(h * window)))
            x0, y0 = (w - cw) // 2, (h - ch) // 2
            image = image[y0:y0 + ch, x0:x0 + cw]
        corners, ids, _ = self.detector.detectMarkers(image)
        if ids is None or not len(ids):
            return [], np.zeros((0, 4, 2))
        pts = np.concatenate(corners, axis=0).reshape(-1, 1, 2).astype(np.float64)
        if x0 or y0:
            pts += (x0, y0)
        und = cv2.undistortPointsIter(pts, self._k, self._d, None, self._p, UNDISTORT_CRITERIA)
        return ids.reshape(-1).tolist(), und.reshape(-1, 4, 2)
