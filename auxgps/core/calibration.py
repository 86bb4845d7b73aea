"""Camera calibration from views of a chessboard: intrinsics and lens distortion with OpenCV.

Pure: images in, a :class:`CameraCalibration` out. ``auxgps camera calibrate`` reads the views (a video or a
folder of images) and writes the result as the ``camera:`` section of a pipeline configuration.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from auxgps.errors import CameraError

_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 1e-4)


@dataclass(frozen=True)
class CameraCalibration:
    """The result of a calibration.

    ``K`` (3, 3) px; ``dist`` (5,) OpenCV's k1 k2 p1 p2 k3; ``rms_px`` the reprojection error over all corners;
    ``per_view_rms_px`` (V,) each view's; ``width_px``, ``height_px`` the images'; ``n_views`` views used;
    ``rejected`` the indices of the views left out as outliers.
    """

    K: np.ndarray
    dist: np.ndarray
    rms_px: float
    per_view_rms_px: np.ndarray
    width_px: int
    height_px: int
    n_views: int
    rejected: tuple[int, ...] = ()

    def camera_section(self) -> dict:
        """The ``camera:`` section of a pipeline configuration (plain lists)."""
        return {
            "width_px": int(self.width_px),
            "height_px": int(self.height_px),
            "K": [[float(v) for v in row] for row in self.K],
            "dist": [float(v) for v in self.dist],
        }


def board_points_m(cols: int, rows: int, square_m: float) -> np.ndarray:
    """(cols * rows, 3) float32 the board's inner corners in its own plane (z = 0), m, in OpenCV's order."""
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2).astype(np.float32)
    return np.column_stack([grid * np.float32(square_m), np.zeros(len(grid), np.float32)])


def find_board(gray: np.ndarray, cols: int, rows: int) -> np.ndarray | None:
    """(cols * rows, 2) float32 the inner corners of a ``cols`` x ``rows`` chessboard in ``gray`` (H, W) uint8,
    refined to a tenth of a pixel or so; None when the whole board is not found."""
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH + cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, (cols, rows), flags=flags)
    if not found:
        return None
    corners = cv2.cornerSubPix(gray, corners, (7, 7), (-1, -1), _SUBPIX_CRITERIA)
    return corners.reshape(-1, 2)


def calibrate(views_px: list[np.ndarray], width_px: int, height_px: int, cols: int, rows: int, square_m: float, *,
              free_k3: bool = False) -> CameraCalibration:
    """Intrinsics and distortion (k1 k2 p1 p2, and k3 when ``free_k3``) from the corners of several views (each
    (cols * rows, 2) px).

    k3 stays 0 unless asked for, as OpenCV advises for all but fish-eye-like lenses: beyond the radius the views
    covered, k2 and k3 trade off freely, and a free k3 bends the image's corners by pixels (seen on simulated
    views: 1 to 2.5 px at the corners with k3 free, 0.2 px with it held). At least 4 views are needed, and 10 to
    30 from different angles and distances, covering the image's corners, give a good one; too few is a
    :class:`CameraError` naming how many there were."""
    if len(views_px) < 4:
        raise CameraError(f"calibration: the board was found in {len(views_px)} view(s); at least 4 are needed "
                          "(10 to 30 from different angles, covering the image's corners, are better)")
    first = _calibrate(views_px, width_px, height_px, cols, rows, square_m, free_k3)
    # A view that fits much worse than the others (a blurred or partly misread board) is left out once.
    limit = max(OUTLIER_FACTOR * float(np.median(first.per_view_rms_px)), OUTLIER_FLOOR_PX)
    bad = tuple(int(k) for k in np.flatnonzero(first.per_view_rms_px > limit))
    if not bad or len(views_px) - len(bad) < 4:
        return first
    kept = [v for k, v in enumerate(views_px) if k not in bad]
    cal = _calibrate(kept, width_px, height_px, cols, rows, square_m, free_k3)
    return CameraCalibration(cal.K, cal.dist, cal.rms_px, cal.per_view_rms_px, cal.width_px, cal.height_px, cal.n_views, bad)


#: A view is an outlier when its reprojection RMS is over this many times the median view's, and over the floor, px.
OUTLIER_FACTOR = 3.0
OUTLIER_FLOOR_PX = 0.3


def _calibrate(views_px, width_px, height_px, cols, rows, square_m, free_k3) -> CameraCalibration:
    obj = board_points_m(cols, rows, square_m)
    flags = 0 if free_k3 else cv2.CALIB_FIX_K3
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        [obj] * len(views_px), [v.reshape(-1, 1, 2).astype(np.float32) for v in views_px], (width_px, height_px), None, None,
        flags=flags)
    per_view = []
    for v, r, t in zip(views_px, rvecs, tvecs):
        uv, _ = cv2.projectPoints(obj, r, t, K, dist)
        per_view.append(float(np.sqrt(np.mean(np.sum((uv.reshape(-1, 2) - v) ** 2, axis=1)))))
    return CameraCalibration(np.asarray(K, float), np.asarray(dist, float).ravel()[:5], float(rms), np.array(per_view),
                             int(width_px), int(height_px), len(views_px))


def distortion_difference_px(K: np.ndarray, dist_a: np.ndarray, dist_b: np.ndarray, width_px: int, height_px: int) -> float:
    """The largest distance (px) between where two distortion models put the same ray, over a grid of the image:
    how different two calibrations' lenses are, in the unit that matters."""
    u, v = np.meshgrid(np.linspace(0, width_px - 1, 33), np.linspace(0, height_px - 1, 19))
    uv = np.column_stack([u.ravel(), v.ravel()]).reshape(-1, 1, 2)
    rays = cv2.undistortPoints(uv, K, dist_a)  # normalised coordinates under model a
    rays3 = np.concatenate([rays.reshape(-1, 2), np.ones((len(uv), 1))], axis=1)
    back, _ = cv2.projectPoints(rays3, np.zeros(3), np.zeros(3), K, dist_b)
    return float(np.max(np.linalg.norm(back.reshape(-1, 2) - uv.reshape(-1, 2), axis=1)))
