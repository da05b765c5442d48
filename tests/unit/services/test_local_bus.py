"""The in-process bus of a one-process lockstep (services/local_bus.py): what the Runtime uses
of a Zenoh session, with Zenoh's matching and ordering."""

import threading

import zenoh

from services import local_bus


def collect(into):
    return lambda sample: into.append((str(sample.key_expr), sample.payload.to_bytes(), sample.kind))


def test_key_expressions_match_as_zenoh_matches_them():
    bus = local_bus.LocalBus()
    s = bus.open()
    everything, imu, star, clocks = [], [], [], []
    s.declare_subscriber("zp/0/**", zenoh.handlers.Callback(collect(everything), indirect=False))
    s.declare_subscriber("zp/0/sim/imu", collect(imu))
    s.declare_subscriber("zp/0/*/health", collect(star))
    s.declare_subscriber("zp/0/@lockstep/clock/*", collect(clocks))
    for key in ("zp/0/sim/imu", "zp/0/motors/health", "zp/0/@lockstep/clock/motors", "zp/1/sim/imu"):
        s.declare_publisher(key).put(key.encode())
    # `**` never matches a verbatim chunk (@lockstep): the recorder is not sent the handshake
    assert [k for k, _, _ in everything] == ["zp/0/sim/imu", "zp/0/motors/health"]
    assert [k for k, _, _ in imu] == ["zp/0/sim/imu"]
    assert [k for k, _, _ in star] == ["zp/0/motors/health"]
    assert [k for k, _, _ in clocks] == ["zp/0/@lockstep/clock/motors"]


def test_one_senders_messages_arrive_in_order_on_its_thread():
    bus = local_bus.LocalBus()
    got, threads = [], []
    bus.open().declare_subscriber("k", lambda s: (got.append(s.payload.to_bytes()), threads.append(threading.get_ident())))
    pub = bus.open().declare_publisher("k")
    for i in range(100):
        pub.put(b"%d" % i)
    assert got == [b"%d" % i for i in range(100)]
    assert set(threads) == {threading.get_ident()}   # delivered before put returns, as the lockstep tags need


def test_a_subscriber_declared_later_is_matched_and_one_undeclared_is_not():
    bus = local_bus.LocalBus()
    pub = bus.open().declare_publisher("a/b")
    pub.put(b"0")   # nobody listens yet
    first = []
    sub = bus.open().declare_subscriber("a/*", collect(first))
    pub.put(b"1")
    sub.undeclare()
    pub.put(b"2")
    assert [p for _, p, _ in first] == [b"1"]


def test_channels_queue_for_the_reader_to_pull():
    bus = local_bus.LocalBus()
    sub = bus.open().declare_subscriber("zp/0/**", zenoh.handlers.FifoChannel(16))
    pub = bus.open().declare_publisher("zp/0/x")
    assert sub.handler.try_recv() is None
    pub.put(b"\x81\xa1a\x01")
    sample = sub.handler.try_recv()
    assert str(sample.key_expr) == "zp/0/x" and sample.payload.to_bytes() == b"\x81\xa1a\x01"
    assert len(sample.payload) == 4 and sample.payload[:1] == b"\x81"   # what screen() looks at
    assert sub.handler.try_recv() is None


def test_liveliness_tokens_come_and_go_with_their_session():
    bus = local_bus.LocalBus()
    watcher, events = bus.open(), []
    watcher.liveliness().declare_subscriber("zp/0/alive/*", collect(events))
    service = bus.open()
    token = service.liveliness().declare_token("zp/0/alive/attitude")
    assert bus.tokens() == ["zp/0/alive/attitude"]
    service.liveliness().declare_token("zp/0/alive/other")
    token.undeclare()
    service.close()   # its remaining token goes with it: the lockstep clock drops it
    assert [(k, kind) for k, _, kind in events] == [
        ("zp/0/alive/attitude", zenoh.SampleKind.PUT), ("zp/0/alive/other", zenoh.SampleKind.PUT),
        ("zp/0/alive/attitude", zenoh.SampleKind.DELETE), ("zp/0/alive/other", zenoh.SampleKind.DELETE)]
    assert bus.tokens() == []


def test_a_closed_session_neither_sends_nor_receives():
    bus = local_bus.LocalBus()
    a, b = bus.open(), bus.open()
    got = []
    b.declare_subscriber("k", collect(got))
    pub = a.declare_publisher("k")
    b.close()
    pub.put(b"x")
    a.close()
    pub.put(b"y")
    assert got == []


def test_a_failing_subscriber_is_reported_and_the_others_still_get_the_message(capsys):
    bus = local_bus.LocalBus()
    got = []

    def broken(sample):
        raise ValueError("bug")
    bus.open().declare_subscriber("k", broken)
    bus.open().declare_subscriber("k", collect(got))
    bus.open().declare_publisher("k").put(b"x")
    assert len(got) == 1
    assert "failed on k: ValueError: bug" in capsys.readouterr().err


def test_output_is_the_receivers_during_its_callback_and_the_runners_inline():
    bus = local_bus.LocalBus()
    owners = []

    def opened_by(name):
        box = {}
        t = threading.Thread(target=lambda: box.setdefault("s", bus.open()), name=name)
        t.start()
        t.join()
        return box["s"]
    opened_by("attitude").declare_subscriber("k", lambda s: owners.append(local_bus.delivering_to()))
    pub = opened_by("sim").declare_publisher("k")
    with local_bus.running_as("motors"):
        pub.put(b"x")
        owners.append(local_bus.delivering_to())
    owners.append(local_bus.delivering_to())
    assert owners == ["attitude", "motors", None]


def test_stop_requests_reach_the_handler_the_service_set_last():
    bus = local_bus.LocalBus()
    calls = []

    def service():
        bus.on_stop(lambda: calls.append("runtime"))
        bus.on_stop(lambda: calls.append("recorder"))   # as signal.signal: the last one set
    t = threading.Thread(target=service, name="recorder")
    t.start()
    t.join()
    assert bus.request_stop("recorder") and calls == ["recorder"]
    assert not bus.request_stop("never-started")


def test_frames_carry_keys_and_payloads_through_a_pipe_and_a_cut_one_is_dropped():
    import io
    messages = [("zp/0/sim/imu", b"\x81\xa1a\x01"), ("zp/0/é", b""), ("k", bytes(range(256)) * 300)]
    data = local_bus.frames(messages)
    assert list(local_bus.read_frames(io.BytesIO(data))) == messages
    assert list(local_bus.read_frames(io.BytesIO(data[:-1]))) == messages[:2]   # a writer killed mid-frame
    assert list(local_bus.read_frames(io.BytesIO(b""))) == []


def test_a_subscriber_added_while_a_publisher_matches_is_never_missed():
    """A subscriber that comes right after a publisher's match (another thread: the simulator
    subscribing to a participant's "ready" as the participant says it) is matched on the next put."""
    bus = local_bus.LocalBus()
    got = []
    pub = bus.open().declare_publisher("zp/0/@lockstep/sync/vision")
    match = bus.matching_versioned

    def match_then_subscribe(key):
        found = match(key)
        bus.matching_versioned = match   # once
        bus.open().declare_subscriber("zp/0/@lockstep/sync/*", collect(got))   # lands just after the match
        return found
    bus.matching_versioned = match_then_subscribe
    pub.put(b"ready")     # matched before the subscriber came: not delivered
    pub.put(b"ready")     # said again: this one must arrive
    assert [p for _, p, _ in got] == [b"ready"]
