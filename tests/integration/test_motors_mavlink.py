"""The motor driver's MAVLink output: a pymavlink receiver checks content and rate."""

import os
import subprocess
import sys
import time

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

import schemas  # noqa: E402
from deploy.launcher import ZENOH_RUNTIME, client_session, free_port, wait_port  # noqa: E402
from flight.mavframes import actuator_controls  # noqa: E402
from flight.control.mixer import mix  # noqa: E402
from flight.vehicle import load_vehicle  # noqa: E402

from .conftest import ROOT  # noqa: E402
from bench.support.gcs import free_udp_port  # noqa: E402

pytestmark = [pytest.mark.integration, pytest.mark.realtime]


def test_actuator_controls_at_the_motor_rate(tmp_path):
    router, udp = f"tcp/127.0.0.1:{free_port()}", free_udp_port()
    env = dict(os.environ, ZENOH_RUNTIME=ZENOH_RUNTIME, PYTHONUNBUFFERED="1")
    procs = [subprocess.Popen([sys.executable, "-m", "deploy.router", "--listen", router], cwd=ROOT, env=env)]
    rx = mavutil.mavlink_connection(f"udpin:127.0.0.1:{udp}")
    try:
        assert wait_port(router, 10.0)
        log = open(tmp_path / "motors.log", "w")
        procs.append(subprocess.Popen([sys.executable, "-m", "services.motors", "-e", router,
                                       "--param", "output=mavlink",
                                       "--param", f"mavlink_endpoint=udpout:127.0.0.1:{udp}"],
                                      cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT))
        v = load_vehicle("x250")
        thrust, torque = 4 * v.hover_thrust_per_motor_n, [0.01, -0.005, 0.001]
        expected = actuator_controls(v.allocation, v.max_thrust_n, mix(v, thrust, torque)[0])
        session = client_session(router)
        sp = {"mode": "position", "armed": True, "position_m": [0, 0, 1], "attitude_rad": [0, 0, 0], "item": 0,
              "phase": "hold", "measure": False, "mission_state": "running"}
        got, seq = [], 0
        start = time.monotonic()
        while time.monotonic() - start < 12.0 and len(got) < 1600:
            now = time.time()
            session.put("zp/0/planner/setpoint", schemas.PLANNER_SETPOINT.encode(now, seq, "test", sp))
            session.put("zp/0/att/command", schemas.ATTITUDE_COMMAND.encode(
                now, seq, "test", {"thrust_n": thrust, "torque_nm": torque, "imu_t_s": now}))
            seq += 1
            deadline = time.monotonic() + 0.005
            while time.monotonic() < deadline:
                m = rx.recv_match(type="SET_ACTUATOR_CONTROL_TARGET", blocking=True, timeout=0.005)
                if m is not None:
                    got.append((time.monotonic(), m))
        session.close()
    finally:
        for p in reversed(procs):
            p.terminate()
            p.wait(10)
        rx.close()
    armed = [(t, m) for t, m in got if m.controls[3] > 0.1]
    assert len(armed) > 400, f"{len(got)} messages, {len(armed)} armed; " + (tmp_path / "motors.log").read_text()
    t, m = armed[-1]
    assert m.group_mlx == 0 and m.target_system == 1
    assert m.controls == pytest.approx(expected, abs=1e-6)
    # rate: the last 400 messages arrive at the motor rate (400 Hz), give or take this VM
    span = armed[-1][0] - armed[-400][0]
    rate = 399 / span
    assert 300 < rate < 500, rate
    times_us = [m.time_usec for _, m in armed[-400:]]
    assert all(b > a for a, b in zip(times_us, times_us[1:]))
