"""Flight metrics from a flight log (see schemas.flightlog.read_log).

Everything is computed from header.t_s (sample time) and the simulator truth;
the result is a plain JSON-serialisable dict (no NaN: missing values are None).

Step responses (attitude_steps, position_steps) are measured on the truth
signal over a window that runs from the step until the planner's reference
next changes (any change of the stepped quantity's reference, or a mode
change) or the log ends. Crossing times are linearly interpolated between
truth samples.

An attitude step is the attitude loop's response (figure 4 of 000: law (8) on the
filters, and the motors): it is timed from the moment the attitude level holds the
new reference (att/state euler_ref_rad), which reaches it one tick per hop after
the planner's setpoint (planner -> position -> attitude: 15-20 ms in lockstep), and
starts from the angle flown then. The same step timed from the planner's setpoint
is kept as command_settle_s, the delay as reference_delay_s.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from flight.quat import quats_to_euler, wrap_angle

ATTITUDE_STEP_MIN_DEG = 1.0
ATTITUDE_REF_TOL_DEG = 1e-3  # the attitude level's reference equals the setpoint's
POSITION_STEP_MIN_M = 0.2
SETTLE_BAND = 0.05  # of the step size
MONOTONE_TOL = 0.01  # of the step size
_REF_EPS = 1e-9  # any reference change larger than this ends a step window


# --------------------------------------------------------------------------- helpers


def _f(x) -> float | None:
    """float() of a numpy value, None for None/NaN/inf."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _sorted(msgs: list[dict]) -> list[dict]:
    return sorted(msgs, key=lambda m: m["header"]["t_s"])  # stable: file order on ties


def _times(msgs: list[dict]) -> np.ndarray:
    return np.array([m["header"]["t_s"] for m in msgs], dtype=np.float64)


def _crossing(t: np.ndarray, s: np.ndarray, level: float) -> float | None:
    """First time the rising signal s reaches level (linear interpolation)."""
    idx = np.nonzero(s >= level)[0]
    if idx.size == 0:
        return None
    i = int(idx[0])
    if i == 0:
        return float(t[0])
    s0, s1 = s[i - 1], s[i]
    frac = (level - s0) / (s1 - s0) if s1 != s0 else 1.0
    return float(t[i - 1] + frac * (t[i] - t[i - 1]))


def step_response(t: np.ndarray, y: np.ndarray, t0: float, y0: float, y1: float) -> dict:
    """Rise (10->90 %), overshoot (% of step), settle (5 % band) and monotonicity of y
    answering a step y0 -> y1 at t0; t, y are the samples of the window only.

    In normalised units s = (y - y0) / (y1 - y0) (0 before, 1 at target):
    - rise_s: t(s first reaches 0.9) - t(s first reaches 0.1); None if 0.9 never reached;
    - overshoot_pct: 100 * max(0, max(s) - 1);
    - settle_s: time from t0 until |s - 1| <= 0.05 for the rest of the window
      (the exit time of the last excursion, interpolated); None if the last sample
      is outside the band (never settled) or there are no samples;
    - monotone: the running maximum of s never drops by more than 0.01 before s
      reaches 0.9 (over the whole window if it never does).
    """
    d = y1 - y0
    out: dict[str, Any] = {"rise_s": None, "overshoot_pct": None, "settle_s": None, "monotone": None}
    if t.size == 0 or d == 0:
        return out
    s = (y - y0) / d
    t10 = _crossing(t, s, 0.1)
    t90 = _crossing(t, s, 0.9)
    if t10 is not None and t90 is not None:
        out["rise_s"] = _f(t90 - t10)
    out["overshoot_pct"] = _f(100.0 * max(0.0, float(np.max(s)) - 1.0))

    err = np.abs(s - 1.0)
    outside = np.nonzero(err > SETTLE_BAND)[0]
    if outside.size == 0:
        out["settle_s"] = 0.0
    elif outside[-1] < t.size - 1:
        i = int(outside[-1])
        e0, e1 = err[i], err[i + 1]
        frac = (e0 - SETTLE_BAND) / (e0 - e1) if e0 != e1 else 1.0
        out["settle_s"] = _f(t[i] + frac * (t[i + 1] - t[i]) - t0)

    n90 = np.nonzero(s >= 0.9)[0]
    end = int(n90[0]) + 1 if n90.size else s.size
    head = s[:end]
    reversal = np.max(np.maximum.accumulate(head) - head) if head.size else 0.0
    out["monotone"] = bool(reversal <= MONOTONE_TOL)
    return out


