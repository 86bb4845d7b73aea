"""Photos located against a photo map alone (:class:`PhotoLocator`).

A photo's features are matched to the map's points (FLANN, ratio test), the full camera pose is found by
PnP inside RANSAC and refined by robust least squares. Its metadata (attitude, height) is a prior that is
checked, never trusted: the fix reports where it disagrees. The reported covariance joins the fit's
(scaled by its own residuals) and the map's georeferencing uncertainty. A photo with too little support
(another place, no overlap, a blank or corrupt image) gets a reason and no fix.

Frames: local NED (m) about the map's origin; camera frame OpenCV (x right, y down, z forward); ``R_ned_cam``
maps camera into NED. Pixels are full-resolution pixels of the stored photo.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from auxgps.core.camera import PinholeCamera
from auxgps.photo.features import PhotoFeatures, _flann
from auxgps.photo.types import PhotoFix, PhotoMap, PhotoNoFix, PhotoPrior, _wrap, camera_heading_rad


class PhotoLocator:
    """Locates photos against a :class:`PhotoMap`. Build once per map; :meth:`locate` per photo."""

    def __init__(self, photo_map: PhotoMap, cfg) -> None:
        self.map = photo_map
        self.cfg = cfg
        self._flann = _flann()
        self._flann.add([photo_map.descriptors.astype(np.float32)])
        self._flann.train()
        p = photo_map.p_ned_m
        self._box = (p[:, :2].min(axis=0), p[:, :2].max(axis=0))
        with np.errstate(invalid="ignore"):
            cov = np.linalg.inv(photo_map.info_ned + np.eye(3)[None] * 1e-6)
        self._point_var_m2 = np.maximum(np.trace(cov, axis1=1, axis2=2) / 3.0, 0.0)

    def locate(self, features: PhotoFeatures, camera: PinholeCamera, prior: PhotoPrior | None = None) -> PhotoFix | PhotoNoFix:
        """Locate one photo from its features alone; ``prior`` (attitude, height: never GPS) is only checked."""
        cfg = self.cfg
        if len(features) < cfg.min_inliers:
            return PhotoNoFix(f"only {len(features)} features in the photo (blank, blurred or tiny)")
        best = np.full(len(self.map), -1)
        best_d = np.full(len(self.map), np.inf)
        for m in self._flann.knnMatch(features.descriptors.astype(np.float32), k=2):
            if len(m) == 2 and m[0].distance < cfg.ratio * m[1].distance and m[0].distance < best_d[m[0].trainIdx]:
                best[m[0].trainIdx] = m[0].queryIdx
                best_d[m[0].trainIdx] = m[0].distance
        lm = np.flatnonzero(best >= 0)
        fi = best[lm]
        n_matches = len(lm)
        if n_matches < cfg.min_inliers:
            return PhotoNoFix(f"only {n_matches} features match the map (not a place it covers)", 0, n_matches)
        X = self.map.p_ned_m[lm]
        uv = features.uv_px[fi]
        scale = np.maximum(features.size_px[fi] / 8.0, 1.0)
        thr = cfg.ransac_px * float(np.median(scale))
        ok, rvec, tvec, inl = cv2.solvePnPRansac(X, uv, camera.K, camera.dist if camera.has_distortion else None,
                                                 iterationsCount=cfg.ransac_iterations, reprojectionError=thr,
                                                 confidence=0.9999, flags=cv2.SOLVEPNP_EPNP)
        if not ok or inl is None or len(inl) < cfg.min_inliers:
            return PhotoNoFix(f"{0 if inl is None else len(inl)} of {n_matches} matches agree on a pose (need {cfg.min_inliers})", 0 if inl is None else len(inl), n_matches)
        R_cam_ned = cv2.Rodrigues(rvec)[0]
        R = R_cam_ned.T
        C = -R @ tvec.ravel()
        sigma_px = cfg.pixel_sigma_px * scale
        inl = inl.ravel()
        # Refine on the inliers, re-select them with the refined pose and the map points' own uncertainty (seen
        # from this camera it adds to the pixel noise), and again.
        for _ in range(3):
            depth = np.maximum((X - C) @ R[:, 2], 1e-3)
            sig = np.sqrt(sigma_px**2 + camera.focal_px**2 * self._point_var_m2[lm] / depth**2)
            R, C, _ = _refine_pose(camera, X[inl], uv[inl], sig[inl], R, C)
            err = _reproject(camera, X, uv, R, C)
            inl = np.flatnonzero(err <= 3.0 * sig)
            if len(inl) < cfg.min_inliers:
                return PhotoNoFix(f"{len(inl)} of {n_matches} matches agree on a pose (need {cfg.min_inliers})", len(inl), n_matches)
        inl = np.flatnonzero(err <= 3.0 * sig)
        n_inl = len(inl)
        share = n_inl / n_matches
        if n_inl < cfg.min_inliers or share < cfg.min_inlier_share:
            return PhotoNoFix(f"{n_inl} of {n_matches} matches agree on a pose (need {cfg.min_inliers} and "
                              f"{cfg.min_inlier_share:.0%})", n_inl, n_matches)
        cov_C, rms_px = _pose_covariance(camera, X[inl], uv[inl], sig[inl], R, C)
        uv_in = uv[inl]
        spread = np.ptp(uv_in[:, 0]) * np.ptp(uv_in[:, 1]) / (camera.width_px * camera.height_px)
        if spread < cfg.min_inlier_spread:
            return PhotoNoFix(f"the {n_inl} agreeing matches cover only {spread:.1%} of the photo", n_inl, n_matches)
        if not np.median(X[inl, 2]) > C[2]:
            return PhotoNoFix("the pose puts the camera below the ground it sees", n_inl, n_matches)
        lo, hi = self._box
        margin = max(cfg.max_outside_map_m, 0.0)
        if np.any(C[:2] < lo - margin) or np.any(C[:2] > hi + margin):
            return PhotoNoFix(f"the pose is {margin:.0f} m or more outside the map", n_inl, n_matches)
        cov = cov_C.copy()
        cov[:2, :2] += np.eye(2) * self.map.shared_sigma_h_m(lm[inl]) ** 2
        notes = _check_prior(prior, R, C, cfg)
        fix = PhotoFix(C, R, cov, n_inl, n_matches, rms_px, tuple(notes), self.map.source_name(lm[inl]))
        if fix.accuracy_m > cfg.max_accuracy_m:
            return PhotoNoFix(f"too uncertain: {fix.accuracy_m:.1f} m one sigma", n_inl, n_matches)
        return fix


def _reproject(camera, X, uv, R, C) -> np.ndarray:
    p_cam = (X - C) @ R
    pred, _ = camera.project_cam(p_cam)
    return np.linalg.norm(np.nan_to_num(pred, nan=1e9) - uv, axis=1)


def _refine_pose(camera, X, uv, sig, R, C):
    """Robust least squares of the pose (small rotation about R, and the centre) over these matches."""

    def fun(x):
        Rx = R @ Rotation.from_rotvec(x[:3]).as_matrix()
        p_cam = (X - x[3:]) @ Rx
        pred, _ = camera.project_cam(p_cam)
        return (np.nan_to_num(pred, nan=1e6) - uv).ravel() / np.repeat(sig, 2)

    res = least_squares(fun, np.concatenate([np.zeros(3), C]), loss="huber", f_scale=1.5, method="trf", x_scale="jac")
    Rn = R @ Rotation.from_rotvec(res.x[:3]).as_matrix()
    Cn = res.x[3:]
    return Rn, Cn, _reproject(camera, X, uv, Rn, Cn)


def _pose_covariance(camera, X, uv, sig, R, C) -> tuple[np.ndarray, float]:
    """Covariance of the camera centre (3, 3) m^2 from the Jacobian at the solution, scaled up by the
    residuals when they are larger than ``sig`` says; and the reprojection RMS (px)."""

    def fun(x):
        Rx = R @ Rotation.from_rotvec(x[:3]).as_matrix()
        pred, _ = camera.project_cam((X - x[3:]) @ Rx)
        return (pred - uv).ravel() / np.repeat(sig, 2)

    x0 = np.concatenate([np.zeros(3), C])
    r0 = fun(x0)
    J = np.empty((len(r0), 6))
    for k in range(6):
        h = 1e-6 if k < 3 else 1e-4
        dx = np.zeros(6)
        dx[k] = h
        J[:, k] = (fun(x0 + dx) - fun(x0 - dx)) / (2 * h)
    dof = max(len(r0) - 6, 1)
    s2 = max(1.0, float(r0 @ r0) / dof)
    cov = np.linalg.inv(J.T @ J) * s2
    rms_px = float(np.sqrt(np.mean(np.sum(((r0.reshape(-1, 2)) * sig[:, None]) ** 2, axis=1))))
    return cov[3:, 3:], rms_px


def _check_prior(prior: PhotoPrior | None, R: np.ndarray, C: np.ndarray, cfg) -> list[str]:
    """Where the photo's own metadata disagrees with the pose the map gives."""
    notes = []
    if prior is None:
        return notes
    if prior.R_ned_cam is not None:
        d = _wrap(camera_heading_rad(R) - camera_heading_rad(prior.R_ned_cam))
        if abs(d) > np.deg2rad(cfg.max_heading_disagreement_deg):
            notes.append(f"pixels turned {np.degrees(d):+.0f} deg from the metadata's camera heading")
        tilt = np.degrees(np.arccos(np.clip(R[:, 2] @ prior.R_ned_cam[:, 2], -1, 1)))
        if tilt > cfg.max_heading_disagreement_deg:
            notes.append(f"optical axis {tilt:.0f} deg from the metadata's")
    if prior.height_m is not None:
        dh = -C[2] - prior.height_m
        if abs(dh) > max(2.0, 0.1 * abs(prior.height_m)):
            notes.append(f"height {-C[2]:.1f} m, metadata says {prior.height_m:.1f} m")
    return notes
