"""Position hold in a steady wind with gusts, on the stack's estimates (target: RMS <= 3 cm).

    python bench/gust_hold.py [--seeds 0 1 2] [--ki 0 16] [--wind 2 0 0] [--gust-std 0.5]
                              [--model gauss-markov|dryden] [--w20 0] [--observer 3] [--wind-estimation]
                              [--set KEY=VALUE ...]

Flies the hover mission in lockstep for each seed and each `position.hold_ki` (0: laws (10) as
000 has them, no integral), in a steady wind plus the simulator's gusts: Gauss-Markov (std per
axis, 2 s correlation) or Dryden (MIL-F-8785C low altitude at the 1 m hover, --w20 the wind 20 ft
up that sets its intensity, 0: the mean wind's by the spec's log profile; 7.72 m/s is its
"light"), and prints the hold's position RMS and worst error from metrics.json. --observer: the
disturbance observer's bandwidth (position.disturbance_bandwidth_rad_s; omitted: the default, off).
--wind-estimation: position.wind_estimation = true (the EKF's disturbance states, fed forward).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from bench.support import flying  # noqa: E402
TARGET_RMS_M = 0.03


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--ki", type=float, nargs="+", default=[0.0, 16.0])
    ap.add_argument("--wind", type=float, nargs=3, default=[2.0, 0.0, 0.0], metavar=("X", "Y", "Z"))
    ap.add_argument("--gust-std", type=float, default=0.5, help="Gauss-Markov: std per axis, m/s")
    ap.add_argument("--model", choices=("gauss-markov", "dryden"), default="gauss-markov")
    ap.add_argument("--w20", type=float, default=0.0, help="Dryden: W20, m/s (0: from the mean wind)")
    ap.add_argument("--observer", type=float, default=None, help="disturbance observer bandwidth, rad/s")
    ap.add_argument("--wind-estimation", action="store_true", help="position.wind_estimation = true")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="more stack settings")
    ap.add_argument("--out", default="runs/bench-gust-hold")
    args = ap.parse_args()
    print("$ python bench/gust_hold.py " + " ".join(sys.argv[1:]))
    if args.model == "dryden":
        gusts = ["--set", "sim.gust_model=dryden", "--set", f"sim.gust_w20_m_s={args.w20}"]
        what = f"Dryden gusts (W20 {args.w20:g} m/s{', from the mean wind' if not args.w20 else ''})"
    else:
        gusts = ["--set", f"sim.gust_std_m_s={args.gust_std}"]
        what = f"Gauss-Markov gusts {args.gust_std} m/s std"
    extra = [a for kv in args.set for a in ("--set", kv)]
    if args.wind_estimation:
        extra += ["--set", "position.wind_estimation=true"]
    if args.observer is not None:
        extra += ["--set", f"position.disturbance_bandwidth_rad_s={args.observer}"]
    print(f"wind {args.wind} m/s, {what}; target RMS <= {TARGET_RMS_M * 100:.0f} cm\n")
    print("| hold_ki | seed | position RMS cm | worst cm | completed |")
    print("|---|---|---|---|---|")
    for ki in args.ki:
        for seed in args.seeds:
            out = Path(args.out) / f"ki{ki:g}-seed{seed}"
            proc = flying.fly(
                ["--lockstep", "--mission", "hover", "--seed", str(seed),
                 "--out", str(out), "--no-plots", "--set", f"sim.wind_m_s={list(args.wind)}",
                 *gusts, "--set", f"position.hold_ki={ki}", *extra],
                f"hold_ki {ki:g} seed {seed}")
            if proc.returncode:
                print(f"| {ki:g} | {seed} | flight failed (status {proc.returncode}) | | |")
                continue
            m = json.loads((out / "metrics.json").read_text())
            print(f"| {ki:g} | {seed} | {100 * m['position_rms_m']:.2f} | {100 * m['max_position_error_m']:.2f} "
                  f"| {m['completed'] and not m['crashed']} |", flush=True)


if __name__ == "__main__":
    main()
