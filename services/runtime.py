"""The runtime every zenpilot service shares.

It owns the I/O so that service modules hold only their algorithm's wiring:
the Zenoh session from the standard flags, the clock, the rate loop or the
lockstep handshake, strict decoding with per-reason reject counters, the
liveliness token, the 1 Hz health message and clean shutdown on SIGINT/SIGTERM.

Lockstep protocol (deterministic; like PX4 SITL lockstep):

* At tick k the simulator publishes its sensor messages, then one
  `@lockstep/clock/<service>` to each service due at k: rate services when k is the
  `next_tick` they announced, event services (e.g. vision) when one of their
  trigger topics was published. The clock carries, for every service, the
  last tick it finished before k.
* A service waits until it has received each upstream's `@lockstep/sync/<upstream>`
  for that tick, then runs once. The run sees exactly: simulator messages
  published up to k, and upstream messages produced by upstream runs before
  k (one tick of transport delay per hop, as on a real bus). Messages are
  tagged on arrival with the last sync tick seen from their producer; Zenoh
  delivers one session's messages over one link in order (callbacks run on
  the receiving thread), so the tag says which run produced them.
* After its outputs, the service publishes `@lockstep/sync/<name>` with the tick done
  and its next tick; the simulator advances once everyone due is done.
* Both keys sit under a verbatim chunk (`@lockstep`), which `zp/<vehicle>/**` never
  matches: the recorder and the tools that take every key are not sent the handshake
  (~1500 messages per simulated second that carry no flight data).
"""

from __future__ import annotations

import abc
import argparse
import gc
import json
import math
import os
import signal
import sys
import threading
import time
from collections import deque
from time import time as _time
from typing import Any, Callable

import zenoh

import schemas
from services import lockstep, security
from services.params import Param
from services.stack import (LOCKSTEP_PARTICIPANTS, SERVICES_LISTEN, Stack, StackError, check_compatible, check_param,
                            load_stack, parse_overrides, resolve_params)

HEALTH_PERIOD_S = 1.0
BEAT_PERIOD_S = 0.1    # the main loop's beat (real time): a hang is seen within 0.4 s (deploy/supervisor.py)
LATE_S = 0.005        # a wake-up later than this past its deadline counts as late
RAW_QUEUE_MAX = 256   # payloads per key waiting to be read; beyond, the oldest is lost (counted)
# Rejecting must stay cheap under a flood of garbage (issue 22): beyond this many diagnosed
# rejects on one key in a second, its bad messages are counted as "flood" without a reason
# (schemas.Message.accept: ~5 us, against up to ~50 us to find the reason).
FLOOD_REJECTS_PER_S = 50
# Large garbage costs by its size (unpacking 1 MB takes ~25 ms; only the plan, mission, camera
# and bookkeeping keys allow payloads over FLOOD_SMALL_BYTES): once a key's rejected payloads
# add up to FLOOD_BYTES_PER_S in a second, its large payloads are dropped undecoded for the rest
# of that second, counted as "flood" (a valid plan among them too: a flood costs the loops little).
FLOOD_SMALL_BYTES = 4096
FLOOD_BYTES_PER_S = 256 * 1024
# Every message is one MessagePack map: its first byte is a fixmap (0x80-0x8f), map16 or map32.
MAP_FIRST_BYTES = frozenset([bytes([b]) for b in range(0x80, 0x90)] + [b"\xde", b"\xdf"])


def screen(message: schemas.Message, payload: zenoh.ZBytes) -> tuple[bytes | None, str]:
    """The cheap first look at a payload, before any decoding: (bytes, "") or (None, the
    reason to reject it): over the message's size bound (not even copied), or not a map."""
    if len(payload) > message.size_limit:
        return None, "too_large"
    data = payload.to_bytes()
    if not data or data[0] & 0xF0 != 0x80 and data[0] | 1 != 0xDF:   # MAP_FIRST_BYTES, by the byte's value
        return None, "malformed"
    return data, ""
# A loop woken by its input (run(..., wake_on=inbox)) runs at the input's arrival, at most
# once per `min_gap` periods; without input it runs on its own timer this much past a period.
WAKE_TIMER_MARGIN = 0.25


# A one-process lockstep (deploy/one_process.py) puts every service of the process on this
# in-process bus (services/local_bus.py) instead of Zenoh; None: each service opens Zenoh.
LOCAL_BUS = None


def on_stop_signals(handler: Callable[[], None]) -> None:
    """Call `handler()` once on the first SIGINT/SIGTERM, from a thread of its own: a signal
    handler runs inside whatever the main thread was doing, maybe holding the very lock the
    handler needs (an Event's, mid-`wait`): set from the handler itself, that deadlocked a
    service for good when two signals came close together."""
    asked = []

    def on_signal(*_):
        if not asked:
            asked.append(True)
            threading.Thread(target=handler, name="stop-request", daemon=True).start()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)


def on_stop_request(handler: Callable[[], None]) -> None:
    """Call `handler()` when this service is asked to stop: its SIGINT/SIGTERM, or the host's
    request in a one-process run (signals belong to the process, not to a thread)."""
    if LOCAL_BUS is not None:
        LOCAL_BUS.on_stop(handler)
    else:
        on_stop_signals(handler)


