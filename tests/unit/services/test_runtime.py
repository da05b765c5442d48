"""The runtime's pieces that need no router: inboxes (decode on the reader's thread, rejects
and losses counted), scheduling requests, param/set checked against the declarations."""

import os
import re
import signal
from collections import deque
import threading
from types import SimpleNamespace

import pytest
import zenoh

import schemas
from services import lockstep, runtime
from services.runtime import RAW_QUEUE_MAX, Inbox, apply_scheduling
from services.stack import StackError
from tests.unit.services.fake_io import FakeIO


class FakeRuntime:
    """What an Inbox asks of its runtime."""

    def __init__(self):
        self.rejected, self.dropped = {}, {}
        self._arrival, self._wake = threading.Event(), threading.Event()
        self._wake_t = 0.0
        self.tick = -1
        self.lockstep = True      # tags matter only in lockstep
        self.event_driven = True

    def _sync_tick(self, upstream):
        return self.tick

    def reject(self, key, exc):
        self.rejected[exc.reason] = self.rejected.get(exc.reason, 0) + 1

    def count_dropped(self, key, n=1):
        self.dropped[key] = self.dropped.get(key, 0) + n

    def count_rejects(self, key, reason, n=1):
        self.rejected[reason] = self.rejected.get(reason, 0) + n


def imu_payload(seq, t=1.0, source="sim"):
    return schemas.IMU.encode(t, seq, source, {"gyro_rad_s": [0.0, 0.0, 0.1], "accel_m_s2": [0.0, 0.0, 9.8]})


def deliver(box, payload):
    box._on_sample(SimpleNamespace(payload=zenoh.ZBytes(payload)))


def test_inbox_decodes_when_read_and_counts_rejects_and_gaps():
    rt = FakeRuntime()
    box = Inbox(rt, schemas.IMU, "zp/0/sim/imu", "sim", keep=8)
    for seq in (0, 1, 3):                      # seq 2 never arrived
        deliver(box, imu_payload(seq, t=1.0 + seq))
    deliver(box, b"\x82\xc1not msgpack")       # malformed, though it starts like a map
    assert rt.rejected == {} and box._raw      # the callback only queued
    taken = box.take()
    assert [m["header"]["seq"] for m in taken] == [0, 1, 3]
    assert rt.rejected == {"malformed": 1}
    assert rt.dropped == {"zp/0/sim/imu": 1}
    assert box.take() == []                    # taken once
    deliver(box, imu_payload(4, t=5.0))
    deliver(box, imu_payload(4, t=5.0))        # a repeat keeps its seq: not a loss
    assert box.latest()["header"]["seq"] == 4 and rt.dropped == {"zp/0/sim/imu": 1}
    deliver(box, imu_payload(0, t=6.0))        # the sender restarted: no loss either
    assert box.latest()["header"]["t_s"] == 6.0 and rt.dropped == {"zp/0/sim/imu": 1}


def test_the_callback_and_the_poll_refuse_exactly_the_payloads_that_cannot_start_a_map():
    """The first-byte test reads the byte's value: it must agree with MAP_FIRST_BYTES on all 256
    (and refuse an empty payload), in the callback and in a polled inbox's screen alike."""
    rt = FakeRuntime()
    box = Inbox(rt, schemas.IMU, "zp/0/sim/imu", "sim", keep=4)
    for b in range(256):
        deliver(box, bytes([b, 0x00]))
    deliver(box, b"")
    assert len(box._raw) == len(runtime.MAP_FIRST_BYTES) == 18
    assert sorted(data[:1] for _, data in box._raw) == sorted(runtime.MAP_FIRST_BYTES)
    assert rt.rejected == {"malformed": 256 - 18 + 1}
    for b in range(256):
        data, reason = runtime.screen(schemas.IMU, zenoh.ZBytes(bytes([b, 0x00])))
        assert (data is not None, reason) == ((True, "") if bytes([b]) in runtime.MAP_FIRST_BYTES
                                              else (False, "malformed")), b
    assert runtime.screen(schemas.IMU, zenoh.ZBytes(b"")) == (None, "malformed")


