import pytest

from simulator.config import SimConfig


def test_defaults_and_from_dict():
    c = SimConfig.from_dict({"tick_rate_hz": 800, "wind_m_s": [1, 0, 0], "physics_substeps": 2})
    assert c.tick_rate_hz == 800.0 and isinstance(c.tick_rate_hz, float)
    assert c.wind_m_s == (1.0, 0.0, 0.0)
    assert SimConfig().ticks_per_sample("camera_rate_hz") == 20
    assert SimConfig.from_dict(SimConfig().to_dict()) == SimConfig()


def test_unknown_key_refused():
    with pytest.raises(ValueError, match=r"simulator\.tick_rate\b"):
        SimConfig.from_dict({"tick_rate": 400})


@pytest.mark.parametrize("key, value", [
    ("tick_rate_hz", "fast"), ("physics_substeps", 2.5), ("physics_substeps", True),
    ("wind_m_s", [1, 2]), ("camera_width_px", 640.0), ("gyro_noise_var", -1.0),
    ("imu_rate_hz", 300.0), ("marker_size_m", 1.5), ("camera_drop_rate", 2.0),
])
def test_bad_values_name_the_key(key, value):
    with pytest.raises(ValueError, match=rf"simulator\.{key}"):
        SimConfig.from_dict({key: value})
