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
                         doc="fly every flip with this method (the mission's items, a ground station's); "
                             "\"\": as the mission says"),
    # a MAVLink flip (command or mission item) needs a controller built before the first tick
    "flip_methods": Param([], choices=FLIP_METHODS,
                          doc="flip controllers built at start-up besides those of the mission's flip items, "
                              "e.g. [\"ilqr-project\"]: a MAVLink flip flies the first; []: only the mission's"),
    # a planner across a link from the vehicle (flight/control/lead.py): its plans would start in the past
    "plan_lead_s": Param(0.0, "s", 0.0, 0.5,
                         doc="an iLQR flip's plans start this far ahead of the planner's clock, from the state "
                             "predicted to then (the measured state flown forward on the model under the plans "
                             "sent): the time a plan takes to reach the motor driver, e.g. 0.04 across a 20 ms "
                             "link; 0: on the planner's clock, the state extrapolated to it (one host). Real "
                             "time only (in lockstep a plan flies in the tick after it is made)"),
    "plan_lead_auto": Param(False, doc="... at least that: the median age of the position states as they arrived "
                                       "over the last 2 s before the flip (the link's latency one way, taken for the "
                                       "plans' too), fixed for the flip; real time only"),
    # across a 5 % loss TLS link the states came ~0.2 s old and a flip planned from them fell 5 m
    # (docs/reliability.md); the open split's UDP across the same link: 0.077 s, flown
    "flip_max_lead_s": Param(0.15, "s", 0.0,
                             doc="with plan_lead_auto: a flip whose plans would lead by more than this (the states "
                                 "reach the planner that late) is refused, never started, the vehicle held "
                                 "(`flip-refused`); 0: no bound"),
    "compile_cache_dir": Param("~/.cache/zenpilot/jax",
                               doc="where compiled iLQR solvers are kept between starts; \"\": compile every start"),
    # flight/control/predict.py; `zenpilot predict` prints the same
    "flip_predict_rollouts": Param(256, "", 0, doc="before the first tick, each iLQR flip (the mission's items, "
                                                   "a ground station's) is predicted over this many uncertain "
                                                   "cases; 0: no check"),
    # off by default: the pre-arm check stays a second or two and errs on the safe side (the replay's
    # losses are the larger); `zenpilot predict` adapts by default, for the calibrated envelope
    "flip_predict_adapt": Param(False, doc="... each case replaying the controller's flight on its own vehicle "
                                           "(20 more flights of the controller at start-up, ~1 s each); false: the "
                                           "nominal's plans and gains in every case (pessimistic on a stronger vehicle)"),
    "flip_clearance_m": Param(0.5, "m", doc="... and refused when its 95th-percentile loss from the hover leaves "
                                            "less than this"),
}
