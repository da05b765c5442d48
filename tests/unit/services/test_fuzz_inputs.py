"""Fuzz every input of every service in-process (issue 22, item 9), bounded for CI: >= 10^5
invalid messages (schemas/fuzz.py: random bytes, valid MessagePack of the wrong types,
missing and extra fields, NaN/inf, wrong version, out of range, huge arrays, deep nesting).

Each service's module sets itself up for real (services.<name>.run up to its main loop, in
lockstep mode, with a Zenoh session on loopback), so the inboxes fed are the ones the service
reads, with its own keys, definitions and runtime. Garbage goes to the inbox callbacks and
to the lockstep clock/sync and param/set callbacks, with valid messages in between: every
bad one is counted in health, none reaches the service, none costs a valid one, and the
lockstep bookkeeping is untouched by garbage on the clock keys."""

from __future__ import annotations

import importlib
import math
import random
import signal
from types import SimpleNamespace

import pytest
import zenoh

import schemas
from schemas.fuzz import KINDS, Garbage, garbage, valid_doc
from services import runtime

SERVICES = ("attitude", "position", "motors", "planner", "vision", "mavlink", "sim")
GARBAGE_PER_INBOX = 3500     # x 25 inboxes, plus the clock/sync/param keys: > 10^5 in all
VALID_EVERY = 10             # one valid message after this many bad ones


class _Captured(Exception):
    pass


def _setup(name: str, monkeypatch) -> runtime.Runtime:
    """The service's Runtime as its module leaves it when it enters its main loop."""
    got = {}

    def run(self, step, triggers=(), wake_on=None, min_gap=0.0):
        got["rt"] = self
        raise _Captured

    monkeypatch.setattr(runtime.Runtime, "run", run)
    module = importlib.import_module(f"services.{name}")
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        if name == "sim":   # the simulator's own lockstep loop follows every participant
            rt = module.SimService(module.service_parser(name, "").parse_args(["--lockstep"])).rt
            for p in runtime.LOCKSTEP_PARTICIPANTS:
                if p in rt.stack.services:
                    rt.follow(p)
            return rt
        with pytest.raises(_Captured):
            module.main(["--lockstep"])
        return got["rt"]
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)


def _sample(payload: bytes):
    return SimpleNamespace(payload=zenoh.ZBytes(payload))


def _values(m: schemas.Message) -> dict:
    return {k: v for k, v in valid_doc(m).items() if k not in ("version", "header")}


def _rejected(rt) -> int:
    return sum(n for reason, n in rt.rejected.items() if reason in schemas.REASONS)


@pytest.fixture(scope="module")
def services():
    mp = pytest.MonkeyPatch()
    rts = {}
    try:
        for name in SERVICES:
            rts[name] = _setup(name, mp)
        yield rts
    finally:
        mp.undo()
        for rt in rts.values():
            rt.session.close()


def test_every_inbox_counts_garbage_and_keeps_every_valid_message(services):
    total = 0
    for name, rt in services.items():
        before = _rejected(rt)
        sent = 0
        assert rt.inboxes, name
        for i, box in enumerate(rt.inboxes):
            g = Garbage(box.message, seed=i)
            valid_seq, taken = 0, []
            for n in range(GARBAGE_PER_INBOX):
                _, payload = g.next()
                box._on_sample(_sample(payload))
                sent += 1
                if n % VALID_EVERY == VALID_EVERY - 1:   # a valid message among the garbage
                    box._on_sample(_sample(box.message.encode(1.0 + valid_seq, valid_seq, "fuzz-test",
                                                              _values(box.message))))
                    valid_seq += 1
                    taken += box.take()
            assert [m["header"]["seq"] for m in taken] == list(range(valid_seq)), (name, box.key)
            assert all(m["header"]["source"] == "fuzz-test" for m in taken)   # no garbage got through
            assert box.key not in rt.dropped, (name, box.key, rt.dropped)       # garbage cost no valid one
        assert _rejected(rt) - before == sent, (name, rt.rejected)
        total += sent
        # and the health message says so
        published = []
        rt._health.put = lambda values, *a, **k: published.append(values)
        rt.publish_health(force=True)
        assert sum(n for r, n in published[-1]["rejected"].items() if r in schemas.REASONS) == _rejected(rt)
        assert math.isfinite(published[-1]["rate_hz"])
    assert total >= 80_000


