import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flight import pnp
from flight.camera import Camera
from flight.pnp import MarkerMap, PoseSolution, solve_pose
from flight.quat import quat_from_euler, quat_to_rotation

CAM = Camera(640, 480, 400.0)
MAP = MarkerMap.grid(0.2, 1.0, 5.0)


def _visible(position, quat):
    """Like simulator MarkerCamera: markers whose 4 corners are in front and in the image."""
    pix, front = CAM.project(MAP.corners_world.reshape(-1, 3), position, quat)
    ok = (front & CAM.in_image(pix)).reshape(-1, 4).all(axis=1)
    return MAP.ids[ok], pix.reshape(-1, 4, 2)[ok]


def _pixels(ids, position, quat):
    pts = np.concatenate([MAP.corners(i) for i in ids])
    pix, front = CAM.project(pts, position, quat)
    assert front.all()
    return pix.reshape(-1)


def _error(sol: PoseSolution, position, quat):
    """[position error, world-frame attitude error rotation vector] (R_est = exp(e) R_true)."""
    r = quat_to_rotation(sol.quaternion_wxyz) @ quat_to_rotation(quat).T
    return np.r_[sol.position_m - position, Rotation.from_matrix(r).as_rotvec()]


def _finite(sol: PoseSolution):
    return (np.all(np.isfinite(sol.position_m)) and np.all(np.isfinite(sol.quaternion_wxyz))
            and np.all(np.isfinite(sol.covariance)) and np.isfinite(sol.reprojection_rms_px))


def test_marker_map():
    assert len(MAP) == 121
    np.testing.assert_allclose(MAP.corners(60), [[0.1, 0.1, 0], [0.1, -0.1, 0], [-0.1, -0.1, 0], [-0.1, 0.1, 0]])
    assert MAP.corners(121) is None and MAP.corners(-1) is None and MAP.corners("x") is None
    assert MAP.corners(np.int64(0)) is not None
    with pytest.raises(Exception):
        MAP.ids = np.zeros(3)   # frozen
    with pytest.raises(ValueError):
        MarkerMap(np.arange(1), np.ones((1, 4, 3)))  # not on the floor


@pytest.mark.parametrize("height", [0.5, 1.0, 2.0, 3.0])
def test_noiseless_recovers_pose(height):
    rng = np.random.default_rng(int(height * 10))
    solved = 0
    for roll, pitch, yaw in [(0, 0, 0), (0.2, -0.3, 2.5), (np.radians(25), 0, -1.0),
                             (0, np.radians(-25), 3.0), (-0.3, 0.25, -2.8), (0.1, 0.1, 0.7)]:
        for _ in range(20):   # find a spot where at least one marker is seen
            pos = np.array([*rng.uniform(-3.5, 3.5, 2), height])
            q = quat_from_euler(roll, pitch, yaw)
            ids, pix = _visible(pos, q)
            if len(ids):
                break
        assert len(ids), "no marker in view"
        sol = solve_pose(CAM, MAP, ids, pix.reshape(-1))
        assert sol.ok and sol.reason == "", sol.reason
        e = _error(sol, pos, q)
        assert np.linalg.norm(e[:3]) < 1e-6 and np.linalg.norm(e[3:]) < 1e-6, e
        assert sol.points_used == 4 * len(ids)
        assert sol.reprojection_rms_px < 1e-6
        assert abs(np.linalg.norm(sol.quaternion_wxyz) - 1) < 1e-12 and sol.quaternion_wxyz[0] >= 0
        assert _finite(sol) and sol.covariance.shape == (6, 6)
        np.testing.assert_allclose(sol.covariance, sol.covariance.T)
        assert np.all(np.linalg.eigvalsh(sol.covariance) > 0)
        solved += 1
    assert solved == 6


def test_single_marker_and_layout():
    pos, q = np.array([0.05, -0.03, 1.2]), quat_from_euler(0.1, -0.15, 0.8)
    pix = _pixels([60], pos, q)
    sol = solve_pose(CAM, MAP, [60], pix)
    assert sol.ok and sol.points_used == 4
    assert np.linalg.norm(_error(sol, pos, q)) < 1e-6
    # (M, 4, 2) arrays and numpy ids work too
    sol2 = solve_pose(CAM, MAP, np.array([60]), pix.reshape(1, 4, 2))
    np.testing.assert_allclose(sol2.position_m, sol.position_m)
    # several markers at a tilt and yaw
    ids = [60, 61, 71, 72]
    pos, q = np.array([0.6, 0.4, 2.5]), quat_from_euler(-0.2, 0.3, -2.0)
    sol = solve_pose(CAM, MAP, ids, _pixels(ids, pos, q))
    assert sol.ok and np.linalg.norm(_error(sol, pos, q)) < 1e-6


