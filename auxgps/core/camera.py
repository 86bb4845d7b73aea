"""A pinhole camera with optional OpenCV distortion: pixels to rays and back."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from auxgps.errors import CameraError


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of a pinhole camera in OpenCV's convention (x right, y down, z forward).

    Attributes
    ----------
    width_px, height_px : int
    K : (3, 3) float64, px
    dist : (k,) float64, OpenCV distortion coefficients (empty for none)
    """

    width_px: int
    height_px: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=float)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise CameraError(f"K must be a finite 3x3 matrix, got shape {K.shape}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CameraError(f"focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        if self.width_px <= 0 or self.height_px <= 0:
            raise CameraError(f"resolution must be positive, got {self.width_px}x{self.height_px}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", np.asarray(self.dist, dtype=float).ravel())
        object.__setattr__(self, "_K_inv", np.linalg.inv(K))

    @classmethod
    def from_hfov(cls, width_px: int, height_px: int, hfov_rad: float) -> "PinholeCamera":
        """Square pixels, principal point at the image centre, horizontal field of view ``hfov_rad``."""
        if not 0 < hfov_rad < np.pi:
            raise CameraError(f"horizontal field of view must be in (0, pi) rad, got {hfov_rad}")
        f = (width_px / 2.0) / np.tan(hfov_rad / 2.0)
        K = np.array([[f, 0.0, width_px / 2.0], [0.0, f, height_px / 2.0], [0.0, 0.0, 1.0]])
        return cls(width_px, height_px, K)

    @property
    def has_distortion(self) -> bool:
        return self.dist.size > 0 and bool(np.any(self.dist != 0))

    @property
    def focal_px(self) -> float:
        """Mean focal length, px."""
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    def pixels_to_normalized(self, uv_px: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) undistorted normalized image coordinates (x/z, y/z)."""
        uv = np.asarray(uv_px, dtype=float).reshape(-1, 2)
        if self.has_distortion:
            # OpenCV's default 5 iterations leave pixels of error at the corners of a strongly distorted lens.
            criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
            return cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K, self.dist, None, None, None, criteria).reshape(-1, 2)
        Ki = self._K_inv  # type: ignore[attr-defined]
        return np.column_stack([(uv[:, 0] - self.K[0, 2]) * Ki[0, 0], (uv[:, 1] - self.K[1, 2]) * Ki[1, 1]])

    def pixels_to_rays_cam(self, uv_px: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 3) unit rays in the camera frame."""
        xy = self.pixels_to_normalized(uv_px)
        rays = np.column_stack([xy, np.ones(len(xy))])
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def project_cam(self, p_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) points in the camera frame -> (N, 2) pixels and (N,) bool 'in front of the camera'.

        Points behind the camera get NaN pixels.
        """
        p = np.atleast_2d(np.asarray(p_cam, dtype=float))
        z = p[:, 2]
        in_front = z > 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = p[:, :2] / z[:, None]
        if self.has_distortion:
            uv = cv2.projectPoints(
                np.column_stack([xy, np.ones(len(xy))]).reshape(-1, 1, 3),
                np.zeros(3),
                np.zeros(3),
                self.K,
                self.dist,
            )[0].reshape(-1, 2)
        else:
            uv = xy * np.array([self.K[0, 0], self.K[1, 1]]) + self.K[:2, 2]
            if self.K[0, 1] != 0.0:
                uv[:, 0] += xy[:, 1] * self.K[0, 1]
        uv[~in_front] = np.nan
        return uv, in_front

    def in_image(self, uv_px: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """(N,) bool: pixel inside the image, at least ``margin_px`` from its border."""
        uv = np.atleast_2d(uv_px)
        return (
            (uv[:, 0] >= margin_px)
            & (uv[:, 0] <= self.width_px - 1 - margin_px)
            & (uv[:, 1] >= margin_px)
            & (uv[:, 1] <= self.height_px - 1 - margin_px)
        )


@dataclass(frozen=True)
class CameraPose:
    """Where a camera is and how it is turned: ``p_cam_in_ned_m`` (3,) m and ``R_ned_cam`` (3, 3)."""

    p_cam_in_ned_m: np.ndarray
    R_ned_cam: np.ndarray

    def ned_to_cam(self, p_ned_m: np.ndarray) -> np.ndarray:
        """(N, 3) NED points -> (N, 3) camera-frame points."""
        return (np.atleast_2d(p_ned_m) - self.p_cam_in_ned_m) @ self.R_ned_cam

    def project(self, camera: PinholeCamera, p_ned_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) NED points -> (N, 2) pixels and (N,) in-front mask."""
        return camera.project_cam(self.ned_to_cam(p_ned_m))

    def rays_ned(self, camera: PinholeCamera, uv_px: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 3) unit rays in NED."""
        return camera.pixels_to_rays_cam(uv_px) @ self.R_ned_cam.T

    def box_in_view(self, camera: PinholeCamera, max_depth_m: float, margin_px: float = 0.0) -> tuple[tuple[float, float], tuple[float, float]] | None:
        """North and east ranges (m) of a box holding every point at most ``max_depth_m`` below the camera that
        projects into the image (widened by ``margin_px``); None when part of the image looks at or above the
        horizon (no bound).

        Through the image's border, 8 points a side (a distorted lens bends it): at that depth, the rays through
        the border enclose those through the image, and a point less deep lies between the camera and that
        section, so the box holds the section and the camera.
        """
        if not max_depth_m > 0.0:
            return None
        xs = np.linspace(-margin_px, camera.width_px - 1 + margin_px, 8)
        ys = np.linspace(-margin_px, camera.height_px - 1 + margin_px, 8)
        border = np.vstack([np.column_stack([xs, np.full(8, ys[0])]), np.column_stack([xs, np.full(8, ys[-1])]),
                            np.column_stack([np.full(8, xs[0]), ys]), np.column_stack([np.full(8, xs[-1]), ys])])
        rays = self.rays_ned(camera, border)
        if np.any(rays[:, 2] <= 1e-6):
            return None
        ne = np.vstack([self.p_cam_in_ned_m[:2], self.p_cam_in_ned_m[:2] + rays[:, :2] * (max_depth_m / rays[:, 2])[:, None]])
        return (float(ne[:, 0].min()), float(ne[:, 0].max())), (float(ne[:, 1].min()), float(ne[:, 1].max()))


def camera_from_config(cfg) -> PinholeCamera:
    """Build a :class:`PinholeCamera` from a :class:`auxgps.config.CameraConfig`."""
    if cfg.K is not None:
        return PinholeCamera(cfg.width_px, cfg.height_px, np.array(cfg.K, float), np.array(cfg.dist, float))
    cam = PinholeCamera.from_hfov(cfg.width_px, cfg.height_px, np.deg2rad(cfg.hfov_deg))
    return PinholeCamera(cam.width_px, cam.height_px, cam.K, np.array(cfg.dist, float))
