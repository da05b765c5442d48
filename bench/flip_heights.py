"""Heights and excursions through a flown flip, from flight logs (bench/flip_stack.py's --out dirs).

    .venv/bin/python bench/flip_heights.py runs/flip-grid/ilqr-project-nominal-seed*

metrics.json's altitude_loss_m is the flip's reported loss: from the hover altitude before the flip
phase (the baseline's from the roll's start: its full-thrust climb counts as take-off).
A flip that climbs before its turn can be judged by more than that; per flight, on the
simulator truth (sim/truth) from the flip phase's start (planner/setpoint's phase):

    roll+3     height where the accumulated roll passes 3 deg (the turn's start), above the start
    peak       highest point until recovery ends, above the start
    lowest     lowest point after the peak until recovery ends, above the start (-loss)
    turn_loss  the turn's start minus that lowest point: the loss measured from the roll
    fall       the peak minus that lowest point
    excursion  farthest horizontal distance from the flip's start to the log's end (the hold
               after the recovery included, which metrics.json's xy_drift_m is not)
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from flight.control.flip import Phase, RollAccumulator, heights  # noqa: E402
from schemas.flightlog import read_log  # noqa: E402

FIELDS = ("roll+3", "peak", "lowest", "turn_loss", "fall", "excursion")


def flip_heights(flight_dir: Path) -> dict[str, float]:
    flip = json.loads((flight_dir / "metrics.json").read_text())["flip"]
    if not flip or not flip.get("completed"):
        raise ValueError(f"{flight_dir}: no completed flip in metrics.json")
    log = read_log(flight_dir / "flight.mcap")
    truth = [m for k, v in log.items() if k.endswith("/sim/truth") for m in v]
    setpoints = [m for k, v in log.items() if k.endswith("/planner/setpoint") for m in v]
    if not truth or not setpoints:
        raise ValueError(f"{flight_dir}: flight.mcap has no sim/truth or planner/setpoint")
    t = np.array([m["header"]["t_s"] for m in truth])
    position = np.array([m["position_m"] for m in truth])
    flip_t_s = next(m["header"]["t_s"] for m in setpoints if m.get("phase") == Phase.FLIP.value)
    start = int(np.searchsorted(t, flip_t_s))
    end = int(np.searchsorted(t, t[start] + flip["duration_s"]))
    roll = RollAccumulator()
    roll.reset(truth[start]["quaternion_wxyz"])
    rolls = np.array([roll.update(m["quaternion_wxyz"]) for m in truth[start:end + 1]])
    return {
        **heights(position[start:end + 1, 2] - position[start, 2], rolls),
        "excursion": float(np.max(np.linalg.norm(position[start:, :2] - position[start, :2], axis=1))),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("flight_dirs", nargs="+", type=Path, help="flight directories (each with metrics.json and flight.mcap)")
    dirs = parser.parse_args(argv).flight_dirs
    print("$ .venv/bin/python bench/flip_heights.py " + " ".join(str(d) for d in dirs))
    rows = []
    for d in sorted(dirs):
        try:
            h = flip_heights(d)
        except (OSError, ValueError, KeyError, StopIteration) as exc:
            print(f"{d}: skipped ({exc!r})")
            continue
        rows.append(h)
        print(f"{d.name:40s} " + " ".join(f"{k} {h[k]:+.3f}" for k in FIELDS))
    if rows:
        print(f"median (worst) over {len(rows)} flights: " + ", ".join(
            f"{k} {statistics.median(r[k] for r in rows):+.2f} "
            f"({(min if k == 'lowest' else max)(r[k] for r in rows):+.2f})" for k in FIELDS))
    return 0 if rows else 1


if __name__ == "__main__":
    sys.exit(main())
