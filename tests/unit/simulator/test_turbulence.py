"""Dryden turbulence (simulator/turbulence.py): the draws' variance and correlation are the
MIL-F-8785C model's, at the simulator's tick as at a coarse step (exact discretisation), and the
simulator's gusts are seeded."""
import math

import numpy as np
import pytest

from flight.vehicle import load_vehicle
from simulator import SimConfig, Simulator
from simulator.turbulence import W20_LIGHT_M_S, DrydenTurbulence, scales, w20_from_wind


def test_low_altitude_scales_as_the_spec_gives_them():
    # MIL-F-8785C at h = 100 ft, light (W20 15 kt): L_w = 100 ft, L_u = 100 / 0.2593^1.2 ft,
    # sigma_w = 1.5 kt, sigma_u = sigma_w / 0.2593^0.4
    (l_u, l_v, l_w), (s_u, s_v, s_w) = scales(100 * 0.3048, W20_LIGHT_M_S)
    c = 0.177 + 0.000823 * 100
    assert l_w == pytest.approx(30.48)
    assert l_u == l_v == pytest.approx(100 / c ** 1.2 * 0.3048)
    assert s_w == pytest.approx(0.1 * 15 * 0.514444)
    assert s_u == s_v == pytest.approx(s_w / c ** 0.4)
    # the log profile: 20 ft up it is W20 itself
    assert w20_from_wind(5.0, 20 * 0.3048) == pytest.approx(5.0)


def test_discretisation_keeps_the_stationary_variance_at_the_tick():
    # exact discretisation: the stationary covariance P of each filter's states is a fixed point
    # of P = A P A' + Q_d (Q_d by quadrature), at 400 Hz as at 10 Hz
    for dt in (1 / 400, 0.1):
        d = DrydenTurbulence([2.0, 0.0, 0.0], 1.0, 3.0, dt)
        for f in (d._v, d._w):
            a00, a01, a10, a11 = f.a
            A = np.array([[a00, a01], [a10, a11]])
            P = np.diag(np.square(f.p))
            L = np.array([[f.l11, 0.0], [f.l21, f.l22]])
            np.testing.assert_allclose(A @ P @ A.T + L @ L.T, P, rtol=1e-9, atol=1e-12 * P.max())
        assert d._u.a ** 2 * d._u.sigma ** 2 + d._u.b ** 2 == pytest.approx(d._u.sigma ** 2, rel=1e-12)


def test_long_draw_matches_the_model_variance_and_correlation():
    # 12000 s at 0.1 s: ~3000 correlation times of u (T_u = 3.9 s), so the sample variance is
    # within ~3 % (1 sigma) and the autocorrelation within ~0.03; tolerances ~4 sigma
    dt, n = 0.1, 120_000
    d = DrydenTurbulence([0.0, 2.0, 0.0], 1.0, 3.17, dt)   # the wind along y: u along y, v along -x
    rng = np.random.default_rng(7)
    g = np.empty((n, 3))
    g[0] = d.start(rng)
    for i in range(1, n):
        g[i] = d.step(rng)
    u, v, w = g[:, 1], -g[:, 0], g[:, 2]
    (s_u, s_v, s_w), (t_u, t_v, t_w) = d.sigmas_m_s, d.taus_s
    for x, s in ((u, s_u), (v, s_v), (w, s_w)):
        assert x.std() == pytest.approx(s, rel=0.12)
        assert abs(x.mean()) < 0.15 * s

    def corr(x, lag_s):
        k = round(lag_s / dt)
        return float(np.mean(x[:-k] * x[k:]) / np.mean(x * x))

    for lag in (0.5 * t_u, t_u, 2 * t_u):
        assert corr(u, lag) == pytest.approx(math.exp(-lag / t_u), abs=0.08)
    for x, tau in ((v, t_v), (w, t_w)):
        for lag in (0.5 * tau, tau, 2 * tau):
            assert corr(x, lag) == pytest.approx((1 - lag / (2 * tau)) * math.exp(-lag / tau), abs=0.08)
    # v's zero crossing at 2 T (the Dryden lateral form), which a first-order process has not
    assert corr(v, 3 * t_v) < 0.0


def _gusts(seed, model="dryden"):
    cfg = SimConfig(initial_position_m=(0, 0, 1.0), wind_m_s=(2.0, 0.0, 0.0), gust_model=model,
                    gust_std_m_s=0.5)
    sim = Simulator(load_vehicle("x250"), cfg, seed=seed)
    out = []
    for _ in range(200):
        sim.step([1500.0] * 4, True)
        out.append(sim.state["wind_m_s"])
    return out


def test_dryden_gusts_are_seeded():
    a, b, c = _gusts(3), _gusts(3), _gusts(4)
    assert a == b
    assert a != c
    assert a != _gusts(3, "gauss-markov")


def test_dryden_needs_a_mean_wind():
    with pytest.raises(ValueError, match="simulator.gust_model"):
        SimConfig(gust_model="dryden")
    with pytest.raises(ValueError, match="gust_model"):
        SimConfig(gust_model="von-karman")
