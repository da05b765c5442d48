"""Every service's parameters, declared once: default, unit, bounds, a line of description.

One module per service (services/params/attitude.py, ...) holds its `PARAMS`, a dict of
name -> `Param`, as PX4's module yaml or ArduPilot's var_info do. They import no transport and
no solver, so the MAVLink bridge reads its parameter table from them (services/mavlink_logic.py
TUNABLE) without loading the services. What uses them:

- services/stack.py `resolve_params`: a stack file's values (and `--param`/`--set`) over the
  defaults, refused at start-up with the file, section and key when of the wrong type, out of
  bounds or not among the choices; its per-value `check_param` also checks a sweep's grid
  (deploy/sweep.py) and, in flight, a `param/set` (services/runtime.py ParamAccess.set_param);
- services/mavlink_logic.py: the parameters with `mavlink=` are the ones a ground station tunes
  in flight, under those names and within those bounds;
- services/params/reference.py: docs/parameters.md.

A nested table (a dict default: attitude `filter`, position `ekf`, ...) is its owner's: the
dataclass named in the doc checks its keys and values. The runtime's `rt.params` holds plain
values (`values(PARAMS)`), so the services' code reads numbers, never declarations.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Param:
    """One parameter. `min`/`max` bound a number, or each element of a list of numbers
    (inclusive; `min_exclusive`: the value must be above `min`). `choices`: the strings it may
    be. `mavlink`: its MAVLink parameter name for in-flight tuning, "NAME" or, for a vector,
    ("NAME_{}", "RPY"): one MAVLink parameter per axis letter (NAME_R, NAME_P, NAME_Y)."""

    default: Any
    unit: str = ""
    min: float | None = None
    max: float | None = None
    doc: str = ""
    choices: tuple[str, ...] = ()
    mavlink: str | tuple[str, str] | None = None
    min_exclusive: bool = False

    def value(self) -> Any:
        """A fresh copy of the default (the runtime may replace a list's values in place)."""
        return copy.deepcopy(self.default)

    def bounds_text(self) -> str:
        """The bounds as an interval, "[0.1, 200]", "(0, 0.5]", "[0, inf)"; "" when unbounded."""
        if self.min is None and self.max is None:
            return ""
        left = f"({self.min:g}" if self.min_exclusive else f"[{self.min:g}" if self.min is not None else "(-inf"
        right = f"{self.max:g}]" if self.max is not None else "inf)"
        return f"{left}, {right}"

    def out_of_bounds(self, x: float) -> bool:
        if self.min is not None and (x <= self.min if self.min_exclusive else x < self.min):
            return True
        return self.max is not None and x > self.max

    def mavlink_names(self) -> list[str]:
        """The MAVLink parameter names of this parameter (one per axis for a vector)."""
        if self.mavlink is None:
            return []
        if isinstance(self.mavlink, str):
            return [self.mavlink]
        pattern, axes = self.mavlink
        return [pattern.format(a) for a in axes]


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
