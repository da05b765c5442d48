"""flight/motor_model.py: the lag's exact step, the thrust-space forms the models carry, and
the plant built on it against RotorPy's multirotor (rotorpy.vehicles.multirotor, a test
dependency) on the same per-rotor thrust commands, drag and aerodynamics off."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from flight import motor_model
from flight.motor_model import MotorModel
from flight.vehicle import load_vehicle
from simulator.plant import Plant

TICK_S = 0.0025  # the simulator's 400 Hz tick, 5 RK4 substeps (SimConfig)
SUBSTEPS = 5


def test_lag_exact_step_matches_a_fine_integration_and_composes():
    tau = 0.02
    w0, wc = np.array([0.0, 500.0, 1500.0, 2100.0]), np.array([1200.0, 1200.0, 0.0, 2100.0])
    w = w0.copy()
    n = 200000
    for _ in range(n):  # the ODE w' = (wc - w) / tau, explicit Euler on a very fine grid
        w = w + (wc - w) * (0.01 / n) / tau
    exact = motor_model.speed_step(w0, wc, 0.01, tau)
    np.testing.assert_allclose(exact, w, rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(exact, wc + (w0 - wc) * math.exp(-0.5), rtol=1e-15)
    # a held command: two half steps are one step (the exact solution, not an integrator's)
    half = motor_model.speed_step(motor_model.speed_step(w0, wc, 0.005, tau), wc, 0.005, tau)
    np.testing.assert_allclose(half, exact, rtol=1e-13)
    # held at the command: stays
    np.testing.assert_array_equal(motor_model.speed_step(wc, wc, 0.01, tau), wc)


def test_thrust_space_forms_are_the_speed_lag():
    """thrust_step (what the plan, the driver and the EKF carry) is kf w^2 of the speed lag,
    whatever kf; its mean is the force's mean over the step, a held command."""
    veh = load_vehicle("q820")
    motors = MotorModel.of(veh)
    assert motors.kf == veh.thrust_coefficient_kf and motors.km == veh.moment_coefficient_km
    assert motors.km / motors.kf == pytest.approx(veh.yaw_moment_m, rel=1e-12)
    assert motors.time_constant_s == veh.motor_time_constant_s
    rng = np.random.default_rng(4)
    for _ in range(50):
        f0, c = rng.uniform(0.0, veh.max_thrust_n, 4), rng.uniform(0.0, veh.max_thrust_n, 4)
        h = rng.uniform(1e-4, 0.05)
        w = motors.speed_step(motors.speed_command(f0), motors.speed_command(c), h)
        np.testing.assert_allclose(motors.thrust_step(f0, c, h), motors.thrust(w), rtol=1e-12)
        np.testing.assert_allclose(motor_model.thrust_step(f0, c, h, motors.time_constant_s), motors.thrust(w),
                                   rtol=1e-12)
        np.testing.assert_allclose(motors.torque(w), veh.yaw_moment_m * motors.thrust(w), rtol=1e-9)
        end, mean = motor_model.thrust_step_and_mean(f0, c, h, motors.time_constant_s)
        ts = (np.arange(4000) + 0.5) / 4000 * h  # midpoint rule
        fine = np.mean([motors.thrust(motors.speed_step(motors.speed_command(f0), motors.speed_command(c), t))
                        for t in ts], axis=0)
        np.testing.assert_allclose(mean, fine, rtol=1e-6)
        np.testing.assert_allclose(end, motors.thrust(w), rtol=1e-12)



