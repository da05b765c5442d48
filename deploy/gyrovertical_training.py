"""`zenpilot train-gyrovertical`: train the adaptive gyro-vertical of 004 on simulator flights.

Steps (004, section "training"):

1. fly ``--flights`` manoeuvre flights of ``--duration-s`` in the simulator
   (deploy/manoeuvres.py, the "training" menu: steps, circles, yaw turns,
   attitude steps, a flip), seeds drawn from ``--seed``;
2. from each, the 9 sequences of 004: the 8 sign combinations of
   +-``--bias-deg-s`` on the three gyros, plus the exact one;
3. minimise criterion (10), the weighted mean RMS pitch/roll error, over the
   12 parameters of (7) (Nelder-Mead, deterministic for a seed), printing
   progress; the fixed-variance baseline is trained the same way on the same
   data, so the comparison with it is fair;
4. write both parameter sets to a TOML file the attitude service reads
   (``[services.attitude.params] gyrovertical_params = FILE``).

Same arguments and seed give the same file.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from deploy.manoeuvres import FlightData, record
from flight.estimation.gyrovertical import (DT_REF, GyroVerticalParams, TrainedParams, TrainingSequence,
                                            make_training_sequences)
from flight.vehicle import load_vehicle

def training_flights(vehicle_name: str, seed: int, flights: int, duration_s: float) -> list[FlightData]:
    """``flights`` training-menu flights, cut to exactly ``duration_s`` (equal lengths batch together)."""
    vehicle = load_vehicle(vehicle_name)
    n = int(round(duration_s / DT_REF))
    out = []
    for i in range(flights):
        data = record(vehicle, "training", duration_s, seed=seed * 1000 + i)
        out.append(data.slice(n))
    return out


# The acceleration compensation as the attitude service feeds it: the position level's velocity
# change over accel_window_s (0.1 s), ending at its newest pos/state (100 Hz) before the IMU sample
# (1 to 4 samples before; 2 here).  Its velocity error, as the flip mission's pos/state shows it
# against the truth: ~0.009 m/s horizontal, ~0.004 vertical (up to 0.026 and 0.02 through the
# flip), correlated over ~0.04 s; drawn somewhat larger here so that training does not over-trust it.
COMPENSATION_WINDOW = 40          # samples of DT_REF: 0.1 s
COMPENSATION_DELAY = 2            # samples
VELOCITY_NOISE_M_S = (0.012, 0.012, 0.006)
VELOCITY_NOISE_TAU_S = 0.04
# The heading that turns it into the gyro-vertical's frame: the attitude filter's yaw, 0.2 deg RMS
# from the truth through the flip mission (1.5 deg at most, in the flip); drawn larger here too.
HEADING_NOISE_RAD = math.radians(0.5)
HEADING_NOISE_TAU_S = 1.0


def _markov(rng, n: int, std, tau_s: float):
    """n samples (DT_REF apart) of a first-order Gauss-Markov process of stationary ``std``."""
    import numpy as np

    std = np.atleast_1d(np.asarray(std, dtype=np.float64))
    phi = math.exp(-DT_REF / tau_s)
    w = rng.standard_normal((n, std.size)) * std * math.sqrt(1.0 - phi * phi)
    e = np.empty_like(w)
    e[0] = rng.standard_normal(std.size) * std
    for i in range(1, n):
        e[i] = phi * e[i - 1] + w[i]
    return e


def reference_accelerations(flight: FlightData, seed: int):
    """((t, t0, t1, a), heading): the compensation's reference at every sample as
    :func:`flight.estimation.gyrovertical.fixed_windows` gives it, from the flight's true velocity plus
    a position estimate's error, and the vehicle's yaw plus an attitude filter's error (both
    first-order Gauss-Markov: VELOCITY_NOISE_*, HEADING_NOISE_*; seeded)."""
    import numpy as np

    from flight.estimation.gyrovertical import fixed_windows
    v = np.gradient(flight.position_m, DT_REF, axis=0)
    rng = np.random.default_rng([seed, 26])
    v = v + _markov(rng, len(v), VELOCITY_NOISE_M_S, VELOCITY_NOISE_TAU_S)
    heading = flight.yaw_rad + _markov(rng, len(v), HEADING_NOISE_RAD, HEADING_NOISE_TAU_S)[:, 0]
    return fixed_windows(v, DT_REF, COMPENSATION_WINDOW, COMPENSATION_DELAY), heading


def sequences_of(flights: list[FlightData], bias_deg_s: float, compensation: bool = False,
                 seed: int = 0) -> list[TrainingSequence]:
    seqs: list[TrainingSequence] = []
    for i, f in enumerate(flights):
        ref, heading = reference_accelerations(f, seed * 1000 + i) if compensation else ((None,) * 4, None)
        seqs += make_training_sequences(f.gyro_rad_s, f.accel_m_s2, f.roll_rad, f.pitch_rad, bias_deg_s=bias_deg_s,
                                        accel_ref=ref[3], heading=heading)
    return seqs


def save(path: Path, trained: TrainedParams) -> None:
    """A small TOML file: a header comment, [meta], [adaptive] and [fixed] tables."""
    def table(name: str, d: dict) -> str:
        lines = [f"[{name}]"]
        for k, v in d.items():
            lines.append(f"{k} = {v!r}" if not isinstance(v, str) else f'{k} = "{v}"')
        return "\n".join(lines)

    text = "\n\n".join([
        "# Adaptive gyro-vertical (004), trained by `zenpilot train-gyrovertical`.\n"
        "# [adaptive]: the 12 parameters of (7), read by the attitude service.\n"
        "# [fixed]: the fixed-variance baseline trained on the same data (comparison only)."
        + ("\n# [fallback]: with the compensation, the variances of a sample without a reference (not trained here)."
           if trained.fallback is not None else ""),
        table("meta", trained.meta), table("adaptive", trained.adaptive.to_dict()),
        table("fixed", trained.fixed.to_dict())]
        + ([table("fallback", trained.fallback.to_dict())] if trained.fallback is not None else [])) + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def run_training(vehicle: str, seed: int, flights: int, duration_s: float, bias_deg_s: float,
                 maxiter: int, log=print, compensation: str = "none", fallback: str | None = None) -> TrainedParams:
    """Train a file; ``fallback`` (with compensation): a parameter file whose [adaptive] becomes this
    one's [fallback], the variances of a sample without a reference (not trained here)."""
    fallback_params = None
    if fallback is not None:
        if compensation == "none":
            raise ValueError("train-gyrovertical: --fallback is for a compensated filter (--compensation window)")
        from flight.estimation.gyrovertical import load_trained
        fallback_params = load_trained(fallback).adaptive
    # imported here: it brings scipy.optimize and JAX (seconds), which every `zenpilot`
    # command would pay for at start-up (deploy/cli.py imports this module for its parser)
    from flight.estimation.gyrovertical_training import train
    t0 = time.monotonic()
    log(f"recording {flights} training flight(s) of {duration_s:g} s ({vehicle}, seed {seed}) ...")
    data = training_flights(vehicle, seed, flights, duration_s)
    comp = (COMPENSATION_WINDOW, COMPENSATION_DELAY) if compensation == "window" else None
    seqs = sequences_of(data, bias_deg_s, comp is not None, seed)
    log(f"  {len(seqs)} sequences of {len(seqs[0].roll)} samples ({time.monotonic() - t0:.1f} s)")
    results = {}
    for adaptive in (True, False):
        name = "adaptive" if adaptive else "fixed-variance"
        start = time.monotonic()

        def progress(k, cost, _params, name=name, start=start):
            if k == 1 or k % 10 == 0:
                log(f"  {name:14s} iteration {k:4d}  criterion (10) {cost:.4f} deg  ({time.monotonic() - start:.0f} s)")

        log(f"training the {name} filter (up to {maxiter} iterations) ...")
        results[adaptive] = train(seqs, GyroVerticalParams(), DT_REF, maxiter=maxiter, seed=seed,
                                  progress=progress, adaptive=adaptive, compensation=comp)
    from flight.estimation.gyrovertical_jax import BatchEvaluator
    costs = {a: BatchEvaluator(seqs, adaptive=a, compensation=comp)(results[a].to_vector()) for a in (True, False)}
    default_cost = BatchEvaluator(seqs, compensation=comp)(GyroVerticalParams().to_vector())
    log(f"criterion (10) on the training sequences: default {default_cost:.4f}, "
        f"adaptive {costs[True]:.4f}, fixed {costs[False]:.4f} deg")
    meta = {"vehicle": vehicle, "seed": seed, "flights": flights, "duration_s": float(duration_s),
            "bias_deg_s": float(bias_deg_s), "maxiter": maxiter,
            "training_cost_deg": round(float(costs[True]), 6),
            "fixed_training_cost_deg": round(float(costs[False]), 6),
            "command": (f"zenpilot train-gyrovertical --vehicle {vehicle} --seed {seed} --flights {flights} "
                        f"--duration-s {duration_s:g} --bias-deg-s {bias_deg_s:g} --maxiter {maxiter}"
                        + (f" --compensation {compensation}" if compensation != "none" else "")
                        + (f" --fallback {fallback}" if fallback is not None else ""))}
    if compensation != "none":   # the attitude service compensates a file trained so (gyrovertical_compensation)
        meta["compensation"] = compensation
    return TrainedParams(results[True], results[False], meta, fallback_params)


