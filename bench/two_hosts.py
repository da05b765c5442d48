"""Fly a mission over two hosts, across an emulated link, and the same mission on one host, and compare.

    python bench/two_hosts.py [--mission hover|flip-short|FILE] [--seed N] [--lockstep]
                              [--placement vehicle|ground|telemetry] [--secure [tls|tls+quic]]
                              [--link none|lan|bad|lan100|lan100-qos|D/J/L]
                              [--emulator auto|netem|forwarder] [--out DIR] [--no-one-host]
                              [--flood BYTES@HZ[:PRIORITY]] [--stop SERVICE@T_S[:FOR_S]]
                              [--outage T_S:FOR_S] [--trace] [--link-rt]

Two hosts are two network namespaces that this bench creates (root, `ip netns`): "vehicle"
(10.77.0.1/24) and "ground" (10.77.0.2/24), loopback up in each, nothing else: no route out, so
nothing of the run can leave them. The link between them (`--link`, each direction alike):
`none` a veth pair; `lan` 20 +- 5 ms, 1 % loss; `bad` 50 +- 20 ms, 5 % loss; `lan100` lan of
100 Mbit/s, one queue; `lan100-qos` the same with the packets marked DSCP 46 (the stack's control
links) sent first; or DELAY_MS/JITTER_MS/LOSS_PCT. An impaired link is `tc netem` on both ends of the veth pair where
the kernel has it, else (this VM) a third namespace "link" joined to each host by a veth pair,
bench/support/linkemu.py forwarding the frames between them with the delay drawn per frame and
the loss seeded (`--link-seed`); either way a direction keeps its packets in order.

Placements (`--placement`, each a stack file; services, rates and parameters the default stack's):
  vehicle  tests/integration/stacks/two-hosts.toml: one router, on the vehicle's link address;
           the vehicle's services, and the ground's recorder, connect to it:
    vehicle:  zenpilot up -d --machine vehicle-router --router tcp/10.77.0.1:7447
    ground:   zenpilot up -d --machine ground --router tcp/10.77.0.1:7447      (the recorder)
    vehicle:  zenpilot up -d --machine vehicle --router tcp/10.77.0.1:7447 --mission M
              --set sim.stop_after_mission=true                                 (the flight)
  ground   tests/integration/stacks/two-hosts-ground.toml (issue 22): sim, motors, attitude,
           position, vision on the vehicle; planner, recorder, MAVLink bridge on the ground; a
           router per host, each host's services on its own router, the routers linked:
    vehicle:  zenpilot up -d --machine vehicle-router                          (listens on the link)
    ground:   zenpilot up -d --machine ground --mission M                      (its router connects)
    vehicle:  zenpilot up -d --machine vehicle --mission M --set sim.stop_after_mission=true
  telemetry  tests/integration/stacks/two-hosts-telemetry.toml: as ground, with the planner on the
           vehicle (the ground: recorder and MAVLink bridge only); started the same way.
`--lockstep` is given to every `up`.

`--secure [LINK]` (ground and telemetry placements): the split secured as docs/security.md says,
made as an operator makes it: the placement's stack file with a [security] table and its link's
endpoints over TLS (secure_text: the same file, no second copy), keys by `zenpilot certs
<out>/keys/keys --stack <out>/keys/stack.toml` (the "trusted computer"; ca.key stays there),
and each host its own copy of the stack file and only its machines' keys (<out>/vehicle/stack.toml
and keys/: vehicle-router.*, vehicle.*, ca.pem; <out>/ground/: ground.*, ca.pem). Every session
presents its machine's login and certificate, the vehicle's router enforces the access control,
the link probes are tools of their host's machine. LINK: `tls` (the default): TLS where the plain
split has TCP (control prio 0-6, bulk 7-7), its UDP link left out; `tls+quic`: QUIC's datagrams
(rel=0) where it has UDP. Across `lan` QUIC's datagrams queue behind its congestion control (the
streams to the ground 1.3 s late, the flip aborted): docs/reliability.md, "A secured split over
an unreliable link". The one-host comparison flies the open stack (`zenpilot fly` refuses a
[security] stack: it is for the split).

The simulator ends the run when the mission ends; the vehicle's `zenpilot down` then stops its
services and router, the ground's stops its own, whose recorder writes flight.mcap on the ground
side (<out>/ground/); the metrics (deploy.metrics, on the log up to the simulator's last
sample: the services still running while `down` stops them one by one are the stack winding
down, not the flight) go to <out>/ground/metrics.json (`zenpilot report <out>/ground` redraws
the plots, on the whole log). Each host has its own run directory and `zenpilot` state directory.

What crossed the link, per key (in metrics.json under two_hosts.keys, and printed): in real time
its latency, arrival minus header time, noted by bench/support/linkprobe.py, a client of the
receiving host's router subscribed to the keys the other host's services publish (the header
time is the sample time: a camera frame's includes its 50 ms exposure-to-publish latency, hence
the `none` link as the baseline); and the messages lost, from the sequence numbers' gaps per
sender up to the simulator's end: in the ground's flight log for the vehicle's keys, in the
vehicle's probe for the ground's (the vehicle keeps no log). The forwarder's own account (frames,
drops, the delay it gave, its CPU) is in <out>/link/.

`--flood BYTES@HZ[:PRIORITY]` (real time): a bulk flood across the link for the whole flight,
e.g. `1048576@200`, 1 MiB camera images at 10x the camera's rate: bench/support/flooder.py
publishes them on the vehicle (a peer of its router, beside its services) and a sink on the
ground subscribes to them (a ground tool showing the camera), so they cross the routers' link
beside the control keys; PRIORITY (control|bulk, default the key's own: bulk) is the priority it
declares; its session is capped as the vehicle machine's services' are (`bulk_max_hz`), unless
`--rogue`. The per-key table then shows what the flood did to the control keys.

`--stop SERVICE@T_S[:FOR_S]` (real time): SIGSTOP one of the vehicle's services T_S into the
flight, SIGCONT after FOR_S (if its supervisor has not killed and restarted it by then), and
report when each host's supervisor saw it: the vehicle's from /proc, the ground's from the
service's beats across the link (deploy/supervisor.py, other machines' services).

`--outage T_S:FOR_S` (real time): the link cut both ways T_S after the simulator's first tick
(its "first tick at" line) for FOR_S, then restored: the link namespace's two veth ends set
down, then up (the forwarder always carries such a link, also `--link none`). Each host's end
then has no carrier, as with a cable pulled or a radio out of range: every frame sent meanwhile
is lost, none queued by the link (what a TCP stream still holds in its host's send buffer it
sends again). metrics.json's two_hosts.outage: when it was cut and restored, per key that
crosses, when it arrived last before the cut and first after the restore (and how many samples
older than the cut came after it); the ground router's link lines (CheckedLink); and the
vehicle's own record across the outage (its probe writes <out>/vehicle/witness.mcap, the keys
deploy.metrics reads: the ground's recorder sees nothing of the vehicle while cut), with its
metrics: crashed or not, failsafes, altitudes.

`--trace` (real time): where the control keys' time goes. bench/support/wiretap.py on each host's
end of the link notes when each EF-marked frame left or came in (the kernel's timestamps), matched
to the probes' rows by header: each message's latency split into the sender's host, the link and
the receiver's host (bench/support/trace.py), the stalls (moments when messages of several keys
were all held on the sender's host: a router that routes nothing), and the CPU of every process
and thread of the machine over the flight. `--link-rt`: the forwarder at SCHED_FIFO above every
service, so that the link is not slowed by the hosts' load on the shared cores. `--pin`: each
host's processes on a core of its own (the vehicle's CPU 0, the ground's CPU 1).

The same mission is then flown on one host with `zenpilot fly` (same stack, seed and mode) into
<out>/one-host/, its per-key losses beside; in lockstep the two logs are compared message for
message. Namespaces, the link and every process in them are removed at the end, also on an error
or Ctrl-C.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.support.flooder import flood_spec  # noqa: E402
from bench.support.trace import CpuWatch  # noqa: E402
from bench.support.trace import split as trace_split  # noqa: E402
from bench.support.trace import stalls as trace_stalls  # noqa: E402
from deploy.metrics import compute_metrics  # noqa: E402
from flight.control.mission import MissionError  # noqa: E402
from schemas.flightlog import LOG_NAME, read_log  # noqa: E402
from services.security import PUBLISHES  # noqa: E402
from services.stack import load_mission, load_stack  # noqa: E402

STACKS = {   # --placement: the stack file that places the services
    "vehicle": ROOT / "tests" / "integration" / "stacks" / "two-hosts.toml",          # ground: the recorder
    "ground": ROOT / "tests" / "integration" / "stacks" / "two-hosts-ground.toml",    # ground: planner, recorder, mavlink
    "telemetry": ROOT / "tests" / "integration" / "stacks" / "two-hosts-telemetry.toml",  # ground: recorder, mavlink
}
STACK = STACKS["vehicle"]
TEST_MISSIONS = ROOT / "tests" / "integration" / "missions"
VEHICLE_IP, GROUND_IP = "10.77.0.1", "10.77.0.2"
ROUTER = f"tcp/{VEHICLE_IP}:7447"     # the vehicle placement's one router, on the vehicle's link address
LOCAL_ROUTER = "tcp/127.0.0.1:7447"   # the ground placement's router on each host (linked: two-hosts-ground.toml)


@dataclasses.dataclass(frozen=True)
class LinkProfile:
    """One way of the link: delay drawn uniformly in delay +- jitter per packet, loss at random;
    with rate_mbit, a capacity (the forwarder's wire), and with priority_dscp its packets marked
    that DSCP or above sent first (bench/support/linkemu.py)."""
    name: str
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    loss_pct: float = 0.0
    rate_mbit: float = 0.0
    priority_dscp: int | None = None

    @property
    def impaired(self) -> bool:
        return bool(self.delay_ms or self.jitter_ms or self.loss_pct or self.rate_mbit)

    def __str__(self) -> str:
        if not self.impaired:
            return f"{self.name} (a plain veth pair)"
        wire = ""
        if self.rate_mbit:
            wire = f", {self.rate_mbit:g} Mbit/s" + (f", DSCP >= {self.priority_dscp} first"
                                                     if self.priority_dscp is not None else ", one queue")
        return f"{self.name} ({self.delay_ms:g} +- {self.jitter_ms:g} ms, {self.loss_pct:g} % loss each way{wire})"


PROFILES = {"none": LinkProfile("none"), "lan": LinkProfile("lan", 20.0, 5.0, 1.0),
            "bad": LinkProfile("bad", 50.0, 20.0, 5.0),
            # lan of 100 Mbit/s: one queue, or queues by DSCP (the stack marks its control links EF, 46)
            "lan100": LinkProfile("lan100", 20.0, 5.0, 1.0, 100.0),
            "lan100-qos": LinkProfile("lan100-qos", 20.0, 5.0, 1.0, 100.0, 46)}


def parse_profile(text: str) -> LinkProfile:
    """A profile's name, or DELAY/JITTER/LOSS (ms, ms, %)."""
    if text in PROFILES:
        return PROFILES[text]
    try:
        d, j, loss = (float(x) for x in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected {', '.join(PROFILES)} or DELAY_MS/JITTER_MS/LOSS_PCT "
                                         f"(e.g. 20/5/1)") from None
    if d < 0 or j < 0 or not 0 <= loss <= 100 or j > d:
        raise argparse.ArgumentTypeError(f"{text!r}: delay >= jitter >= 0 and loss within 0..100")
    return LinkProfile(text, d, j, loss)
# --secure LINK: the link's endpoints as a secured stack has them (docs/security.md). tls+quic: TLS
# where the plain split has TCP, QUIC's datagrams (rel=0) where it has UDP (its best-effort
# streams); tls: TLS only, the UDP link left out (every stream on TLS, behind retransmissions)
SECURE_LINKS = {"tls+quic": {"tcp/": "tls/", "udp/": "quic/"}, "tls": {"tcp/": "tls/", "udp/": None}}
HOST_MACHINES = {"vehicle": ("vehicle-router", "vehicle"), "ground": ("ground",)}   # each host's machines


def secure_text(text: str, path: Path, link: str = "tls+quic") -> str:
    """A two-hosts stack file (STACKS) as its secured split: a [security] table (the keys in "keys"
    beside the file) and every link endpoint (`listen`, `connect`) as SECURE_LINKS[link] says; the
    services, machines and the rest as they are, so one stack literal serves both."""
    out, n = [], 0
    for line in text.splitlines():
        if re.match(r"\s*(listen|connect)\s*=", line):
            for plain, secured in SECURE_LINKS[link].items():
                if secured is None:   # left out: the endpoint and its comma
                    line, k = re.subn(rf'\s*"{plain}\d[^"]*",?', "", line)
                    line = re.sub(r",\s*]", "]", line)
                else:   # tcp/10.77..., never a loopback name
                    line, k = re.subn(rf"\b{plain}(?=\d)", secured, line)
                n += k
        out.append(line)
    if not n:
        raise BenchError(f"{path}: no link endpoint (listen/connect) to secure")
    body = "\n".join(out) + "\n"
    head = (f"# {path.name} secured by bench/two_hosts.py --secure {link}: [security], the link's endpoints\n"
            "[security]\ndir = \"keys\"   # made by `zenpilot certs`; this host's share of them\n\n")
    return head + body


def secure_stacks(placement: str, out: Path, link: str = "tls+quic") -> dict[str, Path]:
    """The secured split of a placement, made as an operator would: the stack file (secure_text),
    its keys by the documented command (`zenpilot certs DIR --stack FILE`, on the "trusted
    computer": <out>/keys, ca.key stays there), then each host its own copy of the stack file and
    only its machines' keys and the CA's certificate (<out>/<host>/stack.toml, keys/). Returns
    {host: its stack file}."""
    src = STACKS[placement]
    made = out / "keys"
    shutil.rmtree(made, ignore_errors=True)   # `zenpilot certs` never overwrites: fresh keys per run
    made.mkdir(parents=True)
    text = secure_text(src.read_text(), src, link)
    (made / "stack.toml").write_text(text)
    run([sys.executable, "-m", "deploy.cli", "certs", str(made / "keys"), "--stack", str(made / "stack.toml")],
        cwd=ROOT, timeout=60)
    stacks = {}
    for host, machines in HOST_MACHINES.items():
        keys = out / host / "keys"
        shutil.rmtree(keys, ignore_errors=True)
        keys.mkdir(parents=True)
        for f in [made / "keys" / "ca.pem", *(p for m in machines for p in (made / "keys").glob(f"{m}.*"))]:
            shutil.copy2(f, keys / f.name)
        stacks[host] = out / host / "stack.toml"
        stacks[host].write_text(text)
    load_stack(stacks["vehicle"])   # checked as every host will (loopback routers, tls/quic links)
    return stacks


# --link-rt: the forwarder's real-time priority, above every service's (the simulator's 90): a
# link is hardware of its own, never slowed by the hosts' CPUs (here two cores shared by both)
LINK_FIFO = 95
RESTART_GRACE_S = 10.0   # a supervisor's back-off (at most 8 s, deploy/supervisor.py) and a start
WALL_CLOCK_FIELDS = ("solve_ms", "overrun_solves")   # the wall clock's, even in lockstep (planner/plan)
SCOUTING_GROUP = "224.0.0.224"  # Zenoh's multicast scouting group (port 7446)
SERVICES = ("sim", "motors", "attitude", "position", "vision", "planner", "mavlink")
WITNESS = "witness.mcap"   # --outage: the vehicle's own record (its probe's), the keys deploy.metrics reads
WITNESS_KEYS = ("sim/truth", "sim/imu", "motors/pwm", "att/state", "pos/state", "pos/setpoint", "vision/pose",
                "planner/setpoint", "*/health")


class BenchError(Exception):
    pass


class Stop(BaseException):
    """SIGTERM, raised in the main thread so that the clean-up runs (as Ctrl-C does)."""


def _stop(signum, frame):
    raise Stop()


def run(argv: list[str], check: bool = True, **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run(argv, capture_output=True, text=True, **kw)
    if check and proc.returncode != 0:
        raise BenchError(f"`{shlex.join(argv)}` failed (status {proc.returncode}): "
                         f"{(proc.stderr or proc.stdout).strip()}")
    return proc


# ---------------------------------------------------------------- the two hosts
class TwoHosts:
    """Two network namespaces joined by a link; `close` removes them and what runs in them.

    An unimpaired profile: one veth pair. Otherwise `tc netem` on both ends of that pair where the
    kernel has it, else (or with emulator="forwarder") a third namespace "link" between them, two
    veth pairs, and bench/support/linkemu.py forwarding the frames with the profile's delay and
    loss. Either way both hosts keep their addresses on one /24 and nothing leaves the namespaces."""

    def __init__(self, tag: str, profile: LinkProfile, emulator: str = "auto", link_seed: int = 0,
                 out: Path | None = None, cuttable: bool = False, link_rt: bool = False, pin: bool = False):
        self.ns = {"vehicle": f"zp{tag}-vehicle", "ground": f"zp{tag}-ground"}
        self.dev = {"vehicle": f"zp{tag}v", "ground": f"zp{tag}g"}  # interface names: 15 characters at most
        self.link_dev = {"vehicle": f"zp{tag}lv", "ground": f"zp{tag}lg"}   # the forwarder's ends
        self.ip = {"vehicle": VEHICLE_IP, "ground": GROUND_IP}
        self.profile, self.emulator, self.link_seed = profile, emulator, link_seed
        self.out = out or Path(".")
        self.created: list[str] = []
        self.method = "veth"            # what impairs the link: veth (nothing), netem, forwarder
        self.forwarder: subprocess.Popen | None = None
        self.forwarder_stats: dict | None = None
        self.cuttable = cuttable        # --outage: the link namespace's ends are what is cut
        self.link_rt = link_rt          # --link-rt: the forwarder above every service (SCHED_FIFO)
        # --pin: every process of a host on a core of its own (inherited by what it starts)
        self.cpu = {"vehicle": "0", "ground": "1"} if pin else {}

    def open(self) -> None:
        for host in ("vehicle", "ground"):
            try:
                run(["ip", "netns", "add", self.ns[host]])
            except BenchError as exc:
                raise BenchError(f"cannot create the two hosts (needs root and `ip netns`): {exc}") from None
            self.created.append(self.ns[host])
        for host in ("vehicle", "ground"):
            run(["ip", "-n", self.ns[host], "link", "set", "lo", "up"])
        if self.profile.rate_mbit and self.emulator == "netem":
            raise BenchError(f"--link {self.profile.name}: its capacity and queues are the forwarder's "
                             f"(--emulator forwarder)")
        if self.cuttable and self.emulator == "netem":
            raise BenchError("--outage cuts the link namespace's ends: --emulator auto or forwarder")
        if self.profile.impaired and not self.profile.rate_mbit and self.emulator in ("auto", "netem") \
                and not self.cuttable and self._netem():
            self.method = "netem"
        elif self.profile.impaired or self.cuttable:
            self._forwarder()
            self.method = "forwarder"
        else:
            self._veth(self.dev["vehicle"], self.ns["vehicle"], self.dev["ground"], self.ns["ground"])
        for host in ("vehicle", "ground"):
            ns, dev = self.ns[host], self.dev[host]
            run(["ip", "-n", ns, "addr", "add", f"{self.ip[host]}/24", "dev", dev])
            run(["ip", "-n", ns, "link", "set", dev, "up"])

    def _veth(self, a: str, ns_a: str, b: str, ns_b: str) -> None:
        run(["ip", "link", "add", a, "netns", ns_a, "type", "veth", "peer", "name", b, "netns", ns_b])

    def _netem(self) -> bool:
        """netem on both ends of a veth pair; False (the pair removed) where the kernel has no netem
        and the emulator may be the forwarder. `rate` keeps each direction in order: netem then
        times a packet from the one before it (sch_netem.c), as the forwarder does; without it a
        jitter reorders. Not run here: this kernel has no sch_netem."""
        p = self.profile
        self._veth(self.dev["vehicle"], self.ns["vehicle"], self.dev["ground"], self.ns["ground"])
        for host in ("vehicle", "ground"):
            netem = ["netem", "delay", f"{p.delay_ms:g}ms", f"{p.jitter_ms:g}ms", "loss", f"{p.loss_pct:g}%",
                     "rate", "10gbit"]
            proc = run(["tc", "-n", self.ns[host], "qdisc", "add", "dev", self.dev[host], "root", *netem], check=False)
            if proc.returncode != 0:
                if self.emulator == "netem":
                    raise BenchError(f"tc netem on {self.dev[host]}: {proc.stderr.strip()} (this kernel has no "
                                     f"sch_netem? --emulator forwarder)")
                run(["ip", "-n", self.ns["vehicle"], "link", "del", self.dev["vehicle"]], check=False)
                return False
        self._one_frame_per_segment()
        return True

    def _one_frame_per_segment(self) -> None:
        # no TCP super-frames (GSO, up to 64 KB) on the link: a loss is one packet's, not 44's
        for host in ("vehicle", "ground"):
            run(["ip", "-n", self.ns[host], "link", "set", "dev", self.dev[host], "gso_max_segs", "1"])

    def _forwarder(self) -> None:
        """vehicle <-veth-> link namespace <-veth-> ground, linkemu forwarding between the two."""
        link = self.ns["link"] = self.ns["vehicle"].rsplit("-", 1)[0] + "-link"
        run(["ip", "netns", "add", link])
        self.created.append(link)
        run(["ip", "-n", link, "link", "set", "lo", "up"])
        for host in ("vehicle", "ground"):
            self._veth(self.dev[host], self.ns[host], self.link_dev[host], link)
            run(["ip", "-n", link, "link", "set", self.link_dev[host], "up"])
        self._one_frame_per_segment()
        p = self.profile
        (self.out / "link").mkdir(parents=True, exist_ok=True)
        log = open(self.out / "link" / "linkemu.log", "w")
        self.forwarder = subprocess.Popen(
            self.argv("link", [*(["chrt", "-f", str(LINK_FIFO)] if self.link_rt else []),
                               sys.executable, "-m", "bench.support.linkemu", self.link_dev["vehicle"],
                               self.link_dev["ground"], "--delay-ms", str(p.delay_ms), "--jitter-ms", str(p.jitter_ms),
                               "--loss-pct", str(p.loss_pct), "--seed", str(self.link_seed),
                               "--stats", str(self.out / "link" / "linkemu.json"),
                               *(["--rate-mbit", str(p.rate_mbit)] if p.rate_mbit else []),
                               *(["--priority-dscp", str(p.priority_dscp)] if p.priority_dscp is not None else [])]),
            cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 10.0
        while "linkemu:" not in (self.out / "link" / "linkemu.log").read_text():
            if self.forwarder.poll() is not None or time.monotonic() > deadline:
                raise BenchError(f"the link forwarder did not start: "
                                 f"{(self.out / 'link' / 'linkemu.log').read_text().strip()}")
            time.sleep(0.05)

    def set_link(self, up: bool) -> float:
        """The link both ways down (an outage: each host's end loses its carrier, frames sent are
        lost) or up again; the wall-clock time once both ends are set."""
        for host in ("vehicle", "ground"):
            run(["ip", "-n", self.ns["link"], "link", "set", "dev", self.link_dev[host], "up" if up else "down"])
        return time.time()

    def stop_forwarder(self) -> dict | None:
        """Stop the forwarder (it writes what it did: frames, losses, the delays it gave, its CPU)."""
        if self.forwarder is not None and self.forwarder.poll() is None:
            self.forwarder.send_signal(signal.SIGTERM)
            try:
                self.forwarder.wait(10)
            except subprocess.TimeoutExpired:
                self.forwarder.kill()
                self.forwarder.wait()
            try:
                self.forwarder_stats = json.loads((self.out / "link" / "linkemu.json").read_text())
            except (OSError, ValueError):
                self.forwarder_stats = None
        return self.forwarder_stats

    def argv(self, host: str, cmd: list[str]) -> list[str]:
        pin = ["taskset", "-c", self.cpu[host]] if host in self.cpu else []
        return ["ip", "netns", "exec", self.ns[host], *pin, *cmd]

    def pids(self, host: str) -> list[int]:
        proc = run(["ip", "netns", "pids", self.ns[host]], check=False)
        return [int(p) for p in proc.stdout.split()] if proc.returncode == 0 else []

    def link_stats(self) -> dict:
        """Bytes and packets the ground's end of the link received and sent."""
        proc = run(["ip", "-n", self.ns["ground"], "-s", "-j", "link", "show", "dev", self.dev["ground"]], check=False)
        try:
            s = json.loads(proc.stdout)[0]["stats64"]
            return {"rx_bytes": s["rx"]["bytes"], "rx_packets": s["rx"]["packets"],
                    "tx_bytes": s["tx"]["bytes"], "tx_packets": s["tx"]["packets"],
                    "rx_dropped": s["rx"]["dropped"], "tx_dropped": s["tx"]["dropped"]}
        except (ValueError, KeyError, IndexError):
            return {}

    def tcp_states(self, host: str) -> dict[str, int]:
        """The host's TCP sockets towards the other host, by state (ESTAB, SYN-SENT, ...), and its UDP
        sockets to it with datagrams waiting unread ("UDP unread")."""
        other = GROUND_IP if host == "vehicle" else VEHICLE_IP
        got: dict[str, int] = {}
        for line in run(["ip", "netns", "exec", self.ns[host], "ss", "-Htan"], check=False).stdout.splitlines():
            if other in line:
                got[line.split()[0]] = got.get(line.split()[0], 0) + 1
        for line in run(["ip", "netns", "exec", self.ns[host], "ss", "-Huan"], check=False).stdout.splitlines():
            if other in line and int(line.split()[1]) > 0:   # datagrams from the other host nobody reads
                got["UDP unread"] = got.get("UDP unread", 0) + 1
        return got

    def sockets(self) -> dict:
        """What crosses the link and whether anything listens for multicast scouting."""
        out = {}
        for host in ("vehicle", "ground"):
            ns = self.ns[host]
            tcp = run(["ip", "netns", "exec", ns, "ss", "-Htn", "state", "established"], check=False).stdout
            udp = run(["ip", "netns", "exec", ns, "ss", "-Huan"], check=False).stdout
            groups = run(["ip", "-n", ns, "maddr", "show"], check=False).stdout
            other = GROUND_IP if host == "vehicle" else VEHICLE_IP
            out[host] = {
                "tcp_across_link": sum(1 for line in tcp.splitlines() if other in line),
                "tcp_local": sum(1 for line in tcp.splitlines() if other not in line),
                "udp": [" -> ".join(line.split()[3:5]) for line in udp.splitlines()],
                "udp_7446": sum(1 for line in udp.splitlines() if line.split()[3].endswith(":7446")),
                "scouting_group_joined": SCOUTING_GROUP in groups,
            }
        return out

    def close(self) -> list[str]:
        """Stop whatever still runs in the namespaces (SIGINT, then SIGKILL), delete them (the
        veth pairs go with them). Returns what was left over (should be nothing)."""
        self.stop_forwarder()
        for sig, wait_s in ((signal.SIGINT, 10.0), (signal.SIGKILL, 5.0)):
            pids = [p for h in self.ns for p in self.pids(h)] if self.created else []
            if not pids:
                break
            for p in pids:
                try:
                    os.kill(p, sig)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + wait_s
            while time.monotonic() < deadline and any(_running(p) for p in pids):
                time.sleep(0.1)
        for ns in reversed(self.created):
            run(["ip", "netns", "del", ns], check=False)
        left = [ns for ns in self.created if ns in run(["ip", "netns", "list"], check=False).stdout.split()]
        links = run(["ip", "-o", "link", "show"], check=False).stdout
        left += [d for d in [*self.dev.values(), *self.link_dev.values()] if f" {d}@" in links or f" {d}:" in links]
        return left


def _running(pid: int) -> bool:
    """Alive and not a zombie (a process `zenpilot up -d` left is not our child: we cannot reap it)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except (OSError, IndexError):
        return False


# ---------------------------------------------------------------- the flights
def flight_metrics(log_path: Path, info: dict, vehicle_id: int, full: bool = False):
    """deploy.metrics on the log up to the simulator's last IMU sample. What the services publish
    after it is the stack winding down, not the flight: the motors re-sending their last command
    (the output age grows by seconds), the EKF predicting without IMU (its error grows by metres);
    one `zenpilot down` stops them one by one. Returns the metrics and how many messages were left
    out (full: also the log and the simulator's first and last IMU sample time)."""
    log = read_log(log_path)
    imu = log.get(f"zp/{vehicle_id}/sim/imu") or []
    t_end = max((x["header"]["t_s"] for x in imu), default=float("inf"))
    t_start = min((x["header"]["t_s"] for x in imu), default=-float("inf"))
    trimmed = {k: [x for x in v if x["header"]["t_s"] <= t_end] for k, v in log.items()}
    left_out = sum(len(v) for v in log.values()) - sum(len(v) for v in trimmed.values())
    m = compute_metrics(trimmed, info, vehicle_id)
    m["left_out_after_sim"] = left_out
    return (m, left_out, log, (t_start, t_end)) if full else (m, left_out)


def zenpilot(hosts: TwoHosts, host: str, out: Path, *args: str, timeout: float = 120) -> tuple[str, float]:
    env = dict(os.environ, ZENPILOT_STATE_DIR=str(out / host / "state"))
    argv = hosts.argv(host, [sys.executable, "-m", "deploy.cli", *args])
    t0 = time.monotonic()
    proc = run(argv, check=False, cwd=ROOT, env=env, timeout=timeout)
    took = time.monotonic() - t0
    if proc.returncode != 0:
        raise BenchError(f"{host}: `zenpilot {shlex.join(args)}` failed (status {proc.returncode}): "
                         f"{(proc.stderr or proc.stdout).strip()}")
    return proc.stdout.strip(), took


def incoming_keys(stack, host_machines: set[str]) -> list[str]:
    """Key expressions of what the services *not* on `host_machines` publish (their topics and
    health): what crosses the link towards the host."""
    v = stack.vehicle_id
    names = [n for n, s in stack.services.items() if s.machine not in host_machines]
    keys = {f"zp/{v}/{t}" for n in names for t in PUBLISHES.get(n, ()) if not t.startswith("@")}
    return sorted(keys | {f"zp/{v}/{n}/health" for n in names})


class Probes:
    """bench/support/linkprobe.py on each host that receives keys from the other: arrival times."""

    def __init__(self, hosts: TwoHosts, out: Path):
        self.hosts, self.out, self.procs = hosts, out, {}

    def start(self, host: str, endpoint: str, keys: list[str], stack: str | None = None,
              log_keys: list[str] | None = None) -> None:
        """`stack`: a secured stack file, whose login the probe presents (the host's machine's);
        `log_keys`: also written, decoded, into <out>/<host>/witness.mcap (the host's own record)."""
        if not keys:
            return
        path = self.out / host / "linkprobe.json"
        path.unlink(missing_ok=True)
        log = open(self.out / host / "linkprobe.log", "w")
        self.procs[host] = subprocess.Popen(
            self.hosts.argv(host, [sys.executable, "-m", "bench.support.linkprobe", "-e", endpoint,
                                   *(["--stack", stack] if stack else []), "--out", str(path),
                                   *([f"--log={self.out / host / WITNESS}", *(f"--log-key={k}" for k in log_keys)]
                                     if log_keys else []), *keys]),
            cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 20.0
        while "linkprobe: listening" not in (self.out / host / "linkprobe.log").read_text():
            if self.procs[host].poll() is not None or time.monotonic() > deadline:
                raise BenchError(f"{host}: the link probe did not start: "
                                 f"{(self.out / host / 'linkprobe.log').read_text().strip()}")
            time.sleep(0.05)

    def stop(self) -> dict[str, dict]:
        """{host: {key: [[arrival, t_s, seq, source], ...]}}"""
        got = {}
        for host, proc in self.procs.items():
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(30)
                got[host] = json.loads((self.out / host / "linkprobe.json").read_text())
            except (subprocess.TimeoutExpired, OSError, ValueError) as exc:
                print(f"two_hosts: the {host} link probe gave nothing: {exc}", file=sys.stderr)
                proc.kill()
                proc.wait()
        self.procs = {}
        return got


def fault_seen(out: Path, fault: dict) -> dict:
    """How long after the SIGSTOP each host's supervisor reported the service (its first event
    after it): the vehicle's own ("stopped", from /proc), the ground's across the link ("stuck",
    from its beats)."""
    seen = {}
    for host, folder in (("vehicle", out / "vehicle"), ("ground", out / "ground")):
        try:
            record = json.loads((folder / "supervisor.json").read_text())
        except (OSError, ValueError):
            continue
        for e in record["events"]:
            t = record["started_unix"] + e["t_s"] - fault["stopped_unix"]
            if e["service"] == fault["service"] and e["event"] in ("stopped", "stuck") and t >= -0.05:
                seen[host] = {"after_s": round(t, 3), "event": e["event"], "detail": e["detail"]}
                break
    return seen


def start_flood(hosts: TwoHosts, out: Path, spec: tuple[int, float, str | None], router: str,
                max_hz: float) -> dict:
    """The flood's sink on the ground, then its publisher on the vehicle (both on their host's
    router; the publisher's session capped as the vehicle's services' are: `max_hz`)."""
    size, hz, priority = spec
    base = [sys.executable, "-m", "bench.support.flooder", "--connect", router]
    procs = {"sink": subprocess.Popen(hosts.argv("ground", base + ["--sink"]), cwd=ROOT, stdout=subprocess.PIPE,
                                      text=True)}
    if procs["sink"].stdout.readline().strip() != "flooder: sink listening":
        raise BenchError("the flood's sink did not start")
    procs["source"] = subprocess.Popen(
        hosts.argv("vehicle", base + ["--bytes", str(size), "--hz", str(hz), "--max-hz", str(max_hz)] + (["--priority", priority] if priority else [])),
        cwd=ROOT, stdout=subprocess.PIPE, text=True)
    return procs


def stop_flood(procs: dict) -> dict:
    """What the flood's two ends printed: {"source": {...}, "sink": {...}}."""
    got = {}
    for name in ("source", "sink"):
        proc = procs.get(name)
        if proc is None:
            continue
        proc.terminate()
        try:
            lines = proc.communicate(timeout=20)[0].strip().splitlines()
            got[name] = json.loads(lines[-1]) if lines else {}
        except (subprocess.TimeoutExpired, ValueError) as exc:
            proc.kill()
            proc.wait()
            got[name] = {"error": str(exc)}
    return got


def stop_trace(taps: dict, cpu, arrivals: dict, out: Path) -> dict:
    """--trace: the wiretaps' frames matched to the probes' rows (bench.support.trace.split), and
    the CPU each process and thread took over the flight."""
    wire = {}
    for host, proc in taps.items():
        proc.terminate()
        try:
            proc.communicate(timeout=60)
            wire[host] = json.loads((out / host / "wiretap.json").read_text())
        except (subprocess.TimeoutExpired, OSError, ValueError) as exc:
            print(f"two_hosts: the {host} wiretap gave nothing: {exc}", file=sys.stderr)
            proc.kill()
            proc.wait()
    other = {"ground": "vehicle", "vehicle": "ground"}
    result = {"cpu": cpu.stop(), "wiretap": {h: {"frames": w["frames"], "dropped_by_kernel": w["dropped_by_kernel"]}
                                             for h, w in wire.items()}, "split": {}}
    result["stalls"] = {}
    for host, rows in arrivals.items():   # the receiving host's probe: sent from the other host's end
        if host in wire and other[host] in wire:
            result["split"].update(trace_split(rows, wire[other[host]]["out"], wire[host]["in"]))
            result["stalls"][other[host]] = trace_stalls(rows, wire[other[host]]["out"])
    return result


def trace_text(trace: dict, keys: list[str]) -> str:
    lines = ["trace: each control message's latency split at the link's ends (kernel timestamps), ms "
             "p50 / p99 [mean over the end-to-end top 1 %]:"]
    for key in keys:
        r = trace["split"].get(key)
        if r:
            lines.append(f"  {key}: " + "; ".join(f"{n} {r[n]['p50']} / {r[n]['p99']} [{r['tail_1pct_mean'][n]}]"
                                                  for n in ("end_to_end", "sender_host", "link", "receiver_host"))
                         + f" ({r['matched']} of {r['of']} matched)")
    for host, st in trace.get("stalls", {}).items():
        lines.append(f"  stalls on the {host}'s host: {st['windows']} ({st['per_s']}/s) moments when messages of 3 keys "
                     f"or more were all held over {st['over_ms']:g} ms before the link, held p50 {st['held_ms']['p50']} / "
                     f"max {st['held_ms']['max']} ms ({st['late']} of {st['messages']} messages over {st['over_ms']:g} ms)")
    c = trace["cpu"]
    lines.append(f"CPU over {c['wall_s']} s, % of one core: the machine busy {c['machine_busy_pct']} of "
                 f"{100 * c['machine_cores']}: the hosts " + ", ".join(f"{k} {v}" for k, v in c["hosts_pct"].items())
                 + f"; the kernel's interrupts {c['interrupts_pct']}; processes outside the hosts {c['outside_pct']} ("
                 + ", ".join(f"{k} {v}" for k, v in c["outside_top"].items()) + ")")
    lines.append("  " + ", ".join(f"{k} {v}" for k, v in c["processes_pct"].items()
                                  if v >= 1.0 and not k.startswith("outside: ")))
    return "\n".join(lines)


def _q(xs: list[float], f: float) -> float | None:
    return xs[min(len(xs) - 1, int(f * len(xs)))] if xs else None


def seq_loss(seqs) -> tuple[int, int]:
    """(lost, expected) from one sender's sequence numbers: the gaps between the first and the last."""
    u = sorted(set(seqs))
    if not u:
        return 0, 0
    expected = u[-1] - u[0] + 1
    return expected - len(u), expected


def link_keys(log: dict, probes: dict, stack, t_window: tuple[float, float] | None) -> dict:
    """Per key that crossed the link: latency (arrival - header time, ms, real time only) from the
    receiving host's probe, and the messages lost (sequence gaps per sender) from the ground's flight
    log for the vehicle's keys and from the vehicle's probe for the ground's (the vehicle has no log)."""
    ground = {n for n, s in stack.services.items() if s.machine == "ground"}
    out: dict[str, dict] = {}
    lo, hi = t_window or (-float("inf"), float("inf"))
    for host, records in probes.items():
        for key, rows in records.items():
            rows = [r for r in rows if lo <= r[1] <= hi]
            lat = sorted(1e3 * (r[0] - r[1]) for r in rows)
            by_source: dict[str, list[int]] = {}
            for r in rows:
                by_source.setdefault(r[3], []).append(r[2])
            lost = [seq_loss(v) for v in by_source.values()]
            out[key] = {"to": host, "n": len(rows), "latency_ms": {"p50": _q(lat, 0.5), "p99": _q(lat, 0.99),
                                                                    "max": lat[-1] if lat else None},
                        "lost_probe": sum(x[0] for x in lost), "expected_probe": sum(x[1] for x in lost)}
    lost = log_loss(log, (lo, hi))
    for key, msgs in log.items():
        sources = {m["header"]["source"] for m in msgs}
        if not sources or sources <= ground or not lost[key][1]:   # the ground's own, or nothing in the flight
            continue
        row = out.setdefault(key, {"to": "ground"})
        row["lost"], row["expected"] = lost[key]
    for row in out.values():   # the vehicle's incoming keys: no log there, the probe's count stands
        if "lost" not in row:
            row["lost"], row["expected"] = row.get("lost_probe", 0), row.get("expected_probe", 0)
    return out


def wait_beating(supervisor_json: Path, name: str, timeout_s: float) -> float:
    """Until the service's loop beats (its supervisor counts the beats: deploy/supervisor.py)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        try:
            if json.loads(supervisor_json.read_text())["services"][name]["beats"] > 0:
                return time.monotonic() - t0
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.2)
    raise BenchError(f"{name} did not start its loop within {timeout_s:.0f} s (see {supervisor_json.parent / 'logs'})")


def fly_two_hosts(hosts: TwoHosts, mission, args, out: Path) -> dict:
    timing, stack_path = {}, STACKS[args.placement]
    split = load_stack(stack_path)
    lockstep = ["--lockstep"] if args.lockstep else []
    for host in ("vehicle", "ground"):
        (out / host).mkdir(parents=True, exist_ok=True)
        # a previous run's results and `up -d` state (its pids) must not be taken for this run's
        shutil.rmtree(out / host / "state", ignore_errors=True)
        for name in (LOG_NAME, "metrics.json", "linkprobe.json", "supervisor.json"):
            (out / host / name).unlink(missing_ok=True)
    # --secure: each host its own secured stack file and its share of the keys; else the one file
    stacks = ({h: str(p) for h, p in secure_stacks(args.placement, out, args.secure).items()} if args.secure
              else dict.fromkeys(("vehicle", "ground"), str(stack_path)))
    # the vehicle placement: one router on the vehicle's link address, everyone its client; the
    # ground placement: each host's services on its own router (the stack's), the routers linked
    router = ROUTER if args.placement == "vehicle" else LOCAL_ROUTER
    _, timing["up vehicle-router s"] = zenpilot(hosts, "vehicle", out, "up", "-d", "--stack", stacks["vehicle"],
                                                "--machine", "vehicle-router", "--router", router,
                                                # its own run folder: one supervisor record (supervisor.json) per machine
                                                "--out", str(out / "vehicle" / "router"))
    # the mission: the ground's planner flies it (ground placement), the recorder draws its airframe
    ground_args = ["--mission", str(mission.path), "--seed", str(args.seed), *lockstep]
    _, timing["up ground s"] = zenpilot(hosts, "ground", out, "up", "-d", "--stack", stacks["ground"], "--machine", "ground",
                                        "--router", router, "--out", str(out / "ground"), *ground_args, timeout=300)
    if not args.lockstep and "planner" in split.services and split.services["planner"].machine == "ground":
        # real time: the vehicle's simulator starts flying at once; the ground's planner must be
        # flying-ready first (its JAX build and flip prediction take 5-30 s on a loaded machine),
        # as an operator waits for `zenpilot status` to show it running
        timing["ground planner ready s"] = wait_beating(out / "ground" / "supervisor.json", "planner", 180.0)
    probes = Probes(hosts, out)
    if not args.lockstep:   # arrival - header time is a latency only when headers are wall-clock times
        probes.start("ground", router, incoming_keys(split, {"ground"}), stacks["ground"] if args.secure else None)
        probes.start("vehicle", router, incoming_keys(split, {"vehicle", "vehicle-router"}),
                     stacks["vehicle"] if args.secure else None,
                     [f"zp/{split.vehicle_id}/{k}" for k in WITNESS_KEYS] if args.outage else None)
    taps, cpu = {}, None
    if args.trace and not args.lockstep:   # --trace: the control frames at each end of the link, CPU per thread
        for host in ("vehicle", "ground"):
            (out / host / "wiretap.json").unlink(missing_ok=True)
            taps[host] = subprocess.Popen(hosts.argv(host, [sys.executable, "-m", "bench.support.wiretap",
                                                            hosts.dev[host], "--out", str(out / host / "wiretap.json")]),
                                          cwd=ROOT, stdout=subprocess.PIPE, text=True)
            if not taps[host].stdout.readline().startswith("wiretap:"):
                raise BenchError(f"{host}: the wiretap did not start")
        cpu = CpuWatch({h: ns for h, ns in hosts.ns.items()})
        cpu.start()
    cap = 0.0 if args.rogue else split.machines[split.service("sim").machine].bulk_max_hz   # the camera's machine
    flood = start_flood(hosts, out, args.flood, router, cap) if args.flood else {}
    t_fly = time.monotonic()
    _, timing["up vehicle s"] = zenpilot(hosts, "vehicle", out, "up", "-d", "--stack", stacks["vehicle"], "--machine", "vehicle",
                                         "--router", router, "--out", str(out / "vehicle"), "--seed", str(args.seed),
                                         "--mission", str(mission.path), "--set", "sim.stop_after_mission=true",
                                         *lockstep, timeout=300)
    def service_pids() -> dict[str, int]:
        """As each host's `up -d` keeps them: a service its supervisor restarted has a new pid."""
        pids = {}
        for host, machine in (("vehicle", "vehicle"), ("ground", "ground")):
            state, = (out / host / "state").glob(f"*/up-{machine}.json")   # one folder per stack (its router)
            try:
                pids.update(json.loads(state.read_text())["pids"])
            except ValueError:   # being rewritten (atomically, but read between two checks): next time
                pass
        pids.pop("router", None)   # the ground placement's ground router: not a service
        return pids

    pids = service_pids()
    limit = mission.timeout_s * (20.0 if args.lockstep else 1.5) + 60.0
    deadline, sampled, status = time.monotonic() + limit, None, ""
    down_since: dict[str, float] = {}
    fault = {"service": args.stop[0], "at_s": args.stop[1], "for_s": args.stop[2]} if args.stop else None
    outage = {"at_s": args.outage[0], "for_s": args.outage[1]} if args.outage else None
    while _running(pids["sim"]):
        if outage is not None and "restored_unix" not in outage:   # --outage: cut, then restore, the link
            if "first_tick_unix" not in outage:
                first = re.search(r"first tick at ([0-9.]+)", _read(out / "vehicle" / "logs" / "sim.log"))
                if first:
                    outage["first_tick_unix"] = float(first.group(1))
            elif "cut_unix" not in outage and time.time() >= outage["first_tick_unix"] + outage["at_s"]:
                outage["cut_unix"] = hosts.set_link(False)
                print(f"two_hosts: the link cut {outage['cut_unix'] - outage['first_tick_unix']:.2f} s after the "
                      f"simulator's first tick", flush=True)
            elif "cut_unix" in outage and time.time() >= outage["cut_unix"] + outage["for_s"]:
                outage["restored_unix"] = hosts.set_link(True)
                print(f"two_hosts: the link restored after {outage['restored_unix'] - outage['cut_unix']:.2f} s",
                      flush=True)
        if outage is not None and "cut_unix" in outage and time.time() < outage.get("restored_unix", float("inf")) + 20:
            # the ground's TCP links to the vehicle while cut and after: each change of their states
            states = hosts.tcp_states("ground")
            tcp = outage.setdefault("ground_tcp", [])
            if not tcp or tcp[-1][1] != states:
                tcp.append([round(time.time() - outage["cut_unix"], 2), states])
        if fault is not None:   # --stop: SIGSTOP a vehicle service, SIGCONT it later (if still there)
            into = time.monotonic() - t_fly
            if "stopped_unix" not in fault and into >= fault["at_s"]:
                fault["pid"] = pids[fault["service"]]
                os.kill(fault["pid"], signal.SIGSTOP)
                fault["stopped_unix"] = time.time()
            elif "stopped_unix" in fault and "continued" not in fault and into >= fault["at_s"] + fault["for_s"]:
                try:
                    os.kill(fault["pid"], signal.SIGCONT)
                except ProcessLookupError:   # its supervisor killed it (a hang) and restarted it
                    pass
                fault["continued"] = True
        # a service not running for RESTART_GRACE_S on end: its supervisor did not bring it back
        # (a kill and restart takes it a back-off and a start; the state file then has the new pid)
        now = time.monotonic()
        if any(not _running(p) for p in pids.values()):
            pids = service_pids()
        for n, pid in pids.items():
            if n == "sim" or _running(pid):
                down_since.pop(n, None)
            else:
                down_since.setdefault(n, now)
        dead = [n for n, t in down_since.items() if now - t > RESTART_GRACE_S]
        if dead:
            raise BenchError(f"service(s) stopped during the flight: {', '.join(dead)} "
                             f"(logs in {out / 'vehicle' / 'logs'} and {out / 'ground' / 'logs'})")
        if time.monotonic() > deadline:
            if outage is None or "restored_unix" not in outage:
                raise BenchError(f"the flight did not end within {limit:.0f} s")
            # after an outage: what crossed and what the vehicle did are the finding (a link back
            # that routes nothing never brings the ground's "mission completed" to the simulator)
            print(f"two_hosts: error: the flight did not end within {limit:.0f} s; stopping it", file=sys.stderr)
            outage["flight_ended"] = False
            break
        # --outage: not while a cut is due or on (`zenpilot status` holds this loop for seconds
        # under load: a cut asked for 3 s after the first tick once came at 5.75 s)
        cut_near = outage is not None and time.time() < outage.get("restored_unix", float("inf")) + 3.0 and (
            "first_tick_unix" not in outage or time.time() > outage["first_tick_unix"] + outage["at_s"] - 5.0)
        if sampled is None and time.monotonic() - t_fly > 5.0 and not cut_near:
            sampled = hosts.sockets()  # mid-flight: every service linked
            # liveliness and health of every service as the ground sees them across the link
            try:
                status, _ = zenpilot(hosts, "ground", out, "status", "--stack", stacks["ground"], timeout=60)
            except (BenchError, subprocess.TimeoutExpired) as exc:
                status = f"(zenpilot status failed: {exc})"
        time.sleep(0.1)
    timing["flight wall s"] = time.monotonic() - t_fly
    if sampled is None:
        sampled = hosts.sockets()
    time.sleep(0.3)
    arrivals = probes.stop()
    flooded = stop_flood(flood)
    trace = stop_trace(taps, cpu, arrivals, out) if cpu is not None else None
    # as `zenpilot fly` stops them: the vehicle's services first (stopped later, the recorder would
    # log the motors re-sending their last command after the simulator ended), then the ground,
    # whose recorder writes the flight log when stopped
    _, timing["down vehicle s"] = zenpilot(hosts, "vehicle", out, "down", timeout=120)
    _, timing["down ground s"] = zenpilot(hosts, "ground", out, "down", timeout=120)
    link = hosts.link_stats()
    forwarder = hosts.stop_forwarder()
    log_path = out / "ground" / LOG_NAME
    if not log_path.exists():
        raise BenchError(f"no flight log on the ground side ({log_path}); see {out / 'ground' / 'logs' / 'recorder.log'}")
    t0 = time.monotonic()
    info = {"mission": mission.name, "mode": "lockstep" if args.lockstep else "realtime", "seed": args.seed,
            "vehicle": mission.vehicle}
    metrics, _, log, window = flight_metrics(log_path, info, split.vehicle_id, full=True)
    timing["metrics s"] = time.monotonic() - t0
    p = hosts.profile
    supervised = {}
    for host in ("vehicle", "ground"):   # what each host's supervisor did: restarts, hangs
        try:
            for name, w in json.loads((out / host / "supervisor.json").read_text())["services"].items():
                if w["restarts"] or w["hangs"]:   # (an exit alone: the simulator ending the flight)
                    supervised[name] = {k: w[k] for k in ("restarts", "hangs", "silences", "stucks", "exits")}
        except (OSError, ValueError, KeyError):
            pass
    if fault is not None and "stopped_unix" in fault:
        fault["seen_s"] = fault_seen(out, fault)
    if outage is not None:
        outage.update(outage_report(out, outage, arrivals, info, split.vehicle_id))
    metrics["two_hosts"] = {"link": link, "sockets": sampled, "timing": timing, "status": status, "fault": fault,
                            "supervisor": supervised, "flood": flooded, "outage": outage, "trace": trace,
                            "placement": args.placement, "stack": stack_path.name, "lockstep": args.lockstep,
                            "secure": args.secure,
                            "profile": dataclasses.asdict(p), "emulator": hosts.method, "forwarder": forwarder,
                            "keys": link_keys(log, arrivals, split, window),
                            "log_on_vehicle_side": (out / "vehicle" / LOG_NAME).exists(),
                            "log_bytes": log_path.stat().st_size}
    if metrics.get("duration_s"):
        metrics["two_hosts"]["wall_per_sim_s"] = timing["flight wall s"] / metrics["duration_s"]
    (out / "ground" / "metrics.json").write_text(json.dumps(metrics, indent=2, sort_keys=True) + "\n")
    return metrics


def _read(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""


ROUTER_LINK_LINE = re.compile(r"zenpilot-router: (.*(?:link to the other host|the machine's router|listening again)"
                              r".*?)(?: \(at ([0-9.]+)\))?$")


def _lost_in_outage(rows: list, cut: float, back: float | None) -> int | None:
    """The samples sent from the cut until `back` (the sample time of the first one sent after the
    restore that came) that never came, per sender: the outage's share of the key's losses (the
    rest is the link's own)."""
    if back is None:
        return None
    lost = 0
    for source in {r[3] for r in rows}:
        mine = sorted((r[2], r[1]) for r in rows if r[3] == source)
        before = [q for q, t in mine if t < cut]
        after = [q for q, t in mine if t >= back]
        if before and after:
            inside = sum(1 for q, t in mine if cut <= t < back)
            lost += after[0] - before[-1] - 1 - inside
    return lost


def outage_report(out: Path, outage: dict, arrivals: dict, info: dict, vehicle_id: int) -> dict:
    """--outage: per key that crossed (the probes' arrivals), when it came last before the cut and
    first after the restore, relative to them (s); the routers' link lines; the vehicle's own record."""
    got: dict = {"keys": {}, "routers": {}}
    cut, restored = outage.get("cut_unix"), outage.get("restored_unix")
    if cut is None:
        got["error"] = "the flight ended before the cut"
        return got
    if "first_tick_unix" in outage:
        got["cut_after_first_tick_s"] = round(cut - outage["first_tick_unix"], 3)
    for host, records in arrivals.items():
        for key, rows in records.items():
            before = [r[0] for r in rows if r[0] <= cut]
            # what arrived with the link down: what was in flight at the cut (the link's delay), else nothing
            during = [r for r in rows if cut + 0.2 < r[0] < (restored or float("inf"))]
            after = [r for r in rows if restored is not None and r[0] >= restored]
            got["keys"][key] = {
                "to": host, "last_before_cut_s": round(before[-1] - cut, 3) if before else None,
                "during": len(during),
                "resumed_after_restore_s": round(after[0][0] - restored, 3) if after else None,
                "gap_s": round(after[0][0] - before[-1], 3) if after and before else None,
                # sent before the restore, delivered after it: held by a TCP stream, or by the
                # kernel while it resolved the other host's address again (its neighbour queue)
                "sent_before_restore_after_it": sum(1 for r in after if r[1] < restored),
                "oldest_after_restore_s": max((round(r[0] - r[1], 3) for r in after if r[1] < restored), default=None),
                "first_age_after_restore_s": round(after[0][0] - after[0][1], 3) if after else None,
                "lost_in_outage": _lost_in_outage(rows, cut, min((r[1] for r in after if r[1] >= restored),
                                                                 default=None))}
    for host, log in (("ground", out / "ground" / "logs" / "router.log"),
                      ("vehicle", out / "vehicle" / "router" / "logs" / "router.log")):
        lines = []
        for line in _read(log).splitlines():
            m = ROUTER_LINK_LINE.search(line)
            if m:
                lines.append({"line": m.group(1), "after_cut_s": round(float(m.group(2)) - cut, 3) if m.group(2) else None})
        got["routers"][host] = lines
    witness = out / "vehicle" / WITNESS
    if witness.exists():
        try:
            m, _ = flight_metrics(witness, info, vehicle_id)
            got["vehicle"] = {k: m.get(k) for k in ("completed", "crashed", "crash_reason", "mission_state",
                                                    "failsafes", "max_tilt_deg", "duration_s")}
            log = read_log(witness)
            truth = [x for x in log.get(f"zp/{vehicle_id}/sim/truth", [])]
            z = [(x["header"]["t_s"], x["position_m"][2]) for x in truth]
            if z:
                got["vehicle"]["altitude_at_cut_m"] = min(z, key=lambda p: abs(p[0] - cut))[1]
                got["vehicle"]["min_altitude_cut_to_restore_m"] = min(
                    (h for t, h in z if cut <= t <= (restored or float("inf"))), default=None)
                if restored is not None:
                    got["vehicle"]["altitude_at_restore_m"] = min(z, key=lambda p: abs(p[0] - restored))[1]
                    got["vehicle"]["max_altitude_after_restore_m"] = max((h for t, h in z if t >= restored), default=None)
        except Exception as exc:   # the record is a bench's: say why it is missing, keep the flight's figures
            got["vehicle"] = {"error": f"{type(exc).__name__}: {exc}"}
    return got


def fly_one_host(mission, args, out: Path) -> tuple[dict | None, float]:
    out.mkdir(parents=True, exist_ok=True)
    for name in (LOG_NAME, "metrics.json"):
        (out / name).unlink(missing_ok=True)
    argv = [sys.executable, "-m", "deploy.cli", "fly", "--stack", str(STACKS[args.placement]), "--mission",
            str(mission.path), "--seed", str(args.seed), "--out", str(out), "--no-plots",
            *(["--lockstep"] if args.lockstep else [])]
    t0 = time.monotonic()
    with open(out / "fly.out", "w") as f:
        proc = subprocess.Popen(argv, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT)
        try:
            proc.wait(timeout=mission.timeout_s * (20.0 if args.lockstep else 1.5) + 180)
        except BaseException:  # Ctrl-C reaches it too; SIGTERM or a timeout: tell it, it stops its services
            proc.send_signal(signal.SIGTERM)
            proc.wait(60)
            raise
    took = time.monotonic() - t0
    if not (out / LOG_NAME).exists():
        print(f"two_hosts: the one-host flight wrote no log (status {proc.returncode}, see {out / 'fly.out'})",
              file=sys.stderr)
        return None, took
    # as the two-host flight's: up to the simulator's end (metrics.json is `zenpilot fly`'s own, whole log)
    info = {"mission": mission.name, "mode": "lockstep" if args.lockstep else "realtime", "seed": args.seed,
            "vehicle": mission.vehicle}
    m, _, log, window = flight_metrics(out / LOG_NAME, info, load_stack(STACKS[args.placement]).vehicle_id, full=True)
    m["lost_per_key"] = {k: r for k, r in log_loss(log, window).items() if r[1]}
    return m, took


def log_loss(log: dict, window: tuple[float, float]) -> dict[str, tuple[int, int]]:
    """{key: (lost, expected)} from a flight log's sequence gaps, per sender, within the window."""
    lo, hi = window
    out = {}
    for key, msgs in log.items():
        by_source: dict[str, list[int]] = {}
        for m in msgs:
            if lo <= m["header"]["t_s"] <= hi:
                by_source.setdefault(m["header"]["source"], []).append(m["header"]["seq"])
        lost = [seq_loss(v) for v in by_source.values()]
        out[key] = (sum(x[0] for x in lost), sum(x[1] for x in lost))
    return out


def same_flight(a: Path, b: Path) -> dict:
    """Two lockstep logs, message for message, on every key but health (wall-clock rates) and what
    the MAVLink bridge sends (it lives on the wall clock, and `zenpilot fly --lockstep` leaves it
    out), every field but the wall-clock measurements (WALL_CLOCK_FIELDS)."""
    la, lb = read_log(a), read_log(b)
    skip = ("/health", "/mavlink/", "planner/command", "planner/mission", "param/set")
    keys = sorted(k for k in set(la) | set(lb) if not any(x in k for x in skip))

    def flight(msgs: list[dict]) -> list[dict]:   # the solver's time and overruns: never the same twice
        return [{f: v for f, v in m.items() if f not in WALL_CLOCK_FIELDS} for m in msgs]

    differ = [k for k in keys if flight(la.get(k, [])) != flight(lb.get(k, []))]
    return {"keys": len(keys), "messages": sum(len(la.get(k, [])) for k in keys), "differ": differ}


# ---------------------------------------------------------------- report
def _fmt(v, unit: str = "") -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.4g}{unit}"
    return f"{v}{unit}"


def planner_build_s(logs: Path) -> float | None:
    """The planner's JAX compile and warm-up before it flies (kept in a cache: the next run is quicker)."""
    try:
        text = (logs / "planner.log").read_text(errors="replace")
    except OSError:
        return None
    built = re.findall(r"built \(JAX compile and warm-up\) in ([0-9.]+) s", text)
    return sum(float(x) for x in built) if built else None


def table(two: dict, one: dict | None) -> str:
    def g(m, *path):
        for p in path:
            if not isinstance(m, dict):
                return None
            m = m.get(p)
        return m

    rows = [("completed", ("completed",)), ("crashed", ("crashed",)), ("mission state", ("mission_state",)),
            ("flown s", ("duration_s",)), ("hover position RMS m", ("position_rms_m",)),
            ("max position error m", ("max_position_error_m",)), ("max tilt deg (outside flips)", ("max_tilt_deg",)),
            ("estimate position RMS m", ("estimation", "position_rms_m")),
            ("estimate attitude RMS deg", ("estimation", "attitude_rms_deg")),
            ("imu->pwm p50 ms", ("latency_ms", "imu_to_pwm_p50")), ("imu->pwm p99 ms", ("latency_ms", "imu_to_pwm_p99")),
            ("imu->pwm max ms", ("latency_ms", "imu_to_pwm_max")),
            ("output age p99 ms", ("latency_ms", "output_age_p99")),
            ("rejected messages", ("rejected_total",)), ("planner JAX build s", ("planner_build_s",)),
            ("msgs after the sim's end (left out)", ("left_out_after_sim",))]
    rows += [(f"rate {s} Hz", ("rates_hz", s)) for s in SERVICES]
    if two.get("flip") or (one or {}).get("flip"):
        rows += [(f"flip {k}", ("flip", k)) for k in
                 ("completed", "aborted", "altitude_loss_m", "xy_drift_m", "recovery_s", "overshoot_deg",
                  "duration_s", "min_altitude_m", "hit_ground", "solves", "failed_solves", "solve_ms_p99")]
    lines = [f"{'':<36} {'two hosts':>12} {'one host':>12}"]
    for label, path in rows:
        lines.append(f"{label:<36} {_fmt(g(two, *path)):>12} {_fmt(g(one, *path)) if one else 'not flown':>12}")
    return "\n".join(lines)


def key_table(keys: dict, one: dict | None = None) -> str:
    """Per key that crossed the link: where to, messages, latency (arrival - header time), lost;
    and lost in the one-host flight's log."""
    one = (one or {}).get("lost_per_key", {})
    lines = [f"{'key':<26} {'to':<8} {'msgs':>6} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8} {'lost':>6} {'lost %':>7}"
             f" {'1 host %':>8}"]
    for key in sorted(keys, key=lambda k: (keys[k]["to"], k)):
        r, lat = keys[key], keys[key].get("latency_ms", {})
        if not r.get("expected") and not r.get("n"):
            continue
        pct = 100.0 * r["lost"] / r["expected"] if r.get("expected") else None
        one_pct = 100.0 * one[key][0] / one[key][1] if key in one else None
        lines.append(f"{key.split('/', 2)[-1]:<26} {r['to']:<8} {r.get('n', r.get('expected', 0)):>6} "
                     f"{_fmt(lat.get('p50')):>8} {_fmt(lat.get('p99')):>8} {_fmt(lat.get('max')):>8} "
                     f"{r['lost']:>6} {_fmt(pct):>7} {_fmt(one_pct):>8}")
    return "\n".join(lines)


def outage_text(o: dict) -> str:
    """--outage: the cut, each key's return, the routers' link lines, the vehicle's own record."""
    if "cut_unix" not in o:
        return f"outage: not made ({o.get('error', 'the flight ended first')})"
    lines = ["outage: THE FLIGHT DID NOT END (the simulator stopped by the bench at its limit)"] \
        if o.get("flight_ended") is False else []
    lines += [f"outage: the link cut {o.get('cut_after_first_tick_s', float('nan')):.2f} s after the simulator's first "
             f"tick for {o['restored_unix'] - o['cut_unix']:.2f} s" if "restored_unix" in o else
             "outage: the link cut and never restored (the flight ended first)"]
    lines.append(f"  {'key':<26} {'to':<8} {'last before cut s':>17} {'during':>6} {'back after restore s':>20} "
                 f"{'gap s':>7} {'sent before, late':>17} {'their oldest s':>14}")
    for key in sorted(o["keys"], key=lambda k: (o["keys"][k]["to"], k)):
        r = o["keys"][key]
        lines.append(f"  {key.split('/', 2)[-1]:<26} {r['to']:<8} {_fmt(r['last_before_cut_s']):>17} {r['during']:>6} "
                     f"{_fmt(r['resumed_after_restore_s']):>20} {_fmt(r['gap_s']):>7} "
                     f"{r['sent_before_restore_after_it']:>17} {_fmt(r['oldest_after_restore_s']):>14}")
    for host, said in o.get("routers", {}).items():
        for x in said:
            lines.append(f"  {host} router, {_fmt(x['after_cut_s'])} s after the cut: {x['line']}")
    if o.get("ground_tcp"):
        lines.append("  the ground's TCP links to the vehicle (s after the cut: states): " + "; ".join(
            f"{t:g}: {', '.join(f'{k} {n}' for k, n in st.items()) or 'none'}" for t, st in o["ground_tcp"]))
    v = o.get("vehicle")
    if v:
        lines.append("  the vehicle's own record: " + ", ".join(f"{k} {_fmt(val)}" for k, val in v.items()))
    return "\n".join(lines)


def resolve_mission(name: str):
    if not name.endswith(".toml") and not (ROOT / "deploy" / "missions" / f"{name}.toml").exists() \
            and (TEST_MISSIONS / f"{name}.toml").exists():
        name = str(TEST_MISSIONS / f"{name}.toml")
    mission = load_mission(name)
    return dataclasses.replace(mission, path=str(Path(mission.path).resolve()))


def stop_spec(text: str) -> tuple[str, float, float]:
    """SERVICE@T_S[:FOR_S] -> (service, t_s, for_s)."""
    service, _, rest = text.partition("@")
    at, _, length = rest.partition(":")
    try:
        out = service, float(at), float(length or 2.0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected SERVICE@T_S[:FOR_S], e.g. vision@8:2") from None
    if not service or out[1] < 0 or out[2] <= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: a service, T_S >= 0, FOR_S > 0")
    return out


def outage_spec(text: str) -> tuple[float, float]:
    """T_S:FOR_S -> (t_s, for_s)."""
    at, sep, length = text.partition(":")
    try:
        out = float(at), float(length)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected T_S:FOR_S, e.g. 8:3") from None
    if not sep or out[0] < 0 or out[1] <= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: T_S >= 0 and FOR_S > 0")
    return out


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mission", default="hover",
                   help="mission name (deploy/missions, then tests/integration/missions) or file (default hover)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--link", type=parse_profile, default=PROFILES["none"],
                   help="the link: none (a plain veth pair), lan (20 +- 5 ms, 1 %% loss each way), "
                        "bad (50 +- 20 ms, 5 %%), lan100 (lan of 100 Mbit/s), lan100-qos (the same, DSCP 46 "
                        "first), or DELAY_MS/JITTER_MS/LOSS_PCT")
    p.add_argument("--emulator", choices=("auto", "netem", "forwarder"), default="auto",
                   help="what impairs the link: tc netem where the kernel has it (auto), else the forwarder "
                        "(bench/support/linkemu.py in a third namespace)")
    p.add_argument("--link-seed", type=int, default=0, help="the forwarder's random seed (delays, losses)")
    p.add_argument("--link-rt", action="store_true",
                   help=f"the forwarder at real-time priority (SCHED_FIFO {LINK_FIFO}, above every service): a link "
                        f"that the hosts' CPU load does not slow, as hardware of its own")
    p.add_argument("--pin", action="store_true",
                   help="each host's processes on a core of its own (vehicle CPU 0, ground CPU 1; the forwarder "
                        "unpinned), as two machines would not share their CPUs")
    p.add_argument("--placement", choices=tuple(STACKS), default="vehicle",
                   help="vehicle: one router on the vehicle, only the recorder on the ground (two-hosts.toml); "
                        "ground: a router per host, planner, recorder and MAVLink on the ground (two-hosts-ground.toml); "
                        "telemetry: the same with the planner on the vehicle (two-hosts-telemetry.toml)")
    p.add_argument("--lockstep", action="store_true", help="lockstep instead of real time")
    p.add_argument("--secure", nargs="?", const="tls", choices=tuple(SECURE_LINKS), metavar="LINK",
                   help="the secured split (ground and telemetry placements): the stack file with [security], keys "
                        "by `zenpilot certs`, user/password and the vehicle router's access control, the routers' "
                        "link over mutual TLS only (tls, the default) or TLS + QUIC's datagrams where the plain "
                        "split has UDP (tls+quic)")
    p.add_argument("--out", help="output directory (default runs/two-hosts-<mission>-<placement>-<link>-<mode>-seed<N>)")
    p.add_argument("--no-one-host", action="store_true", help="skip the one-host comparison flight")
    p.add_argument("--flood", type=flood_spec, metavar="BYTES@HZ[:PRIORITY]",
                   help="real time: flood camera images across the link for the whole flight (e.g. 1048576@200)")
    p.add_argument("--stop", type=stop_spec, metavar="SERVICE@T_S[:FOR_S]",
                   help="real time: SIGSTOP a vehicle service T_S into the flight for FOR_S (default 2) s; "
                        "reports when each host's supervisor saw it")
    p.add_argument("--outage", type=outage_spec, metavar="T_S:FOR_S",
                   help="real time: cut the link both ways T_S after the simulator's first tick, restore it FOR_S "
                        "later; reports when each key crossed again")
    p.add_argument("--trace", action="store_true",
                   help="real time: where the control keys' time goes (wiretaps at the link's two ends, kernel "
                        "timestamps) and the CPU per process and thread over the flight")
    p.add_argument("--rogue", action="store_true",
                   help="the flood from outside the stack: its session not capped as the vehicle's services' are")
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    print("two_hosts: " + shlex.join([sys.executable, *sys.argv]), flush=True)
    try:
        mission = resolve_mission(args.mission)
    except MissionError as exc:
        print(f"two_hosts: error: {exc}", file=sys.stderr)
        return 2
    mode = "lockstep" if args.lockstep else "realtime"
    profile = args.link
    if args.secure and args.placement == "vehicle":
        print("two_hosts: error: --secure: the vehicle placement's ground recorder is a peer of the vehicle's "
              "router and its services listen on the link (an open split); use --placement ground or telemetry",
              file=sys.stderr)
        return 2
    if args.secure and args.flood:
        print("two_hosts: error: --secure with --flood: the secured split's access control never lets camera images "
              "cross the link (services/security.py)", file=sys.stderr)
        return 2
    out = Path(args.out or ROOT / "runs" / f"two-hosts-{mission.name}-{args.placement}-"
               f"{profile.name.replace('/', '_')}-{mode}{f'-secure-{args.secure}' if args.secure else ''}-seed{args.seed}").resolve()
    out.mkdir(parents=True, exist_ok=True)
    stack_path = STACKS[args.placement]
    default, split = load_stack(), load_stack(stack_path)
    drift = [n for n in set(default.services) | set(split.services)
             if n not in default.services or n not in split.services
             or dataclasses.replace(default.services[n], machine="") != dataclasses.replace(split.services[n], machine="")]
    if drift:
        print(f"two_hosts: warning: {stack_path.name} no longer matches the default stack for: "
              f"{', '.join(sorted(drift))}", file=sys.stderr)

    if args.outage and args.lockstep:
        print("two_hosts: error: --outage is real time (in lockstep a cut link stops the clock)", file=sys.stderr)
        return 2
    hosts = TwoHosts(str(os.getpid()), profile, args.emulator, args.link_seed, out, cuttable=bool(args.outage),
                     link_rt=args.link_rt, pin=args.pin)
    signal.signal(signal.SIGTERM, _stop)
    two = one = None
    code = 0
    try:
        hosts.open()
        print(f"two_hosts: {mission.name} ({mission.vehicle}, {mode}, seed {args.seed}); placement {args.placement} "
              f"({stack_path.name}{f', secured: {args.secure}, passwords, access control' if args.secure else ''}); vehicle netns {hosts.ns['vehicle']} {VEHICLE_IP} <-{hosts.method}-> ground netns "
              f"{hosts.ns['ground']} {GROUND_IP}; link {profile}; -> {out}; load average {os.getloadavg()[0]:.1f} "
              f"(other work on these {os.cpu_count()} CPUs skews a real-time flight)", flush=True)
        two = fly_two_hosts(hosts, mission, args, out)
    except (BenchError, subprocess.TimeoutExpired) as exc:
        print(f"two_hosts: error: {exc}", file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, Stop):
        print("two_hosts: interrupted; removing the namespaces", file=sys.stderr)
        code = 130
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # the clean-up is not to be interrupted
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        if hosts.created:
            for host in ("vehicle", "ground"):  # a graceful stop first: the recorder writes what it has
                if (out / host / "state").is_dir() and any((out / host / "state").glob("*/up-*.json")):
                    try:
                        zenpilot(hosts, host, out, "down", timeout=120)
                    except (BenchError, subprocess.TimeoutExpired) as exc:
                        print(f"two_hosts: clean-up: {exc}", file=sys.stderr)
        left = hosts.close()
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, _stop)
        if left:
            print(f"two_hosts: error: left behind: {', '.join(left)}", file=sys.stderr)
            code = 2
        elif hosts.created:
            print(f"two_hosts: removed {', '.join(hosts.created)} (and their veth pairs); no process left in them",
                  flush=True)
    if two is None:
        return code or 2

    one_took = None
    if not args.no_one_host:
        print(f"two_hosts: the same flight on one host: zenpilot fly ... (load average {os.getloadavg()[0]:.1f})",
              flush=True)
        try:
            one, one_took = fly_one_host(mission, args, out / "one-host")
        except (KeyboardInterrupt, Stop, subprocess.TimeoutExpired):
            print("two_hosts: one-host flight interrupted", file=sys.stderr)
    two["planner_build_s"] = planner_build_s(out / "vehicle" / "logs") or planner_build_s(out / "ground" / "logs")
    if one is not None:
        one["planner_build_s"] = planner_build_s(out / "one-host" / "logs")
    th = two["two_hosts"]
    if args.lockstep and one is not None:
        th["same_as_one_host"] = same_flight(out / "ground" / LOG_NAME, out / "one-host" / LOG_NAME)
    if one is not None:
        th["one_host"] = {k: one.get(k) for k in ("completed", "crashed", "position_rms_m", "max_position_error_m",
                                                    "duration_s", "flip", "lost_per_key", "latency_ms")}
        (out / "ground" / "metrics.json").write_text(json.dumps(two, indent=2, sort_keys=True) + "\n")
    print()
    print(table(two, one))
    print()
    print(f"across the link ({profile}, {th['emulator']}; latency = arrival - header time, real time only; "
          f"lost = sequence gaps up to the simulator's end):")
    print(key_table(th["keys"], one))
    print()
    if th.get("fault"):
        f = th["fault"]
        print(f"fault: {f['service']} stopped (SIGSTOP) {f['at_s']:g} s into the flight for {f['for_s']:g} s; seen by "
              + (", ".join(f"the {h}'s supervisor after {v['after_s'] * 1e3:.0f} ms ({v['event']}: {v['detail']})"
                           for h, v in f.get("seen_s", {}).items()) or "no supervisor"))
    if th.get("outage"):
        print(outage_text(th["outage"]))
    if th.get("trace"):
        print(trace_text(th["trace"], sorted(th["trace"]["split"])))
    t = th["timing"]
    if th["status"]:
        print("`zenpilot status` on the ground, mid-flight (the recorder does not log its own health):")
        print("  " + th["status"].replace("\n", "\n  "))
    print("two hosts, wall s: " + ", ".join(f"{k[:-2]} {v:.1f}" for k, v in t.items())
          + (f"; one host: `zenpilot fly` {one_took:.1f}" if one_took else "")
          + (f"; {th['wall_per_sim_s']:.2f} s of wall time per simulated s" if th.get("wall_per_sim_s") else ""))
    if th.get("supervisor"):
        print("supervisors: " + "; ".join(f"{n} {w}" for n, w in th["supervisor"].items()))
    if "same_as_one_host" in th:
        same = th["same_as_one_host"]
        print(f"lockstep: {same['messages']} messages on {same['keys']} keys (health and MAVLink aside) "
              + ("identical to the one-host flight's" if not same["differ"] else
                 f"DIFFER from the one-host flight's on {', '.join(same['differ'])}"))
    link, flight_s = th["link"], t["flight wall s"]
    if link:
        print(f"link (ground end): received {link['rx_bytes'] / 1e6:.1f} MB in {link['rx_packets']} packets, "
              f"sent {link['tx_bytes'] / 1e6:.1f} MB in {link['tx_packets']} packets "
              f"(~{8 * link['rx_bytes'] / 1e6 / max(flight_s, 1e-9):.1f} Mbit/s to the ground over the flight)")
    if th["forwarder"]:
        f = th["forwarder"]
        print(f"forwarder: {f['cpu_s']:.1f} CPU s over {f['wall_s']:.0f} s, {f['cpu_us_per_frame']} us per frame; " +
              "; ".join(f"{k}: {d['received']} frames, {d['dropped']} dropped, delay given p50 {d['delay_ms']['p50']} "
                        f"p99 {d['delay_ms']['p99']} ms" for k, d in f["directions"].items()))
    for host, s in th["sockets"].items():
        print(f"{host}: {s['tcp_across_link']} TCP connections across the link, {s['tcp_local']} on its loopback; "
              f"UDP sockets {s['udp'] or 'none'}; on port 7446: {s['udp_7446']}; "
              f"scouting group {SCOUTING_GROUP} joined: {'yes' if s['scouting_group_joined'] else 'no'}")
    print(f"flight log: {out / 'ground' / LOG_NAME} ({th['log_bytes'] / 1e6:.1f} MB, on the ground side; "
          f"on the vehicle side: {'yes' if th['log_on_vehicle_side'] else 'none'}); metrics: "
          f"{out / 'ground' / 'metrics.json'} (plots: zenpilot report {out / 'ground'})")
    judged = two
    if (th.get("outage") or {}).get("flight_ended") is False:
        return code or 1
    if (th.get("outage") or {}).get("vehicle", {}).get("crashed") is not None:
        # the ground's log has the outage's gap (and samples from it delivered late): a failsafe
        # landing in it may read as "motors cut in the air"; the vehicle's own record has it all
        judged = th["outage"]["vehicle"]
    return code or (0 if judged.get("completed") and not judged.get("crashed") else 1)


if __name__ == "__main__":
    raise SystemExit(main())
