"""Time per camera frame of the vision service's pose solve (flight/estimation/pnp.py), former vs current.

    python bench/vision.py [--frames 40] [--rounds 5] [--seed 0]

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
from simulator.sensors import MarkerCamera  # noqa: E402

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
    args = ap.parse_args(argv)
    print(" ".join(["$ python bench/vision.py", *(sys.argv[1:] if argv is None else argv)]))
    print(f"  (OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}, numpy {np.__version__}, "
          f"{args.frames} frames a case, best of {args.rounds} rounds, CPU ms per frame)")

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


if __name__ == "__main__":
    main()
