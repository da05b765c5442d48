"""Vehicle description: a frozen dataclass loaded from flight/vehicles/<name>.toml.

Allocation (rotor forces F -> body wrench u), with motor i at (x_i, y_i) in body FLU:
    u = [thrust_total_n, torque_x, torque_y, torque_z] = M @ F
    thrust_total = sum F_i
    torque_x     = sum  y_i F_i                     (force up at +y rolls right-side-down: +x torque)
    torque_y     = sum -x_i F_i                     (force up at +x pitches nose up: -y torque)
    torque_z     = sum  sign_i * yaw_moment_m * F_i (rotor reaction torque, lambda = km/kf)
"""
from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path

import functools

import numpy as np

VEHICLES_DIR = Path(__file__).resolve().parent / "vehicles"
# trained parameter files an airframe may name (gyrovertical_params): `zenpilot train-gyrovertical`'s output
PARAMS_DIR = Path(__file__).resolve().parent / "params"


class VehicleError(ValueError):
    """Bad, missing or unknown vehicle description."""


@dataclass(frozen=True)
class Vehicle:
    name: str
    description: str
    mass_kg: float
    inertia_kg_m2: tuple[float, float, float]  # diagonal Ixx, Iyy, Izz
    motor_positions_m: tuple[tuple[float, float], ...]  # 4 x (x, y), body FLU
    motor_yaw_torque_sign: tuple[int, int, int, int]
    yaw_moment_m: float
    max_thrust_n: float  # per motor
    drag_n_per_m_s: float
    motor_time_constant_s: float  # s: the rotor speed's first-order lag (flight/motor_model.py)
    pwm_min_us: float  # the ESC's pulse width at 0 N ...
    pwm_max_us: float  # ... and at max_thrust_n (flight/motor_model.thrust_to_pwm)
    # the flight pack (simulator/battery.py): current = idle + a_per_n * total thrust,
    # voltage = cells * LiPo curve(charge left) - current * resistance
    battery_capacity_mah: float
    battery_cells: int
    battery_internal_resistance_ohm: float
    battery_current_a_per_n: float
    battery_idle_current_a: float
    gravity_m_s2: float = 9.81
    min_thrust_n: float = 0.0
    # optional extras of document 001 (None when the file does not give them)
    thrust_coefficient_kf: float | None = None   # N s^2 (rad^-2): rotor thrust kf w^2, > 0
    moment_coefficient_km: float | None = None   # N m s^2: rotor yaw torque km w^2, km / kf = yaw_moment_m
    max_rotor_speed_rad_s: float | None = None   # rad/s, > 0
    rotor_inertia_kg_m2: float | None = None
    max_body_rate_rad_s: float | None = None
    # the tilt this airframe's position laws may ask for (None: the position service's
    # max_tilt_deg alone); a heavy frame with little torque needs less (q820.toml says why)
    max_tilt_deg: float | None = None
    # the gyro-vertical's trained parameter file for this airframe, a name in flight/params/ (the
    # attitude service's gyrovertical_params, when set, overrides it; None: the service's default)
    gyrovertical_params: str | None = None

    @property
    def gyrovertical_params_path(self) -> Path | None:
        return None if self.gyrovertical_params is None else PARAMS_DIR / self.gyrovertical_params

    @functools.cached_property  # computed once: the mixer runs at 400 Hz
    def allocation(self) -> np.ndarray:
        """4x4 M with [thrust_total_n, torque_x, torque_y, torque_z] = M @ F."""
        xy = np.asarray(self.motor_positions_m, dtype=np.float64)
        signs = np.asarray(self.motor_yaw_torque_sign, dtype=np.float64)
        return np.vstack([
            np.ones(4),
            xy[:, 1],
            -xy[:, 0],
            signs * self.yaw_moment_m,
        ])

    @functools.cached_property
    def allocation_inv(self) -> np.ndarray:
        return np.linalg.inv(self.allocation)

    @functools.cached_property
    def max_angular_accel_rad_s2(self) -> np.ndarray:
        """Largest angular acceleration per body axis (roll, pitch, yaw) the rotors give,
        each axis alone, at a collective in mid-range: sum_j |M[axis, j]| (max - min thrust) / 2 / I."""
        span = self.max_thrust_n - self.min_thrust_n
        torque = np.abs(self.allocation[1:]).sum(axis=1) * span / 2.0
        return torque / np.asarray(self.inertia_kg_m2, dtype=np.float64)

    def tilt_limit_rad(self, requested_deg: float) -> float:
        """The tilt the position laws use: the smaller of the requested limit (the position
        service's max_tilt_deg, live-tunable) and this airframe's own."""
        limit = requested_deg if self.max_tilt_deg is None else min(requested_deg, self.max_tilt_deg)
        return float(np.radians(limit))

    @property
    def inertia_matrix_kg_m2(self) -> np.ndarray:
        return np.diag(np.asarray(self.inertia_kg_m2, dtype=np.float64))

    @property
    def hover_thrust_per_motor_n(self) -> float:
        return self.mass_kg * self.gravity_m_s2 / 4.0


