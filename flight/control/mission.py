"""Missions: a list of items flown by a phase machine (pure; no I/O).

A mission file is TOML:

    [mission]
    name = "hover"
    vehicle = "x250"          # airframe file in flight/vehicles/
    description = "..."
    timeout_s = 60            # the mission fails if it takes longer

    [[items]]
    type = "takeoff"          # arm, climb along a ramp, done within tolerance
    altitude_m = 1.0

Item types and their keys (defaults in ITEM_KEYS):
  arm       wait_s                      arm the motors, wait on the ground
  takeoff   altitude_m climb_rate_m_s tolerance_m
  hold      duration_s settle_s         hold the reference; measured after settle_s
  goto      position_m yaw_deg settle_s hold_s acceptance_m   step the reference; measured after settle_s;
            acceptance_m > 0 (a MAVLink waypoint): done hold_s after coming within acceptance_m
  attitude  roll_deg pitch_deg yaw_deg duration_s attitude reference, altitude held
  land      descent_rate_m_s            descend until landed, then disarm
  flip      method altitude_m settle_s timeout_s baseline_climb_m   a 360-degree roll flip
            (document 001): method "ilqr-project" | "ilqr-thesis" | "baseline"; the flip
            controller (given by the planner service, see MissionRunner.flip) flies it from
            the altitude altitude_m (>= 5 m) and holds settle_s after recovery; the mission
            goes on from where it recovered. Without a flip controller the mission fails.
            baseline_climb_m: the baseline's full-thrust climb before its roll (Appendix И:
            1 m, 5 -> 6 m; 0: it rolls from the hover).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from flight.control.flip import BASELINE_CLIMB_M

ITEM_KEYS: dict[str, dict] = {
    "arm": {"wait_s": 0.5},
    "takeoff": {"altitude_m": 1.0, "climb_rate_m_s": 0.5, "tolerance_m": 0.05},
    "hold": {"duration_s": 10.0, "settle_s": 1.0},
    "goto": {"position_m": None, "yaw_deg": 0.0, "settle_s": 4.0, "hold_s": 2.0, "acceptance_m": 0.0},
    "attitude": {"roll_deg": 0.0, "pitch_deg": 0.0, "yaw_deg": 0.0, "duration_s": 1.0},
    "land": {"descent_rate_m_s": 0.5},
    "flip": {"method": "ilqr-project", "altitude_m": 5.0, "settle_s": 1.0, "timeout_s": 15.0,
             "baseline_climb_m": BASELINE_CLIMB_M},
}
FLIP_METHODS = ("ilqr-project", "ilqr-thesis", "baseline")
FLIP_MIN_ALTITUDE_M = 5.0  # a safe altitude, as in 001
LANDED_Z_M = 0.03      # below this, slow and with the reference under ground: landed
LANDED_FOR_S = 0.5
LAND_TARGET_Z_M = -0.3  # the reference goes below the floor so the vehicle sits down firmly


class MissionError(ValueError):
    """A mission file that cannot be flown; the message names the file and the item."""


@dataclass(frozen=True)
class Mission:
    name: str
    vehicle: str
    description: str
    timeout_s: float
    items: tuple[dict, ...]
    path: str = ""


def parse_mission(doc: dict, path: str = "<mission>") -> Mission:
    """A mission from its parsed TOML document; errors name `path` and the item."""
    head = doc.get("mission", {})
    for key in ("name", "vehicle"):
        if not isinstance(head.get(key), str):
            raise MissionError(f"{path}: [mission] needs a string '{key}'")
    items = []
    for i, raw in enumerate(doc.get("items", [])):
        where = f"{path}: items[{i}]"
        kind = raw.get("type")
        if kind not in ITEM_KEYS:
            raise MissionError(f"{where}: type {kind!r} not one of {', '.join(ITEM_KEYS)}")
        item = {"type": kind, **ITEM_KEYS[kind]}
        for key, value in raw.items():
            if key == "type":
                continue
            if key not in ITEM_KEYS[kind]:
                raise MissionError(f"{where}: unknown key {key!r} for {kind} (known: {', '.join(ITEM_KEYS[kind])})")
            if key == "position_m":
                if not (isinstance(value, list) and len(value) == 3 and all(isinstance(v, (int, float)) for v in value)):
                    raise MissionError(f"{where}: position_m must be 3 numbers")
                value = [float(v) for v in value]
            elif key == "method":
                if value not in FLIP_METHODS:
                    raise MissionError(f"{where}: method {value!r} not one of {', '.join(FLIP_METHODS)}")
            elif not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
                raise MissionError(f"{where}: {key} must be a finite number, got {value!r}")
            item[key] = value
        if kind == "flip" and item["altitude_m"] < FLIP_MIN_ALTITUDE_M:
            raise MissionError(f"{where}: a flip needs altitude_m >= {FLIP_MIN_ALTITUDE_M:g} (got {item['altitude_m']})")
        if kind == "flip" and item["baseline_climb_m"] < 0:
            raise MissionError(f"{where}: baseline_climb_m must be >= 0 (got {item['baseline_climb_m']})")
        if any(v is None for v in item.values()):
            raise MissionError(f"{where}: {kind} needs " + ", ".join(k for k, v in item.items() if v is None))
        items.append(item)
    if not items:
        raise MissionError(f"{path}: no [[items]]")
    timeout = head.get("timeout_s", 120.0)
    if not isinstance(timeout, (int, float)) or timeout <= 0:
        raise MissionError(f"{path}: [mission] timeout_s must be a positive number")
    return Mission(head["name"], head["vehicle"], head.get("description", ""), float(timeout),
                   tuple(items), str(path))


@dataclass
class Setpoint:
    mode: str = "idle"
    armed: bool = False
    position_m: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    attitude_rad: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    item: int = 0
    phase: str = "waiting"
    measure: bool = False
    mission_state: str = "waiting"

    def as_message(self) -> dict:
        return dict(self.__dict__)


class MissionRunner:
    """Phase machine: feed it the time and the state, get the setpoint."""

    def __init__(self, mission: Mission, flip=None):
        self.mission = mission
        # flip(item, t_s, starting) -> (phase, done, failed, position_ref_m): the flip
        # controller (the planner service's iLQR or baseline), None when there is none
        self.flip = flip
        self.index = 0
        self.item_start_t: float | None = None
        self.start_t: float | None = None
        self.sp = Setpoint()
        self.ref = np.zeros(3)
        self.yaw = 0.0
        self.landed_since: float | None = None
        self.reached_since: float | None = None  # goto with acceptance_m: first time within it
        self.ramp_from = 0.0

    def update(self, t: float, position, velocity) -> Setpoint:
        sp = self.sp
        if sp.mission_state in ("completed", "failed"):
            return sp
        position = np.asarray(position, dtype=float)
        if self.start_t is None:
            self.start_t = t
            self.ref = position.copy()
            sp.mission_state = "running"
        if t - self.start_t > self.mission.timeout_s:
            sp.mission_state, sp.mode, sp.armed, sp.phase = "failed", "idle", False, "timeout"
            return sp
        item = self.mission.items[self.index]
        if self.item_start_t is None:
            self.item_start_t = t
            self.ramp_from = float(self.ref[2])
            self.landed_since = self.reached_since = None
            if sp.mode == "attitude" and item["type"] != "attitude":
                self.ref[:2] = position[:2]  # attitude steps drift: hold where they ended
        dt = t - self.item_start_t
        done = getattr(self, "_" + item["type"])(item, dt, t, position, np.asarray(velocity, dtype=float))
        sp.item = self.index
        sp.position_m = [float(v) for v in self.ref]
        if sp.mode != "attitude":
            sp.attitude_rad = [0.0, 0.0, self.yaw]
        if done:
            self.index += 1
            self.item_start_t = None
            if self.index >= len(self.mission.items):
                sp.mission_state, sp.measure = "completed", False
        return sp

    # -- items: each sets self.sp / self.ref and returns True when done ---------
    def _arm(self, item, dt, t, pos, vel) -> bool:
        self.sp.mode, self.sp.armed, self.sp.phase, self.sp.measure = "idle", True, "arm", False
        return dt >= item["wait_s"]

    def _takeoff(self, item, dt, t, pos, vel) -> bool:
        sp = self.sp
        sp.mode, sp.armed, sp.phase, sp.measure = "position", True, "takeoff", False
        target = item["altitude_m"]
        z = self.ramp_from + math.copysign(min(abs(target - self.ramp_from), item["climb_rate_m_s"] * dt),
                                           target - self.ramp_from)
        self.ref[2] = z
        return z == target and abs(pos[2] - target) < item["tolerance_m"]

    def _hold(self, item, dt, t, pos, vel) -> bool:
        sp = self.sp
        sp.mode, sp.armed = "position", True
        settled = dt >= item["settle_s"]
        sp.phase, sp.measure = ("hold", True) if settled else ("settle", False)
        return dt >= item["settle_s"] + item["duration_s"]

    def _goto(self, item, dt, t, pos, vel) -> bool:
        sp = self.sp
        sp.mode, sp.armed = "position", True
        self.ref = np.array(item["position_m"], dtype=float)
        self.yaw = math.radians(item["yaw_deg"])
        if item["acceptance_m"] > 0.0:  # a waypoint: reached, then held hold_s
            if self.reached_since is None and float(np.linalg.norm(pos - self.ref)) < item["acceptance_m"]:
                self.reached_since = t
            sp.phase, sp.measure = ("goto", False) if self.reached_since is None else ("hold", False)
            return self.reached_since is not None and t - self.reached_since >= item["hold_s"]
        settled = dt >= item["settle_s"]
        sp.phase, sp.measure = ("hold", True) if settled else ("goto", False)
        return dt >= item["settle_s"] + item["hold_s"]

    def _attitude(self, item, dt, t, pos, vel) -> bool:
        sp = self.sp
        sp.mode, sp.armed, sp.phase, sp.measure = "attitude", True, "attitude", False
        sp.attitude_rad = [math.radians(item["roll_deg"]), math.radians(item["pitch_deg"]),
                           math.radians(item["yaw_deg"])]
        return dt >= item["duration_s"]

    def _flip(self, item, dt, t, pos, vel) -> bool:
        sp = self.sp
        sp.mode, sp.armed, sp.measure = "plan", True, False
        if self.flip is None:
            sp.mode, sp.phase, sp.mission_state = "position", "flip-unavailable", "failed"
            return False
        phase, done, failed, ref = self.flip(item, t, dt == 0.0)
        sp.phase = "flip" if phase == "flip" else f"flip-{phase}"
        self.ref = np.array(ref, dtype=float)
        if failed or dt > item["timeout_s"]:  # abort: the position level takes over where it is
            sp.mode, sp.mission_state = "position", "failed"
            sp.phase = "flip-refused" if phase == "refused" else "flip-aborted"
            return False
        if done:
            sp.mode = "position"
        return done

    def _land(self, item, dt, t, pos, vel) -> bool:
        sp = self.sp
        sp.mode, sp.armed, sp.phase, sp.measure = "position", True, "land", False
        self.ref[2] = max(LAND_TARGET_Z_M, self.ramp_from - item["descent_rate_m_s"] * dt)
        if pos[2] < LANDED_Z_M and abs(vel[2]) < 0.1 and self.ref[2] <= 0.0:
            self.landed_since = t if self.landed_since is None else self.landed_since
        else:
            self.landed_since = None
        if self.landed_since is not None and t - self.landed_since >= LANDED_FOR_S:
            sp.mode, sp.armed, sp.phase = "idle", False, "landed"
            return True
        return False


# ---------------------------------------------------------------- commands
COMMANDS = ("arm", "disarm", "takeoff", "land", "hold", "goto", "flip")
FOREVER_S = 1e9  # "until the next command"


def command_items(command: str, altitude_m: float = 0.0, position_m=(0.0, 0.0, 0.0),
                  yaw_rad: float = 0.0) -> tuple[dict, ...]:
    """The mission items a command stands for. Raises MissionError for a command
    this planner cannot fly (a flip needs a `flip` item type)."""
    def item(kind, **over):
        return {"type": kind, **ITEM_KEYS[kind], **over}

    forever = item("hold", settle_s=0.0, duration_s=FOREVER_S)
    if command == "arm":
        return (item("arm", wait_s=FOREVER_S),)
    if command == "takeoff":
        if not 0.0 < altitude_m <= 100.0:
            raise MissionError(f"takeoff altitude {altitude_m} m outside (0, 100]")
        return (item("takeoff", altitude_m=float(altitude_m)), forever)
    if command == "hold":
        return (forever,)
    if command == "goto":
        return (item("goto", position_m=[float(v) for v in position_m], yaw_deg=math.degrees(yaw_rad),
                     settle_s=0.0, hold_s=FOREVER_S),)
    if command == "land":
        return (item("land"),)
    if command == "flip" and "flip" in ITEM_KEYS:
        return (item("flip"), forever)
    raise MissionError(f"command {command!r} not supported by this planner")


def mission_items(msg: dict) -> list[dict]:
    """planner/mission's parallel arrays -> mission items (see schemas PLANNER_MISSION)."""
    items = []
    for i, kind in enumerate(msg["types"]):
        pos = [float(v) for v in msg["position_m"][3 * i:3 * i + 3]]
        hold = float(msg["hold_s"][i])
        if kind == "takeoff":
            items.append({"type": "takeoff", "altitude_m": pos[2]})
        elif kind == "goto":
            items.append({"type": "goto", "position_m": pos, "yaw_deg": math.degrees(msg["yaw_rad"][i]),
                          "settle_s": 0.0, "hold_s": hold, "acceptance_m": float(msg["acceptance_m"][i])})
        elif kind == "hold":
            items.append({"type": "hold", "settle_s": 0.0, "duration_s": hold})
        elif kind == "land":
            items.append({"type": "land"})
        else:
            items.append({"type": kind})
    return items


