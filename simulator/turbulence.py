"""Dryden turbulence, MIL-F-8785C low-altitude forms (h < 1000 ft), drawn on the simulator's tick.

The spec's forms (h, L in ft; W20 the wind speed 20 ft above ground; V the airspeed):

    L_w = h,   L_u = L_v = h / (0.177 + 0.000823 h)^1.2
    sigma_w = 0.1 W20,   sigma_u = sigma_v = sigma_w / (0.177 + 0.000823 h)^0.4
    H_u(s) = sigma_u sqrt(2 L_u / (pi V)) / (1 + T_u s)                     T = L / V
    H_v(s) = sigma_v sqrt(L_v / (pi V)) (1 + sqrt(3) T_v s) / (1 + T_v s)^2   (H_w: the same in L_w)

u is along the mean wind's horizontal direction, v across it, w up (world ENU). A hovering
vehicle's airspeed is the mean wind's: V = |wind_m_s| (Taylor's frozen turbulence swept past).
Their autocorrelations: R_u(t) = sigma_u^2 e^(-t/T_u), R_v(t) = sigma_v^2 (1 - t/(2 T_v)) e^(-t/T_v).

Discretised exactly over a tick (not Tustin, as RotorPy's wind-dynamics filters are): each filter
is a linear state-space system driven by white noise; the state moves by e^(A dt), plus a Gaussian
of covariance Q_d = integral_0^dt e^(As) B B' e^(A's) ds (e^(As) in closed form, the integral by
32-point Gauss-Legendre quadrature: exact to rounding for this smooth integrand), so the draws'
variance and correlation are the model's at any tick rate. The state starts drawn from its
stationary covariance (no transient).
"""
from __future__ import annotations

import math

import numpy as np

FT_M = 0.3048
KNOT_M_S = 0.514444
# MIL-F-8785C's low-altitude W20 per severity (15, 30, 45 kt)
W20_LIGHT_M_S = 15 * KNOT_M_S
W20_MODERATE_M_S = 30 * KNOT_M_S
W20_SEVERE_M_S = 45 * KNOT_M_S
LOW_ALTITUDE_MAX_M = 1000 * FT_M
# MIL-F-8785C's wind-shear profile W(h) = W20 ln(h / z0) / ln(20 / z0), z0 = 0.15 ft (phase C)
_Z0_FT = 0.15


def w20_from_wind(speed_m_s: float, altitude_m: float) -> float:
    """The wind speed at 20 ft whose MIL-F-8785C log profile gives speed_m_s at altitude_m."""
    h_ft = max(altitude_m / FT_M, 2.0 * _Z0_FT)    # the profile is zero at z0 and negative below
    return speed_m_s * math.log(20.0 / _Z0_FT) / math.log(h_ft / _Z0_FT)


def scales(altitude_m: float, w20_m_s: float) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """((L_u, L_v, L_w) m, (sigma_u, sigma_v, sigma_w) m/s) at altitude_m for the wind W20."""
    h = altitude_m / FT_M
    c = 0.177 + 0.000823 * h
    l_u = h / c ** 1.2 * FT_M
    sigma_w = 0.1 * w20_m_s
    sigma_u = sigma_w / c ** 0.4
    return (l_u, l_u, altitude_m), (sigma_u, sigma_u, sigma_w)


def _expm_second(t: float, tau: float) -> tuple[float, float, float, float]:
    """e^(A t) for A = [[0, 1], [-1/tau^2, -2/tau]] (a double pole at -1/tau), row-major."""
    e, r = math.exp(-t / tau), t / tau
    return e * (1.0 + r), e * t, -e * t / (tau * tau), e * (1.0 - r)


_GL_X, _GL_W = np.polynomial.legendre.leggauss(32)


class _FirstOrder:
    """sigma / (1 + tau s): a Gauss-Markov process of variance sigma^2, exact per step."""

    def __init__(self, sigma: float, tau: float, dt: float):
        self.a = math.exp(-dt / tau)
        self.b = sigma * math.sqrt(-math.expm1(-2.0 * dt / tau))
        self.sigma = sigma
        self.y = 0.0

    def start(self, n: float) -> None:
        self.y = self.sigma * n

    def step(self, n: float) -> float:
        self.y = self.a * self.y + self.b * n
        return self.y