def _pct(values: np.ndarray, p: float) -> float | None:
    return _f(np.percentile(values, p)) if values.size else None


def _max_or_none(values) -> float | None:
    vals = [v for v in values if v is not None]
    return _f(max(vals)) if vals else None


# --------------------------------------------------------------------------- steps


def _change_points(modes: list[str], ref: np.ndarray) -> np.ndarray:
    """Indices j >= 1 where the mode or the reference differs from setpoint j - 1."""
    mode_change = np.array([modes[j] != modes[j - 1] for j in range(1, len(modes))], dtype=bool)
    ref_change = np.any(np.abs(np.diff(ref, axis=0)) > _REF_EPS, axis=1)
    return np.nonzero(mode_change | ref_change)[0] + 1


def _reference_arrival(loop_t: np.ndarray, loop_ref: np.ndarray, t0: float, t_end: float,
                       value: float) -> float | None:
    """First time in [t0, t_end] the attitude level's reference (display units) equals value."""
    idx = np.nonzero((loop_t >= t0) & (loop_t <= t_end) & (np.abs(loop_ref - value) <= ATTITUDE_REF_TOL_DEG))[0]
    return float(loop_t[idx[0]]) if idx.size else None


def _find_steps(sp: list[dict], sp_t: np.ndarray, truth_t: np.ndarray, truth_val: np.ndarray,
                landed: np.ndarray, mode: str, axes: tuple[str, ...], threshold: float,
                scale: float, loop: tuple[np.ndarray, np.ndarray] | None = None) -> list[dict]:
    """Reference jumps > threshold (in display units: ref * scale) between consecutive
    setpoints of `mode`; each analysed against truth_val[:, axis] * scale.

    loop = (times, references (n, axes)) of the attitude level: attitude steps are then
    timed from the reference's arrival there (module docstring); None, or a reference
    that never arrives, times them from the setpoint (reference_delay_s None)."""
    if not sp or truth_t.size == 0:
        return []
    modes = [m["mode"] for m in sp]
    if mode == "attitude":
        ref = np.array([m["attitude_rad"][:2] for m in sp], dtype=np.float64) * scale
    else:
        ref = np.array([m["position_m"][:3] for m in sp], dtype=np.float64) * scale
    vals = truth_val * scale
    t_last = float(truth_t[-1])
    unit = "deg" if mode == "attitude" else "m"
    changes = _change_points(modes, ref)
    steps = []
    for i in changes:
        if modes[i] != mode:
            continue
        t0 = float(sp_t[i])
        k = int(np.searchsorted(truth_t, t0, side="right")) - 1  # truth at the step
        if mode == "attitude" and modes[i - 1] != mode:
            # entering attitude mode: the step starts from the angle actually flown
            if k < 0:
                continue
            prev = vals[k, : len(axes)]
        elif modes[i - 1] == mode:
            prev = ref[i - 1]
        else:
            continue
        if mode == "position" and (k < 0 or landed[k]):
            continue  # only steps while airborne
        if mode == "attitude" and modes[i - 1] != mode:
            # entering attitude mode, an axis the item leaves level is no step: the tilt flown
            # then is the position law's own correction (±1-3° in a hold), not a commanded one
            jumps = [a for a in range(len(axes)) if abs(ref[i, a]) > threshold and abs(ref[i, a] - prev[a]) > threshold]
        else:
            jumps = [a for a in range(len(axes)) if abs(ref[i, a] - prev[a]) > threshold]
        if not jumps:
            continue
        later = changes[changes > i]
        t_end = float(sp_t[later[0]]) if later.size else t_last  # next reference or mode change
        w = (truth_t >= t0) & (truth_t <= t_end)
        for a in jumps:
            name = axes[a]
            r = step_response(truth_t[w], vals[w, a], t0, float(prev[a]), float(ref[i, a]))
            entry = {"axis": name, "t_s": t0, f"from_{unit}": _f(prev[a]), f"to_{unit}": _f(ref[i, a]),
                     "window_s": _f(t_end - t0), **r}
            if mode == "position":
                entry.pop("monotone")
            else:
                entry["command_settle_s"], entry["reference_delay_s"] = r["settle_s"], None
                t_ref = None if loop is None else _reference_arrival(loop[0], loop[1][:, a], t0, t_end,
                                                                        float(ref[i, a]))
                if t_ref is not None:
                    start = prev[a]
                    if modes[i - 1] != mode:  # entering attitude mode: from the angle flown then
                        start = vals[max(int(np.searchsorted(truth_t, t_ref, side="right")) - 1, 0), a]
                    wl = (truth_t >= t_ref) & (truth_t <= t_end)
                    entry.update(step_response(truth_t[wl], vals[wl, a], t_ref, float(start), float(ref[i, a])))
                    entry[f"from_{unit}"] = _f(start)
                    entry["reference_delay_s"] = _f(t_ref - t0)
            steps.append(entry)
    return steps