def test_inbox_visibility_limit_and_wake():
    rt = FakeRuntime()
    box = Inbox(rt, schemas.IMU, "zp/0/sim/imu", "sim", keep=4)
    box.wakes = True
    rt.tick = 5
    deliver(box, imu_payload(0))
    assert rt._wake.is_set()                   # a woken loop's input wakes it
    other = Inbox(rt, schemas.IMU, "zp/0/sim/imu", "sim", keep=4)
    rt._arrival.clear()
    deliver(other, imu_payload(1))
    assert rt._arrival.is_set()                # an event-driven service runs on any input
    box.limit = 5                              # tagged 5: not visible at tick 5
    assert box.latest() is None and box.take() == []
    box.limit = 6
    assert box.latest()["header"]["seq"] == 0


def test_take_returns_each_visible_message_once_in_arrival_order():
    rt = FakeRuntime()
    box = Inbox(rt, schemas.IMU, "zp/0/sim/imu", "sim", keep=8)
    for seq, tick in enumerate((3, 4, 4, 6, 7)):
        rt.tick = tick
        deliver(box, imu_payload(seq))
    box.limit = 5                              # tags 3, 4, 4 visible; 6 and 7 not yet
    assert [m["header"]["seq"] for m in box.take()] == [0, 1, 2]
    assert box.take() == []
    box.limit = 8
    assert [m["header"]["seq"] for m in box.take()] == [3, 4]
    for seq in range(5, 15):                   # more than keep: the oldest go, the rest taken once
        deliver(box, imu_payload(seq))
    assert [m["header"]["seq"] for m in box.take()] == list(range(7, 15))


def test_unread_overflow_is_a_loss_only_for_a_reader_of_every_message():
    rt = FakeRuntime()
    newest = Inbox(rt, schemas.IMU, "newest", "sim", keep=2)
    every = Inbox(rt, schemas.IMU, "every", "sim", keep=2)
    every.take()
    deliver(newest, imu_payload(0))
    assert newest.latest() is not None       # read once: the overflow after it is not a loss either
    for seq in range(1, RAW_QUEUE_MAX + 10):
        deliver(newest, imu_payload(seq))
    for seq in range(RAW_QUEUE_MAX + 10):
        deliver(every, imu_payload(seq))
    assert newest.latest()["header"]["seq"] == RAW_QUEUE_MAX + 9
    assert "newest" not in rt.dropped          # superseded, never needed
    assert rt.dropped["every"] >= 10
    assert every.take()[-1]["header"]["seq"] == RAW_QUEUE_MAX + 9


def test_scheduling_reports_what_holds_for_every_thread():
    assert apply_scheduling(0, ()) == "normal"
    allowed = sorted(os.sched_getaffinity(0))
    started, stop = threading.Event(), threading.Event()
    helper = threading.Thread(target=lambda: (started.set(), stop.wait()))
    helper.start()
    started.wait()
    try:
        assert apply_scheduling(0, (allowed[0],)) == f"cpu {allowed[0]}"
        assert os.sched_getaffinity(helper.native_id) == {allowed[0]}   # not only the caller
        refused = apply_scheduling(0, (4096,))
        assert "cpu [4096] refused" in refused
    finally:
        apply_scheduling(0, tuple(allowed))
        stop.set()
        helper.join()
    assert os.sched_getaffinity(0) == set(allowed)


def test_refused_priority_is_reported_not_fatal():
    # 100 is beyond SCHED_FIFO's 1..99 for anyone (root included): the OS refuses it, and the
    # policy stays what it was (the suite's workers run at SCHED_IDLE, tests/conftest.py)
    before = os.sched_getscheduler(0)
    assert "priority 100 refused" in apply_scheduling(100, ())
    assert os.sched_getscheduler(0) == before


def test_an_idle_reader_loses_nothing_it_did_not_ask_for():
    rt = FakeRuntime()
    box = Inbox(rt, schemas.IMU, "imu", "sim", keep=2)
    deliver(box, imu_payload(0))
    assert box.take()                          # a failsafe read it ...
    box.idle()                                 # ... and went back to sleep
    for seq in range(1, RAW_QUEUE_MAX + 10):
        deliver(box, imu_payload(seq))
    assert rt.dropped == {}
    assert box.take()[-1]["header"]["seq"] == RAW_QUEUE_MAX + 9   # reading again: the newest


class Reports:
    """What services/lockstep.Progress reports to: a dropped participant, a problem."""

    def __init__(self):
        self.rejected, self.problems = {}, []

    def dropped(self, name, why):
        self.rejected[f"lockstep_dropped_{name}"] = 1
        self.problems.append(f"lockstep: {name} dropped from the clock ({why})")