class _SecondOrder:
    """sigma sqrt(tau) (1 + sqrt(3) tau s) / (1 + tau s)^2 on unit white noise, in the controllable
    form x1' = x2, x2' = -x1/tau^2 - 2 x2/tau + n, y = g (x1/tau^2 + sqrt(3) x2/tau): its
    stationary covariance is diag(tau^3/4, tau/4), so var y = g^2 / tau = sigma^2."""

    def __init__(self, sigma: float, tau: float, dt: float):
        self.c1 = sigma * math.sqrt(tau) / (tau * tau)
        self.c2 = sigma * math.sqrt(tau) * math.sqrt(3.0) / tau
        self.p = (math.sqrt(tau ** 3 / 4.0), math.sqrt(tau / 4.0))   # stationary std of x1, x2
        self.a = _expm_second(dt, tau)
        # Q_d = int_0^dt e^(As) B B' e^(A's) ds, B = [0, 1]': e^(As) B = (a01(s), a11(s))
        q11 = q12 = q22 = 0.0
        for x, w in zip(_GL_X.tolist(), _GL_W.tolist()):
            s = 0.5 * dt * (x + 1.0)
            _, b0, _, b1 = _expm_second(s, tau)
            q11 += w * b0 * b0
            q12 += w * b0 * b1
            q22 += w * b1 * b1
        half = 0.5 * dt
        q11, q12, q22 = q11 * half, q12 * half, q22 * half
        self.l11 = math.sqrt(q11)
        self.l21 = q12 / self.l11
        self.l22 = math.sqrt(max(q22 - self.l21 * self.l21, 0.0))
        self.x1 = self.x2 = 0.0

    def start(self, n1: float, n2: float) -> None:
        self.x1, self.x2 = self.p[0] * n1, self.p[1] * n2

    def step(self, n1: float, n2: float) -> float:
        a00, a01, a10, a11 = self.a
        x1, x2 = self.x1, self.x2
        w1 = self.l11 * n1
        self.x1 = a00 * x1 + a01 * x2 + w1
        self.x2 = a10 * x1 + a11 * x2 + self.l21 * n1 + self.l22 * n2
        return self.output()

    def output(self) -> float:
        return self.c1 * self.x1 + self.c2 * self.x2


class DrydenTurbulence:
    """Dryden gusts in world ENU for the mean wind wind_m_s, at altitude_m, with intensity W20.

    start(rng) draws the stationary start; step(rng) advances one dt and returns the gust (3
    floats). 5 normals a call from rng, in a fixed order (u; v's two; w's two): seeded and
    deterministic."""

    def __init__(self, wind_m_s, altitude_m: float, w20_m_s: float, dt: float):
        wx, wy, wz = (float(v) for v in wind_m_s)
        speed = math.sqrt(wx * wx + wy * wy + wz * wz)
        if not speed > 0.0:
            raise ValueError("Dryden turbulence needs a mean wind (its length scales are swept past at the "
                             "wind's speed): wind_m_s is zero")
        if not 0.0 < altitude_m <= LOW_ALTITUDE_MAX_M:
            raise ValueError(f"Dryden turbulence: altitude {altitude_m:g} m is outside the low-altitude forms "
                             f"(0, {LOW_ALTITUDE_MAX_M:g}] m")
        horiz = math.hypot(wx, wy)
        self.heading = (wx / horiz, wy / horiz) if horiz > 0.0 else (1.0, 0.0)
        self.lengths_m, self.sigmas_m_s = scales(altitude_m, w20_m_s)
        self.taus_s = tuple(length / speed for length in self.lengths_m)
        su, sv, sw = self.sigmas_m_s
        tu, tv, tw = self.taus_s
        self._u = _FirstOrder(su, tu, dt)
        self._v = _SecondOrder(sv, tv, dt)
        self._w = _SecondOrder(sw, tw, dt)

    def start(self, rng: np.random.Generator) -> list[float]:
        n0, n1, n2, n3, n4 = rng.normal(0.0, 1.0, 5).tolist()
        self._u.start(n0)
        self._v.start(n1, n2)
        self._w.start(n3, n4)
        return self._world(self._u.y, self._v.output(), self._w.output())

    def step(self, rng: np.random.Generator) -> list[float]:
        n0, n1, n2, n3, n4 = rng.normal(0.0, 1.0, 5).tolist()
        return self._world(self._u.step(n0), self._v.step(n1, n2), self._w.step(n3, n4))

    def _world(self, u: float, v: float, w: float) -> list[float]:
        cx, cy = self.heading
        return [cx * u - cy * v, cy * u + cx * v, w]
