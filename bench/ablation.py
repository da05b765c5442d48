"""Ablation of the cascade of 000: what each part buys.

    python bench/ablation.py [--mission steps] [--out runs/ablation]

Flies the mission in lockstep (seed 0) once per configuration, every row
with a 10 ms IMU transport delay (so the attitude extrapolator has a delay to
compensate, as on the paper's bus) and the default 50 ms camera delay unless
the row says otherwise, then writes docs/ablation.md and docs/img/ablation.png.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from bench.support import flying  # noqa: E402

from flight.estimation.attitude_filter import FILTER_000  # noqa: E402


def _inline_table(d: dict) -> str:
    """A dict of numbers, booleans and tuples as a TOML inline table (a --set value)."""
    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (tuple, list)):
            return "[" + ",".join(value(e) for e in v) + "]"
        return repr(v)
    return "{" + ",".join(f"{k}={value(v)}" for k, v in d.items()) + "}"


COMMON = ["--set", "sim.imu_latency_s=0.01"]
TRUTH = ["--set", "attitude.state_source=truth", "--set", "position.state_source=truth",
         "--set", "sim.truth_rate_hz=200"]
ROWS = [
    ("truth state", TRUTH),
    ("full cascade", []),
    ("without extrapolator / delayed fusion", ["--set", "attitude.filter={extrapolate=false}",
                                               "--set", "position.fuse_camera_at_exposure=false"]),
    ("without the filter lag in the model", ["--set", "attitude.filter={model_filter_lag=false}"]),
    ("camera delay 100 ms", ["--set", "sim.camera_latency_s=0.1"]),
    ("camera delay 150 ms", ["--set", "sim.camera_latency_s=0.15"]),
    ("camera dropping 20 % of frames", ["--set", "sim.camera_drop_rate=0.2"]),
    ("without the camera level (accelerometer bias left in roll/pitch)", ["--set", "attitude.camera_level=false"]),
    # 000 has no camera at the attitude level
    ("000 as printed: no acceleration compensation", ["--set", "attitude.compensate_acceleration=false",
                                                      "--set", "attitude.camera_level=false"]),
    ("filter of 000 (no gyro-bias state, body rate as Euler rate), velocity-slope compensation",
     ["--set", "attitude.filter=" + _inline_table(FILTER_000), "--set", 'attitude.acceleration_compensation="slope"',
      "--set", "attitude.camera_level=false"]),
]


def fmt(v, scale=1.0, digits=3):
    return "-" if v is None else f"{v * scale:.{digits}g}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mission", default="steps")
    ap.add_argument("--out", default="runs/ablation")
    args = ap.parse_args()
    results = []
    for i, (name, extra) in enumerate(ROWS):
        out = Path(args.out) / f"{i}"
        proc = flying.fly(["--lockstep", "--mission", args.mission, "--out", str(out), *COMMON, *extra],
                          f"row {i + 1}/{len(ROWS)} {name}")
        m = json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").exists() else {}
        est = m.get("estimation") or {}
        results.append((name, m.get("completed", False), m.get("position_rms_m"), m.get("max_position_error_m"),
                        est.get("position_rms_m"), est.get("attitude_rms_deg"), est.get("nees_mean"),
                        m.get("position_step_settle_s_max")))
        print(f"{name:<48} completed={m.get('completed')} rc={proc.returncode}", flush=True)

    lines = [
        f"# Ablation of the cascade (mission `{args.mission}`, lockstep, seed 0, IMU delay 10 ms)",
        "",
        f"Produced by `python bench/ablation.py --mission {args.mission}`.",
        "Hold RMS: truth against the reference over the measured holds. Estimation: truth against "
        "the estimates the controllers used, whole flight while airborne.",
        "",
        "| configuration | completed | hold RMS (m) | max hold error (m) | estimate position RMS (m) "
        "| estimate attitude RMS (deg) | NEES mean | worst step settle (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, done, rms, mx, erms, arms, nees, settle in results:
        lines.append(f"| {name} | {'yes' if done else 'no'} | {fmt(rms)} | {fmt(mx)} | {fmt(erms)} | "
                     f"{fmt(arms)} | {fmt(nees)} | {fmt(settle)} |")
    (ROOT / "docs" / "ablation.md").write_text("\n".join(lines) + "\n")

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    names = [r[0] for r in results]
    y = range(len(names))
    ax[0].barh(y, [r[2] or 0 for r in results], color="tab:blue")
    ax[0].set_yticks(list(y), names)
    ax[0].set_xscale("log")
    ax[0].set_xlabel("hold RMS, truth vs reference [m]")
    ax[0].invert_yaxis()
    ax[1].barh(y, [r[5] or 0 for r in results], color="tab:orange")
    ax[1].set_yticks(list(y), [""] * len(names))
    ax[1].set_xlabel("attitude estimate RMS [deg]")
    ax[1].invert_yaxis()
    for a in ax:
        a.grid(True, axis="x", alpha=0.4)
    fig.suptitle(f"Ablation of the cascade of 000 (mission {args.mission}, lockstep)")
    fig.tight_layout()
    fig.savefig(ROOT / "docs" / "img" / "ablation.png", dpi=100)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
