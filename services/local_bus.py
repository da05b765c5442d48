"""An in-process stand-in for the Zenoh session: the transport of a one-process lockstep.

A lockstep flight spends most of its time carrying messages between processes (each
delivery into a Python process costs ~30-60 us of CPU, docs/performance.md), not in the
services' work. deploy/one_process.py runs every service of a lockstep flight as a thread
of one process; their Runtimes open a `LocalSession` of one `LocalBus` instead of Zenoh.
The services, the lockstep protocol and the bytes on the "wire" are unchanged: a put
encodes the message as before, and each subscriber whose key expression matches gets the
payload on the publisher's thread, in the order it was put, as Zenoh's receiving thread
delivers one sender's messages in order (indirect=False callbacks). Same seed, same log as
the multi-process lockstep (tests/integration/test_flights.py checks the bytes).

Only what the services use is offered: publishers, subscribers (a callback or a
Fifo/Ring channel), liveliness tokens and their subscribers, close.
"""

from __future__ import annotations

import contextlib
import struct
import sys
import threading
from collections import deque
from typing import Any, BinaryIO, Callable, Iterable, Iterator

import zenoh

_PUT, _DELETE = zenoh.SampleKind.PUT, zenoh.SampleKind.DELETE
_FRAME = struct.Struct(">HI")   # a message on a byte stream: key length, payload length, key, payload
_delivery = threading.local()   # .owner: the session whose callback is running on this thread


@contextlib.contextmanager
def running_as(owner: str):
    """Code of `owner` runs on this thread meanwhile (its output goes to its log)."""
    previous = getattr(_delivery, "owner", None)
    _delivery.owner = owner
    try:
        yield
    finally:
        _delivery.owner = previous


def swap_owner(owner: str | None) -> str | None:
    """`running_as` without the context manager (a few microseconds less per call: the lockstep
    clock's inline runs, several per tick): sets the owner, returns the one to put back."""
    previous = getattr(_delivery, "owner", None)
    _delivery.owner = owner
    return previous


def delivering_to() -> str | None:
    """The owner of the session whose subscriber callback runs on this thread now, if any
    (its output belongs to that service, not to the publisher whose thread it borrows)."""
    return getattr(_delivery, "owner", None)


class Payload(bytes):
    """The bytes of a put, with ZBytes's `to_bytes` (what the services call)."""
    __slots__ = ()

    def to_bytes(self) -> bytes:
        return self


class Sample:
    __slots__ = ("key_expr", "payload", "kind")

    def __init__(self, key: str, payload: Payload, kind: zenoh.SampleKind = _PUT):
        self.key_expr, self.payload, self.kind = key, payload, kind


class Channel:
    """FifoChannel/RingChannel's reading side: the receiver pulls with try_recv. Unbounded: the
    publisher never waits for a reader on its own thread (a ring's loss is real time's, and a
    one-process run is lockstep only)."""

    def __init__(self):
        self._queue: deque[Sample] = deque()

    def try_recv(self) -> Sample | None:
        try:
            return self._queue.popleft()
        except IndexError:
            return None


class Subscriber:
    def __init__(self, bus: "LocalBus", session: "LocalSession", key: str, handler: Any, liveliness: bool):
        self.bus, self.session, self.key, self.liveliness = bus, session, zenoh.KeyExpr(key), liveliness
        self.handler = None
        if isinstance(handler, zenoh.handlers.Callback):
            self.deliver: Callable[[Sample], None] = handler.callback
        elif isinstance(handler, (zenoh.handlers.FifoChannel, zenoh.handlers.RingChannel)):
            self.handler = Channel()
            self.deliver = self.handler._queue.append
        elif callable(handler):
            self.deliver = handler
        else:
            raise TypeError(f"local bus: unsupported subscriber handler {handler!r}")

    def undeclare(self) -> None:
        self.bus._remove(self)


class Publisher:
    def __init__(self, session: "LocalSession", key: str):
        self.session, self.key = session, key
        self._kexpr = zenoh.KeyExpr(key)
        self._version = -1
        self._targets: tuple[tuple[str, Callable[[Sample], None]], ...] = ()

    def put(self, payload: bytes) -> None:
        bus = self.session.bus
        if self._version != bus.version:   # subscribers came or went: match again
            # the version read with the match, under one lock: read after it, a subscriber added
            # meanwhile would be missed for good (the simulator then never heard a participant's
            # "ready": a start-up that hung)
            self._version, self._targets = bus.matching_versioned(self._kexpr)
        if self.session.closed:
            return
        bus.deliver(self._targets, Sample(self.key, Payload(payload)))

    def undeclare(self) -> None:
        pass


class Token:
    def __init__(self, session: "LocalSession", key: str):
        self.session, self.key = session, key

    def undeclare(self) -> None:
        self.session.bus._drop_token(self)


class Liveliness:
    def __init__(self, session: "LocalSession"):
        self.session = session

    def declare_token(self, key: str) -> Token:
        return self.session.bus._add_token(Token(self.session, key))

    def declare_subscriber(self, key: str, handler: Any) -> Subscriber:
        return self.session.bus._add(Subscriber(self.session.bus, self.session, key, handler, liveliness=True))


