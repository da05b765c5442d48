"""The float mixer, PWM map and flight/plan helpers against their former numpy versions
(bench/support/sim_reference.py): the same forces and saturation flags, saturation included."""
import math

import numpy as np
import pytest

from bench.support.sim_reference import (ref_mix, ref_motor_forces_update, ref_pwm_to_thrust, ref_scale_collective,
                                         ref_thrust_to_pwm)
from flight.control.mixer import mix, mix_floats
from flight.control.plan import scale_collective, scale_collective_floats
from flight.motor_model import pwm_to_thrust, pwm_to_thrust_floats, thrust_step, thrust_to_pwm, thrust_to_pwm_floats
from flight.vehicle import load_vehicle


@pytest.fixture(params=["x250", "q820"])
def veh(request):
    return load_vehicle(request.param)


def same_mix(v, thrust, torque):
    f, sat = mix(v, thrust, torque)
    g, ref_sat = ref_mix(v, thrust, torque)
    assert type(f) is np.ndarray and f.shape == (4,) and f.dtype == np.float64
    np.testing.assert_allclose(f, g, rtol=1e-12, atol=1e-12, err_msg=f"{thrust} {torque}")
    assert sat is ref_sat, (thrust, torque)
    lists, sat2 = mix_floats(v, thrust, torque)
    assert sat2 is sat and lists == f.tolist() and all(type(e) is float for e in lists)
    return sat


def test_mix_matches_reference_over_varied_commands(veh):
    rng = np.random.default_rng(11)
    hover = 4 * veh.hover_thrust_per_motor_n
    kinds = {True: 0, False: 0}
    for scale in (1e-3, 1e-2, 0.1, 1.0):  # from well inside the range to far beyond it
        for _ in range(400):
            thrust = rng.uniform(-0.5, 1.5) * 4 * veh.max_thrust_n if rng.random() < 0.3 else \
                hover * rng.uniform(0.5, 1.5)
            kinds[same_mix(veh, thrust, rng.normal(0.0, scale, 3))] += 1
    assert kinds[True] > 200 and kinds[False] > 200  # both regimes exercised


def test_mix_matches_reference_in_each_saturation_case(veh):
    l = abs(veh.motor_positions_m[0][1])
    span = veh.max_thrust_n - veh.min_thrust_n
    hover = 4 * veh.hover_thrust_per_motor_n
    cases = [
        (hover, [0.3 * span * l, -0.2 * span * l, 0.0]),     # fits
        (4 * veh.max_thrust_n, [0.05, -0.03, 0.002]),        # collective gives way (down)
        (0.0, [0.05, -0.03, 0.002]),                         # collective gives way (up)
        (hover, [0.8 * span * 2 * l, 0.0, 0.5]),             # yaw scaled down
        (hover, [0.3 * span * 2 * l, 0.3 * span * 2 * l, 10.0]),  # yaw scaled to nothing
        (2.0, [10.0, 5.0, 0.01]),                            # roll/pitch scaled, yaw dropped
        (hover, [0.0, 0.0, 100.0]),                          # yaw alone too big
        (hover, [0.0, 0.0, 0.0]), (-1.0, [0.0, 0.0, 0.0]), (1e6, [0.0, 0.0, 0.0]),
    ]
    for thrust, torque in cases:
        same_mix(veh, thrust, torque)
        same_mix(veh, thrust, [-e for e in torque])


def test_mix_accepts_what_it_accepted(veh):
    torque = [0.01, -0.02, 0.003]
    for form in (torque, tuple(torque), np.array(torque), np.array([torque]), np.array(torque).reshape(3, 1),
                 [np.float64(e) for e in torque], np.array([1, -2, 0])):
        same_mix(veh, np.float64(4.0), form)
    same_mix(veh, 4, [0, 0, 0])
    with pytest.raises(ValueError):
        mix(veh, 4.0, [0.0, 0.0])


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # numpy's, in both versions
def test_mix_non_finite_as_before(veh):
    for thrust, torque in [(math.nan, [0.01, 0.0, 0.0]), (math.inf, [0.01, 0.0, 0.0]), (-math.inf, [0.0, 0.0, 0.0]),
                           (4.0, [math.nan, 0.0, 0.0]), (4.0, [0.0, math.inf, 0.0]), (4.0, [0.0, 0.0, -math.inf])]:
        f, sat = mix(veh, thrust, torque)
        g, ref_sat = ref_mix(veh, thrust, torque)
        np.testing.assert_array_equal(f, g)
        assert sat == ref_sat