# --------------------------------------------------------------------------- metrics


def _until_the_simulator_stops(log: dict[str, list[dict]], p: str) -> dict[str, list[dict]]:
    """The flight is over when the simulator stops: what the services published while the
    stack wound down after it (the estimators coasting on no sensors) is not the flight's.
    Health keeps every message: its last one holds the final counts."""
    imu = log.get(p + "sim/imu", [])
    if not imu:
        return log
    end = max(x["header"]["t_s"] for x in imu) + 0.05   # a service's last step on the last samples
    return {k: (v if k.endswith("/health") else [x for x in v if x["header"]["t_s"] <= end])
            for k, v in log.items()}


def compute_metrics(log: dict[str, list[dict]], info: dict, vehicle_id: int = 0) -> dict:
    """Metrics of one flight; info = {"mission", "mode", "seed", "vehicle"}."""
    p = f"zp/{vehicle_id}/"
    log = _until_the_simulator_stops(log, p)
    truth = _sorted(log.get(p + "sim/truth", []))
    sp = _sorted(log.get(p + "planner/setpoint", []))

    m: dict[str, Any] = {k: info.get(k) for k in ("mission", "mode", "seed", "vehicle")}
    m["completed"] = bool(sp and sp[-1]["mission_state"] == "completed")
    m["mission_state"] = sp[-1]["mission_state"] if sp else None

    truth_t = _times(truth)
    m["duration_s"] = _f(truth_t[-1] - truth_t[0]) if truth else None
    if truth:
        pos = np.array([x["position_m"] for x in truth], dtype=np.float64)
        euler = quats_to_euler(np.array([x["quaternion_wxyz"] for x in truth]))
        landed = np.array([bool(x["landed"]) for x in truth])
    else:
        pos, euler, landed = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=bool)

    # position tracking over measured hold segments
    sp_t = _times(sp)
    m["position_rms_m"] = m["max_position_error_m"] = None
    m["measured_s"] = 0.0
    if truth and sp:
        idx = np.searchsorted(sp_t, truth_t, side="right") - 1
        ok = idx >= 0
        meas = np.array([bool(x["measure"]) and x["mode"] == "position" for x in sp])
        sel = ok & meas[np.clip(idx, 0, None)]
        if sel.any():
            ref = np.array([x["position_m"] for x in sp], dtype=np.float64)[idx[sel]]
            err = np.linalg.norm(pos[sel] - ref, axis=1)
            m["position_rms_m"] = _f(np.sqrt(np.mean(err**2)))
            m["max_position_error_m"] = _f(np.max(err))
            dt = np.diff(truth_t, append=truth_t[-1])
            m["measured_s"] = _f(np.sum(dt[sel]))

    # a crash: the truth on the ground while the mission flies (the planner's "completed"
    # comes from the estimate and cannot see it), or a tilt past 60 degrees (outside flips)
    tilt = np.degrees(np.arccos(np.clip(np.cos(euler[:, 0]) * np.cos(euler[:, 1]), -1.0, 1.0)))
    sp_idx = np.clip(np.searchsorted(sp_t, truth_t, side="right") - 1, 0, len(sp) - 1) if sp else None
    in_flip = (np.array([x["phase"].startswith("flip") for x in sp])[sp_idx] if sp
               else np.zeros(truth_t.size, dtype=bool))
    m["max_tilt_deg"] = _f(np.max(tilt[~in_flip])) if truth and np.any(~in_flip) else None
    m["crashed"] = False
    m["crash_reason"] = None
    if truth and sp:
        flying = np.array([x["phase"] in FLYING_PHASES or x["phase"].startswith("flip") for x in sp])[sp_idx]
        if np.any(landed & flying) and not _failsafes(log, p):
            # (a vehicle's own failsafe landing it mid-mission is judged by the touchdown below)
            m["crash_reason"] = "on the ground while the mission flies"
        elif (m["max_tilt_deg"] or 0.0) > 60.0:
            m["crash_reason"] = "tilted past 60 deg"
    # a disarm or a motor cut in the air, or a hard touchdown, is a crash whatever the planner
    # believes (a disarm command says nothing about where the vehicle is): judged on the truth
    m["touchdown_speed_m_s"] = _touchdown_speed(truth, landed)
    if m["crash_reason"] is None and truth:
        cut = _motor_cut_in_air(log.get(p + "motors/pwm", []), truth_t, pos, landed, in_flip)
        if cut is not None:
            m["crash_reason"] = f"motors cut in the air at t={cut:.2f} s"
        elif (m["touchdown_speed_m_s"] or 0.0) > HARD_TOUCHDOWN_M_S:
            m["crash_reason"] = f"touchdown at {m['touchdown_speed_m_s']:.2f} m/s"
    m["crashed"] = m["crash_reason"] is not None
    m["flip"] = _flip(log, p, sp, truth, truth_t, sp_idx) if truth and in_flip.any() else None
    if m["flip"] is not None:  # a flip that reaches the ground is a crash, whatever the flags say
        flip_z = pos[in_flip, 2]
        low = float(np.min(flip_z))
        m["flip"]["min_altitude_m"] = _f(low)
        m["flip"]["max_altitude_m"] = _f(float(np.max(flip_z)))  # a climb before the turn shows here
        m["flip"]["hit_ground"] = bool(low < GROUND_Z_M)
        if low < GROUND_Z_M:
            m["crashed"] = True
            m["crash_reason"] = m["crash_reason"] or "hit the ground in the flip"
            m["flip"]["completed"] = False

    # service health
    rates: dict[str, float | None] = {}
    rejected: dict[str, dict] = {}
    for key in sorted(log):
        if not (key.startswith(p) and key.endswith("/health")):
            continue
        service = key[len(p):-len("/health")]
        hs = _sorted(log[key])
        if not hs:
            continue
        # median over full 1 s windows: the first windows after start-up are partial
        inner = [h["rate_hz"] for h in hs[1:-1] if h["state"] == "running"]
        rates[service] = _f(np.median(inner)) if inner else None
        rejected[service] = {str(k): int(v) for k, v in hs[-1].get("rejected", {}).items()}
    m["rates_hz"] = rates
    m["failsafes"] = _failsafes(log, p)
    m["rejected_messages"] = rejected
    m["rejected_total"] = int(sum(sum(r.values()) for r in rejected.values()))

    # IMU sample -> PWM output latency: from each IMU sample the attitude level ran on to the
    # first motor output computed from it. The outputs between two attitude commands (the
    # motors run at twice the attitude rate) re-mix an older command: their age is reported apart.
    ages, first, seen = [], [], set()
    for x in _sorted(log.get(p + "motors/pwm", [])):
        if not x["armed"] or x["imu_t_s"] < 0:
            continue
        age = (x["header"]["t_s"] - x["imu_t_s"]) * 1000.0
        ages.append(age)
        if x["imu_t_s"] not in seen:
            seen.add(x["imu_t_s"])
            first.append(age)
    lat, ages = np.array(first, dtype=np.float64), np.array(ages, dtype=np.float64)
    m["latency_ms"] = {"imu_to_pwm_p50": _pct(lat, 50), "imu_to_pwm_p99": _pct(lat, 99),
                       "imu_to_pwm_max": _f(lat.max()) if lat.size else None, "samples": int(lat.size),
                       "output_age_p50": _pct(ages, 50), "output_age_p99": _pct(ages, 99)}

    # step responses
    att_state = _sorted(log.get(p + "att/state", []))
    loop = ((_times(att_state), np.degrees(np.array([x["euler_ref_rad"][:2] for x in att_state], dtype=np.float64)))
            if att_state else None)
    m["attitude_steps"] = _find_steps(sp, sp_t, truth_t, euler[:, :2], landed, "attitude",
                                      ("roll", "pitch"), ATTITUDE_STEP_MIN_DEG, 180.0 / math.pi, loop)
    m["position_steps"] = _find_steps(sp, sp_t, truth_t, pos, landed, "position",
                                      ("x", "y", "z"), POSITION_STEP_MIN_M, 1.0)
    att, ps = m["attitude_steps"], m["position_steps"]
    m["attitude_rise_s_max"] = _max_or_none(s["rise_s"] for s in att)
    m["attitude_overshoot_pct_max"] = _max_or_none(s["overshoot_pct"] for s in att)
    m["attitude_settle_s_max"] = _max_or_none(s["settle_s"] for s in att)
    m["attitude_command_settle_s_max"] = _max_or_none(s["command_settle_s"] for s in att)
    m["attitude_steps_unsettled"] = sum(1 for s in att if s["settle_s"] is None)
    m["position_step_settle_s_max"] = _max_or_none(s["settle_s"] for s in ps)
    m["position_step_overshoot_pct_max"] = _max_or_none(s["overshoot_pct"] for s in ps)
    m["position_steps_unsettled"] = sum(1 for s in ps if s["settle_s"] is None)
    m["estimation"] = _estimation(log, p, truth_t, pos, euler, landed)
    m["vision"] = vision_accuracy(log, p, truth)
    return m