# ---------------------------------------------------------------- CLI and Zenoh
def add_zenoh_args(parser: argparse.ArgumentParser) -> None:
    """The standard Zenoh flags of the zenoh-python examples."""
    g = parser.add_argument_group("zenoh")
    g.add_argument("-m", "--mode", choices=["peer", "client", "router"], default="peer",
                   help="Zenoh session mode (default: peer, connected to the router)")
    g.add_argument("-e", "--connect", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("-l", "--listen", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on (repeatable)")
    g.add_argument("-c", "--config", metavar="FILE", help="Zenoh JSON5 configuration file")
    g.add_argument("--multicast-scouting", action=argparse.BooleanOptionalAction, default=False,
                   help="find peers and routers by UDP multicast (default: off, the stack names its routers)")
    g.add_argument("--cfg", action="append", default=[], metavar="KEY:VALUE",
                   help="Zenoh config entry, VALUE in JSON5, e.g. --cfg 'transport/shared_memory/enabled:false'")


def zenoh_config(args: argparse.Namespace, stack: Stack | None = None, machine: str | None = None) -> zenoh.Config:
    """The session's configuration: the flags, then the stack file's word on where the
    service listens (its machine's services_listen: loopback unless the stack says otherwise;
    Zenoh's own default would be every interface) and, with a [security] table, the machine's
    login and certificates (services/security.py)."""
    conf = zenoh.Config.from_file(args.config) if args.config else zenoh.Config()
    conf.insert_json5("mode", json.dumps(args.mode))
    if args.connect:
        conf.insert_json5("connect/endpoints", json.dumps(args.connect))
    m = stack.machines.get(machine) if stack and machine else None
    listen = args.listen or (list(m.services_listen) if m else list(SERVICES_LISTEN))
    if args.config and not args.listen:   # a configuration file that names its listeners has the word
        given = json.loads(str(conf))["listen"]["endpoints"]
        if given != json.loads(str(zenoh.Config()))["listen"]["endpoints"]:
            listen = given
    if args.mode != "client":   # a client listens nowhere
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if m is not None and m.bulk_max_hz and not getattr(args, "lockstep", False):   # a wall-clock cap: real time only
        conf.insert_json5("downsampling", json.dumps(bulk_downsampling(stack.vehicle_id, m.bulk_max_hz)))
    if stack is not None and stack.security is not None:
        if m is None:
            raise StackError(f"{stack.path}: [security] is set but this session's machine is unknown")
        security.apply_session(conf, stack.security, m.name)
    conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(args.multicast_scouting)))
    # No Zenoh shared memory unless asked for (--cfg): the first message over its size threshold
    # (a flip's plan, 26 KB; camera frames at altitude) creates the pool, 16 MB and three threads,
    # ~11 ms inside that put with the session's receiving thread blocked (measured in a real-time
    # flip); over the TCP link a plan's put takes 0.1-0.3 ms.
    conf.insert_json5("transport/shared_memory/enabled", "false")
    bound_drop_wait(conf)   # a service's put of a droppable image never holds its loop for 50 ms
    for item in args.cfg:
        key, _, value = item.partition(":")
        if not value:
            raise StackError(f"--cfg {item!r}: expected KEY:VALUE")
        conf.insert_json5(key, value)
    return conf


def bound_drop_wait(conf: zenoh.Config) -> None:
    """A droppable message (real time's streams and images) that finds its link's queue full waits
    Zenoh's wait_before_drop (1 ms) and is dropped, a fragmented one too. Zenoh's default gives a
    message it has begun to fragment up to 50 ms more for its other fragments, and the thread that
    pushes it waits: in a router, the thread that routes every other link's messages. A 1 MB image
    on a saturated link held the control keys crossing the vehicle's router for ~50 ms
    (docs/reliability.md, "A link that honours DSCP"). The cost: an image larger than the link's
    queue (a router's bulk queue holds about 1 MB, deploy/router.py) crosses a saturated link only
    when it has room for it whole. Lockstep blocks, never drops: untouched."""
    conf.insert_json5("transport/link/tx/queue/congestion_control/drop/max_wait_before_drop_fragments", "0")


def bulk_downsampling(vehicle_id: int, max_hz: float) -> list[dict]:
    """Zenoh's downsampling rules that forward each bulk key (schemas: priority "bulk") at most
    `max_hz` times a second (a machine's `bulk_max_hz`): applied by its router and by its
    services' own sessions, a flooding camera is cut where it publishes, not on the link."""
    keys = [m.key(vehicle_id, "*") for m in schemas.ALL if m.priority == "bulk"]
    return [{"id": "bulk", "messages": ["put"], "flows": ["egress"],
             "rules": [{"key_expr": k, "freq": max_hz} for k in keys]}]


def service_parser(name: str, description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=f"zenpilot-{name}", description=description)
    p.add_argument("--stack", help="stack file (default: deploy/stacks/default.toml)")
    p.add_argument("--vehicle", help="airframe name or .toml file (default: the stack's)")
    p.add_argument("--lockstep", action="store_true", help="run on the simulator's clock ticks")
    p.add_argument("--seed", type=int, default=0, help="random seed (simulator)")
    p.add_argument("--param", action="append", metavar="KEY=VALUE",
                   help="override a parameter of this service (repeatable)")
    p.add_argument("--restarted", action="store_true",
                   help="started again mid-flight by the supervisor: take control only once settled")
    add_zenoh_args(p)
    return p


def fail(name: str, message: str) -> None:
    """The user interface for a fatal problem: one clear line, exit status 2."""
    print(f"zenpilot-{name}: error: {message}", file=sys.stderr, flush=True)
    raise SystemExit(2)


