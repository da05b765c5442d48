"""The camera's delay watched online, two ways (the position level's camera fixes, 20 Hz).

(a) The delay the stamps show: arrival time minus exposure stamp of each fix, a running median
over the last `window` fixes (a late frame or two do not move it). A median that leaves the level
last reported by more than `step_s` is a delay step: reported, and the level moves there. The EKF
fuses each fix at its own stamp (flight/estimation/position_ekf.py), so a delay the stamps show is
compensated fix by fix; what (a) adds is seeing it (a slower exposure, a loaded detector, a delay
nearing the EKF's history `max_delay_s`).

(b) The delay the stamps do not show: a shutter stamped late, a camera clock offset from the
vehicle's. A fix taken at t - d but fused at t disagrees with the filter along the velocity:
against a filter that is right, its innovation is y = z - p(t) = -v d. The filter does not stay
right: it follows the late fixes, and at a constant velocity it settles v d behind with
zero-mean innovations (an offset of the position and d cannot be told apart there). So the
regressor is the innovation's sensitivity to d through the filter, as a recursive
prediction-error method takes it: phi = -(v + E_p), with E = d(p_hat, v_hat)/dd carried along
the fixes (E_p += E_v dt between fixes; E += K phi at a fused fix, K the EKF's gain of that fix;
a gated fix leaves E alone). At a constant velocity E_p -> -v and phi -> 0: what informs d is
a change of velocity, as it should be (a 1 m step of the missions: a few ms of std).

The v in phi is the filter's velocity less the sum of the camera fixes' corrections to it
(K_v y): the velocity of the model alone (attitude and thrust), which drifts only slowly, and the
sensitivity recursion high-passes it anyway. With the filter's own velocity the fit is biased:
that velocity's error comes from the same fixes as the position error in y, correlated with it
wherever the filter's process noise is above the truth's (in the unit tests' synthetic flight
+11 ms with no offset at all, and 70 ms read as 55; in the missions +5..18 ms).

d is the least-squares fit of y + phi c = phi d over the fixes (c: the correction the fix was
fused with, so the fit sees the whole offset however much of it is corrected already), with
exponential forgetting (time constant `forget_s`), and its standard error is the fit's:
std_d^2 = s_r^2 / sum(phi.phi), s_r^2 the residuals' mean square. Both come from four running
sums: O(1) per fix, plain floats.

The correction: an estimate confident (std_d below `confident_std_s`, `min_fixes` fitted) and
away from the correction applied by more than max(`deadband_s`, `detect_sigmas` std_d) is a
detection (counted). From the first one on, the correction follows the estimate whenever it is
confident (the fit is first order in d - c: it understates a large offset and is exact near it),
at `slew_s_s` at most, within +-`max_correction_s`; the position level fuses each fix at its
stamp less the correction. With the vehicle at rest nothing is learnt, and nothing needs
correcting: a wrong delay costs only where the vehicle moves.
Pure algorithm, no I/O.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from flight.param import Declared, declared

__all__ = ["CameraDelayError", "CameraDelayParams", "CameraDelayEstimator", "STD_CAP_S"]

STD_CAP_S = 1.0   # the std reported when nothing has been learnt (the health message needs a number)


class CameraDelayError(ValueError):
    """Bad parameters or inputs to the camera delay estimator."""


@dataclass(frozen=True)
class CameraDelayParams(Declared):
    """The position service's `camera_delay` table."""

    error = CameraDelayError

    # 20 fixes: a second at 20 Hz; the median moves after half of them
    window: int = declared(20, "", 3, doc="fixes in the running median of (arrival - stamp)")
    # the frame-to-frame spread of the arrival (the 100 Hz loop that takes it) is 10 ms
    step_s: float = declared(0.02, "s", 0.0, min_exclusive=True,
                             doc="a running median this far from the level last reported is a delay step")
    # long enough to hold a step's information through the hold after it, short enough to
    # forget the old delay within a couple of manoeuvres
    forget_s: float = declared(2.0, "s", 0.0, min_exclusive=True,
                               doc="forgetting time constant of the offset's regression on the innovations")
    confident_std_s: float = declared(0.01, "s", 0.0, min_exclusive=True,
                                      doc="the offset estimate is confident when its std is below this")
    detect_sigmas: float = declared(3.0, "", 0.0, doc="an offset this many std from the correction is detected ...")
    # what the fit reads with no offset at all (the model's own timing errors, noise) stays inside
    # it: up to 8 ms in the shipped missions (attitude-steps), 5 ms in the unit tests' flights
    deadband_s: float = declared(0.025, "s", 0.0, doc="... and at least this far")
    max_correction_s: float = declared(0.15, "s", 0.0, doc="the correction's bound (either sign)")
    slew_s_s: float = declared(0.1, "s/s", 0.0, min_exclusive=True, doc="the correction's rate limit")
    correct: bool = declared(True, doc="fuse the fixes at their stamp less the estimated offset (false: estimate "
                                       "and report only)")
    # a position reset, a wrong marker solution: not a timing error
    max_innovation_m: float = declared(0.5, "m", 0.0, min_exclusive=True,
                                       doc="a fix whose innovation is larger is left out of the regression")
    # a handful of fixes fits anything: half a second of them at 20 Hz before trusting the std
    min_fixes: float = declared(10.0, "", 1.0, doc="fixes (forgetting-weighted) the fit needs before it may be "
                                                  "confident")
    # the camera's few-mm noise: a fit better than this is luck, not knowledge
    residual_floor_m: float = declared(0.001, "m", 0.0, doc="floor on the fit's residual std")


