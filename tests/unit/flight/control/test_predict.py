"""The flip's predicted envelope (flight/control/predict.py, `zenpilot predict`)."""
import json
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from flight.control.flip import flip_metrics, heights
from flight.control.predict import (
    PredictError,
    Predictor,
    Uncertainty,
    build_predictor,
    metrics_from_series,
)
from flight.vehicle import load_vehicle

ROOT = Path(__file__).resolve().parents[4]


@pytest.fixture(scope="module")
def predictor():
    """The project's flip from 5 m on the q820, flown once on the planner's model (compiles)."""
    return build_predictor(load_vehicle("q820"), "ilqr-project", 5.0)


CALM_N = 64  # the rollouts with nothing drawn: one batch size, so one compile for every test


@pytest.fixture(scope="module")
def calm_predictor(predictor):
    """The nominal flight's rollouts with nothing drawn: every case flies the nominal flight."""
    return Predictor(predictor.nominal, Uncertainty.none())


def test_rollouts_without_uncertainty_replay_the_nominal_flight(predictor, calm_predictor):
    """The batched rollout is the nominal flight's loop: with nothing drawn it flies the same
    states (float32 against float64: within a millimetre over the whole flip)."""
    nominal = predictor.nominal
    series, _, _ = calm_predictor.series(CALM_N, seed=0)
    shape = (CALM_N, nominal.ticks)
    assert series.shape == shape + (6,)
    np.testing.assert_allclose(series[:, :, 0], np.broadcast_to(nominal.states[:, 2], shape), atol=2e-3)
    np.testing.assert_allclose(series[:, :, 1], np.broadcast_to(nominal.states[:, 0], shape), atol=2e-3)


def test_vectorised_metrics_are_flip_metrics(predictor, calm_predictor):
    """metrics_from_series gives flight.control.flip.flip_metrics' figures for the nominal flight."""
    nominal = predictor.nominal
    series, _, _ = calm_predictor.series(CALM_N, seed=0)
    m = metrics_from_series(series, nominal.flip_tick, nominal.tick_s, nominal.altitude_m)
    t = np.arange(nominal.ticks) * nominal.tick_s
    ref = flip_metrics(t, nominal.states[:, 0:3], nominal.states[:, 6:10], nominal.states[:, 10:13], nominal.phases)
    assert ref.completed and bool(m["completed"][0])
    assert m["loss_from_hover_m"][0] == pytest.approx(ref.altitude_loss_m, abs=2e-3)
    roll = series[0, nominal.flip_tick:, 3] - series[0, nominal.flip_tick, 3]
    span = slice(nominal.flip_tick, nominal.flip_tick + int(round(ref.duration_s / nominal.tick_s)) + 1)
    turn = heights(nominal.states[span, 2] - nominal.states[nominal.flip_tick, 2], roll[:span.stop - span.start])
    assert m["loss_from_turn_m"][0] == pytest.approx(turn["turn_loss"], abs=2e-3)
    assert m["xy_drift_m"][0] == pytest.approx(ref.xy_drift_m, abs=2e-3)
    assert m["overshoot_deg"][0] == pytest.approx(ref.overshoot_deg, abs=0.2)
    assert m["recovery_s"][0] == pytest.approx(ref.recovery_s, abs=2 * nominal.tick_s)
    # the flip of docs/flip.md on the planner's model: no height lost, ~0.23 m drift, ~12 deg
    assert ref.altitude_loss_m < 0.05 and 0.1 < ref.xy_drift_m < 0.4 and 5 < ref.overshoot_deg < 20


def test_prediction_spreads_with_the_uncertainty_and_is_deterministic(predictor, calm_predictor):
    calm = calm_predictor.predict(CALM_N, seed=0)
    default = predictor.predict(256, seed=3)
    again = predictor.predict(256, seed=3)
    harsh = Predictor(predictor.nominal, Uncertainty(mass_frac=0.3, thrust_coefficient_frac=0.2,
                                                     wind_m_s=4.0, gust_m_s=1.0)).predict(256, seed=3)
    assert calm.crash_probability == 0.0 and calm.band("xy_drift_m")[2] - calm.band("xy_drift_m")[0] < 1e-3
    np.testing.assert_array_equal(default.xy_drift_m, again.xy_drift_m)
    assert default.crash_probability <= 0.05 and default.refusal() is None
    for name in ("loss_from_hover_m", "xy_drift_m", "overshoot_deg"):
        assert harsh.band(name)[2] > default.band(name)[2] > calm.band(name)[2] - 1e-3, name
    assert 0.0 <= default.band("loss_from_turn_m")[0] and default.band("recovery_s")[1] < 1.0


def test_a_flip_without_the_height_it_needs_is_refused_with_the_reason(predictor):
    result = predictor.predict(256, seed=0)
    p95 = result.band("loss_from_hover_m")[2]
    assert result.refusal(clearance_m=result.altitude_m - p95 - 0.05) is None
    reason = result.refusal(clearance_m=result.altitude_m - p95 + 0.05)
    assert reason is not None and "95th-percentile altitude loss" in reason, reason
    crashing = replace(result, crashed=np.ones(result.n, dtype=bool))
    assert "P(crash) 100.0%" in crashing.refusal()


def test_bad_uncertainty_and_the_baseline_are_refused():
    with pytest.raises(PredictError, match="mass_frac"):
        Uncertainty(mass_frac=-0.1)
    with pytest.raises(PredictError, match="wind_m_s"):
        Uncertainty(wind_m_s=math.nan)
    with pytest.raises(PredictError, match="baseline"):
        build_predictor(load_vehicle("q820"), "baseline", 5.0)


def test_cli_prints_the_envelope_and_refuses_bad_arguments(tmp_path, jax_compile_cache):
    """One run (it flies the nominal and 256 rollouts): the table, the JSON, and the item refused
    when the clearance asked for leaves no room for its loss (exit 1, the reason printed). With the
    run's compilation cache: the solver and the 256 default rollouts are those the tests above
    compiled (the same shapes), so it loads them."""
    out = tmp_path / "p.json"
    run = subprocess.run([sys.executable, "-m", "deploy.cli", "predict", "--mission", "flip", "-n", "256",
                          "--clearance-m", "4.99", "--json", str(out), "--compile-cache-dir", jax_compile_cache],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 1, run.stdout + run.stderr
    assert "altitude loss from the hover height" in run.stdout and "REFUSED: predicted" in run.stdout, run.stdout
    item = json.loads(out.read_text())["items"][0]
    assert item["method"] == "ilqr-project" and item["rollouts"] == 256 and "95th-percentile" in item["refused"]
    assert item["loss_from_hover_m"]["p95"] > 0.01
    bad = subprocess.run([sys.executable, "-m", "deploy.cli", "predict", "-n", "0"],
                         cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--rollouts must be >= 1" in bad.stderr and "Traceback" not in bad.stderr
    no_flip = subprocess.run([sys.executable, "-m", "deploy.cli", "predict", "--mission", "hover"],
                             cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert no_flip.returncode == 2 and "has no flip item" in no_flip.stderr
