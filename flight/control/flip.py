"""The 360-degree roll flip of document 001: phase machine, adaptive targets, baseline, metrics.

Phases idle -> takeoff -> flip -> recovery -> land -> done change on feedback only
(altitude, vertical speed, accumulated roll, tilt, body rates). For each phase the
machine gives the iLQR its target states (H+1, 13) (flight/control/ilqr.py's x layout).

Accumulated roll is the ZYX Euler roll from the quaternion, unwrapped sample to
sample (as the thesis's Appendix И does with roll_diff): unlike integrating the
body roll rate it does not drift with gyro bias, and for a roll flip (pitch ~ 0)
the Euler roll is continuous through inversion. It needs samples closer than
half a turn apart (at 25 rad/s, any rate above 8 Hz).

Deviations from the thesis's code, which the thesis's own transitions need:
the thesis compares atan2 roll (wrapped to (-pi, pi]) with 2 pi, which can never
match; here the roll is accumulated. Flip targets are spread along the horizon
from the current roll to the adaptive target (the thesis spreads them from 0,
i.e. from level, in the flip phase and from the current roll in recovery).
Recovery aims at level (accumulated roll 2 pi) with zero rate, not back through
the turn.
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from flight.control.laws import STOPPING_ACCEL_FRACTION, attitude_law, position_law, stopping_accel
from flight.control.mixer import mix
from flight.quat import TWO_PI, quat_multiply, quat_to_euler, wrap_angle_float
from flight.quat import quat_tilt as tilt_rad  # the name its users here know it by
from flight.vehicle import Vehicle


class Phase(str, enum.Enum):
    IDLE = "idle"
    TAKEOFF = "takeoff"
    FLIP = "flip"
    RECOVERY = "recovery"
    LAND = "land"
    DONE = "done"


def quat_from_roll(roll_rad: float) -> np.ndarray:
    """Rotation about the world x axis (yaw 0, pitch 0), [w, x, y, z]."""
    return np.array([math.cos(roll_rad / 2), math.sin(roll_rad / 2), 0.0, 0.0])


def braking_reference(start_m, velocity_m_s, t_s, decel_m_s2: float):
    """Horizontal position and velocity at times t_s (N,) after start of a straight-line stop
    from velocity_m_s (2,) at constant deceleration decel_m_s2: (positions (N, 2), velocities
    (N, 2)); at rest from v / decel on, at start + v |v| / (2 decel)."""
    v0 = np.asarray(velocity_m_s, dtype=np.float64)
    speed = float(np.linalg.norm(v0))
    t = np.asarray(t_s, dtype=np.float64)[:, None]
    if speed < 1e-9:
        return np.repeat(np.asarray(start_m, dtype=np.float64)[None, :2], len(t), axis=0), np.zeros((len(t), 2))
    direction = v0 / speed
    tau = np.minimum(np.maximum(t, 0.0), speed / decel_m_s2)
    travelled = speed * tau - 0.5 * decel_m_s2 * tau * tau
    return np.asarray(start_m)[None, :2] + travelled * direction, (speed - decel_m_s2 * tau) * direction


def stopping_point(start_m, velocity_m_s, decel_m_s2: float) -> np.ndarray:
    """Where braking_reference comes to rest (2,): its operations at t = inf (tau = speed /
    decel) on floats, the same bits (tests/unit/flight/control/test_flip.py), a few times cheaper."""
    v, start = np.asarray(velocity_m_s, dtype=np.float64), np.asarray(start_m)
    if v.shape != (2,) or start.dtype != np.float64 or start.shape[0] < 2:   # odd input: braking_reference decides
        return braking_reference(start_m, velocity_m_s, [np.inf], decel_m_s2)[0][0]
    vx, vy = v.tolist()
    speed = math.sqrt(vx * vx + vy * vy)   # np.linalg.norm of a 2-vector: the squares summed in order
    if not speed >= 1e-9:   # at rest (or NaN): braking_reference's own case
        return braking_reference(start_m, velocity_m_s, [np.inf], decel_m_s2)[0][0]
    tau = speed / decel_m_s2
    travelled = speed * tau - 0.5 * decel_m_s2 * tau * tau
    sx, sy = start[:2].tolist()
    return np.array([sx + travelled * (vx / speed), sy + travelled * (vy / speed)])


def quat_from_yaw(yaw_rad: float) -> np.ndarray:
    """Rotation about the world z axis, [w, x, y, z]."""
    return np.array([math.cos(yaw_rad / 2), 0.0, 0.0, math.sin(yaw_rad / 2)])


class RollAccumulator:
    """Accumulated roll (rad) by unwrapping the Euler roll between samples."""

    def __init__(self):
        self.roll_rad = 0.0
        self._last = None

    def reset(self, q) -> None:
        self.roll_rad = 0.0
        self._last = quat_to_euler(q)[0]

    def update(self, q) -> float:
        roll = quat_to_euler(q)[0]
        if self._last is None:
            self._last = roll
        step = wrap_angle_float(roll - self._last)
        self.roll_rad += step
        self._last = roll
        return self.roll_rad


@dataclass(frozen=True)
class FlipConfig:
    """Phase-machine settings; the thesis's values by default (THESIS_FLIP: and its take-off
    check on the altitude alone)."""
    flip_altitude_m: float = 5.0
    takeoff_tolerance_m: float = 0.1       # |z - flip altitude| to start the flip
    hover_speed_m_s: float = 0.3           # ... with |v| below this (a flip from hover)
    hover_rate_rad_s: float = 0.3          # ... and body rates below this
    # False: the altitude tolerance alone starts the flip, as the thesis's code does
    # (Appendix В: abs(z - takeoff_altitude) < takeoff_tol), climbing or not
    takeoff_hover_check: bool = True
    flip_duration_s: float = 1.0           # T: expected roll 2 pi t / T
    flip_gain_base: float = 0.8            # gain = base + 0.3 tanh(roll error)
    flip_gain_tanh: float = 0.3
    flip_rate_error_gain: float = 0.2      # target rate 2 pi / T + 0.2 roll error
    # False (thesis): one adaptive target at t, spread linearly along the horizon, rate
    # 2 pi / T throughout. True: the adaptive rule applied at every horizon step to a
    # smooth reference (rest to rest, quintic), so the plan sees the whole turn and its end.
    lookahead: bool = False
    max_lead_rad: float = 2.5
    turn_tolerance_rad: float = 0.1        # flip -> recovery at 2 pi - this
    recovery_gain_base: float = 0.6        # gain = 0.6 + 0.4 |error| / pi
    recovery_gain_error: float = 0.4
    # False (thesis): recovery targets ramp from the current roll to level along the
    # horizon. True: level and at rest over the whole horizon.
    recovery_direct: bool = False
    # False (thesis): recovery holds the horizontal position where it is, at rest, so the
    # plan brakes the turn's lateral speed while it levels (tilted, 10-15 degrees, for a few
    # tenths of a second). True: level first: the horizontal targets coast at the current
    # horizontal velocity (p + v t, v), so nothing asks for a tilt; the braking is left to the
    # hold that follows (land / the flip item's settle).
    recovery_coast: bool = False
    # False (thesis): recovery targets the heading the flip started with (yaw 0). True: the
    # heading it has now, so the recovery levels and stops every rate, yaw's too, and
    # leaves turning back to the flip's heading to the hold that follows (the plus frame's
    # yaw authority is its weakest: turning back at once keeps the body rates above the
    # level criterion after the tilt is within it).
    recovery_hold_heading: bool = False
    # The hold after recovery (the runner's settle, at the flip's altitude). None: hold
    # where the recovery ended, so the plan brakes the turn's lateral speed and comes
    # back, tilting past the level criterion (5 deg) for a while after the recovery. A
    # value: stop along a straight line at this deceleration (0.5 m/s^2 asks ~3 deg of tilt)
    # and hold where it stops.
    settle_decel_m_s2: float | None = None
    # ... and its heading: None, straight back to the flip's (yaw 0); a value: from the one
    # the recovery ended with back to yaw 0 at this rate (the level criterion allows 0.5 rad/s
    # of body rate in all)
    settle_yaw_rate_rad_s: float | None = None
    # The flip's own reference (lookahead only) starts the turn windup_s after the phase
    # does (the time to climb, climb_m) and may wind up in it: a roll of -windup_rad and
    # back, pushing towards +y first against the turn's own lateral impulse (towards -y,
    # forced by the roll torque).
    windup_rad: float = 0.0
    windup_s: float = 0.0
    # The flip phase's altitude target above the flip's start (m): upside down the rotors
    # pull towards the ground, so a target above asks the plan to climb before the turn
    # and carry the speed through it. Recovery holds the start's altitude again.
    climb_m: float = 0.0
    level_tolerance_rad: float = 0.1       # recovery -> land: roll back within this ...
    level_rate_rad_s: float = 0.5          # ... and body rates below this
    landing_altitude_m: float = 0.2        # land -> done below this
    landing_speed_m_s: float = 0.8         # descent target


THESIS_FLIP = FlipConfig(takeoff_hover_check=False)
# The project's flip (the one source: flight/control/flip_runner.py and bench/flip_sim.py fly it):
# a look-ahead quintic turn of 0.9 s, 0.3 s after the phase starts, with the altitude target 1.5 m
# above the start, so the plan climbs in those 0.3 s and carries the upward speed through the
# inverted half; no wind-up roll (with the climb it only shifts the turn's lateral swing). The
# climbs, wind-ups and recoveries tried: docs/flip-history.md.
PROJECT_FLIP = FlipConfig(lookahead=True, flip_duration_s=0.9, windup_s=0.3, climb_m=1.5, recovery_coast=True,
                          recovery_hold_heading=True, settle_decel_m_s2=0.5, settle_yaw_rate_rad_s=0.25)


def smooth_roll_reference(t_s, duration_s: float):
    """Rest-to-rest roll 0 -> 2 pi over duration_s (quintic 10s^3 - 15s^4 + 6s^5): (roll, rate)."""
    s = np.clip(np.asarray(t_s, dtype=np.float64) / duration_s, 0.0, 1.0)
    roll = TWO_PI * (10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5)
    rate = TWO_PI / duration_s * (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4)
    return roll, rate


def flip_reference(t_s, config: FlipConfig):
    """(roll, rate) of the flip's reference: the optional wind-up, then the quintic turn."""
    t = np.asarray(t_s, dtype=np.float64)
    roll, rate = smooth_roll_reference(t - config.windup_s, config.flip_duration_s)
    if config.windup_s > 0:
        s = np.clip(t / config.windup_s, 0.0, 1.0)
        roll = roll - config.windup_rad * np.sin(math.pi * s) ** 2
        rate = rate - config.windup_rad * math.pi / config.windup_s * np.sin(2 * math.pi * s) * (t < config.windup_s)
    return roll, rate


