"""A parameter's declaration (`Param`: default, unit, bounds, a line of description) and the one
check every value passes against it: a service's parameters from a stack file or `--param`
(services/stack.py resolve_params), the keys of a nested table (a position `ekf`, an attitude
`filter`, ...) and the fields of the settings dataclasses that own those tables, however they
are built (`Declared`). docs/parameters.md is generated from the same declarations
(services/params/reference.py). Pure: no I/O.
"""
from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass
from typing import Any, ClassVar


class ParamError(ValueError):
    """A value its declaration refuses; the message starts with where it was set and its key."""


@dataclass(frozen=True)
class Param:
    """One parameter. `min`/`max` bound a number, or each element of a list of numbers
    (inclusive; `min_exclusive`: the value must be above `min`); a float must be finite.
    `choices`: the strings it may be (with a list default: the strings its elements may be, any
    number of them). `mavlink`: its MAVLink parameter name for in-flight tuning,
    "NAME" or, for a vector, ("NAME_{}", "RPY"): one MAVLink parameter per axis letter (NAME_R,
    NAME_P, NAME_Y). `per_axis`: one number stands for every element of a list. `table`: a
    nested table's owner, a `Declared` dataclass whose fields are its keys."""

    default: Any
    unit: str = ""
    min: float | None = None
    max: float | None = None
    doc: str = ""
    choices: tuple[str, ...] = ()
    mavlink: str | tuple[str, str] | None = None
    min_exclusive: bool = False
    per_axis: bool = False
    table: type | None = None

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

    def check(self, value: Any, where: str) -> Any:
        """`value` as this parameter holds it (an int for a float is a float, a list takes the
        default's container type), or ParamError naming `where`: of the wrong type or length,
        not among the choices, out of bounds or not finite; a nested table is checked key by key
        against its owner's declarations and returned as given."""
        default = self.default
        if isinstance(default, bool):
            value = _expect(value, bool, where)
        elif isinstance(default, float):
            value = _expect(value, float, where)
        elif isinstance(default, int):
            value = _expect(value, int, where)
        elif isinstance(default, str):
            value = _expect(value, str, where)
            if self.choices and value not in self.choices:
                raise ParamError(f"{where}: {value!r} not one of {self.choices}")
        elif isinstance(default, dict):
            value = _expect(value, dict, where)
            if self.table is not None:
                from_table(self.table, value, where)
            return value
        elif isinstance(default, (list, tuple)) and self.choices:   # any number of the choices (no bounds)
            if isinstance(value, str):   # `--set KEY=NAME`: say how a list is written
                raise ParamError(f'{where}: expected a list, e.g. ["{value}"], got {value!r}')
            value = _expect(value, (list, tuple), where)
            for v in value:
                if not isinstance(v, str) or v not in self.choices:
                    raise ParamError(f"{where}: {v!r} not one of {self.choices} (in {list(value)!r})")
            return type(default)(value)
        elif isinstance(default, (list, tuple)):
            if self.per_axis and _is_number(value):
                value = [value] * len(default)
            value = _expect(value, (list, tuple), where)
            if len(value) != len(default):
                raise ParamError(f"{where}: expected {len(default)} values, got {len(value)}")
            value = type(default)(_expect(v, float, f"{where}[{i}]") if isinstance(d, float) else v
                                  for i, (v, d) in enumerate(zip(value, default)))
        numbers = [x for x in (value if isinstance(value, (list, tuple)) else [value]) if _is_number(x)]
        if self.min is not None or self.max is not None:
            for x in numbers:
                if not math.isfinite(x) or self.out_of_bounds(x):
                    unit = f" {self.unit}" if self.unit else ""
                    raise ParamError(f"{where}: {value!r} outside {self.bounds_text()}{unit}")
        elif not all(math.isfinite(x) for x in numbers):
            raise ParamError(f"{where}: {value!r} is not finite")
        return value


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _expect(value: Any, kind: type | tuple, where: str) -> Any:
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        name = kind.__name__ if isinstance(kind, type) else "list"
        raise ParamError(f"{where}: expected {name}, got {value!r}")
    return value


def declared(default: Any, unit: str = "", min: float | None = None, max: float | None = None, doc: str = "",
             **more: Any) -> Any:
    """A dataclass field declared as a parameter: `Param(default, unit, min, max, doc, ...)` in its
    metadata, checked by `Declared` and listed in docs/parameters.md by its table's owner."""
    return dataclasses.field(default=default, metadata={"param": Param(default, unit, min, max, doc, **more)})


def declarations(cls: type) -> dict[str, Param]:
    """A `Declared` dataclass's fields as name -> Param, in declaration order."""
    return {f.name: f.metadata["param"] for f in dataclasses.fields(cls)}


def from_table(cls: type, table: Any, where: str) -> Any:
    """`cls(**table)` with each key checked against its declaration, or the owner's error naming
    `where` and the key: not a table, an unknown key, a value its declaration refuses, or
    settings its owner refuses together."""
    error = getattr(cls, "error", ParamError)
    label = getattr(cls, "label", None) or cls.__name__
    if not isinstance(table, dict):
        raise error(f"{where}: expected a table, got {type(table).__name__}")
    known = declarations(cls)
    kwargs = {}
    for key, value in table.items():
        if key not in known:
            raise error(f"{where}.{key}: unknown key (known: {', '.join(known)})")
        try:
            kwargs[key] = known[key].check(value, f"{where}.{key}")
        except ParamError as exc:
            raise error(str(exc)) from None
    try:
        return cls(**kwargs)
    except ValueError as exc:   # settings refused together: the owner's message names its keys
        raise error(str(exc) if where == label else f"{where}: {exc}") from None


class Declared:
    """Base of a frozen settings dataclass whose fields are all `declared`: every field is
    checked (and an int made a float, a list a tuple) on construction; `from_dict` builds one
    from a table (a stack file's, a mission's). Cross-field rules go in the subclass's
    `__post_init__` after `super().__post_init__()`. A subclass may set `error`, the ValueError
    subclass it raises, and `label`, what its messages call it (its class name)."""

    error: ClassVar[type[ValueError]] = ParamError
    label: ClassVar[str | None] = None

    def __post_init__(self) -> None:
        cls = type(self)
        for name, p in declarations(cls).items():
            try:
                value = p.check(getattr(self, name), f"{cls.label or cls.__name__}.{name}")
            except ParamError as exc:
                raise self.error(str(exc)) from None
            object.__setattr__(self, name, value)

    @classmethod
    def from_dict(cls, d: Any, where: str | None = None):
        """Built from a table; errors name `where` (by default its label) and the key."""
        return from_table(cls, d, where or cls.label or cls.__name__)

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
