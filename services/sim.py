"""zenpilot-sim: the simulated quadcopter and its sensors.

Publishes sim/imu, sim/baro, sim/mag, sim/camera and sim/truth at their own
rates; applies the motor driver's PWM. In lockstep it drives the clock: it
publishes sim/clock for each tick and advances only when every service due
at that tick has reported done. It stops by itself `linger_s` after the
mission completes (or fails), or after `max_duration_s`.
"""

from __future__ import annotations

import dataclasses
import time

import schemas
from deploy.stack import LOCKSTEP_PARTICIPANTS
from flight.vehicle import VehicleError, load_vehicle
from services.runtime import Runtime, main_guard, service_parser
from simulator.config import SimConfig
from simulator.world import Simulator

NAME = "sim"
EXTRA_PARAMS = {
    "stop_after_mission": True,  # `zenpilot fly`: end the run when the mission ends
    "linger_s": 1.0,  # keep simulating after the mission ends (landing settles, logs flush)
    "max_duration_s": 600.0,  # hard stop, simulated seconds
    "mass_scale": 1.0,  # the plant's mass = this x the airframe file's (robustness: the services keep the file's)
}
START_GRACE_S = 0.5  # lockstep: let subscriptions propagate before tick 0


def param_defaults() -> dict:
    d = SimConfig().to_dict()
    d.pop("tick_rate_hz")  # the stack's tick rate is the one source of truth
    return {**{k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}, **EXTRA_PARAMS}


class SimService:
    def __init__(self, args):
        self.rt = rt = Runtime(NAME, args, param_defaults())
        sim_params = {k: v for k, v in rt.params.items() if k not in EXTRA_PARAMS}
        sim_params["tick_rate_hz"] = rt.tick_rate
        try:
            config = SimConfig.from_dict(sim_params)
            vehicle = load_vehicle(rt.vehicle_name)
            if rt.params["mass_scale"] != 1.0:
                if not 0.1 <= rt.params["mass_scale"] <= 10.0:
                    raise ValueError(f"mass_scale {rt.params['mass_scale']} outside [0.1, 10]")
                vehicle = dataclasses.replace(vehicle, mass_kg=vehicle.mass_kg * rt.params["mass_scale"])
        except (ValueError, VehicleError) as exc:
            rt.close()
            raise ValueError(f"{rt.stack.path}: [services.sim.params]: {exc}") from None
        self.sim = Simulator(vehicle, config, seed=args.seed)
        self.pubs = {topic: rt.publisher(msg) for topic, msg in schemas.SIM_TOPICS.items()}
        self.pwm = rt.inbox(schemas.MOTOR_PWM, "motors", keep=2)
        self.mission = rt.inbox(schemas.PLANNER_SETPOINT, "planner", keep=2)
        self.participants = [p for p in LOCKSTEP_PARTICIPANTS if p in rt.stack.services]
        self.end_t: float | None = None
        self.t0 = 0.0  # wall time of tick 0 in real time: headers carry the stack's clock

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
        if (self.end_t is None and self.rt.params["stop_after_mission"] and sp is not None
                and sp["mission_state"] in ("completed", "failed")):
            self.end_t = t + self.rt.params["linger_s"]
        if t >= self.rt.params["max_duration_s"]:
            self.rt.problem(f"stopping at max_duration_s={self.rt.params['max_duration_s']}")
            return False
        return self.end_t is None or t < self.end_t

    # -- lockstep: this service drives the clock ------------------------------
    def run_lockstep(self) -> None:
        rt = self.rt
        clocks = {p: rt.publisher(schemas.CLOCK, schemas.CLOCK.key(rt.vehicle_id, p)) for p in self.participants}
        for p in self.participants:
            rt.follow(p)
        # wait for every participant's "ready"
        while not rt.stop_event.is_set():
            missing = [p for p in self.participants if rt._upstreams[p].last_done < -1]
            if not missing:
                break
            rt._sync_event.wait(0.2)
            rt._sync_event.clear()
        time.sleep(START_GRACE_S)
        rt.state = "running"
        while not rt.stop_event.is_set():
            k = self.sim.tick
            rt._t = self.sim.t
            published = self.publish_outputs()
            due = self.due_at(k, published)
            done = {p: rt._upstreams[p].last_done for p in self.participants}
            for p in due:
                clocks[p].put({"tick": k, "tick_rate_hz": rt.tick_rate, "published": published,
                               "done": done}, t_s=rt._t)
            if not self.wait_done(k, due):
                break
            rt.count_run(rt._t)
            rt.publish_health()
            if not self.advance():
                break

    def due_at(self, k: int, published: list[str]) -> list[str]:
        """Participants that run at tick k: by their announced next tick, or triggered."""
        due = []
        for p in self.participants:
            u = self.rt._upstreams[p]
            if u.next_tick == k or (u.next_tick < 0 and set(published) & set(u.triggers)):
                due.append(p)
        return due

    def wait_done(self, k: int, due: list[str]) -> bool:
        rt = self.rt
        start = time.monotonic()
        warned = False
        while not rt.stop_event.is_set():
            rt._sync_event.clear()
            waiting = [p for p in due if rt._upstreams[p].last_done < k]
            if not waiting:
                return True
            rt._sync_event.wait(0.5)
            if not warned and time.monotonic() - start > 5.0:
                rt.problem(f"lockstep: tick {k} waiting for {', '.join(waiting)}")
                warned = True
        return False

    # -- real time -------------------------------------------------------------
    def run_realtime(self) -> None:
        rate = self.rt.tick_rate

        def step(now: float) -> None:
            # physics keeps up with the wall clock: after a late wake-up, catch up
            # tick by tick (each with its sensor samples) instead of slowing down
            target = int((now - self.t0) * rate)
            while self.sim.tick <= target:
                self.publish_outputs()
                if not self.advance():
                    self.rt.stop_event.set()
                    return

        self.rt.rate_hz = rate
        self.t0 = time.time()
        self.rt._run_realtime(step, ())

    def run(self) -> None:
        wall0 = time.monotonic()
        tick0 = self.sim.tick
        try:
            if self.rt.lockstep:
                self.run_lockstep()
            else:
                self.run_realtime()
        finally:
            self.rt.close()
            wall = time.monotonic() - wall0
            print(f"zenpilot-sim: {self.sim.t:.2f} s simulated in {wall:.2f} s of wall time "
                  f"({(self.sim.tick - tick0) / self.rt.tick_rate / max(wall, 1e-9):.2f}x real time)", flush=True)


def main(argv=None) -> None:
    args = service_parser(NAME, __doc__.splitlines()[0]).parse_args(argv)
    main_guard(NAME, lambda: SimService(args).run())


if __name__ == "__main__":
    main()
