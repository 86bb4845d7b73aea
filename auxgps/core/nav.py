"""Navigation inputs to the core: where the autopilot says the vehicle is and how it is turned."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from auxgps.core.camera import CameraPose
from auxgps.core.heading import HeadingEstimate


@dataclass(frozen=True)
class NavSample:
    """The autopilot's telemetry at a frame's capture time.

    t_s : s; p_gps_ned_m : (3,) m or None without GPS; alt_above_origin_m : height above the local origin (barometric), m;
    R_ned_body : (3, 3) attitude; heading : the autopilot's heading error taken out of it (None: not solved, the
    heading as it came); attitude_sigma_rad : how far the attitude's tilt may be off, one sigma (None: the noise
    model's ``attitude_deg``; more while the body turns, as the frame's timing is uncertain); heading_sigma_rad : how
    far its heading may be off, one sigma (None: the noise model's ``heading_deg``).
    """

    t_s: float
    p_gps_ned_m: np.ndarray | None
    alt_above_origin_m: float
    R_ned_body: np.ndarray
    heading: HeadingEstimate | None = None
    attitude_sigma_rad: float | None = None
    heading_sigma_rad: float | None = None

    def camera_pose(self, R_body_cam: np.ndarray) -> CameraPose:
        """Camera pose from GPS north/east and barometric height (the camera at the body origin)."""
        if self.p_gps_ned_m is None:
            raise ValueError("no GPS position in this sample")
        p = np.array([self.p_gps_ned_m[0], self.p_gps_ned_m[1], -self.alt_above_origin_m], float)
        return CameraPose(p, self.R_ned_body @ R_body_cam)
