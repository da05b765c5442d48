"""`zenpilot up -d` / `status` / `down`, with the stack split over two machines."""

import os
import subprocess
import sys

import pytest

from deploy.launcher import free_port

from .conftest import ROOT

pytestmark = pytest.mark.integration


def zp(*args, env):
    return subprocess.run([sys.executable, "-m", "deploy.cli", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=120)


def test_up_two_machines_status_down(tmp_path):
    env = dict(os.environ, ZENPILOT_STATE_DIR=str(tmp_path))
    router = f"tcp/127.0.0.1:{free_port()}"
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
    finally:
        down = zp("down", env=env)
    assert down.returncode == 0 and "stopped" in down.stdout
    assert (tmp_path / "run-ground" / "flight.mcap").exists()
    assert "wrote" in (tmp_path / "run-ground" / "logs" / "recorder.log").read_text()
