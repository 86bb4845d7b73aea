"""What the estimator is told: the autopilot's telemetry and the camera's frames, as plain timestamped records.

Every time is in seconds on one monotonic clock (the companion's; a simulator's; a recording's), angles in
radians, lengths in metres. The MAVLink link decodes the autopilot's messages into these; a simulator makes them
from its truth plus noise; a replay reads them back from a recording.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Attitude:
    """The autopilot's attitude (ATTITUDE): roll, pitch, yaw of the body in NED, rad, and its body rates (p, q, r:
    rollspeed, pitchspeed, yawspeed), rad/s (None: not sent)."""

    t_s: float
    euler_rad: np.ndarray
    rate_body_rad_s: np.ndarray | None = None


@dataclass(frozen=True)
class Imu:
    """One accelerometer sample (SCALED_IMU): specific force in the FRD body frame, m/s^2."""

    t_s: float
    f_body_m_s2: np.ndarray


@dataclass(frozen=True)
class Gps1:
    """GPS1 as the autopilot reports it (GPS_RAW_INT); ``t_s`` is when the autopilot got the fix, not when the
    receiver measured it (that is the receiver's lag earlier)."""

    t_s: float
    fix_type: int
    satellites: int
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    h_acc_m: float


@dataclass(frozen=True)
class Position:
    """The autopilot's own estimate (GLOBAL_POSITION_INT); auxgps uses its height above home, ``alt_above_home_m``
    (barometric, above where the vehicle armed)."""

    t_s: float
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    alt_above_home_m: float


@dataclass(frozen=True)
class Frame:
    """A camera image, BGR uint8 (H, W, 3), its capture time, s, and how far that time may be from the autopilot's
    clock, one sigma, s (None: the noise model's ``frame_time_s``; 0: exact, as the simulator's own frames are)."""

    t_s: float
    image_bgr: np.ndarray
    time_sigma_s: float | None = None


Telemetry = Attitude | Imu | Gps1 | Position
