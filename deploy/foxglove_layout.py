"""The Foxglove layout shipped as docs/foxglove-layout.json, built with foxglove-sdk's layouts.

    python -m deploy.foxglove_layout [--vehicle 0] [--out docs/foxglove-layout.json]

One layout for both the live view (`zenpilot view`) and flight.mcap: the same topics exist in
both. A 3D scene (the marker grid, the airframe at the estimate in blue and at the truth in green,
setpoint and camera fixes; the view follows the estimate: a real vehicle has no truth) beside
tabs of plots: position and attitude against their references, body rates, motor outputs,
each service's health. Plot series read the raw JSON channels (`zp/<vehicle>/...`, fields as in schemas/messages.py).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import foxglove.layouts as fl

from services.foxglove_map import BODY, WORLD, topic

LAYOUT_PATH = Path(__file__).resolve().parents[1] / "docs" / "foxglove-layout.json"
HEALTH_OF = ("sim", "motors", "attitude", "position", "vision", "planner", "mavlink")
_AXES = ("x", "y", "z")
_ANGLES = ("roll", "pitch", "yaw")
_COLORS = ("#e6194b", "#3cb44b", "#4363d8", "#f58231")


def _plot(title: str, series: list[tuple[str, str]], **config) -> fl.PlotPanel:
    return fl.PlotPanel(title=title, config=fl.PlotConfig(
        paths=[fl.PlotSeries(value=value, label=label, color=_COLORS[i % len(_COLORS)] if "ref" not in label else None,
                             line_style="dashed" if "ref" in label or "setpoint" in label else None)
               for i, (value, label) in enumerate(series)], show_legend=True, **config))


def _tab(title: str, *panels: fl.BasePanel) -> fl.TabItem:
    return fl.TabItem(title=title, content=fl.SplitContainer(
        direction="column", items=[fl.SplitItem(content=p) for p in panels]))


def build_layout(vehicle_id: int = 0) -> fl.Layout:
    zp = f"zp/{vehicle_id}"
    scene = fl.ThreeDeePanel(title="3D: estimate (blue), truth (green)", config=fl.ThreeDeeConfig(
        follow_tf=BODY, fixed_frame=WORLD, follow_mode="follow-position",
        camera_state=fl.ThreeDeeCameraState(distance=4.0, phi=60.0, perspective=True),
        topics={
            topic(vehicle_id, "scene/markers"): fl.BaseRendererSceneUpdateTopicSettings(visible=True),
            topic(vehicle_id, "scene/vehicle"): fl.BaseRendererSceneUpdateTopicSettings(visible=True),
            topic(vehicle_id, "scene/seen"): fl.BaseRendererSceneUpdateTopicSettings(visible=True),
            topic(vehicle_id, "pose/setpoint"): fl.BaseRendererPoseTopicSettings(
                visible=True, type="arrow", color="#f58231"),
            topic(vehicle_id, "pose/vision"): fl.BaseRendererPoseTopicSettings(
                visible=True, type="axis", axis_scale=0.5),
            topic(vehicle_id, "pose/truth"): fl.BaseRendererPoseTopicSettings(visible=False),
            topic(vehicle_id, "pose/estimate"): fl.BaseRendererPoseTopicSettings(visible=False),
        }))
    position = [(f"{zp}/pos/state.position_m[{i}]", f"{a} estimate") for i, a in enumerate(_AXES)] + \
               [(f"{zp}/sim/truth.position_m[{i}]", f"{a} truth") for i, a in enumerate(_AXES)] + \
               [(f"{zp}/planner/setpoint.position_m[{i}]", f"{a} setpoint") for i, a in enumerate(_AXES)]
    attitude = [(f"{zp}/att/state.euler_rad[{i}]", f"{a}") for i, a in enumerate(_ANGLES)] + \
               [(f"{zp}/att/state.euler_ref_rad[{i}]", f"{a} ref") for i, a in enumerate(_ANGLES)]
    rates = [(f"{zp}/att/state.rate_rad_s[{i}]", f"{a} rate") for i, a in enumerate(_ANGLES)]
    thrust = [(f"{zp}/pos/setpoint.thrust_n", "collective setpoint"), (f"{zp}/att/command.thrust_n", "collective")] + \
             [(f"{zp}/att/command.torque_nm[{i}]", f"torque {a}") for i, a in enumerate(_ANGLES)]
    pwm = [(f"{zp}/motors/pwm.pwm_us[{i}]", f"motor {i + 1}") for i in range(4)]
    health_rate = [(f"{zp}/{s}/health.rate_hz", s) for s in HEALTH_OF]
    health_late = [(f"{zp}/{s}/health.lateness_p99_ms", s) for s in HEALTH_OF]
    plots = fl.TabContainer(tabs=[
        _tab("position", _plot("position (m, world ENU)", position)),
        _tab("attitude", _plot("attitude (rad)", attitude), _plot("body rates (rad/s)", rates)),
        _tab("motors", _plot("motor PWM (us)", pwm), _plot("thrust (N) and torques (N m)", thrust)),
        _tab("health", _plot("rate of each service (Hz)", health_rate),
             _plot("wake-up lateness p99 (ms)", health_late)),
    ])
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=1.2, content=scene),
        fl.SplitItem(proportion=1.0, content=plots),
    ]))


def layout_json(vehicle_id: int = 0) -> str:
    return json.dumps(json.loads(build_layout(vehicle_id).to_json()), indent=1) + "\n"   # one key a line: diffs read


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--vehicle", type=int, default=0, help="vehicle id (the <vehicle> of zp/<vehicle>/...)")
    p.add_argument("--out", default=str(LAYOUT_PATH))
    args = p.parse_args(argv)
    Path(args.out).write_text(layout_json(args.vehicle))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
