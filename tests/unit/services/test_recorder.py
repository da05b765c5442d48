"""The recorder's logic (services/recorder.py FlightRecorder) without a router: what it logs,
what it counts and drops, when it flushes, when a stop is done, and the lockstep rewrite."""

import json

import pytest

import schemas
from flight.vehicle import load_vehicle
from schemas.flightlog import LOG_NAME, LogScan, read_log, scan
from schemas.fuzz import valid_doc
from services import recorder
from services.foxglove_map import FoxgloveMap
from services.recorder import DRAIN_MAX_S, QUIET_STEPS, FlightRecorder
from tests.unit.services.fake_io import FakeIO

V = 3   # the vehicle id: keys zp/3/...


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def values(message: schemas.Message) -> dict:
    return {k: v for k, v in valid_doc(message).items() if k not in ("version", "header")}


def imu(seq, t, source="sim"):
    return schemas.IMU.key(V), schemas.IMU.encode(t, seq, source, {"gyro_rad_s": [0.0, 0.0, 0.1 * seq],
                                                                   "accel_m_s2": [0.0, 0.0, 9.8]})


def make(tmp_path, **kw):
    io = FakeIO("recorder", {}, rate_hz=10.0, lockstep=False)
    clock = Clock()
    rec = FlightRecorder(io, tmp_path / LOG_NAME, V, clock=clock, **kw)
    return io, clock, rec


def test_good_messages_logged_as_decoded_and_the_log_complete_after_close(tmp_path):
    io, _, rec = make(tmp_path)
    for seq in range(3):
        rec.receive(*imu(seq, 1.0 + 0.01 * seq))
    health = schemas.HEALTH.encode(1.0, 0, "attitude", values(schemas.HEALTH))
    rec.receive(schemas.HEALTH.key(V, "attitude"), health)
    assert not rec.step()
    said = rec.close()
    found = LogScan(tmp_path / LOG_NAME)
    log = read_log(tmp_path / LOG_NAME, found)
    assert found.complete and found.messages == 4
    got = log[schemas.IMU.key(V)]
    assert [m["header"]["seq"] for m in got] == [0, 1, 2]
    assert got[2]["gyro_rad_s"] == pytest.approx([0.0, 0.0, 0.2]) and got[2]["header"]["source"] == "sim"
    assert log[schemas.HEALTH.key(V, "attitude")][0]["header"]["source"] == "attitude"
    assert said == f"wrote 4 messages to {tmp_path / LOG_NAME}; rejected 0 {{}}"
    assert io.rejected == {}


def test_malformed_and_unknown_keys_counted_and_dropped_own_health_and_liveliness_skipped(tmp_path):
    io, _, rec = make(tmp_path)
    rec.receive(*imu(0, 1.0))
    rec.receive(schemas.IMU.key(V), b"\x82\xc1not msgpack")                         # malformed
    rec.receive(schemas.IMU.key(V), schemas.BARO.encode(1.0, 0, "sim", values(schemas.BARO)))  # another message
    rec.receive(f"zp/{V}/no/such/topic", schemas.IMU.encode(1.0, 0, "sim", values(schemas.IMU)))
    own = schemas.HEALTH.encode(1.0, 0, "recorder", values(schemas.HEALTH))
    rec.receive(schemas.HEALTH.key(V, "recorder"), own)                             # its own health
    rec.receive(f"zp/{V}/alive/attitude", b"")                                      # a liveliness key
    rec.receive(*imu(1, 1.01))
    assert rec.write_arrived() == 7     # every one taken
    said = rec.close()
    log = read_log(tmp_path / LOG_NAME)
    assert list(log) == [schemas.IMU.key(V)]
    assert [m["header"]["seq"] for m in log[schemas.IMU.key(V)]] == [0, 1]   # the garbage cost no good one
    assert io.rejected == {"malformed": 2, "missing_field": 1}
    assert any(f"zp/{V}/no/such/topic" in p and "no message is defined" in p for p in io.problems)
    assert "wrote 2 messages" in said and f"rejected 3 {json.dumps(io.rejected, sort_keys=True)}" in said


