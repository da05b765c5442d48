"""zenpilot-mavlink: the MAVLink 2 bridge to a ground station (QGroundControl, MAVSDK).

Like an autopilot it sends to the GCS port (`udpout:127.0.0.1:14550` by
default) and answers whoever talks to it on that socket. Telemetry comes from
the stack's messages (attitude and position state, IMU/baro/mag, battery,
health of every service, planner setpoint); commands go to the planner as
planner/command, missions as planner/mission and parameter changes to the
services as param/set. The
logic lives in services/mavlink_logic.py; this shell owns the socket.

It is a real-time service: it never takes part in lockstep (a GCS lives on
the wall clock), so in `fly --lockstep` it only watches. Signing is on when
`signing_key_file` names a key (32 raw bytes, 64 hex digits, or a passphrase
hashed with SHA-256 as MAVProxy does): unsigned and replayed messages are
rejected and counted.
"""

from __future__ import annotations

import hashlib
import math
import time
from pathlib import Path

import zenoh

import schemas
from flight.vehicle import load_vehicle
from services.mavlink_logic import (STREAMS, TUNABLE, TUNABLE_DEFAULTS, Bridge, BridgeConfig, ParamTable,
                                    is_loopback_endpoint, latency_summary, mavutil_v2)
from services.params.mavlink import PARAMS  # every parameter: default, unit, bounds, doc
from services.runtime import Inbox, Runtime, main_guard, service_parser

NAME = "mavlink"
INPUTS = {  # bridge input name -> (message, upstream)
    "att": (schemas.ATTITUDE_STATE, "attitude"), "pos": (schemas.POSITION_STATE, "position"),
    "battery": (schemas.BATTERY, "sim"), "setpoint": (schemas.PLANNER_SETPOINT, "planner"),
    "flip": (schemas.PLANNER_FLIP_STATUS, "planner"),   # once a second while the planner can flip
    "ekf": (schemas.POSITION_EKF_HEALTH, "position"),   # 1 Hz: the wind estimate (WIND_COV)
}


def wind_per_accel(vehicle_name: str) -> float:
    """m/s of wind per m/s^2 of the EKF's disturbance: mass / linear drag (NaN without drag)."""
    vehicle = load_vehicle(vehicle_name)
    return vehicle.mass_kg / vehicle.drag_n_per_m_s if vehicle.drag_n_per_m_s > 0 else math.nan


def read_key(path: str) -> bytes:
    """A signing key: 32 raw bytes, 64 hex digits, or a passphrase (SHA-256 of it)."""
    raw = Path(path).read_bytes()
    if len(raw) == 32:
        return raw
    text = raw.decode(errors="replace").strip()
    try:
        if len(text) == 64:
            return bytes.fromhex(text)
    except ValueError:
        pass
    if not text:
        raise ValueError(f"signing key file {path} is empty")
    return hashlib.sha256(text.encode()).digest()


def rates(value: dict, where: str) -> dict:
    for name, hz in value.items():
        if name not in STREAMS:
            raise ValueError(f"{where} rates_hz: unknown stream {name!r} (known: {', '.join(STREAMS)})")
        if isinstance(hz, bool) or not isinstance(hz, (int, float)) or not 0 <= hz <= 400:
            raise ValueError(f"{where} rates_hz.{name}: expected a rate in [0, 400] Hz, got {hz!r}")
    return dict(value)


def current_params(rt: Runtime) -> dict:
    """The stack's values of the tunable parameters (the stack file over each service's defaults)."""
    out = {}
    for service, key, *_ in TUNABLE:
        if service == NAME:  # the bridge's own: its parameters as this run has them
            out[(service, key)] = rt.params[key]
            continue
        if service not in rt.stack.services:
            continue
        spec = rt.stack.services[service].params
        out[(service, key)] = spec[key] if key in spec else TUNABLE_DEFAULTS[(service, key)]
    return out


