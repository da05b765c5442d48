"""`zenpilot down` stops the stack it is asked to, and nothing else: not another stack, not a
process that took a recorded pid since (a pid is signalled only if its command line names the
stack's router)."""

import argparse
import json
import os
import subprocess
import sys
import time

import pytest

from deploy import cli
from services.stack import StackError


def started(router):
    """A stand-in for a service: its command line names the router, as `-e ROUTER` does. Returned
    once it does: between fork and exec the child's command line is still pytest's."""
    p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)", "-e", router])
    cmdline = f"/proc/{p.pid}/cmdline"
    deadline = time.monotonic() + 10.0
    while router.encode() not in open(cmdline, "rb").read() and time.monotonic() < deadline:
        time.sleep(0.01)
    return p


def record(state_dir, router, pids):
    folder = state_dir / router.replace("/", "-").replace(":", "-")
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "up-vehicle.json").write_text(json.dumps({"router": router, "pids": pids}))
    return folder / "up-vehicle.json"


def down(**kw):
    return cli.cmd_down(argparse.Namespace(router=kw.get("router"), all=kw.get("all", False)))


def test_down_stops_one_stack_of_two_and_never_a_stranger(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(cli, "STATE_DIR", tmp_path)
    a, b = "tcp/127.0.0.1:1", "tcp/127.0.0.1:2"
    pa, pb = started(a), started(b)
    try:
        # this test's own process under a recorded name: its command line names no router
        record(tmp_path, a, {"sim": pa.pid, "planner": os.getpid()})
        record(tmp_path, b, {"sim": pb.pid})
        with pytest.raises(StackError, match="several stacks are up"):
            down()
        assert down(router=a) == 0
        assert pa.wait(10) == -15   # SIGTERM
        assert pb.poll() is None    # the other stack runs on
        assert "stopped sim (tcp/127.0.0.1:1)" in capsys.readouterr().out
        assert down() == 0          # one stack left: no need to name it
        assert pb.wait(10) == -15
        assert list(tmp_path.glob("*/up-*.json")) == []
    finally:
        for p in (pa, pb):
            if p.poll() is None:
                p.kill()
