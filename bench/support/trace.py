"""Where a two-host flight's time went (bench/two_hosts.py --trace): CPU per process and thread,
and each control message's latency split at the link's two ends.

CpuWatch: a thread that reads, once a second, the CPU time (utime + stime, /proc/<pid>/task/<tid>/stat)
of every thread of every process in the given network namespaces; `result()` gives each
process's and thread's CPU seconds between the first and the last time it was seen, and their
share of a core over the watch's wall time.

split(): per key that crossed, the probe's rows ([arrival, t_s, seq, source]) matched by (source,
seq, t_s) to the sender's wiretap ("out": when the frame left the sender's end of the link) and
the receiver's ("in": when it came in at the other end), kernel clock: sender host = wire out -
t_s, link = wire in - wire out, receiver host = arrival - wire in; p50/p99 of each, and their
means over the messages in the end-to-end latency's top 1 % (which part the tail is made of).

stalls(): on the sender's host, the moments when messages of several keys were all held (over
10 ms each, within 10 ms of one another): something every key goes through stopped, as a
router's routing does, rather than one service being late.
"""

from __future__ import annotations

import os
import threading
import time

TICK = os.sysconf("SC_CLK_TCK")


def _label(pid: int) -> str:
    """python -m services.sim ... -> services.sim; deploy.router's machine and the flooder's sink named."""
    try:
        argv = open(f"/proc/{pid}/cmdline", "rb").read().split(b"\0")
    except OSError:
        return str(pid)
    argv = [a.decode(errors="replace") for a in argv if a]
    if not argv:
        return str(pid)
    if "-m" in argv[:-1]:
        name = argv[argv.index("-m") + 1]
        if "--machine" in argv[:-1]:
            name += f"[{argv[argv.index('--machine') + 1]}]"
        if "--sink" in argv:
            name += "[sink]"
        return name
    return os.path.basename(argv[0])


def _machine_ticks() -> tuple[int, int]:
    """(busy, interrupts) clock ticks of every CPU since boot (/proc/stat)."""
    fields = [int(x) for x in open("/proc/stat").readline().split()[1:]]
    idle = fields[3] + fields[4]   # idle, iowait
    return sum(fields) - idle, fields[5] + fields[6]   # busy; irq + softirq (the kernel moving packets)


def _ticks(path: str) -> tuple[str, int] | None:
    try:
        text = open(path).read()
    except OSError:
        return None
    comm = text[text.index("(") + 1:text.rindex(")")]
    fields = text[text.rindex(")") + 2:].split()
    return comm, int(fields[11]) + int(fields[12])   # utime, stime (fields 14, 15 of stat)


class CpuWatch(threading.Thread):
    def __init__(self, namespaces: dict[str, str], period_s: float = 1.0):
        super().__init__(name="cpuwatch", daemon=True)
        self.namespaces, self.period_s = namespaces, period_s
        self.stop_event = threading.Event()
        self.seen: dict[tuple[int, int], list] = {}   # (pid, tid) -> [host, label, comm, first, last]
        self.labels: dict[int, str] = {}
        self.t0 = self.t1 = None
        self.stat0 = self.stat1 = (0, 0)

    def sample(self) -> None:
        """Every process of the machine: per thread in the hosts' namespaces, as a whole outside them
        (the bench itself, anything else). A process first seen after the first sample started
        during the watch: all its CPU counts."""
        inode = {}
        for host, ns in self.namespaces.items():
            try:
                inode[os.stat(f"/var/run/netns/{ns}").st_ino] = host
            except OSError:
                pass
        for name in os.listdir("/proc"):
            if not name.isdigit():
                continue
            pid = int(name)
            try:
                host = inode.get(os.stat(f"/proc/{pid}/ns/net").st_ino, "outside")
            except OSError:
                continue
            if pid not in self.labels:
                self.labels[pid] = _label(pid)
            paths = [(0, f"/proc/{pid}/stat")]
            if host != "outside":
                try:
                    paths = [(int(tid), f"/proc/{pid}/task/{tid}/stat") for tid in os.listdir(f"/proc/{pid}/task")]
                except OSError:
                    continue
            for tid, path in paths:
                got = _ticks(path)
                if got is None:
                    continue
                row = self.seen.get((pid, tid))
                if row is None:
                    self.seen[(pid, tid)] = [host, self.labels[pid], got[0], got[1] if self.t1 is None else 0, got[1]]
                else:
                    row[4] = got[1]

    def run(self) -> None:
        self.t0, self.stat0 = time.monotonic(), _machine_ticks()
        while not self.stop_event.is_set():
            self.sample()
            self.t1, self.stat1 = time.monotonic(), _machine_ticks()
            self.stop_event.wait(self.period_s)

    def stop(self) -> dict:
        self.stop_event.set()
        self.join(10)
        return self.result()

    def result(self) -> dict:
        wall = max((self.t1 or 0) - (self.t0 or 0), 1e-9)
        procs: dict[str, float] = {}
        threads: dict[str, float] = {}
        for (pid, _), (host, label, comm, first, last) in self.seen.items():
            cpu = (last - first) / TICK
            procs[f"{host}: {label}"] = procs.get(f"{host}: {label}", 0.0) + cpu
            if host != "outside":
                threads[f"{host}: {label} / {comm}"] = threads.get(f"{host}: {label} / {comm}", 0.0) + cpu
        hosts: dict[str, float] = {}
        for name, cpu in procs.items():
            hosts[name.split(":")[0]] = hosts.get(name.split(":")[0], 0.0) + cpu

        def pct(d: dict) -> dict:
            return {k: round(100 * v / wall, 1) for k, v in sorted(d.items(), key=lambda kv: -kv[1])}
        busy = (self.stat1[0] - self.stat0[0]) / TICK if self.t1 else 0.0   # the whole machine
        irq = (self.stat1[1] - self.stat0[1]) / TICK if self.t1 else 0.0
        outside = hosts.pop("outside", 0.0)
        return {"wall_s": round(wall, 1), "machine_busy_pct": round(100 * busy / wall, 1),
                "machine_cores": os.cpu_count(), "interrupts_pct": round(100 * irq / wall, 1),
                "outside_pct": round(100 * outside / wall, 1),
                "outside_top": {k[len("outside: "):]: v for k, v in list(pct(procs).items())[:40]
                                if k.startswith("outside: ") and v >= 1.0},
                "hosts_pct": pct(hosts), "processes_pct": pct(procs),
                "threads_pct": {k: v for k, v in pct(threads).items() if v >= 1.0}}


