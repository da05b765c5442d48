"""iLQR solve time: the project's solver against the thesis's code, same process.

    .venv/bin/python bench/ilqr.py

Both solve the same problem (THESIS setting: dt 0.1 s, horizon 10, 5 iterations, from
a hover 0.5 m below and 0.3 m beside the target). The thesis's solver is forced to its
5 iterations (tol 0) so both do the same amount of work; the project's runs its
5 iterations (relative tolerance 0). Prints compile times, median solve times over
alternating rounds and the median of the rounds' ratios, timed two ways: on the device
(the same device arrays in, every output computed: how the thesis's code is timed)
and end to end (numpy in, numpy out, as the planner service calls it), then the PROJECT configuration's
solve time and MPC rate; then the planner's start-up in a fresh process: compiling, and
loading from the compile cache the planner service keeps (flight.control.ilqr.use_compile_cache).
"""
from __future__ import annotations

import dataclasses
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# XLA reads its flags at the process's first JAX operation, and bench.ilqr_thesis computes its
# weight matrices (JAX) on import: the small-loop option the planner flies with is asked for
# first, as the planner's first ILQRSolver does ("loops compiled whole" says whether it took).
from flight.control.ilqr import (PROJECT, THESIS, ILQRSolver, hover_state, request_small_loop_hoisting,  # noqa: I001
                                 solver_compiler_options, warm_start)
request_small_loop_hoisting()
from bench.ilqr_thesis import make_thesis_ilqr  # noqa: E402
from flight.vehicle import load_vehicle


def median_time(fn, calls: int = 20) -> float:
    times = []
    for _ in range(calls):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def paired_times(fn_a, fn_b, rounds: int = 15, calls: int = 40) -> tuple[float, float, float]:
    """Medians of fn_a and fn_b over alternating rounds (this machine's load drifts within
    seconds): (median time of a, median time of b, median of the per-round ratios b / a)."""
    a, b = [], []
    for _ in range(rounds):
        a.append(median_time(fn_a, calls))
        b.append(median_time(fn_b, calls))
    return float(np.median(a)), float(np.median(b)), float(np.median(np.array(b) / np.array(a)))


def problem(horizon: int):
    x0 = hover_state([0.3, 0.0, 4.5])
    targets = np.repeat(hover_state([0.0, 0.0, 5.0])[None], horizon + 1, axis=0)
    return x0, targets


STARTUP = """
import sys, time
sys.path.insert(0, {root!r})
from flight.control.ilqr import {config}, ILQRSolver, use_compile_cache
from flight.vehicle import load_vehicle
use_compile_cache({cache!r})
vehicle = load_vehicle("q820")
t0 = time.perf_counter()
ILQRSolver(vehicle, {config})
print(time.perf_counter() - t0)
"""


def startup_s(config: str, cache_dir: str) -> float:
    """Seconds to build and warm up an ILQRSolver in a fresh process with this cache."""
    code = STARTUP.format(root=str(Path(__file__).resolve().parents[1]), config=config, cache=cache_dir)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(out.stdout.split()[-1])


