"""A ground station flips a vehicle whose mission has no flip item (issue 24): the planner
built the flip for MAVLink with `flip_methods`, the bridge accepts MAV_CMD_USER_1 because the
planner says it can fly it (planner/flip_status), and the flip completes on the simulator's
truth. Lockstep (`zenpilot up --lockstep`, the bridge on the wall clock beside it, as in
test_mavsdk.py), on truth state: the MAVLink path is what is judged, the flip's figures are
test_flip.py's. The solver comes from the compile cache when an earlier flight compiled it."""

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from bench.support.gcs import Gcs, free_udp_port, mavlink
from deploy.launcher import free_port
from deploy.metrics import compute_metrics
from schemas.flightlog import LOG_NAME, read_log
from services.mavlink_logic import MODES

from .conftest import ROOT, TRUTH_STATE

pytestmark = pytest.mark.integration

MISSION = str(Path(__file__).resolve().parent / "missions" / "hover-5m.toml")


def test_a_ground_station_flips_a_mission_without_a_flip_item(tmp_path):
    router, udp = f"tcp/127.0.0.1:{free_port()}", free_udp_port()
    run = tmp_path / "run"
    gcs = Gcs(udp)
    # `zenpilot up` in the foreground: the whole stack here, the recorder with it (its log is judged);
    # SIGTERM stops it as Ctrl-C does, the log completed
    with open(tmp_path / "up.log", "w") as out:
        up = subprocess.Popen([sys.executable, "-m", "deploy.cli", "up", "--lockstep", "--router", router,
                               "--out", str(run), "--mission", MISSION, *TRUTH_STATE,
                               "--set", 'planner.flip_methods=["ilqr-project"]',
                               "--set", f"mavlink.endpoint=udpout:127.0.0.1:{udp}"],
                              cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)
    try:
        for _ in range(120):   # the stack is up (the UDP peer is known once the bridge has spoken)
            assert up.poll() is None, (tmp_path / "up.log").read_text()[-3000:]   # refused at start: say why
            try:
                gcs.wait("HEARTBEAT", timeout=1.0)
                break
            except AssertionError:
                continue
        # the mission's hold at 5 m (the simulator runs near real time here: a generous wait)
        gcs.wait("LOCAL_POSITION_NED", lambda m: abs(m.z + 5.0) < 0.1 and abs(m.vz) < 0.1, timeout=90.0)
        ack = gcs.command_retransmitted(mavlink.MAV_CMD_USER_1)
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED, (ack, gcs.latest.get("STATUSTEXT"))
        gcs.wait("HEARTBEAT", lambda m: m.custom_mode == MODES["flip"], timeout=20.0)   # Acro: flipping
        gcs.wait("HEARTBEAT", lambda m: m.custom_mode == MODES["hold"], timeout=60.0)   # done: it holds
    finally:
        up.send_signal(signal.SIGTERM)
        try:
            up.wait(60)
        except subprocess.TimeoutExpired:
            up.kill()
        gcs.conn.close()
    assert up.returncode == 0, (tmp_path / "up.log").read_text()[-3000:]
    log = read_log(run / LOG_NAME)
    m = compute_metrics(log, {"vehicle": "q820"})
    assert not m["crashed"], m["crash_reason"]
    f = m["flip"]
    assert f["completed"] and not f["aborted"] and not f["refused"] and not f["hit_ground"], f
    assert f["method"] == "ilqr-project" and f["altitude_loss_m"] <= 0.5, f
    phases = {x["phase"] for x in log["zp/0/planner/setpoint"]}
    assert {"flip", "flip-recovery", "flip-settle"} <= phases, phases   # from the hover at 5 m: no climb first
    # the planner said what it could fly, once a second, and predicted that flip before any was asked
    status = log["zp/0/planner/flip_status"]
    assert len(status) > 5 and all(s["method"] == "ilqr-project" and not s["refused"] for s in status)
    [prediction] = log["zp/0/planner/flip_prediction"]
    assert prediction["altitude_m"] == 5.0 and not prediction["refused"]
    assert "command flip from mavlink:255/190" in (run / "logs" / "planner.log").read_text()