class FlipPhaseMachine:
    """Feedback phase machine and target generator for the iLQR planner.

    update(t_s, x) advances the phase from the state estimate x (13,), then
    targets(t_s, x) gives the (H+1, 13) target states for that phase.
    """

    def __init__(self, config: FlipConfig, horizon: int, dt_s: float):
        self.config = config
        self.horizon = horizon
        self.dt_s = dt_s
        self.phase = Phase.IDLE
        self.roll = RollAccumulator()
        self.phase_start_s = 0.0
        self.flip_point_m = np.zeros(3)  # where the flip started: held through recovery
        self.home_m = np.zeros(3)
        self._settle = None  # (t_s, yaw) at the hold's start
        self._brake = None   # (t_s, position (2,), velocity (2,)) the stop is planned from

    def start(self, t_s: float, x) -> None:
        self.home_m = np.array(x[0:3], dtype=np.float64)
        self._enter(Phase.TAKEOFF, t_s)

    def _enter(self, phase: Phase, t_s: float) -> None:
        self.phase = phase
        self.phase_start_s = t_s

    def update(self, t_s: float, x) -> Phase:
        c = self.config
        x = np.asarray(x, dtype=np.float64)
        q, rates = x[6:10], x[10:13]
        roll = self.roll.update(q)
        rate_norm = float(np.linalg.norm(rates))
        if self.phase == Phase.TAKEOFF:
            hover = (np.linalg.norm(x[3:6]) < c.hover_speed_m_s and rate_norm < c.hover_rate_rad_s
                     and tilt_rad(q) < c.level_tolerance_rad)
            if abs(x[2] - c.flip_altitude_m) < c.takeoff_tolerance_m and (hover or not c.takeoff_hover_check):
                self.roll.reset(q)
                self.flip_point_m = x[0:3].copy()
                self._enter(Phase.FLIP, t_s)
        elif self.phase == Phase.FLIP:
            if roll >= TWO_PI - c.turn_tolerance_rad:
                self._enter(Phase.RECOVERY, t_s)
        elif self.phase == Phase.RECOVERY:
            if abs(roll - TWO_PI) <= c.level_tolerance_rad and rate_norm < c.level_rate_rad_s:
                self._enter(Phase.LAND, t_s)
        elif self.phase == Phase.LAND and x[2] < c.landing_altitude_m:
            self._enter(Phase.DONE, t_s)
        return self.phase

    def settle_hold_point(self, t_s: float, x) -> np.ndarray:
        """Where the hold after recovery ends up: at the flip's altitude, where the recovery
        ended (the first call, at the hold's start), or with settle_decel_m_s2 where a straight
        stop from the velocity then takes the vehicle. While that stop lasts, a vehicle that
        would stop further on (it slowed less than planned: still accelerating off a tilted
        recovery, a heavier plant climbing back) moves the stop on from where it is now, so
        the plan never asks it to come back against its own speed."""
        x = np.asarray(x, dtype=np.float64)
        decel = self.config.settle_decel_m_s2
        if self._settle is None:
            self._settle = (t_s, quat_to_euler(x[6:10])[2] if self.config.settle_yaw_rate_rad_s else 0.0)
            self._brake = (t_s, x[0:2].copy(), x[3:5].copy() if decel else np.zeros(2))
        elif decel:
            start_t_s, start_m, velocity_m_s = self._brake
            speed = float(np.linalg.norm(velocity_m_s))
            if speed > 0.0 and t_s - start_t_s < speed / decel:
                further = stopping_point(x[0:2], x[3:5], decel) - stopping_point(start_m, velocity_m_s, decel)
                if np.dot(further, velocity_m_s) > 0.0:
                    self._brake = (t_s, x[0:2].copy(), x[3:5].copy())
        _, start_m, velocity_m_s = self._brake
        stop_m = stopping_point(start_m, velocity_m_s, decel or 1.0)  # no decel: zero velocity, stays
        return np.array([stop_m[0], stop_m[1], self.flip_point_m[2]])

    def settle_targets(self, t_s: float, x) -> np.ndarray:
        """Target states (H+1, 13) of the hold after recovery: level, at the flip's altitude,
        horizontally along the stop of settle_hold_point, turning back to yaw 0
        (settle_yaw_rate_rad_s)."""
        hold_m = self.settle_hold_point(t_s, x)
        brake_t_s, start_m, velocity_m_s = self._brake
        positions, velocities = braking_reference(start_m, velocity_m_s,
                                                  t_s - brake_t_s + np.arange(self.horizon + 1) * self.dt_s,
                                                  self.config.settle_decel_m_s2 or 1.0)
        targets = np.zeros((self.horizon + 1, 13))
        targets[:, 0:2], targets[:, 2], targets[:, 3:5] = positions, hold_m[2], velocities
        start_t_s, start_yaw_rad = self._settle
        times = t_s - start_t_s + np.arange(self.horizon + 1) * self.dt_s
        yaw_rate = -math.copysign(self.config.settle_yaw_rate_rad_s or 0.0, start_yaw_rad)
        turning = times < abs(start_yaw_rad) / max(abs(yaw_rate), 1e-9)
        yaws = np.where(turning, start_yaw_rad + yaw_rate * times, 0.0)
        targets[:, 6:10] = [[math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)] for yaw in yaws.tolist()]  # quat_from_yaw's
        targets[:, 12] = np.where(turning, yaw_rate, 0.0)
        return targets

    def targets(self, t_s: float, x) -> np.ndarray:
        """Target states (H+1, 13) for the current phase; the last repeats the one before."""
        c = self.config
        x = np.asarray(x, dtype=np.float64)
        n = self.horizon
        alphas = np.arange(n) / n
        position = np.repeat(x[None, 0:3], n, axis=0)
        rolls = np.zeros(n)
        rate = np.zeros((n, 3))
        roll_now = self.roll.roll_rad
        if self.phase == Phase.TAKEOFF:
            position[:, 2] = c.flip_altitude_m
        elif self.phase == Phase.FLIP:
            t_local = t_s - self.phase_start_s
            position[:] = self.flip_point_m
            position[:, 2] += c.climb_m
            if c.lookahead:
                roll_ref, rate_ref = flip_reference(t_local + np.arange(n) * self.dt_s, c)
                error = roll_ref - roll_now
                lead = (c.flip_gain_base + c.flip_gain_tanh * np.tanh(error)) * error
                # the attitude error is the geodesic angle: a target a half turn or more
                # ahead would alias onto one behind, so the lead is capped below pi
                rolls = roll_now + np.clip(lead, -c.max_lead_rad, c.max_lead_rad)
                rate[:, 0] = rate_ref + c.flip_rate_error_gain * error[0]
            else:
                error = TWO_PI * min(max(t_local, 0.0), c.flip_duration_s) / c.flip_duration_s - roll_now
                gain = c.flip_gain_base + c.flip_gain_tanh * math.tanh(error)
                rolls = roll_now + alphas * gain * error
                rate[:, 0] = TWO_PI / c.flip_duration_s + c.flip_rate_error_gain * error
        elif self.phase == Phase.RECOVERY and c.recovery_direct:
            rolls[:] = TWO_PI  # stop where it is: going back to the point would tilt it again
            position[:, 2] = self.flip_point_m[2]
        elif self.phase == Phase.RECOVERY:
            # level first: hold the flip's altitude, stop where it is (land returns to the point)
            error = TWO_PI - roll_now
            gain = c.recovery_gain_base + c.recovery_gain_error * abs(error) / math.pi
            rolls = roll_now + alphas * gain * error
            position[:, 2] = self.flip_point_m[2]
        elif self.phase == Phase.LAND:
            position[:, 2] = max(x[2] - c.landing_speed_m_s * n * self.dt_s, 0.0)
        targets = np.zeros((n + 1, 13))
        targets[:n, 0:3] = position
        if self.phase == Phase.RECOVERY and c.recovery_coast:
            targets[:n, 0:2] = x[0:2] + x[3:5] * (np.arange(n) * self.dt_s)[:, None]
            targets[:n, 3:5] = x[3:5]
        if self.phase == Phase.RECOVERY and c.recovery_hold_heading:
            heading = quat_from_yaw(quat_to_euler(x[6:10])[2])
            targets[:n, 6:10] = np.array([quat_multiply(heading, quat_from_roll(r)) for r in rolls])
        else:
            targets[:n, 6:10] = [[math.cos(r / 2), math.sin(r / 2), 0.0, 0.0] for r in rolls.tolist()]  # quat_from_roll's
        targets[:n, 10:13] = rate
        targets[n] = targets[n - 1]
        if self.phase in (Phase.IDLE, Phase.DONE):
            targets[:, 0:3] = x[0:3]
        return targets


