"""Integration tests: `zenpilot fly` spawns a local Zenoh router on a free port and
every service as its own process; the tests read what the flight wrote."""

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

# the ablation "truth state": the control laws of 000 on the simulator's truth (issue 2's figures)
TRUTH_STATE = ("--set", "attitude.state_source=truth", "--set", "position.state_source=truth",
               "--set", "sim.truth_rate_hz=200")


def fly(out: Path, mission: str, *extra: str, lockstep: bool = True, seed: int = 0,
        timeout: float = 400, background: bool = False, plots: bool = False):
    argv = [sys.executable, "-m", "deploy.cli", "fly", "--mission", mission, "--seed", str(seed),
            "--out", str(out), *extra]
    if not plots:   # ~2 s a flight; the hover fixture's flight draws them and a test checks them
        argv.append("--no-plots")
    if lockstep:
        argv.append("--lockstep")
    if background:   # SIGINT as a terminal gives it, even where the suite runs in the background
        # (a shell's background job ignores SIGINT, and Python keeps an inherited SIG_IGN)
        return subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    proc = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    assert (out / "metrics.json").exists(), proc.stdout + proc.stderr
    return proc, json.loads((out / "metrics.json").read_text())


@pytest.fixture(scope="session")
def hover_lockstep(tmp_path_factory):
    out = tmp_path_factory.mktemp("hover-lockstep")
    return out, fly(out, "hover", *TRUTH_STATE, plots=True)


@pytest.fixture(scope="session")
def hover_lockstep_live(tmp_path_factory):
    """The same hover with every service its own process over the router and a Foxglove live view
    watching it (foxglove_client.py), once for the two tests that read it: test_foxglove (what the
    viewer received) and test_flights' determinism (its log and metrics against hover_lockstep's,
    as a `--processes` flight's: a viewer only listens). (out, proc, its output, the advertised
    channels, the messages received per channel.)"""
    import asyncio
    import time

    from deploy.launcher import free_port

    from .foxglove_client import watch
    out = tmp_path_factory.mktemp("hover-lockstep-live")
    port = free_port()
    proc = fly(out, "hover", *TRUTH_STATE, "--foxglove", str(port), background=True)
    try:
        channels, received = asyncio.run(watch(port, proc, time.monotonic() + 400))
        said, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    return out, proc, said, channels, received


@pytest.fixture(scope="session")
def hover_real_time(tmp_path_factory):
    """The truth-state hover flown on the wall clock, once for the tests that read it (its quality
    in test_flights, its Foxglove channels in test_foxglove): ~28 s of the real-time group each."""
    out = tmp_path_factory.mktemp("hover-real-time")
    return out, fly(out, "hover", *TRUTH_STATE, lockstep=False)


def command_line(pid: int) -> str:
    """A process's command line, for a failure message ("(gone)" once it has ended)."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace")[:160]
    except OSError:
        return "(gone)"


def processes_mentioning(text: str) -> list[int]:
    """The processes whose command line contains `text` (a run's router endpoint or folder)."""
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
