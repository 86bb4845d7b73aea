"""Geotagging while GPS is good: features of each frame become, or refine, landmarks of the map.

For every frame: project the landmarks that should be in view with the GPS pose and full attitude, match each
feature to the nearest-looking landmark among those projecting close to it (guided matching), fuse each match as
a ray observation, and add the unmatched features as new landmarks placed on the ground plane with a loose
height. Rays from different places then fix each landmark's height, so a cube's top corner lands on that corner.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from auxgps.core.camera import PinholeCamera
from auxgps.core.features import Features, hamming, pairs_within
from auxgps.core.geometry import intersect_rays_with_horizontal_plane
from auxgps.core.landmarks import LandmarkMap
from auxgps.core.nav import NavSample
from auxgps.core.stopwatch import null_stopwatch


@dataclass(frozen=True)
class MappingResult:
    """What one frame did to the map. ``landmark_ids`` (N,) gives, per feature, the landmark it fed (-1: none)."""

    n_features: int
    n_matched: int
    n_added: int
    landmark_ids: np.ndarray


def ray_information(rays_ned: np.ndarray, sigma_perp_m: np.ndarray) -> np.ndarray:
    """(M, 3, 3) information of ray observations: (I - d d^T) / sigma_perp^2, 1/m^2."""
    P = np.eye(3)[None] - rays_ned[:, :, None] * rays_ned[:, None, :]
    return P / (sigma_perp_m**2)[:, None, None]


def ray_mahalanobis2(L: np.ndarray, cov_L: np.ndarray, c: np.ndarray, d: np.ndarray, sigma_perp_m: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distance (2 dof) of landmarks ``L`` (M, 3) with covariance ``cov_L`` (M, 3, 3) from
    rays ``c + t d`` (unit ``d`` (M, 3)) with isotropic cross-ray noise ``sigma_perp_m`` (M,)."""
    helper = np.where(np.abs(d[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(d, e1)
    E = np.stack([e1, e2], axis=1)  # (M, 2, 3)
    r = np.einsum("mij,mj->mi", E, L - c)
    S = np.einsum("mij,mjk,mlk->mil", E, cov_L, E) + (sigma_perp_m**2)[:, None, None] * np.eye(2)[None]
    return np.einsum("mi,mij,mj->m", r, np.linalg.inv(S), r)


class Mapper:
    """Builds a :class:`LandmarkMap` from frames with known GPS poses."""

    def __init__(self, cfg, camera: PinholeCamera, R_body_cam: np.ndarray, landmarks: LandmarkMap, stopwatch=None) -> None:
        self.cfg = cfg
        self.stopwatch = stopwatch if stopwatch is not None else null_stopwatch  # instrumentation a benchmark passes in; times nothing here
        self.camera = camera
        self.R_body_cam = R_body_cam
        self.map = landmarks
        noise = cfg.noise
        self._sigma_att_rad = np.deg2rad(noise.attitude_deg)
        self._sigma_pos_m = noise.gps_horizontal_m
        half_diag = np.hypot(camera.width_px, camera.height_px) / 2.0 / camera.focal_px
        self._footprint_tan = half_diag + 0.5  # room for some tilt

    def process(self, features: Features, nav: NavSample) -> MappingResult:
        n = len(features)
        ids_out = np.full(n, -1, int)
        if n == 0:
            return MappingResult(0, 0, 0, ids_out)
        cfg = self.cfg.mapping
        pose = nav.camera_pose(self.R_body_cam)
        c = pose.p_cam_in_ned_m
        rays = pose.rays_ned(self.camera, features.uv_px)
        # A keypoint found on a coarser pyramid level is located less precisely.
        sigma_px = self.cfg.noise.pixel_px * self.cfg.detector.scale_factor ** features.octave / features.scale

        # Candidates: landmarks whose projection falls in the image.
        reach = max(nav.alt_above_origin_m, 1.0) * self._footprint_tan + 5.0
        with self.stopwatch("matching"):
            cand = self.map.ids_in_box((c[0] - reach, c[0] + reach), (c[1] - reach, c[1] + reach))
            cand = cand[self.map.source[cand] == 0]  # a prior map's landmarks are used to position, never refined
        matched_feat = matched_lm = np.zeros(0, int)
        if len(cand):
            uv_lm, in_front = pose.project(self.camera, self.map.p_ned_m[cand].astype(float))
            keep = in_front & self.camera.in_image(np.nan_to_num(uv_lm, nan=-1e6), -cfg.edge_margin_px)
            cand, uv_lm = cand[keep], uv_lm[keep]
            self.map.count_visible(cand[self.camera.in_image(uv_lm)], nav.t_s)
            if len(cand):
                with self.stopwatch("matching"):
                    matched_feat, matched_lm, chi2 = self._guided_match(features, cand, uv_lm, rays, c, sigma_px)

        # Fuse matches as ray observations.
        if len(matched_feat):
            d = rays[matched_feat]
            rng_m = np.linalg.norm(self.map.p_ned_m[matched_lm].astype(float) - c, axis=1)
            A = ray_information(d, self._sigma_perp(rng_m, sigma_px[matched_feat]))
            b = np.einsum("nij,j->ni", A, c)
            self.map.observe(matched_lm, A, b, features.descriptors[matched_feat], d[:, 2].astype(np.float16), chi2,
                             rng_m / features.scale, nav.t_s)
            ids_out[matched_feat] = matched_lm

        # Unmatched features become new landmarks on the ground plane, their height free within a few metres
        # (initial_height_sigma_m) until views from elsewhere fix it.
        new = np.setdiff1d(np.arange(n), matched_feat)
        p0, valid = intersect_rays_with_horizontal_plane(c, rays[new], 0.0)
        new, p0 = new[valid], p0[valid]
        n_added = 0
        if len(new):
            rng_m = np.linalg.norm(p0 - c, axis=1)
            A = ray_information(rays[new], self._sigma_perp(rng_m, sigma_px[new]))
            A[:, 2, 2] += 1.0 / cfg.initial_height_sigma_m**2
            ids_out[new] = self.map.add(features.descriptors[new], p0, A, rays[new, 2].astype(np.float16), rng_m / features.scale,
                                        nav.t_s)
            n_added = len(new)
        return MappingResult(n, len(matched_feat), n_added, ids_out)

    def _sigma_perp(self, range_m: np.ndarray, sigma_px: np.ndarray) -> np.ndarray:
        """One-sigma offset of a ray at ``range_m`` across its direction: pixel, attitude and GPS noise, m."""
        sigma_angle = np.hypot(sigma_px / self.camera.focal_px, self._sigma_att_rad)
        return np.hypot(range_m * sigma_angle, self._sigma_pos_m)

    def _guided_match(self, features, cand, uv_lm, rays, c, sigma_px) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One-to-one matches (feature indices, landmark ids, squared Mahalanobis innovations).

        GPS and attitude errors shift every landmark's predicted pixel alike, by a few pixels; corners of a
        small cube are only a few more apart. So the shift common to the frame is measured first, from the
        established landmarks, and each landmark is then paired only with a feature close to its shifted
        prediction (within what its own uncertainty allows), with agreeing descriptors, and inside the
        chi-square gate.
        """
        cfg = self.cfg.mapping
        none = np.zeros(0, int), np.zeros(0, int), np.zeros(0)
        fi, ci = pairs_within(features.uv_px, uv_lm, cfg.match_radius_px)
        if len(fi) == 0:
            return none
        offsets = features.uv_px[fi] - uv_lm[ci]  # (P, 2) px
        ham = hamming(features.descriptors[fi], self.map.descriptors[cand[ci]])
        ok = ham <= cfg.max_hamming
        fi, ci, ham, offsets = fi[ok], ci[ok], ham[ok], offsets[ok]
        if len(fi) == 0:
            return none
        lm = cand[ci]
        cov = self.map.covariance(lm)
        shift = self._common_shift(offsets, self.map.n_seen[lm] >= 3)
        # Each landmark's own pixel uncertainty: its largest position sigma seen from this range.
        L = self.map.p_ned_m[lm].astype(float)
        range_m = np.linalg.norm(L - c, axis=1)
        sigma_lm_px = np.sqrt(np.linalg.eigvalsh(cov)[:, -1]) / range_m * self.camera.focal_px
        radius = np.minimum(3.0 * np.hypot(sigma_px[fi] * 2.0, sigma_lm_px), cfg.match_radius_px)
        d_shifted = np.linalg.norm(offsets - shift, axis=1)
        m2 = ray_mahalanobis2(L, cov, c, rays[fi], self._sigma_perp(range_m, sigma_px[fi]))
        ok = (d_shifted <= radius) & (m2 <= cfg.gate_chi2)
        fi, ci, ham, m2, d_shifted = fi[ok], ci[ok], ham[ok], m2[ok], d_shifted[ok]
        # Greedy one-to-one assignment, nearest first, then best descriptor.
        order = np.lexsort((ham, d_shifted))
        used_f, used_c = set(), set()
        chosen = []
        for k in order:
            f, cc = int(fi[k]), int(ci[k])
            if f in used_f or cc in used_c:
                continue
            used_f.add(f)
            used_c.add(cc)
            chosen.append(k)
        if not chosen:
            return none
        chosen = np.array(chosen, int)
        return fi[chosen], cand[ci[chosen]], m2[chosen]

    @staticmethod
    def _common_shift(offsets_px: np.ndarray, established: np.ndarray, agree_px: float = 2.0) -> np.ndarray:
        """The pixel shift most established candidate pairs agree on (their mean within ``agree_px``), or zero."""
        off = offsets_px[established]
        if len(off) < 3:
            return np.zeros(2)
        votes = cKDTree(off).query_ball_point(off, agree_px, return_length=True)  # pairs within agree_px, itself included
        best = int(np.argmax(votes))
        if votes[best] < 3:
            return np.zeros(2)
        return off[np.linalg.norm(off - off[best], axis=1) <= agree_px].mean(axis=0)
