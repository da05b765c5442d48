"""Real-time flights split over two hosts (bench/two_hosts.py), each host a network namespace:

- a short hover with the vehicle's router and services in one, the ground station's recorder in
  the other, joined by a veth pair; the flight log is written on the ground side (about 25 s: what
  it checks, where the log and the sockets are, does not depend on how long it holds);
- the short flip mission across an emulated `lan` link (20 +- 5 ms, 1 % loss each way: tc netem,
  or bench/support/linkemu.py in a third namespace where the kernel has no netem) with the issue's
  placement: planner, recorder and MAVLink bridge on the ground, a router per host (about 25 s):
  the plans cross the link at 50 Hz and start ahead by its latency (planner.plan_lead_auto);
- the short hover across `lan` with the same placement secured (`--secure tls`: [security], keys by
  `zenpilot certs`, mutual TLS, passwords, the vehicle router's access control; about 30 s): it
  flies, and the vehicle's telemetry reaches the ground in time (TLS + QUIC's datagrams, queued
  behind QUIC's congestion control, brought it 1.3 s late: docs/reliability.md); and with the
  link cut both ways for 2 s in its landing (`--outage 5:2`) the vehicle holds on its own, both
  directions cross again soon after the restore, and the vehicle goes down to the planner's
  reference, not up (docs/reliability.md, "The link lost mid-flight").

Nothing is left behind; needs root."""

import json
import os
import re
import time
import shutil
import signal
import subprocess
import sys

import pytest

from .conftest import ROOT

pytestmark = [pytest.mark.integration, pytest.mark.realtime]


def _netns_refused() -> str | None:
    """Why two network namespaces joined by a veth pair cannot be made here (None: they can)."""
    if shutil.which("ip") is None:
        return "no `ip` command (iproute2) for the network namespaces"
    name = f"zpprobe{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", name], capture_output=True, text=True)
    if made.returncode != 0:
        return f"`ip netns add` is not permitted here (needs root): {made.stderr.strip()}"
    try:
        veth = subprocess.run(["ip", "-n", name, "link", "add", "zpprobe0", "type", "veth", "peer", "name", "zpprobe1"],
                              capture_output=True, text=True)
        if veth.returncode != 0:
            return f"no veth pair in a network namespace here: {veth.stderr.strip()}"
    finally:
        subprocess.run(["ip", "netns", "del", name], capture_output=True)
    return None


