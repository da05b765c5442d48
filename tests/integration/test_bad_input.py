"""Malformed messages on every input key are counted and dropped; the flight goes on."""

import math
import threading
import time

import msgpack
import pytest

from deploy.launcher import alive_services, client_session, free_port

from .conftest import TRUTH_STATE, fly

pytestmark = pytest.mark.integration

INPUT_KEYS = ["zp/0/sim/truth", "zp/0/pos/setpoint", "zp/0/att/command", "zp/0/planner/setpoint",
              "zp/0/motors/pwm", "zp/0/pos/state", "zp/0/@lockstep/clock/attitude",
              "zp/0/@lockstep/sync/motors"]
RECEIVERS = {"sim", "attitude", "position", "motors", "planner", "recorder"}
HEADER = {"t_s": 1.0, "seq": 0, "source": "intruder"}
BAD_PAYLOADS = {
    "malformed": b"\xc1\x00garbage",
    "wrong_type": msgpack.packb({"version": 1, "header": {**HEADER, "seq": "first"}}),
    "non_finite": msgpack.packb({"version": 1, "header": {**HEADER, "t_s": math.nan}}),
}


def inject(endpoint: str, stop: threading.Event, sent: dict) -> None:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not stop.is_set():
        try:
            session = client_session(endpoint)
            break
        except Exception:
            time.sleep(0.2)
    else:
        return
    # every receiver alive, then a moment to declare its subscriptions (starts are slow on a loaded machine)
    while not stop.is_set() and not alive_services(session, 0) >= RECEIVERS:
        time.sleep(0.2)
    time.sleep(2.0)
    for _ in range(3):
        for key in INPUT_KEYS:
            for reason, payload in BAD_PAYLOADS.items():
                session.put(key, payload)
                sent[reason] = sent.get(reason, 0) + 1
                if "/@lockstep/" not in key:   # the recorder's zp/0/** does not match the handshake's keys
                    sent["recordable"] = sent.get("recordable", 0) + 1
        time.sleep(0.5)
    session.close()


def test_garbage_on_every_input_is_counted_and_dropped(tmp_path):
    port = free_port()
    stop, sent = threading.Event(), {}
    thread = threading.Thread(target=inject, args=(f"tcp/127.0.0.1:{port}", stop, sent))
    thread.start()
    try:
        proc, m = fly(tmp_path, "hover", "--port", str(port), *TRUTH_STATE)
    finally:
        stop.set()
        thread.join()
    assert sent, "nothing was injected"
    assert proc.returncode == 0 and m["completed"], proc.stdout + proc.stderr
    assert m["position_rms_m"] < 0.01  # the flight did not notice
    rejected = m["rejected_messages"]
    for service in ("attitude", "position", "motors", "planner", "sim"):
        assert set(rejected[service]) >= {"malformed", "wrong_type", "non_finite"}, (service, rejected)
    # the recorder decodes everything it is sent: it saw every bad message once
    assert f"rejected {sent['recordable']} " in (tmp_path / "logs" / "recorder.log").read_text()