class CameraDelayEstimator:
    """(a) and (b) of the module doc. `transport` and `innovation` per camera fix, `reset` when the
    filter restarts its position; the figures as properties. One per filter, one thread."""

    def __init__(self, params: CameraDelayParams | None = None):
        self.params = p = params if params is not None else CameraDelayParams()
        # (a)
        self._delays: deque = deque(maxlen=p.window)
        self.transport_level_s: float | None = None   # the level last reported
        self.transport_steps = 0
        # (b): E = (E_p, E_v) per axis, the sums of the fit, the correction
        self._ep = [0.0, 0.0, 0.0]
        self._ev = [0.0, 0.0, 0.0]
        self._vcam = [0.0, 0.0, 0.0]
        self._t: float | None = None    # the last fix's fusion time
        self._a = self._b = self._c = self._n = 0.0   # sum phi.phi, phi.y~, y~.y~, scalar observations
        self.correction_s = 0.0
        self._target = 0.0
        self._discrepant = False   # the estimate is outside the detection threshold
        self._engaged = False      # an offset was detected: the correction follows the estimate when confident
        self.detections = 0
        self.fitted = 0

    # ------------------------------------------------------------------ (a)
    def transport(self, t_arrival_s: float, t_stamp_s: float) -> bool:
        """A fix stamped t_stamp_s arrived at t_arrival_s; True when this makes a delay step."""
        d = t_arrival_s - t_stamp_s
        if not math.isfinite(d):
            raise CameraDelayError(f"transport: times must be finite (got {t_arrival_s!r}, {t_stamp_s!r})")
        delays = self._delays
        delays.append(d)
        if len(delays) < delays.maxlen:
            return False
        median = self.transport_s
        if self.transport_level_s is None:
            self.transport_level_s = median
            return False
        if abs(median - self.transport_level_s) > self.params.step_s:
            self.transport_level_s = median
            self.transport_steps += 1
            return True
        return False

    @property
    def transport_s(self) -> float:
        """The running median of arrival - stamp (NaN before the first fix)."""
        s = sorted(self._delays)
        n = len(s)
        if not n:
            return math.nan
        return s[n // 2]   # the upper median of an even count: a step moves it once, not through the middle

    @property
    def transport_spread_s(self) -> float:
        """max - min of arrival - stamp over the window (0 before the first fix)."""
        return max(self._delays) - min(self._delays) if self._delays else 0.0

    # ------------------------------------------------------------------ (b)
    def innovation(self, t_fuse_s: float, y, v, gain=None, fit: bool = True) -> bool:
        """A fix fused (or gated) at t_fuse_s with the correction `correction_s`: its innovation y
        (3), the filter's velocity v (3) there, and the gain K (13x3 or at least 6x3: the rows of the
        position and velocity) when it was fused, None when gated. Returns True on a detection.
        Updates the estimate, then moves the correction (toward the estimate, rate limited).
        fit=False: the sensitivities follow the fix, the fit leaves it out (the filter coasted
        meanwhile, e.g. through a flip: its error then is not a matter of timing)."""
        p = self.params
        # plain floats: at this size numpy's per-call overhead, not the arithmetic, is the cost
        y0, y1, y2 = y.tolist() if isinstance(y, np.ndarray) else map(float, y)
        v0, v1, v2 = v.tolist() if isinstance(v, np.ndarray) else map(float, v)
        t = float(t_fuse_s)
        if not math.isfinite(t + y0 + y1 + y2 + v0 + v1 + v2):   # a sum is finite only if every term is
            raise CameraDelayError("innovation: inputs must be finite")
        ep, ev, vc = self._ep, self._ev, self._vcam
        h = 0.0 if self._t is None else max(0.0, t - self._t)
        self._t = t
        if h:   # E_p += E_v h: the velocity's sensitivity carries the position's on
            ep[0] += ev[0] * h
            ep[1] += ev[1] * h
            ep[2] += ev[2] * h
            lam = math.exp(-h / p.forget_s)
            self._a *= lam
            self._b *= lam
            self._c *= lam
            self._n *= lam
        # phi = dy/dd, on the velocity less the camera's corrections: the model's own (module doc)
        f0, f1, f2 = -(v0 - vc[0] + ep[0]), -(v1 - vc[1] + ep[1]), -(v2 - vc[2] + ep[2])
        if gain is not None:   # the correction K y moved the state by K phi per unit of d
            k0, k1, k2, k3, k4, k5 = gain[0:6].tolist() if isinstance(gain, np.ndarray) else gain[0:6]
            ep[0] += k0[0] * f0 + k0[1] * f1 + k0[2] * f2
            ep[1] += k1[0] * f0 + k1[1] * f1 + k1[2] * f2
            ep[2] += k2[0] * f0 + k2[1] * f1 + k2[2] * f2
            ev[0] += k3[0] * f0 + k3[1] * f1 + k3[2] * f2
            ev[1] += k4[0] * f0 + k4[1] * f1 + k4[2] * f2
            ev[2] += k5[0] * f0 + k5[1] * f1 + k5[2] * f2
            vc[0] += k3[0] * y0 + k3[1] * y1 + k3[2] * y2
            vc[1] += k4[0] * y0 + k4[1] * y1 + k4[2] * y2
            vc[2] += k5[0] * y0 + k5[1] * y1 + k5[2] * y2
        m = p.max_innovation_m
        if fit and -m <= y0 <= m and -m <= y1 <= m and -m <= y2 <= m:
            c = self.correction_s   # y = phi (d - c): fit y + phi c = phi d
            w0, w1, w2 = y0 + f0 * c, y1 + f1 * c, y2 + f2 * c
            self._a += f0 * f0 + f1 * f1 + f2 * f2
            self._b += f0 * w0 + f1 * w1 + f2 * w2
            self._c += w0 * w0 + w1 * w1 + w2 * w2
            self._n += 3.0
            self.fitted += 1
        return self._decide(h)

    def _decide(self, h: float) -> bool:
        p = self.params
        detected = False
        if self._n >= 3.0 * p.min_fixes:
            std = self.offset_std_s
            if std < p.confident_std_s:   # confident
                d = self._b / self._a
                discrepant = abs(d - self.correction_s) > max(p.deadband_s, p.detect_sigmas * std)
                if discrepant and not self._discrepant:
                    detected = self._engaged = True
                    self.detections += 1
                self._discrepant = discrepant
                if self._engaged:   # once an offset was found, the correction follows the estimate
                    # (the fit is first order in d - correction: exact only near it)
                    self._target = min(p.max_correction_s, max(-p.max_correction_s, d))
        if p.correct and self._target != self.correction_s:
            step = p.slew_s_s * min(h, 0.2)   # a gap in the fixes is no licence to jump
            c = self.correction_s
            self.correction_s = min(self._target, c + step) if self._target > c else max(self._target, c - step)
        return detected

    @property
    def offset_s(self) -> float:
        """The estimated offset d (s; positive: the fixes are older than their stamps say); 0
        before anything is learnt."""
        return self._b / self._a if self._a > 0.0 else 0.0

    @property
    def offset_std_s(self) -> float:
        """Its standard error (s), STD_CAP_S at most (nothing learnt)."""
        a = self._a
        if a <= 0.0 or self._n <= 1.0:
            return STD_CAP_S
        ssr = max(0.0, self._c - self._b * self._b / a)
        var_r = max(ssr / (self._n - 1.0), self.params.residual_floor_m ** 2)
        return min(STD_CAP_S, math.sqrt(var_r / a))

    @property
    def confident(self) -> bool:
        return self._n >= 3.0 * self.params.min_fixes and self.offset_std_s < self.params.confident_std_s

    def reset(self) -> None:
        """The filter restarted its position at a fix (PositionEKF.reset_position): the
        sensitivities start again; what the fit learnt stays."""
        self._ep = [0.0, 0.0, 0.0]
        self._ev = [0.0, 0.0, 0.0]
