"""What auxgps tells the autopilot: the fields of one GPS_INPUT message, from the filter's estimate.

Pure: SI units, degrees and metres; the MAVLink link turns these into the message's integer units.

Rules (see README, "What auxgps sends when"):
- ``fix_type`` 3 (3D) only while auxgps believes its estimate: the filter has been corrected by GPS1 or by a
  visual fix within ``max_age_s``, and its horizontal sigma is at most ``max_sigma_h_m``. Otherwise 1 (no fix),
  still at the full rate, so the autopilot sees a healthy receiver without a position, never a guess.
- ``horiz_accuracy``, ``vert_accuracy``, ``speed_accuracy``: the filter's one-sigma (worst horizontal axis).
- Satellites: never more than GPS1 reports while GPS1 has a 3D fix, so that ArduPilot's "use best" switching
  cannot prefer auxgps over a healthy GPS1; 6 otherwise (EKF3 does not inflate its noise at 6 or more).
- GPS week time of the estimate, so that ArduPilot timestamps it by the estimate's time, not its arrival.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from auxgps.core.fusion import FusedEstimate
from auxgps.core.geometry import LocalFrame

GPS_EPOCH_UNIX_S = 315964800.0  # 1980-01-06T00:00:00Z
GPS_LEAP_S = 18.0  # GPS - UTC since 2017-01-01
SECONDS_PER_WEEK = 604800.0
FIX_NONE, FIX_3D = 1, 3


@dataclass(frozen=True)
class GpsOutput:
    """One GPS_INPUT's content. Angles deg, lengths m, speeds m/s."""

    time_week: int
    time_week_ms: int
    fix_type: int
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    vel_ned_m_s: np.ndarray
    horiz_accuracy_m: float
    vert_accuracy_m: float
    speed_accuracy_m_s: float
    hdop: float
    vdop: float
    satellites: int


def gps_week_time(t_unix_s: float) -> tuple[int, int]:
    """(GPS week, milliseconds into the week) of a Unix time."""
    gps_s = t_unix_s - GPS_EPOCH_UNIX_S + GPS_LEAP_S
    week = int(gps_s // SECONDS_PER_WEEK)
    return week, int(round((gps_s - week * SECONDS_PER_WEEK) * 1000.0))


def gps_output(
    estimate: FusedEstimate | None,
    frame: LocalFrame,
    t_unix_of_estimate_s: float,
    *,
    believed: bool,
    gps1_sats: int | None,
    max_sigma_h_m: float,
) -> GpsOutput:
    """The GPS_INPUT content for ``estimate`` (None: nothing to say yet).

    ``believed``: the caller's judgement that the estimate is backed by recent evidence (GPS1 or a visual
    fix); ``gps1_sats``: GPS1's satellites while it has a 3D fix, else None.
    """
    week, week_ms = gps_week_time(t_unix_of_estimate_s)
    sats = 6 if gps1_sats is None else max(0, min(6, int(gps1_sats)))
    if estimate is None:
        return GpsOutput(week, week_ms, FIX_NONE, frame.lat_deg, frame.lon_deg, frame.alt_amsl_m, np.zeros(3), 999.0, 999.0, 99.0, 99.99, 99.99, 0)
    lat, lon, alt = frame.to_geodetic(estimate.p_ned_m)
    sigma_h = estimate.sigma_h_worst_m
    fix = FIX_3D if believed and np.isfinite(sigma_h) and sigma_h <= max_sigma_h_m else FIX_NONE
    return GpsOutput(
        time_week=week,
        time_week_ms=week_ms,
        fix_type=fix,
        lat_deg=float(lat),
        lon_deg=float(lon),
        alt_amsl_m=float(alt),
        vel_ned_m_s=estimate.v_ned_m_s.copy(),
        horiz_accuracy_m=float(sigma_h),
        vert_accuracy_m=estimate.sigma_v_m,
        speed_accuracy_m_s=estimate.sigma_speed_m_s,
        # HDOP as a receiver would give it for this accuracy (about 0.5 m of range error per unit of HDOP).
        hdop=float(np.clip(sigma_h / 0.5, 0.5, 99.99)),
        vdop=float(np.clip(estimate.sigma_v_m / 0.5, 0.5, 99.99)),
        satellites=sats if fix == FIX_3D else 0,
    )