def test_garbage_on_clock_sync_and_param_keys_is_counted_and_changes_nothing(services):
    rt = services["attitude"]
    before = _rejected(rt)
    pools = {m.name: Garbage(m, seed=7, pool=16) for m in (schemas.SYNC_DONE, schemas.CLOCK, schemas.PARAM_SET)}
    sent = 0
    upstreams = {name: rt._make_sync_cb(name) for name in rt.progress.upstreams}
    done_before = {name: u.last_done for name, u in rt.progress.upstreams.items()}
    for _ in range(4000):
        for name, on_sync in upstreams.items():
            on_sync(_sample(pools["sync_done"].next()[1]))
            sent += 1
        rt._on_clock(_sample(pools["clock"].next()[1]))
        rt._on_param_set(_sample(pools["param_set"].next()[1]))
        sent += 2
    assert _rejected(rt) - before == sent
    # the lockstep bookkeeping did not move: no tick taken, no upstream's progress changed
    assert not rt.progress.clocks and rt.progress.sim_tick == -1
    assert {name: u.last_done for name, u in rt.progress.upstreams.items()} == done_before
    # and a valid sync after the garbage is taken as it comes
    name, on_sync = next(iter(upstreams.items()))
    on_sync(_sample(schemas.SYNC_DONE.encode(0.0, 0, name, {"tick": 5, "next_tick": 10, "triggers": [],
                                                              "period_ticks": 5})))
    assert rt.progress.upstreams[name].last_done == 5


def test_a_run_done_message_stands_for_its_sync_and_garbage_takes_no_tick(services):
    """schemas.RUN_DONE: the motors' PWM marks their run done at the sim (an input there), the
    attitude's state marks its run done at the sim too (a subscription of its own); garbage, or
    a valid message from another source, moves nothing; the PWM is still tagged with the
    motors' previous run, so the sim sees it only once that run counts as done."""
    rt = services["sim"]
    rt.subscribe_run_done()
    assert "attitude" in rt._done_light and "motors" in rt._done_boxes
    pwm_box = next(b for b in rt.inboxes if b.message is schemas.MOTOR_PWM)
    rt.progress.upstreams["motors"].last_done = 6
    pool = Garbage(schemas.MOTOR_PWM, seed=5, pool=16)
    before = _rejected(rt)
    for _ in range(200):
        pwm_box._on_sample(_sample(pool.next()[1]))
    pwm_box._on_sample(_sample(schemas.MOTOR_PWM.encode(9 / rt.tick_rate, 0, "intruder", _values(schemas.MOTOR_PWM))))
    assert rt.progress.upstreams["motors"].last_done == 6
    pwm_box._on_sample(_sample(schemas.MOTOR_PWM.encode(7 / rt.tick_rate, 1, "motors", _values(schemas.MOTOR_PWM))))
    assert rt.progress.upstreams["motors"].last_done == 7
    pwm_box.take()
    assert _rejected(rt) - before == 200
    assert pwm_box._items[-1][0] == 6   # tagged with the run before it
    # the attitude's state, on the sim's own subscription for it
    on_state = rt._done_light["attitude"]
    on_state(_sample(b"\xc1garbage"))
    assert rt.progress.upstreams["attitude"].last_done < 0
    on_state(_sample(schemas.ATTITUDE_STATE.encode(8 / rt.tick_rate, 0, "attitude", _values(schemas.ATTITUDE_STATE))))
    assert rt.progress.upstreams["attitude"].last_done == 8


def test_rejection_reasons_cover_every_kind(services):
    """Each kind of garbage is refused for the reason it deserves (where not flooded)."""
    rt = services["motors"]
    box = rt.inboxes[0]
    expected = {"random_bytes": {"malformed"}, "not_a_map": {"malformed"}, "huge_array": {"too_large"},
                "wrong_type": {"wrong_type"}, "missing_field": {"missing_field"},
                "extra_field": {"unknown_field"}, "non_finite": {"non_finite"},
                "wrong_version": {"wrong_version"}, "out_of_range": {"out_of_range"},
                "deep_nesting": {"malformed", "too_large", "wrong_type", "unknown_field", "missing_field"}}
    rng = random.Random(3)
    for kind, reasons in expected.items():
        for _ in range(5):
            box._window_start, box._window_rejects = -math.inf, 0
            before = dict(rt.rejected)
            box._on_sample(_sample(garbage(box.message, kind, rng)))
            box.take()
            diff = {r for r, n in rt.rejected.items() if n != before.get(r, 0)}
            assert len(diff) == 1 and diff <= reasons, (kind, diff)


