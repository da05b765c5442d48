"""bench/predict_calibration.py's cache of flown flights: a re-run flies only what is missing."""
import json
import math

from bench import predict_calibration as bench


def test_flown_flights_are_cached_and_only_the_missing_flown(tmp_path, monkeypatch):
    flown = []

    def fake_fly(controller, vehicle, cases, i, ticks, uncertainty):
        flown.append(i)
        return {"completed": True, "loss_from_turn_m": 0.1 * i, "loss_from_hover_m": 0.0, "xy_drift_m": 0.2,
                "overshoot_deg": float("nan"), "recovery_s": 0.4}
    monkeypatch.setattr(bench, "fly_case", fake_fly)

    def run(flights, row="wind-2m/s", seed=1002):
        return bench.flown_figures(None, None, {}, flights, 10, None, tmp_path, row, seed)
    first = run(3)
    assert flown == [0, 1, 2] and [f["loss_from_turn_m"] for f in first] == [0.0, 0.1, 0.2]
    path = tmp_path / "wind-2m_s-seed1002-n3.json"
    cached = json.loads(path.read_text())
    del cached["1"]                      # as if the run had stopped before flight 1
    path.write_text(json.dumps(cached))
    again = run(3)
    assert flown == [0, 1, 2, 1] and again[1]["loss_from_turn_m"] == 0.1 and math.isnan(again[2]["overshoot_deg"])
    run(3, seed=2002)                    # another draw: its own file, flown
    assert flown == [0, 1, 2, 1, 0, 1, 2]
    assert bench.flown_figures(None, None, {}, 2, 10, None, None, "nominal", 1000) and flown[-2:] == [0, 1]
