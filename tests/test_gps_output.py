"""GPS_INPUT content: known answers for GPS time, fix rules and satellite counts."""

import datetime

import numpy as np
import pytest

from auxgps.core.fusion import FusedEstimate
from auxgps.core.geometry import LocalFrame
from auxgps.core.gps_output import FIX_3D, FIX_NONE, gps_output, gps_week_time

FRAME = LocalFrame(47.397742, 8.545594, 488.0)


def estimate(sigma=0.1):
    return FusedEstimate(0.0, np.array([10.0, -5.0, -15.0]), np.array([1.0, 0.0, 0.0]), np.eye(3) * sigma**2, np.eye(3) * 0.01)


def test_gps_week_time_known_answers():
    assert gps_week_time(315964800.0 - 18.0) == (0, 0)  # the GPS epoch, in Unix time (UTC)
    # 2026-11-23T00:00:00Z is a Monday: GPS week 2446 began on Sunday 2026-11-22 (2446 * 7 days after the epoch).
    assert (datetime.date(2026, 11, 22) - datetime.date(1980, 1, 6)).days == 2446 * 7
    week, ms = gps_week_time(datetime.datetime(2026, 11, 23, tzinfo=datetime.timezone.utc).timestamp())
    assert week == 2446 and ms == (86400 + 18) * 1000


def test_believed_estimate_is_a_3d_fix_at_its_position():
    out = gps_output(estimate(), FRAME, 1.8e9, believed=True, gps1_sats=None, max_sigma_h_m=2.0)
    assert out.fix_type == FIX_3D and out.satellites == 6
    back = FRAME.to_ned(lat_deg=out.lat_deg, lon_deg=out.lon_deg, alt_amsl_m=out.alt_amsl_m)
    assert np.allclose(back, [10.0, -5.0, -15.0], atol=1e-6)
    assert out.horiz_accuracy_m == pytest.approx(0.1) and out.alt_amsl_m == pytest.approx(503.0, abs=1e-3)


@pytest.mark.parametrize("believed,sigma", [(False, 0.1), (True, 3.0), (True, float("nan"))])
def test_doubt_is_no_fix(believed, sigma):
    out = gps_output(estimate(sigma), FRAME, 1.8e9, believed=believed, gps1_sats=None, max_sigma_h_m=2.0)
    assert out.fix_type == FIX_NONE and out.satellites == 0


def test_never_more_satellites_than_a_healthy_gps1():
    assert gps_output(estimate(), FRAME, 1.8e9, believed=True, gps1_sats=10, max_sigma_h_m=2.0).satellites == 6
    assert gps_output(estimate(), FRAME, 1.8e9, believed=True, gps1_sats=5, max_sigma_h_m=2.0).satellites == 5
    assert gps_output(None, FRAME, 1.8e9, believed=True, gps1_sats=None, max_sigma_h_m=2.0).fix_type == FIX_NONE
