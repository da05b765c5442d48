"""Flight plots (PNG) from a flight log (see schemas.flightlog.read_log)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from flight.quat import quats_to_euler, wrap_angle  # noqa: E402

_DPI = 110


def _series(msgs: list[dict], field: str) -> tuple[np.ndarray, np.ndarray]:
    msgs = sorted(msgs, key=lambda m: m["header"]["t_s"])
    t = np.array([m["header"]["t_s"] for m in msgs], dtype=np.float64)
    v = np.array([m[field] for m in msgs], dtype=np.float64)
    return t, v


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def _min_span(ax, span: float) -> None:
    """Keep an almost constant signal from being blown up to rounding noise."""
    lo, hi = ax.get_ylim()
    if hi - lo < span:
        mid = 0.5 * (lo + hi)
        ax.set_ylim(mid - span / 2, mid + span / 2)


def _shade_measured(ax, sp: list[dict], t0: float, label: bool) -> None:
    """Shade the spans where the planner setpoint has measure True in position mode."""
    sp = sorted(sp, key=lambda m: m["header"]["t_s"])
    start = None
    first = True
    for i, m in enumerate(sp):
        on = bool(m["measure"]) and m["mode"] == "position"
        t = m["header"]["t_s"] - t0
        if on and start is None:
            start = t
        last = i == len(sp) - 1
        if start is not None and (not on or last):
            ax.axvspan(start, t, color="tab:green", alpha=0.12, lw=0,
                       label="measured hold" if (label and first) else None)
            first = False
            start = None


def _position_plot(log, p, t0, out: Path) -> Path | None:
    truth = log.get(p + "sim/truth", [])
    sp = log.get(p + "planner/setpoint", [])
    if not truth:
        return None
    tt, pos = _series(truth, "position_m")
    fig, axes = plt.subplots(3, 1, sharex=True, figsize=(10, 8))
    if sp:
        ts, ref = _series(sp, "position_m")
    for a, (ax, name) in enumerate(zip(axes, "xyz")):
        ax.plot(tt - t0, pos[:, a], label="truth", color="tab:blue")
        if sp:
            ax.step(ts - t0, ref[:, a], where="post", label="planner reference", color="tab:orange", ls="--")
            _shade_measured(ax, sp, t0, label=(a == 0))
        ax.set_ylabel(f"{name} [m]")
        _min_span(ax, 0.1)
        ax.grid(True, alpha=0.4)
    axes[0].legend(loc="best")
    axes[0].set_title("Position (world ENU): truth vs planner reference")
    axes[-1].set_xlabel("time since start of log [s]")
    return _save(fig, out / "position.png")


def _attitude_plot(log, p, t0, out: Path) -> Path | None:
    truth = log.get(p + "sim/truth", [])
    att = log.get(p + "att/state", [])
    if not truth and not att:
        return None
    fig, axes = plt.subplots(3, 1, sharex=True, figsize=(10, 8))
    if truth:
        tt, q = _series(truth, "quaternion_wxyz")
        eul = np.degrees(quats_to_euler(q))
        eul[:, 2] = np.degrees(np.unwrap(np.radians(eul[:, 2])))
    if att:
        ta, ref = _series(att, "euler_ref_rad")
        ref = np.degrees(ref)
    for a, (ax, name) in enumerate(zip(axes, ("roll", "pitch", "yaw"))):
        if truth:
            ax.plot(tt - t0, eul[:, a], label="truth", color="tab:blue")
        if att:
            ax.plot(ta - t0, ref[:, a], label="reference (att/state)", color="tab:orange", ls="--")
        ax.set_ylabel(f"{name} [deg]")
        _min_span(ax, 1.0)
        ax.grid(True, alpha=0.4)
    axes[0].legend(loc="best")
    axes[0].set_title("Attitude (ZYX Euler): truth vs attitude reference")
    axes[-1].set_xlabel("time since start of log [s]")
    return _save(fig, out / "attitude.png")


def _motors_plot(log, p, t0, out: Path) -> Path | None:
    pwm = log.get(p + "motors/pwm", [])
    truth = log.get(p + "sim/truth", [])
    if not pwm and not truth:
        return None
    fig, axes = plt.subplots(2, 1, sharex=True, figsize=(10, 6))
    if pwm:
        tp, us = _series(pwm, "pwm_us")
        for i in range(us.shape[1]):
            axes[0].plot(tp - t0, us[:, i], label=f"motor {i + 1}", lw=0.8)
        axes[0].legend(loc="best", ncol=4)
    axes[0].set_ylabel("PWM [us]")
    axes[0].set_title("Motor driver output (motors/pwm)")
    if truth:
        tt, thr = _series(truth, "motor_thrust_n")
        for i in range(thr.shape[1]):
            axes[1].plot(tt - t0, thr[:, i], label=f"motor {i + 1}", lw=0.8)
        axes[1].legend(loc="best", ncol=4)
    axes[1].set_ylabel("thrust [N]")
    axes[1].set_title("Motor thrust (simulator truth)")
    axes[1].set_xlabel("time since start of log [s]")
    for ax in axes:
        ax.grid(True, alpha=0.4)
    return _save(fig, out / "motors.png")


def _estimation_plot(log, p, t0, out: Path) -> Path | None:
    truth = log.get(p + "sim/truth", [])
    att = [m for m in log.get(p + "att/state", []) if m.get("state_source") == "estimate"]
    pos = [m for m in log.get(p + "pos/state", []) if m.get("state_source") == "estimate"]
    if not truth or not (att or pos):
        return None
    tt, tpos = _series(truth, "position_m")
    _, tq = _series(truth, "quaternion_wxyz")
    teul = quats_to_euler(tq)
    fig, axes = plt.subplots(2, 1, sharex=True, figsize=(10, 7))
    if pos:
        tp, epos = _series(pos, "position_m")
        for a, name in enumerate("xyz"):
            tru = np.interp(tp, tt, tpos[:, a])
            axes[0].plot(tp - t0, tru - epos[:, a], label=name, lw=0.8)
        axes[0].legend(loc="best")
    else:
        axes[0].text(0.5, 0.5, "position from truth (no estimate)", ha="center", transform=axes[0].transAxes)
    axes[0].set_ylabel("truth - estimate [m]")
    _min_span(axes[0], 0.01)
    axes[0].set_title("Position estimation error")
    if att:
        ta, eeul = _series(att, "euler_rad")
        for a, name in enumerate(("roll", "pitch", "yaw")):
            tru = np.interp(ta, tt, np.unwrap(teul[:, a]))
            err = wrap_angle(tru - eeul[:, a])
            axes[1].plot(ta - t0, np.degrees(err), label=name, lw=0.8)
        axes[1].legend(loc="best")
    else:
        axes[1].text(0.5, 0.5, "attitude from truth (no estimate)", ha="center", transform=axes[1].transAxes)
    axes[1].set_ylabel("truth - estimate [deg]")
    _min_span(axes[1], 0.1)
    axes[1].set_title("Attitude estimation error")
    axes[1].set_xlabel("time since start of log [s]")
    for ax in axes:
        ax.grid(True, alpha=0.4)
    return _save(fig, out / "estimation.png")


def _flip_plot(log, p, t0, out: Path, kf: float) -> Path | None:
    """The flip: accumulated roll against the phase machine's adaptive target, altitude,
    XY, rotor speeds and the planner's solve times, around the flip item."""
    plans = sorted(log.get(p + "planner/plan", []), key=lambda m: m["header"]["t_s"])
    truth = sorted(log.get(p + "sim/truth", []), key=lambda m: m["header"]["t_s"])
    sp = sorted(log.get(p + "planner/setpoint", []), key=lambda m: m["header"]["t_s"])
    flip_t = [m["header"]["t_s"] for m in sp if m["phase"].startswith("flip")]
    if not plans or not truth or not flip_t:
        return None
    lo, hi = flip_t[0] - 1.0, flip_t[-1] + 1.0
    truth = [m for m in truth if lo <= m["header"]["t_s"] <= hi]
    tt, pos = _series(truth, "position_m")
    _, q = _series(truth, "quaternion_wxyz")
    roll = np.unwrap(quats_to_euler(q)[:, 0])
    tp = np.array([m["header"]["t_s"] for m in plans])
    plan_roll = np.array([m["roll_rad"] for m in plans])
    # the truth's roll accumulated from the same origin as the phase machine's
    offset = np.interp(tp[0], tt, roll) - plan_roll[0]
    fig, axes = plt.subplots(5, 1, sharex=True, figsize=(10, 13))
    ax = axes[0]
    ax.plot(tt - t0, np.degrees(roll - offset), label="roll (truth, accumulated)", color="tab:blue")
    ax.plot(tp - t0, np.degrees(plan_roll), label="roll (planner's estimate)", color="tab:green", lw=0.8, ls=":")
    ax.step(tp - t0, np.degrees([m["target_roll_rad"][min(1, len(m["target_roll_rad"]) - 1)] for m in plans]),
            where="post", label="adaptive target (next plan step)", color="tab:orange", ls="--")
    ax.step(tp - t0, np.degrees([m["target_roll_rad"][-1] for m in plans]), where="post",
            label="adaptive target (horizon end)", color="tab:red", ls="--", lw=0.8)
    ax.axhline(360.0, color="grey", lw=0.6)
    ax.set_ylabel("roll [deg]")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(f"Flip ({plans[-1]['method']}): roll against the adaptive target")
    axes[1].plot(tt - t0, pos[:, 2], color="tab:blue")
    axes[1].set_ylabel("altitude z [m]")
    _min_span(axes[1], 0.2)
    axes[2].plot(tt - t0, pos[:, 0], label="x")
    axes[2].plot(tt - t0, pos[:, 1], label="y")
    axes[2].set_ylabel("position [m]")
    axes[2].legend(loc="best")
    _min_span(axes[2], 0.2)
    _, thrust = _series(truth, "motor_thrust_n")
    speeds = np.sqrt(np.maximum(thrust, 0.0) / kf)
    for i in range(speeds.shape[1]):
        axes[3].plot(tt - t0, speeds[:, i], lw=0.8, label=f"rotor {i + 1}")
    axes[3].set_ylabel("rotor speed [rad/s]")
    axes[3].legend(loc="best", ncol=4, fontsize=8)
    axes[4].plot(tp - t0, [m["solve_ms"] for m in plans], ".", ms=3, color="tab:purple", label="solve")
    dts = np.diff(tp)
    if dts.size:
        axes[4].axhline(1e3 * float(np.median(dts)), color="grey", ls="--", lw=0.8, label="re-solve period")
    axes[4].set_ylabel("solve time [ms]")
    axes[4].legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("time since start of log [s]")
    for a in axes:
        a.grid(True, alpha=0.4)
        for name, color in (("flip", "tab:red"), ("flip-recovery", "tab:green")):
            ts = [m["header"]["t_s"] - t0 for m in sp if m["phase"] == name]
            if ts:
                a.axvspan(ts[0], ts[-1], color=color, alpha=0.08, lw=0)
    return _save(fig, out / "flip.png")


def make_plots(log: dict, out_dir: Path, vehicle_id: int = 0, vehicle: str | None = None) -> list[Path]:
    """Write position.png, attitude.png, motors.png (and estimation.png when a state
    estimate was flown, flip.png when the mission flew a flip) into out_dir; plots whose topics are missing are skipped."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    p = f"zp/{vehicle_id}/"
    starts = [min(m["header"]["t_s"] for m in msgs) for k, msgs in log.items() if k.startswith(p) and msgs]
    t0 = float(min(starts)) if starts else 0.0
    written = []
    for fn in (_position_plot, _attitude_plot, _motors_plot, _estimation_plot):
        path = fn(log, p, t0, out)
        if path is not None:
            written.append(path)
    kf = _thrust_coefficient(vehicle)
    if kf is not None:
        path = _flip_plot(log, p, t0, out, kf)
        if path is not None:
            written.append(path)
    return written


def _thrust_coefficient(vehicle: str | None) -> float | None:
    """kf of the flight's airframe (rotor speed = sqrt(thrust / kf)); None without one."""
    from flight.vehicle import VehicleError, load_vehicle
    try:
        return load_vehicle(vehicle).thrust_coefficient_kf if vehicle else None
    except VehicleError:
        return None
