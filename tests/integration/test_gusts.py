"""Position hold in Dryden gusts (issue 26), on the stack's estimates, in lockstep, with the
wind estimation on."""

import numpy as np
import pytest

from flight.vehicle import load_vehicle
from schemas.flightlog import read_log

from .conftest import fly

pytestmark = pytest.mark.integration

# 2 m/s mean wind, MIL-F-8785C turbulence at the 1 m hover (W20 from the mean wind: sigma_u 0.63
# m/s). With the wind estimation the EKF learns the wind's pull as its disturbance states and the
# position law feeds it forward (docs/results.md, "Hold in wind")
DRYDEN = ("--set", "sim.wind_m_s=[2,0,0]", "--set", "sim.gust_model=dryden")
WIND_ESTIMATION = ("--set", "position.wind_estimation=true")


@pytest.mark.parametrize("seed", [0, 1])
def test_short_hover_in_dryden_gusts_holds_within_3_cm(tmp_path, seed):
    # the bench's 10 s holds measure 1.9-2.4 cm RMS over seeds 0-4; this 3 s hold after 2 s of
    # settling gets the same bound (the drag of a 2 m/s wind alone would hold laws (10) 3 cm off:
    # a_wind / (alpha k)); without the estimation these seeds hold 9-10 cm off
    proc, m = fly(tmp_path, "tests/integration/missions/hover-gusts.toml", *DRYDEN, *WIND_ESTIMATION, seed=seed)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert m["completed"] and not m["crashed"]
    assert m["measured_s"] >= 2.9
    assert m["position_rms_m"] < 0.03
    assert m["rejected_messages"]["position"].get("fusion_position_reset", 0) == 0
    # what the EKF learnt is the wind's drag: (drag / mass) x the simulator's wind, averaged over the hold
    log = read_log(tmp_path / "flight.mcap")
    vehicle = load_vehicle("x250")
    wind = np.mean([t["wind_m_s"][:2] for t in log["zp/0/sim/truth"] if t["header"]["t_s"] > 4.0], axis=0)
    pull = wind * vehicle.drag_n_per_m_s / vehicle.mass_kg
    learnt = log["zp/0/pos/ekf_health"][-1]["disturbance_m_s2"]
    assert np.allclose(learnt, pull, atol=0.15), (learnt, pull)
