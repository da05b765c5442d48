"""The image mode in a flight: the simulator renders what the camera sees, the vision service
detects the markers with OpenCV and flies the short hover on those poses, in lockstep."""

import pytest

from schemas.flightlog import read_log
from tests.integration.conftest import fly

pytestmark = pytest.mark.integration


def test_hover_on_image_mode_vision(tmp_path):
    proc, m = fly(tmp_path, "tests/integration/missions/hover-short.toml", "--set", "sim.camera_mode=image")
    assert m["completed"] and not m["crashed"], proc.stdout + proc.stderr
    assert m["position_rms_m"] < 0.02
    v = m["vision"]
    # every exposure in the air gave a pose, each within a centimetre of the truth
    assert v["pose_rate_airborne"] > 0.95 and v["position_err_mm_max"] < 10.0 and v["poses"] > 50
    log = read_log(tmp_path / "flight.mcap")
    assert "zp/0/sim/camera" not in log and not any("@image" in key or "camera_image" in key for key in log)
    assert "images, markers found in" in (tmp_path / "logs" / "vision.log").read_text()
