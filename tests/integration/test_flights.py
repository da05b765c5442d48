"""Whole flights, every service a process, in lockstep (quality) and real time (it flies)."""

import json

import pytest

from schemas import REASONS

from .conftest import TRUTH_STATE, fly

pytestmark = pytest.mark.integration


def test_truth_state_hover_lockstep_holds_within_a_centimetre(hover_lockstep):
    out, (proc, m) = hover_lockstep
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert m["completed"] and not m["crashed"] and m["mode"] == "lockstep" and m["vehicle"] == "x250"
    assert m["measured_s"] >= 9.9  # the 10 s hold was measured
    assert m["position_rms_m"] < 0.01
    for service, rate in {"sim": 400, "motors": 400, "attitude": 200, "position": 100, "planner": 50}.items():
        assert m["rates_hz"][service] == pytest.approx(rate, rel=0.01), service
    # no message was rejected (vision's "pose_*" counts are frames it could not solve)
    assert all(not set(r) & set(REASONS) for r in m["rejected_messages"].values())
    for plot in ("position.png", "attitude.png", "motors.png"):
        assert (out / plot).stat().st_size > 10_000
    page = (out / "report.html").read_text()   # one page: the plots inlined, the mission and stack files
    assert page.count("data:image/png;base64,") >= 3 and "[mission]" in page and "[stack]" in page


def test_lockstep_is_deterministic(hover_lockstep, hover_lockstep_live, tmp_path):
    """Same seed, same bytes: and the same whether the services run as threads of one process
    (the default, as the fixture flew) or each in its own process over the router (the flight
    test_foxglove's live view watched: `--foxglove` flies as `--processes` does, a viewer beside)."""
    out, (_, first) = hover_lockstep
    again_out, proc, said, _, _ = hover_lockstep_live
    assert proc.returncode == 0, said
    again = json.loads((again_out / "metrics.json").read_text())
    assert again == first
    assert (again_out / "flight.mcap").read_bytes() == (out / "flight.mcap").read_bytes()
    _, other = fly(tmp_path / "other-seed", "hover", *TRUTH_STATE, seed=1)
    assert other["seed"] == 1  # another seed: other sensor noise in the log
    assert (tmp_path / "other-seed" / "flight.mcap").read_bytes() != (out / "flight.mcap").read_bytes()


def test_attitude_steps_reproduce_figure_4(tmp_path):
    proc, m = fly(tmp_path, "attitude-steps", *TRUTH_STATE)
    assert m["completed"], proc.stdout
    steps = m["attitude_steps"]
    assert len(steps) == 8 and {s["axis"] for s in steps} == {"roll", "pitch"}
    for s in steps:
        assert abs(abs(s["to_deg"] - s["from_deg"]) - 10.0) < 0.01
        assert s["rise_s"] <= 0.25, s
        assert s["overshoot_pct"] <= 2.0, s
        assert s["settle_s"] is not None and s["settle_s"] <= 0.35, s
        assert s["monotone"], s


def test_position_steps_settle_within_4_s(tmp_path):
    proc, m = fly(tmp_path, "steps", *TRUTH_STATE)
    assert m["completed"], proc.stdout
    axes = {s["axis"] for s in m["position_steps"]}
    assert axes == {"x", "y", "z"}
    for s in m["position_steps"]:
        assert s["settle_s"] is not None and s["settle_s"] <= 4.0, s
        assert s["overshoot_pct"] <= 10.0, s
    assert m["position_rms_m"] < 0.01


@pytest.mark.realtime
def test_hover_real_time(hover_real_time):
    out, (proc, m) = hover_real_time
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert m["completed"] and m["mode"] == "realtime"
    assert m["position_rms_m"] < 0.02
    assert m["latency_ms"]["imu_to_pwm_p50"] is not None
    for service in ("sim", "motors", "attitude", "position", "planner"):
        assert m["rates_hz"][service] > 0
    metrics_text = (out / "metrics.json").read_text()
    assert "NaN" not in metrics_text and json.loads(metrics_text)