def add_parser(sub) -> None:
    p = sub.add_parser("train-gyrovertical", help="train the adaptive gyro-vertical (004) on simulator flights",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--vehicle", default="x250", help="vehicle profile (default x250)")
    p.add_argument("--seed", type=int, default=0, help="seed of the flights and the optimiser (default 0)")
    p.add_argument("--flights", type=int, default=2, help="number of training flights (default 2)")
    p.add_argument("--duration-s", type=float, default=300.0, help="length of each flight, s (default 300)")
    p.add_argument("--bias-deg-s", type=float, default=0.05, help="gyro bias of the sequences, deg/s (default 0.05)")
    p.add_argument("--maxiter", type=int, default=250, help="optimiser iterations per filter (default 250)")
    p.add_argument("--compensation", choices=("none", "window"), default="none",
                   help="window: train the filter with the acceleration compensation, fed the flights' "
                        "velocity change over 0.1 s with a position estimate's error (the file says so; "
                        "the attitude service then compensates it); none: 004's filter (default)")
    p.add_argument("--fallback", help="with --compensation window: a parameter file whose [adaptive] the filter "
                                      "uses for samples without a reference (written as [fallback]; not trained)")
    p.add_argument("--out", help="parameter file to write (default runs/gyrovertical-<vehicle>-seed<N>.toml)")
    p.set_defaults(func=cmd_train)


def cmd_train(args) -> int:
    for name, value, ok in (("--flights", args.flights, args.flights >= 1),
                            ("--duration-s", args.duration_s, math.isfinite(args.duration_s) and args.duration_s >= 5),
                            ("--bias-deg-s", args.bias_deg_s, math.isfinite(args.bias_deg_s) and args.bias_deg_s >= 0),
                            ("--maxiter", args.maxiter, args.maxiter >= 1)):
        if not ok:
            raise ValueError(f"train-gyrovertical: {name} {value!r} is out of range "
                             "(flights >= 1, duration >= 5 s, bias >= 0, maxiter >= 1)")
    load_vehicle(args.vehicle)   # refuse a bad vehicle before minutes of flying
    if args.fallback is not None:   # and a bad fallback
        if args.compensation == "none":
            raise ValueError("train-gyrovertical: --fallback is for a compensated filter (--compensation window)")
        from flight.estimation.gyrovertical import load_trained
        load_trained(args.fallback)
    out = Path(args.out or f"runs/gyrovertical-{args.vehicle}-seed{args.seed}.toml")
    trained = run_training(args.vehicle, args.seed, args.flights, args.duration_s, args.bias_deg_s,
                           args.maxiter, log=lambda s: print(s, flush=True), compensation=args.compensation,
                           fallback=args.fallback)
    save(out, trained)
    print(f"wrote {out}; fly it with --set attitude.gyrovertical_params={out}, or copy it into flight/params/ "
          f"and name it in flight/vehicles/{args.vehicle}.toml (gyrovertical_params = \"NAME.toml\")", file=sys.stdout)
    return 0


# ---------------------------------------------------------------- evaluation on control flights
ESTIMATORS = ("integration", "fixed", "adaptive", "kalman-000")


def control_flight(vehicle_name: str, seed: int, duration_s: float) -> FlightData:
    """A control-menu flight (figure-eights, sprints, doublets, climbs, a flip) never used in training."""
    n = int(round(duration_s / DT_REF))
    return record(load_vehicle(vehicle_name), "control", duration_s, seed=10_000 + seed).slice(n)


def estimate(flight: FlightData, estimator: str, trained: TrainedParams,
             bias_rad_s=(0.0, 0.0, 0.0), vehicle_name: str = "x250", compensation: bool | None = None,
             seed: int = 0):
    """(roll, pitch) estimates (N,) of one estimator on a flight whose gyros carry ``bias_rad_s``.

    compensation ('fixed', 'adaptive'): the acceleration compensation fed :func:`reference_accelerations`
    (its error drawn from ``seed``); None: as the file was trained (its meta's compensation).
    Every estimator starts from the true attitude and sees the same samples;
    'kalman-000' is the attitude filter of 000 as printed (raw accelerometer
    angles, the recorded torques, 200 Hz calls with the two samples since the last).
    """
    import numpy as np

    from flight.estimation.gyrovertical import GyroIntegrator, run_sequence
    from flight.quat import quat_from_euler

    gyro = flight.gyro_rad_s + np.asarray(bias_rad_s, dtype=np.float64)
    q0 = quat_from_euler(float(flight.roll_rad[0]), float(flight.pitch_rad[0]), float(flight.yaw_rad[0]))
    if estimator == "integration":
        return run_sequence(GyroIntegrator(DT_REF, q0), gyro, flight.accel_m_s2)
    if estimator in ("fixed", "adaptive"):
        import jax.numpy as jnp

        from flight.estimation.gyrovertical_jax import run_batch
        if compensation is None:
            compensation = trained.meta.get("compensation", "none") == "window"
        params, fallback = trained.flown(compensation)
        if estimator == "fixed":
            params, fallback = trained.fixed, None
        ref = heading = None
        if compensation:
            (_, _, _, ref), heading = reference_accelerations(flight, seed)
            ref, heading = jnp.asarray(ref[None]), jnp.asarray(heading[None])
        fallback = jnp.asarray(fallback.to_vector()) if fallback is not None else None
        r, p = run_batch(jnp.asarray(params.to_vector()), jnp.asarray(gyro[None]),
                         jnp.asarray(flight.accel_m_s2[None]), jnp.asarray(q0[None]), ref, heading, fallback,
                         adaptive=estimator == "adaptive", window=COMPENSATION_WINDOW if compensation else 0,
                         delay=COMPENSATION_DELAY if compensation else 0)
        return np.asarray(r[0], dtype=np.float64), np.asarray(p[0], dtype=np.float64)
    if estimator == "kalman-000":
        from flight.estimation.attitude_filter import AttitudeFilter
        filt = AttitudeFilter(load_vehicle(vehicle_name).inertia_kg_m2)
        roll, pitch = np.empty(len(gyro)), np.empty(len(gyro))
        for i in range(1, len(gyro), 2):   # one 200 Hz call per two IMU samples, estimate at the newer one
            t = float(flight.t_s[i])
            samples = [(float(flight.t_s[j]), gyro[j], flight.accel_m_s2[j]) for j in (i - 1, i)]
            est = filt.update(samples, None, flight.torque_nm[i - 1], t)
            roll[i - 1:i + 1], pitch[i - 1:i + 1] = est.euler_rad[0], est.euler_rad[1]
        if len(gyro) % 2:
            roll[-1], pitch[-1] = roll[-2], pitch[-2]
        return roll, pitch
    raise ValueError(f"gyrovertical: estimator must be one of {ESTIMATORS}, got {estimator!r}")


def manoeuvring(flight: FlightData, threshold: float = 0.05):
    """Samples where the load factor is more than ``threshold`` away from 1 g (low-passed over 0.1 s)."""
    import numpy as np

    n = np.linalg.norm(flight.accel_m_s2, axis=1) / 9.80665
    k = int(0.1 / DT_REF)
    smooth = np.convolve(n, np.ones(k) / k, mode="same")
    return np.abs(smooth - 1.0) > threshold


def tilt_error_deg(flight: FlightData, roll, pitch):
    """Per-sample (roll, pitch) errors, degrees, wrapped."""
    import numpy as np

    from flight.quat import wrap_angle as wrap
    return np.degrees(wrap(roll - flight.roll_rad)), np.degrees(wrap(pitch - flight.pitch_rad))
