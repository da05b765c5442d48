"""The float rewrites of the plant, the sensors and the simulator's tick against the former
numpy implementation (bench/support/sim_reference.py): the same physics to rounding, the same
noise draws in the same order."""
import math

import numpy as np
import pytest

from bench.support.sim_reference import RefImu, RefMagnetometer, RefMarkerCamera, RefPlant, RefSimulator
from flight.control.laws import attitude_law, position_law
from flight.control.mixer import mix
from flight.motor_model import thrust_to_pwm
from flight.quat import quat_from_euler, quat_to_euler, quat_to_rotation
from flight.vehicle import load_vehicle
from simulator import SimConfig, Simulator
from simulator.plant import Plant
from simulator import sensors
from simulator.sensors import IMU_DRAW_BLOCK, Imu, Magnetometer, MarkerCamera

RTOL, ATOL = 1e-9, 1e-10  # "equal to rounding" over seconds of flight
DT = 1.0 / 2000.0


def close(a, b, what=""):
    np.testing.assert_allclose(np.asarray(a, float), np.asarray(b, float), rtol=RTOL, atol=ATOL, err_msg=what)


def pair(vehicle, **kw):
    return Plant(vehicle, **kw), RefPlant(vehicle, **kw)


def fly_both(new, ref, ticks, command, wind, substeps=5):
    """Step both plants with the same inputs, comparing after every tick (new: one advance()
    of `substeps`, ref: `substeps` step() calls)."""
    for k in range(ticks):
        cmd, w = command(k), wind(k)
        new.advance(DT, substeps, cmd, w)
        for _ in range(substeps):
            ref.step(DT, cmd, w)
        assert new.landed == ref.landed, f"tick {k}"
        close(new.x, ref.x, f"tick {k}")


@pytest.mark.parametrize("name", ["x250", "q820"])
def test_plant_free_flight_varied_inputs_matches_reference(name):
    v = load_vehicle(name)
    rng = np.random.default_rng(1)
    hover = v.hover_thrust_per_motor_n
    new, ref = pair(v, position_m=(0.0, 0.0, 50.0), velocity_m_s=(0.5, -0.3, 1.0), rate_rad_s=(2.0, -1.0, 0.5),
                    motor_thrust_n=np.full(4, hover))
    q = quat_from_euler(0.4, -0.3, 2.0)
    new.x[6:10] = q
    ref.x[6:10] = q
    cmds = hover + rng.normal(0.0, 0.3 * hover, (1200, 4))
    cmds[::50] = 0.0                          # motors cut now and then
    cmds[25::50] = 1.5 * v.max_thrust_n       # and asked beyond their range
    winds = rng.normal(0.0, 3.0, (1200, 3))
    fly_both(new, ref, 1200, lambda k: cmds[k], lambda k: winds[k])  # 3 s
    assert not new.landed and new.x[2] > 0.0


def test_plant_ground_rest_takeoff_impact_and_landing_matches_reference():
    v = load_vehicle("x250")
    new, ref = pair(v, position_m=(0.0, 0.0, 0.0), yaw_rad=0.7)
    assert new.landed and ref.landed
    hover = v.hover_thrust_per_motor_n
    tilt = np.array([1.0, 1.2, 0.8, 1.0])  # uneven: takes off tilted, lands tilted

    def command(k):
        if k < 100:
            return np.full(4, 0.5 * hover)    # resting: not enough to lift
        if k < 300:
            return 1.6 * hover * tilt         # take off
        if k < 700:
            return np.zeros(4)                # cut: falls, hits the floor fast
        if k < 800:
            return np.full(4, 0.999 * hover)  # resting just below lift-off
        return np.full(4, 1.3 * hover)        # lifts off again

    seen = []

    def wind(k):
        return np.array([2.0, -1.0, 0.3 if k < 750 else -0.3])

    for k in range(900):
        fly_both(new, ref, 1, lambda _: command(k), lambda _: wind(k))
        seen.append(new.landed)
    assert seen[0] and not seen[250] and seen[650] and not seen[-1]  # rested, flew, landed, flew
    # the rest is level with the yaw kept
    new2, ref2 = pair(v, position_m=(0.0, 0.0, 0.2), velocity_m_s=(1.0, 0.0, -3.0), rate_rad_s=(0.0, 0.0, 4.0))
    q = quat_from_euler(0.3, -0.2, 1.0)
    new2.x[6:10] = q
    ref2.x[6:10] = q
    fly_both(new2, ref2, 200, lambda k: np.zeros(4), lambda k: np.zeros(3))
    assert new2.landed
    assert quat_to_euler(new2.x[6:10])[:2] == (0.0, 0.0)


