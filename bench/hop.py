"""One hop, project publish -> project callback, against raw zenoh-python pub/sub in the same run.

    python bench/hop.py [--rounds 30] [--pings 200] [--topologies stack,routed,direct] [--diagnose]
                        [--baseline DIR]

Two processes per topology: A (ping) and B (echo), each a services.runtime.Runtime built
from `--stack deploy/stacks/default.toml` and its own -e/-l endpoints, started the way the
launcher starts services (ZENOH_RUNTIME set the same way, peer mode). A sends one message,
B answers it, A times the round trip with perf_counter (one clock, no clock sync) and sends
the next; one message is in flight at a time. BOTH directions take the variant's path, so
a round trip is two identical hops and the ratio of round trips is the ratio of hops;
one-way is shown as RTT/2.

Variants (each hop, from the sender's call to the receiver holding the data):

  raw            publisher.put(bytes) of a pre-packed IMU message (zenoh-python publisher,
                 express=True, congestion DROP) -> subscriber callback (Callback,
                 indirect=False) on Zenoh's thread: sample.payload.to_bytes(). The callback
                 sends the answer / the next ping itself.
  project        Publisher.put(values) (schemas.IMU encode + put on the runtime's express
                 publisher) -> Inbox._on_sample (tag + queue) then Inbox.latest() (strict
                 decode, seq check) called in the same Zenoh callback. Same threads as raw:
                 the difference is only the project's code on the hot path.
  raw-woken      as raw, but the callback queues the bytes and sets a threading.Event; a
                 reader thread wakes, takes them and sends (a reader-thread hand-off done
                 with the same primitives as the runtime: deque + Event).
  project-woken  as the services run with run(wake_on=inbox): an Inbox as Runtime.inbox()
                 makes it, wakes=True sets the runtime's wake event from _on_sample, the
                 reader thread wakes and calls latest() (decode on the reader's thread), then
                 Publisher.put (from a Python thread, as a service's step does). Compare
                 with raw-woken (same hand-off).

Fair pairs (the verdict, target project <= 1.2x raw): project/raw and
project-woken/raw-woken. project-woken/raw is shown too: the whole cost of the services'
input path against the leanest raw callback.

--diagnose adds variants that take the project's path apart (inline, except the -woken ones):
  raw+msgpack    msgpack.packb of the same map / msgpack.unpackb, no checks: the floor of
                 any serialisation
  raw+encode     schemas.IMU.encode (as Publisher.put calls it) + raw put / raw receive
  raw+decode     raw send / to_bytes + schemas.IMU.decode
  publisher      Publisher.put / raw receive
  inbox          raw send / Inbox._on_sample + latest()
  raw-split, project-split, raw-woken-split, project-woken-split
                 the same as raw, project, ... with A timing the parts of its side in place

--baseline DIR adds `baseline` and `baseline-woken`: project and project-woken with the Inbox and
Publisher classes of DIR/services/runtime.py and the IMU compiled by DIR/schemas/core.py's codec
(another checkout, e.g. `git archive main | tar -x -C DIR`), the rest (the message definitions,
Zenoh, the runtime that owns them) this tree's. Their blocks take
turns with the others in every round, so `project / baseline` is an A/B of the two inboxes paired
round by round, in the same run, whatever the machine's load does meanwhile.

Topologies:

  stack   A and B peers connected to a router (deploy.router) on a free port, exactly the
          services' flags (-e ROUTER). Zenoh's gossip lets the two peers find each other
          through the router and open a direct link: the header says what A is linked to.
  routed  A and B in client mode (-m client -e ROUTER): every message goes A -> router -> B,
          the router's own hop (peers would take the direct link; docs/performance.md).
  direct  no router: B listens on a free port, A connects to it.

The blocks (one variant, one topology, --pings round trips after --warm unrecorded ones)
are interleaved: every round runs every topology and variant, in an order rotated each
round. Figures: p50 and p99 over all rounds' round trips, the spread of the per-round
medians, and the ratio to raw paired by round (the median over rounds of this block's
median / raw's in the same round), which the verdict uses: it cancels the slow drifts of
a shared machine. Wall-clock figures depend on the machine and its load (2 cores here:
A, B and the router share them with whatever else runs).
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from pathlib import Path
from types import SimpleNamespace

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

STACK = str(ROOT / "deploy" / "stacks" / "default.toml")
VARIANTS = ("raw", "project", "raw-woken", "project-woken")
# --diagnose: the project's path taken apart (see the module's doc)
DIAGNOSE = ("raw+msgpack", "raw+encode", "raw+decode", "publisher", "inbox",
            "raw-split", "project-split", "raw-woken-split", "project-woken-split")
INLINE = {"raw": ("raw", "raw"), "project": ("publisher", "inbox"),   # (sender, receiver), in the callback
          "baseline": ("baseline", "inbox"),
          "raw+msgpack": ("msgpack", "unpack"),
          "raw+encode": ("encode", "raw"), "raw+decode": ("raw", "decode"),
          "publisher": ("publisher", "raw"), "inbox": ("raw", "inbox"),
          "raw-split": ("raw", "raw"), "project-split": ("publisher", "inbox")}
LEGEND = {   # what one hop of each main variant includes (the module's doc has the rest)
    "raw": "pub.put(pre-packed 132 B IMU bytes) -> callback: sample.payload.to_bytes()",
    "project": "Publisher.put(values) [IMU encode+put] -> callback: Inbox._on_sample + Inbox.latest() [decode]",
    "raw-woken": "as raw; callback: to_bytes, deque.append, Event.set -> reader thread wakes, takes it",
    "project-woken": "Publisher.put -> callback: Inbox._on_sample (wakes=True) -> reader thread wakes, latest()",
}
RAWS = ("raw", "raw-woken", "raw-split", "raw-woken-split")
BASE = {"project-woken": "raw-woken", "project-split": "raw-split",   # the raw each is compared with
        "baseline-woken": "raw-woken",
        "project-woken-split": "raw-woken-split"}
TOPOLOGIES = ("stack", "routed", "direct")
PAIRS = (("project", "raw"), ("project-woken", "raw-woken"))   # judged against TARGET
BASELINE = ("baseline", "baseline-woken")   # --baseline: the same as project, project-woken, another runtime.py's classes
INFO_PAIRS = (("project-woken", "raw"), ("project", "baseline"), ("project-woken", "baseline-woken"),
              ("baseline", "raw"), ("baseline-woken", "raw-woken"))   # shown, not judged
TARGET = 1.2
VALUES = {"gyro_rad_s": [0.01, -0.02, 0.1], "accel_m_s2": [0.1, 0.2, 9.81]}
TAG = "HOP "           # A's protocol lines on its stdout start with this
ECHO_TIMEOUT_S = 1.0   # no answer this long: the block stops (a lost message)


def keys(topo: str, variant: str) -> tuple[str, str]:
    return f"bench/hop/{topo}/{variant}/ping", f"bench/hop/{topo}/{variant}/pong"


# ================================================================ child processes (A and B)
def open_runtime(name: str, zargs: list[str]):
    from services.runtime import Runtime, service_parser
    args = service_parser(name, "hop bench").parse_args(["--stack", STACK] + zargs)
    rt = Runtime(name, args)

    def leave(*_):
        raise SystemExit(0)
    for sig in (signal.SIGINT, signal.SIGTERM):   # the runtime's handlers only set stop_event
        signal.signal(sig, leave)
    return rt


class Side:
    """One process's end of every variant: what it sends and what it does with what arrives.
    `on_arrival(variant)` is called after the variant's receive work (inline variants on
    Zenoh's thread, woken variants on the reader thread)."""

    def __init__(self, rt, topo: str, role: str, variants: tuple[str, ...], baseline=None):
        import zenoh
        import schemas
        from services.runtime import Inbox, Publisher
        self.rt = rt
        self.send: dict = {}
        self.recv: dict = {}        # woken variants: variant -> fn(timeout) -> True if a new message
        self.on_arrival = lambda variant: None
        self.payload = schemas.IMU.encode(time.time(), 0, rt.name, VALUES)  # raw: packed once
        mine, theirs = (0, 1) if role == "ping" else (1, 0)
        session = rt.session
        drop = zenoh.CongestionControl.DROP   # what Publisher uses in real time
        encode, decode, name = schemas.IMU.encode, schemas.IMU.decode, rt.name
        from msgpack import packb, unpackb
        for variant in variants:
            k = keys(topo, variant)
            out_key, in_key = k[mine], k[theirs]
            sender, receiver = INLINE.get(variant, (variant.split("-")[0], None))
            if sender in ("raw", "encode", "msgpack"):
                pub = session.declare_publisher(out_key, express=True, congestion_control=drop)
                put, payload = pub.put, self.payload
                if sender == "raw":
                    self.send[variant] = lambda put=put, payload=payload: put(payload)
                elif sender == "msgpack":   # the same map, no checks
                    seq = [0]

                    def send(put=put, seq=seq):
                        put(packb({"version": 1, "header": {"t_s": time.time(), "seq": seq[0], "source": name},
                                   "gyro_rad_s": VALUES["gyro_rad_s"], "accel_m_s2": VALUES["accel_m_s2"]},
                                  use_bin_type=True))
                        seq[0] += 1
                    self.send[variant] = send
                else:   # what Publisher.put does, without the Publisher object
                    seq = [0]

                    def send(put=put, seq=seq):
                        put(encode(time.time(), seq[0], name, VALUES))
                        seq[0] += 1
                    self.send[variant] = send
            else:   # project: this tree's Publisher; baseline: --baseline's
                pub = (baseline.Publisher(rt, baseline.IMU, out_key) if variant.startswith("baseline")
                       else Publisher(rt, schemas.IMU, out_key))
                self.send[variant] = lambda put=pub.put: put(VALUES)
            box_class, imu = (baseline.Inbox, baseline.IMU) if variant.startswith("baseline") else (Inbox, schemas.IMU)
            if receiver == "raw":
                def cb(sample, v=variant):
                    self.last = sample.payload.to_bytes()
                    self.on_arrival(v)
            elif receiver == "unpack":
                def cb(sample, v=variant):
                    self.last = unpackb(sample.payload.to_bytes(), raw=False)
                    self.on_arrival(v)
            elif receiver == "decode":
                def cb(sample, v=variant):
                    self.last = decode(sample.payload.to_bytes())
                    self.on_arrival(v)
            elif receiver == "inbox":
                box = box_class(rt, imu, in_key, "sim", keep=4)

                def cb(sample, box=box, v=variant):
                    box._on_sample(sample)
                    self.last = box.latest()
                    self.on_arrival(v)
            elif variant.startswith("raw-woken"):
                q, ev = deque(), threading.Event()

                def cb(sample, q=q, ev=ev):
                    q.append(sample.payload.to_bytes())
                    ev.set()

                def recv(timeout, q=q, ev=ev):
                    if not ev.wait(timeout):
                        return False
                    self.t_woke = time.perf_counter()
                    ev.clear()
                    got = False
                    while q:
                        self.last = q.popleft()
                        got = True
                    return got
                self.recv[variant] = recv
            else:   # project-woken (baseline-woken): an inbox as Runtime.inbox() makes it, woken as run(wake_on=) does
                owner = rt
                if variant != "project-woken":
                    # the runtime has one wake event; a second woken inbox gets a view of the
                    # runtime with its own (else two readers race for one event)
                    owner = SimpleNamespace(_sync_tick=rt._sync_tick, count_dropped=rt.count_dropped,
                                            reject=rt.reject, count_rejects=rt.count_rejects,
                                            lockstep=rt.lockstep, event_driven=rt.event_driven,
                                            _arrival=rt._arrival, _wake=threading.Event(), _wake_t=0.0)
                box = box_class(owner, imu, in_key, "sim", keep=4)
                rt.inboxes.append(box)
                box.wakes = True   # what run(wake_on=box) sets
                seen = [None]   # the last message read: each decoded message is a new dict

                def recv(timeout, box=box, seen=seen, wake=owner._wake):
                    if not wake.wait(timeout):
                        return False
                    self.t_woke = time.perf_counter()
                    wake.clear()
                    m = box.latest()
                    if m is None or m is seen[0]:
                        return False
                    seen[0] = m
                    self.last = m
                    return True
                self.recv[variant] = recv
                if variant.endswith("-split") and role == "ping":
                    rt.subscribe(in_key, self._timed(box._on_sample))
                else:
                    rt.subscribe(in_key, box._on_sample)   # what Runtime.inbox() subscribes
                continue
            rt.subscribe(in_key, self._timed(cb) if variant.endswith("-split") and role == "ping" else cb)

    def _timed(self, cb):
        """-split variants on A: the callback's entry and return times."""
        clock = time.perf_counter

        def timed(sample):
            self.t_in = clock()
            cb(sample)
            self.t_out = clock()
        return timed


