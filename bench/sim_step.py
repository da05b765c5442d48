"""Time of the simulator's 400 Hz tick and of the motor driver's per-step mixing, against
the 2.5 ms period they must fit in, with the former numpy implementation as the baseline.

    python bench/sim_step.py [--vehicle x250] [--ticks 2000] [--calls 20000] [--rounds 5]

Per tick: Simulator.outputs() + Simulator.step() (5 RK4 substeps, the sensors due at that
tick, the truth, the battery; no Zenoh), hovering in the air and resting on the ground.
Per call: the mixer and the helpers services/motors.py calls every step. Each figure is the
best of --rounds rounds (mean per tick or call within a round); "old" is
bench/support/sim_reference.py (the numpy code before the float rewrite), run in the same
process on the same inputs, the two alternating round by round.

A second table times the sensor outputs against zenpilot 6b2add1's tick
(bench/support/sim_6b2add1.py: the IMU's noise drawn per sample, every marker of the grid
projected): Simulator.outputs() alone per tick (step() run between, untimed), and one
camera frame (MarkerCamera.sample) at a few poses; the messages of the two are compared.
"""
from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.support.sim_6b2add1 import Simulator6b2add1  # noqa: E402
from bench.support.sim_reference import (RefMarkerCamera, RefPlant, RefSimulator, ref_mix,  # noqa: E402
                                         ref_motor_forces_update, ref_scale_collective, ref_thrust_to_pwm)
from flight.control.mixer import mix  # noqa: E402
from flight.control.plan import scale_collective  # noqa: E402
from flight.motor_model import thrust_to_pwm  # noqa: E402
from flight.quat import quat_from_euler  # noqa: E402
from flight.motor_model import thrust_step as motor_forces_update  # noqa: E402
from flight.vehicle import load_vehicle  # noqa: E402
from simulator import SimConfig, Simulator  # noqa: E402
from simulator.plant import Plant  # noqa: E402
from simulator.sensors import MarkerCamera  # noqa: E402

PERIOD_US = 1e6 / 400.0


def best_us(fn, n: int, rounds: int, other=None, other_best=None) -> float:
    """Best mean time per call of fn over `rounds` rounds of n calls (alternating with other)."""
    best = float("inf")
    for _ in range(rounds):
        t0 = time.perf_counter()
        fn(n)
        best = min(best, (time.perf_counter() - t0) / n * 1e6)
        if other is not None:
            t0 = time.perf_counter()
            other(n)
            other_best[0] = min(other_best[0], (time.perf_counter() - t0) / n * 1e6)
    return best


def pair_us(new, old, n: int, rounds: int) -> tuple[float, float]:
    old_best = [float("inf")]
    return best_us(new, n, rounds, old, old_best), old_best[0]


def sim_loop(sim_cls, vehicle, cfg, pwm, armed):
    sim = sim_cls(vehicle, cfg, seed=0)
    for _ in range(40):  # past the first camera frame and truth
        sim.outputs()
        sim.step(pwm, armed)

    def run(n):
        for _ in range(n):
            sim.outputs()
            sim.step(pwm, armed)
    return run


def outputs_loop(sim_cls, vehicle, cfg, pwm, armed, sent):
    """Simulator.outputs() timed alone (step() between, untimed); the messages kept in `sent`."""
    sim = sim_cls(vehicle, cfg, seed=0)
    for _ in range(40):
        sim.outputs()
        sim.step(pwm, armed)

    def run(n):
        pc, total = time.perf_counter, 0.0
        outputs, step = sim.outputs, sim.step
        for _ in range(n):
            t0 = pc()
            msgs = outputs()
            total += pc() - t0
            sent.append(msgs)
            step(pwm, armed)
        return total
    return run


def pair_timed_us(new, old, n: int, rounds: int) -> tuple[float, float]:
    """As pair_us for runs that return the seconds they timed themselves."""
    best_new = best_old = float("inf")
    for _ in range(rounds):
        best_new = min(best_new, new(n) / n * 1e6)
        best_old = min(best_old, old(n) / n * 1e6)
    return best_new, best_old


