"""bench/two_hosts.py --trace: the wiretap's reading of frames and the latency split."""

import struct

import msgpack

from bench.support.trace import split, stalls
from bench.support.wiretap import headers


def _frame(payload: bytes, proto: int = 17, tos: int = 0xB8) -> bytes:
    eth = b"\x00" * 12 + b"\x08\x00"
    ip = struct.pack("!BBHHHBBH4s4s", 0x45, tos, 20 + 8 + len(payload), 0, 0, 64, proto, 0,
                     bytes([10, 77, 0, 1]), bytes([10, 77, 0, 2]))
    return eth + ip + struct.pack("!HHHH", 7450, 40000, 8 + len(payload), 0) + payload


def _msg(t_s: float, seq: int, source: str) -> bytes:
    return msgpack.packb({"version": 1, "header": {"t_s": t_s, "seq": seq, "source": source}, "x": [1.0, 2.0]})


def test_every_header_of_a_udp_frame_is_read_and_tcp_frames_are_left_alone():
    payload = b"\x01\x02zenoh" + _msg(12.5, 7, "sim") + b"\x03" + _msg(12.75, 8, "motors")
    assert headers(_frame(payload)) == [(12.5, 7, "sim"), (12.75, 8, "motors")]
    assert headers(_frame(payload, proto=6)) == []
    assert headers(_frame(payload[:payload.rfind(b"motors")])) == [(12.5, 7, "sim")]   # the second header cut off


def test_split_puts_each_message_s_time_where_it_was_spent():
    # 100 messages: 1 ms on the sender, 20 ms on the link, 1 ms on the receiver; one late by 50 ms on the sender
    rows, sent, received = [], [], []
    for i in range(100):
        t_s = 100.0 + i * 0.01
        late = 0.05 if i == 42 else 0.0
        sent.append([t_s + 0.001 + late, t_s, i, "sim"])
        received.append([t_s + 0.021 + late, t_s, i, "sim"])
        rows.append([t_s + 0.022 + late, t_s, i, "sim"])
    rows.append([200.0, 150.0, 999, "sim"])   # never seen on the wire: left out
    got = split({"zp/0/sim/imu": rows}, sent, received)["zp/0/sim/imu"]
    assert got["matched"] == 100 and got["of"] == 101
    assert abs(got["link"]["p50"] - 20.0) < 1e-6 and abs(got["receiver_host"]["max"] - 1.0) < 1e-6
    assert abs(got["sender_host"]["max"] - 51.0) < 1e-6
    tail = got["tail_1pct_mean"]
    assert abs(tail["end_to_end"] - 72.0) < 1e-6 and abs(tail["sender_host"] - 51.0) < 1e-6


def test_stalls_are_moments_when_several_keys_were_held_together():
    probe, sent = {}, []
    for key, source in (("zp/0/sim/imu", "sim"), ("zp/0/motors/pwm", "motors"), ("zp/0/att/command", "attitude"),
                        ("zp/0/sim/camera", "camera")):
        rows = []
        for i in range(200):
            t_s = 100.0 + i * 0.005
            held = 0.001
            if 50 <= i < 60 and source != "camera":   # all three control keys held together: one stall
                held = 0.040
            if i == 150 and source == "sim":           # one key late alone: no stall
                held = 0.030
            if source == "camera":                     # late by design (exposure time): left out
                held = 0.052
            sent.append([t_s + held, t_s, i, source])
            rows.append([t_s + held + 0.02, t_s, i, source])
        probe[key] = rows
    got = stalls(probe, sent)
    assert got["windows"] == 1 and got["messages"] == 600 and got["late"] == 31
    assert abs(got["held_ms"]["max"] - 40.0) < 1e-6
