"""`zenpilot sweep`'s grid: seeds, values, parameters and scenarios checked and expanded
(deploy/sweep.py; the flights themselves: tests/integration/test_sweep.py)."""

import json

import pytest

from deploy.cli import build_parser
from deploy.sweep import (SCENARIOS, Flight, expand_grid, flatten, flight_status, make_row, parse_seeds, split_values,
                          write_tables)
from services.stack import StackError


def test_seeds_ranges_and_lists():
    assert parse_seeds("0-99") == list(range(100))
    assert parse_seeds("1,3,5") == [1, 3, 5]
    assert parse_seeds("0-2, 10") == [0, 1, 2, 10]
    assert parse_seeds("7") == [7]


@pytest.mark.parametrize("bad, said", [("5-2", "runs backwards"), ("x", "not a seed or a range"),
                                       ("1,,2", "not a seed"), ("-3", "not a seed"), ("0-3,2", "given twice"),
                                       ("0-999999", "more than")])
def test_bad_seeds_refused(bad, said):
    with pytest.raises(StackError, match=said):
        parse_seeds(bad)


def test_values_split_outside_brackets():
    assert split_values("8,12,16") == ["8", "12", "16"]
    assert split_values("[8,8,6],[12,12,6]") == ["[8,8,6]", "[12,12,6]"]
    assert split_values('"a,b",c') == ['"a,b"', "c"]


def test_grid_is_the_product_seed_major():
    grid = expand_grid(["hover"], "0-2", ["attitude.k=8,12,16", "sim.camera_drop_rate=0.0,0.2"],
                       ["nominal,wind-2m/s"])
    assert len(grid.flights) == 3 * 3 * 2 * 2
    assert [f.seed for f in grid.flights[:12]] == [0] * 12            # every point at seed 0 first
    assert len({f.id for f in grid.flights}) == len(grid.flights)      # a folder each
    assert grid.dimensions == ["attitude.k", "sim.camera_drop_rate", "scenario"]
    f = grid.flights[0]
    argv = f.fly_argv()
    assert argv[:7] == ["fly", "--mission", "hover", "--seed", "0", "--lockstep", "--no-plots"]
    assert "--out" not in argv and "--port" not in argv               # the task's own
    # a number for a list of numbers sets every element, as the service reads it
    assert "attitude.k=[8.0,8.0,8.0]" in argv
    assert f.values()["attitude.k"] == "8"


def test_scenarios_and_fixed_settings_reach_the_flight():
    grid = expand_grid(["hover"], "0", None, ["wind-2m/s"], ["attitude.k=[12,12,12]"])
    (f,) = grid.flights
    assert f.set_items() == [*SCENARIOS["wind-2m/s"], "attitude.k=[12,12,12]"]
    assert grid.dimensions == []       # nothing varies but the (single) seed
    assert f.id == "hover-wind-2m_s-seed0"


def test_list_values_kept_whole():
    grid = expand_grid(["hover"], "0", ["attitude.k=[8,8,6],[12,12,6]"])
    assert [f.values()["attitude.k"] for f in grid.flights] == ["[8,8,6]", "[12,12,6]"]
    assert len({f.id for f in grid.flights}) == 2


@pytest.mark.parametrize("params, scenarios, sets, said", [
    (["attitude.kk=8"], None, None, "unknown parameter 'kk'"),
    (["atitude.k=8"], None, None, "no service 'atitude'"),
    (["attitude.k=fast"], None, None, "expected list"),
    (["attitude.k=[1,2]"], None, None, "expected 3 values"),
    (["attitude.state_source=1"], None, None, "expected str"),
    (["attitude.k"], None, None, "expected SERVICE.KEY=V1,V2"),
    (["attitude.k=8,"], None, None, "empty value"),
    (["attitude.k=8,8"], None, None, "given twice"),
    (["attitude.k=8", "attitude.k=12"], None, None, "given twice"),
    (["attitude.k=8,12"], None, ["attitude.k=[1,1,1]"], "also fixed by --set"),
    (None, ["windy"], None, "unknown .*scenarios: nominal"),
    (None, None, ["sim.mass=2"], "unknown parameter 'mass'"),
    # bounds and choices, as the service checks them at start: refused before any flight
    (["attitude.k=8,500"], None, None,
     r"--param 'attitude\.k=500': attitude\.k: \[500\.0, 500\.0, 500\.0\] outside \[0\.1, 200\] 1/s"),
    (["attitude.k=[8,8,0]"], None, None, r"attitude\.k: \[8\.0, 8\.0, 0\.0\] outside \[0\.1, 200\]"),
    (["sim.mass_scale=1.0,11"], None, None, r"--param 'sim\.mass_scale=11': sim\.mass_scale: 11\.0 outside \[0\.1, 10\]"),
    (None, None, ["attitude.setpoint_timeout_s=0"],
     r"--set 'attitude\.setpoint_timeout_s=0': attitude\.setpoint_timeout_s: 0\.0 outside \(0, inf\) s"),
    (['attitude.state_source="estimate","guess"'], None, None, r"attitude\.state_source: 'guess' not one of"),
])
def test_bad_grids_refused(params, scenarios, sets, said):
    with pytest.raises(StackError, match=said):
        expand_grid(["hover"], "0", params, scenarios, sets)


