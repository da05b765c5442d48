"""The simulator service's parameters (services/sim.py): the simulator's settings, declared with
their units, bounds and docs beside their defaults in simulator/config.py SimConfig, and the
service's own."""

from __future__ import annotations

import dataclasses

from flight.param import declarations
from services.params import Param
from simulator.config import SimConfig


def _from_config() -> dict[str, Param]:
    out = {}
    for name, p in declarations(SimConfig).items():
        if name == "tick_rate_hz":   # the stack's tick rate is the one source of truth
            continue
        # a stack file's arrays are lists, as the services' other parameters
        out[name] = dataclasses.replace(p, default=list(p.default)) if isinstance(p.default, tuple) else p
    return out


SIM_CONFIG_KEYS = frozenset(declarations(SimConfig)) - {"tick_rate_hz"}
PARAMS = {
    **_from_config(),
    "stop_after_mission": Param(True, doc="`zenpilot fly`: end the run when the mission ends"),
    "linger_s": Param(1.0, "s", 0.0, doc="keep simulating this long after the mission ends (landing settles, "
                                         "logs flush)"),
    "max_duration_s": Param(600.0, "s", 0.0, min_exclusive=True, doc="hard stop, simulated time"),
    # robustness: the services keep the airframe file's mass
    "mass_scale": Param(1.0, "", 0.1, 10.0, doc="the plant's mass is this times the airframe file's"),
}
