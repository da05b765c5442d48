"""Training the gyro-vertical of 004: criterion (10) minimised over the parameters of (7).

Apart from :mod:`flight.estimation.gyrovertical` (the filter that flies) so that the filter
imports neither scipy nor JAX; the batched JAX evaluation lives in
:mod:`flight.estimation.gyrovertical_jax`.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable, Sequence

import numpy as np
from scipy.optimize import minimize

from flight.estimation.gyrovertical import _FUNCS, DT_REF, GyroVerticalParams, TrainingSequence, evaluate
from flight.estimation.gyrovertical_jax import BatchEvaluator


def fixed(params: GyroVerticalParams) -> GyroVerticalParams:
    """The same variances at every n* (each function held at its n* = 0 value): the non-adaptive baseline."""
    return dataclasses.replace(params, **{f"{fn}_var2": getattr(params, f"{fn}_var0") for fn in _FUNCS})


FIXED_FREE = tuple(i for i, k in enumerate(GyroVerticalParams.names()) if k.endswith("_var0"))


def train(sequences: Sequence[TrainingSequence], initial: GyroVerticalParams | None = None,
          dt: float = DT_REF, maxiter: int = 100, seed: int = 0,
          progress: Callable[[int, float, GyroVerticalParams], None] | None = None,
          weights: tuple[float, float] = (0.5, 0.5), method: str = "Nelder-Mead",
          step: float = 0.7, adaptive: bool = True,
          compensation: tuple[int, int] | None = None) -> GyroVerticalParams:
    """Minimise (10) over the log-parameters with scipy.optimize (Nelder-Mead or Powell).

    adaptive=True: the 12 parameters of (7).  adaptive=False: the fixed-variance
    baseline, trained the same way over its 4 free parameters (the ``*_var0``;
    the result has ``var2 = var0``).  Sequences of one length are evaluated by
    the filter's step batched in JAX (:mod:`flight.estimation.gyrovertical_jax`, tested equal to
    :class:`GyroVertical`), others by :class:`GyroVertical` one sample at a time.
    The Nelder-Mead initial simplex is the initial point plus one vertex per
    free coordinate displaced by +-``step`` (natural log) with signs drawn from
    ``seed``, so the result is deterministic for a seed.  ``progress(k,
    best_cost, best_params)`` is called after every iteration.  Returns the
    best parameters evaluated (never worse than ``initial`` on these sequences).
    compensation: (window, delay) in samples: the filter with the acceleration compensation fed
    the sequences' accel_ref (:func:`flight.estimation.gyrovertical_jax.run_batch`); None: 004's.
    """
    initial = initial if initial is not None else GyroVerticalParams()
    if not adaptive:
        initial = fixed(initial)
    full0 = initial.to_vector()
    free = np.arange(12) if adaptive else np.array(FIXED_FREE)

    def expand(v) -> np.ndarray:
        full = full0.copy()
        full[free] = v
        if not adaptive:   # var2 follows var0: the functions are flat
            full[free + 2] = v
        return full

    if len({len(s.roll) for s in sequences}) == 1:
        batch = BatchEvaluator(sequences, dt, weights, adaptive, compensation)
        evaluate_full = batch
    else:
        def evaluate_full(full):
            return evaluate(GyroVerticalParams.from_vector(full), sequences, dt, weights, adaptive, compensation)

    x0 = full0[free]
    best = {"cost": math.inf, "x": x0.copy()}
    cache: dict[bytes, float] = {}

    def cost(v):
        key = np.asarray(v, dtype=np.float64).tobytes()
        if key not in cache:
            c = float(evaluate_full(expand(v)))
            cache[key] = c
            if c < best["cost"]:
                best["cost"], best["x"] = c, np.array(v, dtype=np.float64)
        return cache[key]

    it = [0]

    def callback(*_args, **_kw):
        it[0] += 1
        if progress is not None:
            progress(it[0], best["cost"], GyroVerticalParams.from_vector(expand(best["x"])))

    cost(x0)
    if method == "Nelder-Mead":
        rng = np.random.default_rng(seed)
        signs = rng.choice([-1.0, 1.0], size=x0.size)
        simplex = np.vstack([x0] + [x0 + step * signs[i] * np.eye(x0.size)[i] for i in range(x0.size)])
        minimize(cost, x0, method="Nelder-Mead", callback=callback,
                 options={"maxiter": int(maxiter), "initial_simplex": simplex,
                          "xatol": 1e-3, "fatol": 1e-4})
    elif method == "Powell":
        minimize(cost, x0, method="Powell", callback=callback,
                 options={"maxiter": int(maxiter), "xtol": 1e-3, "ftol": 1e-4})
    else:
        raise ValueError(f"gyrovertical: method must be 'Nelder-Mead' or 'Powell', got {method!r}")
    return GyroVerticalParams.from_vector(expand(best["x"]))