def calls(fn, *args):
    def run(n):
        for _ in range(n):
            fn(*args)
    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicle", default="x250")
    ap.add_argument("--ticks", type=int, default=2000, help="simulator ticks per round (default 2000 = 5 s)")
    ap.add_argument("--calls", type=int, default=20000, help="calls per round for the per-call rows")
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    print("$ python " + " ".join(shlex.quote(a) for a in sys.argv))
    v = load_vehicle(args.vehicle)
    hover = v.hover_thrust_per_motor_n
    hover_pwm = thrust_to_pwm(v, np.full(4, hover))
    air = SimConfig(initial_position_m=(0.0, 0.0, 1.0))
    rows = []

    def row(name, new, old, n):
        t_new, t_old = pair_us(new, old, n, args.rounds)
        rows.append((name, t_new, t_old))

    row("sim tick: outputs+step, hover in the air", sim_loop(Simulator, v, air, hover_pwm, True),
        sim_loop(RefSimulator, v, air, hover_pwm, True), args.ticks)
    row("sim tick: outputs+step, resting disarmed", sim_loop(Simulator, v, SimConfig(), [1000.0] * 4, False),
        sim_loop(RefSimulator, v, SimConfig(), [1000.0] * 4, False), args.ticks)
    gusty = SimConfig(initial_position_m=(0.0, 0.0, 1.0), gust_std_m_s=0.5, camera_drop_rate=0.1)
    row("sim tick: outputs+step, gusts + drops", sim_loop(Simulator, v, gusty, hover_pwm, True),
        sim_loop(RefSimulator, v, gusty, hover_pwm, True), args.ticks)

    new_p, old_p = Plant(v, position_m=(0, 0, 100.0)), RefPlant(v, position_m=(0, 0, 100.0))
    cmd, wind = np.full(4, hover), np.array([1.0, 0.0, 0.0])

    def old_substeps(n):
        for _ in range(n):
            for _ in range(5):
                old_p.step(0.0005, cmd, wind)
    row("plant: 5 RK4 substeps (one tick)", calls(new_p.advance, 0.0005, 5, cmd, wind), old_substeps, args.ticks)

    torque = [0.01, -0.02, 0.003]
    row("mix, unsaturated", calls(mix, v, 4 * hover, torque), calls(ref_mix, v, 4 * hover, torque), args.calls)
    big = [1.0, 0.5, 0.01]
    row("mix, roll/pitch saturated", calls(mix, v, 4 * hover, big), calls(ref_mix, v, 4 * hover, big), args.calls)
    forces = mix(v, 4 * hover, torque)[0]
    row("thrust_to_pwm", calls(thrust_to_pwm, v, forces), calls(ref_thrust_to_pwm, v, forces), args.calls)
    a = v.allocation
    row("scale_collective", calls(scale_collective, a, forces, 1.01), calls(ref_scale_collective, a, forces, 1.01),
        args.calls)
    held = np.zeros(4)
    row("motor_forces_update", calls(motor_forces_update, held, forces, 0.0025, 0.02),
        calls(ref_motor_forces_update, held, forces, 0.0025, 0.02), args.calls)

    def driver(mix_fn, pwm_fn, scale_fn, lag_fn):
        def run(n):
            h = np.zeros(4)
            for _ in range(n):
                f, _ = mix_fn(v, 4 * hover, torque)
                pwm_fn(v, f)
                h = lag_fn(h, scale_fn(a, f, 1.01), 0.0025, 0.02)
        return run
    row("motor driver step: mix+pwm+scale+lag", driver(mix, thrust_to_pwm, scale_collective, motor_forces_update),
        driver(ref_mix, ref_thrust_to_pwm, ref_scale_collective, ref_motor_forces_update), args.calls)

    print(f"vehicle {v.name}, best of {args.rounds} rounds; period 2.5 ms (400 Hz)")
    w = max(len(r[0]) for r in rows)
    print(f"{'':{w}}  {'new us':>8}  {'old us':>8}  {'old/new':>7}  {'new %':>6}  {'old %':>6}")
    for name, t_new, t_old in rows:
        print(f"{name:{w}}  {t_new:8.2f}  {t_old:8.2f}  {t_old / t_new:6.1f}x  {100 * t_new / PERIOD_US:5.2f}%  "
              f"{100 * t_old / PERIOD_US:5.2f}%")

    # against 6b2add1: the sensor outputs
    rows, same = [], True
    for name, cfg, pwm, armed in (("outputs per tick, hover at 1 m", air, hover_pwm, True),
                                  ("outputs per tick, gusts + drops", gusty, hover_pwm, True),
                                  ("outputs per tick, resting disarmed", SimConfig(), [1000.0] * 4, False)):
        sent_new, sent_old = [], []
        t_new, t_old = pair_timed_us(outputs_loop(Simulator, v, cfg, pwm, armed, sent_new),
                                     outputs_loop(Simulator6b2add1, v, cfg, pwm, armed, sent_old),
                                     args.ticks, args.rounds)
        same = same and sent_new == sent_old
        rows.append((name, t_new, t_old))
    for name, height, euler in (("camera frame, 1 m, level", 1.0, (0.02, -0.01, 0.3)),
                                ("camera frame, 1 m, 15 deg roll", 1.0, (0.26, 0.0, 0.3)),
                                ("camera frame, 3 m, level", 3.0, (0.02, -0.01, 0.3))):
        pos, q = np.array([0.2, -0.1, height]), quat_from_euler(*euler)
        cam_new, cam_old = MarkerCamera(air, np.random.default_rng(1)), RefMarkerCamera(air, np.random.default_rng(1))
        same = same and cam_new.sample(pos, q) == cam_old.sample(pos, q)
        rows.append((name, *pair_us(calls(cam_new.sample, pos, q), calls(cam_old.sample, pos, q),
                                    max(args.ticks // 10, 1), args.rounds)))
    print(f"\nthe sensor outputs against zenpilot 6b2add1 (bench/support/sim_6b2add1.py), best of {args.rounds} rounds")
    w = max(len(r[0]) for r in rows)
    print(f"{'':{w}}  {'new us':>8}  {'6b2add1':>8}  {'ratio':>7}")
    for name, t_new, t_old in rows:
        print(f"{name:{w}}  {t_new:8.2f}  {t_old:8.2f}  {t_old / t_new:6.2f}x")
    print("messages and frames: " + ("identical" if same else "DIFFER from 6b2add1's"))


if __name__ == "__main__":
    main()