CAMERA_PERIOD_S = 0.05   # the simulator's camera_rate_hz (20 Hz): the frames' exposure instants
AIRBORNE_M = 0.3         # the camera sees whole markers from about here up (0.2 m markers, f = 400 px)


def vision_accuracy(log, p, truth) -> dict | None:
    """Each vision pose against the truth at its exposure time (the truth's 100 Hz samples hold
    every 20 Hz exposure instant): position and attitude error per frame (median, p95, max), and
    the fraction of the exposures above AIRBORNE_M that gave a pose (detected, solved, accepted)."""
    poses = log.get(p + "vision/pose", [])
    if not poses or not truth:
        return None
    t_truth = np.array([m["header"]["t_s"] for m in truth])
    order = np.argsort(t_truth)
    t_truth = t_truth[order]
    pos = np.array([truth[i]["position_m"] for i in order])
    quat = np.array([truth[i]["quaternion_wxyz"] for i in order])
    dp, dth, t_pose = [], [], []
    for m in poses:
        t = m["header"]["t_s"]
        k = int(np.searchsorted(t_truth, t))
        k = min(max(k, 0), len(t_truth) - 1)
        if k > 0 and abs(t_truth[k - 1] - t) < abs(t_truth[k] - t):
            k -= 1
        if abs(t_truth[k] - t) > 1e-3:
            continue
        q1, q2 = quat[k], np.asarray(m["quaternion_wxyz"], dtype=float)
        dot = abs(float(q1 @ q2) / (np.linalg.norm(q1) * np.linalg.norm(q2)))
        dp.append(float(np.linalg.norm(np.asarray(m["position_m"]) - pos[k])))
        dth.append(math.degrees(2.0 * math.acos(min(1.0, dot))))
        t_pose.append(t)
    if not dp:
        return None
    dp_a, dth_a = np.array(dp), np.array(dth)
    # exposures in the air: the truth samples on the camera's instants, above AIRBORNE_M
    on_frame = np.abs(t_truth / CAMERA_PERIOD_S - np.round(t_truth / CAMERA_PERIOD_S)) < 1e-6
    airborne = on_frame & (pos[:, 2] > AIRBORNE_M)
    air_t = set(np.round(t_truth[airborne] / CAMERA_PERIOD_S).astype(int).tolist())
    posed = set(int(round(t / CAMERA_PERIOD_S)) for t in t_pose)
    return {"poses": len(dp), "position_err_mm_p50": 1e3 * float(np.median(dp_a)),
            "position_err_mm_p95": 1e3 * float(np.percentile(dp_a, 95)), "position_err_mm_max": 1e3 * float(dp_a.max()),
            "attitude_err_deg_p50": float(np.median(dth_a)), "attitude_err_deg_p95": float(np.percentile(dth_a, 95)),
            "attitude_err_deg_max": float(dth_a.max()),
            "pose_rate_airborne": len(air_t & posed) / len(air_t) if air_t else None}


