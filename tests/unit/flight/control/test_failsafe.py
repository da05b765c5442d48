import math

import pytest

from flight.control.failsafe import Descent, DescentParams, LevelEstimate
from flight.quat import quat_from_euler, quat_to_rotation

G = 9.81


def test_level_estimate_follows_the_gyro_and_levels_on_the_accelerometer():
    # started 10 deg off in roll while the vehicle sits level: the accelerometer pulls it back
    est = LevelEstimate(quat_from_euler(math.radians(10), 0.0, 0.3), 0.0, accel_gain=1.0)
    for k in range(1, 2001):   # 5 s at 400 Hz
        est.update(k / 400, (0.0, 0.0, 0.0), (0.0, 0.0, G))
    roll, pitch, yaw = est.euler
    assert abs(math.degrees(roll)) < 0.1 and abs(pitch) < 1e-3 and yaw == pytest.approx(0.3, abs=1e-3)
    # a pure yaw rate integrates (the accelerometer cannot see yaw)
    for k in range(2001, 2401):
        est.update(k / 400, (0.0, 0.0, 0.5), (0.0, 0.0, G))
    assert est.euler[2] == pytest.approx(0.8, abs=1e-3)
    # samples out of order are ignored, a NaN-free estimate stays normalised
    est.update(1.0, (5.0, 0.0, 0.0), (0.0, 0.0, G))
    assert est.euler[2] == pytest.approx(0.8, abs=1e-3)
    assert sum(v * v for v in est.q) == pytest.approx(1.0)


@pytest.mark.parametrize("mass_error", [1.0, 1.3])
def test_descent_sinks_at_its_rate_and_ends_below_the_ground(mass_error):
    # a point mass with linear drag and a 50 ms motor lag, hovering at 5 m; the law thinks m = 1 kg
    m_true, drag, tau, dt = 1.0 * mass_error, 0.3, 0.05, 0.0025
    law = Descent(DescentParams(), mass_kg=1.0, gravity_m_s2=G, max_thrust_n=40.0)
    z, vz, f = 5.0, 0.0, m_true * G
    law.start(0.0, height_m=5.0, vz_m_s=0.0, thrust_n=f)
    q = (1.0, 0.0, 0.0, 0.0)
    touchdown, speeds, t = None, [], 0.0
    while not law.landed and t < 60.0:
        t += dt
        accel_world = 0.0 if z <= 0.0 else (f - drag * vz) / m_true - G
        specific = accel_world + G if z > 0.0 else G    # at rest on the ground: +1 g, no impact seen
        cmd = law.update(t, q, (0.0, 0.0, specific))
        f += (cmd - f) * dt / tau
        if z > 0.0:
            vz += accel_world * dt
            z += vz * dt
            speeds.append(-vz)
            if z <= 0.0:
                z, touchdown, vz = 0.0, speeds[-1], 0.0
    assert touchdown is not None and law.landed
    assert 0.3 < touchdown < 0.8          # a gentle touchdown near the sink rate
    # no fall on the way (30 % heavier than the law believes: it sinks faster until the I term has it)
    assert max(speeds) < (0.7 if mass_error == 1.0 else 1.5)
    assert law.update(t + dt, q, (0.0, 0.0, G)) == 0.0   # cut once over


def test_descent_params_are_checked():
    with pytest.raises(ValueError, match="unknown"):
        DescentParams.from_dict({"sink": 1.0})
    with pytest.raises(ValueError, match="sink_rate_m_s"):
        DescentParams.from_dict({"sink_rate_m_s": -1.0})