def _q(xs: list[float], f: float) -> float | None:
    return round(xs[min(len(xs) - 1, int(f * len(xs)))], 2) if xs else None


def split(probe_rows: dict[str, list], sent: list, received: list) -> dict:
    """Per key: the probe's rows matched to the wiretaps' (sender's "out", receiver's "in")."""
    out_at = {(r[3], r[2], r[1]): r[0] for r in sent}
    in_at = {(r[3], r[2], r[1]): r[0] for r in received}
    result = {}
    for key, rows in probe_rows.items():
        parts = []
        for arrival, t_s, seq, source in rows:
            k = (source, seq, t_s)
            if k in out_at and k in in_at:
                w_out, w_in = out_at[k], in_at[k]
                parts.append((1e3 * (arrival - t_s), 1e3 * (w_out - t_s), 1e3 * (w_in - w_out), 1e3 * (arrival - w_in)))
        if not parts:
            continue
        names = ("end_to_end", "sender_host", "link", "receiver_host")
        row = {"matched": len(parts), "of": len(rows)}
        for i, name in enumerate(names):
            xs = sorted(p[i] for p in parts)
            row[name] = {"p50": _q(xs, 0.5), "p99": _q(xs, 0.99), "max": _q(xs, 1.0)}
        tail = sorted(parts, key=lambda p: p[0])[int(0.99 * len(parts)):]
        row["tail_1pct_mean"] = {name: round(sum(p[i] for p in tail) / len(tail), 2) for i, name in enumerate(names)}
        result[key] = row
    return result


def stalls(probe_rows: dict[str, list], sent: list, late_ms: float = 10.0, keys_at_least: int = 3) -> dict:
    """Windows in which messages of >= `keys_at_least` keys each spent over `late_ms` on the sender's
    host (wire out - t_s), none more than `late_ms` apart; keys late by design (a median over
    `late_ms`: a camera's header is its exposure time) left out."""
    out_at = {(r[3], r[2], r[1]): r[0] for r in sent}
    rows = []
    for key, records in probe_rows.items():
        mine = [(t_s, 1e3 * (out_at[(src, seq, t_s)] - t_s), key) for _, t_s, seq, src in records
                if (src, seq, t_s) in out_at]
        if mine and sorted(d for _, d, _ in mine)[len(mine) // 2] <= late_ms:
            rows += mine
    rows.sort()
    windows, current = [], []
    for row in (r for r in rows if r[1] > late_ms):
        if current and row[0] - current[-1][0] > late_ms / 1e3:
            windows.append(current)
            current = []
        current.append(row)
    windows = [w for w in windows + [current] if len({r[2] for r in w}) >= keys_at_least]
    held = sorted(max(r[1] for r in w) for w in windows)
    span = rows[-1][0] - rows[0][0] if rows else 0.0
    return {"messages": len(rows), "over_ms": late_ms, "late": sum(1 for r in rows if r[1] > late_ms),
            "windows": len(windows), "per_s": round(len(windows) / span, 2) if span else None,
            "held_ms": {"p50": _q(held, 0.5), "max": _q(held, 1.0)}}
