"""The link emulator's rules (bench/support/linkemu.py: delay drawn per frame, loss, order) on fake
sockets, and the bench's link profiles and loss count (bench/two_hosts.py)."""

import argparse

import pytest

from bench.support.linkemu import PACKET_OUTGOING, VNET_HDR_LEN, Direction, dscp
from bench.two_hosts import PROFILES, _lost_in_outage, outage_spec, parse_profile, seq_loss

HOST = 0   # sll_pkttype of a frame for this host


class FakeSocket:
    def __init__(self):
        self.waiting, self.sent = [], []

    def recvfrom(self, _n):
        if not self.waiting:
            raise BlockingIOError
        return self.waiting.pop(0)

    def send(self, frame):
        self.sent.append(frame)


def run(direction: Direction, n: int, gap_s: float, src: FakeSocket, kind: int = HOST) -> list[tuple[float, bytes]]:
    """n frames, one every gap_s; returns (departure, frame) as the forwarder sends them."""
    out, t = [], 0.0
    for i in range(n):
        src.waiting.append((i.to_bytes(4, "big"), ("veth", 3, kind, 1, b"")))
        direction.take(t)
        t += gap_s
        before = len(direction.dst.sent)
        direction.send_due(t)
        out += [(t, f) for f in direction.dst.sent[before:]]
    for _ in range(1000):   # the frames still in flight, as time goes on
        t += gap_s
        before = len(direction.dst.sent)
        direction.send_due(t)
        out += [(t, f) for f in direction.dst.sent[before:]]
    return out


def make(loss=0.0, seed=0, reorder=False, delay_s=0.020, jitter_s=0.005):
    src, dst = FakeSocket(), FakeSocket()
    return Direction("a->b", src, dst, delay_s, jitter_s, loss, seed, reorder), src


