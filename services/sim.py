"""zenpilot-sim: the simulated quadcopter and its sensors.

Publishes sim/imu, sim/baro, sim/mag, sim/camera and sim/truth at their own
rates; applies the motor driver's PWM. In lockstep it drives the clock: it
publishes @lockstep/clock for each tick and steps the physics once the runs whose
outputs it applies (the motors' PWM, the planner's mission state) are done
(services/lockstep.py). It stops by itself `linger_s` after the
mission completes (or fails), or after `max_duration_s`.
"""

from __future__ import annotations

import dataclasses
import time

import schemas
from flight.vehicle import VehicleError, load_vehicle
from services import lockstep
from services.params.sim import PARAMS, SIM_CONFIG_KEYS  # SimConfig's settings and the service's own
from services.runtime import Runtime, main_guard, service_parser
from services.stack import LOCKSTEP_PARTICIPANTS, intrinsics_path
from simulator.config import SimConfig
from simulator.world import Simulator

NAME = "sim"
BEHIND_WARN_TICKS = 4  # real time: this many ticks behind the wall clock is reported


class SimLoop:
    """The simulator's wiring, inputs in and outputs out (no Zenoh; tests/unit/services/test_sim.py):
    the newest PWM applied each tick, every sensor sample published at its sample time, the run
    ended `linger_s` after the mission completes or fails or at `max_duration_s`, and in real time
    the ticks the wall clock asks for, never falling behind silently. `io` is the service's
    Runtime in flight, a fake in the unit tests."""

    def __init__(self, io, sim: Simulator, params: dict):
        self.io = io
        self.sim = sim
        self.params = params
        self.pubs = {topic: io.publisher(msg) for topic, msg in schemas.SIM_TOPICS.items()}
        self.pwm = io.inbox(schemas.MOTOR_PWM, "motors", keep=2)
        self.mission = io.inbox(schemas.PLANNER_SETPOINT, "planner", keep=2)
        self.end_t: float | None = None
        self.behind_ticks = 0  # real time: ticks simulated late, catching up
        self.behind_reported = -1e9
        self.t0: float | None = 0.0  # wall time of tick 0 in real time: headers carry the stack's clock

    def publish_outputs(self) -> list[str]:
        published = []
        for topic, t_s, fields in self.sim.outputs():
            self.pubs[topic].put(fields, t_s=self.t0 + t_s)
            published.append(topic)
        return published

    def advance(self) -> bool:
        """Apply the newest PWM, step one tick; False when the run is over."""
        pwm = self.pwm.latest()
        if pwm is None:
            self.sim.step([0.0] * 4, armed=False)
        else:
            self.sim.step(pwm["pwm_us"], armed=pwm["armed"])
        t = self.sim.t
        sp = self.mission.latest()
        if (self.end_t is None and self.params["stop_after_mission"] and sp is not None
                and sp["mission_state"] in ("completed", "failed")):
            self.end_t = t + self.params["linger_s"]
        if t >= self.params["max_duration_s"]:
            self.io.problem(f"stopping at max_duration_s={self.params['max_duration_s']}")
            return False
        return self.end_t is None or t < self.end_t

    def realtime_step(self, now: float) -> bool:
        """Real time: the ticks up to the wall clock's `now`, each with its sensor samples (after
        a late wake-up it catches up tick by tick instead of slowing down). False when the run is over."""
        rate = self.sim.config.tick_rate_hz
        if self.t0 is None:   # tick 0 is the loop's first deadline: samples go out on their ticks
            self.t0 = now
            print(f"zenpilot-sim: first tick at {now:.3f}", flush=True)
        target = int((now - self.t0) * rate + 0.5)
        behind = target - self.sim.tick
        if behind >= BEHIND_WARN_TICKS:   # never silently: the sensors came late (reported once a second)
            self.behind_ticks += behind
            if now - self.behind_reported >= 1.0:
                self.behind_reported = now
                self.io.problem(f"real time: {1e3 * behind / rate:.1f} ms behind the wall clock at "
                                f"t={self.sim.t:.2f} s (caught up; {self.behind_ticks} ticks late so far)")
        while self.sim.tick <= target:
            self.publish_outputs()
            if not self.advance():
                return False
        return True


