"""Fly a mission and kill (SIGKILL) or freeze (SIGSTOP, then SIGCONT) one service mid-flight.

The stack runs as `zenpilot fly` runs it (deploy.launcher), but a service that dies is not a
reason to stop the flight: the vehicle's failsafes are what is tested. The fault is injected
when the simulator's truth (watched on the bus) reaches `at_s`; the flight then goes on until
the simulator stops (mission over, or sim.max_duration_s). Returns the metrics of the flight
(deploy.metrics: crash_reason, touchdown_speed_m_s, failsafes, ...) with the fault's figures.

    python -m tests.integration.faults --service attitude --fault kill [--realtime] [--truth-state]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import schemas
from deploy.cli import _param_overrides, analyse
from deploy.launcher import Launcher, client_session, free_port
from services.stack import load_mission, load_stack, lockstep_services

TRUTH_STATE = ("attitude.state_source=truth", "position.state_source=truth", "sim.truth_rate_hz=200")


def first_tick(out: Path, deadline_s: float) -> float:
    """Real time: the wall time of the simulator's tick 0 (its log says it)."""
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        found = re.search(r"first tick at ([0-9.]+)", (out / "logs" / "sim.log").read_text())
        if found:
            return float(found.group(1))
        time.sleep(0.05)
    raise RuntimeError("the simulator did not start ticking")


def fly_with_fault(out: Path, service: str, fault: str = "kill", at_s: float = 8.0, stop_s: float = 2.0,
                   mission: str = "hover", settings: tuple[str, ...] = (), lockstep: bool = True,
                   seed: int = 0, wall_limit_s: float = 600.0, keep: dict | None = None) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    stack = load_stack(None)
    m = load_mission(mission)
    router = f"tcp/127.0.0.1:{free_port()}"
    launcher = Launcher(stack, out, router, lockstep=lockstep, seed=seed, vehicle=m.vehicle,
                        mission=m.path, params=_param_overrides(list(settings), stack))
    names = lockstep_services(stack.services) if lockstep else list(stack.services)
    seen = {"t": -1.0, "z": 0.0}
    reached = threading.Event()
    fault_info: dict = {"service": service, "fault": fault, "at_s": at_s, "injected_at_s": None}
    session = None
    try:
        launcher.start_router()
        launcher.start_services(names)
        missing = launcher.wait_alive(names)
        if missing:
            raise RuntimeError(f"no liveliness token from {sorted(missing)}")
        session = client_session(router)
        # truth headers: simulated time in lockstep; in real time the wall clock from the first tick
        t_origin = 0.0 if lockstep else first_tick(out, deadline_s=30.0)

        def on_truth(sample) -> None:
            msg = schemas.TRUTH.decode(sample.payload.to_bytes())
            seen["t"], seen["z"] = msg["header"]["t_s"], msg["position_m"][2]
            if seen["t"] - t_origin >= t_fault:
                reached.set()
        t_fault = at_s
        sub = session.declare_subscriber(schemas.TRUTH.key(stack.vehicle_id), on_truth)
        deadline = time.monotonic() + wall_limit_s
        while not reached.wait(0.1):
            if launcher.procs["sim"].poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the flight ended before t={at_s} s (truth at {seen['t']:.2f} s)")
        fault_info["injected_at_s"] = seen["t"]   # on the truth's clock
        fault_info["flight_time_s"] = seen["t"] - t_origin
        fault_info["altitude_m"] = seen["z"]
        pid = launcher.procs[service].pid
        if fault == "kill":
            os.kill(pid, signal.SIGKILL)
        elif fault == "stop":
            os.kill(pid, signal.SIGSTOP)
            time.sleep(stop_s)
            os.kill(pid, signal.SIGCONT)
        else:
            raise ValueError(f"fault {fault!r}: kill or stop")
        sub.undeclare()
        while launcher.procs["sim"].poll() is None:
            if time.monotonic() > deadline:
                raise RuntimeError(f"the flight did not finish within {wall_limit_s} s of wall time")
            time.sleep(0.1)
    finally:
        if session is not None:
            session.close()
        launcher.stop([n for n in names if n != "recorder"])
        time.sleep(0.3)
        launcher.stop(["recorder"], grace_s=60.0)
        launcher.stop(["router"])
    kept: dict = {}
    metrics = analyse(out, {"mission": mission, "mode": "lockstep" if lockstep else "realtime",
                            "seed": seed, "vehicle": m.vehicle}, plots=False, keep=kept)
    log = kept["log"]   # the log analyse read (not read again)
    if keep is not None:   # for a caller that reads it too
        keep["log"] = log
    p = f"zp/{stack.vehicle_id}/"
    truth = sorted(log.get(p + "sim/truth", []), key=lambda x: x["header"]["t_s"])
    after = [x for x in truth if x["header"]["t_s"] >= fault_info["injected_at_s"]]   # same clock
    fault_info["landed_at_end"] = bool(truth and truth[-1]["landed"])
    fault_info["min_altitude_after_m"] = min((x["position_m"][2] for x in after), default=None)
    # the fault's own effect, before the mission's later items (its landing) count
    soon = [x["position_m"][2] for x in after if x["header"]["t_s"] <= fault_info["injected_at_s"] + stop_s + 3.0]
    fault_info["min_altitude_soon_m"] = min(soon, default=None)
    fault_info["max_altitude_after_m"] = max((x["position_m"][2] for x in after), default=None)
    # when the truth first rested on the ground after the fault (s after it), if it did
    down = next((x["header"]["t_s"] for x in after if x["landed"]), None)
    fault_info["ground_after_s"] = None if down is None else down - after[0]["header"]["t_s"]
    metrics["fault"] = fault_info
    (out / "fault.json").write_text(json.dumps(metrics, indent=1))
    return metrics


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--service", required=True)
    ap.add_argument("--fault", choices=("kill", "stop"), default="kill")
    ap.add_argument("--at", type=float, default=8.0, help="simulated time of the fault (s)")
    ap.add_argument("--stop-s", type=float, default=2.0)
    ap.add_argument("--mission", default="hover")
    ap.add_argument("--realtime", action="store_true")
    ap.add_argument("--truth-state", action="store_true")
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    out = Path(args.out or tempfile.mkdtemp(prefix=f"fault-{args.service}-{args.fault}-"))
    settings = tuple(args.set) + (TRUTH_STATE if args.truth_state else ())
    m = fly_with_fault(out, args.service, args.fault, args.at, args.stop_s, args.mission, settings,
                       lockstep=not args.realtime)
    keys = ("completed", "crashed", "crash_reason", "touchdown_speed_m_s", "max_tilt_deg", "failsafes", "fault")
    print(json.dumps({k: m.get(k) for k in keys}, indent=1))
    print(f"run in {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
