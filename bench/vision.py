"""Time per camera frame of the vision service's pose solve (flight/estimation/pnp.py), former vs current;
the hand PnP against cv2.solvePnP on the same corners; the image mode's detection and pose.

    python bench/vision.py [--frames 40] [--rounds 5] [--seed 0] [--only old-new|hand-opencv|image]

Frames come from the simulator's own camera (simulator.sensors.MarkerCamera with the
default SimConfig: 640 x 480, f = 400 px, 0.2 m markers every 0.5 m, 0.5 px noise), at
random spots near the middle of the grid with a random yaw, level or tilted by the given
angle in a random direction: 1 m is the x250's hover, 5 m the q820's flip altitude (the
camera and the map are the same for both vehicles; the vehicle only names the case).

Each solver gets the same frames, as the vision service passes them (Python lists of ids
and corner pixels, no prior). Times are CPU time of this process per frame (the best of
--rounds passes over the frames), with one BLAS thread like the services (deploy/launcher.py).
"old" is the solver as it was (bench/support/pnp_reference.py, verbatim); the last columns
are the largest differences between the two poses over the frames.

hand-opencv: the same frames' corners to the hand solver (method "hand") and to
cv2.solvePnP (method "opencv": IPPE, then solvePnPRefineLM; the same checks and covariance),
each pose's error against the truth (median and worst), CPU time per frame and the ratio.

image: the same poses rendered by the simulator's image mode (simulator/render.py: the
default intrinsics with their lens distortion, 4 ms exposure, noise 2 grey levels; still,
no motion blur), the markers detected by the vision service's detector
(flight/estimation/markers.py) and solved both ways: detection rate (frames with a pose),
markers found against those the corner mode sees whole, pose error, CPU ms per frame of
detection and of each solve (the render is the simulator's, not timed here); "crop": the
detection in the image's central 2/3 (of width and height) only, as the vision service does
after a frame with more than crop_above_markers (60) markers. "frame ms": detection and the hand solve, as the
service does them. OpenCV on one thread, as in the service.
"""

from __future__ import annotations

import os

for _key in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_key, "1")   # before numpy: the services run with one BLAS thread

import argparse  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.support import pnp_reference as ref  # noqa: E402
from flight.estimation import pnp  # noqa: E402
from flight.quat import quat_conjugate, quat_from_euler, quat_multiply  # noqa: E402
from simulator.config import SimConfig  # noqa: E402
from simulator.sensors import ImageCamera, MarkerCamera  # noqa: E402

CROP = 0.67   # the vision service's crop_window

CASES = [  # (vehicle, what, altitude m, tilt deg)
    ("x250", "hover", 1.0, 0.0),
    ("x250", "hover", 1.0, 20.0),
    ("q820", "flip altitude", 5.0, 0.0),
    ("q820", "flip altitude", 5.0, 20.0),
]


def frames_for(cam: MarkerCamera, rng: np.random.Generator, altitude_m: float, tilt_deg: float, count: int):
    """count frames with >= 1 marker: (ids list, corners list, true position, true quaternion)."""
    out = []
    while len(out) < count:
        pos = np.array([*rng.uniform(-0.5, 0.5, 2), altitude_m])
        axis = rng.uniform(-np.pi, np.pi)           # tilt direction
        c, s = math.cos(math.radians(tilt_deg) / 2), math.sin(math.radians(tilt_deg) / 2)
        q_tilt = np.array([c, s * math.cos(axis), s * math.sin(axis), 0.0])
        q = quat_multiply(quat_from_euler(0.0, 0.0, float(rng.uniform(-np.pi, np.pi))), q_tilt)
        frame = cam.sample(pos, q)
        if frame is not None and frame["marker_ids"]:
            out.append((frame["marker_ids"], frame["corners_px"], pos, q))
    return out


def cpu_per_frame(solve, frames, rounds: int) -> float:
    best = math.inf
    for _ in range(rounds):
        t0 = time.process_time()
        for ids, corners, _, _ in frames:
            solve(ids, corners)
        best = min(best, (time.process_time() - t0) / len(frames))
    return best


