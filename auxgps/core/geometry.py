"""Frames and rotations.

Conventions
-----------
- Local frame: NED (north, east, down) in metres, anchored at a geodetic origin (:class:`LocalFrame`).
- Body frame: FRD (forward, right, down). ``R_ned_body`` maps body coordinates into NED.
- Camera frame: OpenCV (x right, y down in the image, z along the optical axis). ``R_body_cam`` maps camera
  coordinates into the body frame. The default mount looks straight down with image-up towards the nose.
- Euler angles are aerospace ZYX (yaw, then pitch, then roll), in radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pymap3d
from scipy.spatial.transform import Rotation

#: Camera looking straight down, image top towards the nose: cam x = body right, cam y = body back, cam z = body down.
R_BODY_CAM_DOWN = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


_TRIU = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


def pack_sym(M: np.ndarray) -> np.ndarray:
    """(..., 3, 3) symmetric -> (..., 6) upper triangle."""
    return M[..., _TRIU[0], _TRIU[1]]


def unpack_sym(v: np.ndarray) -> np.ndarray:
    """(..., 6) upper triangle -> (..., 3, 3) symmetric."""
    v = np.asarray(v, float)
    M = np.empty(v.shape[:-1] + (3, 3))
    M[..., _TRIU[0], _TRIU[1]] = v
    M[..., _TRIU[1], _TRIU[0]] = v
    return M


def solve_sym3(a_packed: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``A^-1 v`` for symmetric positive definite ``A`` given packed (..., 6), ``v`` (..., 3), by cofactors: for
    thousands of 3x3 systems at once, several times faster than ``np.linalg.solve``."""
    a00, a01, a02, a11, a12, a22 = np.moveaxis(np.asarray(a_packed, float), -1, 0)
    c00, c01, c02 = a11 * a22 - a12 * a12, a02 * a12 - a01 * a22, a01 * a12 - a02 * a11
    c11, c12, c22 = a00 * a22 - a02 * a02, a01 * a02 - a00 * a12, a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    v0, v1, v2 = np.moveaxis(np.asarray(v, float), -1, 0)
    return np.stack([c00 * v0 + c01 * v1 + c02 * v2, c01 * v0 + c11 * v1 + c12 * v2, c02 * v0 + c12 * v1 + c22 * v2], axis=-1) / det[..., None]


def cross_matrix(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]x`` (..., 3, 3) of vectors ``v`` (..., 3): ``[v]x @ u = v x u``."""
    v = np.asarray(v, float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return S


def R_ned_body_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """Rotation body -> NED from aerospace ZYX Euler angles (rad). Returns (3, 3) float64."""
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
    cy, sy = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def euler_from_R_ned_body(R_ned_body: np.ndarray) -> tuple[float, float, float]:
    """Aerospace ZYX Euler angles (roll, pitch, yaw) in rad from a body -> NED rotation."""
    pitch = -np.arcsin(np.clip(R_ned_body[2, 0], -1.0, 1.0))
    roll = np.arctan2(R_ned_body[2, 1], R_ned_body[2, 2])
    yaw = np.arctan2(R_ned_body[1, 0], R_ned_body[0, 0])
    return float(roll), float(pitch), float(yaw)


def body_rates_from_euler_rates(euler_rad: np.ndarray, euler_rate_rad_s: np.ndarray) -> np.ndarray:
    """Body angular rates (p, q, r) rad/s from ZYX Euler angles (rad) and their rates (rad/s)."""
    roll, pitch, _ = euler_rad
    droll, dpitch, dyaw = euler_rate_rad_s
    return np.array([
        droll - dyaw * np.sin(pitch),
        dpitch * np.cos(roll) + dyaw * np.sin(roll) * np.cos(pitch),
        -dpitch * np.sin(roll) + dyaw * np.cos(roll) * np.cos(pitch),
    ])


def euler_step_rad(euler_from_rad: np.ndarray, euler_to_rad: np.ndarray) -> np.ndarray:
    """ZYX Euler angles (rad) less the ones before them, the heading's step taken the short way round."""
    step = np.asarray(euler_to_rad, float) - np.asarray(euler_from_rad, float)
    step[2] = (step[2] + np.pi) % (2 * np.pi) - np.pi
    return step


