"""The runtime's pieces that need no Zenoh session: inboxes (decode on the reader's thread,
rejects and losses counted), scheduling requests."""

import os
import threading
from types import SimpleNamespace


import zenoh

import schemas
from services import lockstep, runtime
from services.runtime import RAW_QUEUE_MAX, Inbox, apply_scheduling


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
    # 100 is beyond SCHED_FIFO's 1..99 for anyone (root included): the OS refuses it
    assert "priority 100 refused" in apply_scheduling(100, ())
    assert os.sched_getscheduler(0) == os.SCHED_OTHER


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
