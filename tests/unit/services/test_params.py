"""Parameters are declared once (services/params/): every declaration complete, checked at start-up
with the file, section and key, the MAVLink table and docs/parameters.md generated from them, the
default stack file holding only overrides."""

from __future__ import annotations

import dataclasses
import importlib
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from flight.control.failsafe import DescentParams
from flight.estimation.attitude_filter import AttitudeFilterParams
from flight.estimation.camera_level import CameraLevelParams
from flight.estimation.camera_delay import CameraDelayParams
from flight.estimation.gyro_carrier import GyroCarrierParams
from flight.estimation.position_ekf import PositionEKFError, PositionEKFParams
from flight.param import declarations
from services.mavlink_logic import BRIDGE_PARAM_DEFAULTS, TUNABLE, TUNABLE_DEFAULTS, ParamTable
from services.params import Param, values
from services.params.reference import DECLARED, render
from services.stack import DEFAULT_STACK, SERVICE_MODULES, StackError, check_compatible, load_stack, resolve_params
from simulator.config import SimConfig

ROOT = Path(__file__).resolve().parents[3]
WHERE = "s.toml: [services.attitude.params]"


def stack_file(path: Path, params: str = "") -> Path:
    """A small stack file, with `params` (TOML tables) after its services."""
    needed = ("sim", "motors", "attitude", "position", "planner")
    services = "".join(f"[services.{s}]\nrate_hz = 100.0\n" for s in needed)
    path.write_text(f'[machines.vehicle]\nrouter = "tcp/127.0.0.1:7447"\n{services}{params}')
    return path


def test_every_service_declares_every_parameter_with_a_doc():
    assert set(DECLARED) | {"recorder"} == set(SERVICE_MODULES)
    for service, module in SERVICE_MODULES.items():
        params = importlib.import_module(module).PARAMS
        assert params is DECLARED.get(service, params), f"{service}: PARAMS is not its declarations"
        for key, p in params.items():
            assert isinstance(p, Param), f"{service}.{key}"
            assert p.doc and "\n" not in p.doc, f"{service}.{key}: a one-line doc"
            listed = p.default if isinstance(p.default, list) else [p.default]   # a list: each element
            assert not p.choices or all(v in p.choices for v in listed), f"{service}.{key}"
            assert resolve_params(params, {key: p.value()}, service)[key] == p.default   # within its own bounds


# every nested table a service parameter holds, and the dataclass that owns its keys
NESTED = {("attitude", "filter"): AttitudeFilterParams, ("attitude", "failsafe_descent"): DescentParams,
          ("attitude", "camera_level_settings"): CameraLevelParams, ("attitude", "carrier"): GyroCarrierParams,
          ("motors", "failsafe_descent"): DescentParams, ("position", "ekf"): PositionEKFParams,
          ("position", "camera_delay"): CameraDelayParams}


def test_every_nested_table_declares_every_key_with_unit_bounds_and_doc():
    """A nested table's keys are its owner's fields, each declared (default, unit, bounds, one-line
    doc), the defaults the owner's and within their bounds; only the MAVLink bridge's per-stream
    rates (free stream names) stay an open table."""
    tables = {(s, k): p.table for s, ps in DECLARED.items() for k, p in ps.items() if isinstance(p.default, dict)}
    assert {k: t for k, t in tables.items() if t is not None} == NESTED
    assert [k for k, t in tables.items() if t is None] == [("mavlink", "rates_hz")]
    for (service, key), owner in NESTED.items():
        assert DECLARED[service][key].default == {}   # every key at its owner's default
        fields = dataclasses.fields(owner)
        assert list(declarations(owner)) == [f.name for f in fields]
        for f in fields:
            p = f.metadata["param"]
            assert p.doc and "\n" not in p.doc, f"{service}.{key}.{f.name}: a one-line doc"
            assert p.default == f.default and p.check(p.value(), f.name) == f.default, f"{service}.{key}.{f.name}"
            if isinstance(p.default, float):
                assert p.unit or p.min is not None, f"{service}.{key}.{f.name}: a number with no unit nor bounds"
        assert owner.from_dict({}) == owner()
        assert resolve_params(DECLARED[service], {key: {}}, service)[key] == {}


