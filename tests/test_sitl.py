"""The closed loop on ArduPilot's own copter SITL: found through ARDUPILOT_SITL, skipped without it."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import load_tool

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


def test_lag_correlation_known_answers():
    """Errors made of a constant shared part and fresh per-frame noise of equal variance correlate 0.5 at every lag;
    fresh noise alone does not correlate; a lag with no pair inside the tolerance gives None."""
    sf = load_tool("sitl_flight")
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 600.0, 0.1)
    shared = np.repeat(rng.standard_normal((len(t) // 100, 2)), 100, axis=0)  # constant over 10 s blocks
    fresh = rng.standard_normal((len(t), 2))
    corr = sf.lag_correlation(t, shared + fresh, lags_s=(0.1, 1.0))
    assert corr["0.1s"] == pytest.approx([0.5, 0.5], abs=0.05) and corr["1s"] == pytest.approx([0.45, 0.45], abs=0.05)
    assert sf.lag_correlation(t, fresh, lags_s=(0.1,))["0.1s"] == pytest.approx([0.0, 0.0], abs=0.05)
    assert sf.lag_correlation(t, fresh, lags_s=(0.05,), tol_s=0.01)["0.05s"] is None
