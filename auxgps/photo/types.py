"""Records shared by photo mapping and locating, and camera-attitude helpers.

Frames: local NED (m) about the map's origin; camera frame OpenCV (x right, y down, z forward); ``R_ned_cam``
maps camera into NED. Pixels are full-resolution pixels of the stored photo.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from auxgps.core import prior_map
from auxgps.core.camera import PinholeCamera
from auxgps.photo.features import PhotoFeatures


@dataclass(frozen=True)
class PhotoPrior:
    """What a photo's metadata says, as priors. Any of them may be None.

    gps_ne_m : (2,) north, east of the camera, m (the map's origin frame)
    height_m : camera height above the map origin (the take-off point), m
    R_ned_cam : (3, 3) attitude from the gimbal
    gps_alt_m : the GPS altitude over the map origin's level, m, for a photo without ``height_m`` (a receiver's
        altitude: metres of noise, and the ground's own level unknown, so it is no height above ground)
    """

    gps_ne_m: np.ndarray | None = None
    height_m: float | None = None
    R_ned_cam: np.ndarray | None = None
    gps_alt_m: float | None = None


@dataclass(frozen=True)
class MapPhoto:
    """One photo's input to mapping: its name, features, initial camera (intrinsics shared by ``camera_id``)."""

    name: str
    features: PhotoFeatures
    camera: PinholeCamera
    camera_id: str
    prior: PhotoPrior


@dataclass(frozen=True)
class SolvedPhoto:
    """A map photo's solved pose. ``gps_residual_ne_m`` (2,) solved minus GPS; ``yaw_vs_metadata_rad`` solved
    camera heading minus the gimbal's (None without one); ``rms_px`` the reprojection RMS of its
    ``n_observations`` kept observations (full-resolution px; None when not known, e.g. read from a map file)."""

    name: str
    p_cam_in_ned_m: np.ndarray
    R_ned_cam: np.ndarray
    n_observations: int
    gps_residual_ne_m: np.ndarray | None
    yaw_vs_metadata_rad: float | None
    rms_px: float | None = None


@dataclass(frozen=True)
class PhotoMap:
    """A map of 3D points geotagged from photos.

    p_ned_m : (M, 3) float64, m
    info_ned : (M, 3, 3) float64, information (inverse covariance) of each point's position relative to the
        others, 1/m^2; the map's common georeferencing error is ``georef_sigma_h_m``, not in here
    descriptors : (M, 128) uint8
    n_views : (M,) int
    cameras : camera id -> refined :class:`PinholeCamera`
    georef_sigma_h_m : one-sigma horizontal error of the whole map's placement on Earth, m (per axis)
    photos : the solved map photos
    messages : what happened to individual photos (left out, metadata found wrong), one line each
    source, sources : for a map of several sources (photos, orthophotos: ``auxgps locate --map A --map B``),
        each point's source (M,) as an index into ``sources`` (:class:`MapSource`, each with its own placement
        error); None and (): one source, of ``georef_sigma_h_m`` (a map being built)
    """

    p_ned_m: np.ndarray
    info_ned: np.ndarray
    descriptors: np.ndarray
    n_views: np.ndarray
    cameras: dict
    georef_sigma_h_m: float
    photos: tuple
    messages: tuple = ()
    source: np.ndarray | None = None
    sources: tuple = ()

    def __len__(self) -> int:
        return len(self.p_ned_m)

    def shared_sigma_h_m(self, idx: np.ndarray) -> float:
        """The horizontal placement error points ``idx`` share through their sources, m (one sigma; variances
        weighed by each source's share of them)."""
        if self.source is None or not len(idx):
            return self.georef_sigma_h_m
        return prior_map.shared_sigma_h_m(self.source, self.sources, idx)

    def source_name(self, idx: np.ndarray) -> str:
        """The name of the source most of points ``idx`` come from ("" for a map being built)."""
        if self.source is None or not len(idx) or not self.sources:
            return ""
        return prior_map.main_source(self.source, self.sources, idx).name


@dataclass(frozen=True)
class PhotoFix:
    """A located photo: camera position ``p_cam_in_ned_m`` (3,), attitude ``R_ned_cam`` (3, 3), position
    covariance ``cov_ned_m2`` (3, 3) (fit and map together), inlier count, reprojection RMS (px) and notes on
    where the photo's own metadata disagrees; ``map_source``: the map most of its inliers come from (a map of
    several sources), else ""."""

    p_cam_in_ned_m: np.ndarray
    R_ned_cam: np.ndarray
    cov_ned_m2: np.ndarray
    n_inliers: int
    n_matches: int
    rms_px: float
    notes: tuple = ()
    map_source: str = ""

    @property
    def accuracy_m(self) -> float:
        """Horizontal one-sigma along the worst axis, m."""
        return float(np.sqrt(np.linalg.eigvalsh(self.cov_ned_m2[:2, :2])[-1]))


@dataclass(frozen=True)
class PhotoNoFix:
    """No position for this photo, and why."""

    reason: str
    n_inliers: int = 0
    n_matches: int = 0


# --------------------------------------------------------------------------------------------------- geometry


def camera_heading_rad(R_ned_cam: np.ndarray) -> float:
    """Heading of the image's up direction (-y of the camera) projected on the ground, rad from north."""
    up = R_ned_cam @ np.array([0.0, -1.0, 0.0])
    return float(np.arctan2(up[1], up[0]))


def R_ned_cam_nadir(heading_rad: float) -> np.ndarray:
    """A camera looking straight down with the image's top towards ``heading_rad`` (from north)."""
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    # cam y (image down) points opposite the heading; cam x is cam y turned 90 degrees clockwise seen from above.
    x = np.array([-s, c, 0.0])
    y = np.array([-c, -s, 0.0])
    return np.column_stack([x, y, [0.0, 0.0, 1.0]])


def R_ned_cam_from_gimbal(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """Camera attitude from DJI gimbal angles (ZYX, NED): at zero the camera looks forward along the yaw with
    the image's top up; pitch -pi/2 looks straight down with the image's top along the yaw."""
    from auxgps.core.geometry import R_ned_body_from_euler

    R_gimbal_cam = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    return R_ned_body_from_euler(roll_rad, pitch_rad, yaw_rad) @ R_gimbal_cam


def _wrap(a: float) -> float:
    return float((a + np.pi) % (2 * np.pi) - np.pi)