def load_baseline(tree: str | None):
    """--baseline: DIR/services/runtime.py's Inbox and Publisher, and the IMU by DIR's codec."""
    if not tree:
        return None
    import schemas
    from bench.support.baseline_tree import baseline_message, load_module
    runtime = load_module(tree, "services/runtime.py", "hop_baseline_runtime")
    return SimpleNamespace(Inbox=runtime.Inbox, Publisher=runtime.Publisher, IMU=baseline_message(tree, schemas.IMU))


def echo_main(topo: str, variants: tuple[str, ...], zargs: list[str], baseline: str | None = None) -> None:
    rt = open_runtime("bench-echo", zargs)
    side = Side(rt, topo, "pong", variants, load_baseline(baseline))
    send = side.send
    side.on_arrival = lambda v: send[v]()   # inline: answer from the callback
    stop = threading.Event()

    def reader(variant):
        recv, out = side.recv[variant], send[variant]
        while not stop.is_set():
            if recv(0.5):
                out()
    threads = [threading.Thread(target=reader, args=(v,), daemon=True) for v in side.recv]
    rt.enter_loop()
    for t in threads:
        t.start()
    try:
        sys.stdin.read()   # until the bench closes our stdin (or dies)
    finally:
        stop.set()
        rt.close()


class Pinger:
    def __init__(self, side: Side):
        self.side = side
        self.active = None      # the inline variant being timed
        self.rtts: list[float] = []
        self.n = 0
        self.t0 = 0.0
        self.done = threading.Event()
        self.stray = 0          # arrivals while no block was timed
        self.got = threading.Event()
        self.split: list[dict[str, float]] = []   # -split: named durations (s) per round trip
        side.on_arrival = self.arrived

    def arrived(self, variant: str) -> None:   # inline variants, on Zenoh's thread
        t1 = time.perf_counter()
        if variant != self.active:
            self.stray += 1
            self.got.set()
            return
        self.rtts.append(t1 - self.t0)
        if len(self.rtts) >= self.n:
            self.active = None
            self.done.set()
            return
        self.t0 = time.perf_counter()
        self.side.send[variant]()
        if variant[-6:] == "-split":
            self.split.append({"receive": t1 - self.side.t_in, "send": time.perf_counter() - self.t0})

    def ping_once(self, variant: str, timeout: float) -> bool:
        """Untimed: one ping, True if its answer came."""
        if variant in self.side.recv:
            self.side.send[variant]()
            return self.side.recv[variant](timeout)
        self.got.clear()
        self.side.send[variant]()
        return self.got.wait(timeout)

    def ready(self, timeout_s: float) -> dict:
        """Ping every variant until it answers; then count answers to a single ping."""
        deadline = time.monotonic() + timeout_s
        for v in self.side.send:
            while not self.ping_once(v, 0.2):
                if time.monotonic() > deadline:
                    raise SystemExit(f"hop bench: no answer on {v} within {timeout_s:.0f} s")
        time.sleep(0.3)
        self.quiet()
        answers = {}
        for v in self.side.send:   # exactly one answer per message, or the timing is meaningless
            before = self.stray
            count = 0
            if v in self.side.recv:
                self.side.send[v]()
                t_end = time.monotonic() + 0.3
                while time.monotonic() < t_end:
                    count += self.side.recv[v](0.05)
            else:
                self.side.send[v]()
                time.sleep(0.3)
                count = self.stray - before
            answers[v] = count
        self.quiet()
        return answers

    def quiet(self) -> None:
        for v, recv in self.side.recv.items():
            while recv(0.0):
                pass

    def block(self, variant: str, n: int, warm: int) -> dict:
        side = self.side
        lost = 0
        self.split = []
        if variant in side.recv:          # woken: timed on this (the reader's) thread
            send, recv, clock = side.send[variant], side.recv[variant], time.perf_counter
            split = variant.endswith("-split")
            rtts = []
            for i in range(warm + n):
                t0 = clock()
                send()
                if split:
                    ts = clock()
                while not recv(ECHO_TIMEOUT_S):
                    if clock() - t0 > ECHO_TIMEOUT_S:
                        lost = 1
                        break
                if lost:
                    break
                t1 = clock()
                if i >= warm:
                    rtts.append(t1 - t0)
                    if split:
                        self.split.append({"send": ts - t0, "callback": side.t_out - side.t_in,
                                           "wake": side.t_woke - side.t_out, "read": t1 - side.t_woke})
        else:                              # inline: the ping-pong runs in the callbacks
            for stage, count in (("warm", warm), ("timed", n)):
                if count == 0:
                    continue
                self.rtts, self.n = [], count
                self.done.clear()
                self.active = variant
                self.t0 = time.perf_counter()
                side.send[variant]()
                while not self.done.wait(ECHO_TIMEOUT_S):
                    progress = len(self.rtts)
                    time.sleep(0.05)
                    if len(self.rtts) == progress:
                        self.active = None
                        lost = 1
                        break
                if lost:
                    break
            rtts = [] if lost else self.rtts
        if lost:   # an answer this late may still come: let it, and drop it, before going on
            time.sleep(ECHO_TIMEOUT_S)
        self.quiet()
        rt = side.rt
        split = {}
        if self.split and not lost:
            for what in self.split[0]:
                xs = sorted(x[what] for x in self.split[-n:])
                split[what] = round(xs[len(xs) // 2] * 1e6, 2)
        return {"split": split, "rtt_us": [round(r * 1e6, 2) for r in rtts], "lost": lost,
                "dropped": sum(rt.dropped.values()), "rejected": sum(rt.rejected.values())}


def ping_main(topo: str, variants: tuple[str, ...], zargs: list[str], baseline: str | None = None) -> None:
    rt = open_runtime("bench-ping", zargs)
    side = Side(rt, topo, "ping", variants, load_baseline(baseline))
    pinger = Pinger(side)
    answers = pinger.ready(20.0)
    info = rt.session.info
    rt.enter_loop()
    out = sys.stdout
    out.write(TAG + json.dumps({
        "ready": True, "answers": answers, "payload_bytes": len(side.payload),
        "peers": len(list(info.peers_zid())), "routers": len(list(info.routers_zid()))}) + "\n")
    out.flush()
    try:
        for line in sys.stdin:
            cmd = json.loads(line)
            res = pinger.block(cmd["variant"], cmd["n"], cmd["warm"])
            out.write(TAG + json.dumps(res) + "\n")
            out.flush()
    finally:
        rt.close()


# ================================================================ the bench (parent)
def _die_with_parent() -> None:
    """In the child before exec: SIGTERM when the bench dies, even by SIGKILL (Linux)."""
    try:
        import ctypes
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG
    except Exception:
        pass


class Procs:
    def __init__(self, logdir: Path):
        from deploy.launcher import ZENOH_RUNTIME
        self.logdir = logdir
        self.env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.env.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)   # as the launcher does
        self.procs: list[tuple[str, subprocess.Popen]] = []
        self._buf: dict[int, bytes] = {}

    def spawn(self, name: str, argv: list[str], pipe_out: bool = False) -> subprocess.Popen:
        log = open(self.logdir / f"{name}.log", "wb")
        p = subprocess.Popen(argv, cwd=ROOT, env=self.env, stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE if pipe_out else log, stderr=log,
                             start_new_session=True, preexec_fn=_die_with_parent)
        self.procs.append((name, p))
        return p

    def readline(self, name: str, p: subprocess.Popen, timeout_s: float) -> dict:
        """The next protocol line of a child (other lines are logged), or an error."""
        fd = p.stdout.fileno()
        buf = self._buf.get(fd, b"")
        deadline = time.monotonic() + timeout_s
        with open(self.logdir / f"{name}.log", "ab") as log:
            while True:
                while b"\n" in buf:
                    line, buf = buf.split(b"\n", 1)
                    text = line.decode(errors="replace")
                    if text.startswith(TAG):
                        self._buf[fd] = buf
                        return json.loads(text[len(TAG):])
                    log.write(line + b"\n")
                left = deadline - time.monotonic()
                if left <= 0 or p.poll() is not None and not select.select([fd], [], [], 0)[0]:
                    self._buf[fd] = buf
                    why = f"exited {p.returncode}" if p.poll() is not None else "timeout"
                    raise RuntimeError(f"{name}: no answer ({why}); log:\n{self.tail(name)}")
                if select.select([fd], [], [], min(left, 0.5))[0]:
                    chunk = os.read(fd, 1 << 20)
                    if not chunk and p.poll() is not None:
                        p.wait()
                    buf += chunk

    def tail(self, name: str, lines: int = 15) -> str:
        try:
            text = (self.logdir / f"{name}.log").read_text(errors="replace").splitlines()
        except OSError:
            return "(no log)"
        return "\n".join("    " + t for t in text[-lines:])

    def close(self) -> None:
        """Stop every child: stdin closed, SIGTERM, then SIGKILL after a grace period."""
        for _, p in self.procs:
            try:
                p.stdin.close()
            except OSError:
                pass
        for _, p in self.procs:
            if p.poll() is None:
                try:
                    p.send_signal(signal.SIGTERM)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + 3.0
        for _, p in self.procs:
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
            if p.stdout:
                p.stdout.close()


def start_topologies(procs: Procs, topologies: list[str], variants: tuple[str, ...], baseline: str | None = None):
    from deploy.launcher import free_port, wait_port
    me = [sys.executable, str(Path(__file__).resolve()), "--variants", ",".join(variants)]
    if baseline:
        me += ["--baseline", baseline]
    pairs, flags = {}, {}
    for topo in topologies:
        if topo in ("stack", "routed"):
            router = f"tcp/127.0.0.1:{free_port()}"
            procs.spawn(f"router-{topo}", [sys.executable, "-m", "deploy.router", "--listen", router])
            if not wait_port(router, 10.0):
                raise RuntimeError(f"router for {topo} did not open {router}:\n{procs.tail('router-' + topo)}")
            a = b = ["-e", router] if topo == "stack" else ["-m", "client", "-e", router]
        else:
            ep = f"tcp/127.0.0.1:{free_port()}"
            a, b = ["-e", ep], ["-l", ep]
        flags[topo] = (a, b)
        procs.spawn(f"echo-{topo}", me + ["--role", "echo", "--topo", topo, "--"] + b)
        pairs[topo] = procs.spawn(f"ping-{topo}", me + ["--role", "ping", "--topo", topo, "--"] + a, pipe_out=True)
    info = {}
    for topo, p in pairs.items():
        info[topo] = procs.readline(f"ping-{topo}", p, 40.0)
        bad = {v: c for v, c in info[topo]["answers"].items() if c != 1}
        if bad:
            raise RuntimeError(f"{topo}: answers per message {bad} (expected exactly 1)")
    return pairs, info, flags


def pct(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, int(q * len(s)))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=30, help="alternating rounds (default 30)")
    ap.add_argument("--pings", type=int, default=200, help="timed round trips per block (default 200)")
    ap.add_argument("--max-s", type=float, default=60.0,
                    help="start no round that would end after this many seconds (default 60)")
    ap.add_argument("--warm", type=int, default=20, help="untimed round trips before each block (default 20)")
    ap.add_argument("--topologies", default=",".join(TOPOLOGIES), help="comma list of " + ",".join(TOPOLOGIES))
    ap.add_argument("--diagnose", action="store_true",
                    help="add variants that take the project's path apart: " + ", ".join(DIAGNOSE))
    ap.add_argument("--baseline", metavar="DIR",
                    help="add baseline, baseline-woken: project's variants with DIR/services/runtime.py's "
                         "Inbox and Publisher and DIR/schemas/core.py's codec (an A/B in the same run)")
    ap.add_argument("--variants", help=argparse.SUPPRESS)
    ap.add_argument("--role", choices=["ping", "echo"], help=argparse.SUPPRESS)
    ap.add_argument("--topo", help=argparse.SUPPRESS)
    ap.add_argument("zargs", nargs="*", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.role == "echo":
        return echo_main(args.topo, tuple(args.variants.split(",")), args.zargs, args.baseline)
    if args.role == "ping":
        return ping_main(args.topo, tuple(args.variants.split(",")), args.zargs, args.baseline)

    topologies = [t for t in args.topologies.split(",") if t]
    if not topologies or set(topologies) - set(TOPOLOGIES):
        ap.error(f"--topologies: choose from {','.join(TOPOLOGIES)}")
    from importlib.metadata import version

    def on_term(*_):
        raise KeyboardInterrupt
    for sig in (signal.SIGINT, signal.SIGTERM):   # also when started with SIGINT ignored (a background job)
        signal.signal(sig, on_term)
    print("command:", " ".join([Path(sys.executable).name, *sys.argv]))
    print("each round trip = 2 hops, both directions through the variant's path; one hop:")
    for v, text in LEGEND.items():
        print(f"  {v:<14} {text}")
    print("  (inline variants answer from the Zenoh callback; woken ones from the reader thread)")
    load0 = os.getloadavg()[0]
    t_start = time.monotonic()
    if args.baseline:
        args.baseline = str(Path(args.baseline).resolve())
        if not (Path(args.baseline) / "services" / "runtime.py").is_file():
            ap.error(f"--baseline {args.baseline}: no services/runtime.py there")
    variants = VARIANTS + (BASELINE if args.baseline else ()) + (DIAGNOSE if args.diagnose else ())
    results = {(t, v): [] for t in topologies for v in variants}
    round_medians = {(t, v): [] for t in topologies for v in variants}
    lost = {(t, v): 0 for t in topologies for v in variants}
    splits = {(t, v): [] for t in topologies for v in variants}
    counters = {}
    with tempfile.TemporaryDirectory(prefix="zenpilot-hop-") as tmp:
        procs = Procs(Path(tmp))
        print(f"eclipse-zenoh {version('eclipse-zenoh')}, {os.cpu_count()} CPUs, "
              f"ZENOH_RUNTIME={procs.env['ZENOH_RUNTIME']}")
        print(f"stack {Path(STACK).relative_to(ROOT)}; {args.rounds} rounds x {len(topologies)} topologies x "
              f"{len(variants)} variants, {args.pings} timed round trips per block (+{args.warm} warm-up)")
        try:
            pairs, info, flags = start_topologies(procs, topologies, variants, args.baseline)
            for topo in topologies:
                i = info[topo]
                print(f"  {topo:<7} A {' '.join(flags[topo][0])} | B {' '.join(flags[topo][1])} -> A linked to "
                      f"{i['peers']} peer(s), {i['routers']} router(s); IMU payload {i['payload_bytes']} B")
            print(f"  start-up {time.monotonic() - t_start:.1f} s", flush=True)
            done_rounds, t_rounds = 0, time.monotonic()
            for r in range(args.rounds):
                spent = time.monotonic() - t_start
                if r and spent + (time.monotonic() - t_rounds) / r > args.max_s:
                    print(f"  stopping after {r} rounds: the next would end past --max-s {args.max_s:.0f} s")
                    break
                order = variants[r % len(variants):] + variants[:r % len(variants)]
                if r % 2:
                    order = order[::-1]
                for k, topo in enumerate(topologies):
                    p = pairs[topo]
                    for v in order[k % len(order):] + order[:k % len(order)]:
                        p.stdin.write((json.dumps({"variant": v, "n": args.pings, "warm": args.warm}) + "\n").encode())
                        p.stdin.flush()
                        res = procs.readline(f"ping-{topo}", p, 60.0)
                        results[(topo, v)] += res["rtt_us"]
                        lost[(topo, v)] += res["lost"]
                        round_medians[(topo, v)].append(statistics.median(res["rtt_us"]) if res["rtt_us"] else None)
                        if res["split"]:
                            splits[(topo, v)].append(res["split"])
                        counters[topo] = (res["dropped"], res["rejected"])
                done_rounds = r + 1
                print(f"  round {r + 1}/{args.rounds} done at {time.monotonic() - t_start:.1f} s", flush=True)
        except KeyboardInterrupt:
            print("interrupted: stopping the processes", file=sys.stderr)
            raise SystemExit(130)
        except RuntimeError as exc:
            print(f"hop bench: error: {exc}", file=sys.stderr)
            raise SystemExit(1)
        finally:
            procs.close()
    report(topologies, variants, results, round_medians, lost, splits, counters)
    print(f"{done_rounds} rounds; total {time.monotonic() - t_start:.1f} s; load average {load0:.2f} at the start, "
          f"{os.getloadavg()[0]:.2f} at the end ({os.cpu_count()} CPUs)")


def base_of(variant: str) -> str | None:
    if variant in RAWS:
        return None
    return BASE.get(variant, "raw")


def paired(a: list, b: list) -> list[float]:
    """Per-round ratios of block medians (the same round: the same state of the machine)."""
    return sorted(x / y for x, y in zip(a, b) if x is not None and y is not None)


def report(topologies, variants, results, round_medians, lost, splits, counters) -> None:
    print()
    print(f"{'topology':<8} {'variant':<19} {'n':>6} {'RTT p50':>8} {'RTT p99':>8} {'1-way p50':>9} "
          f"{'1-way p99':>9} {'rounds p50':>11}  ratio to raw: paired p50 [quartiles], pooled p50, pooled p99")
    stat, ratios = {}, {}
    for topo in topologies:
        for v in variants:
            xs = results[(topo, v)]
            extra = f"  LOST {lost[(topo, v)]} block(s)" if lost[(topo, v)] else ""
            if not xs:
                print(f"{topo:<8} {v:<19} no data{extra}")
                continue
            p50, p99 = pct(xs, 0.5), pct(xs, 0.99)
            stat[(topo, v)] = (p50, p99)
            base = base_of(v)
            ratio = ""
            if base and (topo, base) in stat:
                b50, b99 = stat[(topo, base)]
                pr = paired(round_medians[(topo, v)], round_medians[(topo, base)])
                if pr:
                    ratios[(topo, v)] = (pr[len(pr) // 2], p99 / b99)
                    ratio = (f"{pr[len(pr) // 2]:.2f}x [{pr[len(pr) // 4]:.2f}..{pr[(3 * len(pr)) // 4]:.2f}], "
                             f"{p50 / b50:.2f}x, {p99 / b99:.2f}x  vs {base}")
            rm = [m for m in round_medians[(topo, v)] if m is not None]
            spread = f"{min(rm):.0f}..{max(rm):.0f}"
            print(f"{topo:<8} {v:<19} {len(xs):>6} {p50:>8.1f} {p99:>8.1f} {p50 / 2:>9.1f} {p99 / 2:>9.1f} "
                  f"{spread:>11}  {ratio}{extra}")
    print("(microseconds; RTT = two hops, both through the variant's path; 1-way = RTT/2; rounds p50: the")
    print(" lowest..highest block median; paired: median over rounds of this block's median / raw's)")
    for topo, (dropped, rejected) in counters.items():
        if dropped or rejected:
            print(f"  {topo}: A's runtime counted {dropped} dropped, {rejected} rejected messages")
    if any(splits.values()):
        print()
        print("in place, on A (us, median of the blocks' medians): send = the put call (raw: pub.put;")
        print("project: Publisher.put, encode included); inline: receive = callback entry to the data in")
        print("hand (raw: to_bytes; project: Inbox._on_sample + latest()); woken: callback = the Zenoh")
        print("callback (raw: to_bytes, append, Event.set; project: Inbox._on_sample), wake = callback")
        print("return to the reader running, read = reader: wake to the data in hand (project: latest())")
        for topo in topologies:
            for v in variants:
                sp = splits[(topo, v)]
                if sp:
                    parts = {k: statistics.median(x[k] for x in sp) for k in sp[0]}
                    print(f"  {topo:<7} {v:<20} " + "  ".join(f"{k} {x:6.2f}" for k, x in parts.items())
                          + f"  sum {sum(parts.values()):6.2f}")
    print()
    print(f"verdict (target: project hop <= {TARGET}x raw hop; paired p50 ratio):")
    verdicts = []
    for topo in topologies:
        for proj, raw in PAIRS + INFO_PAIRS:
            if (topo, proj) not in stat or (topo, raw) not in stat:
                continue
            (p50, _), (b50, _) = stat[(topo, proj)], stat[(topo, raw)]
            if (proj, raw) in INFO_PAIRS:
                pr = paired(round_medians[(topo, proj)], round_medians[(topo, raw)])
                r = pr[len(pr) // 2] if pr else p50 / b50
                note = ("  [for information: includes the reader-thread hand-off raw lacks]" if raw == "raw"
                        and proj == "project-woken" else "  [for information: A/B, --baseline]")
            else:
                r = ratios.get((topo, proj), (p50 / b50, 0))[0]
                note = ""
            ok = "PASS" if r <= TARGET else "FAIL"
            label = "" if note else ok
            if not note:
                verdicts.append((topo, proj, r, ok))
            print(f"  {topo:<7} {proj:>14} / {raw:<14} {r:.2f}x  ({(p50 - b50) / 2:+.1f} us per hop, pooled p50)  "
                  f"{label}{note}")

    if verdicts:
        bad = [f"{t} {p} {r:.2f}x" for t, p, r, ok in verdicts if ok == "FAIL"]
        print(f"overall: {'FAIL: ' + ', '.join(bad) if bad else 'PASS'}")


if __name__ == "__main__":
    main()