def test_flushed_every_flush_s_so_a_killed_recorder_leaves_a_readable_log(tmp_path):
    _, clock, rec = make(tmp_path, flush_s=1.0)
    rec.receive(*imu(0, 1.0))
    rec.step()
    assert read_log(tmp_path / LOG_NAME) == {}     # in the chunk in progress: not handed to the OS yet
    clock.t += 1.0
    rec.receive(*imu(1, 1.1))
    rec.step()                                     # due: flushed
    rec.receive(*imu(2, 1.2))
    clock.t += 0.5
    rec.step()                                     # not due again yet
    # the process killed now (never closed): what was flushed is readable, the file cut
    found = LogScan(tmp_path / LOG_NAME)
    log = read_log(tmp_path / LOG_NAME, found)
    assert not found.complete
    assert [m["header"]["seq"] for m in log[schemas.IMU.key(V)]] == [0, 1]
    rec.close()
    assert len(read_log(tmp_path / LOG_NAME)[schemas.IMU.key(V)]) == 3


def test_a_stop_drains_until_quiet_then_is_done(tmp_path):
    _, clock, rec = make(tmp_path)
    assert not rec.step()                           # no stop asked: never done
    rec.ask_stop()
    for seq in range(5):                            # messages still coming: not done
        rec.receive(*imu(seq, 1.0 + seq))
        clock.t += 0.1
        assert not rec.step()
    for i in range(QUIET_STEPS):
        clock.t += 0.1
        assert rec.step() == (i == QUIET_STEPS - 1)
    rec.close()
    assert len(read_log(tmp_path / LOG_NAME)[schemas.IMU.key(V)]) == 5


def test_a_stop_is_done_after_drain_max_s_however_much_still_comes(tmp_path):
    _, clock, rec = make(tmp_path)
    rec.ask_stop()
    clock.t += 1.0
    rec.ask_stop()                                  # asked again: the first request counts
    steps = 0
    while True:
        rec.receive(*imu(steps, 1.0 + steps))
        clock.t += 0.1
        steps += 1
        if rec.step():
            break
        assert steps < 100
    assert clock.t - 100.0 > DRAIN_MAX_S and clock.t - 100.0 - 0.1 <= DRAIN_MAX_S + 1e-9


def test_lockstep_rewrite_sorts_by_sample_time_keeps_each_message_once(tmp_path):
    (tmp_path / (LOG_NAME + ".sorted")).write_bytes(b"left by a recorder killed while sorting")
    _, _, rec = make(tmp_path)
    assert not (tmp_path / (LOG_NAME + ".sorted")).exists()
    baro = schemas.BARO.key(V)
    rec.receive(*imu(1, 2.0))
    rec.receive(baro, schemas.BARO.encode(1.5, 0, "sim", values(schemas.BARO)))
    rec.receive(*imu(0, 1.0))
    rec.receive(*imu(0, 1.0))                       # sent again (same seq, same bytes): kept once
    rec.step()
    rec.close()
    assert rec.sort() == 3
    assert not (tmp_path / (LOG_NAME + ".sorted")).exists()
    found = LogScan(tmp_path / LOG_NAME)
    times = [(m.log_time, c.topic) for c, m in scan(tmp_path / LOG_NAME, found)]
    assert found.complete
    assert times == [(1_000_000_000, schemas.IMU.key(V)), (1_500_000_000, baro), (2_000_000_000, schemas.IMU.key(V))]


def test_real_time_foxglove_messages_written_beside_the_bus_messages(tmp_path):
    fmap = FoxgloveMap(load_vehicle("x250").motor_positions_m, V, poses=False)
    _, _, rec = make(tmp_path, foxglove=fmap)
    truth = values(schemas.TRUTH)
    truth["quaternion_wxyz"] = [1.0, 0.0, 0.0, 0.0]
    rec.receive(schemas.TRUTH.key(V), schemas.TRUTH.encode(2.0, 0, "sim", truth))
    rec.close()
    channels = {c.topic: c.message_encoding for c, _ in scan(tmp_path / LOG_NAME)}
    assert channels[schemas.TRUTH.key(V)] == "json"
    assert any(t.endswith("tf/truth") and enc == "protobuf" for t, enc in channels.items())
    assert read_log(tmp_path / LOG_NAME).keys() == {schemas.TRUTH.key(V)}   # the bus channels as they came


def test_keys_beyond_the_lookup_bound_are_still_logged(tmp_path, monkeypatch):
    monkeypatch.setattr(recorder, "MAX_KEYS", 2)
    io, _, rec = make(tmp_path)
    keys = [schemas.HEALTH.key(V, s) for s in ("sim", "attitude", "position", "motors")]
    for k, s in zip(keys, ("sim", "attitude", "position", "motors")):
        rec.receive(k, schemas.HEALTH.encode(1.0, 0, s, values(schemas.HEALTH)))
    rec.write_arrived()
    assert len(rec.decoders) == 2
    rec.close()
    assert set(read_log(tmp_path / LOG_NAME)) == set(keys) and io.rejected == {}