GROUND_Z_M = 0.05  # truth altitude below this during a flip item: it hit the ground
# motors disarmed or asked for no thrust at all while the truth is this high and not resting: a cut
# (a landing disarms on the ground; higher than a landing's last bounce)
MOTOR_CUT_ALTITUDE_M = 0.3
HARD_TOUCHDOWN_M_S = 2.0   # vertical speed at touchdown above this: a fall, not a landing


FAILSAFE_COUNTS = ("failsafe_engaged", "failsafe_landed", "failsafe_recovered", "planner_lost", "planner_back",
                   "planner_lost_landed", "vision_lost")


def _failsafes(log, p) -> dict:
    """service -> {failsafe count: n} from each service's last health (empty: none engaged)."""
    out = {}
    for key, msgs in log.items():
        if key.startswith(p) and key.endswith("/health") and msgs:
            last = _sorted(msgs)[-1].get("rejected", {})
            got = {k: int(v) for k, v in last.items() if k in FAILSAFE_COUNTS or k.startswith("lockstep_dropped_")}
            if got:
                out[key[len(p):-len("/health")]] = got
    return out


def _motor_cut_in_air(pwm: list[dict], truth_t: np.ndarray, pos: np.ndarray, landed: np.ndarray,
                      in_flip: np.ndarray) -> float | None:
    """Time of the first motor output that is disarmed or asks no thrust of any motor while the
    truth (at that time) is airborne above MOTOR_CUT_ALTITUDE_M, outside a flip; or None."""
    if not pwm or truth_t.size == 0:
        return None
    out = _sorted(pwm)
    t = _times(out)
    cut = np.array([not x["armed"] or not any(x["thrust_n"]) for x in out])
    if not cut.any():
        return None
    t, idx = t[cut], np.searchsorted(truth_t, t[cut], side="right") - 1
    ok = idx >= 0
    t, idx = t[ok], idx[ok]
    air = ~landed[idx] & (pos[idx, 2] > MOTOR_CUT_ALTITUDE_M) & ~in_flip[idx]
    return float(t[air][0]) if air.any() else None


