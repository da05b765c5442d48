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
    ANCHOR_KNOTS,
    AnchoredPolicy,
    PredictError,
    Predictor,
    Uncertainty,
    anchor_extents,
    anchor_plant,
    build_predictor,
    case_parameters,
    draw_cases,
    fly_nominal,
    metrics_from_series,
    nominal_params,
)
from flight.control.replan import Replan
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
    # the nominal's policy in every case (adapt=False): 20 flights fewer, and pessimistic, which
    # only widens the harsh bands
    harsh = Predictor(predictor.nominal, Uncertainty(mass_frac=0.3, thrust_coefficient_frac=0.2,
                                                     wind_m_s=4.0, gust_m_s=1.0), adapt=False).predict(256, seed=3)
    assert calm.crash_probability == 0.0 and calm.band("xy_drift_m")[2] - calm.band("xy_drift_m")[0] < 1e-3
    np.testing.assert_array_equal(default.xy_drift_m, again.xy_drift_m)
    assert default.crash_probability <= 0.05 and default.refusal() is None
    for name in ("loss_from_hover_m", "xy_drift_m", "overshoot_deg"):
        assert harsh.band(name)[2] > default.band(name)[2] > calm.band(name)[2] - 1e-3, name
    assert 0.0 <= default.band("loss_from_turn_m")[0] and default.band("recovery_s")[1] < 1.0


def test_the_default_prediction_flies_the_controller_on_the_knots_of_every_drawn_parameter(predictor):
    policy = predictor.policy
    assert policy.flights == 2 * len(ANCHOR_KNOTS) * 5 and policy.flight_s > 0.0
    assert {name for name, _ in policy.columns} == {"mass", "inertia_x", "inertia_y", "inertia_z", "motor_lag"}
    assert policy.u_plan.shape[:2] == (1 + policy.flights, predictor.nominal.ticks)


def _fake_vehicle():
    from types import SimpleNamespace
    return SimpleNamespace(mass_kg=1.0, inertia_kg_m2=(0.01, 0.02, 0.03), motor_time_constant_s=0.02)


def test_anchor_weights_interpolate_through_the_knots_on_each_side():
    """A case's weights are those of the polynomial through the centre (0) and the knots of its
    side: at a knot all on that knot's row, exact for a parabola on each side (two knots), a
    line with one; each parameter's rows independently of the others'."""
    knots = [-0.05, -0.1, 0.04, 0.08]
    policy = AnchoredPolicy(None, None, None, [("mass", k) for k in knots] + [("motor_lag", 0.2)])
    e = np.array([-0.12, -0.1, -0.075, -0.05, -0.02, 0.0, 0.02, 0.04, 0.06, 0.08, 0.09])
    lag = np.linspace(-0.1, 0.3, e.size)   # its one knot: the centre's side below it, none on the other
    cases = {"mass": np.exp(e), "thrust_scale": np.ones_like(e), "tau": 0.02 * np.exp(lag),
             "inertia": np.tile([0.01, 0.02, 0.03], (e.size, 1))}
    w = policy.weights(_fake_vehicle(), Uncertainty(), cases)
    assert w.shape == (e.size, 6) and np.all(w[:, 0] == 1.0)
    k = np.array(knots)
    np.testing.assert_allclose(w[:, 1:5] @ k, e, atol=1e-6)                  # a line
    left, right = np.where(k < 0, k, 0.0), np.where(k > 0, k, 0.0)
    np.testing.assert_allclose(w[:, 1:5] @ (3 * left ** 2 - 2 * right ** 2),  # a parabola a side
                               np.where(e < 0, 3 * e ** 2, -2 * e ** 2), atol=1e-6)
    np.testing.assert_allclose(w[1], [1, 0, 1, 0, 0, 0], atol=1e-6)          # at a knot: its row
    np.testing.assert_allclose(w[5, :5], [1, 0, 0, 0, 0], atol=1e-6)         # the centre (the mass's)
    np.testing.assert_allclose(w[:, 5], np.maximum(lag, 0.0) / 0.2, atol=1e-6)


def test_the_thrust_scale_is_folded_into_mass_and_inertia():
    """A vehicle 5 % heavier with 5 % more thrust accelerates as the centre's: the anchors see it
    as the centre (mass / thrust, inertia / thrust)."""
    v = _fake_vehicle()
    cases = {"mass": np.array([1.05]), "thrust_scale": np.array([1.05]), "tau": np.array([0.02]),
             "inertia": np.array([[0.0105, 0.021, 0.0315]])}
    for value in case_parameters(v, Uncertainty(), cases).values():
        assert value[0] == pytest.approx(0.0, abs=1e-12)
    low, high = anchor_extents(Uncertainty(mass_frac=0.1, thrust_coefficient_frac=0.05))["mass"]
    assert math.exp(low) == pytest.approx(0.9 / 1.05) and math.exp(high) == pytest.approx(1.1 / 0.95)
    assert "mass" not in anchor_extents(Uncertainty.none())