def progress_of(*names):
    reports = Reports()
    progress = lockstep.Progress(threading.Event(), reports.dropped)
    for n in names:
        progress.follow(n)
    return progress, reports


def test_lockstep_wait_drops_a_participant_whose_token_went():
    progress, reports = progress_of("attitude", "planner")
    progress.upstreams["planner"].last_done = 10
    progress.drop("planner", "its liveliness token is gone")   # gone, but owed nothing: not reported
    assert progress.wait_synced({"planner": 10}, 10, reports.problems.append) and reports.rejected == {}
    result = []
    waiter = threading.Thread(target=lambda: result.append(progress.wait_synced({"attitude": 8}, 9, print)))
    waiter.start()
    waiter.join(0.3)
    assert waiter.is_alive()                   # attitude owes tick 8: waiting
    progress.drop("attitude", "its liveliness token is gone")
    waiter.join(2.0)
    assert result == [True]
    assert reports.rejected == {"lockstep_dropped_attitude": 1}
    assert "attitude dropped from the clock (its liveliness token is gone)" in reports.problems[-1]


def test_lockstep_wait_drops_a_silent_participant_after_the_timeout(monkeypatch):
    monkeypatch.setattr(lockstep, "DROP_AFTER_S", 0.6)
    progress, reports = progress_of("position")
    assert progress.wait_synced({"position": 3}, 4, print)   # frozen: dropped after 0.6 s (checked every 0.5 s)
    assert progress.gone == {"position"} and reports.rejected == {"lockstep_dropped_position": 1}


def test_lockstep_progress_from_syncs_and_run_done_messages_only_moves_forward():
    progress, _ = progress_of("motors")
    assert progress.last_done("motors") == -2 and progress.last_done("nobody") == -2
    progress.on_sync("motors", {"tick": -1, "next_tick": 0, "triggers": [], "period_ticks": 1})
    assert progress.wait_ready(["motors"])
    progress.on_run_done("motors", 7)
    progress.on_sync("motors", {"tick": 5, "next_tick": 6, "triggers": [], "period_ticks": 1})   # late: kept at 7
    assert progress.last_done("motors") == 7 and progress.upstreams["motors"].next_tick == 6
    progress.on_clock({"tick": 8})
    assert progress.sim_tick == 8 and progress.clocks[-1]["tick"] == 8


def test_multicast_scouting_is_off_unless_asked_for():
    import json

    def scouting(*argv):
        args = runtime.service_parser("attitude", "").parse_args(["-e", "tcp/127.0.0.1:7447", *argv])
        return json.loads(str(runtime.zenoh_config(args)))["scouting"]["multicast"]["enabled"]

    assert scouting() is False
    assert scouting("--no-multicast-scouting") is False
    assert scouting("--multicast-scouting") is True


# ---------------------------------------------------------------- param/set in flight
@pytest.fixture
def attitude_runtime():
    """The attitude service's Runtime as it starts (a Zenoh peer on loopback, no router)."""
    from services.params.attitude import PARAMS

    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    rt = runtime.Runtime("attitude", runtime.service_parser("attitude", "").parse_args([]), PARAMS)
    try:
        yield rt
    finally:
        rt.session.close()
        for s, h in handlers.items():
            signal.signal(s, h)


def param_set(rt, key, value, service="attitude"):
    rt._on_param_set(SimpleNamespace(payload=zenoh.ZBytes(schemas.PARAM_SET.encode(
        1.0, 0, "mavlink", {"service": service, "key": key, "value": value}))))


def test_param_set_within_the_declaration_applies_live(attitude_runtime):
    rt = attitude_runtime
    k = rt.live_array("k")
    param_set(rt, "k", [8.0, 8.0, 6.0])
    assert rt.params["k"] == [8.0, 8.0, 6.0] and list(k) == [8.0, 8.0, 6.0]
    param_set(rt, "stopping_accel_fraction", [1.0])     # on the bound: inclusive
    assert rt.params["stopping_accel_fraction"] == 1.0
    param_set(rt, "k", [1.0, 1.0, 1.0], service="position")   # another service's: not this one's business
    assert rt.params["k"] == [8.0, 8.0, 6.0] and "param_rejected" not in rt.rejected


