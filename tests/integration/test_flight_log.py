"""A stop never loses the flight log: Ctrl-C of `zenpilot fly` mid-flight leaves a complete,
indexed log holding every message up to the stop; a recorder killed with -9 leaves the chunks
it wrote, which `zenpilot log recover` makes a complete log and `zenpilot report` reads."""

import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from mcap.reader import make_reader

from schemas.flightlog import LogScan, read_log

from .conftest import ROOT, TRUTH_STATE, fly, processes_mentioning

pytestmark = pytest.mark.integration

FLYING_S = 4.0   # wall time flown before the stop: a few of the recorder's 1 s chunks
MISSIONS = ROOT / "tests" / "integration" / "missions"


def zp(*args):
    return subprocess.run([sys.executable, "-m", "deploy.cli", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)


def fly_until_flying(out, *extra):
    proc = fly(out, str(MISSIONS / "hover-long.toml"), *TRUTH_STATE, *extra, background=True)
    deadline = time.monotonic() + 120
    while "first tick" not in _read(out / "logs" / "sim.log"):
        assert proc.poll() is None and time.monotonic() < deadline, proc.stdout.read() if proc.stdout else ""
        time.sleep(0.2)
    time.sleep(FLYING_S)
    return proc


def _read(path):
    try:
        return path.read_text()
    except OSError:
        return ""


def contiguous(seqs):
    """Each key's sequence numbers with no gap (a message repeated until answered counts once)."""
    seqs = [s for i, s in enumerate(seqs) if i == 0 or s != seqs[i - 1]]
    return seqs == list(range(seqs[0], seqs[0] + len(seqs)))


def test_ctrl_c_mid_flight_leaves_a_complete_log_of_every_message(tmp_path):
    out = tmp_path / "run"
    proc = fly_until_flying(out)
    try:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130
    with open(out / "flight.mcap", "rb") as fh:
        summary = make_reader(fh).get_summary()   # indexed
    log = read_log(out / "flight.mcap")
    # read_log gives the bus messages (JSON channels); the Foxglove channels are made from them
    bus = [c.id for c in summary.channels.values() if c.message_encoding == "json"]
    assert sum(summary.statistics.channel_message_counts[c] for c in bus) == sum(map(len, log.values()))
    for key, msgs in log.items():
        assert contiguous([m["header"]["seq"] for m in msgs]), key
    imu = [m["header"]["t_s"] for m in log["zp/0/sim/imu"]]
    assert imu[-1] > 0.25   # stopped while flying (0.9 s of sim in 4 s of wall time seen on the loaded VM)
    assert np.allclose(np.diff(imu), 1 / 400)   # every 400 Hz sample, in order
    # ... up to the stop: every tick the simulator ran (and the one in progress) is in the log
    ticks = int(re.search(r"stopping; .*?; (\d+) runs", _read(out / "logs" / "sim.log")).group(1))
    assert len(imu) in (ticks, ticks + 1)


def test_a_recorder_killed_leaves_its_chunks_and_recover_completes_them(tmp_path):
    out = tmp_path / "run"
    proc = fly_until_flying(out, "--processes")   # the recorder in a process of its own, to kill
    try:
        recorder, = [p for p in processes_mentioning(str(out)) if b"services.recorder" in
                     open(f"/proc/{p}/cmdline", "rb").read()]
        os.kill(recorder, signal.SIGKILL)
        said, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 2 and "zenpilot log recover" in said, said
    cut = LogScan(out / "flight.mcap")
    log = read_log(out / "flight.mcap", cut)
    assert not cut.complete and cut.chunks >= 2, cut.describe()
    for key, msgs in log.items():   # the readable part has no gap
        assert contiguous([m["header"]["seq"] for m in msgs]), key
    report = zp("report", str(out))   # on the cut log: a report of what it holds, and why
    assert report.returncode == 0 and "cut" in report.stderr and "Traceback" not in report.stderr, report.stderr
    recovered = zp("log", "recover", str(out))
    assert recovered.returncode == 0, recovered.stderr
    with open(out / "flight.mcap", "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None and summary.statistics.message_count == cut.messages
    assert read_log(out / "flight.mcap") == log
    assert (out / "flight.cut.mcap").stat().st_size == cut.size_bytes   # the cut file kept as it was
    assert zp("log", "info", str(out)).returncode == 0


@pytest.mark.parametrize("mode", [[], ["--processes"]], ids=["one process", "processes"])
def test_fly_killed_takes_its_stack_with_it_and_the_log_is_complete(tmp_path, mode):
    """`zenpilot fly` killed with -9 (a test's timeout, an OOM kill): its services get SIGTERM from
    the kernel (services.runtime.tie_to_parent), stop as on Ctrl-C, and the log is complete."""
    out = tmp_path / "run"
    proc = fly_until_flying(out, *mode)
    stack = processes_mentioning(str(out))
    assert stack
    proc.kill()
    proc.wait(timeout=10)
    deadline = time.monotonic() + 60
    while (left := processes_mentioning(str(out))) and time.monotonic() < deadline:
        time.sleep(0.2)
    try:
        assert not left, f"still running after fly was killed: {left}"
    finally:
        for p in left:
            os.kill(p, signal.SIGKILL)
    with open(out / "flight.mcap", "rb") as fh:
        summary = make_reader(fh).get_summary()   # indexed: the recorder finished its log
    assert summary is not None and summary.statistics.message_count > 0
    imu = [m["header"]["t_s"] for m in read_log(out / "flight.mcap")["zp/0/sim/imu"]]
    assert imu[-1] > 0.25 and np.allclose(np.diff(imu), 1 / 400)