# ---------------------------------------------------------------- inputs
class Inbox:
    """Messages of one key, decoded strictly on the service's thread, tagged for lockstep visibility.

    The Zenoh callback only queues the payload with its lockstep tag; the reader decodes
    what arrived when it asks (`latest`, `take`), so every message is still validated and
    counted, and no decoding holds up Zenoh's receiving thread.

    One thread reads an inbox at a time (the service's loop, or in one process the simulator's
    thread running it inline, in turn): the reader's state takes no lock, and the callback
    shares only the raw deque with it (append and popleft are atomic). Each message's path is
    kept to few Python steps (docs/performance.md, "One hop"): the callback and the reader run
    cold, after a wait, where every call and lookup costs several times its warm price."""

    def __init__(self, runtime: "Runtime", message: schemas.Message, key: str, upstream: str, keep: int):
        self.runtime = runtime
        self.message = message
        self.key = key
        self.upstream = upstream  # "sim" or the producing service
        # not on the lockstep clock (e.g. the MAVLink bridge): visible from the
        # next tick after arrival, like a simulator message
        self.clocked = upstream == "sim" or upstream not in LOCKSTEP_PARTICIPANTS
        self.keep = keep
        # appended on Zenoh's thread, drained by the reader: (tag, payload) in lockstep, the payload
        # alone in real time (no tag to keep: a tuple less per message)
        self._raw: deque = deque()
        self._items: deque[tuple[int, int, dict]] = deque(maxlen=keep)  # (tag, arrival number, message)
        self._taken = -1
        self.limit = math.inf  # visibility: tag < limit (set per run in lockstep)
        self.arrived = 0
        self._next_seq: dict[str, int] = {}   # per sender: the sequence number expected next
        self.wakes = False   # set by Runtime.run(wake_on=...)
        self.marks_done = False  # lockstep: this key is the upstream's RUN_DONE message (Runtime.inbox)
        self._takes = False  # the reader takes every message (take), not only the newest
        self._superseded = False  # unread messages went to make room: no loss for a reader of the newest
        # the compiled codec itself (Message.decode only forwards to it: one call less per message)
        self._decode, self._accept = message._decode, message._accept
        self.max_bytes = message.size_limit
        self._tagged = runtime.lockstep   # lockstep tags each arrival (fixed with the runtime's mode)
        self.valid = 0          # messages accepted so far
        self._valid_seen = 0    # ... when fresh() last looked
        # this second's rejects: the window opens at the first reject after the last one closed
        self._window_start, self._window_rejects, self._window_bytes = -math.inf, 0, 0
        self._channel = None    # polled (real time, not the loop's wake): Zenoh queues, the reader pulls

    def _poll(self) -> None:
        """Pull what Zenoh queued for a polled inbox: the same first look as `_on_sample`, on
        the reader's thread. Zenoh's receiving thread then never takes the GIL for this key."""
        channel, raw, rt, tagged = self._channel, self._raw, self.runtime, self._tagged
        pulled = 0
        while (sample := channel.try_recv()) is not None:
            pulled += 1
            data, reason = screen(self.message, sample.payload)
            if data is None:
                rt.count_rejects(self.key, reason)
            else:
                raw.append((0, data) if tagged else data)   # (polled: real time, untagged)
        if pulled >= RAW_QUEUE_MAX:   # the ring may have let the oldest go: as a full raw queue does
            if self._takes:
                rt.count_dropped(self.key)
            else:
                self._superseded = True
        while len(raw) > RAW_QUEUE_MAX:
            raw.popleft()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        # Garbage is refused here, before it is copied, queued or wakes the reader: over the
        # definition's size bound (a huge array costs ~20 ms to unpack), or not a map at all.
        payload = sample.payload
        if len(payload) > self.max_bytes:
            self.runtime.count_rejects(self.key, "too_large")
            return
        data = payload.to_bytes()
        # MAP_FIRST_BYTES, tested on the first byte's value (cheaper than a slice and a set lookup)
        if not data or data[0] & 0xF0 != 0x80 and data[0] | 1 != 0xDF:
            self.runtime.count_rejects(self.key, "malformed")
            return
        raw = self._raw
        if self._tagged:
            rt = self.runtime
            if self.marks_done:   # tagged before it counts as the upstream's sync: its run's own outputs precede it
                tag = rt._sync_tick(self.upstream)
                msg = self._accept(data)   # garbage: None, undiagnosed (the reader diagnoses it once)
                if msg is None:
                    raw.append((tag, data))   # counted by the reader; no tick taken from it
                else:   # queued before it says "done": a reader woken by that finds it
                    raw.append((tag, msg))
                    rt._run_done(self.upstream, msg)
            else:
                raw.append((rt._sync_tick(self.upstream), data))
        else:
            raw.append(data)
        if len(raw) > RAW_QUEUE_MAX:   # not read for a while: the oldest goes
            raw.popleft()
            if self._takes:   # a reader of every message lost one; a reader of the newest did not
                self.runtime.count_dropped(self.key)
            else:
                self._superseded = True
        if self.wakes:   # the service's loop runs on this input's arrival (real time)
            rt = self.runtime
            rt._wake_t = _time()
            rt._wake.set()
        elif self.runtime.event_driven:
            self.runtime._arrival.set()  # wakes an event-driven service in real time

    def _drain(self) -> None:
        """Decode what is queued, oldest first, into the items (the reader's thread)."""
        raw, items, next_seq = self._raw, self._items, self._next_seq
        if self._superseded:
            self._superseded = False
            next_seq.clear()
        # A flooded key (FLOOD_REJECTS_PER_S rejects, or FLOOD_BYTES_PER_S of rejected payload, in
        # this second of wall time): bad messages are counted in bulk ("flood"), undiagnosed. The
        # clock is read only while a window holds rejects: a clean stream never reads it.
        flooded = False
        if self._window_rejects or self._window_bytes:
            if time.monotonic() - self._window_start >= 1.0:
                self._window_rejects, self._window_bytes = 0, 0
            else:
                flooded = self._window_rejects >= FLOOD_REJECTS_PER_S or self._window_bytes >= FLOOD_BYTES_PER_S
        # (raw.popleft() and items.append() called as methods: a bound method kept in a local is
        # an object made per drain, and a drain most often finds one message)
        decode, arrived, valid, tagged, tag = self._decode, self.arrived, self.valid, self._tagged, 0
        try:
            while raw:
                if tagged:
                    tag, payload = raw.popleft()
                else:
                    payload = raw.popleft()
                arrived += 1
                if type(payload) is dict:   # decoded on arrival (a RUN_DONE message in lockstep)
                    msg = payload
                elif not flooded:
                    try:
                        msg = decode(payload)
                    except schemas.SchemaError as exc:
                        flooded = self._rejected(payload, exc)
                        continue
                else:
                    if len(payload) > FLOOD_SMALL_BYTES and self._window_bytes >= FLOOD_BYTES_PER_S:
                        self.runtime.count_rejects(self.key, "flood")
                        continue
                    msg = self._accept(payload)
                    if msg is None:
                        self._window_bytes += len(payload)
                        self.runtime.count_rejects(self.key, "flood")
                        continue
                valid += 1
                header = msg["header"]
                seq, source = header["seq"], header["source"]
                expected = next_seq.get(source)
                if seq == expected or expected is None:   # in order, or the first from this sender
                    next_seq[source] = seq + 1
                else:
                    if seq > expected:
                        self.runtime.count_dropped(self.key, seq - expected)
                    if seq >= expected - 1 or seq < expected - 1000:  # a repeat keeps its seq; a restart starts over
                        next_seq[source] = seq + 1
                items.append((tag, arrived, msg))
        finally:
            self.arrived, self.valid = arrived, valid

    def _rejected(self, payload: bytes, exc: schemas.SchemaError) -> bool:
        """A payload the decoder refused: counted with its reason and in this second's flood
        window (opened now if none is open). Returns whether the key is now flooded."""
        if not (self._window_rejects or self._window_bytes):
            self._window_start = time.monotonic()
        self._window_rejects += 1
        self._window_bytes += len(payload)
        self.runtime.reject(self.key, exc)
        return self._window_rejects >= FLOOD_REJECTS_PER_S or self._window_bytes >= FLOOD_BYTES_PER_S

    def fresh(self) -> bool:
        """Whether a valid message came since the last call (decodes what is queued): a loop
        woken by this input runs only for a real message, never for garbage."""
        if self._channel is not None:
            self._poll()
        if self._raw:
            self._drain()
        new = self.valid != self._valid_seen
        self._valid_seen = self.valid
        return new

    def latest(self) -> dict | None:
        """The newest visible message, or None."""
        if self._channel is not None:
            self._poll()
        if self._raw:
            self._drain()
        items = self._items
        if items:
            tag, _, msg = items[-1]
            if tag < self.limit:   # the newest is visible: always, in real time
                return msg
            limit = self.limit
            for tag, _, msg in reversed(items):
                if tag < limit:
                    return msg
        return None

    def idle(self) -> None:
        """The reader stops reading for now (e.g. a failsafe's input between uses): what is
        queued is let go, and messages that do not fit while nobody reads are not counted lost."""
        if self._channel is not None:
            while self._channel.try_recv() is not None:
                pass
        self._raw.clear()
        self._superseded = True
        self._takes = False

    def take(self) -> list[dict]:
        """Visible messages not taken before, oldest first."""
        self._takes = True
        if self._channel is not None:
            self._poll()
        if self._raw:
            self._drain()
        limit, taken = self.limit, self._taken
        # arrival numbers rise along the deque: the ones not taken are a suffix, read from the
        # newest back (a keep=32 inbox read each run scanned all 32 for its one or two new)
        out = []
        for tag, n, m in reversed(self._items):
            if n <= taken:
                break
            if tag < limit:
                out.append(m)
                if n > self._taken:
                    self._taken = n
        out.reverse()
        return out