def test_frames_keep_their_order_and_get_the_drawn_delay():
    d, src = make()
    sent = run(d, 2000, 0.002, src)   # frames 2 ms apart, jitter +-5 ms: a draw may be shorter than the one before
    order = [int.from_bytes(f, "big") for _, f in sent]
    assert order == sorted(order) and len(order) == 2000
    delays = sorted(d.delays)
    assert 0.015 <= delays[0] and delays[-1] <= 0.025 + 0.002 + 1e-9   # within the draw, and the 2 ms step of the test
    assert delays[len(delays) // 2] > 0.020   # kept in order, a frame waits for the slower one before it


def test_reorder_lets_a_shorter_draw_overtake():
    d, src = make(reorder=True)
    order = [int.from_bytes(f, "big") for _, f in run(d, 2000, 0.002, src)]
    assert sorted(order) == list(range(2000)) and order != sorted(order)


def test_loss_is_seeded_and_near_its_rate():
    lost = []
    for seed in (1, 1, 2):
        d, src = make(loss=0.05, seed=seed)
        kept = {int.from_bytes(f, "big") for _, f in run(d, 20000, 0.001, src)}
        assert d.dropped == 20000 - len(kept)
        lost.append(set(range(20000)) - kept)
    assert lost[0] == lost[1] != lost[2]
    assert 0.04 < len(lost[0]) / 20000 < 0.06


def test_frames_the_host_sent_itself_are_not_forwarded():
    d, src = make(jitter_s=0.0)
    assert run(d, 10, 0.001, src, kind=PACKET_OUTGOING) == [] and d.received == 0


def test_an_interface_set_down_is_an_error_once_not_the_forwarder_s_end():
    """--outage sets the forwarder's interfaces down: its raw socket reports ENETDOWN once, then
    nothing until they are up again; the forwarder counts it and forwards what comes after."""
    d, src = make(jitter_s=0.0)
    waiting = src.recvfrom

    def down_once(n, state={"down": True}):
        if state.pop("down", False):
            raise OSError(100, "Network is down")
        return waiting(n)
    src.recvfrom = down_once
    d.take(0.0)
    assert d.recv_errors == 1 and d.received == 0
    assert len(run(d, 5, 0.001, src)) == 5 and d.stats()["recv_errors"] == 1


def test_outage_spec_and_what_the_outage_lost():
    assert outage_spec("8:3") == (8.0, 3.0) and outage_spec("0:0.5") == (0.0, 0.5)
    for bad in ("8", "8:", "-1:3", "8:0", "x:3"):
        with pytest.raises(argparse.ArgumentTypeError):
            outage_spec(bad)
    # [arrival, sample time, seq, source]: seq 1-3 before the cut at 10.0, 4-5 sent while cut and
    # delivered late, 6-9 never, 10 on once back (the first sent after the restore: at 12.4): 4 lost
    # to the outage; another sender's gap before the cut (its seq 2) is the link's, not the outage's
    rows = [[t + 0.02, t, q, "a"] for q, t in ((1, 9.8), (2, 9.9), (3, 9.95))]
    rows += [[12.3, 10.1, 4, "a"], [12.3, 10.2, 5, "a"], [12.5, 12.4, 10, "a"]]
    rows += [[9.0, 9.0, 1, "b"], [9.5, 9.5, 3, "b"], [12.6, 12.6, 30, "b"]]
    assert _lost_in_outage(rows, 10.0, 12.4) == 4 + 26
    assert _lost_in_outage(rows, 10.0, None) is None


def test_profiles():
    assert (PROFILES["lan"].delay_ms, PROFILES["lan"].jitter_ms, PROFILES["lan"].loss_pct) == (20.0, 5.0, 1.0)
    assert (PROFILES["bad"].delay_ms, PROFILES["bad"].jitter_ms, PROFILES["bad"].loss_pct) == (50.0, 20.0, 5.0)
    assert not PROFILES["none"].impaired and parse_profile("none") is PROFILES["none"]
    assert parse_profile("30/10/2").delay_ms == 30.0
    for bad in ("fast", "30/10", "5/10/1", "30/10/101", "-1/0/0"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_profile(bad)


def test_seq_loss_counts_the_gaps():
    assert seq_loss([]) == (0, 0)
    assert seq_loss([5, 6, 7]) == (0, 3)
    assert seq_loss([5, 7, 7, 10]) == (3, 6)   # 6, 8, 9 missing; a repeat is not a message more


def ipv4_frame(tos: int, size: int, tag: int) -> bytes:
    """A frame as the emulator reads it: virtio-net header, Ethernet (IPv4), IP header with `tos`."""
    eth = b"\x00" * 12 + b"\x08\x00"
    ip = bytes([0x45, tos]) + b"\x00" * 18
    body = tag.to_bytes(4, "big")
    return b"\x00" * VNET_HDR_LEN + eth + ip + body + b"\x00" * max(0, size - VNET_HDR_LEN - 38)


def test_dscp_is_read_from_ipv4_and_ipv6_frames():
    assert dscp(ipv4_frame(0xB8, 100, 0)) == 46 and dscp(ipv4_frame(0x20, 100, 0)) == 8
    v6 = b"\x00" * VNET_HDR_LEN + b"\x00" * 12 + b"\x86\xdd" + bytes([0x6B, 0x80]) + b"\x00" * 40
    assert dscp(v6) == 46   # traffic class 0xB8 across the first two bytes
    assert dscp(b"\x00\x01") == 0   # too short: unmarked


def wire(priority_dscp=None, rate_bit_s=8e6, queue_bytes=1 << 20):
    src, dst = FakeSocket(), FakeSocket()
    return Direction("a->b", src, dst, 0.010, 0.0, 0.0, 0, False, rate_bit_s=rate_bit_s,
                     priority_dscp=priority_dscp, queue_bytes=queue_bytes), src, dst


def flood_and_control(priority_dscp):
    """100 bulk frames of 10 kB (1 s of an 8 Mbit/s wire) at t=0, then a control frame at 0.5 s:
    when the control frame leaves."""
    d, src, dst = wire(priority_dscp)
    for i in range(100):
        src.waiting.append((ipv4_frame(0x20, 10_000, i), ("veth", 3, HOST, 1, b"")))
    d.take(0.0)
    t = 0.0
    while t < 3.0:
        if abs(t - 0.5) < 1e-9:
            src.waiting.append((ipv4_frame(0xB8, 200, 999), ("veth", 3, HOST, 1, b"")))
            d.take(t)
        d.serialise(t)
        d.send_due(t)
        for f in dst.sent:
            if dscp(f) == 46:
                return t, d
        t = round(t + 0.0005, 4)
    raise AssertionError("the control frame never left")


def test_the_wire_carries_its_rate_and_a_marked_frame_goes_first():
    left, d = flood_and_control(priority_dscp=None)   # one queue: behind the flood's remaining half second
    assert 0.99 <= left <= 1.03, left
    left, d = flood_and_control(priority_dscp=46)     # its own queue: the frame on the wire (10 ms), then it
    assert 0.5 + 0.010 <= left <= 0.5 + 0.010 + 0.010 + 0.001, left
    assert d.stats()["wire"]["frames"] == {"high": 1, "low": 100}


def test_a_full_transmit_queue_drops_the_newest():
    d, src, _ = wire(rate_bit_s=8e6, queue_bytes=50_000)
    for i in range(10):
        src.waiting.append((ipv4_frame(0, 10_000, i), ("veth", 3, HOST, 1, b"")))
    d.take(0.0)
    assert d.tx_frames[1] == 5 and d.tx_dropped[1] == 5


def test_the_secured_split_is_the_placement_stack_with_its_link_over_tls(tmp_path):
    """bench/two_hosts.py --secure: the same stack file, [security] added and the link's endpoints
    over TLS (tls: the UDP link left out; tls+quic: QUIC's datagrams for it); a secured stack the
    loader accepts (loopback routers, only tls/quic between hosts), services untouched."""
    import re

    from bench.two_hosts import STACKS, secure_text
    from services.stack import load_stack

    for placement in ("ground", "telemetry"):
        src = STACKS[placement]
        plain = load_stack(src)
        for link, expect in (("tls", {"tls"}), ("tls+quic", {"tls", "quic"})):
            path = tmp_path / f"{placement}-{link}.toml"
            path.write_text(secure_text(src.read_text(), src, link))
            stack = load_stack(path)
            assert stack.security is not None and stack.security.dir == tmp_path / "keys"
            ends = stack.machines["vehicle-router"].listen
            assert ends == stack.machines["ground"].connect
            assert {e.split("/")[0] for e in ends} == expect
            assert len(ends) == len(plain.machines["vehicle-router"].listen) - (link == "tls")
            assert [re.sub(r"^\w+/", "", e) for e in ends] == [
                re.sub(r"^\w+/", "", e) for e in plain.machines["ground"].connect if link != "tls" or "udp/" not in e]
            assert stack.services == plain.services


def test_a_stack_without_a_link_is_not_secured_silently(tmp_path):
    from bench.two_hosts import BenchError, secure_text
    with pytest.raises(BenchError, match="no link endpoint"):
        secure_text("[stack]\nvehicle_id = 0\n", tmp_path / "x.toml")
