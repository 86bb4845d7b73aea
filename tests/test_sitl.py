"""The closed loop on ArduPilot's own copter SITL: found through ARDUPILOT_SITL, skipped without it."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SITL = os.environ.get("ARDUPILOT_SITL")


@pytest.mark.sitl
@pytest.mark.skipif(not SITL or not Path(SITL).exists(), reason="set ARDUPILOT_SITL to an ArduCopter SITL binary to fly the real autopilot")
def test_sitl_flies_home_on_auxgps_through_a_gps1_failure(tmp_path):
    proc = subprocess.run([sys.executable, str(REPO / "tools" / "sitl_flight.py"), "--sitl", SITL, "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=1500, cwd=REPO)
    result = json.loads((tmp_path / "result.json").read_text())
    print(json.dumps(result))
    assert result["landed"] and result["landing_error_m"] <= 1.0, proc.stderr[-2000:]
    assert 3 in result["gps2_fix_types_seen"]  # the autopilot's GPS2 carried auxgps's 3D fix while GPS1 was down
    assert result["denied_s"] >= 180  # the closed loop: GPS1 down for at least 3 minutes
    assert len((tmp_path / "truth.csv").read_text().splitlines()) > 1000  # the truth track, to score it again
