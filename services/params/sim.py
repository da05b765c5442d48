"""The simulator service's parameters (services/sim.py): the simulator's settings, declared with
their units, bounds and docs beside their defaults in simulator/config.py SimConfig, and the
service's own."""

from __future__ import annotations

from dataclasses import fields

from services.params import Param
from simulator.config import SimConfig


def _from_config() -> dict[str, Param]:
    out = {}
    for f in fields(SimConfig):
        if f.name == "tick_rate_hz":   # the stack's tick rate is the one source of truth
            continue
        m = f.metadata
        default = list(f.default) if isinstance(f.default, tuple) else f.default
        out[f.name] = Param(default, m["unit"], m["min"], m["max"], m["doc"], min_exclusive=m["min_exclusive"])
    return out


SIM_CONFIG_KEYS = frozenset(f.name for f in fields(SimConfig)) - {"tick_rate_hz"}
PARAMS = {
    **_from_config(),
    "stop_after_mission": Param(True, doc="`zenpilot fly`: end the run when the mission ends"),
    "linger_s": Param(1.0, "s", 0.0, doc="keep simulating this long after the mission ends (landing settles, "
                                         "logs flush)"),
    "max_duration_s": Param(600.0, "s", 0.0, min_exclusive=True, doc="hard stop, simulated time"),
    # robustness: the services keep the airframe file's mass
    "mass_scale": Param(1.0, "", 0.1, 10.0, doc="the plant's mass is this times the airframe file's"),
}