def _rotation(euler_rad: np.ndarray) -> Rotation:
    return Rotation.from_euler("ZYX", [euler_rad[2], euler_rad[1], euler_rad[0]])


def _euler(r: Rotation) -> np.ndarray:
    yaw, pitch, roll = r.as_euler("ZYX")
    return np.array([roll, pitch, yaw])


def attitude_between(t_s: float, t0_s: float, euler0_rad: np.ndarray, t1_s: float, euler1_rad: np.ndarray) -> np.ndarray:
    """The attitude (ZYX Euler, rad) at ``t_s`` in ``[t0_s, t1_s]`` between two samples, turning at the one rate
    that carries the first into the second (spherical interpolation)."""
    r0 = _rotation(euler0_rad)
    u = float(np.clip((t_s - t0_s) / (t1_s - t0_s), 0.0, 1.0))
    return _euler(r0 * Rotation.from_rotvec(u * (r0.inv() * _rotation(euler1_rad)).as_rotvec()))


def attitude_turned(euler_rad: np.ndarray, rate_body_rad_s: np.ndarray, dt_s: float) -> np.ndarray:
    """The attitude (ZYX Euler, rad) ``dt_s`` after ``euler_rad``, turning at ``rate_body_rad_s`` (p, q, r)."""
    return _euler(_rotation(euler_rad) * Rotation.from_rotvec(np.asarray(rate_body_rad_s, float) * dt_s))


def R_body_cam_from_mount(roll_rad: float = 0.0, pitch_rad: float = 0.0, yaw_rad: float = 0.0) -> np.ndarray:
    """Camera -> body rotation for a camera turned by ZYX angles (rad, in the body frame) from straight down."""
    return R_ned_body_from_euler(roll_rad, pitch_rad, yaw_rad) @ R_BODY_CAM_DOWN


def intersect_rays_with_horizontal_plane(
    origin_ned_m: np.ndarray, dirs_ned: np.ndarray, plane_down_m: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Intersect rays ``origin + t * dir`` (t > 0) with the plane ``down = plane_down_m``.

    Parameters
    ----------
    origin_ned_m : (3,) float64, m
    dirs_ned : (N, 3) float64, any length
    plane_down_m : float, m (0 is the origin's level; up is negative)

    Returns
    -------
    points_ned_m : (N, 3) float64, m; NaN where there is no forward intersection
    valid : (N,) bool
    """
    dirs_ned = np.atleast_2d(dirs_ned)
    dz = dirs_ned[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (plane_down_m - origin_ned_m[2]) / dz
    valid = np.isfinite(t) & (t > 0)
    points = origin_ned_m[None, :] + t[:, None] * dirs_ned
    points[~valid] = np.nan
    return points, valid


@dataclass(frozen=True)
class LocalFrame:
    """A local NED frame anchored at a geodetic origin (WGS84). All conversions go through pymap3d."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float

    def to_geodetic(self, p_ned_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(N, 3) or (3,) NED metres -> (lat_deg, lon_deg, alt_amsl_m) arrays."""
        p = np.asarray(p_ned_m, dtype=float)
        return pymap3d.ned2geodetic(p[..., 0], p[..., 1], p[..., 2], self.lat_deg, self.lon_deg, self.alt_amsl_m)

    def to_ned(self, *, lat_deg, lon_deg, alt_amsl_m) -> np.ndarray:
        """Geodetic (degrees, metres AMSL) -> NED metres, shape (..., 3)."""
        n, e, d = pymap3d.geodetic2ned(lat_deg, lon_deg, alt_amsl_m, self.lat_deg, self.lon_deg, self.alt_amsl_m)
        return np.stack([np.asarray(n, float), np.asarray(e, float), np.asarray(d, float)], axis=-1)
