"""Position hold in Dryden gusts (issue 26), on the stack's estimates, in lockstep."""

import pytest

from .conftest import fly

pytestmark = pytest.mark.integration

# 2 m/s mean wind, MIL-F-8785C turbulence at the 1 m hover (W20 from the mean wind: sigma_u 0.63
# m/s); the wind settings: the disturbance observer, the hold integral, and an EKF velocity noise
# for the wind's unmodelled drag (docs/results.md)
DRYDEN = ("--set", "sim.wind_m_s=[2,0,0]", "--set", "sim.gust_model=dryden")
WIND_SETTINGS = ("--set", "position.disturbance_bandwidth_rad_s=3", "--set", "position.hold_ki=16",
                 "--set", "position.ekf={q_velocity_m2_s3=0.1}")


def test_short_hover_in_dryden_gusts_holds_within_3_cm(tmp_path):
    # the bench's 10 s holds measure 1.6-2.2 cm RMS over seeds 0-4; this 3 s hold after 2 s of settling gets the
    # same bound (the drag of a 2 m/s wind alone would hold laws (10) 3 cm off: a_wind / (alpha k))
    proc, m = fly(tmp_path, "tests/integration/missions/hover-gusts.toml", *DRYDEN, *WIND_SETTINGS)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert m["completed"] and not m["crashed"]
    assert m["measured_s"] >= 2.9
    assert m["position_rms_m"] < 0.03
