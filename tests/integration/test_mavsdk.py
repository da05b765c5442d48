"""MAVSDK (the real `mavsdk` package, 4.x) flies the stack through the MAVLink bridge.

The flows are MAVSDK's own example flows, written as a user would: telemetry,
health and parameters on the ground; arm / take off / hold / offboard position
steps / land in one flight; the README's script (examples/mavsdk_mission.py, run
as it is) flies a 4-waypoint mission and returns to launch in another. The
stack runs with no mission (the planner waits for commands), twice: in lockstep
(the bridge lives on the wall clock, so every wait is generous: the simulator runs
slower than real time on a busy machine, and the suite runs it at idle priority beside the
real-time tests), then in real time on the default stack
(the estimators, as a user flies it). One stack serves every test of a mode, in
order: first a plain pymavlink listener checks the messages QGroundControl relies
on, then MAVSDK binds the same port.
"""

import asyncio
import contextlib
import math
import os
import shutil
import socket
import subprocess
import sys
import time

import pytest

os.environ.setdefault("MAVLINK20", "1")
os.environ.setdefault("MAVLINK_DIALECT", "common")
from pymavlink import mavutil  # noqa: E402

from deploy.launcher import free_port  # noqa: E402

from .conftest import ROOT  # noqa: E402

import mavsdk  # noqa: E402  (the `test` extra: mavsdk 4.x, which ships its C++ core)
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.mission import MissionAsync  # noqa: E402
from mavsdk.asyncio.plugins.offboard import OffboardAsync, PositionNedYaw  # noqa: E402
from mavsdk.asyncio.plugins.param import ParamAsync  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import FlightMode, LandedState, TelemetryAsync  # noqa: E402