def _touchdown_speed(truth: list[dict], landed: np.ndarray) -> float | None:
    """Largest downward speed of the truth at its last sample before each touchdown; None
    when it never touched down from the air."""
    down = np.nonzero(landed[1:] & ~landed[:-1])[0]   # i: airborne at i, resting at i + 1
    if down.size == 0:
        return None
    return _f(max(max(0.0, -truth[i]["velocity_m_s"][2]) for i in down))
FLIP_PHASES = {"flip": "flip", "flip-recovery": "recovery"}  # setpoint phase -> flip.Phase


def _flip(log, p, sp, truth, truth_t, sp_idx) -> dict:
    """The flip object: flight.control.flip.flip_metrics on the truth (its first flip), the method,
    and the planner's re-solves as they ran (rate, compute time, failures)."""
    from flight.control.flip import flip_metrics

    phases = [FLIP_PHASES.get(sp[i]["phase"], "idle") for i in sp_idx]
    fm = flip_metrics(truth_t, [x["position_m"] for x in truth], [x["quaternion_wxyz"] for x in truth],
                      [x["rate_rad_s"] for x in truth], phases)
    out: dict[str, Any] = {k: (v if isinstance(v, bool) else _f(v)) for k, v in fm.__dict__.items()}
    flip_sp = [x for x in sp if x["phase"].startswith("flip")]
    out["turn_loss_m"] = _turn_loss(fm, truth, truth_t, phases)
    out["aborted"] = any(x["phase"] == "flip-aborted" for x in sp)
    out["refused"] = any(x["phase"] == "flip-refused" for x in sp)  # predicted unsafe, never started
    plans = _sorted(log.get(p + "planner/plan", []))
    out["method"] = plans[-1]["method"] if plans else None
    out["solves"] = plans[-1]["solves"] if plans else 0
    out["failed_solves"] = plans[-1]["failed_solves"] if plans else 0
    out["overrun_solves"] = plans[-1]["overrun_solves"] if plans else 0
    ms = np.array([x["solve_ms"] for x in plans], dtype=np.float64)
    out["solve_ms_p50"], out["solve_ms_p99"] = _pct(ms, 50), _pct(ms, 99)
    out["solve_ms_max"] = _f(ms.max()) if ms.size else None
    span = (flip_sp[-1]["header"]["t_s"] - flip_sp[0]["header"]["t_s"]) if len(flip_sp) > 1 else 0.0
    out["plan_rate_hz"] = _f(len(plans) / span) if span > 0 else None  # plans sent per second of flip item
    fallbacks: dict[str, int] = {}
    for h in _sorted(log.get(p + "motors/health", []))[-1:]:
        fallbacks = {k: int(v) for k, v in h["rejected"].items() if k.startswith("plan_fallback")}
    out["motor_fallbacks"] = fallbacks
    out["predicted"] = _predicted_against_flown(log, p, out)
    return out