def test_pwm_maps_match_reference_bit_for_bit(veh):
    rng = np.random.default_rng(2)
    for f in [rng.uniform(-1, 1.5 * veh.max_thrust_n, 4) for _ in range(200)] + [
            [-1, 1e6, 0, veh.max_thrust_n], [math.nan, math.inf, -math.inf, 0.0], [0, 1, 2, 3]]:
        np.testing.assert_array_equal(thrust_to_pwm(veh, f), ref_thrust_to_pwm(veh, f))
        np.testing.assert_array_equal(thrust_to_pwm_floats(veh, np.asarray(f, float).tolist()),
                                      ref_thrust_to_pwm(veh, f))
    for p in [rng.uniform(500, 2500, 4) for _ in range(200)] + [[500, 2500, 1000, 2000], [1000, 1500, 2000, 1999.5]]:
        np.testing.assert_array_equal(pwm_to_thrust(veh, p), ref_pwm_to_thrust(veh, p))
        assert pwm_to_thrust_floats(veh, list(map(float, p))) == ref_pwm_to_thrust(veh, p).tolist()
    # other shapes keep the array behaviour
    many = rng.uniform(0, veh.max_thrust_n, (7, 4))
    np.testing.assert_array_equal(thrust_to_pwm(veh, many), ref_thrust_to_pwm(veh, many))
    np.testing.assert_array_equal(pwm_to_thrust(veh, 1500.0), ref_pwm_to_thrust(veh, 1500.0))
    assert thrust_to_pwm(veh, np.zeros(4)).dtype == np.float64


def test_scale_collective_and_motor_lag_match_reference(veh):
    rng = np.random.default_rng(5)
    a = veh.allocation
    for _ in range(300):
        f = rng.uniform(0.0, veh.max_thrust_n, 4)
        factor = rng.uniform(0.5, 2.0) if rng.random() < 0.9 else 1.0
        np.testing.assert_allclose(scale_collective(a, f, factor), ref_scale_collective(a, f, factor),
                                   rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(scale_collective(a, list(f), factor), ref_scale_collective(a, f, factor),
                                   rtol=1e-12, atol=1e-12)
        floats = scale_collective_floats(a, f.tolist(), factor)   # the motor driver's: the same bits
        assert floats == scale_collective(a, f, factor).tolist() and all(type(e) is float for e in floats)
        g = rng.uniform(0.0, veh.max_thrust_n, 4)
        np.testing.assert_array_equal(thrust_step(f, g, 0.0025, 0.02),
                                      ref_motor_forces_update(f, g, 0.0025, 0.02))
    # a copy of the allocation (another object) and many force vectors at once
    np.testing.assert_allclose(scale_collective(a.copy(), f, 1.1), ref_scale_collective(a, f, 1.1), rtol=1e-12)
    many = rng.uniform(0.0, veh.max_thrust_n, (4, 5))
    np.testing.assert_allclose(scale_collective(a, many, 0.9), ref_scale_collective(a, many, 0.9), rtol=1e-12)
    np.testing.assert_allclose(scale_collective(a.tolist(), f, 0.9), ref_scale_collective(a, f, 0.9), rtol=1e-12)
    assert scale_collective_floats(a.tolist(), f.tolist(), 0.9) == scale_collective(a.tolist(), f, 0.9).tolist()
    # round trip as the driver and the planner use it
    sent = scale_collective(a, f, 1 / 0.9)
    np.testing.assert_allclose(scale_collective(a, sent, 0.9), f, atol=1e-12)