# --- baseline of Appendix И --------------------------------------------------------

@dataclass(frozen=True)
class BaselineConfig:
    """Appendix И: hover at hover_altitude_m, full thrust up to flip_altitude_m, a fixed
    roll rate at low thrust until 315 degrees, then recovery thrust with the attitude
    hold. Thrusts are fractions of the four rotors' maximum.

    Roll and recovery go through a rate loop (torque = I k_rate (rate_sp - rate), as a
    flight controller's inner loop; Appendix И sends rate set-points to Clover's PX4): the
    fixed command while rolling, then an attitude P loop's set-point clipped to
    max_rate_rad_s, so the vehicle stops turning when the command ends.

    roll_rate_rad_s: Appendix И's 17 rad/s is Clover's. On q820 the roll torque
    (0.15 m x 6.53 N) gives at most 21.8 rad/s^2, so stopping from 17 rad/s takes
    6.6 rad, more than a turn: the 45 degrees left at 315 degrees allow about
    sqrt(2 x 21.8 x 0.79) = 5.9 rad/s. THESIS_BASELINE keeps 17 (it over-rotates)."""
    hover_altitude_m: float = 5.0
    flip_altitude_m: float = 6.0
    climb_thrust: float = 1.0
    roll_rate_rad_s: float = 6.0
    flip_thrust: float = 0.25
    stop_roll_rad: float = math.radians(315.0)
    recovery_thrust: float = 0.6
    rate_gain_1_s: float = 20.0            # body-rate loop, torque = I k (rate_sp - rate)
    recovery_attitude_gain_1_s: float = 6.0  # attitude P loop: rate_sp = k (angle_ref - angle)
    max_rate_rad_s: float = 6.0            # its set-point limit
    attitude_gain: float = 16.0            # law (8) of 000, k = alpha (take-off, hold)
    # law (8)'s rate demand capped as the stack's attitude service caps it (0: law (8) as
    # printed): uncapped, the q820's saturated hold can limit-cycle and, the mixer raising
    # the collective to keep the torque, climb away (docs/results.md)
    stopping_accel_fraction: float = STOPPING_ACCEL_FRACTION
    position_gain: float = 4.0             # laws (9)-(11) of 000, k = alpha
    hold_max_tilt_rad: float = 0.6         # the hold's position laws (before the flip): at most
                                           # this and the vehicle's own limit (Vehicle.tilt_limit_rad)
    land_position_gain: float = 1.5        # after recovery: altitude hold, horizontal damping ...
    land_max_tilt_rad: float = 0.07        # ... gently (the metrics' level is 5 degrees)
    ready_rate_rad_s: float = 0.05         # Appendix И: |roll rate| < 0.05 and |roll| < 2 deg
    ready_roll_rad: float = math.radians(2.0)
    ready_altitude_tolerance_m: float = 0.5
    level_tolerance_rad: float = 0.1       # recovery ends (then hold altitude) when level ...
    level_rate_rad_s: float = 0.5          # ... and slow