class MissionPlanner:
    """A mission file (or none: idle, waiting for commands) plus commands from
    outside (MAVLink) that replace whatever is being flown."""

    def __init__(self, mission: Mission | None, flip=None, flip_method: str | None = None):
        self.flip = flip  # the flip controller for flip items (see MissionRunner.flip)
        self.flip_method = flip_method  # the method a commanded or uploaded flip flies (their items name none)
        self.runner = MissionRunner(mission, flip) if mission is not None else None
        self.sp = self.runner.sp if self.runner else Setpoint()
        self.last_command = ""

    def command(self, command: str, altitude_m: float = 0.0, position_m=(0.0, 0.0, 0.0),
                yaw_rad: float = 0.0) -> None:
        """Start flying `command` from the next update. Raises MissionError if it cannot."""
        prev = self.runner
        if command == "disarm":
            self.runner = None
            self.sp = Setpoint(phase="disarmed", mission_state="completed")
        else:
            if command == "flip" and self.flip is None:
                raise MissionError("command 'flip': this planner has no flip controller "
                                   "(the planner's flip_methods parameter builds one)")
            items = command_items(command, altitude_m, position_m, yaw_rad)
            if self.flip_method:
                items = tuple({**i, "method": self.flip_method} if i["type"] == "flip" else i for i in items)
            runner = MissionRunner(Mission(f"command-{command}", "", "", math.inf, items), self.flip)
            if prev is not None:
                runner.yaw = prev.yaw
                runner.sp.mode, runner.sp.armed = prev.sp.mode, prev.sp.armed
            elif command == "arm" or self.sp.armed:
                runner.sp.armed = self.sp.armed
            self.runner, self.sp = runner, runner.sp
        self.last_command = command

    def fly(self, items: list[dict], name: str = "uploaded") -> None:
        """Fly a list of mission items (e.g. a MAVLink mission) from the next update; the
        setpoint's `item` indexes this list. Raises MissionError for an item it cannot fly."""
        checked = []
        for i, raw in enumerate(items):
            kind = raw.get("type")
            if kind not in ITEM_KEYS:
                raise MissionError(f"{name}: item {i}: type {kind!r} not one of {', '.join(ITEM_KEYS)}")
            if kind == "flip" and self.flip is None:
                raise MissionError(f"{name}: item {i}: this planner has no flip controller "
                                   f"(the planner's flip_methods parameter builds one)")
            unknown = set(raw) - set(ITEM_KEYS[kind]) - {"type"}
            if unknown:
                raise MissionError(f"{name}: item {i}: unknown keys {sorted(unknown)} for {kind}")
            method = {"method": self.flip_method} if kind == "flip" and self.flip_method else {}
            checked.append({"type": kind, **ITEM_KEYS[kind], **method, **raw})
        if not checked:
            raise MissionError(f"{name}: no items")
        prev = self.runner
        runner = MissionRunner(Mission(name, "", "", math.inf, tuple(checked)), self.flip)
        if prev is not None:
            runner.yaw = prev.yaw
        runner.sp.mode, runner.sp.armed = self.sp.mode, self.sp.armed
        self.runner, self.sp = runner, runner.sp
        self.last_command = "mission"

    def update(self, t: float, position, velocity) -> Setpoint:
        if self.runner is None:
            return self.sp
        self.sp = self.runner.update(t, position, velocity)
        return self.sp
