"""deploy/view.py's reader: strict decoding, counted drops, no work for channels nobody watches."""

import foxglove

import schemas
from deploy.view import LiveView
from flight.vehicle import load_vehicle
from services.foxglove_map import FoxgloveMap


def view():
    return LiveView(FoxgloveMap(load_vehicle("x250").motor_positions_m), foxglove.Context())


def imu(seq):
    return schemas.IMU.encode(seq / 400, seq, "sim", {"gyro_rad_s": [0.0, 0.0, 0.0], "accel_m_s2": [0.0, 0.0, 9.81]})


def test_malformed_and_unknown_messages_are_counted_and_dropped():
    v = view()
    v.handle("zp/0/sim/imu", b"\xc1not msgpack")
    v.handle("zp/0/no/such/topic", b"")
    v.handle("zp/0/sim/imu", schemas.BARO.encode(0.0, 0, "sim", {"pressure_pa": 101325.0, "temperature_k": 288.0}))
    assert v.stats.received == 3 and v.stats.forwarded == 0
    assert v.stats.rejected == {"malformed": 1, "no_schema": 1, "missing_field": 1}


def test_liveliness_is_not_served():
    v = view()
    v.handle("zp/0/alive/motors", b"")
    assert v.stats.rejected == {} and v._raw == {"zp/0/alive/motors": None}


def test_sequence_gaps_are_counted_and_nothing_is_sent_without_a_client():
    v = view()
    for seq in (0, 1, 2, 5, 6):
        v.handle("zp/0/sim/imu", imu(seq))
    assert v.stats.gaps == 2 and v.stats.received == 5
    assert v.stats.forwarded == 0   # no client subscribed: no JSON, no encoding
