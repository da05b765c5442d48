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


def _processes_mentioning(text: str) -> list[int]:
    pids = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/cmdline", "rb") as f:
                    if text.encode() in f.read():
                        pids.append(int(entry))
            except OSError:
                continue
    return pids


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
        while time.monotonic() < deadline and len(_processes_mentioning(router)) < 4:
            time.sleep(0.2)
        started = _processes_mentioning(router)
        assert len(started) >= 4, "the stack did not start"
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 143, err
        assert "terminated" in err
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and _processes_mentioning(router):
            time.sleep(0.2)
        assert _processes_mentioning(router) == []
    finally:
        if proc.poll() is None:
            proc.kill()
        for pid in _processes_mentioning(router):
            os.kill(pid, signal.SIGKILL)