def test_a_start_position_error_moves_the_flight_and_nothing_else(predictor):
    """The phase machine's targets are where the flip starts, and nothing in the model depends on
    the position: a case that starts 5 cm off flies the nominal flight 5 cm off (float32)."""
    nominal = predictor.nominal
    moved = Predictor(nominal, replace(Uncertainty.none(), position_sigma_m=0.05))
    assert moved.policy.flights == 0
    series, _, _ = moved.series(CALM_N, seed=1)
    cases, _ = draw_cases(nominal.vehicle, nominal, CALM_N, moved.uncertainty, 1)
    offset = cases["start_error"][:, 0:3].astype(np.float64)
    assert np.abs(offset).max() > 0.05
    for column, axis in ((0, 2), (1, 0), (2, 1)):
        np.testing.assert_allclose(series[:, :, column] - offset[:, axis:axis + 1],
                                   np.broadcast_to(nominal.states[:, axis], series.shape[:2]), atol=3e-3)


def test_a_case_on_a_knot_flies_the_controllers_flight_on_that_vehicle(predictor):
    """The anchors are the controller's own flights: a case drawn exactly at a knot (nothing else
    drawn) flies the flight of fly_nominal on that vehicle, not the nominal's."""
    nominal = predictor.nominal
    u = replace(Uncertainty.none(), mass_frac=0.1)
    anchored = Predictor(nominal, u)
    assert anchored.policy.flights == 2 * len(ANCHOR_KNOTS)   # the mass's knots, nothing else drawn
    name, knot = anchored.policy.columns[-1]
    plant = anchor_plant(nominal.vehicle, u, name, knot)
    flight = fly_nominal(nominal.vehicle, nominal.method, nominal.altitude_m, controller=nominal.controller,
                         plant=plant)
    cases, _ = draw_cases(nominal.vehicle, nominal, 1, u, seed=0)
    cases["mass"] = np.array([plant["mass"]], dtype=np.float32)
    cases["weights"] = anchored.policy.weights(nominal.vehicle, u, cases)
    assert cases["weights"][0, -1] == pytest.approx(1.0, abs=1e-5) and np.abs(cases["weights"][0, 1:-1]).max() < 1e-5
    series = np.asarray(anchored._rollouts(cases, *anchored.tables()), dtype=np.float64)[0]
    ticks = min(flight.ticks, nominal.ticks)
    np.testing.assert_allclose(series[:ticks, 0], flight.states[:ticks, 2], atol=3e-3)
    # and that flight is not the nominal's: the knot's vehicle turns differently
    assert np.abs(flight.states[:ticks, 6:10] - nominal.states[:ticks, 6:10]).max() > 0.02


def test_replanning_rollouts_replan_each_case_on_its_own_vehicle(predictor):
    """The re-planning rollouts (flight/control/replan.py, the nominal's linearisation): no anchor
    flights; with nothing drawn a case flies the nominal flight (the cheap re-plans' own error:
    5.7 cm of height, measured), and a case 10 % heavier re-plans its own flip: it follows the
    controller's flight on that vehicle (fly_nominal on it), which departs 0.24 m from the nominal's."""
    nominal = predictor.nominal
    replanning = Predictor(nominal, Uncertainty.none(), replan=Replan(100.0, linearise="nominal"))
    assert replanning.policy.flights == 0
    cases, _ = draw_cases(nominal.vehicle, nominal, 2, Uncertainty.none(), seed=0)
    cases["mass"][1] *= 1.1
    series = np.asarray(replanning._rollouts(cases, *replanning.tables()), dtype=np.float64)
    assert series.shape == (2, nominal.ticks, 6)
    assert np.abs(series[0, :, 0] - nominal.states[:, 2]).max() < 0.08
    plant = nominal_params(nominal.vehicle) | {"mass": np.float32(nominal.vehicle.mass_kg * 1.1)}
    heavy = fly_nominal(nominal.vehicle, nominal.method, nominal.altitude_m, controller=nominal.controller,
                        plant=plant)
    ticks = min(heavy.ticks, nominal.ticks)
    assert np.abs(series[1, :ticks, 0] - heavy.states[:ticks, 2]).max() < 0.1
    assert np.abs(series[1, :ticks, 0] - nominal.states[:ticks, 2]).max() > 0.15
    m = metrics_from_series(series, nominal.flip_tick, nominal.tick_s, nominal.altitude_m)
    assert m["completed"].all() and m["overshoot_deg"][1] > m["overshoot_deg"][0] + 1.0