THESIS_BASELINE = BaselineConfig(roll_rate_rad_s=17.0, max_rate_rad_s=17.0)
# Appendix И's full-thrust climb from the hover to its roll (5 -> 6 m); a flip item may change it
BASELINE_CLIMB_M = BaselineConfig.flip_altitude_m - BaselineConfig.hover_altitude_m


class BaselineFlip:
    """The thesis's model-free flip as a pure controller: command(t_s, x) -> rotor forces (N)."""

    def __init__(self, vehicle: Vehicle, config: BaselineConfig = BaselineConfig()):
        self.vehicle = vehicle
        self.config = config
        self.phase = Phase.TAKEOFF
        self.roll = RollAccumulator()
        self.rolling = False
        self.hold_point_m = None
        self._max_total_n = 4.0 * vehicle.max_thrust_n
        self._max_accel = stopping_accel(vehicle.max_angular_accel_rad_s2, config.stopping_accel_fraction)

    def command(self, t_s: float, x) -> np.ndarray:
        c, v = self.config, self.vehicle
        x = np.asarray(x, dtype=np.float64)
        q, rates = x[6:10], x[10:13]
        roll_acc = self.roll.update(q)
        roll, pitch, yaw = quat_to_euler(q)
        if self.phase == Phase.TAKEOFF:
            if (abs(x[2] - c.hover_altitude_m) < c.ready_altitude_tolerance_m
                    and abs(rates[0]) < c.ready_rate_rad_s and abs(roll) < c.ready_roll_rad):
                self.phase = Phase.FLIP
                self.roll.reset(q)
                self._yaw = yaw
                roll_acc = 0.0
            else:
                return self._hold(x, np.array([x[0], x[1], c.hover_altitude_m]) if self.hold_point_m is None
                                  else self.hold_point_m, roll, pitch, yaw)
        if self.phase == Phase.FLIP:
            if not self.rolling and x[2] >= c.flip_altitude_m:
                self.rolling = True
            if roll_acc > c.stop_roll_rad:
                self.phase = Phase.RECOVERY
            elif not self.rolling:
                torque = attitude_law(v.inertia_kg_m2, (roll, pitch, yaw), rates, (0.0, 0.0, self._yaw),
                                      c.attitude_gain, c.attitude_gain, self._max_accel)
                return self._mix(c.climb_thrust * self._max_total_n, torque)
            else:
                return self._rate_loop(np.array([c.roll_rate_rad_s, 0.0, 0.0]), rates, c.flip_thrust)
        if self.phase == Phase.RECOVERY:
            if abs(roll) < c.level_tolerance_rad and np.linalg.norm(rates) < c.level_rate_rad_s:
                self.phase = Phase.LAND  # hand over to the altitude hold, as Appendix И lands
                self.hold_point_m = x[0:3].copy()
            else:
                error = np.array([-roll, -pitch, wrap_angle_float(self._yaw - yaw)])
                rate_sp = np.clip(c.recovery_attitude_gain_1_s * error, -c.max_rate_rad_s, c.max_rate_rad_s)
                return self._rate_loop(rate_sp, rates, c.recovery_thrust)
        # land (as Appendix И hands over): hold the altitude, damp the horizontal speed
        return self._hold(x, np.array([x[0], x[1], self.hold_point_m[2]]), roll, pitch, yaw,
                          c.land_position_gain, c.land_max_tilt_rad)

    @property
    def reported_phase(self) -> Phase:
        """The phase for the metrics: the climb to the flip altitude counts as take-off,
        the flip starts with the roll (where Appendix И resets its accumulated roll)."""
        return Phase.TAKEOFF if self.phase == Phase.FLIP and not self.rolling else self.phase

    def _rate_loop(self, rate_sp, rates, thrust_fraction: float) -> np.ndarray:
        torque = np.asarray(self.vehicle.inertia_kg_m2) * self.config.rate_gain_1_s * (rate_sp - rates)
        return self._mix(thrust_fraction * self._max_total_n, torque)

    def _hold(self, x, point, roll, pitch, yaw, gain=None, max_tilt_rad: float | None = None) -> np.ndarray:
        c, v = self.config, self.vehicle
        gain = c.position_gain if gain is None else gain
        max_tilt_rad = v.tilt_limit_rad(math.degrees(c.hold_max_tilt_rad if max_tilt_rad is None else max_tilt_rad))
        roll_ref, pitch_ref, thrust = position_law(v.mass_kg, v.gravity_m_s2, x[0:3], x[3:6], point,
                                                   gain, gain, yaw, max_tilt_rad)
        torque = attitude_law(v.inertia_kg_m2, (roll, pitch, yaw), x[10:13], (roll_ref, pitch_ref, yaw),
                              c.attitude_gain, c.attitude_gain, self._max_accel)
        return self._mix(thrust, torque)

    def _mix(self, thrust_n, torque_nm) -> np.ndarray:
        forces, _ = mix(self.vehicle, thrust_n, torque_nm)
        return forces


