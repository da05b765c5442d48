"""The simulator service's logic (services/sim.py SimLoop) without a router."""

import numpy as np

import schemas
from flight.vehicle import load_vehicle
from services.params.sim import PARAMS
from services.sim import BEHIND_WARN_TICKS, SimLoop
from simulator.config import SimConfig
from simulator.world import Simulator
from tests.unit.services.fake_io import FakeIO

SETPOINT = {"mode": "position", "armed": True, "position_m": [0.0, 0.0, 1.0], "attitude_rad": [0.0, 0.0, 0.0],
            "item": 0, "phase": "hold", "measure": False, "mission_state": "running"}


def make(params=None):
    io = FakeIO("sim", PARAMS, params or {}, rate_hz=400.0)
    return io, SimLoop(io, Simulator(load_vehicle("x250"), SimConfig(), seed=0), io.params)


def test_each_sensor_is_published_at_its_rate_and_sample_time():
    io, loop = make()
    for _ in range(40):   # 0.1 s at 400 Hz
        loop.publish_outputs()
        assert loop.advance()
    imu, mag, camera = io.sent(schemas.IMU), io.sent(schemas.MAG), io.sent(schemas.CAMERA)
    assert len(imu) == 40 and len(mag) == 5
    assert [t for t, _ in camera] == [0.0]   # the frame exposed at 0.05 s goes out camera_latency_s later
    assert [t for t, _ in imu[:3]] == [0.0, 0.0025, 0.005]
    assert all(np.isfinite(m["accel_m_s2"]).all() for _, m in imu)


def test_the_newest_pwm_drives_the_plant_and_disarmed_it_stays_on_the_ground():
    io, loop = make()
    for _ in range(200):
        loop.publish_outputs()
        loop.advance()
    assert abs(io.sent(schemas.TRUTH)[-1][1]["position_m"][2]) < 1e-3   # no PWM yet: on the ground
    pwm = io.received(schemas.MOTOR_PWM, "motors")
    pwm.push(loop.sim.t, {"pwm_us": [2000.0] * 4, "thrust_n": [5.0] * 4, "armed": True,
                                "saturated": False, "imu_t_s": -1.0})
    for _ in range(200):   # 0.5 s at full throttle: it climbs
        loop.publish_outputs()
        loop.advance()
    truth = io.sent(schemas.TRUTH)[-1][1]
    assert truth["position_m"][2] > 0.2


def test_the_run_ends_linger_s_after_the_mission_and_at_max_duration():
    io, loop = make({"linger_s": 0.05})
    io.received(schemas.PLANNER_SETPOINT, "planner").push(
        0.0, {**SETPOINT, "mission_state": "completed"})
    ticks = 0
    while loop.advance():
        ticks += 1
    assert 20 <= ticks <= 21   # linger_s at 400 Hz after the first tick saw the completed mission
    io, loop = make({"max_duration_s": 0.01})
    while loop.advance():
        pass
    assert abs(loop.sim.t - 0.01) < 1e-9 and any("max_duration_s" in p for p in io.problems)


def test_real_time_catches_up_tick_by_tick_and_says_so():
    io, loop = make()
    loop.t0 = None
    assert loop.realtime_step(100.0) and loop.sim.tick == 1   # tick 0 at the first deadline
    assert loop.realtime_step(100.0 + 10 / 400) and loop.sim.tick == 11   # ten ticks late: all simulated
    assert loop.behind_ticks == 9 >= BEHIND_WARN_TICKS   # the wall clock asked for tick 10 at tick 1
    assert len(io.problems) == 1 and "behind the wall clock" in io.problems[0]
    assert [t for t, _ in io.sent(schemas.IMU)][:2] == [100.0, 100.0025]   # stamped on the stack's clock
    assert loop.realtime_step(100.0 + 11 / 400) and loop.sim.tick == 12 and loop.behind_ticks == 9   # on time

