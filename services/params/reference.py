"""Every service's declarations in one table, and the parameter reference page generated from it:
`python -m services.params.reference > docs/parameters.md`."""

from __future__ import annotations

import sys

from flight.estimation.position_ekf import PositionEKFParams
from flight.param import declarations
from services.params import Param, attitude, mavlink, motors, planner, position, sim, vision

# service -> its declarations, in the order of the data flow (the recorder has no parameters)
DECLARED: dict[str, dict[str, Param]] = {
    "sim": sim.PARAMS, "motors": motors.PARAMS, "attitude": attitude.PARAMS, "position": position.PARAMS,
    "vision": vision.PARAMS, "planner": planner.PARAMS, "mavlink": mavlink.PARAMS,
}


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, float):
        return f"{v:g}" if "e" in f"{v:g}" else repr(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_value(x)}" for k, x in v.items()) + "}"
    return str(v)


def _row(service: str, key: str, p: Param) -> str:
    bounds = " / ".join(f"`{c}`" if c else '`""`' for c in p.choices) if p.choices else p.bounds_text()
    names = p.mavlink_names()
    mav = ", ".join(f"`{n}`" for n in names)
    doc = p.doc + ("; one number: every element" if p.per_axis else "")
    return (f"| {service} | `{key}` | `{_value(p.default)}` | {p.unit} | {bounds} | "
            f"{doc.replace('|', '/')} | {mav} |")


def _rows(service: str, key: str, p: Param) -> list[str]:
    """A parameter's row, and a nested table's keys after it as TABLE.KEY."""
    nested = declarations(p.table).items() if p.table is not None else ()
    return [_row(service, key, p), *[_row(service, f"{key}.{k}", q) for k, q in nested]]


def render() -> str:
    out = [
        "# zenpilot parameter reference",
        "",
        "Generated from the declarations in `services/params/` by `python -m services.params.reference`; "
        "do not edit by hand.",
        "",
        "Every service's parameters: default, unit, bounds, what it does, and the MAVLink name a ground "
        "station tunes it by in flight. A stack file (`deploy/stacks/default.toml`) sets only what "
        "differs, under `[services.NAME.params]`; `zenpilot fly --set SERVICE.KEY=VALUE` for one "
        "flight. A service refuses an unknown key, a wrong type, a value out of bounds or not among "
        "the choices at start, with the file, section and key; `zenpilot sweep` refuses them in its "
        "grid before any flight, and a running service refuses them on `param/set` (counted as "
        "`param_rejected`, the old value kept), by the same check. Bounds are inclusive unless the "
        "interval says otherwise (`(0, 0.5]`: above 0, at most 0.5); a list's bounds hold for each "
        "element. A `{}` default is a nested table; a declared one's keys follow it as `TABLE.KEY`, "
        "each at its default unless the table gives it (`ekf = {max_delay_s = 0.5}`; "
        "`--set 'position.ekf={max_delay_s=0.5}'`), declared beside the code that owns them (named in "
        "the description) and checked at start like the rest.",
        "",
        "Settings that cannot fly together are refused as well: the simulator's `camera_latency_s` "
        "must stay below the position EKF's history (`position.ekf` `max_delay_s`, "
        f"{PositionEKFParams.max_delay_s:g} s by default), or every camera fix would be dropped.",
        "",
    ]
    for service, declared in DECLARED.items():
        out += [
            f"## {service}",
            "",
            "| service | key | default | unit | bounds | description | MAVLink |",
            "|---|---|---|---|---|---|---|",
            *[row for key, p in declared.items() for row in _rows(service, key, p)],
            "",
        ]
    return "\n".join(out)


if __name__ == "__main__":
    sys.stdout.write(render())
