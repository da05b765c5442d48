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

Cost (bench/vision.py): ~0.3-0.5 ms a frame whether 5 or 200 markers are seen. Each
step over the points is one numpy operation over all corners (a frame at the flip's
5 m sees ~180 markers, ~700 corners), nothing per marker or per point in Python. The
DLT null vector comes from the system's 9 x 9 Gram matrix (24 moments), with the thin
SVD deciding near-degenerate cases (a full SVD would also build a 2N x 2N U: 16 MB at
700 corners). The Gauss-Newton normal equations are formed in the camera frame,
J^T J = B^T (K^T K) B with B = diag(R_cw, R_cw), from the normalised image coordinates,
in a buffer made once per frame. bench/support/pnp_reference.py is the same algorithm
written plainly (full SVD, per-marker loops); tests/unit/flight/estimation/test_pnp.py
holds the two to the same poses and decisions.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from flight.camera import R_CAM_FROM_BODY, Camera, marker_grid
from flight.quat import quat_from_rotation, quat_to_rotation

METHODS = ("hand", "opencv")
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
    _sorted_ids: np.ndarray = field(init=False, repr=False, compare=False)
    _sorted_rows: np.ndarray = field(init=False, repr=False, compare=False)

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
        order = np.argsort(ids, kind="stable")
        object.__setattr__(self, "_sorted_ids", ids[order])
        object.__setattr__(self, "_sorted_rows", order)

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

    def _rows(self, ids: np.ndarray) -> np.ndarray | None:
        """Rows of corners_world for an integer id array, None if any id is unknown."""
        if len(self._sorted_ids) == 0:
            return None if len(ids) else np.zeros(0, dtype=np.int64)
        pos = np.searchsorted(self._sorted_ids, ids)
        np.minimum(pos, len(self._sorted_ids) - 1, out=pos)
        if not np.array_equal(self._sorted_ids[pos], ids):
            return None
        return self._sorted_rows[pos]


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

def _rot_exp(w) -> np.ndarray:
    """exp([w]x) = I + a [w]x + b [w]x^2 (Rodrigues), on floats: [w]x^2 = w w^T - |w|^2 I."""
    x, y, z = float(w[0]), float(w[1]), float(w[2])
    th2 = x * x + y * y + z * z
    th = math.sqrt(th2)
    if th < 1e-8:
        a, b = 1.0, 0.5
    else:
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    bxy, bxz, byz = b * x * y, b * x * z, b * y * z
    return np.array([
        [1.0 - b * (y * y + z * z), bxy - a * z, bxz + a * y],
        [bxy + a * z, 1.0 - b * (x * x + z * z), byz - a * x],
        [bxz - a * y, byz + a * x, 1.0 - b * (x * x + y * y)],
    ])


def _orthonormalise(m: np.ndarray) -> np.ndarray:
    """The rotation nearest to m: U diag(1, 1, sign det(U V^T)) V^T."""
    u, _, vt = np.linalg.svd(m)
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, 2] = -u[:, 2]
        r = u @ vt
    return r


def _hartley(pts: np.ndarray) -> tuple[float, float, float]:
    """(s, cx, cy) of the similarity s (p - c) moving 2-D points (2, N) to centroid 0, mean
    distance sqrt(2)."""
    n = pts.shape[1]
    cx, cy = (pts.sum(axis=1) / n).tolist()
    dx, dy = pts[0] - cx, pts[1] - cy
    d = float(np.sqrt(dx * dx + dy * dy).sum()) / n
    s = math.sqrt(2.0) / d if d > 1e-12 else 1.0
    return s, cx, cy


def _similarity(s: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[s, 0.0, -s * cx], [0.0, s, -s * cy], [0.0, 0.0, 1.0]])