def _turn_loss(fm, truth, truth_t, phases) -> float | None:
    """The height lost from the turn's start (flight.control.flip.heights), None without a completed flip."""
    from flight.control.flip import RollAccumulator, heights
    if not fm.completed:
        return None
    start = phases.index("flip")
    end = int(np.searchsorted(truth_t, truth_t[start] + fm.duration_s + 1e-9, side="right"))
    z = np.array([x["position_m"][2] for x in truth[start:end]])
    roll = RollAccumulator()
    roll.reset(truth[start]["quaternion_wxyz"])
    return _f(heights(z - z[0], [roll.update(x["quaternion_wxyz"]) for x in truth[start:end]])["turn_loss"])


# the planner's prediction's figures -> the flown figure of the same definition
PREDICTED_FIGURES = {"loss_from_turn_m": "turn_loss_m", "loss_from_hover_m": "altitude_loss_m",
                     "xy_drift_m": "xy_drift_m", "overshoot_deg": "overshoot_deg", "recovery_s": "recovery_s"}


def _predicted_against_flown(log, p, flown: dict) -> dict | None:
    """The planner's planner/flip_prediction for the method flown, each figure's band beside the
    flown value and whether it fell inside [p5, p95]; None when the planner predicted nothing."""
    preds = [x for x in _sorted(log.get(p + "planner/flip_prediction", []))
             if flown.get("method") in (None, x["method"])]
    if not preds:
        return None
    pred = preds[0]
    out: dict[str, Any] = {"rollouts": pred["rollouts"], "p_crash": _f(pred["p_crash"]), "refused": pred["refused"]}
    for name, flown_name in PREDICTED_FIGURES.items():
        band, value = pred[name], flown.get(flown_name)
        inside = (len(band) == 3 and value is not None and band[0] - 1e-3 <= value <= band[2] + 1e-3)
        out[name] = {"p5": _f(band[0]) if band else None, "p50": _f(band[1]) if band else None,
                     "p95": _f(band[2]) if band else None, "flown": value, "inside": bool(inside)}
    return out


NEES_BAND_95_3DOF = (0.2158, 9.3484)  # chi-square 2.5 % and 97.5 % points for 3 dof
FLYING_PHASES = ("settle", "hold", "goto", "attitude")  # mission phases that must be airborne


