"""The adaptive gyro-vertical (004) against its baselines on control flights.

    python bench/gyrovertical.py [--params FILE] [--quick]

Control flights are simulator flights of the "control" manoeuvre menu
(figure-eights, sprints, attitude doublets, climbs, a flip) with seeds that
training never used.  Every estimator sees the same IMU samples, with a
constant gyro bias of +0.05 deg/s on each axis unless said otherwise, and
starts from the true attitude:

* integration  - model 1 of 004 alone (quaternion integration of the gyros);
* fixed        - the same filter with fixed variances, trained on the same data;
* adaptive     - the gyro-vertical of 004 with the trained parameters;
* kalman-000   - the attitude filter of 000 (accelerometer angles, as printed).

Writes docs/gyrovertical.md (the table) and three figures in docs/img/:
pitch and its error over a flight (004 fig. 2), RMS error against gyro bias
(004 fig. 4) and error against flight duration (a 10-minute flight).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from deploy.gyrovertical_training import (ESTIMATORS, control_flight, estimate,  # noqa: E402
                                          manoeuvring, tilt_error_deg)
from flight.estimation.gyrovertical import PAPER_PARAMS_FILE, load_trained  # noqa: E402

BIAS_DEG_S = 0.05
Q820_SECTION = "\n## The q820"
COLORS = {"integration": "tab:red", "fixed": "tab:orange", "adaptive": "tab:blue", "kalman-000": "tab:green"}


def rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", default=str(PAPER_PARAMS_FILE), help="trained parameter file")
    ap.add_argument("--quick", action="store_true", help="shorter flights (a smoke run; does not write docs/)")
    args = ap.parse_args()
    trained = load_trained(args.params)
    cmd = "python bench/gyrovertical.py" + (f" --params {args.params}" if args.params != str(PAPER_PARAMS_FILE) else "")
    print(f"$ {cmd}{' --quick' if args.quick else ''}\nparameters: {args.params} ({trained.meta.get('command', '?')})")
    short_s, long_s, seeds = (30.0, 120.0, (0,)) if args.quick else (120.0, 600.0, (0, 1, 2))
    bias = np.radians(np.full(3, BIAS_DEG_S))
    t_start = time.monotonic()

    # ---- table: three control flights + the long one, bias +0.05 deg/s on every gyro
    flights = [control_flight("x250", s, short_s) for s in seeds]
    long_flight = control_flight("x250", 99, long_s)
    rows = {e: {"roll": [], "pitch": [], "man": [], "max": []} for e in ESTIMATORS}
    traces = {}
    for i, f in enumerate(flights + [long_flight]):
        man = manoeuvring(f)
        for e in ESTIMATORS:
            r, p = estimate(f, e, trained, bias)
            er, ep = tilt_error_deg(f, r, p)
            tilt = np.hypot(er, ep)
            if f is long_flight:
                traces[e] = (er, ep)
                continue
            rows[e]["roll"].append(rms(er))
            rows[e]["pitch"].append(rms(ep))
            rows[e]["man"].append(rms(tilt[man]))
            rows[e]["max"].append(float(np.max(tilt)))
            if i == 0:
                traces.setdefault("first", {})[e] = (r, p)
        print(f"  flight {i + 1}/{len(flights) + 1} done ({time.monotonic() - t_start:.0f} s)", flush=True)
    man_share = float(np.mean(np.concatenate([manoeuvring(f) for f in flights])))

    # ---- error against duration on the long flight (RMS tilt error per minute)
    minute = int(60.0 / 0.0025)
    per_minute = {e: [rms(np.hypot(*[x[k:k + minute] for x in traces[e]])) for k in range(0, len(traces[e][0]), minute)]
                  for e in ESTIMATORS}

    # ---- error against gyro bias (first flight; sign pattern +,-,+ so roll and pitch both drift)
    biases = (0.0, 0.05, 0.1, 0.2)
    by_bias = {e: [] for e in ESTIMATORS}
    for b in biases:
        vec = np.radians(b) * np.array([1.0, -1.0, 1.0])
        for e in ESTIMATORS:
            r, p = estimate(flights[0], e, trained, vec)
            er, ep = tilt_error_deg(flights[0], r, p)
            by_bias[e].append((rms(ep), rms(er)))

    # ---- print and write
    lines = [
        "| estimator | RMS roll, deg | RMS pitch, deg | RMS tilt in manoeuvres, deg | worst tilt error, deg |"
        f" RMS tilt, minute 1 of {long_s / 60:g} | RMS tilt, last minute |",
        "|---|---|---|---|---|---|---|"]
    for e in ESTIMATORS:
        d = rows[e]
        lines.append(f"| {e} | {np.mean(d['roll']):.3f} | {np.mean(d['pitch']):.3f} | {np.mean(d['man']):.3f} | "
                     f"{np.max(d['max']):.2f} | {per_minute[e][0]:.3f} | {per_minute[e][-1]:.3f} |")
    bias_lines = ["| estimator | " + " | ".join(f"{b:g} deg/s" for b in biases) + " |",
                  "|---|" + "---|" * len(biases)]
    for e in ESTIMATORS:
        bias_lines.append(f"| {e} | " + " | ".join(f"{p:.3f} / {r:.3f}" for p, r in by_bias[e]) + " |")
    print("\n".join(lines))
    print("\nRMS pitch / roll error against gyro bias (first control flight):")
    print("\n".join(bias_lines))
    print(f"\n({time.monotonic() - t_start:.0f} s)")
    if args.quick:
        return

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    img = ROOT / "docs" / "img"
    img.mkdir(parents=True, exist_ok=True)
    f0 = flights[0]
    fig, ax = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    ax[0].plot(f0.t_s, np.degrees(f0.pitch_rad), "k", lw=1.2, label="truth")
    for e in ESTIMATORS:
        r, p = traces["first"][e]
        ax[0].plot(f0.t_s, np.degrees(p), color=COLORS[e], lw=0.8, label=e)
        ax[1].plot(f0.t_s, np.degrees(np.angle(np.exp(1j * (p - f0.pitch_rad)))), color=COLORS[e], lw=0.8, label=e)
    ax[0].set_ylabel("pitch, deg")
    ax[1].set_ylabel("pitch error, deg")
    ax[1].set_ylim(-10, 10)
    ax[1].set_xlabel("t, s")
    ax[0].legend(ncol=5, fontsize=8)
    ax[0].set_title(f"control flight 1, gyro bias +{BIAS_DEG_S} deg/s on every axis")
    fig.tight_layout()
    fig.savefig(img / "gyrovertical_pitch.png", dpi=90)
    plt.close(fig)

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for e in ESTIMATORS:
        ax[0].plot(biases, [p for p, _ in by_bias[e]], "o-", color=COLORS[e], label=e)
        ax[1].plot(biases, [r for _, r in by_bias[e]], "o-", color=COLORS[e], label=e)
    for a, name in zip(ax, ("pitch", "roll")):
        a.set_xlabel("gyro bias, deg/s")
        a.set_ylabel(f"RMS {name} error, deg")
        a.set_yscale("log")
        a.grid(True, alpha=0.3)
    ax[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(img / "gyrovertical_bias.png", dpi=90)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(8, 4))
    for e in ESTIMATORS:
        ax.plot(np.arange(1, len(per_minute[e]) + 1), per_minute[e], "o-", color=COLORS[e], label=e)
    ax.set_xlabel("minute of flight")
    ax.set_ylabel("RMS tilt error in that minute, deg")
    ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"{long_s / 60:g}-minute control flight, gyro bias +{BIAS_DEG_S} deg/s")
    fig.tight_layout()
    fig.savefig(img / "gyrovertical_duration.png", dpi=90)
    plt.close(fig)

    doc = [
        "# Adaptive gyro-vertical (004) against its baselines",
        "",
        f"Produced by `{cmd}` with the parameters of `{Path(args.params).relative_to(ROOT) if Path(args.params).is_relative_to(ROOT) else args.params}`,",
        f"trained by `{trained.meta.get('command', '?')}`.",
        "",
        f"Control flights (manoeuvre menu \"control\": figure-eights, sprints, attitude doublets, climbs, a flip; "
        f"seeds never used in training): {len(flights)} flights of {short_s:g} s for the first four columns, "
        f"one of {long_s:g} s for the last two. Every gyro carries a constant bias of +{BIAS_DEG_S} deg/s; "
        "every estimator starts from the true attitude and sees the same samples. "
        f"'In manoeuvres' is the {100 * man_share:.0f} % of samples where the load factor, low-passed over 0.1 s, "
        "is more than 0.05 g from 1 g. kalman-000 is the attitude filter of 000 with accelerometer angles as printed "
        "(its per-axis Euler angles do not survive the flip, which dominates its worst error).",
        "",
        *lines,
        "",
        "RMS pitch / roll error (deg) against the gyro bias, first control flight, bias pattern (+b, -b, +b):",
        "",
        *bias_lines,
        "",
        "![pitch and its error](img/gyrovertical_pitch.png)",
        "",
        "![error against gyro bias](img/gyrovertical_bias.png)",
        "",
        "![error against flight duration](img/gyrovertical_duration.png)",
        "",
    ]
    out = ROOT / "docs" / "gyrovertical.md"
    # the q820's section (bench/gyrovertical_q820.py, by hand) is kept as it is
    kept = out.read_text().partition(Q820_SECTION)[2] if out.is_file() else ""
    out.write_text("\n".join(doc) + (Q820_SECTION + kept if kept else ""))
    print("wrote docs/gyrovertical.md and docs/img/gyrovertical_{pitch,bias,duration}.png")


if __name__ == "__main__":
    main()