def _dlt_gram_index():
    """(9, 9) index into [24 moments, 0] and sign making the DLT system's Gram matrix.

    The DLT rows of a point are [0, -a, b1 a] and [a, 0, -b0 a] (a = (x, y, 1) on the plane,
    (b0, b1) in the image), so rows^T rows = [[S, 0, -S0], [0, S, -S1], [-S0, -S1, Sbb]] with
    S, S0, S1, Sbb the sums of a a^T weighted by 1, b0, b1, b0^2 + b1^2.
    """
    sym = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])     # a a^T from [x^2, x y, x, y^2, y, 1]
    idx = np.full((9, 9), 24)
    sign = np.zeros((9, 9))
    for (bi, bj), (w, s) in {(0, 0): (0, 1.0), (1, 1): (0, 1.0), (0, 2): (1, -1.0), (2, 0): (1, -1.0),
                             (1, 2): (2, -1.0), (2, 1): (2, -1.0), (2, 2): (3, 1.0)}.items():
        idx[3 * bi:3 * bi + 3, 3 * bj:3 * bj + 3] = 6 * w + sym
        sign[3 * bi:3 * bi + 3, 3 * bj:3 * bj + 3] = s
    return idx, sign


_GRAM_INDEX, _GRAM_SIGN = _dlt_gram_index()
# Below this s_7 / s_0 (of the Gram matrix's eigenvalues: accurate to ~1e-8 there) the thin SVD
# of the DLT system decides, so every accept / reject near HOMOGRAPHY_MIN_SV_RATIO is the SVD's.
_GRAM_MIN_SV_RATIO = 1e-4


def _homography_pose(xy: np.ndarray, mn: np.ndarray):
    """Pose (R_wb, position) from plane points xy (N,2) and normalised image points mn (N,2).

    Returns None when the homography is ill-conditioned.
    """
    xy_t, mn_t = np.ascontiguousarray(xy.T), np.ascontiguousarray(mn.T)    # (2, N)
    (sw, xw, yw), (sm, xm, ym) = _hartley(xy_t), _hartley(mn_t)
    tw, tm = _similarity(sw, xw, yw), _similarity(sm, xm, ym)
    ax, ay = sw * xy_t[0] - sw * xw, sw * xy_t[1] - sw * yw          # normalised plane points
    b0, b1 = sm * mn_t[0] - sm * xm, sm * mn_t[1] - sm * ym          # normalised image points
    n = len(xy)
    h = None
    if 2 * n >= 10:
        # null vector of the 2N x 9 DLT system from its 9 x 9 Gram matrix, built from 24
        # moments in one (4, N) x (N, 6) product: no 2N x 9 system, no SVD of it
        q = np.empty((6, n))
        np.multiply(ax, ax, out=q[0])
        np.multiply(ax, ay, out=q[1])
        q[2] = ax
        np.multiply(ay, ay, out=q[3])
        q[4] = ay
        q[5] = 1.0
        w = np.empty((4, n))
        w[0] = 1.0
        w[1] = b0
        w[2] = b1
        np.multiply(b0, b0, out=w[3])
        w[3] += b1 * b1
        moments = np.empty(25)
        moments[:24] = (w @ q.T).reshape(-1)
        moments[24] = 0.0
        ev, vec = np.linalg.eigh(moments[_GRAM_INDEX] * _GRAM_SIGN)
        if ev[8] > 0 and ev[1] > 0 and ev[1] / ev[8] >= _GRAM_MIN_SV_RATIO ** 2:
            h = vec[:, 0]
    if h is None:
        ah = np.column_stack([ax, ay, np.ones(n)])
        rows = np.zeros((2 * n, 9))
        rows[0::2, 3:6] = -ah
        rows[0::2, 6:9] = b1[:, None] * ah
        rows[1::2, 0:3] = ah
        rows[1::2, 6:9] = -b0[:, None] * ah
        # only s and the last row of V^T are needed: the thin SVD (no 2N x 2N U) gives the
        # same ones; with fewer than 9 rows (one marker) the null vector is only in the full V^T
        _, s, vt = np.linalg.svd(rows, full_matrices=2 * n < 9)
        if len(s) < 8 or s[0] <= 0 or s[7] / s[0] < HOMOGRAPHY_MIN_SV_RATIO:
            return None
        h = vt[-1]
    h = np.linalg.solve(tm, h.reshape(3, 3)) @ tw      # ~ [r1 r2 t] of p_cam = R_cw X + t
    n1, n2 = np.linalg.norm(h[:, 0]), np.linalg.norm(h[:, 1])
    if not (n1 > 0 and n2 > 0 and np.isfinite(n1 + n2)):
        return None
    h = h * (2.0 / (n1 + n2))
    depth = xy @ h[2, :2] + h[2, 2]
    if depth.mean() < 0:
        h = -h
    (h00, h01, _), (h10, h11, _), (h20, h21, _) = h.tolist()
    r_cw = _orthonormalise(np.array([[h00, h01, h10 * h21 - h20 * h11],     # [h1, h2, h1 x h2]
                                     [h10, h11, h20 * h01 - h00 * h21],
                                     [h20, h21, h00 * h11 - h10 * h01]]))
    t = h[:, 2]
    r_wb = r_cw.T @ R_CAM_FROM_BODY
    position = -r_cw.T @ t
    return r_wb, position


