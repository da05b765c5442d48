"""The thesis's flip (001's configuration: THESIS weights, 20 Hz, its phase machine) on the
simulator's plant, truth state, at other flip durations and heights than the printed ones.

    .venv/bin/python bench/flip_thesis_durations.py 1.0,5 1.0,20 1.5,20 2.0,20   # T s, altitude m
"""
import dataclasses, sys, time
sys.path.insert(0, str(__import__('pathlib').Path(__file__).resolve().parents[1]))
from bench.flip_sim import simulate_mpc, _report
from flight.control.ilqr import THESIS, ILQRSolver
from flight.control.flip import THESIS_FLIP
from flight.vehicle import load_vehicle
v = load_vehicle("q820")
planner = ILQRSolver(v, THESIS)
for arg in sys.argv[1:]:
    T, H = (float(x) for x in arg.split(","))
    flip = dataclasses.replace(THESIS_FLIP, flip_duration_s=T, flip_altitude_m=H)
    t = time.time()
    r = simulate_mpc(v, planner, flip, 20.0, max_time_s=30.0)
    print(_report(f"thesis T={T} H={H}", r), f"({time.time()-t:.0f} s)", flush=True)
