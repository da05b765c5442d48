import dataclasses
import math

import numpy as np
import pytest

from flight.vehicle import VEHICLES_DIR, VehicleError, load_vehicle


def test_x250_allocation_is_mixer_of_000():
    v = load_vehicle("x250")
    l = 0.125 * np.sin(np.pi / 4)
    lam = v.yaw_moment_m
    rng = np.random.default_rng(1)
    for _ in range(20):
        f1, f2, f3, f4 = f = rng.uniform(0, 2.5, 4)
        expected = [f1 + f2 + f3 + f4,
                    l * (f1 + f2 - f3 - f4),
                    l * (-f1 + f2 + f3 - f4),
                    lam * (f1 - f2 + f3 - f4)]
        np.testing.assert_allclose(v.allocation @ f, expected, atol=1e-12)
    np.testing.assert_allclose(v.allocation_inv @ v.allocation, np.eye(4), atol=1e-12)
    assert v.mass_kg == 0.4 and v.inertia_kg_m2 == (7.5e-3, 7.5e-3, 14.2e-3)
    assert v.hover_thrust_per_motor_n == pytest.approx(0.4 * 9.81 / 4)
    assert v.thrust_coefficient_kf == 4.0e-7 and v.moment_coefficient_km == pytest.approx(0.016 * 4.0e-7)


def test_q820_allocation_is_torque_of_001():
    v = load_vehicle("q820")
    kf, km, arm = 1.48e-6, 9.4e-8, 0.15
    assert v.thrust_coefficient_kf == kf and v.moment_coefficient_km == km
    assert v.max_thrust_n == pytest.approx(kf * 2100 ** 2)
    rng = np.random.default_rng(2)
    for _ in range(20):
        w = rng.uniform(0, 2100, 4)
        t = kf * w ** 2
        expected = [t.sum(), arm * (t[1] - t[3]), arm * (t[2] - t[0]),
                    km * (w[0] ** 2 - w[1] ** 2 + w[2] ** 2 - w[3] ** 2)]
        np.testing.assert_allclose(v.allocation @ t, expected, rtol=1e-9, atol=1e-12)


def test_load_by_path(tmp_path):
    v = load_vehicle("x250")
    src = (VEHICLES_DIR / "x250.toml").read_text()
    p = tmp_path / "mine.toml"
    p.write_text(src)
    assert load_vehicle(str(p)) == v


def test_unknown_name():
    with pytest.raises(VehicleError, match="nosuch"):
        load_vehicle("nosuch")


@pytest.mark.parametrize("edit, field", [
    (lambda s: s.replace("mass_kg = 0.4\n", ""), "mass_kg"),
    (lambda s: s.replace("mass_kg = 0.4", "mass_kg = -1"), "mass_kg"),
    (lambda s: s.replace("mass_kg = 0.4", 'mass_kg = "heavy"'), "mass_kg"),
    (lambda s: s.replace("motor_yaw_torque_sign = [1, -1, 1, -1]",
                         "motor_yaw_torque_sign = [1, -1, 2, -1]"), "motor_yaw_torque_sign"),
    (lambda s: s.replace("inertia_kg_m2 = [7.5e-3, 7.5e-3, 14.2e-3]",
                         "inertia_kg_m2 = [7.5e-3, 7.5e-3]"), "inertia_kg_m2"),
    (lambda s: s + "\nmass_gk = 1.0\n", "mass_gk"),
    (lambda s: s.replace("motor_time_constant_s = 0.02\n", ""), "motor_time_constant_s"),
    (lambda s: s.replace("pwm_max_us = 2000\n", ""), "pwm_max_us"),
    (lambda s: s.replace("thrust_coefficient_kf = 4.0e-7\n", "").replace("moment_coefficient_km = 6.4e-9\n", "")
     .replace("max_rotor_speed_rad_s = 2500.0\n", ""), "thrust_coefficient_kf"),
])
def test_bad_field_names_file_and_field(tmp_path, edit, field):
    src = (VEHICLES_DIR / "x250.toml").read_text()
    p = tmp_path / "bad.toml"
    p.write_text(edit(src))
    with pytest.raises(VehicleError) as e:
        load_vehicle(str(p))
    assert str(p) in str(e.value) and field in str(e.value)
    assert isinstance(e.value, ValueError)


def test_missing_file(tmp_path):
    with pytest.raises(VehicleError, match="not found"):
        load_vehicle(str(tmp_path / "none.toml"))