def angle_between(q1, q2) -> float:
    """Rotation angle between two attitudes (rad), accurate for tiny angles."""
    d = quat_multiply(quat_conjugate(q1), q2)
    return 2.0 * math.atan2(float(np.linalg.norm(d[1:])), abs(float(d[0])))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40, help="frames per case")
    ap.add_argument("--rounds", type=int, default=5, help="timed passes over the frames (the best is kept)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", choices=("old-new", "hand-opencv", "image"), help="one table only")
    args = ap.parse_args(argv)
    print(" ".join(["$ python bench/vision.py", *(sys.argv[1:] if argv is None else argv)]))
    print(f"  (OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}, numpy {np.__version__}, "
          f"{args.frames} frames a case, best of {args.rounds} rounds, CPU ms per frame)")

    print(f"  load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())} ({os.cpu_count()} CPUs, shared)")
    if args.only in (None, "old-new"):
        old_new(args)
    if args.only in (None, "hand-opencv"):
        hand_opencv(args)
    if args.only in (None, "image"):
        image_mode(args)
    print(f"  load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


def old_new(args) -> None:
    cfg = SimConfig()
    rng = np.random.default_rng(args.seed)
    cam = MarkerCamera(cfg, np.random.default_rng(args.seed + 1))
    camera = cam.camera
    grid = (cfg.marker_size_m, cfg.marker_spacing_m, cfg.marker_grid_half_extent_m)
    map_old, map_new = ref.MarkerMap.grid(*grid), pnp.MarkerMap.grid(*grid)
    sigma, limit = cfg.camera_pixel_noise_px, 3.0   # the vision service's parameters

    def old(ids, corners):
        return ref.solve_pose(camera, map_old, ids, corners, pixel_sigma_px=sigma, max_reprojection_px=limit)

    def new(ids, corners):
        return pnp.solve_pose(camera, map_new, ids, corners, pixel_sigma_px=sigma, max_reprojection_px=limit)

    header = (f"{'vehicle':<7} {'case':<14} {'alt m':>5} {'tilt':>5} {'markers':>13} "
              f"{'old ms':>8} {'new ms':>8} {'ratio':>6} {'ok o/n':>7} {'max dp m':>9} {'max dth rad':>11}")
    print(header)
    print("-" * len(header))
    for vehicle, what, alt, tilt in CASES:
        frames = frames_for(cam, rng, alt, tilt, args.frames)
        counts = [len(f[0]) for f in frames]
        dp = dth = 0.0
        ok_old = ok_new = 0
        for ids, corners, _, _ in frames:
            a, b = old(ids, corners), new(ids, corners)
            if (a.ok, a.reason) != (b.ok, b.reason):
                raise SystemExit(f"decisions differ: old {a.reason or 'ok'}, new {b.reason or 'ok'}")
            ok_old += a.ok
            ok_new += b.ok
            dp = max(dp, float(np.abs(a.position_m - b.position_m).max()))
            dth = max(dth, angle_between(a.quaternion_wxyz, b.quaternion_wxyz))
        t_old = cpu_per_frame(old, frames, args.rounds)
        t_new = cpu_per_frame(new, frames, args.rounds)
        markers = f"{np.mean(counts):.0f} ({min(counts)}-{max(counts)})"
        print(f"{vehicle:<7} {what:<14} {alt:>5.1f} {tilt:>4.0f}d {markers:>13} "
              f"{1e3 * t_old:>8.3f} {1e3 * t_new:>8.3f} {t_old / t_new:>5.1f}x "
              f"{ok_old:>3}/{ok_new:<3} {dp:>9.1e} {dth:>11.1e}")



def errors(sol, pos, q) -> tuple[float, float]:
    """(position error m, attitude error deg) of a solution against the truth (NaN if refused)."""
    if not sol.ok:
        return math.nan, math.nan
    return float(np.linalg.norm(sol.position_m - pos)), math.degrees(angle_between(sol.quaternion_wxyz, q))


def summary(values) -> str:
    v = np.asarray([x for x in values if np.isfinite(x)])
    return f"{np.median(v):.2g}/{v.max():.2g}" if len(v) else "-"


def hand_opencv(args) -> None:
    cfg = SimConfig()
    rng = np.random.default_rng(args.seed)
    cam = MarkerCamera(cfg, np.random.default_rng(args.seed + 1))
    camera = cam.camera
    markers = pnp.MarkerMap.grid(cfg.marker_size_m, cfg.marker_spacing_m, cfg.marker_grid_half_extent_m)
    sigma = cfg.camera_pixel_noise_px
    solvers = {m: (lambda ids, corners, m=m: pnp.solve_pose(camera, markers, ids, corners, pixel_sigma_px=sigma,
                                                           max_reprojection_px=3.0, method=m))
               for m in pnp.METHODS}
    print()
    print("hand PnP against cv2.solvePnP (IPPE + LM) on the same corners (0.5 px noise): pose error median/max, "
          "CPU ms per frame")
    header = (f"{'case':<14} {'alt m':>5} {'tilt':>5} {'markers':>8} {'hand dp mm':>11} {'cv dp mm':>11} "
              f"{'hand dth deg':>12} {'cv dth deg':>12} {'hand ms':>8} {'cv ms':>7} {'cv/hand':>7} {'ok h/cv':>7}")
    print(header)
    print("-" * len(header))
    for _, what, alt, tilt in CASES:
        frames = frames_for(cam, rng, alt, tilt, args.frames)
        err = {m: [errors(solvers[m](ids, c), pos, q) for ids, c, pos, q in frames] for m in pnp.METHODS}
        ms = {m: 1e3 * cpu_per_frame(solvers[m], frames, args.rounds) for m in pnp.METHODS}
        ok = {m: sum(np.isfinite(e[0]) for e in err[m]) for m in pnp.METHODS}
        markers_seen = np.mean([len(f[0]) for f in frames])
        print(f"{what:<14} {alt:>5.1f} {tilt:>4.0f}d {markers_seen:>8.0f} "
              f"{summary([1e3 * e[0] for e in err['hand']]):>11} {summary([1e3 * e[0] for e in err['opencv']]):>11} "
              f"{summary([e[1] for e in err['hand']]):>12} {summary([e[1] for e in err['opencv']]):>12} "
              f"{ms['hand']:>8.3f} {ms['opencv']:>7.3f} {ms['opencv'] / ms['hand']:>6.2f}x "
              f"{ok['hand']:>3}/{ok['opencv']:<3}")


def image_mode(args) -> None:
    import cv2

    from flight.estimation.markers import MarkerDetector

    cv2.setNumThreads(1)   # as the vision service

    cfg = SimConfig(camera_mode="image")
    rng = np.random.default_rng(args.seed)
    corner_cam = MarkerCamera(SimConfig(camera_pixel_noise_px=0.0), np.random.default_rng(args.seed + 1))
    image_cam = ImageCamera(cfg, np.random.default_rng(args.seed + 2))
    markers = pnp.MarkerMap.grid(cfg.marker_size_m, cfg.marker_spacing_m, cfg.marker_grid_half_extent_m)
    detector = MarkerDetector(image_cam.intrinsics, len(markers))
    camera = detector.camera
    print()
    print(f"image mode: {cfg.camera_width_px} x {cfg.camera_height_px} mono8 rendered (distortion "
          f"{list(image_cam.intrinsics.distortion)}, noise {cfg.camera_image_noise} grey), detected "
          "(cv2.aruco, sub-pixel corners), solved both ways: CPU ms per frame")
    header = (f"{'case':<14} {'alt m':>5} {'tilt':>5} {'found/whole':>11} {'pose %':>6} {'hand dp mm':>11} "
              f"{'cv dp mm':>11} {'hand dth deg':>12} {'cv dth deg':>12} {'detect ms':>9} {'hand ms':>8} "
              f"{'cv ms':>7} {'frame ms':>8} | {'crop: found':>11} {'dp mm':>8} {'detect ms':>9} {'frame ms':>8}")
    print(header)
    print("-" * len(header))
    for _, what, alt, tilt in CASES:
        poses = [(pos, q) for _, _, pos, q in frames_for(corner_cam, rng, alt, tilt, args.frames)]
        images = [image_cam.sample(pos, q, np.zeros(3), np.zeros(3)) for pos, q in poses]
        images = [np.frombuffer(f["pixels"], np.uint8).reshape(f["height_px"], f["width_px"]) for f in images]
        whole = [len(corner_cam.sample(pos, q)["marker_ids"]) for pos, q in poses]
        found = [detector.detect(img) for img in images]
        half = [detector.detect(img, window=CROP) for img in images]   # the service's crop (> 60 markers)
        err_half = [errors(pnp.solve_pose(camera, markers, ids, c, pixel_sigma_px=0.3), pos, q)
                    if len(ids) >= 4 else (math.nan, math.nan) for (ids, c), (pos, q) in zip(half, poses)]
        err = {m: [errors(pnp.solve_pose(camera, markers, ids, c, pixel_sigma_px=0.3, method=m), pos, q)
                   if ids else (math.nan, math.nan) for (ids, c), (pos, q) in zip(found, poses)]
               for m in pnp.METHODS}
        best = {}
        for name, fn in (("detect", lambda: [detector.detect(img) for img in images]),
                         ("half", lambda: [detector.detect(img, window=CROP) for img in images]),
                         *((m, lambda m=m: [pnp.solve_pose(camera, markers, ids, c, pixel_sigma_px=0.3, method=m)
                                            for ids, c in found if ids]) for m in pnp.METHODS)):
            t_best = math.inf
            for _ in range(args.rounds):
                t0 = time.process_time()
                fn()
                t_best = min(t_best, time.process_time() - t0)
            best[name] = 1e3 * t_best / len(images)
        rate = 100.0 * np.mean([np.isfinite(e[0]) for e in err["hand"]])
        n_found, n_whole = np.mean([len(ids) for ids, _ in found]), np.mean(whole)
        print(f"{what:<14} {alt:>5.1f} {tilt:>4.0f}d {n_found:>5.0f}/{n_whole:<5.0f} {rate:>6.0f} "
              f"{summary([1e3 * e[0] for e in err['hand']]):>11} {summary([1e3 * e[0] for e in err['opencv']]):>11} "
              f"{summary([e[1] for e in err['hand']]):>12} {summary([e[1] for e in err['opencv']]):>12} "
              f"{best['detect']:>9.2f} {best['hand']:>8.3f} {best['opencv']:>7.3f} "
              f"{best['detect'] + best['hand']:>8.2f} | "
              f"{np.mean([len(ids) for ids, _ in half]):>11.0f} {summary([1e3 * e[0] for e in err_half]):>8} "
              f"{best['half']:>9.2f} {best['half'] + best['hand']:>8.2f}")


if __name__ == "__main__":
    main()