def test_plant_step_is_advance_of_one_and_substeps_one_by_one():
    v = load_vehicle("x250")
    a = Plant(v, position_m=(0, 0, 3.0), rate_rad_s=(1.0, 0.2, -0.4))
    b = Plant(v, position_m=(0, 0, 3.0), rate_rad_s=(1.0, 0.2, -0.4))
    cmd, wind = [1.5, 0.5, 1.0, 0.2], (0.5, 0.0, -0.2)
    for _ in range(300):
        a.advance(DT, 5, cmd, wind)
        for _ in range(5):
            b.step(DT, np.array(cmd), np.array(wind))
    np.testing.assert_array_equal(a.x, b.x)
    assert a.landed == b.landed


def test_plant_derivative_and_acceleration_match_reference():
    v = load_vehicle("q820")
    rng = np.random.default_rng(4)
    new, ref = pair(v, position_m=(0, 0, 10.0))
    for _ in range(200):
        x = rng.normal(0.0, 2.0, 17)
        x[6:10] /= np.linalg.norm(x[6:10])
        cmd, wind = rng.uniform(0, 10, 4), rng.normal(0, 3, 3)
        close(new.derivative(x, cmd, wind), ref.derivative(x, cmd, wind))
        new.x, ref.x = x.copy(), x.copy()
        close(new.acceleration_m_s2(cmd, wind), ref.acceleration_m_s2(cmd, wind))
        close(new.rotation, ref.rotation)
        close(np.reshape(new.rotation_rows(), (3, 3)), ref.rotation)
    new.landed = ref.landed = True
    np.testing.assert_array_equal(new.acceleration_m_s2(cmd, wind), ref.acceleration_m_s2(cmd, wind))


def test_plant_bad_quaternion_raises_as_before():
    v = load_vehicle("x250")
    new, ref = pair(v, position_m=(0, 0, 3.0))
    new.x[6:10] = np.nan
    ref.x[6:10] = np.nan
    with pytest.raises(ValueError, match="quaternion"):
        ref.step(DT, np.zeros(4), np.zeros(3))
    with pytest.raises(ValueError, match="quaternion"):
        new.step(DT, np.zeros(4), np.zeros(3))