class _Problem:
    """The reprojection problem of one frame, laid out by coordinate: (3, N) points, (2, N)
    pixels, residuals [u_0 .. u_N-1, v_0 .. v_N-1]. One work buffer for the Jacobian, made
    once per frame and reused by every iteration."""

    def __init__(self, camera: Camera, pts: np.ndarray, pix: np.ndarray):
        self.f = float(camera.focal_px)
        self.c = np.array(camera.principal_point_px, dtype=np.float64)
        self.pts = pts
        self.pix = pix
        self.pts_t = np.ascontiguousarray(pts.T)                        # (3, N)
        self.pix_t = np.ascontiguousarray((pix - self.c).T)             # (2, N), from the centre
        n = len(pts)
        self._k = np.empty((6, 2, n))   # camera-frame Jacobian / f, transposed
        self._b = np.zeros((6, 6))

    def residuals(self, r_wb, p):
        """((2N,) residuals, (2, N) normalised image coordinates, (N,) 1/depth, R_cw), or None
        if a point is not in front."""
        r_cw = R_CAM_FROM_BODY @ r_wb.T
        pc = r_cw @ self.pts_t
        pc -= (r_cw @ p)[:, None]
        z = pc[2]
        if not z.min() > _MIN_DEPTH_M:          # also False for NaN
            return None
        iz = 1.0 / z
        nrm = pc[:2]
        nrm *= iz
        res = self.f * nrm
        res -= self.pix_t
        return res.reshape(-1), nrm, iz, r_cw

    def normal_equations(self, ev):
        """J^T J (6, 6) and J^T r (6,) over [dp, dtheta], J = d residual / d [dp, dtheta].

        With p_c = R_cw (X - p): d p_c / d p = -R_cw and d p_c / d theta = R_cw [X - p]x =
        [p_c]x R_cw, so J = K B with B = diag(R_cw, R_cw) and K the camera-frame Jacobian,
        rows (x, y = normalised coordinates, w = 1/depth, times f)
            u: [-w, 0, x w, x y, -(1 + x^2), y],   v: [0, -w, y w, 1 + y^2, -x y, -x].
        """
        res, nrm, iz, r_cw = ev
        k = self._k                                          # (6, 2, N): [column][u / v][point]
        np.multiply(_NEG_EYE2, iz, out=k[0:2])               # -w, 0 / 0, -w
        np.multiply(nrm, iz, out=k[2])                       # x w / y w
        xy = nrm[:, None, :] * nrm[None, :, :]               # [[x x, x y], [y x, y y]]
        np.add(xy[:, 1], _U0_V1, out=k[3])                   # x y / 1 + y y
        np.subtract(_UM1_V0, xy[0], out=k[4])                # -(1 + x x) / -x y
        np.multiply(nrm[::-1], _U1_VM1, out=k[5])            # y / -x
        kk = k.reshape(6, -1)
        b = self._b
        b[:3, :3] = r_cw
        b[3:, 3:] = r_cw
        jtj = b.T @ ((self.f * self.f) * (kk @ kk.T)) @ b
        g = b.T @ (self.f * (kk @ res))
        return jtj, g


_NEG_EYE2 = -np.eye(2)[:, :, None]
_U0_V1 = np.array([[0.0], [1.0]])
_UM1_V0 = np.array([[-1.0], [0.0]])
_U1_VM1 = np.array([[1.0], [-1.0]])