def test_airframe_tilt_limit_lowers_the_position_service_limit(tmp_path):
    """q820.toml limits its position laws to 10 deg (its torque saturates for reference steps
    over ~5 deg); the x250 gives none, so the position service's max_tilt_deg applies; the
    smaller of the two wins either way; a bad value is refused with the file and field."""
    q820, x250 = load_vehicle("q820"), load_vehicle("x250")
    assert q820.max_tilt_deg == 10.0 and x250.max_tilt_deg is None
    assert q820.tilt_limit_rad(20.0) == pytest.approx(np.radians(10.0))
    assert q820.tilt_limit_rad(5.0) == pytest.approx(np.radians(5.0))
    assert x250.tilt_limit_rad(20.0) == pytest.approx(np.radians(20.0))
    p = tmp_path / "bad.toml"
    p.write_text((VEHICLES_DIR / "x250.toml").read_text() + "\nmax_tilt_deg = -5\n")
    with pytest.raises(VehicleError, match="max_tilt_deg"):
        load_vehicle(str(p))


def test_motor_time_constant_comes_from_the_vehicle_file_everywhere(tmp_path):
    """A copy of x250.toml with slower motors: the simulator's plant, the position EKF's motor
    input (built as services/position.py builds it) and the iLQR planner's dynamics all lag by
    the file's time constant: after one step of a doubled command each gives the speed lag's
    exact forces for 0.05 s, not for the stock 0.02 s."""
    import jax

    from flight.control.ilqr import PROJECT, ILQRSolver, hover_state
    from flight.control.predict import nominal_params
    from flight.estimation.position_ekf import LaggedMotorInput
    from flight.motor_model import MotorModel
    from simulator.plant import Plant

    src = (VEHICLES_DIR / "x250.toml").read_text()
    assert "motor_time_constant_s = 0.02\n" in src
    p = tmp_path / "slow_motors.toml"
    p.write_text(src.replace("motor_time_constant_s = 0.02\n", "motor_time_constant_s = 0.05\n"))
    stock, slow = load_vehicle("x250"), load_vehicle(str(p))
    assert slow.motor_time_constant_s == 0.05
    assert dataclasses.replace(slow, motor_time_constant_s=stock.motor_time_constant_s) == stock

    h = PROJECT.dt_s   # one planner step
    hover = stock.hover_thrust_per_motor_n

    def expected(tau):  # sqrt(f) moves to sqrt(c) as exp(-t / tau); c = 2 hover
        s = math.sqrt(2 * hover) + (math.sqrt(hover) - math.sqrt(2 * hover)) * math.exp(-h / tau)
        return s * s

    def plant(v):
        pl = Plant(v, position_m=(0.0, 0.0, 10.0), motor_thrust_n=np.full(4, hover))
        pl.advance(h / 10, 10, np.full(4, 2 * hover), np.zeros(3))
        return pl.motor_thrust_n

    def ekf_input(v):
        lag = LaggedMotorInput(v.motor_time_constant_s)
        lag.add(0.0, np.full(4, hover))
        lag.add(0.0, np.full(4, 2 * hover))   # held from t = 0
        lag.mean_to(h)
        return lag.forces

    def planner(v):
        solver = ILQRSolver(v, PROJECT, warm_up=False)
        assert solver.models_motors and solver.motor_time_constant_s == v.motor_time_constant_s
        x = np.concatenate([hover_state([0.0, 0.0, 10.0]), np.full(4, hover)])
        u = np.full(4, math.sqrt(2.0) * solver.u_hover_rad_s)   # kf u^2 = 2 hover
        return np.asarray(jax.jit(solver.dynamics)(x, u))[13:17]

    for v, tau in ((stock, 0.02), (slow, 0.05)):
        assert MotorModel.of(v).time_constant_s == tau and nominal_params(v)["tau"] == np.float32(tau)
        np.testing.assert_allclose(plant(v), expected(tau), rtol=1e-12)
        np.testing.assert_allclose(ekf_input(v), expected(tau), rtol=1e-12)
        np.testing.assert_allclose(planner(v), expected(tau), rtol=1e-5)   # float32
    assert expected(0.05) < expected(0.02) - 0.1   # the slow motors are well behind


BATTERY_FIELDS = ("battery_capacity_mah", "battery_cells", "battery_internal_resistance_ohm",
                  "battery_current_a_per_n", "battery_idle_current_a")