def test_missions_checked_when_asked():
    def no_such(name):
        raise StackError(f"no mission {name!r}")
    with pytest.raises(StackError, match="no mission 'nope'"):
        expand_grid(["nope"], "0", check_mission=no_such)
    grid = expand_grid(["hover,steps"], "0-1")
    assert len(grid.flights) == 4 and grid.dimensions == ["mission"]


def test_rows_flatten_metrics_and_failed_rows_keep_the_grid(tmp_path):
    flight = Flight("hover", "nominal", 3, (("attitude.k", "8", "[8.0,8.0,8.0]"),))
    metrics = {"mission": "hover", "seed": 3, "completed": True, "crashed": False, "position_rms_m": 0.002,
               "estimation": {"nees_band_95": [0.2, 9.3], "attitude_rms_deg": 0.25}, "flip": None,
               "failsafes": {}}
    ok = make_row(flight, {"metrics": metrics, "wall_s": 12.5, "attempts": 1, "resumed": False}, None, tmp_path)
    assert ok["status"] == "ok" and ok["attitude.k"] == "8" and ok["seed"] == 3
    assert ok["estimation.attitude_rms_deg"] == 0.25 and json.loads(ok["estimation.nees_band_95"]) == [0.2, 9.3]
    failed = make_row(flight, None, "exit status 2: bad", tmp_path)
    assert failed["status"] == "failed" and failed["error"] == "exit status 2: bad" and failed["attitude.k"] == "8"
    assert flight_status({"completed": True, "crashed": True}) == "crashed"
    assert flight_status({"completed": False}) == "incomplete"
    assert flatten({"a": {"b": {"c": 1}}, "d": {}}) == {"a.b.c": 1, "d": None}
    csv_path, pq_path = write_tables([ok, failed], tmp_path, ["attitude.k"])
    header = csv_path.read_text().splitlines()[0].split(",")
    assert header[:6] == ["flight", "status", "mission", "scenario", "seed", "attitude.k"]
    import pyarrow.parquet as pq
    table = pq.read_table(pq_path)
    assert table.num_rows == 2 and table.column("status").to_pylist() == ["ok", "failed"]


def test_sweep_help_documents_the_cluster(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["sweep", "--help"])
    text = capsys.readouterr().out
    for word in ("--workers", "--scheduler", "LocalCluster", "tcp://", "--seeds", "--param", "--scenario",
                 "sweep.parquet", "retried"):
        assert word in text


def test_a_scenario_out_of_bounds_is_refused_naming_it():
    with pytest.raises(StackError, match=r"--scenario heavy 'sim\.mass_scale=20': sim\.mass_scale: 20\.0 "
                                         r"outside \[0\.1, 10\]"):
        expand_grid(["hover"], "0", None, ["heavy"], scenario_table={"heavy": ("sim.mass_scale=20",)})


def test_a_value_out_of_bounds_stops_the_sweep_before_any_flight(tmp_path, monkeypatch):
    import deploy.sweep

    def fly(*a, **k):
        raise AssertionError("a flight was started")
    monkeypatch.setattr(deploy.sweep, "run_sweep", fly)
    monkeypatch.setattr(deploy.sweep, "fly_task", fly)
    args = build_parser().parse_args(["sweep", "--param", "attitude.k=8,12,300", "--seeds", "0-3",
                                      "--out", str(tmp_path / "sweep")])
    with pytest.raises(StackError, match=r"attitude\.k: \[300\.0, 300\.0, 300\.0\] outside \[0\.1, 200\]"):
        args.func(args)
    assert not (tmp_path / "sweep").exists()