pytestmark = pytest.mark.integration
mavlink = mavutil.mavlink
HOME = (47.397742, 8.545594, 488.0)   # the bridge's default home (services/params/mavlink.py)


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def zp(*args, env):
    return subprocess.run([sys.executable, "-m", "deploy.cli", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=180)


# the real-time stack is a real-time test (alone among real-time flights); the lockstep one runs
# beside them like any lockstep flight
@pytest.fixture(scope="module", params=["lockstep", pytest.param("real time", marks=pytest.mark.realtime)])
def stack(request, tmp_path_factory):
    """`zenpilot up` (`--lockstep`, then in real time) with no mission (the planner waits for
    commands); the bridge it starts (on the wall clock, as always) talks to this test's UDP port."""
    tmp = tmp_path_factory.mktemp("mavsdk")
    env = dict(os.environ, ZENPILOT_STATE_DIR=str(tmp))
    router, udp = f"tcp/127.0.0.1:{free_port()}", free_udp_port()
    mode = ["--lockstep"] if request.param == "lockstep" else []
    up = zp("up", "-d", *mode, "--router", router, "--out", str(tmp / "run"),
            "--set", "planner.mission=none", "--set", f"mavlink.endpoint=udpout:127.0.0.1:{udp}", env=env)
    try:
        assert up.returncode == 0, up.stdout + up.stderr
        yield udp, tmp / "run"
    finally:
        zp("down", env=env)


async def until(agen, cond, timeout_s: float, what: str):
    """The first value of a telemetry stream that satisfies cond, within timeout_s; a timeout says
    the last value the stream gave and when (a stream that stopped, or a vehicle elsewhere)."""
    seen = []

    async def first():
        async for value in agen:
            seen[:] = [value, time.monotonic()]
            if cond(value):
                return value
    try:
        return await asyncio.wait_for(first(), timeout_s)
    except asyncio.TimeoutError:
        last = f"{time.monotonic() - seen[1]:.1f} s before: {seen[0]}" if seen else "nothing"
        raise AssertionError(f"no {what} within {timeout_s} s; the last value came {last}") from None


async def connect(udp: int):
    sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    await sdk.add_any_connection(f"udpin://127.0.0.1:{udp}")
    system = await sdk.first_autopilot(timeout_s=30.0)
    assert system is not None, "no autopilot heard"
    return sdk, system


def run(coro, run_dir=None):
    """Run a MAVSDK flow; a failure carries what the bridge and the planner said (their logs)."""
    try:
        return asyncio.run(asyncio.wait_for(coro, 400.0))
    except AssertionError as exc:
        if run_dir is None:
            raise
        said = "".join(f"\n--- {name}.log\n" + (run_dir / "logs" / f"{name}.log").read_text()[-2000:]
                       for name in ("mavlink", "planner") if (run_dir / "logs" / f"{name}.log").exists())
        raise AssertionError(f"{exc}{said}") from None


def udp_sockets(port: int) -> str:
    """The sockets on this UDP port, with their processes: where the bridge's messages go."""
    if not shutil.which("ss"):
        return ""
    lines = subprocess.run(["ss", "-uanp"], capture_output=True, text=True).stdout.splitlines()
    return f"\n--- UDP sockets on port {port}\n" + "\n".join(line for line in lines if f":{port} " in line)


def test_qgc_messages_at_their_rates(stack):
    """What QGroundControl needs to show a vehicle, at the rates it is used to (PX4's defaults)."""
    udp, _ = stack
    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{udp}", source_system=255, source_component=190)
    try:
        counts: dict[str, int] = {}
        first = {}
        start = time.monotonic()
        while time.monotonic() - start < 60.0:  # until the stack streams its state
            m = conn.recv_match(blocking=True, timeout=0.1)
            if m is not None and m.get_type() == "GLOBAL_POSITION_INT":
                break
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            if conn.clients and not first:
                conn.mav.command_long_send(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                           mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
                first["asked"] = True
            m = conn.recv_match(blocking=True, timeout=0.1)
            if m is not None and m.get_srcSystem() == 1:
                counts[m.get_type()] = counts.get(m.get_type(), 0) + 1
                first.setdefault(m.get_type(), m)
        hz = {name: n / 10.0 for name, n in counts.items()}
        hb = first["HEARTBEAT"]
        assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4 and hb.type == mavlink.MAV_TYPE_QUADROTOR
        assert hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        version = first["AUTOPILOT_VERSION"]
        for cap in ("MAVLINK2", "MISSION_INT", "PARAM_FLOAT", "COMMAND_INT", "SET_POSITION_TARGET_LOCAL_NED"):
            assert version.capabilities & getattr(mavlink, "MAV_PROTOCOL_CAPABILITY_" + cap), cap
        expected = {"HEARTBEAT": 1.0, "SYS_STATUS": 1.0, "EXTENDED_SYS_STATE": 1.0, "GLOBAL_POSITION_INT": 10.0,
                    "HOME_POSITION": 0.2, "ATTITUDE": 25.0, "LOCAL_POSITION_NED": 25.0, "BATTERY_STATUS": 1.0,
                    "MISSION_CURRENT": 1.0}
        for name, rate in expected.items():  # the bridge's rates on the wall clock; a busy machine drops some
            assert 0.6 * rate <= hz.get(name, 0.0) <= 1.5 * rate + 0.1, (name, hz)
        home = first["HOME_POSITION"]
        assert (home.latitude, home.longitude, home.altitude) == (
            round(HOME[0] * 1e7), round(HOME[1] * 1e7), round(HOME[2] * 1000))
        gp = first["GLOBAL_POSITION_INT"]
        assert abs(gp.lat - home.latitude) < 100 and abs(gp.relative_alt) < 100  # on the ground, at home
    finally:
        conn.close()


async def telemetry_and_parameters(udp: int):
    sdk, drone = await connect(udp)
    async with sdk:
        telemetry, param = TelemetryAsync(drone), ParamAsync(drone)
        health = await until(telemetry.subscribe_health(), lambda h: h.is_armable, 60.0, "armable vehicle")
        assert health.is_gyrometer_calibration_ok and health.is_accelerometer_calibration_ok
        assert await until(telemetry.subscribe_flight_mode(), lambda m: m != FlightMode.UNKNOWN, 10.0,
                           "flight mode") == FlightMode.HOLD
        pos = await until(telemetry.subscribe_position(), lambda p: True, 10.0, "position")
        assert pos.latitude_deg == pytest.approx(HOME[0], abs=1e-5) and abs(pos.relative_altitude_m) < 0.2
        home = await until(telemetry.subscribe_home(), lambda p: True, 15.0, "home")
        assert home.absolute_altitude_m == pytest.approx(HOME[2])
        battery = await until(telemetry.subscribe_battery(), lambda b: True, 10.0, "battery")
        assert 0.5 < battery.remaining_percent <= 100.0 and battery.voltage_v > 10.0
        assert await until(telemetry.subscribe_landed_state(), lambda s: True, 10.0,
                           "landed state") == LandedState.ON_GROUND
        assert not await until(telemetry.subscribe_armed(), lambda a: True, 10.0, "armed")
        # parameters: read, write (reaches the position level), unknown names refused at once
        assert await param.get_param_float("POS_K_Z") == pytest.approx(4.0)
        await param.set_param_float("POS_K_Z", 4.5)
        assert await param.get_param_float("POS_K_Z") == pytest.approx(4.5)
        await param.set_param_float("POS_K_Z", 4.0)  # as it was: the flights that follow fly the stack's gains
        assert await param.get_param_float("MIS_TAKEOFF_ALT") == pytest.approx(2.0)
        t0 = time.monotonic()
        with pytest.raises(mavsdk.plugins.param.ParamError):
            await param.get_param_float("NO_SUCH_PARAM")
        unknown_s = time.monotonic() - t0
        everything = await param.get_all_params()
        names = {p.name for p in everything.float_params}
        assert {"ATT_K_R", "POS_MAX_TILT", "MIS_TAKEOFF_ALT", "COM_OF_LOSS_T"} <= names
        return unknown_s


def test_telemetry_health_and_parameters(stack):
    udp, run_dir = stack
    unknown_s = run(telemetry_and_parameters(udp), run_dir)
    assert unknown_s < 2.0, f"an unknown parameter took {unknown_s:.1f} s to be refused"
    time.sleep(0.5)
    log = (run_dir / "logs" / "position.log").read_text()
    assert "param k = [4.0, 4.0, 4.5]" in log and "param k = [4.0, 4.0, 4.0]" in log


async def takeoff_offboard_land(udp: int):
    """MAVSDK's takeoff_and_land and offboard_position_ned examples in one flight; a flight that
    fails is landed, so the next test of the stack starts on the ground."""
    sdk, drone = await connect(udp)
    async with sdk:
        telemetry, action = TelemetryAsync(drone), ActionAsync(drone)
        try:
            await fly_takeoff_offboard_land(telemetry, action, OffboardAsync(drone))
        except Exception as exc:
            held = udp_sockets(udp)   # while this ground station still holds its port
            with contextlib.suppress(Exception):   # the flight's own failure is what the test reports
                await action.land()
                await until(telemetry.subscribe_armed(), lambda a: not a, 90.0, "disarmed after the failure")
            if isinstance(exc, AssertionError):
                raise AssertionError(f"{exc}{held}") from None
            raise


async def fly_takeoff_offboard_land(telemetry, action, offboard):
    await until(telemetry.subscribe_health(), lambda h: h.is_armable, 60.0, "armable vehicle")
    await action.set_takeoff_altitude(2.0)
    await action.arm()
    await until(telemetry.subscribe_armed(), lambda a: a, 10.0, "armed")
    await action.takeoff()
    await until(telemetry.subscribe_position(), lambda p: p.relative_altitude_m > 1.9, 60.0, "2 m up")
    await until(telemetry.subscribe_in_air(), lambda a: a, 10.0, "in air")
    await action.hold()
    assert await until(telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.HOLD, 10.0,
                       "hold mode") == FlightMode.HOLD
    # offboard: a setpoint first, then start; steps north and east, as the example does
    await offboard.set_position_ned(PositionNedYaw(0.0, 0.0, -2.0, 0.0))
    await offboard.start()
    await until(telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.OFFBOARD, 10.0, "offboard")
    for north, east in ((1.5, 0.0), (1.5, 1.5), (0.0, 0.0)):
        await offboard.set_position_ned(PositionNedYaw(north, east, -2.0, 0.0))
        await until(telemetry.subscribe_position_velocity_ned(),
                    lambda p: math.dist((p.position.north_m, p.position.east_m, p.position.down_m),
                                        (north, east, -2.0)) < 0.2,
                    90.0, f"offboard position ({north}, {east}, -2)")
    await offboard.stop()
    await action.land()
    await until(telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.LAND, 10.0, "land mode")
    await until(telemetry.subscribe_armed(), lambda a: not a, 90.0, "disarmed after landing")
    assert await until(telemetry.subscribe_landed_state(), lambda s: True, 10.0, "") == LandedState.ON_GROUND


def test_takeoff_offboard_land(stack):
    udp, run_dir = stack
    run(takeoff_offboard_land(udp), run_dir)


async def after_the_example(udp: int):
    """What the README's script left: its mission stored as uploaded, the vehicle home and landed."""
    sdk, drone = await connect(udp)
    async with sdk:
        telemetry, mission = TelemetryAsync(drone), MissionAsync(drone)
        back = await mission.download_mission()
        home = await until(telemetry.subscribe_home(), lambda p: True, 15.0, "home")
        expected = [(0, 0, 2.0), (2, 0, 2.0), (2, 2, 2.5), (0, 2, 2.0)]
        assert len(back.mission_items) == 4
        for (north, east, up), got in zip(expected, back.mission_items):
            assert got.latitude_deg == pytest.approx(home.latitude_deg + math.degrees(north / 6378137.0), abs=1e-6)
            assert got.relative_altitude_m == pytest.approx(up)
        pv = await until(telemetry.subscribe_position_velocity_ned(), lambda p: True, 10.0, "position")
        assert math.hypot(pv.position.north_m, pv.position.east_m) < 0.3 and pv.position.down_m > -0.1
        assert await until(telemetry.subscribe_landed_state(), lambda s: True, 10.0, "") == LandedState.ON_GROUND
        await mission.clear_mission()
        assert await until(telemetry.subscribe_flight_mode(), lambda m: m != FlightMode.UNKNOWN, 10.0,
                           "flight mode") in (FlightMode.RETURN_TO_LAUNCH, FlightMode.HOLD)


def test_readme_mission_example_flies_four_waypoints_and_returns(stack):
    """examples/mavsdk_mission.py (the README's script, run as a user runs it): upload, arm, mission,
    progress to 4/4, return to launch, landed; then the mission downloads as uploaded."""
    udp, run_dir = stack
    script = ROOT / "examples" / "mavsdk_mission.py"
    assert script.read_text().split('"""', 2)[2].strip() in (ROOT / "README.md").read_text(), \
        "the README shows examples/mavsdk_mission.py as it is"
    done = subprocess.run([sys.executable, str(script), f"udpin://127.0.0.1:{udp}"], cwd=ROOT,
                          capture_output=True, text=True, timeout=400)
    assert done.returncode == 0, done.stdout + done.stderr
    progress = [tuple(map(int, line.split()[-1].split("/"))) for line in done.stdout.splitlines()
                if line.startswith("mission progress")]
    assert progress[-1] == (4, 4) and [c for c, _ in progress] == sorted(c for c, _ in progress), progress
    assert done.stdout.rstrip().endswith("landed and disarmed")
    run(after_the_example(udp), run_dir)
    planner = (run_dir / "logs" / "planner.log").read_text()
    assert "mission of 9 items" in planner and "mission of 2 items" in planner  # the square, then RTL
    # the stack's second take-off (the first flew the offboard test): the camera's silence on the
    # ground between the flights is no loss of vision
    position = (run_dir / "logs" / "position.log").read_text()
    assert "no camera fix" not in position, position
