"""`zenpilot up -d` / `status` / `down`, with the stack split over two machines."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest
from mcap.reader import make_reader

from deploy.launcher import free_port

from .conftest import ROOT, command_line, processes_mentioning

OTHER_STACK = ROOT / "tests" / "integration" / "stacks" / "recorder-only.toml"

pytestmark = pytest.mark.integration


def zp(*args, env):
    return subprocess.run([sys.executable, "-m", "deploy.cli", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=120)


@pytest.mark.realtime
def test_up_two_machines_status_down(tmp_path):
    """`down` stops its own stack only (another one beside it keeps running), services first and
    the recorder last, which leaves a complete, indexed flight log."""
    env = dict(os.environ, ZENPILOT_STATE_DIR=str(tmp_path))
    router = f"tcp/127.0.0.1:{free_port()}"
    other = f"tcp/127.0.0.1:{free_port()}"
    try:
        vehicle = zp("up", "-d", "--machine", "vehicle", "--router", router, env=env)
        assert vehicle.returncode == 0, vehicle.stderr
        ground = zp("up", "-d", "--machine", "ground", "--router", router, env=env)
        assert ground.returncode == 0, ground.stderr
        status = zp("status", env=env)
        assert status.returncode == 0, status.stderr
        rows = {line.split()[0]: line.split() for line in status.stdout.splitlines()[1:]}
        for service in ("sim", "motors", "attitude", "position", "planner", "recorder"):
            assert rows[service][1] == "yes", status.stdout
            assert rows[service][2] in ("running", "degraded"), status.stdout
        # the background `up` supervises: attitude killed, it is started again and `down` knows the new pid
        state = next(tmp_path.glob("*/up-vehicle.json"))
        killed = json.loads(state.read_text())["pids"]["attitude"]
        os.kill(killed, signal.SIGKILL)
        deadline = time.monotonic() + 15
        while json.loads(state.read_text())["pids"]["attitude"] == killed:
            assert time.monotonic() < deadline, next(tmp_path.glob("*/run-vehicle/logs/up.log")).read_text()
            time.sleep(0.1)
        restarted = json.loads(state.read_text())["pids"]["attitude"]
        assert os.path.exists(f"/proc/{restarted}")
        assert "attitude killed by signal 9" in next(tmp_path.glob("*/run-vehicle/logs/up.log")).read_text()
        beside = zp("up", "-d", "--stack", str(OTHER_STACK), "--machine", "solo", "--router", other, env=env)
        assert beside.returncode == 0, beside.stderr
        which = zp("down", env=env)   # two stacks up: `down` must be told which
        assert which.returncode == 2 and router in which.stderr and other in which.stderr, which.stderr
        down = zp("down", "--router", router, env=env)
        assert down.returncode == 0 and "stopped" in down.stdout, down.stdout + down.stderr
        assert processes_mentioning(router) == []
        assert not os.path.exists(f"/proc/{restarted}")   # the restarted service was stopped too
        beside_procs = {pid: command_line(pid) for pid in processes_mentioning(other)}
        assert len(beside_procs) == 3, beside_procs   # the other stack's router, recorder and its `up`
    finally:
        zp("down", "--all", env=env)
    assert processes_mentioning(other) == []
    run = next(tmp_path.glob("*/run-ground"))
    assert "flight log" in down.stdout and "complete" in down.stdout, down.stdout
    with open(run / "flight.mcap", "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None and summary.statistics.message_count > 1000
    assert "wrote" in (run / "logs" / "recorder.log").read_text()


def test_terminated_fly_stops_its_services(tmp_path):
    """SIGTERM to `zenpilot fly` (a batch job cancelled, a bench killed) stops the router
    and every service it started instead of leaving them running."""
    import signal
    import time
    port = free_port()
    router = f"tcp/127.0.0.1:{port}"
    proc = subprocess.Popen([sys.executable, "-m", "deploy.cli", "fly", "--lockstep", "--mission", "hover",
                             "--port", str(port), "--out", str(tmp_path / "run")],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(processes_mentioning(router)) < 4:
            time.sleep(0.2)
        started = processes_mentioning(router)
        assert len(started) >= 4, "the stack did not start"
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 143, err
        assert "terminated" in err
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and processes_mentioning(router):
            time.sleep(0.2)
        assert processes_mentioning(router) == []
    finally:
        if proc.poll() is None:
            proc.kill()
        for pid in processes_mentioning(router):
            os.kill(pid, signal.SIGKILL)