@pytest.mark.parametrize("service, given, needle", [
    ("attitude", {"filter": {"lpf_tau_s": -1.0}},
     "[services.attitude.params].filter.lpf_tau_s: -1.0 outside (0, inf) s"),
    ("attitude", {"filter": {"rate_meas_var": [1e-5, 1e-5]}},
     "[services.attitude.params].filter.rate_meas_var: expected 3 values"),
    ("attitude", {"filter": {"max_delay_steps": 2.5}}, "[services.attitude.params].filter.max_delay_steps: expected int"),
    ("attitude", {"filter": {"lpf": 0.02}}, "[services.attitude.params].filter.lpf: unknown key (known: lpf_tau_s, "),
    ("attitude", {"filter": {"mag_field_world_ut": [0.0, 0.0, -45.0]}},
     "[services.attitude.params].filter: AttitudeFilterParams.mag_field_world_ut: needs a horizontal component"),
    ("attitude", {"carrier": {"exit_tilt_deg": 50.0}},
     "[services.attitude.params].carrier: GyroCarrierParams: need exit_tilt_deg <= enter_tilt_deg"),
    ("attitude", {"camera_level_settings": {"gate_rad": 0}},
     "[services.attitude.params].camera_level_settings.gate_rad: 0.0 outside (0, inf) rad"),
    ("attitude", {"failsafe_descent": {"sink_rate_m_s": "fast"}},
     "[services.attitude.params].failsafe_descent.sink_rate_m_s: expected float, got 'fast'"),
    ("motors", {"failsafe_descent": {"max_thrust_fraction": 1.5}},
     "[services.motors.params].failsafe_descent.max_thrust_fraction: 1.5 outside (0, 1]"),
    ("position", {"ekf": {"gate_probability": 0.0}}, "[services.position.params].ekf.gate_probability: 0.0 outside (0, 1]"),
    ("position", {"ekf": {"max_delay_s": float("inf")}}, "[services.position.params].ekf.max_delay_s: inf outside [0, inf) s"),
    ("position", {"ekf": 0.3}, "[services.position.params].ekf: expected dict, got 0.3"),
])
def test_bad_nested_values_are_refused_with_the_table_and_key(service, given, needle):
    with pytest.raises(StackError) as err:
        resolve_params(DECLARED[service], given, f"s.toml: [services.{service}.params]")
    assert str(err.value).startswith("s.toml: ") and needle in str(err.value), str(err.value)


def test_nested_values_are_checked_as_their_owner_takes_them():
    """One check for a key however it comes: a stack file's table, or the owner built in code
    (the same words, the owner's name for where); a per-axis number is every axis."""
    given = {"filter": {"rate_meas_var": 2e-5, "max_delay_steps": 4}, "carrier": {"enter_tilt_deg": 50}}
    params = resolve_params(DECLARED["attitude"], given, WHERE)
    assert params["filter"] == given["filter"] and params["carrier"] == given["carrier"]   # plain values, as given
    f = AttitudeFilterParams.from_dict(params["filter"])
    assert f.rate_meas_var == (2e-5, 2e-5, 2e-5) and f.max_delay_steps == 4
    assert GyroCarrierParams.from_dict(params["carrier"]).enter_tilt_deg == 50.0
    with pytest.raises(PositionEKFError, match=r"^PositionEKFParams.max_delay_s: -0.1 outside \[0, inf\) s$"):
        PositionEKFParams(max_delay_s=-0.1)
    with pytest.raises(ValueError, match=r"^DescentParams.ramp_s: 0.0 outside \(0, inf\) s$"):
        DescentParams(ramp_s=0.0)
    with pytest.raises(ValueError, match=r"^simulator.camera_drop_rate: 2.0 outside \[0, 1\]$"):
        SimConfig(camera_drop_rate=2.0)


def test_runtime_values_are_plain_copies():
    v = values(DECLARED["attitude"])
    assert v["k"] == [16.0, 16.0, 16.0] and isinstance(v["k"], list)
    v["k"][0] = 1.0
    assert DECLARED["attitude"]["k"].default == [16.0, 16.0, 16.0]


