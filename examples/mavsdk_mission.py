"""Fly a 4-waypoint square with MAVSDK, as one would fly PX4 (the README's example; a test runs it).

    zenpilot up --set planner.mission=none      # in another terminal
    python examples/mavsdk_mission.py           # or: python examples/mavsdk_mission.py udpin://0.0.0.0:14550
"""

import asyncio
import math
import sys

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.mission import MissionAsync, MissionItem, MissionPlan
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync


def waypoint(home, north_m, east_m, up_m):
    lat = home.latitude_deg + math.degrees(north_m / 6378137.0)
    lon = home.longitude_deg + math.degrees(east_m / (6378137.0 * math.cos(math.radians(home.latitude_deg))))
    return MissionItem(latitude_deg=lat, longitude_deg=lon, relative_altitude_m=up_m, speed_m_s=1.0,
                       is_fly_through=False, acceptance_radius_m=0.3, loiter_time_s=0.5)


async def main(url):
    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as sdk:
        await sdk.add_any_connection(url)
        drone = await sdk.first_autopilot(timeout_s=30.0)
        telemetry, action, mission = TelemetryAsync(drone), ActionAsync(drone), MissionAsync(drone)

        async for health in telemetry.subscribe_health():
            if health.is_armable:
                break
        async for home in telemetry.subscribe_home():
            break
        square = [waypoint(home, 0, 0, 2), waypoint(home, 2, 0, 2), waypoint(home, 2, 2, 2.5), waypoint(home, 0, 2, 2)]
        await mission.upload_mission(MissionPlan(square))
        await action.arm()
        await mission.start_mission()
        async for progress in mission.subscribe_mission_progress():
            print(f"mission progress {progress.current}/{progress.total}", flush=True)
            if progress.current == progress.total:
                break
        await action.return_to_launch()
        async for armed in telemetry.subscribe_armed():
            if not armed:
                break
        print("landed and disarmed", flush=True)


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1] if len(sys.argv) > 1 else "udpin://0.0.0.0:14550"))
