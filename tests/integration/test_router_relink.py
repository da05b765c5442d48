"""The connecting machine's router opens its link and itself again when the link has carried
nothing for RELINK_S (deploy/router.py): after an outage past Zenoh's lease the routers' link may
form again and route nothing, ever (docs/reliability.md, "The link lost mid-flight"). On loopback,
the two machines' routers as `zenpilot up` runs them (an open link of two endpoints: checked),
RELINK_S shortened to 3 s; the vehicle's router frozen 6 s stands for the lost link (no echo, no
health: what the watch sees of an outage). About 20 s."""

import signal
import subprocess
import sys
import threading
import time

import pytest

from deploy.launcher import client_session, free_port, wait_port

from .conftest import ROOT

pytestmark = pytest.mark.integration

RELINK_S = 3.0
SERVICES = "\n".join(f'[services.{name}]\nmachine = "{machine}"\nrate_hz = {rate}\n' for name, machine, rate in (
    ("sim", "vehicle", 400.0), ("motors", "vehicle", 400.0), ("attitude", "vehicle", 200.0),
    ("position", "vehicle", 100.0), ("vision", "vehicle", 0.0), ("planner", "ground", 50.0),
    ("recorder", "ground", 10.0), ("mavlink", "ground", 50.0)))


def _stack(folder) -> str:
    ports = [free_port() for _ in range(4)]
    link = [f"tcp/127.0.0.1:{ports[2]}?prio=0-6", f"tcp/127.0.0.1:{ports[3]}?prio=7-7"]
    path = folder / "relink.toml"
    path.write_text(f"""
[stack]
vehicle_id = 0
[machines.vehicle]
router = "tcp/127.0.0.1:{ports[0]}"
runs_router = true
listen = ["{link[0]}", "{link[1]}"]
[machines.ground]
router = "tcp/127.0.0.1:{ports[1]}"
runs_router = true
connect = ["{link[0]}", "{link[1]}"]
{SERVICES}""")
    return str(path)


class Lines:
    """A process's stderr, read as it comes."""

    def __init__(self, proc: subprocess.Popen):
        self.lines: list[str] = []
        threading.Thread(target=lambda: self.lines.extend(iter(proc.stderr.readline, "")), daemon=True).start()

    def wait(self, text: str, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if any(text in line for line in self.lines):
                return True
            time.sleep(0.1)
        return False


def test_a_link_silent_for_long_opens_again_and_routes(tmp_path):
    from services.stack import load_stack
    path = _stack(tmp_path)
    stack = load_stack(path)
    vehicle = subprocess.Popen([sys.executable, "-m", "deploy.router", "--stack", path, "--machine", "vehicle"],
                               cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ground = subprocess.Popen(
        [sys.executable, "-c", f"import deploy.router as r; r.RELINK_S = {RELINK_S}; "
                               f"r.main(['--stack', {path!r}, '--machine', 'ground'])"],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    said = Lines(ground)
    sessions = []
    got: list[float] = []
    stop = threading.Event()
    try:
        for machine in ("vehicle", "ground"):   # the ground's once its link echoed
            assert wait_port(stack.machines[machine].router, 20.0), "".join(said.lines)
        sender = client_session(stack.machines["vehicle"].router)
        sessions.append(sender)
        receiver = client_session(stack.machines["ground"].router)
        sessions.append(receiver)
        receiver.declare_subscriber("zp/0/sim/health", lambda _s: got.append(time.monotonic()))
        pub = sender.declare_publisher("zp/0/sim/health")

        def beat():   # the vehicle's service health, as a service sends it (here 20 Hz)
            while not stop.wait(0.05):
                pub.put(b"x")
        threading.Thread(target=beat, daemon=True).start()
        deadline = time.monotonic() + 15.0
        while not got and time.monotonic() < deadline:
            time.sleep(0.1)
        assert got, "the routers never linked: " + "".join(said.lines)
        # the link lost: nothing from the vehicle (no echo, no health) for longer than RELINK_S
        vehicle.send_signal(signal.SIGSTOP)
        try:
            assert said.wait("open again", RELINK_S + 6.0), "".join(said.lines)
        finally:
            vehicle.send_signal(signal.SIGCONT)
        back = time.monotonic()
        # the link and the ground's router opened again as at the start, and route: the ground's
        # client (reconnected to its router) gets the vehicle's health again
        assert said.wait("listening again", 20.0), "".join(said.lines)
        deadline = time.monotonic() + 15.0
        while not [t for t in got if t > back] and time.monotonic() < deadline:
            time.sleep(0.1)
        assert [t for t in got if t > back], "nothing routed after the re-link: " + "".join(said.lines)
        assert ground.poll() is None and vehicle.poll() is None
    finally:
        stop.set()
        for s in sessions:
            s.close()
        for proc in (ground, vehicle):
            proc.send_signal(signal.SIGCONT)
            proc.terminate()
        for proc in (ground, vehicle):
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
