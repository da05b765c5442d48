"""The planner's parameters (services/planner.py)."""

from __future__ import annotations

from flight.control.mission import FLIP_METHODS
from services.params import Param

PARAMS = {
    "mission": Param("hover", doc="the mission it flies: a shipped name (deploy/missions/) or a .toml path; "
                                  "`none`: wait for a ground station's"),
    "mpc_rate_hz": Param(0.0, "Hz", 0.0, doc="the flip's re-solve rate; 0: the method's default "
                                             "(project 100, thesis 20, baseline 200)"),
    "flip_method": Param("", choices=("", *FLIP_METHODS),
                         doc="fly every flip item with this method; \"\": as the mission says"),
    "compile_cache_dir": Param("~/.cache/zenpilot/jax",
                               doc="where compiled iLQR solvers are kept between starts; \"\": compile every start"),
    # flight/control/predict.py; `zenpilot predict` prints the same
    "flip_predict_rollouts": Param(256, "", 0, doc="before the first tick, each iLQR flip item is predicted over "
                                                   "this many uncertain cases; 0: no check"),
    "flip_clearance_m": Param(0.5, "m", doc="... and refused when its 95th-percentile loss from the hover leaves "
                                            "less than this"),
}