class SimService:
    """The process: its Runtime, the simulator built from the stack's parameters and vehicle,
    the lockstep clock or the real-time loop around a SimLoop."""

    def __init__(self, args):
        self.rt = rt = Runtime(NAME, args, PARAMS)
        sim_params = {k: v for k, v in rt.params.items() if k in SIM_CONFIG_KEYS}
        sim_params["tick_rate_hz"] = rt.tick_rate
        if sim_params.get("camera_intrinsics"):   # relative to the stack file, as its other files
            sim_params["camera_intrinsics"] = str(intrinsics_path(rt.stack.path, sim_params["camera_intrinsics"]))
        try:
            config = SimConfig.from_dict(sim_params)
            vehicle = load_vehicle(rt.vehicle_name)
            if rt.params["mass_scale"] != 1.0:
                vehicle = dataclasses.replace(vehicle, mass_kg=vehicle.mass_kg * rt.params["mass_scale"])
            self.sim = Simulator(vehicle, config, seed=args.seed)   # the image mode reads its intrinsics here
        except (ValueError, VehicleError) as exc:
            rt.close()
            raise ValueError(f"{rt.stack.path}: [services.sim.params]: {exc}") from None
        self.loop = SimLoop(rt, self.sim, rt.params)
        self.participants = [p for p in LOCKSTEP_PARTICIPANTS if p in rt.stack.services]
        self.first_tick: float | None = None   # time.monotonic() of tick 0

    # -- lockstep: this service drives the clock (services/lockstep.py) ----------
    def run_lockstep(self) -> None:
        rt = self.rt
        loop = self.loop
        clock = lockstep.Clock(rt, self.participants, applied={loop.pwm.upstream, loop.mission.upstream})
        if not clock.start():
            return
        rt.state = "running"
        rt.enter_loop()
        self.first_tick = time.monotonic()
        print(f"zenpilot-sim: first tick at {time.time():.3f}", flush=True)
        try:
            self._ticks(clock)
        finally:
            clock.close()

    def _ticks(self, clock: lockstep.Clock) -> None:
        """Tick until the flight is over or the service is stopped."""
        rt, loop, timer = self.rt, self.loop, time.perf_counter
        while not rt.stop_event.is_set():
            t0 = timer()
            k = self.sim.tick
            rt._t = self.sim.t
            due = clock.tick(k, rt._t, loop.publish_outputs())
            t1 = timer()
            if not clock.wait_applied(due, k):
                break
            t2 = timer()
            rt.count_run(rt._t)
            rt.publish_health()
            more = loop.advance()
            rt.step_s += (t1 - t0) + (timer() - t2)   # physics and publishing; wait_s: the services
            rt.wait_s += t2 - t1
            rt.cycles += 1
            if not more:
                clock.finish(k)
                break

    # -- real time -------------------------------------------------------------
    def run_realtime(self) -> None:
        def step(now: float) -> None:
            if self.first_tick is None:
                self.first_tick = time.monotonic()
            if not self.loop.realtime_step(now):
                self.rt.stop_event.set()

        self.rt.rate_hz = self.rt.tick_rate
        self.loop.t0 = None
        self.rt._run_realtime(step, ())

    def run(self) -> None:
        tick0 = self.sim.tick
        try:
            if self.rt.lockstep:
                self.run_lockstep()
            else:
                self.run_realtime()
        finally:
            self.rt.close()
            # from the first tick: the others' start-up (the planner's JAX compile) is start-up's
            wall = time.monotonic() - self.first_tick if self.first_tick is not None else 0.0
            print(f"zenpilot-sim: {self.sim.t:.2f} s simulated in {wall:.2f} s of wall time "
                  f"({(self.sim.tick - tick0) / self.rt.tick_rate / max(wall, 1e-9):.2f}x real time"
                  f"{f'; {self.loop.behind_ticks} ticks simulated late' if not self.rt.lockstep else ''})", flush=True)


def main(argv=None) -> None:
    args = service_parser(NAME, __doc__.splitlines()[0]).parse_args(argv)
    main_guard(NAME, lambda: SimService(args).run())


if __name__ == "__main__":
    main()
