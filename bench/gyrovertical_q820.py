"""The gyro-vertical (004) on the q820: through its flips and over a long flight, per parameter file.

    python bench/gyrovertical_q820.py [--log FLIGHT.mcap] [--flights N] [--long-s S] [--cache DIR]
                                      [--params FILE ...]

Three measurements, every estimator starting from the true attitude:

* ``--log``: a flip-mission flight log (``zenpilot fly --lockstep --mission flip``): roll/pitch RMS
  error from the flip item's start to its end (the planner's phases flip .. flip-settle) of the
  stack's own estimate (att/state) and of each file's gyro-vertical run on the logged IMU (the
  simulator's own gyro bias, as the attitude service would see it), compensated with the logged
  pos/state's velocity windows as the attitude service would (``--compensation``); and where in the
  item the error is: the second of hover before it, the flip phase, the recovery (flip-recovery and
  flip-settle);
* q820 control flights (deploy/manoeuvres.py "control" menu, seeds 10000 + i that training never
  uses), +0.05 deg/s bias on every gyro: roll/pitch RMS through each flip segment and overall;
* one control flight of ``--long-s`` (one flip a minute), the same bias: RMS tilt error per
  minute, first and last minute, and the worst tilt error of the last minute (bounded or drifting).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from deploy.gyrovertical_training import control_flight, estimate, tilt_error_deg
from deploy.manoeuvres import FlightData
from flight.estimation.gyrovertical import GyroVertical, load_trained, run_sequence
from flight.quat import quats_to_euler, wrap_angle
from flight.vehicle import PARAMS_DIR

BIAS_DEG_S = 0.05
FILES = ("gyrovertical_q820_compensated.toml", "gyrovertical_q820_mems.toml", "gyrovertical_q820.toml", "gyrovertical_x250_mems.toml", "gyrovertical_x250.toml")


def rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def log_reference(log, p: str, it, window_s: float = 0.1):
    """((t, t0, t1, a), heading) of run_sequence from a log's pos/state and att/state, as
    services/attitude.py feeds the gyro-vertical: the velocity change over window_s ending at the
    newest pos/state before each sample, the yaw of the newest att/state before it."""
    ps = log[p + "pos/state"]
    pt = np.array([x["header"]["t_s"] for x in ps])
    pv = np.array([x["velocity_m_s"] for x in ps])
    dt = float(np.median(np.diff(it)))
    j1 = np.searchsorted(pt, it - 0.5 * dt + 1e-9, side="right") - 1
    ok = j1 >= 0
    j1 = np.clip(j1, 0, None)
    t1 = pt[j1]
    j0 = np.searchsorted(pt, t1 - window_s - 1e-9)
    t0 = pt[j0]
    ok &= (t1 - t0) >= 0.5 * window_s
    a = np.full((len(it), 3), np.nan)
    a[ok] = (pv[j1[ok]] - pv[j0[ok]]) / (t1[ok] - t0[ok])[:, None]
    att = log[p + "att/state"]
    at = np.array([x["header"]["t_s"] for x in att])
    ay = np.array([x["euler_rad"][2] for x in att])
    k = np.searchsorted(at, it - 1e-9) - 1
    heading = np.where(k >= 0, ay[np.clip(k, 0, None)], 0.0)
    return (it, t0, t1, a), heading


def compensated(trained, mode: str) -> bool:
    return (trained.meta.get("compensation", "none") if mode == "file" else mode) == "window"


def flip_log(path: str, files, mode: str = "file") -> None:
    from schemas.flightlog import read_log
    log, p = read_log(path), "zp/0/"
    sp = log[p + "planner/setpoint"]
    flip_t = [x["header"]["t_s"] for x in sp if x["phase"].startswith("flip")]
    lo, hi = min(flip_t), max(flip_t)
    recovery_t = min(x["header"]["t_s"] for x in sp if x["phase"] in ("flip-recovery", "flip-settle"))
    truth = log[p + "sim/truth"]
    tt = np.array([x["header"]["t_s"] for x in truth])
    te = quats_to_euler(np.array([x["quaternion_wxyz"] for x in truth]))

    def errors(t, roll, pitch):
        # at the truth's (100 Hz) sample times within the flip item, then its parts
        i = np.clip(np.searchsorted(tt, t + 1e-9, side="right") - 1, 0, len(tt) - 1)
        at_truth = np.abs(tt[i] - t) < 1e-6
        er, ep = np.degrees(wrap_angle(roll - te[i, 0])), np.degrees(wrap_angle(pitch - te[i, 1]))
        out = []
        for a, b in ((lo, hi), (lo - 1.0, lo - 1e-6), (lo, recovery_t - 1e-6), (recovery_t, hi)):
            m = (t >= a) & (t <= b) & at_truth
            out += [rms(er[m]), rms(ep[m])]
        return tuple(out) + (int(((t >= lo) & (t <= hi) & at_truth).sum()),)

    att = log[p + "att/state"]
    at, ae = np.array([x["header"]["t_s"] for x in att]), np.array([x["euler_rad"] for x in att])
    print(f"flip log {path}: flip item {lo:.2f}-{hi:.2f} s (flip phase to {recovery_t:.2f} s)")
    print("| estimator | RMS roll, deg | RMS pitch, deg | roll / pitch, the second before | in the flip phase | "
          "in the recovery | samples |\n|---|---|---|---|---|---|---|")
    row = "| %.3f | %.3f | %.3f / %.3f | %.3f / %.3f | %.3f / %.3f | %d |"
    print("| stack att/state " + row % errors(at, ae[:, 0], ae[:, 1]))
    imu = log[p + "sim/imu"]
    it = np.array([x["header"]["t_s"] for x in imu])
    gyro, accel = np.array([x["gyro_rad_s"] for x in imu]), np.array([x["accel_m_s2"] for x in imu])
    q0 = np.array(truth[int(np.clip(np.searchsorted(tt, it[0] + 1e-9, side="right") - 1, 0, len(tt) - 1))]
                  ["quaternion_wxyz"])
    reference, heading = log_reference(log, p, it)
    for f in files:
        trained = load_trained(f)
        comp = compensated(trained, mode)
        params, fallback = trained.flown(comp)
        r, pch = run_sequence(GyroVertical(params, dt=float(np.median(np.diff(it))), q0=q0, fallback=fallback),
                              gyro, accel, reference if comp else None, heading if comp else None)
        print(f"| gyro-vertical {Path(f).name}{' (compensated)' if comp else ''} " + row % errors(it, r, pch))


def flip_mask(f: FlightData) -> np.ndarray:
    m, t0 = np.zeros(len(f.t_s), bool), 0.0
    for s in f.segments:
        if s.kind == "flip":
            m |= (f.t_s >= t0) & (f.t_s < t0 + s.duration_s)
        t0 += s.duration_s
    return m


def cached_flight(seed: int, duration_s: float, cache: Path | None) -> FlightData:
    """A q820 control flight, kept as .npz in ``cache`` (a 1-hour one takes minutes to fly)."""
    import pickle
    path = cache / f"q820-control-{seed}-{duration_s:g}.pkl" if cache else None
    if path and path.is_file():
        return pickle.loads(path.read_bytes())
    f = control_flight("q820", seed, duration_s)
    if path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(f))
    return f


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--log", help="a flip-mission flight.mcap")
    ap.add_argument("--flights", type=int, default=3, help="q820 control flights (default 3)")
    ap.add_argument("--short-s", type=float, default=90.0, help="their length, s (default 90: two flips)")
    ap.add_argument("--long-s", type=float, default=600.0, help="the long flight, s (default 600; 0: none)")
    ap.add_argument("--cache", help="folder to keep the recorded flights in")
    ap.add_argument("--params", nargs="+", default=[str(PARAMS_DIR / f) for f in FILES])
    ap.add_argument("--compensation", choices=("file", "window", "none"), default="file",
                    help="the acceleration compensation: as each file was trained (default), or for all")
    args = ap.parse_args()
    cache = Path(args.cache) if args.cache else None
    trained = {Path(f).name: load_trained(f) for f in args.params}
    t_start = time.monotonic()
    if args.log:
        flip_log(args.log, args.params, args.compensation)
    bias = np.radians(np.full(3, BIAS_DEG_S))
    if args.flights:
        flights = [cached_flight(s, args.short_s, cache) for s in range(args.flights)]
        print(f"\nq820 control flights: {args.flights} x {args.short_s:g} s, bias +{BIAS_DEG_S} deg/s "
              f"({time.monotonic() - t_start:.0f} s)")
        print("| file | RMS roll in flips, deg | RMS pitch in flips, deg | RMS roll, deg | RMS pitch, deg |")
        print("|---|---|---|---|---|")
        for name, tr in trained.items():
            rows = []
            for f in flights:
                er, ep = tilt_error_deg(f, *estimate(f, "adaptive", tr, bias, vehicle_name="q820",
                                                    compensation=compensated(tr, args.compensation)))
                m = flip_mask(f)
                rows.append((rms(er[m]), rms(ep[m]), rms(er), rms(ep)))
            print(f"| {name} | " + " | ".join(f"{v:.3f}" for v in np.mean(rows, axis=0)) + " |")
    if args.long_s:
        f = cached_flight(99, args.long_s, cache)
        print(f"\nq820 control flight of {args.long_s:g} s, bias +{BIAS_DEG_S} deg/s on every gyro "
              f"({time.monotonic() - t_start:.0f} s)")
        print("| file | RMS tilt, minute 1 | RMS tilt, last minute | worst tilt, last minute | "
              "largest minute's RMS | RMS roll / pitch in flips |")
        print("|---|---|---|---|---|---|")
        minute = int(60.0 / 0.0025)
        m = flip_mask(f)
        for name, tr in trained.items():
            er, ep = tilt_error_deg(f, *estimate(f, "adaptive", tr, bias, vehicle_name="q820",
                                                    compensation=compensated(tr, args.compensation)))
            tilt = np.hypot(er, ep)
            per = [rms(tilt[k:k + minute]) for k in range(0, len(tilt), minute)]
            print(f"| {name} | {per[0]:.3f} | {per[-1]:.3f} | {np.max(tilt[-minute:]):.2f} | {max(per):.3f} | "
                  f"{rms(er[m]):.3f} / {rms(ep[m]):.3f} |")
    print(f"({time.monotonic() - t_start:.0f} s)")


if __name__ == "__main__":
    main()