def test_noise_consistent_with_covariance():
    """200 random frames at 1 m with 0.5 px noise: NEES of the 6-vector averages ~6."""
    rng = np.random.default_rng(7)
    nees, errs, multi = [], [], []
    while len(nees) < 200:
        pos = np.array([*rng.uniform(-4, 4, 2), 1.0])
        q = quat_from_euler(*rng.uniform(-0.17, 0.17, 2), rng.uniform(-np.pi, np.pi))
        ids, pix = _visible(pos, q)
        if not len(ids):
            continue
        sol = solve_pose(CAM, MAP, ids, pix + rng.normal(0, 0.5, pix.shape), pixel_sigma_px=0.5)
        assert sol.ok, sol.reason
        assert _finite(sol)
        e = _error(sol, pos, q)
        nees.append(e @ np.linalg.solve(sol.covariance, e))
        errs.append(e)
        multi.append(len(ids) > 1)
        assert sol.reprojection_rms_px < 1.5
    nees, errs, multi = np.array(nees), np.array(errs), np.array(multi)
    assert 4.5 < nees.mean() < 7.5, nees.mean()
    pos_std = errs[:, :3].std(axis=0)
    # one 0.2 m marker at 1 m: ~1-3 cm horizontally (tilt/shift coupling), < 1 cm with 2+ markers
    assert np.all(pos_std < 0.05), pos_std
    assert np.all(errs[multi, :3].std(axis=0) < 0.012), errs[multi, :3].std(axis=0)
    assert np.all(errs[:, 3:].std(axis=0) < 0.05)


def test_rejections():
    pos, q = np.array([0.1, 0.0, 1.0]), quat_from_euler(0.05, 0.0, 0.3)
    ids = [60, 61]
    pix = _pixels(ids, pos, q)

    sol = solve_pose(CAM, MAP, [60, 999], pix)
    assert not sol.ok and sol.reason == "unknown_marker" and _finite(sol)

    three = pix.copy()
    three[6:8] = np.nan                      # marker 60 with its 4th corner lost
    sol = solve_pose(CAM, MAP, [60], three[:8])
    assert not sol.ok and sol.reason == "too_few_points" and sol.points_used == 3 and _finite(sol)
    sol = solve_pose(CAM, MAP, [], [])
    assert not sol.ok and sol.reason == "too_few_points"

    for k in range(4):                        # one corner moved 50 px
        bad = pix.copy()
        bad[2 * k] += 50.0
        sol = solve_pose(CAM, MAP, ids, bad)
        assert not sol.ok and sol.reason == "reprojection" and sol.reprojection_rms_px > 3.0, sol
        assert _finite(sol)
    bad = _pixels([60], pos, q)
    bad[5] += 50.0
    sol = solve_pose(CAM, MAP, [60], bad)
    assert not sol.ok and sol.reason == "reprojection"

    with pytest.raises(ValueError):
        solve_pose(CAM, MAP, ids, pix[:-1])


def test_degenerate_collinear_points():
    # markers 60 and 71 share x; their corners 0 and 1 lie on the line x = 0.1
    pos, q = np.array([0.0, 0.5, 1.5]), quat_from_euler(0, 0, 0)
    pix = _pixels([60, 71], pos, q).reshape(2, 4, 2)
    pix[:, 2:] = np.nan
    sol = solve_pose(CAM, MAP, [60, 71], pix)
    assert not sol.ok and sol.reason == "degenerate" and _finite(sol)
    # a prior gives a start, but the geometry stays unobservable
    sol = solve_pose(CAM, MAP, [60, 71], pix, prior=(pos + 0.01, q))
    assert not sol.ok and sol.reason == "degenerate" and _finite(sol)


def test_prior_used_and_not_converged(monkeypatch):
    pos, q = np.array([0.1, 0.2, 1.0]), quat_from_euler(0.1, 0.0, 0.5)
    ids = [60, 61, 71]
    pix = _pixels(ids, pos, q)
    # force the homography path off: the prior alone must lead to the solution
    monkeypatch.setattr(pnp, "_homography_pose", lambda xy, mn: None)
    sol = solve_pose(CAM, MAP, ids, pix, prior=(pos + [0.1, -0.1, 0.1], quat_from_euler(0.2, -0.1, 0.3)))
    assert sol.ok and np.linalg.norm(_error(sol, pos, q)) < 1e-6
    monkeypatch.setattr(pnp, "MAX_ITERATIONS", 1)
    sol = solve_pose(CAM, MAP, ids, pix, prior=(pos + [0.3, -0.3, 0.3], quat_from_euler(0.3, -0.2, 1.0)))
    assert not sol.ok and sol.reason == "not_converged" and _finite(sol)


def test_non_finite_and_garbage_never_nan():
    rng = np.random.default_rng(3)
    for _ in range(50):
        n = int(rng.integers(1, 4))
        ids = rng.choice(121, n, replace=False)
        pix = rng.uniform(-1e3, 1e3, 8 * n)
        pix[rng.random(8 * n) < 0.1] = np.nan
        sol = solve_pose(CAM, MAP, ids, pix)
        assert _finite(sol)
        assert sol.reason in ("",) + pnp.REASONS
        assert sol.ok == (sol.reason == "")


def test_speed():
    ids = [60, 61, 71, 72]
    pos, q = np.array([0.5, 0.5, 2.0]), quat_from_euler(0.1, -0.1, 0.4)
    pix = _pixels(ids, pos, q)
    rng = np.random.default_rng(0)
    frames = [pix + rng.normal(0, 0.5, pix.shape) for _ in range(50)]
    t = time.perf_counter()
    for f in frames:
        assert solve_pose(CAM, MAP, ids, f).ok
    per_solve = (time.perf_counter() - t) / len(frames)
    assert per_solve < 0.02, per_solve   # typically ~1 ms; generous for loaded machines
