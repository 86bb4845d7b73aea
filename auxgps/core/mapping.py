"""Geotagging while GPS is good: features of each frame become, or refine, landmarks of the map.

For every frame: project the landmarks that should be in view with the GPS pose and full attitude, match each
feature to the nearest-looking landmark among those projecting close to it (guided matching), fuse each match as
a ray observation, and add the unmatched features as new landmarks placed on the ground plane with a loose
height. Rays from different places then fix each landmark's height, so a cube's top corner lands on that corner.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from auxgps.core.camera import CameraPose, PinholeCamera
from auxgps.core.features import Features, greedy_one_to_one, hamming_pairs, pair_order, pairs_within, pairs_within_radii, spots
from auxgps.core.geometry import intersect_rays_with_horizontal_plane
from auxgps.core.landmarks import LandmarkMap
from auxgps.core.retag import HeadingView
from auxgps.core.nav import NavSample
from auxgps.core.stopwatch import null_stopwatch


@dataclass(frozen=True)
class MappingResult:
    """What one frame did to the map. ``landmark_ids`` (N,) gives, per feature, the landmark it fed (-1: none)."""

    n_features: int
    n_matched: int
    n_added: int
    landmark_ids: np.ndarray


def ray_information(rays_ned: np.ndarray, sigma_perp_m: np.ndarray, sigma_turn_m: np.ndarray | None = None) -> np.ndarray:
    """(M, 3, 3) information of ray observations, 1/m^2: (I - d d^T) / sigma_perp^2, and with ``sigma_turn_m``
    less along ``u``, the horizontal direction across the ray, where a heading error moves the ray's far end:
    ``sigma_perp^2 + sigma_turn^2`` there (a turn about the vertical through the camera moves a point at
    horizontal distance ``r`` by the turn times ``r``, across; none at nadir)."""
    P = np.eye(3)[None] - rays_ned[:, :, None] * rays_ned[:, None, :]
    inv_s2 = 1.0 / sigma_perp_m**2
    A = P * inv_s2[:, None, None]
    if sigma_turn_m is not None:
        h = np.hypot(rays_ned[:, 0], rays_ned[:, 1])
        u = np.column_stack([-rays_ned[:, 1], rays_ned[:, 0], np.zeros(len(h))]) / np.maximum(h, 1e-12)[:, None]
        less = inv_s2 - 1.0 / (sigma_perp_m**2 + sigma_turn_m**2)
        A -= less[:, None, None] * u[:, :, None] * u[:, None, :]
    return A


def ray_bias_terms(rays_ned: np.ndarray, range_m: np.ndarray, sigma_angle_rad: np.ndarray, sigma_perp_m: np.ndarray) -> np.ndarray:
    """(M, 3) 1/m: each ray observation's term of :attr:`LandmarkMap.ray_bias_sum`, ``2 s^2 t d / sigma_perp^2``
    (``s`` its angular sigma per axis, ``t`` its range, ``d`` its unit direction)."""
    return (2.0 * np.square(sigma_angle_rad) * range_m / np.square(sigma_perp_m))[:, None] * rays_ned


def ray_mahalanobis2(L: np.ndarray, cov_L: np.ndarray, c: np.ndarray, d: np.ndarray, sigma_perp_m: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distance (2 dof) of landmarks ``L`` (M, 3) with covariance ``cov_L`` (M, 3, 3) from
    rays ``c + t d`` (unit ``d`` (M, 3)) with isotropic cross-ray noise ``sigma_perp_m`` (M,).

    In the plane across each ray, spanned by ``e1 = d x h / |d x h|`` (``h`` down, or north for a ray near
    vertical) and ``e2 = d x e1``; written out per component, as this runs on every candidate pair of a frame."""
    dx, dy, dz = np.asarray(d, float).T
    steep = np.abs(dz) >= 0.9
    # d x (0, 0, 1) = (dy, -dx, 0); d x (1, 0, 0) = (0, dz, -dy)
    e1 = np.where(steep[:, None], np.column_stack([np.zeros_like(dx), dz, -dy]), np.column_stack([dy, -dx, np.zeros_like(dx)]))
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.column_stack([dy * e1[:, 2] - dz * e1[:, 1], dz * e1[:, 0] - dx * e1[:, 2], dx * e1[:, 1] - dy * e1[:, 0]])
    v = L - c
    r1, r2 = np.einsum("mi,mi->m", e1, v), np.einsum("mi,mi->m", e2, v)
    Ce1, Ce2 = np.einsum("mij,mj->mi", cov_L, e1), np.einsum("mij,mj->mi", cov_L, e2)
    s2 = sigma_perp_m**2
    s11 = np.einsum("mi,mi->m", e1, Ce1) + s2
    s22 = np.einsum("mi,mi->m", e2, Ce2) + s2
    s12 = np.einsum("mi,mi->m", e1, Ce2)
    return (r1 * r1 * s22 - 2.0 * r1 * r2 * s12 + r2 * r2 * s11) / (s11 * s22 - s12 * s12)


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
        self._sigma_heading_rad = np.deg2rad(noise.heading_deg)
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
        sigma_att_rad = self._sigma_att_rad if nav.attitude_sigma_rad is None else nav.attitude_sigma_rad
        sigma_heading_rad = self._sigma_heading_rad if nav.heading_sigma_rad is None else nav.heading_sigma_rad
        # A keypoint found on a coarser pyramid level is located less precisely.
        sigma_px = self.cfg.noise.pixel_px * self.cfg.detector.scale_factor ** features.octave / features.scale

        # Candidates: landmarks whose projection falls in the image (near it), from the box the image sees down to
        # the deepest landmark of the map; a camera that sees the horizon takes the square its footprint's reach
        # spans, with some tilt.
        with self.stopwatch("matching"):
            box = pose.box_in_view(self.camera, self.map.deepest_down_m() - c[2], cfg.edge_margin_px) if len(self.map) else None
            if box is None:
                reach = max(nav.alt_above_origin_m, 1.0) * self._footprint_tan + 5.0
                box = (c[0] - reach, c[0] + reach), (c[1] - reach, c[1] + reach)
            cand = self.map.ids_in_box(*box)
            cand = cand[self.map.source[cand] == 0]  # a prior map's landmarks are used to position, never refined
        matched_feat = matched_lm = np.zeros(0, int)
        if len(cand):
            uv_lm, in_front = pose.project(self.camera, self.map.p_ned_m[cand].astype(float))
            keep = in_front & self.camera.in_image(np.nan_to_num(uv_lm, nan=-1e6), -cfg.edge_margin_px)
            cand, uv_lm = cand[keep], uv_lm[keep]
            self.map.count_visible(cand[self.camera.in_image(uv_lm)], nav.t_s)
            if len(cand):
                with self.stopwatch("matching"):
                    matched_feat, matched_lm, chi2 = self._guided_match(features, cand, uv_lm, rays, pose, sigma_px, sigma_att_rad)

        # What the views are geotagged with, for turning them again when the heading is better known.
        view = HeadingView(nav.heading.offset_rad, c.copy(), nav.heading.memory) if nav.heading is not None else None
        # Fuse matches as ray observations.
        if len(matched_feat):
            d = rays[matched_feat]
            rng_m = np.linalg.norm(self.map.p_ned_m[matched_lm].astype(float) - c, axis=1)
            sigma_angle = self._sigma_angle(sigma_px[matched_feat], sigma_att_rad)
            sigma_perp = self._sigma_perp(rng_m, sigma_angle)
            A = ray_information(d, sigma_perp, sigma_heading_rad * rng_m * np.hypot(d[:, 0], d[:, 1]))
            b = np.einsum("nij,j->ni", A, c)
            self.map.observe(matched_lm, A, b, features.descriptors[matched_feat], d[:, 2].astype(np.float16), chi2,
                             rng_m / features.scale, nav.t_s, view,
                             ray_bias_terms(d, rng_m, sigma_angle, sigma_perp))
            ids_out[matched_feat] = matched_lm

        # Unmatched features become new landmarks on the ground plane, their height free within a few metres
        # (initial_height_sigma_m) until views from elsewhere fix it. One per spot of the image (features within
        # positioning.same_point_px, a corner found on two pyramid levels), and none on a spot that fed a landmark:
        # a second landmark of one corner lets a frame that finds it twice count it twice.
        unmatched = np.ones(n, bool)
        unmatched[matched_feat] = False
        new = np.flatnonzero(unmatched)
        radius_px = self.cfg.positioning.same_point_px / features.scale
        if len(new) and radius_px > 0:
            spot = spots(cKDTree(features.uv_px, balanced_tree=False, compact_nodes=False), radius_px)
            fed = np.zeros(n, bool)
            fed[spot[matched_feat]] = True
            new = new[~fed[spot[new]]]
            new = new[np.sort(np.unique(spot[new], return_index=True)[1])]
        p0, valid = intersect_rays_with_horizontal_plane(c, rays[new], 0.0)
        new, p0 = new[valid], p0[valid]
        n_added = 0
        if len(new):
            rng_m = np.linalg.norm(p0 - c, axis=1)
            sigma_angle = self._sigma_angle(sigma_px[new], sigma_att_rad)
            sigma_perp = self._sigma_perp(rng_m, sigma_angle)
            A = ray_information(rays[new], sigma_perp, sigma_heading_rad * rng_m * np.hypot(rays[new, 0], rays[new, 1]))
            A[:, 2, 2] += 1.0 / cfg.initial_height_sigma_m**2
            ids_out[new] = self.map.add(features.descriptors[new], p0, A, rays[new, 2].astype(np.float16), rng_m / features.scale,
                                        nav.t_s, view, ray_bias_terms(rays[new], rng_m, sigma_angle, sigma_perp))
            n_added = len(new)
        return MappingResult(n, len(matched_feat), n_added, ids_out)

    def _sigma_angle(self, sigma_px: np.ndarray, sigma_att_rad: float) -> np.ndarray:
        """One-sigma error of a ray's direction, per axis: pixel and attitude noise, rad (the GPS's offset of the
        camera moves the ray without turning it)."""
        return np.hypot(sigma_px / self.camera.focal_px, sigma_att_rad)

    def _sigma_perp(self, range_m: np.ndarray, sigma_angle_rad: np.ndarray) -> np.ndarray:
        """One-sigma offset of a ray at ``range_m`` across its direction: its direction's error there and GPS noise, m."""
        return np.hypot(range_m * sigma_angle_rad, self._sigma_pos_m)

    #: The frame's common shift is measured on at most this many established landmarks, spread over the candidates.
    SHIFT_SAMPLE = 256

    def _guided_match(self, features: Features, cand: np.ndarray, uv_lm: np.ndarray, rays: np.ndarray, pose: CameraPose, sigma_px: np.ndarray,
                      sigma_att_rad: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One-to-one matches (feature indices, landmark ids, squared Mahalanobis innovations).

        GPS and attitude errors shift every landmark's predicted pixel alike, by a few pixels; corners of a
        small cube are only a few more apart. So the shift common to the frame is measured first, on established
        landmarks, and each landmark is then paired only with a feature close to its shifted prediction (within
        3 sigma of its covariance carried through the projection, and the feature's pixel noise), with agreeing
        descriptors, and inside the chi-square gate.
        """
        cfg = self.cfg.mapping
        c = pose.p_cam_in_ned_m
        none = np.zeros(0, int), np.zeros(0, int), np.zeros(0)
        shift = self._frame_shift(features, cand, uv_lm)
        cov = self.map.covariance(cand)
        L = self.map.p_ned_m[cand].astype(float)
        sigma_lm_px = self._pixel_sigma_px(L, cov, pose)
        reach_px = np.minimum(3.0 * np.hypot(2.0 * sigma_px.max(), sigma_lm_px), cfg.match_radius_px)
        fi, ci = pairs_within_radii(features.uv_px, uv_lm + shift, reach_px)
        ham = hamming_pairs(features.descriptors, fi, self.map.descriptors[cand], ci)
        ok = np.flatnonzero(ham <= cfg.max_hamming)
        # In order of feature, then landmark, which breaks the ties below (put in order only those kept: cheaper)
        ok = ok[pair_order(fi[ok], ci[ok], len(features), len(cand))]
        fi, ci, ham = fi[ok], ci[ok], ham[ok]
        if len(fi) == 0:
            return none
        radius = np.minimum(3.0 * np.hypot(sigma_px[fi] * 2.0, sigma_lm_px[ci]), cfg.match_radius_px)
        d_shifted = np.linalg.norm(features.uv_px[fi] - uv_lm[ci] - shift, axis=1)
        range_m = np.linalg.norm(L[ci] - c, axis=1)
        m2 = ray_mahalanobis2(L[ci], cov[ci], c, rays[fi], self._sigma_perp(range_m, self._sigma_angle(sigma_px[fi], sigma_att_rad)))
        ok = (d_shifted <= radius) & (m2 <= cfg.gate_chi2)
        fi, ci, ham, m2, d_shifted = fi[ok], ci[ok], ham[ok], m2[ok], d_shifted[ok]
        # Greedy one-to-one assignment, nearest first, then best descriptor.
        order = np.lexsort((ham, d_shifted))
        chosen = order[greedy_one_to_one(fi[order], ci[order])]
        if len(chosen) == 0:
            return none
        return fi[chosen], cand[ci[chosen]], m2[chosen]

    def _frame_shift(self, features: Features, cand: np.ndarray, uv_lm: np.ndarray) -> np.ndarray:
        """The pixel shift common to the frame (:meth:`_common_shift`), from the pairs of established landmarks (seen
        three times or more) with agreeing descriptors within ``match_radius_px``: at most :attr:`SHIFT_SAMPLE` of
        them, evenly spread over the candidates (a mode of a few thousand offsets is found as well from a sample,
        and the pairs of all cost most of a frame's matching)."""
        cfg = self.cfg.mapping
        est = np.flatnonzero(self.map.n_seen[cand] >= 3)
        if len(est) > self.SHIFT_SAMPLE:
            est = est[np.linspace(0, len(est) - 1, self.SHIFT_SAMPLE).astype(int)]
        fi, si = pairs_within(features.uv_px, uv_lm[est], cfg.match_radius_px, ordered=False)
        ok = np.flatnonzero(hamming_pairs(features.descriptors, fi, self.map.descriptors[cand[est]], si) <= cfg.max_hamming)
        ok = ok[pair_order(fi[ok], si[ok], len(features), len(est))]  # in order of feature, then landmark: the ties
        offsets = features.uv_px[fi[ok]] - uv_lm[est[si[ok]]]
        return self._common_shift(offsets)

    def _pixel_sigma_px(self, L_ned_m: np.ndarray, cov_ned_m2: np.ndarray, pose: CameraPose) -> np.ndarray:
        """(M,) the largest one-sigma of each landmark's predicted pixel, px: its covariance carried through the
        projection (a landmark loose along the ray it was first seen on moves in the image only as far as the
        camera has moved since; its largest sigma over its range would count all of it)."""
        p = pose.ned_to_cam(L_ned_m)
        C = pose.R_ned_cam.T @ cov_ned_m2 @ pose.R_ned_cam  # (M, 3, 3) in the camera frame
        a, b = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
        # J = (f / z) [[1, 0, -a], [0, 1, -b]]
        s11 = C[:, 0, 0] - 2.0 * a * C[:, 0, 2] + a * a * C[:, 2, 2]
        s22 = C[:, 1, 1] - 2.0 * b * C[:, 1, 2] + b * b * C[:, 2, 2]
        s12 = C[:, 0, 1] - a * C[:, 1, 2] - b * C[:, 0, 2] + a * b * C[:, 2, 2]
        half_sum, half_diff = 0.5 * (s11 + s22), 0.5 * (s11 - s22)
        largest = half_sum + np.sqrt(half_diff * half_diff + s12 * s12)
        return np.sqrt(np.maximum(largest, 0.0)) * self.camera.focal_px / p[:, 2]

    @staticmethod
    def _common_shift(offsets_px: np.ndarray, agree_px: float = 2.0, exact_votes: int = 64) -> np.ndarray:
        """The pixel shift most candidate pairs agree on (the mean of the offsets within ``agree_px``
        of the offset with the most such neighbours, itself included), or zero when fewer than 3 agree.

        Counting every offset's neighbours costs the cluster's size squared, and most of a frame's pairs are in
        that cluster; so the counts are first read off a histogram (bins ``agree_px / 4`` wide, summed over a
        disk of ``agree_px``), and only the ``exact_votes`` offsets it counts highest are counted exactly. The
        first offset of the most neighbours among those is the one an exact count of every offset finds unless
        the histogram's rounding ranks it below ``exact_votes`` others, which takes a broad cluster of many
        near-equal counts, whose shifts differ by a fraction of a pixel.
        """
        off = np.asarray(offsets_px, float)
        if len(off) < 3:
            return np.zeros(2)
        bin_px, r_bins = agree_px / 4.0, 4
        lo = off.min(axis=0) - (r_bins + 1) * bin_px
        idx = np.floor((off - lo) / bin_px).astype(np.int64)
        h, w = idx.max(axis=0) + r_bins + 2
        hist = np.bincount(idx[:, 0] * w + idx[:, 1], minlength=h * w).reshape(h, w).astype(np.float32)
        approx = cv2.filter2D(hist, -1, _disk(r_bins), borderType=cv2.BORDER_CONSTANT)[idx[:, 0], idx[:, 1]]
        cand = np.arange(len(off)) if len(off) <= exact_votes else np.sort(np.argpartition(-approx, exact_votes - 1)[:exact_votes])
        # Only offsets inside the candidates' box widened by agree_px can be within agree_px of one of them
        c = off[cand]
        lo_c, hi_c = c.min(axis=0) - agree_px, c.max(axis=0) + agree_px
        near = off[(off[:, 0] >= lo_c[0]) & (off[:, 0] <= hi_c[0]) & (off[:, 1] >= lo_c[1]) & (off[:, 1] <= hi_c[1])]
        dn = c[:, 0, None] - near[:, 0]
        de = c[:, 1, None] - near[:, 1]
        dn *= dn
        de *= de
        dn += de
        votes = (dn <= agree_px * agree_px).sum(axis=1)
        best = int(cand[np.argmax(votes)])
        if votes.max() < 3:
            return np.zeros(2)
        return off[np.linalg.norm(off - off[best], axis=1) <= agree_px].mean(axis=0)


def _disk(r: int) -> np.ndarray:
    """A (2r+1, 2r+1) float32 kernel of ones within ``r`` of its centre."""
    y, x = np.mgrid[-r : r + 1, -r : r + 1]
    return (x * x + y * y <= r * r).astype(np.float32)