# field -> (kind, required); kinds: "str", "pos" (>0 float), "nonneg", "count" (int >= 1), "vec3pos", "xy4",
# "sign4"
_FIELDS: dict[str, tuple[str, bool]] = {
    "name": ("str", True),
    "description": ("str", False),
    "mass_kg": ("pos", True),
    "inertia_kg_m2": ("vec3pos", True),
    "motor_positions_m": ("xy4", True),
    "motor_yaw_torque_sign": ("sign4", True),
    "yaw_moment_m": ("pos", True),
    "max_thrust_n": ("pos", True),
    "drag_n_per_m_s": ("nonneg", True),
    "gravity_m_s2": ("pos", False),
    "min_thrust_n": ("nonneg", False),
    "motor_time_constant_s": ("pos", True),
    "pwm_min_us": ("pos", True),
    "pwm_max_us": ("pos", True),
    "battery_capacity_mah": ("pos", True),
    "battery_cells": ("count", True),
    "battery_internal_resistance_ohm": ("nonneg", True),
    "battery_current_a_per_n": ("nonneg", True),
    "battery_idle_current_a": ("nonneg", True),
    "thrust_coefficient_kf": ("pos", False),
    "moment_coefficient_km": ("pos", False),
    "max_rotor_speed_rad_s": ("pos", False),
    "rotor_inertia_kg_m2": ("pos", False),
    "max_body_rate_rad_s": ("pos", False),
    "max_tilt_deg": ("pos", False),
    "gyrovertical_params": ("paramfile", False),
}


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _check(src: str, key: str, kind: str, v):
    def bad(why: str) -> VehicleError:
        return VehicleError(f"{src}: field '{key}': {why} (got {v!r})")

    if kind == "str":
        if not isinstance(v, str):
            raise bad("must be a string")
        return v
    if kind in ("pos", "nonneg"):
        if not _is_num(v):
            raise bad("must be a finite number")
        if kind == "pos" and v <= 0 or kind == "nonneg" and v < 0:
            raise bad("must be > 0" if kind == "pos" else "must be >= 0")
        return float(v)
    if kind == "count":
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise bad("must be an integer >= 1")
        return v
    if kind == "vec3pos":
        if not isinstance(v, list) or len(v) != 3 or not all(_is_num(e) and e > 0 for e in v):
            raise bad("must be a list of 3 positive numbers")
        return tuple(float(e) for e in v)
    if kind == "xy4":
        if (not isinstance(v, list) or len(v) != 4
                or not all(isinstance(p, list) and len(p) == 2 and all(_is_num(e) for e in p) for p in v)):
            raise bad("must be a list of 4 [x, y] pairs of numbers")
        return tuple((float(p[0]), float(p[1])) for p in v)
    if kind == "sign4":
        if (not isinstance(v, list) or len(v) != 4
                or not all(isinstance(e, int) and not isinstance(e, bool) and e in (1, -1) for e in v)):
            raise bad("must be a list of 4 integers, each +1 or -1")
        return tuple(v)
    if kind == "paramfile":
        # a bare name, so the airframe file cannot point outside the shipped parameters
        if not isinstance(v, str) or not re.fullmatch(r"[A-Za-z0-9_\-.]+\.toml", v) or v.startswith("."):
            raise bad("must be the name of a .toml file in flight/params/ (no folders)")
        # not opened here: `zenpilot train-gyrovertical --vehicle` loads the airframe before its file
        # exists; the attitude service refuses a missing or bad one when it flies the gyro-vertical
        return v
    raise AssertionError(kind)