def test_replanning_rollouts_with_the_planners_solve_are_the_flown_loop(predictor):
    """linearise="solver": each case runs the planner's own solve at its rate, so with nothing
    drawn the rollout is the nominal flight itself (float32 against float64)."""
    nominal = predictor.nominal
    exact = Predictor(nominal, Uncertainty.none(), replan=Replan(100.0, linearise="solver"))
    cases, _ = draw_cases(nominal.vehicle, nominal, 1, Uncertainty.none(), seed=0)
    series = np.asarray(exact._rollouts(cases, *exact.tables()), dtype=np.float64)[0]
    np.testing.assert_allclose(series[:, 0], nominal.states[:, 2], atol=0.02)   # measured 9 mm, 4 mm
    np.testing.assert_allclose(series[:, 1], nominal.states[:, 0], atol=0.01)


def test_bad_replan_settings_are_refused():
    for bad in ({"rate_hz": 33.0}, {"rate_hz": 0.0}, {"iterations": 0}, {"horizon": 1}, {"alphas": (0.0,)},
                {"linearise": "sometimes"}, {"rate_hz": float("nan")}):
        with pytest.raises(PredictError, match="replan"):
            Replan(**bad)


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
    """One run (it flies the nominal, the controller on the mass's knots and 256 rollouts): the
    table, the JSON, and the item refused when the clearance asked for leaves no room for its loss
    (exit 1, the reason printed). Only the mass drawn among the vehicle's parameters (the thrust's
    spread scales the inertia too): 4 flights on the knots, not the default's 20 (~11 s of CPU;
    the default policy is the fixture's, tested above), still the adapted path. With the run's
    compilation cache: the solver is the one the tests above compiled, so it loads it."""
    out = tmp_path / "p.json"
    run = subprocess.run([sys.executable, "-m", "deploy.cli", "predict", "--mission", "flip", "-n", "256",
                          "--inertia-frac", "0", "--thrust-frac", "0", "--motor-lag-frac", "0",
                          "--clearance-m", "4.99", "--json", str(out), "--compile-cache-dir", jax_compile_cache],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 1, run.stdout + run.stderr
    assert "altitude loss from the hover height" in run.stdout and "REFUSED: predicted" in run.stdout, run.stdout
    assert f"{2 * len(ANCHOR_KNOTS)} flights on the knots' vehicles" in run.stdout, run.stdout
    item = json.loads(out.read_text())["items"][0]
    assert item["method"] == "ilqr-project" and item["rollouts"] == 256 and "95th-percentile" in item["refused"]
    assert item["loss_from_hover_m"]["p95"] > 0.01
    bad = subprocess.run([sys.executable, "-m", "deploy.cli", "predict", "-n", "0"],
                         cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--rollouts must be >= 1" in bad.stderr and "Traceback" not in bad.stderr
    no_flip = subprocess.run([sys.executable, "-m", "deploy.cli", "predict", "--mission", "hover"],
                             cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert no_flip.returncode == 2 and "has no flip item" in no_flip.stderr


def test_cli_replay_and_replan_flags_ask_for_their_models(monkeypatch, capsys):
    """`zenpilot predict --replay` builds the predictor with adapt=False (no flights on the knots);
    without it, adapt=True. The predictor is stubbed: only what the command asks for is checked."""
    import argparse

    import flight.control.predict as predict
    from deploy import predict_cli
    asked = []

    def build(vehicle, method, altitude_m, uncertainty, adapt=True, replan=None):
        asked.append((adapt, replan))
        raise PredictError("stub")
    monkeypatch.setattr(predict, "build_predictor", build)
    parser = argparse.ArgumentParser()
    predict_cli.add_parser(parser.add_subparsers())
    for argv, adapt in ((["predict", "--replay"], False), (["predict"], True)):
        args = parser.parse_args(argv)
        assert args.func(args) == 0 and asked[-1] == (adapt, None)
    assert "cannot predict: stub" in capsys.readouterr().out
    # --replan: every case re-plans with the planner's own solve at its rate; not with --replay
    args = parser.parse_args(["predict", "--replan"])
    assert args.func(args) == 0 and asked[-1] == (True, Replan(100.0, linearise="solver"))
    with pytest.raises(ValueError, match="two models"):
        args = parser.parse_args(["predict", "--replan", "--replay"])
        args.func(args)