def _estimation(log, p, truth_t, truth_pos, truth_euler, landed) -> dict | None:
    """Truth against the estimates the controllers used, while airborne; None when
    the flight ran on truth."""
    pos = [x for x in _sorted(log.get(p + "pos/state", [])) if x["state_source"] == "estimate"]
    att = [x for x in _sorted(log.get(p + "att/state", [])) if x["state_source"] == "estimate"]
    if not (pos or att) or truth_t.size == 0:
        return None
    out: dict[str, Any] = {"position_rms_m": None, "attitude_rms_deg": None, "nees_mean": None}

    def truth_index(msgs):
        t = _times(msgs)
        idx = np.clip(np.searchsorted(truth_t, t + 1e-9, side="right") - 1, 0, truth_t.size - 1)
        return idx, ~landed[idx]

    if pos:
        idx, air = truth_index(pos)
        est = np.array([x["position_m"] for x in pos])[air]
        err = truth_pos[idx[air]] - est
        if len(err):
            out["position_rms_m"] = _f(np.sqrt(np.mean(np.sum(err**2, axis=1))))
            cov = np.array([x["position_cov_m2"] for x in pos])[air].reshape(-1, 3, 3)
            nees = np.array([e @ np.linalg.solve(c, e) for e, c in zip(err, cov)
                             if np.all(np.linalg.eigvalsh(c) > 0)])
            if nees.size:
                out["nees_mean"] = _f(np.mean(nees))
                out["nees_band_95"] = list(NEES_BAND_95_3DOF)
                out["nees_within_band_fraction"] = _f(np.mean((nees >= NEES_BAND_95_3DOF[0])
                                                              & (nees <= NEES_BAND_95_3DOF[1])))
        # the EKF's thrust scale when the flight ended (1 / the plant's mass_scale if learned)
        out["thrust_scale_final"] = _f(pos[-1].get("thrust_scale", 1.0))
    if att:
        idx, air = truth_index(att)
        est = np.array([x["euler_rad"] for x in att])[air]
        err = np.degrees(wrap_angle(truth_euler[idx[air]] - est))
        if len(err):
            out["attitude_rms_deg"] = _f(np.sqrt(np.mean(np.sum(err**2, axis=1))))
            for i, axis in enumerate(("roll", "pitch", "yaw")):
                out[f"{axis}_rms_deg"] = _f(np.sqrt(np.mean(err[:, i] ** 2)))
    return out


# --------------------------------------------------------------------------- table


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def format_table(metrics: dict) -> str:
    """Two-column text table: scalar metrics, latency, one line per service and per step."""
    rows: list[tuple[str, str]] = []
    for k, v in metrics.items():
        if not isinstance(v, (dict, list)):
            rows.append((k, _fmt(v)))
    for k, v in metrics.get("latency_ms", {}).items():
        rows.append((f"latency_ms.{k}", _fmt(v)))
    for k, v in (metrics.get("flip") or {}).items():
        if k == "predicted":
            continue
        rows.append((f"flip.{k}", _fmt(v) if not isinstance(v, dict) else str(v)))
    predicted = (metrics.get("flip") or {}).get("predicted") or {}
    for k in PREDICTED_FIGURES:
        if k in predicted:
            b = predicted[k]
            rows.append((f"flip predicted {k}", f"p5 {_fmt(b['p5'])} / p50 {_fmt(b['p50'])} / p95 {_fmt(b['p95'])}, "
                                                 f"flown {_fmt(b['flown'])} ({'inside' if b['inside'] else 'OUTSIDE'})"))
    for k, v in (metrics.get("estimation") or {}).items():
        rows.append((f"estimation.{k}", _fmt(v) if not isinstance(v, list) else str(v)))
    for k, v in (metrics.get("vision") or {}).items():
        rows.append((f"vision.{k}", _fmt(v)))
    rej = metrics.get("rejected_messages", {})
    for svc in sorted(set(metrics.get("rates_hz", {})) | set(rej)):
        r = rej.get(svc) or {}
        rtxt = ", ".join(f"{k}={n}" for k, n in sorted(r.items())) or "none"
        rows.append((f"service {svc}", f"{_fmt(metrics.get('rates_hz', {}).get(svc))} Hz, rejected: {rtxt}"))
    for kind, unit in (("attitude_steps", "deg"), ("position_steps", "m")):
        for s in metrics.get(kind, []):
            txt = (f"{_fmt(s[f'from_{unit}'])} -> {_fmt(s[f'to_{unit}'])} {unit}: "
                   f"rise {_fmt(s['rise_s'])} s, overshoot {_fmt(s['overshoot_pct'])} %, "
                   f"settle {_fmt(s['settle_s'])} s")
            if "monotone" in s:
                txt += f", monotone {_fmt(s['monotone'])}"
            if s.get("reference_delay_s") is not None:
                txt += (f" (at the attitude level, {1e3 * s['reference_delay_s']:.0f} ms after the setpoint;"
                        f" from the setpoint {_fmt(s['command_settle_s'])} s)")
            rows.append((f"{kind[:-1]} {s['axis']} @ {s['t_s']:.2f} s", txt))
    width = max((len(k) for k, _ in rows), default=0)
    return "\n".join(f"{k.ljust(width)}  {v}" for k, v in rows)