def _refine(prob: _Problem, r_wb, p):
    """Levenberg-Marquardt. Returns (r_wb, p, converged)."""
    ev = prob.residuals(r_wb, p)
    if ev is None:
        return r_wb, p, False
    res = ev[0]
    cost = float(res @ res)
    jtj, g = prob.normal_equations(ev)
    lam = 1e-6                    # relative (Marquardt) damping of diag(J^T J)
    for _ in range(MAX_ITERATIONS):
        d = jtj.diagonal().copy()
        dmax = float(d.max())
        while True:
            a = jtj.copy()
            a.flat[::7] += lam * d + 1e-15 * dmax
            try:
                step = -np.linalg.solve(a, g)
            except np.linalg.LinAlgError:
                return r_wb, p, False
            steps = step.tolist()
            if not all(map(math.isfinite, steps)):
                return r_wb, p, False
            small = max(map(abs, steps)) < _STEP_TOL
            r_new = _rot_exp(step[3:]) @ r_wb
            p_new = p + step[:3]
            ev_new = prob.residuals(r_new, p_new)
            cost_new = float(ev_new[0] @ ev_new[0]) if ev_new is not None else np.inf
            if cost_new <= cost:
                flat = cost - cost_new <= _COST_RTOL * cost
                r_wb, p, ev = r_new, p_new, ev_new
                cost = cost_new
                if small or flat:
                    return _orthonormalise(r_wb), p, True
                jtj, g = prob.normal_equations(ev)
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
        quaternion_wxyz=quat_from_rotation(r_wb) if ok_pose else np.array([1.0, 0.0, 0.0, 0.0]),
        covariance=_FAILED_COVARIANCE * np.eye(6),
        reprojection_rms_px=float(rms) if np.isfinite(rms) else 0.0,
        points_used=int(n))


def _world_corners(marker_map, ids: np.ndarray):
    """(4 M, 3) world corners of the ids, None if one is unknown."""
    if isinstance(marker_map, MarkerMap) and ids.dtype.kind in "iu" and (
            ids.dtype.kind == "i" or len(ids) == 0 or int(ids.max()) < 2 ** 62):
        rows = marker_map._rows(ids.astype(np.int64, copy=False))
        if rows is None:
            return None
        return marker_map.corners_world[rows].reshape(-1, 3)
    world = []                    # any other id type, or a map that only has corners()
    for marker_id in ids:
        c = marker_map.corners(marker_id)
        if c is None:
            return None
        world.append(c)
    return np.concatenate(world, axis=0) if world else np.zeros((0, 3))


# --------------------------------------------------------------------------- solver

def solve_pose(camera: Camera, marker_map: MarkerMap, marker_ids, corners_px,
               pixel_sigma_px: float = 0.5, max_reprojection_px: float = 3.0,
               prior=None, method: str = "hand") -> PoseSolution:
    """Body pose from detected marker corners.

    marker_ids: M ids; corners_px: 8 M numbers (u0, v0, ..., u3, v3 per marker, the
    MarkerCamera layout) or an (M, 4, 2) array. A corner with a non-finite pixel is
    left out (a detector may lose single corners). prior: optional (position (3,),
    quaternion wxyz (4,)) used as the start when the homography is ill-conditioned.
    method: "hand" (this module's homography and Levenberg-Marquardt) or "opencv"
    (cv2.solvePnP, _solve_opencv); the checks and the covariance are the same.
    Raises ValueError only for a corners_px whose size does not match marker_ids.
    """
    ids = np.asarray(marker_ids).reshape(-1) if marker_ids is not None else np.zeros(0, dtype=np.int64)
    pix = np.asarray(corners_px if corners_px is not None else [], dtype=np.float64).reshape(-1)
    if pix.size != 8 * len(ids):
        raise ValueError(f"solve_pose: {len(ids)} markers need {8 * len(ids)} corner numbers, got {pix.size}")
    pix = pix.reshape(-1, 2)
    pts = _world_corners(marker_map, ids)
    if pts is None:
        return _fail("unknown_marker", 0)
    if not len(pts):
        return _fail("too_few_points", 0)
    keep = np.isfinite(pix).all(axis=1)
    if not keep.all():
        pts, pix = pts[keep], pix[keep]
    n = len(pts)
    if n < 4:
        return _fail("too_few_points", n)

    if method == "opencv":
        return _solve_opencv(camera, pts, pix, pixel_sigma_px, max_reprojection_px, prior)
    if method != "hand":
        raise ValueError(f"solve_pose: method {method!r} is not one of {METHODS}")
    f = float(camera.focal_px)
    cxy = np.array(camera.principal_point_px, dtype=np.float64)
    start = _homography_pose(pts[:, :2], (pix - cxy) / f)
    if start is None and prior is not None:
        try:
            p0 = np.asarray(prior[0], dtype=np.float64).reshape(3)
            q0 = np.asarray(prior[1], dtype=np.float64).reshape(4)
            if np.all(np.isfinite(p0)) and np.all(np.isfinite(q0)) and np.linalg.norm(q0) > 0:
                start = (quat_to_rotation(q0), p0)
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
            ev1 = prob.residuals(r_wb, p)
            ev2 = prob.residuals(r2, p2)
            if conv2 and ev1 is not None and ev2 is not None and ev2[0] @ ev2[0] < ev1[0] @ ev1[0]:
                r_wb, p = r2, p2
    return _checked(prob, r_wb, p, converged, n, pixel_sigma_px, max_reprojection_px)


