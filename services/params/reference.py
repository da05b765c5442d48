"""Every service's declarations in one table."""

from __future__ import annotations

from services.params import Param, attitude, mavlink, motors, planner, position, sim, vision

# service -> its declarations, in the order of the data flow (the recorder has no parameters)
DECLARED: dict[str, dict[str, Param]] = {
    "sim": sim.PARAMS, "motors": motors.PARAMS, "attitude": attitude.PARAMS, "position": position.PARAMS,
    "vision": vision.PARAMS, "planner": planner.PARAMS, "mavlink": mavlink.PARAMS,
}