ZENOH_PRIORITIES = {"control": zenoh.Priority.REAL_TIME, "bulk": zenoh.Priority.BACKGROUND}


def zenoh_priority(name: str) -> zenoh.Priority:
    """Zenoh's priority for a key's priority class (schemas.PRIORITIES)."""
    try:
        return ZENOH_PRIORITIES[name]
    except KeyError:
        raise ValueError(f"priority {name!r}: expected one of {', '.join(ZENOH_PRIORITIES)}") from None


def publisher_reliability(message: schemas.Message, lockstep: bool) -> zenoh.Reliability:
    """Reliable in lockstep (a lost message would stall the handshake) and for what the schema
    sends reliably (Message.sent_reliably); best effort for the streams."""
    if lockstep or message.sent_reliably:
        return zenoh.Reliability.RELIABLE
    return zenoh.Reliability.BEST_EFFORT


class Publisher:
    def __init__(self, runtime: "Runtime", message: schemas.Message, key: str):
        self.runtime = runtime
        self.message = message
        self.key = key
        self.seq = 0
        # Express: sent at once, not held for batching (a control hop must not wait for
        # the next batch). Lockstep must not lose a message (the handshake would stall),
        # so it blocks under congestion and is reliable; real time drops stale data instead,
        # and sends a stream best effort: across a lossy link its samples then take an
        # unreliable link where the stack file declares one (`?rel=0`, UDP), so that no fresh
        # sample waits behind a lost one's retransmission (publisher_reliability). The key's
        # priority (schemas.PRIORITIES) gives bulk messages a queue of their own on each link.
        congestion = zenoh.CongestionControl.BLOCK if runtime.lockstep else zenoh.CongestionControl.DROP
        self._pub = runtime.session.declare_publisher(
            key, express=True, congestion_control=congestion, priority=zenoh_priority(message.priority),
            reliability=publisher_reliability(message, runtime.lockstep))
        self._put = self._pub.put
        self._encode = message._encode   # the compiled codec (Message.encode only forwards to it)
        self._source = runtime.instance
        self.tracked = runtime.lockstep   # a lockstep run's last put is noted (Runtime._run_lockstep)
        self.last_t = -1.0

    def put(self, values: dict[str, Any], t_s: float | None = None, repeat: bool = False) -> None:
        """Publish; invalid values (NaN, out of range) are reported, never sent.
        `repeat`: send the same message again (same seq) until the next one."""
        if t_s is None:   # Runtime.now, inlined (a call less per message); mavlink's runtime leaves lockstep
            rt = self.runtime
            t = rt._t if rt.lockstep else _time()
        else:
            t = t_s
        try:
            payload = self._encode(t, self.seq, self._source, values)
        except schemas.SchemaError as exc:
            self.runtime.problem(f"not publishing {self.key}: {exc}")
            return
        self._put(payload)
        if self.tracked:
            self.runtime._last_put = self
            self.last_t = t
        if not repeat:
            self.seq += 1


# ---------------------------------------------------------------- runtime
class ParamAccess(abc.ABC):
    """Reading a service's resolved parameters, with errors that say where they were set: the
    Runtime's in flight, a fake's in the services' unit tests."""

    params: dict[str, Any]
    declared: dict[str, Any]   # name -> services.params.Param (or a bare default): what params were checked against
    _param_callbacks: dict[str, list[Callable[[Any], None]]]

    @abc.abstractmethod
    def where(self) -> str:
        """Where the parameters were set (file and section), for error messages."""

    def table(self, key: str, from_dict: Callable[[dict], Any]) -> Any:
        """A nested parameter table, validated by its owner's from_dict."""
        try:
            return from_dict(self.params[key])
        except (ValueError, TypeError) as exc:
            raise ValueError(f"{self.where()} {key}: {exc}") from None

    def live_array(self, key: str):
        """A numpy copy of a numeric parameter that param/set updates in place: pass it
        to the law each step and a new gain applies from the next step."""
        import numpy as np
        arr = np.array(self.params[key], dtype=float)
        self.on_param(key, lambda v: arr.__setitem__(slice(None), v))
        return arr

    @abc.abstractmethod
    def on_param(self, key: str, callback: Callable[[Any], None]) -> None:
        """Call `callback(new_value)` when the parameter `key` changes in flight."""

    def set_param(self, key: str, value: list[float], source: str = "test") -> Any:
        """A param/set of `key` to `value` (numbers, as the message carries them: one for a
        scalar), checked against its declaration as start-up checks the stack file's
        (services/stack.py check_param: type, length, bounds, choices), then applied and its
        callbacks called. Refused with StackError naming the key and the bound: the old value stays."""
        d = self.declared.get(key)
        default = d.default if isinstance(d, Param) else d
        given: Any = list(value)
        if isinstance(default, (int, float)) and not isinstance(default, bool) and len(given) == 1:
            given = given[0]   # a scalar parameter: its one number, an int where it is declared one
            if isinstance(default, int) and float(given).is_integer():
                given = int(given)
        new = check_param(self.declared, key, given, f"param/set from {source}: {self.name}")
        self.params[key] = new
        for cb in self._param_callbacks.get(key, []):
            cb(new)
        return new