# --- metrics -----------------------------------------------------------------------

@dataclass(frozen=True)
class FlipMetrics:
    completed: bool          # turned 360 deg (less the level tolerance) and recovered
    altitude_loss_m: float   # z at flip start minus lowest z until recovery ends
    xy_drift_m: float        # largest horizontal distance from the flip start until recovery ends
    overshoot_deg: float     # accumulated roll past 360 deg
    recovery_s: float        # turn complete -> level within 5 deg, rates < 0.5 rad/s, held
    duration_s: float        # flip start -> recovery end


TURN_START_RAD = math.radians(3.0)  # the turn has started (the height loss "from the turn's start")


def heights(z, roll_rad) -> dict[str, float]:
    """From the flip's start to its recovery's end: z (m) about the start, accumulated roll (rad).
    roll+3: height where the roll passes TURN_START_RAD (the turn's start); peak: the highest
    point; lowest: the lowest after the peak; turn_loss: roll+3 less lowest (the loss measured
    from the turn's start); fall: peak less lowest."""
    z = np.asarray(z, dtype=np.float64)
    turn = int(np.argmax(np.asarray(roll_rad) > TURN_START_RAD))
    peak = int(np.argmax(z))
    lowest = float(np.min(z[peak:]))
    return {"roll+3": float(z[turn]), "peak": float(z[peak]), "lowest": lowest,
            "turn_loss": float(z[turn]) - lowest, "fall": float(z[peak]) - lowest}