def test_size_bounds_fit_the_largest_valid_messages():
    for m in schemas.ALL:
        doc = valid_doc(m, source="s" * schemas.core.STR_MAX_BYTES)
        for f in m.fields:   # fixed arrays at their length, strings at the bound, numbers as floats
            if f.kind == "str" and not f.choices:
                doc[f.name] = "é" * (schemas.core.STR_MAX_BYTES // 2)
        payload = m.encode(1e9, 2**62, doc["header"]["source"], _values_of(doc))
        assert len(payload) <= m.size_limit, m.name
        assert m.decode(payload)["header"]["seq"] == 2**62
    # the largest flip plan the definition allows fits its bound
    h, n = 1000, 17
    plan = _values(schemas.PLANNER_PLAN) | {"horizon": h, "state_dim": n, "states": [-1e6 + 0.1] * ((h + 1) * n),
                                           "controls_rad_s": [1e5 - 0.1] * (4 * h), "gains": [1e6 - 0.1] * (4 * h * n),
                                           "target_roll_rad": [-99.9] * h}
    assert len(schemas.PLANNER_PLAN.encode(1.0, 0, "planner", plan)) <= schemas.PLANNER_PLAN.size_limit
    with pytest.raises(schemas.SchemaError, match="too_large"):
        schemas.IMU.decode(b"\x84" + b"\x00" * schemas.IMU.size_limit)


def _values_of(doc: dict) -> dict:
    return {k: v for k, v in doc.items() if k not in ("version", "header")}


def test_accept_agrees_with_decode_on_every_kind_of_garbage():
    rng = random.Random(11)
    for m in schemas.ALL:
        assert m.fast_exact, m.name   # else accept falls back to decode: still exact, only slower
        for kind in KINDS:
            for _ in range(3 if kind in ("huge_array", "deep_nesting") else 20):
                payload = garbage(m, kind, rng)
                with pytest.raises(schemas.SchemaError):
                    m.decode(payload)
                assert m.accept(payload) is None, (m.name, kind)
        good = m.encode(2.0, 3, "x", _values(m))
        assert m.accept(good) == m.decode(good)


class _Counting:
    """The runtime as an Inbox sees it, counting with the real Runtime's methods."""
    reject, count_rejects = runtime.Runtime.reject, runtime.Runtime.count_rejects

    def __init__(self):
        import threading
        self.rejected, self.dropped, self._reported, self.detail = {}, {}, set(), ""
        self._count_lock, self._arrival, self._wake = threading.Lock(), threading.Event(), threading.Event()
        self._wake_t, self.lockstep, self.event_driven = 0.0, False, False

    def problem(self, text):
        self.detail = text

    def _sync_tick(self, upstream):
        return 0

    def count_dropped(self, key, n=1):
        self.dropped[key] = self.dropped.get(key, 0) + n


def test_a_flooded_key_counts_in_bulk_and_still_takes_valid_messages():
    rt = _Counting()
    box = runtime.Inbox(rt, schemas.PLANNER_PLAN, "zp/0/planner/plan", "planner", keep=64)
    bad = schemas.PLANNER_PLAN.encode(1.0, 0, "x", _values(schemas.PLANNER_PLAN))[:-1] + b"\xc1"  # last value broken
    for _ in range(runtime.FLOOD_REJECTS_PER_S + 30):
        box._on_sample(_sample(bad))
    box.take()
    assert rt.rejected == {"malformed": runtime.FLOOD_REJECTS_PER_S, "flood": 30}
    # large garbage past the byte budget is not even decoded; a valid plan among it still comes through
    huge = garbage(schemas.PLANNER_PLAN, "huge_array", random.Random(1))
    assert runtime.FLOOD_SMALL_BYTES < len(huge) < schemas.PLANNER_PLAN.size_limit
    box._on_sample(_sample(huge))
    box._on_sample(_sample(schemas.PLANNER_PLAN.encode(1.0, 0, "planner", _values(schemas.PLANNER_PLAN))))
    box._on_sample(_sample(huge))
    assert [m["header"]["source"] for m in box.take()] == ["planner"]
    assert rt.rejected["flood"] == 32 and box._window_bytes >= runtime.FLOOD_BYTES_PER_S


def test_garbage_never_wakes_or_counts_as_fresh():
    rt = _Counting()
    box = runtime.Inbox(rt, schemas.IMU, "zp/0/sim/imu", "sim", keep=4)
    box.wakes = True
    box._on_sample(_sample(b"\x00" * 10))                       # refused in the callback: no wake
    box._on_sample(_sample(b"\xde" + b"\x00" * 5000))           # over the size bound: not even copied
    assert not rt._wake.is_set() and not box._raw and rt.rejected == {"malformed": 1, "too_large": 1}
    box._on_sample(_sample(garbage(schemas.IMU, "wrong_type", random.Random(2))))   # map-shaped: queued
    assert rt._wake.is_set() and not box.fresh()                # ... but the woken loop does not run for it
    box._on_sample(_sample(schemas.IMU.encode(1.0, 0, "sim", _values(schemas.IMU))))
    assert box.fresh() and not box.fresh()