def run(args) -> None:
    rt = Runtime(NAME, args, PARAMS)
    if args.endpoint:
        rt.params["endpoint"] = args.endpoint
    lockstep = rt.lockstep
    rt.lockstep = False  # a real-time service in every mode: it watches, the clock is not its business
    rt.rate_hz = rt.rate_hz or 50.0
    p = rt.params
    config = BridgeConfig(p["system_id"], p["component_id"], p["home_lat_deg"], p["home_lon_deg"], p["home_alt_m"],
                          p["gcs_timeout_s"], p["failsafe_hold_s"], p["health_timeout_s"],
                          rates_hz=rates(p["rates_hz"], rt.where()),
                          converged_position_std_m=p["converged_position_std_m"],
                          converged_attitude_std_deg=p["converged_attitude_std_deg"],
                          wind_per_accel_s=wind_per_accel(rt.vehicle_name))
    if not p["signing_key_file"] and not p["allow_unsigned_link"] and not is_loopback_endpoint(p["endpoint"]):
        raise ValueError(f"{rt.where()} endpoint {p['endpoint']!r} leaves this machine: set signing_key_file "
                         f"(MAVLink 2 signing; the ground station needs the same key), or allow_unsigned_link = true")
    try:
        conn = mavutil_v2().mavlink_connection(p["endpoint"], source_system=p["system_id"],
                                          source_component=p["component_id"], autoreconnect=True)
    except Exception as exc:
        raise ValueError(f"{rt.where()} endpoint: cannot open {p['endpoint']!r}: {exc}") from None
    signing = bool(p["signing_key_file"])
    if signing:
        try:
            key = read_key(p["signing_key_file"])
        except OSError as exc:
            raise ValueError(f"{rt.where()} signing_key_file: {exc}") from None
        conn.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=lambda mav, msg_id: False)
    boxes = {name: rt.inbox(msg, upstream) for name, (msg, upstream) in INPUTS.items()}
    # sensor inputs (the IMU at 400 Hz) cost CPU on a small computer: subscribed only while
    # HIGHRES_IMU is streamed or was requested
    sensors = {name: Inbox(rt, msg, msg.key(rt.vehicle_id), "sim", keep=1)
               for name, msg in (("imu", schemas.IMU), ("baro", schemas.BARO), ("mag", schemas.MAG))}
    subs: dict = {}
    command_out = rt.publisher(schemas.PLANNER_COMMAND)
    param_out = rt.publisher(schemas.PARAM_SET)
    mission_out = rt.publisher(schemas.PLANNER_MISSION)
    bridge = Bridge(conn.mav, config, ParamTable(current_params(rt)), tuple(rt.stack.services), rt.rejected,
                    t_origin_s=0.0 if lockstep else time.time(), problem=rt.problem)
    bridge.health_on_stack_clock = lockstep

    def on_health(sample: zenoh.Sample) -> None:
        try:
            msg = schemas.HEALTH.decode(sample.payload.to_bytes())
        except schemas.SchemaError as exc:
            rt.reject(str(sample.key_expr), exc)
            return
        bridge.health[msg["header"]["source"]] = (time.time(), msg)

    rt.subscribe(rt.key("*/health"), on_health)

    def act(actions) -> None:
        for kind, fields in actions:
            if kind == "command":
                command_out.put(fields)
            elif kind == "mission":
                mission_out.put(fields)
            else:
                param_out.put(fields)

    def follow_sensors() -> None:
        wanted = bridge.intervals_s["HIGHRES_IMU"] > 0 or bridge.imu_requested
        if wanted and not subs:
            subs.update({name: rt.subscribe(box.key, box._on_sample) for name, box in sensors.items()})
        elif not wanted and subs:
            for name, sub in subs.items():
                sub.undeclare()
                bridge.inputs.pop(name, None)
            subs.clear()
        for name in subs:
            if (msg := sensors[name].latest()) is not None:
                bridge.inputs[name] = msg

    def incoming():
        """The messages waiting on the socket, at most max_messages_per_step (bounded work)."""
        for _ in range(p["max_messages_per_step"]):
            try:
                msg = conn.recv_msg()
            except Exception as exc:  # a socket error must not end the bridge
                rt.rejected["mavlink_recv_error"] = rt.rejected.get("mavlink_recv_error", 0) + 1
                rt.problem(f"receive failed: {type(exc).__name__}: {exc}")
                return
            if msg is None:
                return
            yield msg

    def step(now_wall: float) -> None:
        follow_sensors()
        for name, box in boxes.items():
            msg = box.latest()
            if msg is not None:
                bridge.inputs[name] = msg
        # the stack's clock: wall time, or in lockstep the newest simulated sample time
        now = max((m["header"]["t_s"] for m in bridge.inputs.values()), default=0.0) if lockstep else now_wall
        act(bridge.cycle(now, now_wall, incoming()))
        if signing:  # pymavlink counts signature failures itself (bad or replayed: badsig)
            s = conn.mav.signing
            for reason, value in (("mavlink_unsigned", s.reject_count - s.badsig_count),
                                  ("mavlink_bad_signature", s.badsig_count)):
                if value:
                    rt.rejected[reason] = value

    print(f"zenpilot-mavlink: {p['endpoint']} as system {p['system_id']}"
          f"{', signed' if signing else ''}; {len(bridge.params.rows)} parameters", flush=True)
    try:
        rt.run(step)
    finally:
        for name, (p50, p99, n) in latency_summary(bridge).items():
            print(f"zenpilot-mavlink: {name} sample->send p50 {p50:.2f} ms p99 {p99:.2f} ms (n={n})", flush=True)
        conn.close()


def main(argv=None) -> None:
    parser = service_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--endpoint", help="MAVLink connection, e.g. udpout:127.0.0.1:14550 or udpin:0.0.0.0:14540 "
                        "(default: the stack's mavlink.endpoint)")
    args = parser.parse_args(argv)
    main_guard(NAME, lambda: run(args))


if __name__ == "__main__":
    main()