@pytest.mark.parametrize("key, value, said", [
    ("k", [500.0, 16.0, 16.0],
     r"param/set from mavlink: attitude\.k: \[500\.0, 16\.0, 16\.0\] outside \[0\.1, 200\] 1/s"),
    ("k", [16.0, 16.0, 0.0], r"attitude\.k: .* outside \[0\.1, 200\]"),
    ("setpoint_timeout_s", [0.0], r"attitude\.setpoint_timeout_s: 0\.0 outside \(0, inf\) s"),
    ("stopping_accel_fraction", [1.5], r"outside \[0, 1\]"),
    ("k", [8.0, 8.0], r"attitude\.k: expected 3 values, got 2"),
    ("stopping_accel_fraction", [0.5, 0.5], r"expected float, got \[0\.5, 0\.5\]"),
    ("state_source", [1.0], r"attitude\.state_source: expected str"),       # a choice is a string, never a number
    ("compensate_acceleration", [1.0], r"expected bool"),
    ("kk", [1.0], r"unknown parameter 'kk'"),
])
def test_param_set_out_of_its_declaration_refused_counted_and_the_old_value_kept(attitude_runtime, key, value, said):
    rt = attitude_runtime
    k = rt.live_array("k")
    before = {name: list(v) if isinstance(v, list) else v for name, v in rt.params.items()}
    param_set(rt, key, value)
    assert rt.rejected == {"param_rejected": 1}
    assert rt.params == before and list(k) == before["k"]
    assert re.search(said, rt.detail), rt.detail
    if key in before:
        assert rt.detail.endswith(f"; {key} stays {before[key]}")


def test_param_set_checks_an_integer_parameter_as_start_up_does():
    """The check is the declarations' (services/stack.py check_param), shared with the services'
    fakes: an int parameter takes a whole number, within its bounds."""
    from services.params.mavlink import PARAMS

    io = FakeIO("mavlink", PARAMS)
    assert io.set_param("system_id", [3.0]) == 3 and type(io.params["system_id"]) is int
    with pytest.raises(StackError, match=r"param/set from test: mavlink\.system_id: 300 outside \[1, 255\]"):
        io.set_param("system_id", [300.0])
    with pytest.raises(StackError, match=r"mavlink\.system_id: expected int, got 2\.5"):
        io.set_param("system_id", [2.5])
    assert io.params["system_id"] == 3
class FakeChannel:
    """Zenoh's ring channel as a polled inbox reads it."""

    def __init__(self, payloads):
        self.samples = deque(SimpleNamespace(payload=zenoh.ZBytes(p)) for p in payloads)

    def try_recv(self):
        return self.samples.popleft() if self.samples else None


def test_polled_inbox_reads_what_zenoh_queued_screens_it_and_counts_rejects():
    rt = FakeRuntime()
    rt.lockstep = False
    box = Inbox(rt, schemas.IMU, "zp/0/sim/imu", "sim", keep=8)
    box._channel = FakeChannel([imu_payload(0), b"not a map", imu_payload(2),
                                b"\x82\xc1not msgpack", b"\x80" + bytes(schemas.IMU.size_limit)])
    assert [m["header"]["seq"] for m in box.take()] == [0, 2]
    assert rt.rejected == {"malformed": 2, "too_large": 1}
    assert rt.dropped == {"zp/0/sim/imu": 1}        # seq 1 never came
    box._channel = FakeChannel([imu_payload(3), imu_payload(4)])
    assert box.latest()["header"]["seq"] == 4 and box.fresh()
    box._channel = FakeChannel([imu_payload(5)])
    box.idle()                                       # a reader that stops lets the queue go
    assert 5 not in [m["header"]["seq"] for m in box.take()] and not box._channel.samples


def test_a_full_ring_counts_a_loss_for_a_reader_of_every_message_only():
    rt = FakeRuntime()
    rt.lockstep = False
    newest = Inbox(rt, schemas.IMU, "zp/0/sim/imu", "sim", keep=4)
    newest.latest()
    newest._channel = FakeChannel([imu_payload(s) for s in range(1000, 1000 + RAW_QUEUE_MAX)])
    assert newest.latest()["header"]["seq"] == 1000 + RAW_QUEUE_MAX - 1 and rt.dropped == {}
    every = Inbox(rt, schemas.IMU, "zp/0/sim/imu2", "sim", keep=4)
    every._channel = FakeChannel([])
    every.take()
    every._channel = FakeChannel([imu_payload(s) for s in range(RAW_QUEUE_MAX)])
    every.take()
    assert rt.dropped.get("zp/0/sim/imu2", 0) >= 1