def vehicle_from_dict(d: dict, src: str = "<dict>") -> Vehicle:
    """Validate a parsed TOML table and build the Vehicle; src names the file in errors."""
    unknown = sorted(set(d) - set(_FIELDS))
    if unknown:
        raise VehicleError(f"{src}: field '{unknown[0]}': unknown field")
    kwargs = {}
    for key, (kind, required) in _FIELDS.items():
        if key not in d:
            if required:
                raise VehicleError(f"{src}: field '{key}': missing")
            continue
        kwargs[key] = _check(src, key, kind, d[key])
    veh = Vehicle(**kwargs)

    if veh.min_thrust_n >= veh.max_thrust_n:
        raise VehicleError(f"{src}: field 'min_thrust_n': must be below max_thrust_n")
    if veh.thrust_coefficient_kf is None and veh.max_rotor_speed_rad_s is None:
        raise VehicleError(f"{src}: field 'thrust_coefficient_kf': missing, and no max_rotor_speed_rad_s "
                           "to take it from (the rotor speed's scale, flight/motor_model.py)")
    if veh.pwm_min_us >= veh.pwm_max_us:
        raise VehicleError(f"{src}: field 'pwm_max_us': must be above pwm_min_us")
    if veh.hover_thrust_per_motor_n >= veh.max_thrust_n:
        raise VehicleError(f"{src}: field 'max_thrust_n': cannot lift mass_kg (hover needs "
                           f"{veh.hover_thrust_per_motor_n:.3f} N per motor)")
    if veh.thrust_coefficient_kf is not None and veh.moment_coefficient_km is not None:
        ratio = veh.moment_coefficient_km / veh.thrust_coefficient_kf
        if not math.isclose(ratio, veh.yaw_moment_m, rel_tol=1e-6):
            raise VehicleError(f"{src}: field 'moment_coefficient_km': km / kf = {ratio:.6g} m must equal "
                               f"yaw_moment_m ({veh.yaw_moment_m:.6g} m): one motor model")
    m = veh.allocation
    if abs(np.linalg.det(m)) < 1e-12:
        raise VehicleError(f"{src}: field 'motor_positions_m': allocation matrix is singular")
    # The mixer moves collective thrust along [1,1,1,1]; that must not create torque,
    # i.e. motors centred on the CG and yaw signs balanced.
    if not np.allclose(m @ np.ones(4), [4, 0, 0, 0], atol=1e-9):
        raise VehicleError(f"{src}: field 'motor_positions_m': motors must be centred on the "
                           "centre of mass with balanced motor_yaw_torque_sign")
    return veh


def load_vehicle(name_or_path: str) -> Vehicle:
    """'x250' -> flight/vehicles/x250.toml; a path ending in .toml -> that file."""
    if str(name_or_path).endswith(".toml"):
        path = Path(name_or_path)
    else:
        if not re.fullmatch(r"[A-Za-z0-9_\-]+", str(name_or_path)):
            raise VehicleError(f"bad vehicle name {name_or_path!r}")
        path = VEHICLES_DIR / f"{name_or_path}.toml"
        if not path.is_file():
            known = sorted(p.stem for p in VEHICLES_DIR.glob("*.toml"))
            raise VehicleError(f"{path}: unknown vehicle {name_or_path!r} (known: {', '.join(known)})")
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise VehicleError(f"{path}: file not found") from None
    except tomllib.TOMLDecodeError as e:
        raise VehicleError(f"{path}: not valid TOML: {e}") from None
    return vehicle_from_dict(data, str(path))


def per_vehicle_cache(make):
    """A getter of make(vehicle), made once per vehicle object: keyed by identity (hashing a
    dataclass of tuples costs more than the 400 Hz work it serves); an entry holds its vehicle,
    so an id is never reused while the entry lives."""
    cache: dict[int, tuple] = {}

    def get(vehicle):
        entry = cache.get(id(vehicle))
        if entry is not None and entry[0] is vehicle:
            return entry[1]
        if len(cache) >= 64:
            cache.clear()
        value = make(vehicle)
        cache[id(vehicle)] = (vehicle, value)
        return value
    return get