class LocalSession:
    """What a Runtime uses of zenoh.Session, on a LocalBus; `owner` names the service."""

    def __init__(self, bus: "LocalBus", owner: str):
        self.bus, self.owner, self.closed = bus, owner, False

    def declare_publisher(self, key: str, **_qos) -> Publisher:
        return Publisher(self, key)

    def declare_subscriber(self, key: str, handler: Any) -> Subscriber:
        return self.bus._add(Subscriber(self.bus, self, key, handler, liveliness=False))

    def liveliness(self) -> Liveliness:
        return Liveliness(self)

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.bus._close(self)


class LocalBus:
    """The subscribers and liveliness tokens of one process's sessions."""

    def __init__(self):
        self._lock = threading.Lock()
        self._subs: list[Subscriber] = []
        self._tokens: list[Token] = []
        self.version = 0   # changes whenever a subscriber comes or goes
        self.token_event = threading.Event()   # set whenever a token is declared
        self._stop_handlers: dict[str, Callable[[], None]] = {}
        self.participants: dict[str, Any] = {}   # lockstep participants run inline (services.lockstep.serve_inline)

    def on_stop(self, handler: Callable[[], None]) -> None:
        """What stops the calling thread's service (its SIGTERM handler, in a process of its own:
        as with signal.signal, the last one set is the one called)."""
        with self._lock:
            self._stop_handlers[threading.current_thread().name] = handler

    def request_stop(self, owner: str) -> bool:
        """Ask `owner` to stop; False if it has not said how yet (still starting)."""
        with self._lock:
            handler = self._stop_handlers.get(owner)
        if handler is not None:
            handler()
        return handler is not None

    def open(self, _conf: Any = None) -> LocalSession:
        """A session for the calling thread's service (Runtime's stand-in for zenoh.open)."""
        return LocalSession(self, threading.current_thread().name)

    def matching(self, key: zenoh.KeyExpr, liveliness: bool) -> tuple[tuple[str, Callable[[Sample], None]], ...]:
        with self._lock:
            return tuple((s.session.owner, s.deliver) for s in self._subs
                         if s.liveliness == liveliness and s.key.intersects(key))

    def matching_versioned(self, key: zenoh.KeyExpr) -> tuple[int, tuple[tuple[str, Callable[[Sample], None]], ...]]:
        """The data subscribers matching `key`, with the version they are as of."""
        with self._lock:
            return self.version, tuple((s.session.owner, s.deliver) for s in self._subs
                                       if not s.liveliness and s.key.intersects(key))

    @staticmethod
    def deliver(targets, sample: Sample) -> None:
        previous = getattr(_delivery, "owner", None)
        for owner, callback in targets:
            _delivery.owner = owner
            try:
                callback(sample)
            except Exception as exc:   # as Zenoh does: the receiver's bug stays the receiver's
                print(f"local bus: a subscriber of {owner} failed on {sample.key_expr}: "
                      f"{type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
        _delivery.owner = previous

    def tokens(self) -> list[str]:
        with self._lock:
            return [t.key for t in self._tokens]

    def _add(self, sub: Subscriber) -> Subscriber:
        with self._lock:
            self._subs.append(sub)
            self.version += 1
        return sub

    def _remove(self, sub: Subscriber) -> None:
        with self._lock:
            if sub in self._subs:
                self._subs.remove(sub)
                self.version += 1

    def _add_token(self, token: Token) -> Token:
        with self._lock:
            self._tokens.append(token)
        self.token_event.set()
        self.deliver(self.matching(zenoh.KeyExpr(token.key), liveliness=True), Sample(token.key, Payload(b"")))
        return token

    def _drop_token(self, token: Token) -> None:
        with self._lock:
            if token not in self._tokens:
                return
            self._tokens.remove(token)
        self.deliver(self.matching(zenoh.KeyExpr(token.key), liveliness=True),
                     Sample(token.key, Payload(b""), _DELETE))

    def _close(self, session: LocalSession) -> None:
        for token in [t for t in self._tokens if t.session is session]:
            self._drop_token(token)
        with self._lock:
            self._subs = [s for s in self._subs if s.session is not session]
            self.version += 1


# ---------------------------------------------------------------- messages over a pipe
def frames(messages: Iterable[tuple[str, bytes]]) -> bytes:
    """(key, payload) pairs as one byte string for a pipe (read_frames reads them back):
    how a one-process lockstep hands the bus's messages to its recorder's process."""
    parts = []
    for key, payload in messages:
        k = key.encode()
        parts += (_FRAME.pack(len(k), len(payload)), k, payload)
    return b"".join(parts)


def read_frames(stream: BinaryIO) -> Iterator[tuple[str, bytes]]:
    """The (key, payload) pairs `frames` wrote, until the stream ends (a cut last frame is dropped)."""
    size = _FRAME.size
    while len(head := stream.read(size)) == size:
        key_len, payload_len = _FRAME.unpack(head)
        key, payload = stream.read(key_len), stream.read(payload_len)
        if len(key) < key_len or len(payload) < payload_len:
            return
        yield key.decode(errors="replace"), payload
