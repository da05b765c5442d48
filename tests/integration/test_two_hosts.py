"""A real-time hover split over two hosts (bench/two_hosts.py): the vehicle's router and services
in one network namespace, the ground station's recorder in another, joined by a veth pair; the
flight log is written on the ground side and nothing is left behind. About 50 s; needs root."""

import json
import os
import re
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


def test_hover_over_two_hosts(tmp_path):
    refused = _netns_refused()
    if refused:
        pytest.skip(refused)
    bench = subprocess.Popen([sys.executable, str(ROOT / "bench" / "two_hosts.py"), "--mission", "hover",
                              "--no-one-host", "--out", str(tmp_path)],
                             cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        out, _ = bench.communicate(timeout=240)
    except subprocess.TimeoutExpired:
        bench.send_signal(signal.SIGTERM)  # the bench removes its namespaces and processes
        out, _ = bench.communicate(timeout=120)
        pytest.fail("the two-host flight did not finish in 240 s:\n" + out)
    assert bench.returncode == 0, out
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
