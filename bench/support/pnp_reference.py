# flight/estimation/pnp.py as of zenpilot ab1f93b, verbatim (full SVD, per-marker loops):
# the reference the solver is checked against (tests/unit/flight/estimation/test_pnp.py) and
# timed against (bench/vision.py). Not used in flight.
"""Pose of the vehicle from the pixel corners of floor markers (planar PnP).

Pure numpy: this module takes pixel corners only, so any detector (the
simulator's MarkerCamera, OpenCV's ArUco, ...) can feed it.

Conventions (see flight.camera): world ENU with the markers on the floor z = 0,
body FLU, quaternions [w, x, y, z] body->world. The camera sits at the body
origin, rotated by R_CAM_FROM_BODY, so the solved pose is the body pose.

Method:
  1. initial guess from the plane-to-image homography (normalised DLT on
     intrinsics-normalised image coordinates, decomposed into R, t and
     orthonormalised); when the homography is ill-conditioned (e.g. collinear
     points) the caller's `prior` pose is used instead, if given;
  2. Levenberg-Marquardt on the pixel reprojection error over the 6-DOF pose,
     with an analytic Jacobian. The pose is perturbed as
         position <- position + dp,   R_wb <- exp([dtheta]x) R_wb
     i.e. dtheta is a small world-frame rotation vector;
  3. covariance = sigma^2 (J^T J)^-1 at the solution, over
     [position (3), attitude error dtheta (3)], with R_true = exp([dtheta]x) R_est
     (to first order the sign convention does not change the covariance).

Rejections (ok False, `reason` set): "too_few_points" (< 4 finite corners),
"unknown_marker" (an id not in the map), "degenerate" (homography or J^T J
ill-conditioned, non-finite input), "not_converged", "reprojection" (RMS
reprojection error above the limit: the corners are inconsistent with any pose).
A rejected solution carries the last estimate if one exists (diagnostic only,
zeros / identity otherwise) and a huge covariance; nothing is ever NaN.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flight.camera import R_CAM_FROM_BODY, Camera, marker_grid

REASONS = ("too_few_points", "unknown_marker", "degenerate", "not_converged", "reprojection")

MAX_CONDITION = 1e10          # J^T J condition number above which the geometry is degenerate
HOMOGRAPHY_MIN_SV_RATIO = 1e-7  # 2nd-smallest / largest singular value of the DLT system
MAX_ITERATIONS = 50
_STEP_TOL = 1e-11             # converged when the accepted step is this small (m / rad)
_COST_RTOL = 1e-10           # ... or when an accepted step lowers the cost by less than this fraction
_MIN_DEPTH_M = 1e-3
_FLIP_CHECK_MAX_POINTS = 8  # also refine the mirrored pose for this few points
_FAILED_COVARIANCE = 1e6      # diagonal of the covariance of a rejected solution


@dataclass(frozen=True, eq=False)
class MarkerMap:
    """Known markers: ids (M,) and world corners (M, 4, 3), all on the floor z = 0."""

    ids: np.ndarray
    corners_world: np.ndarray
    _index: dict = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        ids = np.array(self.ids, dtype=np.int64).reshape(-1)
        corners = np.array(self.corners_world, dtype=np.float64)
        if corners.shape != (len(ids), 4, 3):
            raise ValueError(f"MarkerMap: corners must have shape ({len(ids)}, 4, 3), got {corners.shape}")
        if not np.all(np.isfinite(corners)) or np.any(corners[:, :, 2] != 0.0):
            raise ValueError("MarkerMap: corners must be finite and on the floor z = 0")
        if len(set(ids.tolist())) != len(ids):
            raise ValueError("MarkerMap: duplicate marker ids")
        ids.setflags(write=False)
        corners.setflags(write=False)
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "corners_world", corners)
        object.__setattr__(self, "_index", {int(i): k for k, i in enumerate(ids)})

    @classmethod
    def grid(cls, size_m: float, spacing_m: float, half_extent_m: float) -> "MarkerMap":
        ids, corners = marker_grid(size_m, spacing_m, half_extent_m)
        return cls(ids, corners)

    def __len__(self) -> int:
        return len(self.ids)

    def corners(self, marker_id) -> np.ndarray | None:
        """World corners (4, 3) of a marker (flight.camera corner order), None if unknown."""
        try:
            k = self._index.get(int(marker_id))
        except (TypeError, ValueError, OverflowError):
            return None
        if k is None or int(marker_id) != marker_id:
            return None
        return self.corners_world[k].copy()


@dataclass
class PoseSolution:
    ok: bool
    reason: str                      # "" when ok, else one of REASONS
    position_m: np.ndarray           # (3,) body origin in the world
    quaternion_wxyz: np.ndarray      # (4,) body->world, w >= 0
    covariance: np.ndarray           # (6, 6) over [position, world-frame attitude error]
    reprojection_rms_px: float       # RMS over the 2 N pixel coordinates
    points_used: int


# --------------------------------------------------------------------------- helpers

def _skew(v: np.ndarray) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _rot_exp(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    k = _skew(w)
    if th < 1e-8:
        return np.eye(3) + k + 0.5 * k @ k
    return np.eye(3) + (np.sin(th) / th) * k + ((1.0 - np.cos(th)) / th ** 2) * k @ k


def _orthonormalise(m: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _quat_from_rotation(r: np.ndarray) -> np.ndarray:
    """Unit quaternion [w, x, y, z] (w >= 0) of a rotation matrix (Shepperd)."""
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    cands = np.array([tr, r[0, 0], r[1, 1], r[2, 2]])
    k = int(np.argmax(cands))
    if k == 0:
        s = 2.0 * np.sqrt(max(1.0 + tr, 0.0))
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif k == 1:
        s = 2.0 * np.sqrt(max(1.0 + r[0, 0] - r[1, 1] - r[2, 2], 0.0))
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(max(1.0 - r[0, 0] + r[1, 1] - r[2, 2], 0.0))
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(max(1.0 - r[0, 0] - r[1, 1] + r[2, 2], 0.0))
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def _quat_to_rotation(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _hartley(pts: np.ndarray) -> np.ndarray:
    """3x3 similarity moving 2-D points to centroid 0, mean distance sqrt(2)."""
    c = pts.mean(axis=0)
    d = np.sqrt(((pts - c) ** 2).sum(axis=1)).mean()
    s = np.sqrt(2.0) / d if d > 1e-12 else 1.0
    return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])


def _homography_pose(xy: np.ndarray, mn: np.ndarray):
    """Pose (R_wb, position) from plane points xy (N,2) and normalised image points mn (N,2).

    Returns None when the homography is ill-conditioned.
    """
    tw, tm = _hartley(xy), _hartley(mn)
    a = xy @ tw[:2, :2].T + tw[:2, 2]
    b = mn @ tm[:2, :2].T + tm[:2, 2]
    n = len(xy)
    ah = np.column_stack([a, np.ones(n)])
    rows = np.zeros((2 * n, 9))
    rows[0::2, 3:6] = -ah
    rows[0::2, 6:9] = b[:, 1:2] * ah
    rows[1::2, 0:3] = ah
    rows[1::2, 6:9] = -b[:, 0:1] * ah
    _, s, vt = np.linalg.svd(rows)
    if len(s) < 8 or s[0] <= 0 or s[7] / s[0] < HOMOGRAPHY_MIN_SV_RATIO:
        return None
    h = np.linalg.solve(tm, vt[-1].reshape(3, 3)) @ tw      # ~ [r1 r2 t] of p_cam = R_cw X + t
    n1, n2 = np.linalg.norm(h[:, 0]), np.linalg.norm(h[:, 1])
    if not (n1 > 0 and n2 > 0 and np.isfinite(n1 + n2)):
        return None
    h = h * (2.0 / (n1 + n2))
    depth = np.column_stack([xy, np.ones(n)]) @ h[2]
    if depth.mean() < 0:
        h = -h
    r_cw = _orthonormalise(np.column_stack([h[:, 0], h[:, 1], np.cross(h[:, 0], h[:, 1])]))
    t = h[:, 2]
    r_wb = r_cw.T @ R_CAM_FROM_BODY
    position = -r_cw.T @ t
    return r_wb, position


class _Problem:
    def __init__(self, camera: Camera, pts: np.ndarray, pix: np.ndarray):
        self.f = float(camera.focal_px)
        self.c = np.array(camera.principal_point_px, dtype=np.float64)
        self.pts = pts
        self.pix = pix

    def residuals(self, r_wb, p):
        """(2N,) residuals [u0-uo0, v0-vo0, ...] or None if a point is not in front."""
        r_cw = R_CAM_FROM_BODY @ r_wb.T
        pc = (self.pts - p) @ r_cw.T
        z = pc[:, 2]
        if not np.all(z > _MIN_DEPTH_M):
            return None, None, None
        uv = self.f * pc[:, :2] / z[:, None] + self.c
        return (uv - self.pix).reshape(-1), pc, r_cw

    def jacobian(self, r_wb, p, pc, r_cw):
        """(2N, 6) d residual / d [dp, dtheta]."""
        w = self.pts - p
        z = pc[:, 2]
        n = len(z)
        dproj = np.zeros((n, 2, 3))
        dproj[:, 0, 0] = self.f / z
        dproj[:, 1, 1] = self.f / z
        dproj[:, :, 2] = -self.f * pc[:, :2] / (z * z)[:, None]
        # d pc / d p = -R_cw ;  d pc / d theta = R_cw [w]x
        j_p = -np.einsum("nij,jk->nik", dproj, r_cw)
        a = np.einsum("nij,jk->nik", dproj, r_cw)                  # (n, 2, 3)
        # row a_r @ [w]x = a_r x w
        j_t = np.empty_like(a)
        wx, wy, wz = w[:, None, 0], w[:, None, 1], w[:, None, 2]
        j_t[:, :, 0] = a[:, :, 1] * wz - a[:, :, 2] * wy
        j_t[:, :, 1] = a[:, :, 2] * wx - a[:, :, 0] * wz
        j_t[:, :, 2] = a[:, :, 0] * wy - a[:, :, 1] * wx
        return np.concatenate([j_p, j_t], axis=2).reshape(2 * n, 6)


def _refine(prob: _Problem, r_wb, p):
    """Levenberg-Marquardt. Returns (r_wb, p, converged)."""
    res, pc, r_cw = prob.residuals(r_wb, p)
    if res is None:
        return r_wb, p, False
    cost = float(res @ res)
    j = prob.jacobian(r_wb, p, pc, r_cw)
    lam = 1e-6                    # relative (Marquardt) damping of diag(J^T J)
    for _ in range(MAX_ITERATIONS):
        jtj = j.T @ j
        g = j.T @ res
        d = np.diag(jtj).copy()
        dmax = float(np.max(d))
        while True:
            a = jtj + np.diag(lam * d + 1e-15 * dmax)
            try:
                step = -np.linalg.solve(a, g)
            except np.linalg.LinAlgError:
                return r_wb, p, False
            if not np.all(np.isfinite(step)):
                return r_wb, p, False
            small = float(np.max(np.abs(step))) < _STEP_TOL
            r_new = _rot_exp(step[3:]) @ r_wb
            p_new = p + step[:3]
            res_new, pc_new, r_cw_new = prob.residuals(r_new, p_new)
            cost_new = float(res_new @ res_new) if res_new is not None else np.inf
            if cost_new <= cost:
                flat = cost - cost_new <= _COST_RTOL * cost
                r_wb, p, res, pc, r_cw = r_new, p_new, res_new, pc_new, r_cw_new
                cost = cost_new
                if small or flat:
                    return _orthonormalise(r_wb), p, True
                j = prob.jacobian(r_wb, p, pc, r_cw)
                lam = max(lam / 5.0, 1e-12)
                break
            if small:                     # cannot improve: at the numerical minimum
                return r_wb, p, True
            lam *= 8.0
            if lam > 1e12:
                return r_wb, p, False
    return r_wb, p, False


def _flipped(prob: _Problem, r_wb, p):
    """The other planar-pose candidate: the plane normal mirrored about the ray to the centroid.

    Few, close-together points (one marker) see the plane nearly orthographically, and then
    a pose tilted the other way about the line of sight fits almost as well (the classic
    two-fold planar ambiguity). Returns None when the two coincide.
    """
    r_cw = R_CAM_FROM_BODY @ r_wb.T
    centroid = prob.pts.mean(axis=0)
    c = r_cw @ (centroid - p)
    v = c / np.linalg.norm(c)
    nrm = r_cw[:, 2]
    axis = np.cross(nrm, v)
    s = float(np.linalg.norm(axis))
    if s < 1e-9:
        return None
    angle = 2.0 * np.arctan2(s, float(nrm @ v))
    r_cw2 = _rot_exp(axis / s * angle) @ r_cw
    r_wb2 = r_cw2.T @ R_CAM_FROM_BODY
    p2 = centroid - r_cw2.T @ c
    return r_wb2, p2


def _fail(reason, n, r_wb=None, p=None, rms=0.0) -> PoseSolution:
    ok_pose = r_wb is not None and np.all(np.isfinite(r_wb)) and np.all(np.isfinite(p))
    return PoseSolution(
        ok=False, reason=reason,
        position_m=np.array(p, dtype=np.float64) if ok_pose else np.zeros(3),
        quaternion_wxyz=_quat_from_rotation(r_wb) if ok_pose else np.array([1.0, 0.0, 0.0, 0.0]),
        covariance=_FAILED_COVARIANCE * np.eye(6),
        reprojection_rms_px=float(rms) if np.isfinite(rms) else 0.0,
        points_used=int(n))


# --------------------------------------------------------------------------- solver

def solve_pose(camera: Camera, marker_map: MarkerMap, marker_ids, corners_px,
               pixel_sigma_px: float = 0.5, max_reprojection_px: float = 3.0,
               prior=None) -> PoseSolution:
    """Body pose from detected marker corners.

    marker_ids: M ids; corners_px: 8 M numbers (u0, v0, ..., u3, v3 per marker, the
    MarkerCamera layout) or an (M, 4, 2) array. A corner with a non-finite pixel is
    left out (a detector may lose single corners). prior: optional (position (3,),
    quaternion wxyz (4,)) used as the start when the homography is ill-conditioned.
    Raises ValueError only for a corners_px whose size does not match marker_ids.
    """
    ids = list(np.asarray(marker_ids).reshape(-1)) if marker_ids is not None else []
    pix = np.asarray(corners_px if corners_px is not None else [], dtype=np.float64).reshape(-1)
    if pix.size != 8 * len(ids):
        raise ValueError(f"solve_pose: {len(ids)} markers need {8 * len(ids)} corner numbers, got {pix.size}")
    pix = pix.reshape(-1, 2)
    world = []
    for marker_id in ids:
        c = marker_map.corners(marker_id)
        if c is None:
            return _fail("unknown_marker", 0)
        world.append(c)
    if not world:
        return _fail("too_few_points", 0)
    pts = np.concatenate(world, axis=0)
    keep = np.all(np.isfinite(pix), axis=1)
    pts, pix = pts[keep], pix[keep]
    n = len(pts)
    if n < 4:
        return _fail("too_few_points", n)

    f = float(camera.focal_px)
    cxy = np.array(camera.principal_point_px, dtype=np.float64)
    start = _homography_pose(pts[:, :2], (pix - cxy) / f)
    if start is None and prior is not None:
        try:
            p0 = np.asarray(prior[0], dtype=np.float64).reshape(3)
            q0 = np.asarray(prior[1], dtype=np.float64).reshape(4)
            if np.all(np.isfinite(p0)) and np.all(np.isfinite(q0)) and np.linalg.norm(q0) > 0:
                start = (_quat_to_rotation(q0), p0)
        except (TypeError, ValueError, IndexError):
            start = None
    if start is None:
        return _fail("degenerate", n)

    prob = _Problem(camera, pts, pix)
    r_wb, p, converged = _refine(prob, *start)
    if converged and n <= _FLIP_CHECK_MAX_POINTS:
        alt = _flipped(prob, r_wb, p)
        if alt is not None:
            r2, p2, conv2 = _refine(prob, *alt)
            res1 = prob.residuals(r_wb, p)[0]
            res2 = prob.residuals(r2, p2)[0]
            if conv2 and res1 is not None and res2 is not None and res2 @ res2 < res1 @ res1:
                r_wb, p = r2, p2
    res, pc, r_cw = prob.residuals(r_wb, p)
    if res is None or not converged or not np.all(np.isfinite(res)):
        return _fail("not_converged", n, r_wb, p)
    rms = float(np.sqrt(np.mean(res * res)))
    j = prob.jacobian(r_wb, p, pc, r_cw)
    jtj = j.T @ j
    cond = np.linalg.cond(jtj)
    if not np.isfinite(cond) or cond > MAX_CONDITION:
        return _fail("degenerate", n, r_wb, p, rms)
    if rms > max_reprojection_px:
        return _fail("reprojection", n, r_wb, p, rms)
    cov = float(pixel_sigma_px) ** 2 * np.linalg.inv(jtj)
    cov = 0.5 * (cov + cov.T)
    if not np.all(np.isfinite(cov)):
        return _fail("degenerate", n, r_wb, p, rms)
    return PoseSolution(ok=True, reason="", position_m=np.array(p, dtype=np.float64),
                        quaternion_wxyz=_quat_from_rotation(r_wb), covariance=cov,
                        reprojection_rms_px=rms, points_used=n)