def test_imu_and_mag_same_draws_same_numbers():
    cfg = SimConfig(gyro_bias_walk=0.0)  # a zero std still draws
    rng = np.random.default_rng(9)
    new_imu, ref_imu = Imu(cfg, np.random.default_rng(3)), RefImu(cfg, np.random.default_rng(3))
    new_mag, ref_mag = Magnetometer(cfg, np.random.default_rng(5)), RefMagnetometer(cfg, np.random.default_rng(5))
    for _ in range(300):
        rot = quat_to_rotation(rng.normal(size=4))
        rate, acc = rng.normal(0, 2, 3), rng.normal(0, 5, 3)
        a, b = new_imu.sample(rot, rate, acc, 9.81), ref_imu.sample(rot, rate, acc, 9.81)
        assert a.keys() == b.keys() and all(type(e) is float for e in a["gyro_rad_s"] + a["accel_m_s2"])
        for key in a:
            np.testing.assert_allclose(a[key], b[key], rtol=1e-12, atol=1e-14)
        c, d = new_mag.sample(rot), ref_mag.sample(rot)
        np.testing.assert_allclose(c["field_ut"], d["field_ut"], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(new_imu.gyro_bias, ref_imu.gyro_bias, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(new_imu.accel_bias, ref_imu.accel_bias, rtol=1e-12, atol=1e-15)
    ref_imu.rng.standard_normal(new_imu.draws_ahead)   # the IMU draws its noise a block ahead
    assert new_imu.rng.bit_generator.state == ref_imu.rng.bit_generator.state
    assert new_mag.rng.bit_generator.state == ref_mag.rng.bit_generator.state


def test_imu_noise_is_the_per_sample_draw_across_blocks():
    """Each sample's 12 normals are those standard_normal(12) per sample would give: the
    block draws change the generator's position, never the noise (same seed, same noise)."""
    cfg = SimConfig(gyro_noise_var=1.0, accel_noise_var=1.0, gyro_bias_var=0.0, accel_bias_var=0.0,
                    gyro_bias_walk=0.0, accel_bias_walk=0.0)
    imu, rng = Imu(cfg, np.random.default_rng(4)), np.random.default_rng(4)
    rng.normal(0.0, 0.0, 3), rng.normal(0.0, 0.0, 3)   # the biases' draws at start
    for k in range(3 * IMU_DRAW_BLOCK + 5):
        z = rng.standard_normal(12).tolist()
        s = imu.sample_rows((1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0)
        assert s["gyro_rad_s"] == z[:3] and s["accel_m_s2"] == z[3:6], k   # std 1, no bias: the draws
        assert imu.draws_ahead == 12 * (IMU_DRAW_BLOCK - 1 - k % IMU_DRAW_BLOCK)


def test_camera_footprint_cull_gives_the_full_grids_frames():
    """The markers projected are those the image's footprint can hold: the frames (ids, pixels,
    noise) and the generator equal the full grid's, bit for bit, level, tilted, low, high,
    near the grid's edge, beyond it, inverted, under the floor."""
    cfg = SimConfig(camera_drop_rate=0.1)
    new, ref = MarkerCamera(cfg, np.random.default_rng(2)), RefMarkerCamera(cfg, np.random.default_rng(2))
    boxes = MarkerCamera(cfg, np.random.default_rng(2))
    assert new._grid is not None
    boxes._grid = None      # the cull without marker_grid's layout: every marker's box tested
    rng = np.random.default_rng(11)
    seen = culled = 0
    for k in range(600):
        pos = rng.uniform([-7.0, -7.0, -0.5], [7.0, 7.0, 6.0])
        if k % 3 == 0:
            pos[:2] *= 0.3
        euler = rng.normal(0.0, [0.05, 0.3, 1.2][k % 3], 3)
        if k % 50 == 0:
            euler[0] = np.pi          # inverted
        q = quat_from_euler(*euler)
        if k % 40 == 1:               # resting level on the floor, as the plant leaves it
            pos[2], q = 0.0, np.array([math.cos(euler[2] / 2), 0.0, 0.0, math.sin(euler[2] / 2)])
        elif k % 40 == 21:            # on the floor, tilted (the horizon in view)
            pos[2], q = 0.0, quat_from_euler(1.1 * np.sign(euler[0]), euler[1], euler[2])
        a, b = new.sample(pos, q), ref.sample(pos, q)
        assert a == b == boxes.sample(pos, q), (k, pos, euler)
        if a is not None:
            assert all(type(i) is int for i in a["marker_ids"]) and all(type(e) is float for e in a["corners_px"])
            seen += bool(a["marker_ids"])
            idx = new.candidates(pos, q)
            culled += idx is not None and len(idx) < len(new.ids) // 4
    assert new.rng.bit_generator.state == ref.rng.bit_generator.state == boxes.rng.bit_generator.state
    assert seen > 150 and culled > 150   # the cull did its work on most of the poses that see markers


def test_camera_rotation_is_quat_to_rotation_bit_for_bit():
    rng = np.random.default_rng(6)
    for _ in range(3000):
        q = rng.normal(size=4) * rng.uniform(0.2, 3.0)
        np.testing.assert_array_equal(sensors._rotation(q), quat_to_rotation(q))


def _same_messages(a, b, tick):
    assert [(topic, t) for topic, t, _ in a] == [(topic, t) for topic, t, _ in b], f"tick {tick}"
    for (topic, _, fa), (_, _, fb) in zip(a, b):
        assert fa.keys() == fb.keys(), topic
        for key, va in fa.items():
            vb = fb[key]
            if isinstance(va, list) and va and isinstance(va[0], float):
                assert all(type(e) is float for e in va), (topic, key)
                close(va, vb, f"tick {tick} {topic}.{key}")
            elif isinstance(va, float):
                close(va, vb, f"tick {tick} {topic}.{key}")
                assert type(va) is float
            else:
                assert va == vb and type(va) is type(vb), (tick, topic, key)


@pytest.mark.parametrize("imu_latency_s", [0.0, 0.005])
def test_simulator_matches_reference_through_a_flight(imu_latency_s):
    """Rest, take-off, a closed-loop move in wind and gusts with camera drops, a descent, a fall
    onto the floor: every message of every tick and the state agree, and the generators end equal."""
    v = load_vehicle("x250")
    cfg = SimConfig(wind_m_s=(1.0, -0.5, 0.0), gust_std_m_s=0.7, camera_drop_rate=0.2,
                    imu_latency_s=imu_latency_s, initial_yaw_rad=0.3)
    new, ref = Simulator(v, cfg, seed=7), RefSimulator(v, cfg, seed=7)
    yaw_ref = 0.3
    low = thrust_to_pwm(v, np.full(4, 0.3 * v.hover_thrust_per_motor_n))
    for k in range(1800):  # 4.5 s
        a, b = new.outputs(), ref.outputs()
        _same_messages(a, b, k)
        assert new.outputs() == a  # idempotent
        s = new.state
        _same_messages([("truth", 0.0, s)], [("truth", 0.0, ref.state)], k)
        if k < 100:
            new.step([1000.0] * 4, False)
            ref.step([1000.0] * 4, False)
            continue
        if k >= 1450:  # thrust cut: falls onto the floor and rests there
            new.step(low, True)
            ref.step(low, True)
            continue
        target = [0.3, -0.2, 1.0] if k < 1100 else [0.0, 0.0, -1.0]  # then down towards the floor
        roll, pitch, yaw = quat_to_euler(s["quaternion_wxyz"])
        r_ref, p_ref, thrust = position_law(v.mass_kg, v.gravity_m_s2, s["position_m"], s["velocity_m_s"],
                                            target, [4.0] * 3, [4.0] * 3, yaw)
        tau = attitude_law(v.inertia_kg_m2, [roll, pitch, yaw], s["rate_rad_s"], [r_ref, p_ref, yaw_ref],
                           [16.0] * 3, [16.0] * 3)
        forces, _ = mix(v, thrust, tau)
        pwm = thrust_to_pwm(v, forces)
        new.step(pwm, True)
        ref.step(pwm.copy(), True)
    assert new.landed and ref.landed
    close(new.wind_m_s, ref.wind_m_s)
    ref.imu.rng.standard_normal(new.imu.draws_ahead)   # the IMU draws its noise a block ahead
    for attr in ("imu", "baro", "mag", "camera"):
        assert getattr(new, attr).rng.bit_generator.state == getattr(ref, attr).rng.bit_generator.state, attr
    assert new._wind_rng.bit_generator.state == ref._wind_rng.bit_generator.state
    assert new.battery.fields() == pytest.approx(ref.battery.fields(), rel=1e-12)


def test_simulator_without_gust_matches_reference():
    """No gust: the wind's generator is left alone (nothing else reads it); the rest the same."""
    v = load_vehicle("q820")
    cfg = SimConfig(initial_position_m=(0, 0, 2.0), wind_m_s=(0.0, 2.0, 0.0))
    new, ref = Simulator(v, cfg, seed=3), RefSimulator(v, cfg, seed=3)
    pwm = thrust_to_pwm(v, np.full(4, 1.02 * v.hover_thrust_per_motor_n))
    for k in range(400):
        _same_messages(new.outputs(), ref.outputs(), k)
        new.step(list(pwm), True)
        ref.step(pwm, True)
    _same_messages([("truth", 0.0, new.state)], [("truth", 0.0, ref.state)], 400)


def test_simulator_step_refuses_bad_pwm_as_before():
    sim = Simulator(load_vehicle("x250"), SimConfig(), seed=0)
    for bad in ([1000.0] * 3, [1000.0, math.nan, 1000.0, 1000.0], [[1000.0] * 4], [1000.0, math.inf, 0, 0]):
        with pytest.raises(ValueError, match="pwm_us must be 4 finite numbers"):
            sim.step(bad, True)
