"""Benchmark the MAVLink bridge: telemetry latency from a message's sample time to
the ground station, while the real-time stack hovers under GCS command.

    python bench/mavlink.py [--seconds 20] [--rate-hz 50] [--estimate]

A pymavlink GCS arms, takes off to 1 m, asks ATTITUDE, LOCAL_POSITION_NED and
HIGHRES_IMU at --rate-hz and listens. The stack's clock is wall time; the
bridge's boot time comes from SYSTEM_TIME, so sample time = boot + time_boot_ms
(1 ms resolution; HIGHRES_IMU: 1 us). Printed: GCS-side p50/p99 (sample ->
received) and the bridge's own sample -> send figures, and its CPU.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("MAVLINK20", "1")
os.environ.setdefault("MAVLINK_DIALECT", "common")

from deploy.launcher import free_port  # noqa: E402
from services.mavlink_logic import mavutil  # noqa: E402
from bench.support.gcs import Gcs, free_udp_port, takeoff  # noqa: E402

mavlink = mavutil.mavlink
TRUTH_STATE = ["--set", "attitude.state_source=truth", "--set", "position.state_source=truth",
               "--set", "sim.truth_rate_hz=200"]
STREAMS = {"ATTITUDE": 30, "LOCAL_POSITION_NED": 32, "HIGHRES_IMU": 105}


def pct(values, q):
    v = sorted(values)
    return v[min(len(v) - 1, int(q * len(v)))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--rate-hz", type=float, default=50.0)
    ap.add_argument("--estimate", action="store_true", help="full estimator cascade (default: truth-state ablation)")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench-mavlink-"))
    env = dict(os.environ, ZENPILOT_STATE_DIR=str(tmp))
    udp = free_udp_port()
    gcs = Gcs(udp)
    up = [sys.executable, "-m", "deploy.cli", "up", "-d", "--router", f"tcp/127.0.0.1:{free_port()}", "--out",
          str(tmp / "run"), "--set", "planner.mission=none", "--set", f"mavlink.endpoint=udpout:127.0.0.1:{udp}",
          *([] if args.estimate else TRUTH_STATE)]
    proc = subprocess.run(up, cwd=ROOT, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"bench: `zenpilot up` failed: {proc.stderr}")
    lat: dict[str, list[float]] = {n: [] for n in STREAMS}
    try:
        gcs.wait("HEARTBEAT", timeout=30.0)
        for mid in STREAMS.values():
            gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mid, 1e6 / args.rate_hz)
        takeoff(gcs, 1.0)
        st = gcs.wait("SYSTEM_TIME")
        boot = st.time_unix_usec / 1e6 - st.time_boot_ms / 1e3
        end = time.monotonic() + args.seconds
        while time.monotonic() < end:
            m = gcs.pump()
            if m is None:
                continue
            now, kind = time.time(), m.get_type()
            if kind == "SYSTEM_TIME":
                boot = m.time_unix_usec / 1e6 - m.time_boot_ms / 1e3
            elif kind == "HIGHRES_IMU":
                lat[kind].append(now - (boot + m.time_usec / 1e6))
            elif kind in lat:
                lat[kind].append(now - (boot + m.time_boot_ms / 1e3))
        gcs.command(mavlink.MAV_CMD_NAV_LAND)
    finally:
        subprocess.run([sys.executable, "-m", "deploy.cli", "down"], cwd=ROOT, env=env, capture_output=True)
        gcs.conn.close()
    print(f"bench/mavlink.py: {args.seconds:.0f} s hovering, streams at {args.rate_hz:g} Hz, "
          f"{'estimate' if args.estimate else 'truth-state ablation'}, real time")
    print(f"{'stream':<20} {'n':>6} {'rate Hz':>8} {'p50 ms':>8} {'p99 ms':>8}   (sample -> GCS receipt)")
    for name, values in lat.items():
        if values:
            print(f"{name:<20} {len(values):>6} {len(values) / args.seconds:>8.1f} "
                  f"{statistics.median(values) * 1e3:>8.2f} {pct(values, 0.99) * 1e3:>8.2f}")
    log = (tmp / "run" / "logs" / "mavlink.log").read_text()
    for line in re.findall(r"zenpilot-mavlink: (\S+ sample->send .*)", log):
        print("bridge:", line)
    cpu = re.search(r"cpu ([0-9.]+) s", log)
    if cpu:
        print(f"bridge CPU: {cpu.group(1)} s over the whole run (logs in {tmp / 'run' / 'logs'})")


if __name__ == "__main__":
    main()
