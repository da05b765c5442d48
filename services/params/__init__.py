"""Every service's parameters, declared once: default, unit, bounds, a line of description.

One module per service (services/params/attitude.py, ...) holds its `PARAMS`, a dict of
name -> `Param` (flight/param.py), as PX4's module yaml or ArduPilot's var_info do. They import
no transport and no solver, so the MAVLink bridge reads its parameter table from them
(services/mavlink_logic.py TUNABLE) without loading the services. What uses them:

- services/stack.py `resolve_params`: a stack file's values (and `--param`/`--set`) over the
  defaults, refused at start-up with the file, section and key when of the wrong type, out of
  bounds or not among the choices; its per-value `check_param` also checks a sweep's grid
  (deploy/sweep.py) and, in flight, a `param/set` (services/runtime.py ParamAccess.set_param);
- services/mavlink_logic.py: the parameters with `mavlink=` are the ones a ground station tunes
  in flight, under those names and within those bounds;
- services/params/reference.py: docs/parameters.md.

A nested table (a dict default: attitude `filter`, position `ekf`, ...) has its keys declared
beside the code that owns them, as the fields of a settings dataclass (`Param.table`, e.g.
flight/estimation/position_ekf.py PositionEKFParams), and checked by the same `Param.check` at
start-up. The runtime's `rt.params` holds plain values (`values(PARAMS)`), so the services' code
reads numbers, never declarations.
"""

from __future__ import annotations

from typing import Any

from flight.param import Param

__all__ = ["Param", "tunable", "values"]


def values(declarations: dict[str, Param]) -> dict[str, Any]:
    """name -> default: the plain values a service runs on before the stack file's."""
    return {name: p.value() for name, p in declarations.items()}


def tunable(services: dict[str, dict[str, Param]]) -> tuple:
    """The MAVLink parameter table: (service, key, name pattern, axis letters or None, (min, max)),
    services in the given order, each service's parameters in its declaration order (the
    parameter protocol's index)."""
    rows = []
    for service, declarations in services.items():
        for key, p in declarations.items():
            if p.mavlink is None:
                continue
            if p.min is None or p.max is None or p.min_exclusive:
                raise ValueError(f"{service}.{key}: a MAVLink parameter needs closed bounds (min, max)")
            pattern, axes = (p.mavlink, None) if isinstance(p.mavlink, str) else p.mavlink
            rows.append((service, key, pattern, axes, (p.min, p.max)))
    return tuple(rows)