class Runtime(ParamAccess):
    def __init__(self, name: str, args: argparse.Namespace, param_defaults: dict[str, Any] | None = None,
                 announce: bool = True):
        self.name = name
        # the process's own name on the bus (token, health, beat, messages' source): the service's,
        # or the hot-standby driver's "motors.b" (services/standby.py); parameters stay the service's
        self.instance = getattr(args, "instance", None) or name
        self.args = args
        try:
            self.stack: Stack = load_stack(args.stack)
            spec = self.stack.services.get(name)
            given = dict(spec.params) if spec else {}
            overrides = parse_overrides(getattr(args, "param", None))
            given.update(overrides)
            self.declared = param_defaults or {}
            self.params = resolve_params(self.declared, given, f"{self.stack.path}: [services.{name}.params]")
            if overrides:   # this service's --param may clash with another service's settings in the file
                check_compatible(f"{self.stack.path} with --param",
                                 {**{n: s.params for n, s in self.stack.services.items()}, name: given})
            self.conf = zenoh_config(args, self.stack, spec.machine if spec else next(iter(self.stack.machines)))
        except (StackError, zenoh.ZError, ValueError) as exc:
            fail(name, str(exc))
        self.spec = spec
        self.vehicle_id = self.stack.vehicle_id
        self.vehicle_name = args.vehicle or self.stack.vehicle
        self.lockstep = bool(args.lockstep)
        self.restarted = bool(getattr(args, "restarted", False))   # the supervisor's restart, mid-flight
        self.real_time_scheduling = not self.lockstep   # (the recorder keeps wall time in lockstep, not the priority)
        self.rate_hz = spec.rate_hz if spec else 0.0
        self.tick_rate = self.stack.tick_rate_hz
        self.stop_event = threading.Event()
        self.rejected: dict[str, int] = {}
        self._count_lock = threading.Lock()
        self._reported: set[tuple[str, str]] = set()
        self.detail = ""
        self.overruns = 0
        self.late = 0
        self.cycles = 0
        self.step_s = 0.0
        self.wait_s = 0.0
        self.cpu_inline_s = 0.0   # one process: CPU of this service's runs on another thread (less, of others' on this)
        self.dropped: dict[str, int] = {}
        self._lateness: list[float] = []   # wake-up lateness (s) since the last health message
        self.late_max_ms = 0.0             # the worst of the run, for the log line at exit
        self.scheduling = "normal"
        self.state = "starting"
        self._run_times: deque[float] = deque()
        self._periods: deque[float] = deque(maxlen=2000)
        self._t = 0.0
        self.progress = lockstep.Progress(self.stop_event, self._report_dropped)   # lockstep: the others
        self._arrival = threading.Event()
        self._wake = threading.Event()
        self._wake_t = 0.0
        self.event_driven = False   # real time, no rate: the loop runs on any input's arrival
        self.inboxes: list[Inbox] = []
        self._param_callbacks: dict[str, list[Callable[[Any], None]]] = {}
        self.local_bus = LOCAL_BUS
        try:
            self.session = zenoh.open(self.conf) if LOCAL_BUS is None else LOCAL_BUS.open(self.conf)
        except zenoh.ZError as exc:
            fail(name, f"cannot open the Zenoh session: {exc}")
        # the liveliness token says "up"; a service whose inputs must be in place first (the
        # recorder's subscription) announces itself later (announce_alive)
        self._token = self.session.liveliness().declare_token(self.key(f"alive/{self.instance}")) if announce else None
        self._last_put: Publisher | None = None   # lockstep: the last tracked put of the run
        self._done_light: dict[str, Callable] = {}   # upstream -> callback of its RUN_DONE key's own subscription
        self._done_boxes: set[str] = set()        # ... or an inbox
        self._health = Publisher(self, schemas.HEALTH, schemas.HEALTH.key(self.vehicle_id, self.instance))
        self._health.tracked = False   # nobody on the clock reads health: it may follow a run's last message
        self._next_health = 0.0
        # real time: a beat every BEAT_PERIOD_S from the main loop, for the supervisor's hang watch
        self._beat = None if self.lockstep or LOCAL_BUS is not None else \
            Publisher(self, schemas.BEAT, schemas.BEAT.key(self.vehicle_id, self.instance))
        self._next_beat = 0.0
        self.subscribe(schemas.PARAM_SET.key(self.vehicle_id), self._on_param_set)
        on_stop_request(self.stop_event.set)

    # -- helpers ---------------------------------------------------------
    def where(self) -> str:
        return f"{self.stack.path}: [services.{self.name}.params]"

    def key(self, topic: str) -> str:
        return f"zp/{self.vehicle_id}/{topic}"

    def announce_alive(self) -> None:
        if self._token is None:
            self._token = self.session.liveliness().declare_token(self.key(f"alive/{self.instance}"))

    def now(self) -> float:
        return self._t if self.lockstep else time.time()

    def problem(self, text: str) -> None:
        if text != self.detail:
            print(f"zenpilot-{self.instance}: {text}", file=sys.stderr, flush=True)
        self.detail = text

    def count_dropped(self, key: str, n: int = 1) -> None:
        self.dropped[key] = self.dropped.get(key, 0) + n

    def reject(self, key: str, exc: schemas.SchemaError) -> None:
        with self._count_lock:
            self.rejected[exc.reason] = self.rejected.get(exc.reason, 0) + 1
        if (key, exc.reason) not in self._reported:  # log once per kind
            self._reported.add((key, exc.reason))
            self.problem(f"dropped a message on {key}: {exc}")

    def count_rejects(self, key: str, reason: str, n: int = 1) -> None:
        """Count rejected messages (from Zenoh's threads and the service's: under a lock, so
        that none is lost); the first of each kind per key is reported."""
        with self._count_lock:
            self.rejected[reason] = self.rejected.get(reason, 0) + n
        if (key, reason) not in self._reported:
            self._reported.add((key, reason))
            self.problem(f"dropped a message on {key}: {reason}")

    def inbox(self, message: schemas.Message, upstream: str, key: str | None = None, keep: int = 4,
              others_only: bool = False) -> Inbox:
        """Subscribe to `message` from `upstream` ("sim" or a service name). others_only (real time):
        not this process's own messages on that key (the hot-standby drivers hear each other only)."""
        key = key or message.key(self.vehicle_id)
        box = Inbox(self, message, key, upstream, keep)
        if self.lockstep and not box.clocked:
            self.follow(upstream)
            if schemas.RUN_DONE.get(upstream) is message and key == message.key(self.vehicle_id):
                if upstream in self._done_light:   # two callbacks: the tag would depend on their order
                    raise RuntimeError(f"{self.name}: inbox for {key} declared after its lockstep subscription")
                box.marks_done = True
                self._done_boxes.add(upstream)
        if self.lockstep or self.rate_hz <= 0:   # lockstep tags on arrival; an event-driven loop wakes on it
            box._subscriber = self.subscribe(key, box._on_sample)
        else:
            box._subscriber = self.session.declare_subscriber(
                key, zenoh.handlers.RingChannel(RAW_QUEUE_MAX), allowed_origin=zenoh.Locality.REMOTE if others_only else None)
            box._channel = box._subscriber.handler
        self.inboxes.append(box)
        return box

    def _wake_on(self, box: Inbox) -> None:
        """The loop runs on `box`'s arrival: from polled to a callback that wakes it (before the
        loop starts; what was queued meanwhile is kept)."""
        box.wakes = True
        if box._channel is None:
            return
        box._poll()   # (on the reader's thread, before its loop: no read runs meanwhile)
        box._subscriber.undeclare()   # (its ring goes with it)
        box._channel = None
        box._subscriber = self.subscribe(box.key, box._on_sample)

    def follow(self, upstream: str) -> None:
        """Track another service's lockstep progress (its syncs and its RUN_DONE messages)."""
        if self.progress.follow(upstream):
            self.subscribe(schemas.SYNC_DONE.key(self.vehicle_id, upstream), self._make_sync_cb(upstream))

    def subscribe_run_done(self) -> None:
        """Lockstep, once the inputs are declared: for each upstream followed whose RUN_DONE
        message is not one of this service's inputs, a subscription that only notes its runs."""
        for upstream in self.progress.upstreams:
            message = schemas.RUN_DONE.get(upstream)
            if message is None or upstream in self._done_boxes or upstream in self._done_light:
                continue
            key = message.key(self.vehicle_id)

            def on_done(sample: zenoh.Sample, upstream=upstream, message=message, key=key) -> None:
                data, reason = screen(message, sample.payload)
                if data is None:   # garbage: counted and dropped, no tick taken from it
                    self.count_rejects(key, reason)
                    return
                try:
                    msg = message.decode(data)
                except schemas.SchemaError as exc:
                    self.reject(key, exc)
                    return
                self._run_done(upstream, msg)
            self._done_light[upstream] = on_done
            self.subscribe(key, on_done)

    def _run_done(self, upstream: str, msg: dict) -> None:
        """A valid RUN_DONE message arrived (Zenoh's thread): its run is done, as a sync would say."""
        header = msg["header"]
        if header["source"] != upstream:
            return
        self.progress.on_run_done(upstream, round(header["t_s"] * self.tick_rate))

    def subscribe(self, key: str, callback: Callable[[zenoh.Sample], None]):
        """Subscribe with the callback run on Zenoh's receiving thread (indirect=False):
        one sender's messages then reach every callback in the order they were sent,
        which lockstep relies on. Callbacks must be short."""
        return self.session.declare_subscriber(key, zenoh.handlers.Callback(callback, indirect=False))

    def publisher(self, message: schemas.Message, key: str | None = None) -> Publisher:
        return Publisher(self, message, key or message.key(self.vehicle_id))

    # -- live parameters (param/set, e.g. from the MAVLink parameter protocol) --------
    def on_param(self, key: str, callback: Callable[[Any], None]) -> None:
        """Call `callback(new_value)` (on a Zenoh thread) when param/set changes `key`."""
        self._param_callbacks.setdefault(key, []).append(callback)

    def _on_param_set(self, sample: zenoh.Sample) -> None:
        data, reason = screen(schemas.PARAM_SET, sample.payload)
        if data is None:
            self.count_rejects("param/set", reason)
            return
        try:
            msg = schemas.PARAM_SET.decode(data)
        except schemas.SchemaError as exc:
            self.reject("param/set", exc)
            return
        if msg["service"] != self.name:
            return
        key, source = msg["key"], msg["header"]["source"]
        try:
            new = self.set_param(key, msg["value"], source)
        except StackError as exc:   # unknown, wrong type or length, out of bounds: counted, the old value kept
            with self._count_lock:
                self.rejected["param_rejected"] = self.rejected.get("param_rejected", 0) + 1
            self.problem(f"refused {exc}" + (f"; {key} stays {self.params[key]}" if key in self.params else ""))
            return
        print(f"zenpilot-{self.name}: param {key} = {new} (from {source})", flush=True)

    # -- lockstep wiring (services/lockstep.py; callbacks on Zenoh's threads) ---------
    def _sync_tick(self, upstream: str) -> int:
        """The lockstep tag of a message from `upstream` arriving now (Inbox visibility)."""
        if upstream == "sim" or upstream not in LOCKSTEP_PARTICIPANTS:
            return self.progress.sim_tick
        return self.progress.last_done(upstream)

    def _make_sync_cb(self, upstream: str) -> Callable:
        def on_sync(sample: zenoh.Sample) -> None:
            data, reason = screen(schemas.SYNC_DONE, sample.payload)
            if data is None:   # garbage on a sync key: counted and dropped, the clock untouched
                self.count_rejects(f"@lockstep/sync/{upstream}", reason)
                return
            try:
                msg = schemas.SYNC_DONE.decode(data)
            except schemas.SchemaError as exc:
                self.reject(f"@lockstep/sync/{upstream}", exc)
                return
            self.progress.on_sync(upstream, msg)
        return on_sync

    def watch_participants(self) -> None:
        """Lockstep: drop a participant from the clock when its liveliness token goes."""
        prefix = self.key("alive/")

        def on_token(sample: zenoh.Sample) -> None:
            name = str(sample.key_expr)[len(prefix):]
            if sample.kind == zenoh.SampleKind.DELETE and name in self.progress.upstreams:
                self.progress.drop(name, "its liveliness token is gone")
        self.session.liveliness().declare_subscriber(self.key("alive/*"), on_token)

    def _report_dropped(self, name: str, why: str) -> None:
        self.rejected[f"lockstep_dropped_{name}"] = 1
        self.problem(f"lockstep: {name} dropped from the clock ({why}); the others run on")

    def subscribe_clock(self) -> None:
        """The simulator's clocks addressed to this service."""
        self.subscribe(schemas.CLOCK.key(self.vehicle_id, self.name), self._on_clock)

    def _on_clock(self, sample: zenoh.Sample) -> None:
        data, reason = screen(schemas.CLOCK, sample.payload)
        if data is None:   # garbage on the clock key: counted and dropped, no tick taken from it
            self.count_rejects(self.key("@lockstep/clock"), reason)
            return
        try:
            msg = schemas.CLOCK.decode(data)
        except schemas.SchemaError as exc:
            self.reject(self.key("@lockstep/clock"), exc)
            return
        self.progress.on_clock(msg)

    # -- health ------------------------------------------------------------
    def count_run(self, t: float) -> None:
        if self._run_times:
            self._periods.append(t - self._run_times[-1])
        self._run_times.append(t)
        while self._run_times and self._run_times[0] <= t - HEALTH_PERIOD_S:
            self._run_times.popleft()

    def publish_health(self, force: bool = False) -> None:
        """Called from the main loop on every run: the beat and, once per period, health."""
        t = self.now()
        if t >= self._next_beat and self._beat is not None:
            self._next_beat = t + 0.9 * BEAT_PERIOD_S   # a 10 Hz loop beats on every run, not every other
            self._beat.put({"cycles": self.cycles}, t_s=t)
        if not force and t < self._next_health:
            return
        self._next_health = (math.floor(t / HEALTH_PERIOD_S) + 1) * HEALTH_PERIOD_S
        nominal = 1.0 / self.rate_hz if self.rate_hz > 0 else None
        jitter = 0.0
        if nominal and self._periods and not self.lockstep:
            dev = sorted(abs(p - nominal) for p in self._periods)
            jitter = dev[min(len(dev) - 1, int(0.99 * len(dev)))] * 1e3
            self._periods.clear()
        late = sorted(self._lateness)
        self._lateness.clear()
        p50, p99, worst = (1e3 * late[len(late) // 2], 1e3 * late[min(len(late) - 1, int(0.99 * len(late)))],
                           1e3 * late[-1]) if late else (0.0, 0.0, 0.0)
        self.late_max_ms = max(self.late_max_ms, worst)
        self._health.put({
            "state": self.state, "rate_hz": float(len(self._run_times)) / HEALTH_PERIOD_S,
            "target_rate_hz": float(self.rate_hz), "overruns": self.overruns,
            "jitter_p99_ms": jitter, "lateness_p50_ms": p50, "lateness_p99_ms": p99, "lateness_max_ms": worst,
            # wall-clock figures stay out of a lockstep log (same seed, same bytes): the log line at exit has them
            "late": self.late, "cycles": self.cycles, "step_s": 0.0 if self.lockstep else self.step_s,
            "wait_s": 0.0 if self.lockstep else self.wait_s,
            "rejected": dict(self.rejected), "dropped": dict(self.dropped), "scheduling": self.scheduling,
            "detail": self.detail,
        })

    # -- main loops ----------------------------------------------------------
    def run(self, step: Callable[[float], None], triggers: tuple[str, ...] = (),
            wake_on: Inbox | None = None, min_gap: float = 0.0) -> None:
        """Call `step(t)` at the service's rate (or on `triggers`) until stopped.

        wake_on (real time): run when a message arrives on that inbox, at most once per
        `min_gap` periods, and on a timer WAKE_TIMER_MARGIN past a period when nothing comes:
        the loop then keeps the phase of its input (an attitude loop runs as its IMU sample
        arrives, the motor driver as its command does) instead of adding up to a period of
        waiting per hop. Lockstep runs on the ticks as always."""
        try:
            if self.lockstep and self.local_bus is not None:
                lockstep.serve_inline(self, step, triggers)
            elif self.lockstep:
                lockstep.follow_clock(self, step, triggers)
            elif wake_on is not None and self.rate_hz > 0:
                self._wake_on(wake_on)
                self._run_woken(step, min_gap, wake_on)
            else:
                self._run_realtime(step, triggers)
        finally:
            self.close()

    def _run_woken(self, step: Callable[[float], None], min_gap: float, box: Inbox) -> None:
        self.state = "running"
        self.enter_loop()
        period = 1.0 / self.rate_hz
        clock, wake, lateness = time.time, self._wake, self._lateness
        gap, timer_after = min_gap * period, (1.0 + WAKE_TIMER_MARGIN) * period
        t_last = clock() - period
        while not self.stop_event.is_set():
            deadline = t_last + timer_after
            while True:
                wait = deadline - clock()
                if wait <= 0.0:   # nothing came in time: the timer's run
                    break
                if wake.wait(wait):
                    wake.clear()
                    arrived = self._wake_t
                    if arrived - t_last >= gap and box.fresh():   # garbage does not run the loop
                        deadline = arrived   # lateness from the input's arrival
                        break
            now = clock()
            self._t = now
            late = now - deadline
            lateness.append(late if late > 0.0 else 0.0)
            if late > LATE_S:
                self.late += 1
            if now - t_last > 2.0 * period + LATE_S:   # no input and the timer late: a missed cycle
                self.overruns += int((now - t_last) / period) - 1
            t_last = now
            self.count_run(now)
            self._safe_step(step, now)
            self.publish_health()

    def enter_loop(self) -> None:
        """Set-up is over: the scheduling the stack file asks for (real time), for every thread
        of the process (Zenoh's, XLA's); set-up itself ran at normal scheduling, so a long one (the
        flip's JAX compile) never takes the CPU from normal processes. Then everything allocated
        so far goes out of the garbage collector's way."""
        if self.real_time_scheduling and self.spec is not None and LOCAL_BUS is None:   # per process, not thread
            self.scheduling = apply_scheduling(self.spec.priority, self.spec.cpu)
            if "refused" in self.scheduling:
                self.problem(f"scheduling: {self.scheduling}")
            elif self.scheduling != "normal":
                print(f"zenpilot-{self.instance}: scheduling {self.scheduling}", flush=True)
        gc.collect()
        gc.freeze()  # start-up objects (modules, JAX, tables) are never scanned again

    def _run_realtime(self, step: Callable[[float], None], triggers: tuple[str, ...]) -> None:
        self.state = "running"
        self.enter_loop()
        if self.rate_hz <= 0:  # event driven: run when a message arrives, not on a timer
            self.event_driven = True
            while not self.stop_event.is_set():
                if self._arrival.wait(BEAT_PERIOD_S):   # idle, it still beats
                    self._arrival.clear()
                    self._t = time.time()
                    self._safe_step(step, self._t)
                self._t = time.time()
                self.publish_health()
            return
        period = 1.0 / self.rate_hz
        clock, sleep, lateness = time.time, time.sleep, self._lateness
        t_next = clock()
        while not self.stop_event.is_set():
            delay = t_next - clock()
            if delay > 0:
                sleep(delay)
            now = clock()
            self._t = now
            late = now - t_next   # against the absolute deadline, never the previous wake-up
            lateness.append(late if late > 0.0 else 0.0)
            if late > LATE_S:
                self.late += 1
            self.count_run(now)
            self._safe_step(step, now)
            self.publish_health()
            t_next += period
            if clock() > t_next:  # missed the next deadline: count it, do not catch up in a burst
                missed = int((clock() - t_next) / period) + 1
                self.overruns += missed
                t_next += missed * period

    def _safe_step(self, step: Callable[[float], None], t: float) -> None:
        t0 = time.perf_counter()
        try:
            step(t)
        except Exception as exc:  # a failing step is reported and the loop goes on
            self.state = "degraded"
            self.problem(f"step failed at t={t:.3f}: {type(exc).__name__}: {exc}")
        self.step_s += time.perf_counter() - t0
        self.cycles += 1

    def close(self) -> None:
        if self.state != "stopping":
            cpu = os.times()   # one process of several threads: this service's thread and its inline runs
            used = cpu.user + cpu.system if LOCAL_BUS is None else time.thread_time() + self.cpu_inline_s
            # the worst lateness of the run: a service stalled on a busy machine shows in its log
            late_max = max(self.late_max_ms, 1e3 * max(self._lateness, default=0.0))
            print(f"zenpilot-{self.instance}: stopping; cpu {used:.2f} s; {self.cycles} runs, "
                  f"step {self.step_s:.3f} s, waited {self.wait_s:.3f} s"
                  f"{'' if self.lockstep else f'; late at most {late_max:.1f} ms'}", flush=True)
        self.state = "stopping"
        try:
            self.publish_health(force=True)
            if self._token is not None:
                self._token.undeclare()
            self.session.close()
        except Exception:  # already closing; nothing left to report to
            pass


def _threads() -> list[int]:
    """Every thread of this process (Linux); [0], the calling thread, elsewhere."""
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return [0]


def apply_scheduling(priority: int, cpus: tuple[int, ...]) -> str:
    """Ask the OS, for every thread of the process, for SCHED_FIFO at `priority` (0: leave the
    normal scheduler) and for the CPUs `cpus` (empty: any); threads started later inherit it.
    Returns what holds, with the reason for what was refused."""
    parts, refused = [], []
    threads = _threads()
    if cpus:
        try:
            for tid in threads:
                _per_thread(os.sched_setaffinity, tid, set(cpus))
            parts.append("cpu " + ",".join(map(str, sorted(cpus))))
        except (OSError, ValueError, AttributeError) as exc:
            refused.append(f"cpu {list(cpus)} refused: {exc}")
    if priority:
        try:
            for tid in threads:
                _per_thread(os.sched_setscheduler, tid, os.SCHED_FIFO, os.sched_param(priority))
            parts.insert(0, f"fifo {priority}")
        except (OSError, AttributeError) as exc:
            refused.append(f"priority {priority} refused ({exc}); normal scheduling")
    return ", ".join((parts or ["normal"]) + refused)


def _per_thread(call, tid: int, *args) -> None:
    try:
        call(tid, *args)
    except ProcessLookupError:   # a thread that ended meanwhile
        pass


PARENT_ENV = "ZENPILOT_PARENT_PID"   # set by a launcher whose processes end with it (`zenpilot fly`)


def tie_to_parent() -> None:
    """End with the process that started us when it asked so (PARENT_ENV: its pid): the kernel
    sends SIGTERM when it dies, killed or not, so a simulated flight whose `zenpilot fly` was
    killed stops, its log written, instead of flying on unwatched. A vehicle's `zenpilot up` does
    not ask: its services outlive a lost launcher. Taken out of the environment: for us only."""
    parent = os.environ.pop(PARENT_ENV, None)
    if parent is None or not sys.platform.startswith("linux"):
        return
    import ctypes
    PR_SET_PDEATHSIG = 1
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    if str(os.getppid()) != parent:   # it died before we asked: the signal will not come
        os.kill(os.getpid(), signal.SIGTERM)


def main_guard(name: str, fn: Callable[[], None]) -> None:
    """Run a service's main: configuration problems become one line, not a traceback."""
    tie_to_parent()
    try:
        fn()
    except (StackError, ValueError) as exc:
        fail(name, str(exc))
    except KeyboardInterrupt:
        pass
