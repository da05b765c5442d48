"""zenpilot view: a live Foxglove view of a running stack (the Foxglove WebSocket protocol).

A ground-side tool, off the vehicle's path: a Zenoh client of the stack's router that
only listens (it publishes nothing, so a lockstep flight's log is the same with or without
it) and serves, with foxglove-sdk, on loopback by default:

- every message of zp/<vehicle>/** on a JSON channel named by its key, with the JSON Schema
  flight.mcap uses (schemas/flightlog.json_schema): the same topics and fields as the log, so
  one layout (docs/foxglove-layout.json) serves both; plots of setpoints, attitude, rates,
  motor outputs and each service's health come from these;
- the well-known channels of services/foxglove_map.py (poses and transforms of truth and
  estimate, the scene).

Zenoh's callback only queues the payload; decoding, conversion and encoding run on the
reader thread, and only for channels a Foxglove client subscribes to. When the reader falls
behind, the oldest payloads go (counted and printed at exit): a viewer never holds up the stack.
"""

from __future__ import annotations

import json
import queue
import sys
import threading
from dataclasses import dataclass, field

import foxglove
from foxglove import channels as fg_channels

import schemas
from schemas.flightlog import json_schema
from services.foxglove_map import FoxgloveMap, MarkerGrid

QUEUE_MAX = 20000      # payloads waiting for the reader (~10 s of the whole stack's traffic)
# messages the server holds per client before dropping its oldest (the SDK's default is 1024,
# half a second of the stack's stream): a client stalled a second or two catches up instead
CLIENT_BACKLOG = 8192
# keys the view leaves out: liveliness tokens (lockstep's clock and handshake are under a
# verbatim @lockstep chunk, which zp/<vehicle>/** never matches)
SKIP_PARTS = ("/alive/",)


@dataclass
class ViewStats:
    received: int = 0
    forwarded: int = 0
    lost: int = 0        # queue full: the oldest payload dropped
    gaps: int = 0        # messages that never reached the view (sequence gaps: dropped on the way)
    rejected: dict[str, int] = field(default_factory=dict)   # by reason (malformed, no schema)


class LiveView:
    """Zenoh samples in (callback queues), Foxglove channels out (reader thread)."""

    def __init__(self, fmap: FoxgloveMap, context: foxglove.Context):
        self.fmap = fmap
        self.context = context
        self.stats = ViewStats()
        self._queue: queue.Queue = queue.Queue(QUEUE_MAX)
        self._raw: dict[str, foxglove.Channel | None] = {}   # per key: its channel, None to skip
        self._decoders: dict[str, object] = {}
        self._known: dict[str, object] = {}   # well-known channels by topic
        self._next_seq: dict[str, int] = {}   # per key: the sequence number expected next
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, name="foxglove-view", daemon=True)

    # -- Zenoh's thread: queue only --------------------------------------------------
    def on_sample(self, sample) -> None:
        item = (str(sample.key_expr), sample.payload.to_bytes())
        try:
            self._queue.put_nowait(item)
        except queue.Full:   # the reader is behind: the oldest goes, the newest is shown
            try:
                self._queue.get_nowait()
                self.stats.lost += 1
                self._queue.put_nowait(item)
            except (queue.Empty, queue.Full):
                self.stats.lost += 1

    # -- the reader thread -------------------------------------------------------------
    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)

    def _read(self) -> None:
        get = self._queue.get
        while not self._stop.is_set():
            try:
                key, payload = get(timeout=0.1)
            except queue.Empty:
                continue
            self.handle(key, payload)

    def handle(self, key: str, payload: bytes) -> None:
        """Decode one payload and log what it makes on the channels someone listens to."""
        self.stats.received += 1
        channel = self._raw.get(key, False)
        if channel is False:
            channel = self._raw_channel(key)
        if channel is None:
            return
        try:
            msg = self._decoders[key](payload)
        except schemas.SchemaError as exc:
            self.stats.rejected[exc.reason] = self.stats.rejected.get(exc.reason, 0) + 1
            return
        header = msg["header"]
        expected = self._next_seq.get(key)
        if expected is not None and header["seq"] > expected:
            self.stats.gaps += header["seq"] - expected
        self._next_seq[key] = header["seq"] + 1
        t_ns = int(round(header["t_s"] * 1e9))
        if channel.has_sinks():
            channel.log(json.dumps(msg, separators=(",", ":")).encode(), log_time=t_ns)
            self.stats.forwarded += 1
        for topic, message in self.fmap.convert(key, msg):   # stateful: runs for every message
            out = self._known.get(topic)
            if out is None:
                out = self._known[topic] = getattr(fg_channels, type(message).__name__ + "Channel")(
                    topic, context=self.context)
            if out.has_sinks():
                out.log(message, log_time=t_ns)
                self.stats.forwarded += 1

    def _raw_channel(self, key: str):
        definition = None if any(p in key for p in SKIP_PARTS) else schemas.message_for_key(key)
        if definition is None:
            if not any(p in key for p in SKIP_PARTS):
                self.stats.rejected["no_schema"] = self.stats.rejected.get("no_schema", 0) + 1
            channel = None
        else:
            self._decoders[key] = definition.decode
            channel = foxglove.Channel(key, message_encoding="json", context=self.context, schema=foxglove.Schema(
                name=definition.name, encoding="jsonschema", data=json.dumps(json_schema(definition)).encode()))
        if len(self._raw) < 4096:   # keys come from the network: bound what is remembered
            self._raw[key] = channel
        return channel


def serve(router: str, vehicle_id: int, motor_positions_m, markers: MarkerGrid, host: str, port: int,
          stop: threading.Event, out=sys.stdout) -> ViewStats:
    """Serve the live view until `stop` is set; returns what it did."""
    from deploy.launcher import client_session

    context = foxglove.Context()
    view = LiveView(FoxgloveMap(motor_positions_m, vehicle_id, markers), context)
    session = client_session(router)
    try:
        server = foxglove.start_server(name=f"zenpilot vehicle {vehicle_id}", host=host, port=port, context=context,
                                       message_backlog_size=CLIENT_BACKLOG)
    except RuntimeError as exc:   # e.g. the port is taken
        session.close()
        raise ValueError(f"--host {host} --port {port}: cannot serve the Foxglove WebSocket: {exc}") from None
    try:
        view.start()
        session.declare_subscriber(f"zp/{vehicle_id}/**", view.on_sample)
        print(f"zenpilot view: Foxglove WebSocket on ws://{host}:{server.port} (vehicle {vehicle_id}, "
              f"router {router}); open it in Foxglove: Open connection -> Foxglove WebSocket", file=out, flush=True)
        while not stop.wait(0.2):
            pass
    finally:
        session.close()
        view.stop()
        server.stop()
        s = view.stats
        print(f"zenpilot view: stopped; {s.received} messages received, {s.forwarded} forwarded, "
              f"{s.lost} lost (reader behind), {s.gaps} never arrived (sequence gaps), rejected {json.dumps(s.rejected, sort_keys=True)}",
              file=out, flush=True)
    return view.stats