@pytest.mark.parametrize("given, needle", [
    ({"k": [16.0, 0.0, 16.0]}, "[services.attitude.params].k: [16.0, 0.0, 16.0] outside [0.1, 200] 1/s"),
    ({"stopping_accel_fraction": 1.5}, "[services.attitude.params].stopping_accel_fraction: 1.5 outside [0, 1]"),
    ({"accel_window_s": 0.0}, "[services.attitude.params].accel_window_s: 0.0 outside (0, 0.5] s"),
    ({"accel_window_s": float("nan")}, "accel_window_s: nan outside (0, 0.5] s"),
    ({"estimator": "ekf"}, "[services.attitude.params].estimator: 'ekf' not one of ('kalman-000', 'gyro-vertical')"),
    ({"k": [1, 2]}, "expected 3 values"),
    ({"state_source": 3}, "expected str"),
    ({"kk": 1}, "unknown parameter 'kk'"),
])
def test_bad_values_are_refused_with_the_key(given, needle):
    with pytest.raises(StackError) as err:
        resolve_params(DECLARED["attitude"], given, WHERE)
    assert needle in str(err.value) and str(err.value).startswith("s.toml: "), str(err.value)


@pytest.mark.parametrize("in_file, param, needle", [
    ("stopping_accel_fraction = 2.0\n", None, "[services.attitude.params].stopping_accel_fraction: 2.0 outside [0, 1]"),
    ("filter = {lpf_tau_s = 0.0}\n", None, "[services.attitude.params].filter.lpf_tau_s: 0.0 outside (0, inf) s"),
    ("", "carrier={enter_rate_rad_s=-6.0}",
     "[services.attitude.params].carrier.enter_rate_rad_s: -6.0 outside (0, inf) rad/s"),
])
def test_a_service_refuses_a_bad_bound_at_start(tmp_path, in_file, param, needle):
    """End to end: the attitude service started on a stack file (or with a --param) with a value
    out of bounds, a nested table's too, stops at once with exit status 2, naming the file, the
    section and the key (no router needed)."""
    stack = stack_file(tmp_path / "s.toml", f"[services.attitude.params]\n{in_file}")
    extra = ["--param", param] if param else []
    proc = subprocess.run([sys.executable, "-m", "services.attitude", "--stack", str(stack), "-e", "tcp/127.0.0.1:9",
                           *extra], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert f"{stack}: {needle}" in proc.stderr, proc.stderr


# the table as it was written by hand before the declarations: MAVSDK and QGC see the same
TUNABLE_BEFORE = (
    ("attitude", "k", "ATT_K_{}", "RPY", (0.1, 200.0)),
    ("attitude", "alpha", "ATT_ALPHA_{}", "RPY", (0.1, 200.0)),
    ("position", "k", "POS_K_{}", "XYZ", (0.05, 50.0)),
    ("position", "alpha", "POS_ALPHA_{}", "XYZ", (0.05, 50.0)),
    ("position", "max_tilt_deg", "POS_MAX_TILT", None, (1.0, 80.0)),
    ("motors", "command_timeout_s", "MOT_CMD_TIMEOUT", None, (0.005, 1.0)),
    ("mavlink", "takeoff_alt_m", "MIS_TAKEOFF_ALT", None, (0.2, 100.0)),
    ("mavlink", "return_alt_m", "RTL_RETURN_ALT", None, (0.0, 100.0)),
    ("mavlink", "acceptance_radius_m", "NAV_ACC_RAD", None, (0.05, 10.0)),
    ("mavlink", "offboard_timeout_s", "COM_OF_LOSS_T", None, (0.1, 10.0)),
)


def test_the_mavlink_table_is_generated_as_it_was():
    assert TUNABLE == TUNABLE_BEFORE
    assert BRIDGE_PARAM_DEFAULTS == {"takeoff_alt_m": 2.0, "return_alt_m": 0.0, "acceptance_radius_m": 0.3,
                                     "offboard_timeout_s": 1.0}
    table = ParamTable(TUNABLE_DEFAULTS)
    assert [(r["name"], r["value"], r["bounds"]) for r in table.rows] == [
        ("ATT_K_R", 16.0, (0.1, 200.0)), ("ATT_K_P", 16.0, (0.1, 200.0)), ("ATT_K_Y", 16.0, (0.1, 200.0)),
        ("ATT_ALPHA_R", 16.0, (0.1, 200.0)), ("ATT_ALPHA_P", 16.0, (0.1, 200.0)), ("ATT_ALPHA_Y", 16.0, (0.1, 200.0)),
        ("POS_K_X", 4.0, (0.05, 50.0)), ("POS_K_Y", 4.0, (0.05, 50.0)), ("POS_K_Z", 4.0, (0.05, 50.0)),
        ("POS_ALPHA_X", 4.0, (0.05, 50.0)), ("POS_ALPHA_Y", 4.0, (0.05, 50.0)), ("POS_ALPHA_Z", 4.0, (0.05, 50.0)),
        ("POS_MAX_TILT", 20.0, (1.0, 80.0)), ("MOT_CMD_TIMEOUT", 0.05, (0.005, 1.0)),
        ("MIS_TAKEOFF_ALT", 2.0, (0.2, 100.0)), ("RTL_RETURN_ALT", 0.0, (0.0, 100.0)),
        ("NAV_ACC_RAD", 0.3, (0.05, 10.0)), ("COM_OF_LOSS_T", 1.0, (0.1, 10.0)),
    ]


def test_the_bridge_loads_declarations_not_services():
    """The MAVLink logic reads the parameter table without the services (their transport, filters, solvers)."""
    code = ("import sys, services.mavlink_logic; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('zenoh', 'jax', 'filterpy', 'scipy', "
            "'simulator') or m in ('services.attitude', 'services.position', 'services.motors', 'services.runtime')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr


def test_default_stack_holds_only_overrides():
    doc = tomllib.loads(DEFAULT_STACK.read_text())
    for service, section in doc["services"].items():
        for key, value in section.get("params", {}).items():
            default = DECLARED[service][key].default
            assert value != default, f"[services.{service}.params] {key} = {value!r} is the declared default"


def test_reference_page_is_current():
    """docs/parameters.md is generated; regenerate with `python -m services.params.reference > docs/parameters.md`."""
    assert (ROOT / "docs" / "parameters.md").read_text() == render()


def test_sim_declarations_are_the_simulator_config():
    """The simulator's settings keep their defaults and bounds in SimConfig; the service declares those."""
    from simulator.config import SimConfig
    sim = DECLARED["sim"]
    assert sim["camera_drop_rate"].bounds_text() == "[0, 1]" and sim["camera_focal_px"].bounds_text() == "(0, inf)"
    for key, value in SimConfig().to_dict().items():
        if key != "tick_rate_hz":
            assert sim[key].default == (list(value) if isinstance(value, tuple) else value), key
    with pytest.raises(StackError, match=r"\[services.sim.params\].mass_scale: 20.0 outside \[0.1, 10\]"):
        resolve_params(sim, {"mass_scale": 20.0}, "s.toml: [services.sim.params]")


def test_camera_latency_past_the_ekf_history_is_refused(tmp_path):
    """Above the position EKF's history every camera fix would be dropped, without a word."""
    f = stack_file(tmp_path / "s.toml", "[services.sim.params]\ncamera_latency_s = 0.3\n")
    with pytest.raises(StackError) as err:
        load_stack(f)
    said = str(err.value)
    assert str(f) in said and "camera_latency_s = 0.3 s" in said and "ekf.max_delay_s = 0.3 s" in said, said
    # a longer history lets it fly
    f = stack_file(tmp_path / "s.toml", "[services.sim.params]\ncamera_latency_s = 0.3\n"
                                        "[services.position.params]\nekf = {max_delay_s = 0.5}\n")
    assert load_stack(f).service("sim").params["camera_latency_s"] == 0.3
    # a --param on one service is checked against the other's settings in the file (services.runtime)
    given = {n: s.params for n, s in load_stack(DEFAULT_STACK).services.items()}
    check_compatible("here", {**given, "sim": {"camera_latency_s": 0.2}})
    with pytest.raises(StackError, match="here: .*camera_latency_s = 0.4 s is not below"):
        check_compatible("here", {**given, "sim": {"camera_latency_s": 0.4}})
    with pytest.raises(StackError, match=r"ekf.max_delay_s = 0.04 s"):
        check_compatible("here", {**given, "position": {"ekf": {"max_delay_s": 0.04}}})
    check_compatible("here", {**given, "sim": {"camera_latency_s": "slow"}})   # a wrong type: its owner's to say
    # the defaults fit, so a stack that sets neither is not checked
    from flight.estimation.position_ekf import PositionEKFParams
    assert DECLARED["sim"]["camera_latency_s"].default < PositionEKFParams.max_delay_s