def test_one_formula_on_floats_numpy_and_jax():
    """The lag's float forms (the 400 Hz driver, the simulator, the EKF's input), its numpy
    form and its JAX form (the planner's dynamics, root_step_and_mean on jnp arrays) give the
    same bits: one formula."""
    import jax.numpy as jnp
    rng = np.random.default_rng(7)
    tau = 0.03
    for _ in range(200):
        f0, c = rng.uniform(0.0, 8.0, 4), rng.uniform(0.0, 8.0, 4)
        c[rng.random(4) < 0.2] = 0.0
        h = rng.uniform(1e-4, 0.05)
        d = motor_model.decay(h, tau)
        weights = motor_model.mean_weights(h, tau)
        end = motor_model.thrust_step(f0, c, h, tau)   # 4-vectors: its float path
        np.testing.assert_array_equal(end, motor_model.thrust_step(f0[None], c[None], h, tau)[0])  # numpy
        np.testing.assert_array_equal(end, motor_model.thrust_step_floats(f0.tolist(), c.tolist(), d))
        ends, means = motor_model.thrust_step_and_mean_floats(f0.tolist(), c.tolist(), weights)
        end_np, mean_np = motor_model.thrust_step_and_mean(f0, c, h, tau)
        np.testing.assert_array_equal(ends, end_np)
        np.testing.assert_array_equal(means, mean_np)
        np.testing.assert_array_equal(end_np, end)
        end_j, mean_j = motor_model.root_step_and_mean(jnp.sqrt(jnp.asarray(f0, jnp.float32)),
                                                       jnp.sqrt(jnp.asarray(c, jnp.float32)), weights)
        np.testing.assert_allclose(np.asarray(end_j), end_np, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(np.asarray(mean_j), mean_np, rtol=1e-5, atol=1e-6)
    # the speed form, at RK4's stage times
    half, half2, full, end = motor_model.rk4_stage_decays(0.01, tau)
    assert (half, full) == (motor_model.decay(0.005, tau), motor_model.decay(0.01, tau)) and half2 == half and end == full
    assert motor_model.speed_derivative(100.0, 400.0, tau) == 300.0 / tau
    assert motor_model.speed_command_floats([4.0, 0.0, -1.0], 1e-6) == [2000.0, 0.0, 0.0]

# --------------------------------------------------------------------------- against RotorPy

def _commands(veh, seconds: float = 3.0) -> np.ndarray:
    """(ticks, 4) thrust commands (N): hover with each rotor's own sine and steps, so the
    vehicle rolls, pitches, yaws and climbs a little over the 3 s."""
    t = np.arange(int(round(seconds / TICK_S))) * TICK_S
    hover = veh.hover_thrust_per_motor_n
    freq, phase = np.array([1.3, 2.1, 0.7, 1.7]), np.array([0.0, 1.0, 2.0, 3.0])
    cmd = hover * (1.0 + 0.04 * np.sin(2 * np.pi * freq * t[:, None] + phase))
    cmd[(t > 1.0) & (t < 1.1)] *= np.array([1.25, 0.8, 1.25, 0.8])  # a yaw kick
    cmd[(t > 2.0) & (t < 2.05)] *= 1.3                               # a collective step
    return cmd


def _rotorpy_params(veh) -> dict:
    kf, km = veh.thrust_coefficient_kf, veh.moment_coefficient_km
    ix, iy, iz = veh.inertia_kg_m2
    return {
        "mass": veh.mass_kg, "Ixx": ix, "Iyy": iy, "Izz": iz, "Ixy": 0.0, "Ixz": 0.0, "Iyz": 0.0,
        "c_Dx": 0.0, "c_Dy": 0.0, "c_Dz": 0.0,
        "num_rotors": 4,
        "rotor_pos": {f"r{i + 1}": np.array([x, y, 0.0]) for i, (x, y) in enumerate(veh.motor_positions_m)},
        "rotor_directions": np.array(veh.motor_yaw_torque_sign, dtype=float),
        "rotor_radius": 0.1,
        "k_eta": kf, "k_m": km, "k_d": 0.0, "k_z": 0.0, "k_h": 0.0, "k_flap": 0.0,
        "tau_m": veh.motor_time_constant_s,
        "rotor_speed_min": 0.0, "rotor_speed_max": 10.0 * veh.max_rotor_speed_rad_s,
        "motor_noise_std": 0.0,
    }


def fly_both(name: str, plant_cls=Plant, seconds: float = 3.0) -> dict:
    """The plant and RotorPy from hover at 10 m on the same commands (drag off in both):
    the largest position (m) and yaw (deg) difference over the flight."""
    multirotor = pytest.importorskip("rotorpy.vehicles.multirotor")
    from scipy.spatial.transform import Rotation

    veh = dataclasses.replace(load_vehicle(name), drag_n_per_m_s=0.0)
    hover = veh.hover_thrust_per_motor_n
    plant = plant_cls(veh, position_m=(0.0, 0.0, 10.0), motor_thrust_n=np.full(4, hover))
    w_hover = math.sqrt(hover / veh.thrust_coefficient_kf)
    state = {"x": np.array([0.0, 0.0, 10.0]), "v": np.zeros(3), "q": np.array([0.0, 0.0, 0.0, 1.0]),
             "w": np.zeros(3), "wind": np.zeros(3), "rotor_speeds": np.full(4, w_hover)}
    rp = multirotor.Multirotor(_rotorpy_params(veh), initial_state=state, control_abstraction="cmd_motor_thrusts",
                               aero=False, enable_ground=False,
                               integrator_kwargs={"method": "DOP853", "rtol": 1e-11, "atol": 1e-12})
    dp, dyaw, travel = 0.0, 0.0, 0.0
    for c in _commands(veh, seconds):
        plant.advance(TICK_S / SUBSTEPS, SUBSTEPS, c, np.zeros(3))
        state = rp.step(state, {"cmd_motor_thrusts": c}, TICK_S)
        dp = max(dp, float(np.linalg.norm(plant.position_m - state["x"])))
        travel = max(travel, float(np.linalg.norm(plant.position_m - [0.0, 0.0, 10.0])))
        yaw_p = Rotation.from_quat(np.roll(plant.quaternion, -1)).as_euler("ZYX")[0]
        yaw_r = Rotation.from_quat(state["q"]).as_euler("ZYX")[0]
        dyaw = max(dyaw, abs(math.degrees(math.remainder(yaw_p - yaw_r, 2 * math.pi))))
    return {"position_m": dp, "yaw_deg": dyaw, "travel_m": travel,
            "rate_rad_s": float(np.linalg.norm(plant.rate_rad_s - state["w"]))}


@pytest.mark.parametrize("name", ["x250", "q820"])
def test_plant_matches_rotorpy_multirotor_within_a_millimetre(name):
    d = fly_both(name)
    assert d["travel_m"] > 0.05  # the commands move it: the comparison means something
    assert d["position_m"] <= 1e-3, d
    assert d["yaw_deg"] <= 0.01, d


if __name__ == "__main__":  # the figures: python -m tests.unit.flight.test_motor_model
    for n in ("x250", "q820"):
        print(n, fly_both(n))