def _two_hosts(tmp_path, *args: str) -> str:
    """bench/two_hosts.py ARGS --no-one-host into tmp_path (skipped where namespaces cannot be
    made); its output, once it has exited 0."""
    refused = _netns_refused()
    if refused:
        pytest.skip(refused)
    bench = subprocess.Popen([sys.executable, str(ROOT / "bench" / "two_hosts.py"), *args, "--no-one-host",
                              "--out", str(tmp_path)],
                             cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        out, _ = bench.communicate(timeout=240)
    except subprocess.TimeoutExpired:
        bench.send_signal(signal.SIGTERM)  # the bench removes its namespaces and processes
        out, _ = bench.communicate(timeout=120)
        pytest.fail("the two-host flight did not finish in 240 s:\n" + out)
    assert bench.returncode == 0, out
    return out


def test_hover_over_two_hosts(tmp_path):
    out = _two_hosts(tmp_path, "--mission", "hover-short")
    namespaces = re.findall(r"netns (zp\d+-(?:vehicle|ground))", out)
    assert len(namespaces) == 2, out
    assert not set(namespaces) & set(subprocess.run(["ip", "netns", "list"], capture_output=True,
                                                    text=True).stdout.split()), "namespaces left behind"

    metrics = json.loads((tmp_path / "ground" / "metrics.json").read_text())
    assert metrics["completed"] and not metrics["crashed"], out
    assert metrics["rates_hz"]["sim"] and metrics["rates_hz"]["attitude"], out  # the vehicle's health came across
    # the flight log was written on the ground side, by the recorder, and only there
    assert (tmp_path / "ground" / "flight.mcap").exists()
    assert not (tmp_path / "vehicle" / "flight.mcap").exists()
    assert "wrote" in (tmp_path / "ground" / "logs" / "recorder.log").read_text()
    # the stream crossed the link; no multicast scouting in either namespace
    link = metrics["two_hosts"]
    assert link["sockets"]["ground"]["tcp_across_link"] >= 1, out
    for host in ("vehicle", "ground"):
        assert link["sockets"][host]["udp_7446"] == 0 and not link["sockets"][host]["scouting_group_joined"], out


def test_the_flip_across_a_lossy_link_with_the_planner_on_the_ground(tmp_path):
    t0 = time.monotonic()
    out = _two_hosts(tmp_path, "--mission", "flip-short", "--placement", "ground", "--link", "lan")
    took = time.monotonic() - t0
    namespaces = re.findall(r"removed (zp\d+-vehicle), (zp\d+-ground)(?:, (zp\d+-link))?", out)
    assert namespaces, out
    assert not {n for n in namespaces[0] if n} & set(subprocess.run(["ip", "netns", "list"], capture_output=True,
                                                                     text=True).stdout.split()), "left behind"

    metrics = json.loads((tmp_path / "ground" / "metrics.json").read_text())
    assert metrics["completed"] and not metrics["crashed"], out
    # docs/flip.md's targets: loss <= 1 m, drift <= 0.27 m, recovery <= 0.5 s (the bench, seeds 0-4,
    # quiet: loss 0, drift 0.20-0.23 m, recovery 0.41-0.46 s; 0.1 s more allowed for a loaded CI run).
    # Before the plans' lead, the 50 Hz re-solves and the routers' queue it fell 5 m
    flip = metrics["flip"]
    assert flip["altitude_loss_m"] <= 1.0 and flip["xy_drift_m"] <= 0.27 and flip["recovery_s"] <= 0.6, flip
    link = metrics["two_hosts"]
    assert link["emulator"] in ("netem", "forwarder") and link["placement"] == "ground", out
    # the placement: planner, recorder, bridge ran on the ground, the control path on the vehicle
    assert {p.stem for p in (tmp_path / "ground" / "logs").glob("*.log")} >= {"planner", "recorder", "mavlink", "router"}
    assert not {"planner", "recorder", "mavlink"} & {p.stem for p in (tmp_path / "vehicle" / "logs").glob("*.log")}
    # only the two routers' link crosses (a TCP stream per priority range: control, bulk): every
    # service talks to its own host's router
    for host in ("vehicle", "ground"):
        assert link["sockets"][host]["tcp_across_link"] == 2, link["sockets"]
        assert link["sockets"][host]["udp_7446"] == 0 and not link["sockets"][host]["scouting_group_joined"], out
    # the delay was really there, both ways: the ground's inputs and the vehicle's setpoints came
    # late by at least the link's 15 ms minimum (on loopback they take ~1-2 ms)
    keys = link["keys"]
    assert keys["zp/0/pos/state"]["to"] == "ground" and keys["zp/0/planner/setpoint"]["to"] == "vehicle"
    for key in ("zp/0/pos/state", "zp/0/sim/imu", "zp/0/planner/setpoint"):
        assert keys[key]["n"] > 100 and keys[key]["latency_ms"]["p50"] >= 15.0, (key, keys[key])
    if link["emulator"] == "forwarder":   # and the losses: frames dropped each way
        assert all(d["dropped"] > 0 and 15.0 <= d["delay_ms"]["p50"] <= 40.0
                   for d in link["forwarder"]["directions"].values()), link["forwarder"]
    print(f"across lan in {took:.0f} s: " + ", ".join(
        f"{k.split('/', 2)[-1]} p50 {keys[k]['latency_ms']['p50']:.0f} ms, lost {keys[k]['lost']}/{keys[k]['expected']}"
        for k in ("zp/0/pos/state", "zp/0/planner/setpoint")))


# after a 2 s cut of the secured lan link the keys crossed again 1.0-1.3 s after the restore (TCP's
# retransmission, load average 5-7); a loaded CI machine is given 5 s
RESUME_BOUND_S = 5.0


def test_the_secured_split_hovers_across_a_lossy_link(tmp_path):
    out = _two_hosts(tmp_path, "--mission", "hover-short", "--placement", "ground", "--link", "lan", "--secure", "tls",
                     "--outage", "5:2")
    assert "secured: tls" in out, out
    metrics = json.loads((tmp_path / "ground" / "metrics.json").read_text())
    assert metrics["completed"] and not metrics["crashed"], out
    link = metrics["two_hosts"]
    assert link["secure"] == "tls" and link["emulator"] in ("netem", "forwarder"), out
    # each host has its own share of the keys: the ground nothing of the vehicle's, the CA's key on neither
    assert {p.name for p in (tmp_path / "ground" / "keys").iterdir()} == {"ca.pem", "ground.pem", "ground.key",
                                                                         "ground.login", "ground.users"}
    assert not (tmp_path / "vehicle" / "keys" / "ca.key").exists()
    # only the routers' two TLS links cross (control, bulk), nothing over UDP
    for host in ("vehicle", "ground"):
        assert link["sockets"][host]["tcp_across_link"] == 2, link["sockets"]
    assert not [u for u in link["sockets"]["vehicle"]["udp"] if u.startswith("10.77.")], link["sockets"]
    # the ground got the vehicle's telemetry, late by the link (>= its 15 ms minimum) and not by seconds
    # (TLS + QUIC: p50 1.2 s), and the flight log on the ground has the vehicle's health (its rates); a
    # TCP stream loses what the routers drop while it waits out a retransmission: 0.5-2.9 % measured,
    # 11.5 % once in a CI run beside two other jobs (the outage's own share left out: 8 % with the
    # TCP streams' backlog after it)
    keys, outage = link["keys"], link["outage"]
    for key in ("zp/0/pos/state", "zp/0/sim/imu"):
        r = keys[key]
        assert r["to"] == "ground" and r["n"] > 100, (key, r)
        assert 15.0 <= r["latency_ms"]["p50"] <= 200.0, (key, r)
        assert r["lost_probe"] - outage["keys"][key]["lost_in_outage"] <= 0.25 * r["expected_probe"], (key, r)
    assert keys["zp/0/planner/setpoint"]["n"] > 50, keys["zp/0/planner/setpoint"]
    assert metrics["rates_hz"]["sim"] and metrics["rates_hz"]["attitude"], out
    # the outage: cut in the landing (5 s after the first tick: the climb to 1 m, 0.5 + 1 s held),
    # nothing crossed while cut, both ways back within the bound; the vehicle (its own record: the
    # ground saw none of it) noticed the planner gone (position's failsafe), held its height, was
    # never crashed, and went on down: back, the planner's reference was ~0.9 m below, and stepped
    # to it the vehicle climbed to 3 m, once 83 m (now reached as a ramp: `planner_back`)
    assert outage["restored_unix"] - outage["cut_unix"] >= 2.0, outage
    for key in ("zp/0/pos/state", "zp/0/sim/imu", "zp/0/planner/setpoint"):
        r = outage["keys"][key]
        assert r["during"] == 0 and r["resumed_after_restore_s"] is not None, (key, r)
        assert r["resumed_after_restore_s"] <= RESUME_BOUND_S, (key, r)
    vehicle = outage["vehicle"]
    assert not vehicle["crashed"] and vehicle["failsafes"]["position"]["planner_lost"] >= 1, vehicle
    # in the air at the cut (0.64 / 1.0 m measured: a loaded machine lands later) and held there, not
    # fallen (0.19 m below at most), nor climbing after it (0.46 / 1.0 m at the highest)
    assert vehicle["altitude_at_cut_m"] >= 0.3, vehicle
    assert vehicle["min_altitude_cut_to_restore_m"] >= vehicle["altitude_at_cut_m"] - 0.25, vehicle
    assert vehicle["max_altitude_after_restore_m"] <= vehicle["altitude_at_cut_m"] + 0.2, vehicle