def main() -> None:
    print("$ .venv/bin/python bench/ilqr.py")
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}")
    vehicle = load_vehicle("q820")
    fixed_thesis = dataclasses.replace(THESIS, relative_tolerance=0.0)

    t0 = time.perf_counter()
    planner = ILQRSolver(vehicle, fixed_thesis)
    compile_project_s = time.perf_counter() - t0
    x0, targets = problem(THESIS.horizon)
    u_hover = planner.hover_controls()
    iterations = planner.solve(x0, targets).iterations

    thesis_solve = make_thesis_ilqr(vehicle, THESIS.dt_s, THESIS.horizon)
    args = (jnp.asarray(x0, jnp.float32), jnp.asarray(u_hover, jnp.float32),
            jnp.asarray(targets, jnp.float32), jnp.asarray(u_hover, jnp.float32))

    def thesis_once():
        *_, cost = thesis_solve(*args, tol=0.0)
        cost.block_until_ready()

    def thesis_host():  # numpy in, numpy out, as ILQRSolver.solve
        host_args = [np.asarray(a, np.float32) for a in (x0, u_hover, targets, u_hover)]
        states, controls, _, cost = thesis_solve(*host_args, tol=0.0)
        return np.asarray(states, np.float64), np.asarray(controls, np.float64), float(cost)

    def project_once():  # the jitted solve on the same device arrays, every output ready
        jax.block_until_ready(planner._solve(*args, *planner._stops))

    t0 = time.perf_counter()
    thesis_once()
    compile_thesis_s = time.perf_counter() - t0
    project_s, thesis_s, ratio = paired_times(project_once, thesis_once)
    project_host_s, thesis_host_s, ratio_host = paired_times(lambda: planner.solve(x0, targets), thesis_host)
    options = solver_compiler_options()
    if options:  # the project's XLA options given to the thesis code too: what they are worth to it
        thesis_tuned = make_thesis_ilqr(vehicle, THESIS.dt_s, THESIS.horizon, compiler_options=options)
        thesis_tuned(*args, tol=0.0)[-1].block_until_ready()
        tuned_s, _, tuned_ratio = paired_times(lambda: thesis_tuned(*args, tol=0.0)[-1].block_until_ready(),
                                               thesis_once, rounds=5)

    print(f"THESIS setting (dt {THESIS.dt_s} s, horizon {THESIS.horizon}, {iterations} iterations; "
          f"{planner.loops_compiled_whole()} of the solve's loops compiled whole):")
    print(f"  compile: project {compile_project_s:.1f} s (target < 5 s), thesis code {compile_thesis_s:.1f} s")
    print(f"  solve on the device (device arrays in, outputs ready, as the thesis code is timed): project "
          f"{1e3 * project_s:.2f} ms, thesis code {1e3 * thesis_s:.2f} ms, ratio {ratio:.1f}x (target >= 10x)")
    print(f"  solve end to end (numpy in, numpy out: ILQRSolver.solve): project {1e3 * project_host_s:.2f} ms, "
          f"thesis code {1e3 * thesis_host_s:.2f} ms, ratio {ratio_host:.1f}x")
    print("  (medians over 15 alternating rounds of 40 calls; the machine's load drifts within seconds)")
    if options:
        print(f"  the project's XLA options {options} given to the thesis code too: {1e3 * tuned_s:.2f} ms "
              f"({tuned_ratio:.2f}x its defaults' speed), project ratio against it {tuned_s / project_s:.1f}x")

    t0 = time.perf_counter()
    project = ILQRSolver(vehicle, PROJECT)
    compile_s = time.perf_counter() - t0
    x0, targets = problem(PROJECT.horizon)
    plan = project.solve(x0, targets)
    warm_s = median_time(lambda: project.solve(x0, targets, warm=warm_start(plan, PROJECT.dt_s)))
    cold_s = median_time(lambda: project.solve(x0, targets))
    print(f"PROJECT (dt {PROJECT.dt_s} s, horizon {PROJECT.horizon}, <= {PROJECT.max_iterations} iterations, "
          f"{PROJECT.integrator}, {project.loops_compiled_whole()} loops compiled whole): compile {compile_s:.1f} s, solve cold {1e3 * cold_s:.2f} ms, "
          f"warm {1e3 * warm_s:.2f} ms -> MPC up to {1.0 / cold_s:.0f} Hz (cold) / {1.0 / warm_s:.0f} Hz (warm)")
    with tempfile.TemporaryDirectory() as cache:
        for config in ("THESIS", "PROJECT"):
            first, again = startup_s(config, cache), startup_s(config, cache)
            print(f"planner start-up, {config}: compile {first:.1f} s, from the compile cache {again:.2f} s")


if __name__ == "__main__":
    main()