def test_battery_pack_comes_from_the_vehicle_file(tmp_path):
    """A copy of x250.toml with a 2S 650 mAh pack of twice the resistance and a hungrier motor
    set: the simulator's battery counts, sags and reports by the file's numbers, and the
    simulator's settings hold none of the pack's (no second value to disagree with the file)."""
    from flight.motor_model import thrust_to_pwm
    from simulator import SimConfig, Simulator
    from simulator.battery import Battery

    src = (VEHICLES_DIR / "x250.toml").read_text()
    stock_pack = {"battery_capacity_mah": "1300.0", "battery_cells": "3", "battery_internal_resistance_ohm": "0.05",
                  "battery_current_a_per_n": "2.0", "battery_idle_current_a": "0.3"}
    small_pack = {"battery_capacity_mah": "650.0", "battery_cells": "2", "battery_internal_resistance_ohm": "0.1",
                  "battery_current_a_per_n": "3.0", "battery_idle_current_a": "0.5"}
    for key, value in stock_pack.items():
        assert f"\n{key} = {value}\n" in src, key
        src = src.replace(f"\n{key} = {value}\n", f"\n{key} = {small_pack[key]}\n")
    p = tmp_path / "small_pack.toml"
    p.write_text(src)
    stock, small = load_vehicle("x250"), load_vehicle(str(p))
    assert (small.battery_capacity_mah, small.battery_cells, small.battery_internal_resistance_ohm,
            small.battery_current_a_per_n, small.battery_idle_current_a) == (650.0, 2, 0.1, 3.0, 0.5)
    assert dataclasses.replace(small, **{k: getattr(stock, k) for k in BATTERY_FIELDS}) == stock

    def hover_one_second(v):
        sim = Simulator(v, SimConfig(initial_position_m=(0.0, 0.0, 1.0)), seed=0)
        assert vars(sim.battery) == vars(Battery.of(v))   # a full pack of this airframe
        rest = sim.battery.voltage_v
        pwm = thrust_to_pwm(v, np.full(4, v.hover_thrust_per_motor_n))
        for _ in range(400):
            sim.step(pwm, True)
        return rest, sim.battery.fields()

    for v, (cells, r, a_per_n, idle, capacity) in ((stock, (3, 0.05, 2.0, 0.3, 1300.0)),
                                                    (small, (2, 0.1, 3.0, 0.5, 650.0))):
        rest, b = hover_one_second(v)
        assert rest == pytest.approx(cells * 4.2 - idle * r)   # full: 4.2 V a cell at rest
        current = idle + a_per_n * v.mass_kg * v.gravity_m_s2   # hovering: the rotors carry the weight
        assert b["cells"] == cells and b["current_a"] == pytest.approx(current, rel=0.02)
        assert b["consumed_mah"] == pytest.approx(current / 3.6, rel=0.02)   # 1 s of that current
        assert b["remaining"] == pytest.approx(1.0 - b["consumed_mah"] / capacity)


def test_every_airframe_number_of_the_pack_is_in_its_vehicle_file_only():
    """Each vehicle file gives its pack once; the simulator's settings (and so the sim service's
    parameters and docs/parameters.md) give none of it."""
    from simulator.config import SimConfig

    for path in sorted(VEHICLES_DIR.glob("*.toml")):
        lines = path.read_text().splitlines()
        for key in BATTERY_FIELDS:
            assert sum(line.startswith(f"{key} =") for line in lines) == 1, f"{path.name}: {key}"
    sim_settings = {f.name for f in dataclasses.fields(SimConfig)}
    assert not sim_settings & set(BATTERY_FIELDS) and "battery_rate_hz" in sim_settings   # the message rate stays
    with pytest.raises(ValueError, match="simulator.battery_capacity_mah: unknown key"):
        SimConfig.from_dict({"battery_capacity_mah": 1300.0})


@pytest.mark.parametrize("value, why", [('"../vehicles/x250.toml"', "no folders"), ('"/etc/x.toml"', "no folders"),
                                        ('"params.json"', "a .toml file"), ("3", "no folders")])
def test_a_bad_gyrovertical_file_name_is_refused_naming_the_field(tmp_path, value, why):
    src = (VEHICLES_DIR / "q820.toml").read_text().replace('"gyrovertical_q820_compensated.toml"', value)
    p = tmp_path / "bad.toml"
    p.write_text(src)
    with pytest.raises(VehicleError, match=f"bad.toml: field 'gyrovertical_params': .*{why}"):
        load_vehicle(str(p))
