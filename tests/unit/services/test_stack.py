"""Stack files, missions and service command lines: bad input is refused with where and what."""

import subprocess
import sys
from pathlib import Path

import pytest

from flight.control.mission import MissionError, MissionRunner
from services.stack import SERVICE_MODULES, StackError, available_missions, load_mission, load_stack, resolve_params

ROOT = Path(__file__).resolve().parents[3]


def test_default_stack_loads():
    stack = load_stack()
    assert stack.vehicle == "x250"
    assert stack.period_ticks("attitude") == 2 and stack.period_ticks("position") == 4
    # the bridge yields the CPU to the flight loops; the loops run at the default priority
    assert stack.service("mavlink").nice == 10 and stack.service("attitude").nice == 0
    # the control path's loops ask for real-time priority, the plant highest; the recorder below
    # every loop (above the machine's normal work, so that the log keeps up); the bridge normal
    prio = {name: stack.service(name).priority for name in stack.services}
    assert prio["sim"] > prio["motors"] > prio["attitude"] > prio["position"] > prio["planner"] > prio["recorder"] > 0
    assert prio["mavlink"] == 0


@pytest.mark.parametrize("text, needle", [
    ("[stack]\nvehicle = 3\n", "vehicle"),
    ("not toml [", "not valid TOML"),
    ("[stack]\n[machines.a]\n[services.bogus]\n", "unknown service"),
    ("[stack]\n[machines.a]\n[services.sim]\nmachine = 'b'\n", "machine 'b'"),
    ("[stack]\ntick_rate_hz = 400\n[machines.a]\n[services.sim]\nrate_hz = 300\n", "must divide"),
    ("[stack]\n[machines.a]\n[services.sim]\nnice = -5\n", "[services.sim]: nice -5 must be within 0..19"),
    ("[stack]\n[machines.a]\n[services.sim]\nnice = 'low'\n", "[services.sim] nice: expected int"),
    ("[stack]\n[machines.a]\n[services.sim]\npriority = 120\n", "[services.sim]: priority 120 must be within 0..99"),
    ("[stack]\n[machines.a]\n[services.sim]\npriority = 'high'\n", "[services.sim] priority: expected int"),
    ("[stack]\n[machines.a]\n[services.sim]\ncpu = 1\n", "[services.sim] cpu: expected list"),
    ("[stack]\n[machines.a]\n[services.sim]\ncpu = [-1]\n", "[services.sim]: cpu [-1] must be a list of CPU numbers"),
    ("[stack]\n[machines.a]\nbulk_max_hz = -1\n", "[machines.a] bulk_max_hz: must be >= 0"),
    ("[stack]\n[machines.a]\nbulk_max_hz = nan\n", "[machines.a] bulk_max_hz: must be >= 0"),
    ("[stack]\n[machines.a]\nbulk_max_hz = '40'\n", "[machines.a] bulk_max_hz: expected float"),
    ("[stack]\n[machines.a]\nlisten = ['tcp/10.0.0.1']\n", "[machines.a] listen[0]: endpoint"),
])
def test_bad_stack_is_refused_with_location(tmp_path, text, needle):
    f = tmp_path / "s.toml"
    f.write_text(text)
    with pytest.raises(StackError) as err:
        load_stack(f)
    assert needle in str(err.value) and str(f) in str(err.value)


def test_params_refuse_unknown_and_wrong_type():
    defaults = {"k": [16.0, 16.0, 16.0], "state_source": "truth"}
    assert resolve_params(defaults, {"k": [1, 2, 3]}, "here")["k"] == [1.0, 2.0, 3.0]
    with pytest.raises(StackError, match="here: unknown parameter 'kk'"):
        resolve_params(defaults, {"kk": 1}, "here")
    with pytest.raises(StackError, match="expected 3 values"):
        resolve_params(defaults, {"k": [1.0]}, "here")
    with pytest.raises(StackError, match="expected str"):
        resolve_params(defaults, {"state_source": 3}, "here")


def test_shipped_missions_load():
    assert {"hover", "steps", "attitude-steps"} <= set(available_missions())
    for name in available_missions():
        assert load_mission(name).vehicle


def test_bad_mission_names_the_item(tmp_path):
    f = tmp_path / "m.toml"
    f.write_text('[mission]\nname="m"\nvehicle="x250"\n[[items]]\ntype="takeoff"\naltitude="high"\n')
    with pytest.raises(MissionError, match=r"items\[0\]: unknown key 'altitude'"):
        load_mission(str(f))


def test_flip_item_refuses_a_negative_baseline_climb(tmp_path):
    f = tmp_path / "m.toml"
    f.write_text('[mission]\nname="m"\nvehicle="q820"\n[[items]]\ntype="flip"\nbaseline_climb_m=-1.0\n')
    with pytest.raises(MissionError, match=r"items\[0\]: baseline_climb_m must be >= 0"):
        load_mission(str(f))
    from_hover = load_mission(str(ROOT / "tests/integration/missions/flip-short-baseline-from-hover.toml"))
    assert [i.get("baseline_climb_m") for i in from_hover.items if i["type"] == "flip"] == [0.0]


def test_mission_runner_flies_hover_phases():
    runner = MissionRunner(load_mission("hover"))
    t, z = 0.0, 0.0
    phases = []
    while runner.sp.mission_state not in ("completed", "failed") and t < 60:
        sp = runner.update(t, [0, 0, z], [0, 0, 0])
        z = max(0.0, sp.position_m[2])  # a perfect vehicle
        phases.append(sp.phase)
        t += 0.02
    assert runner.sp.mission_state == "completed"
    assert {"takeoff", "settle", "hold", "land", "landed"} <= set(phases)
    assert not runner.sp.armed


@pytest.mark.parametrize("service", sorted(SERVICE_MODULES))
def test_every_service_has_help(service):
    out = subprocess.run([sys.executable, "-m", SERVICE_MODULES[service], "--help"],
                         capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 0 and "--connect" in out.stdout and "--stack" in out.stdout


def test_bad_parameter_is_one_line_not_a_traceback():
    out = subprocess.run([sys.executable, "-m", "services.attitude", "--param", "kk=3"],
                         capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 2
    assert "unknown parameter 'kk'" in out.stderr and "Traceback" not in out.stderr


def test_cli_refuses_unknown_mission():
    out = subprocess.run([sys.executable, "-m", "deploy.cli", "fly", "--mission", "nope"],
                         capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 2 and "no file" in out.stderr and "Traceback" not in out.stderr


def test_the_cli_starts_without_jax_or_scipy():
    """Every `zenpilot` command imports deploy.cli: what only training and prediction use is
    imported when they run, so that a refused argument or `zenpilot fly` starts at once."""
    code = "import sys, deploy.cli; print(sorted(m for m in ('jax', 'scipy.optimize') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.stdout.strip().splitlines()[-1] == "[]", out.stdout + out.stderr


def test_pure_packages_do_no_io():
    """flight/ and simulator/ hold algorithms only: no Zenoh, msgpack or MAVLink."""
    banned = ("zenoh", "msgpack", "pymavlink", "socket", "subprocess")
    for pkg in ("flight", "simulator"):
        for f in (ROOT / pkg).rglob("*.py"):
            text = f.read_text()
            for name in banned:
                assert f"import {name}" not in text and f"from {name}" not in text, (f, name)