def flip_metrics(t_s, position_m, quaternion, rate_rad_s, phase,
                 level_tolerance_rad: float = math.radians(5.0), level_rate_rad_s: float = 0.5,
                 hold_s: float = 0.2) -> FlipMetrics:
    """Metrics of one flip over a time series (N samples); phase: N phase names/Phases.

    The flip starts at the first 'flip' sample; the turn is complete when the accumulated
    roll reaches 360 deg - level_tolerance_rad; recovery ends at the first later sample from
    which tilt and body-rate norm stay within limits for hold_s (or to the series' end).
    """
    t = np.asarray(t_s, dtype=np.float64)
    pos = np.asarray(position_m, dtype=np.float64)
    quat = np.asarray(quaternion, dtype=np.float64)
    rates = np.asarray(rate_rad_s, dtype=np.float64)
    names = [Phase(p).value for p in phase]
    nan = float("nan")
    if Phase.FLIP.value not in names:
        return FlipMetrics(False, nan, nan, nan, nan, nan)
    start = names.index(Phase.FLIP.value)
    acc = RollAccumulator()
    acc.reset(quat[start])
    roll = np.array([acc.update(q) for q in quat[start:]])
    turned = np.nonzero(roll >= TWO_PI - level_tolerance_rad)[0]
    end = len(t) - 1
    turn = recovered = None
    if len(turned):
        turn = start + int(turned[0])
        calm = np.array([tilt_rad(q) <= level_tolerance_rad for q in quat]) & (
            np.linalg.norm(rates, axis=1) < level_rate_rad_s)
        for i in range(turn, len(t)):
            window = (t >= t[i]) & (t <= t[i] + hold_s)
            if calm[i] and np.all(calm[window]):
                recovered = i
                break
    if recovered is not None:
        end = recovered
    span = slice(start, end + 1)
    altitude_loss = float(pos[start, 2] - np.min(pos[span, 2]))
    drift = float(np.max(np.linalg.norm(pos[span, 0:2] - pos[start, 0:2], axis=1)))
    overshoot = max(0.0, math.degrees(float(np.max(roll[: end - start + 1]))) - 360.0)
    completed = turn is not None and recovered is not None
    return FlipMetrics(
        completed=completed,
        altitude_loss_m=altitude_loss,
        xy_drift_m=drift,
        overshoot_deg=overshoot,
        recovery_s=float(t[recovered] - t[turn]) if completed else nan,
        duration_s=float(t[end] - t[start]) if completed else nan,
    )