def _checked(prob: _Problem, r_wb, p, converged: bool, n: int, pixel_sigma_px: float,
             max_reprojection_px: float) -> PoseSolution:
    """The solution at (r_wb, p) with its covariance, or the reason it is refused."""
    ev = prob.residuals(r_wb, p)
    if ev is None or not converged or not np.all(np.isfinite(ev[0])):
        return _fail("not_converged", n, r_wb, p)
    res = ev[0]
    rms = math.sqrt(float(res @ res) / len(res))
    jtj, _ = prob.normal_equations(ev)
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
                        quaternion_wxyz=quat_from_rotation(r_wb), covariance=cov,
                        reprojection_rms_px=rms, points_used=n)


def _solve_opencv(camera: Camera, pts: np.ndarray, pix: np.ndarray, pixel_sigma_px: float,
                  max_reprojection_px: float, prior) -> PoseSolution:
    """cv2.solvePnP on the same points: IPPE (the planar solver: both of the plane's pose
    candidates, the better kept) then cv2.solvePnPRefineLM; with `prior` only when IPPE fails.
    The checks and covariance as the hand solver's (_checked). cv2 is imported here only."""
    import cv2

    n = len(pts)
    k = np.array([[camera.focal_px, 0.0, camera.principal_point_px[0]],
                  [0.0, camera.focal_px, camera.principal_point_px[1]], [0.0, 0.0, 1.0]])
    obj = np.ascontiguousarray(pts, dtype=np.float64)
    img = np.ascontiguousarray(pix, dtype=np.float64)
    try:
        ok, rvec, tvec = cv2.solvePnP(obj, img, k, None, flags=cv2.SOLVEPNP_IPPE)
        if ok:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, None, rvec, tvec)
        elif prior is not None:
            r_cw0 = R_CAM_FROM_BODY @ quat_to_rotation(np.asarray(prior[1], dtype=np.float64)).T
            rvec = cv2.Rodrigues(r_cw0)[0]
            tvec = (-r_cw0 @ np.asarray(prior[0], dtype=np.float64)).reshape(3, 1)
            ok, rvec, tvec = cv2.solvePnP(obj, img, k, None, rvec, tvec, True, cv2.SOLVEPNP_ITERATIVE)
    except cv2.error:
        ok = False
    if not ok:
        return _fail("degenerate", n)
    r_cw = cv2.Rodrigues(rvec)[0]
    r_wb = _orthonormalise(r_cw.T @ R_CAM_FROM_BODY)
    p = -r_cw.T @ tvec.reshape(3)
    if not (np.all(np.isfinite(r_wb)) and np.all(np.isfinite(p))):
        return _fail("not_converged", n)
    return _checked(_Problem(camera, pts, pix), r_wb, p, True, n, pixel_sigma_px, max_reprojection_px)
