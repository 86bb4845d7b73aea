"""Positioning without GPS: where is the camera, given this frame's features and the landmark map?

With the attitude from the autopilot and the barometric height, one feature-landmark correspondence fixes the
camera's ground position. Every correspondence (each feature to its k nearest descriptors) is thus a
hypothesis; the hypothesis that the most distinct features agree with wins, is refined by weighted least squares
over its inliers (3D position, height softly tied to the barometer), and is checked for ambiguity: when a
clearly different position is nearly as well supported (a corner matched to the wrong one of identical cubes),
there is no fix. A single wrong match cannot move the fix, because it cannot outvote the rest.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from auxgps.core.camera import CameraPose, PinholeCamera
from auxgps.core.features import Features, greedy_one_to_one, hamming_pairs, pairs_within, spots
from auxgps.core.geometry import cross_matrix
from auxgps.core.landmarks import LandmarkMap
from auxgps.core.stopwatch import null_stopwatch
from auxgps.core.tracking import Followed


@dataclass(frozen=True)
class PositionPrior:
    """Where the vehicle is believed to be: ``p_ned_m`` (3,) and a horizontal one-sigma ``sigma_h_m``, the same on
    every axis (the search is a circle; the filter gives its worst axis)."""

    p_ned_m: np.ndarray
    sigma_h_m: float


@dataclass(frozen=True)
class Fix:
    """A visual position fix of the camera at ``t_s``: ``p_ned_m`` (3,), ``cov_ned_m2`` (3, 3).

    ``heading_turn_rad``: the turn about the vertical (positive
    clockwise seen from above) the frame's rays needed to fit them, as the image alone says it, with its variance
    ``heading_turn_var_rad2`` (None: the image does not tell, the attitude's prior decided it).

    ``prior_share``: the share of its inliers that are prior-map landmarks (an orthophoto's), whose placement
    error they all share: not in ``cov_ned_m2`` (the filter carries it as a state); ``map_source``: the source
    most of its inliers come from ("flight", or the prior map's name)."""

    t_s: float
    p_ned_m: np.ndarray
    cov_ned_m2: np.ndarray
    n_inliers: int
    n_correspondences: int
    n_features: int
    heading_turn_rad: float | None = None
    heading_turn_var_rad2: float | None = None
    prior_share: float = 0.0
    map_source: str = "flight"
    t_mapped_s: float = np.nan  # the median time its inliers were first geotagged (NaN: not known, a loaded map's)
    followed: bool = False  # located from an earlier fix's inliers carried here by optical flow, not a detection
    inliers: Followed | None = None  # its inliers' pixels and landmarks, for the next frame to follow

    @property
    def sigma_h_rms_m(self) -> float:
        """Horizontal one-sigma as the root of the mean of the north and east variances, m (what the fixes log
        shows; the filter's output reports its worst axis, :attr:`FusedEstimate.sigma_h_worst_m`)."""
        return float(np.sqrt(0.5 * (self.cov_ned_m2[0, 0] + self.cov_ned_m2[1, 1])))


@dataclass(frozen=True)
class NoFix:
    """No position from this frame, and why. ``rivals_apart_m``: an ambiguous frame's two readings were this far
    apart (None: not ambiguous)."""

    t_s: float
    reason: str
    n_inliers: int = 0
    n_correspondences: int = 0
    n_features: int = 0
    rivals_apart_m: float | None = None


LocateResult = Fix | NoFix

#: Correspondence-seed distances measured at a time (600 kB of float64, as 256 correspondences by 300 seeds): they
#: stay in a core's cache.
_CONSENSUS_BLOCK_PAIRS = 256 * 300
#: A reading this far below the best in log-likelihood weighs e^-20 (2e-9) of it in the fix's spread: nothing.
_NEGLIGIBLE_LL = 20.0


def _ransac_seeds(inlier_share: float, confidence: float) -> float:
    """Seeds drawn at random needed to draw one of a set holding ``inlier_share`` of all with probability
    ``confidence``: ``log(1 - confidence) / log(1 - inlier_share)`` (inf when certainty is asked for, 1 when
    every one is in the set)."""
    if inlier_share >= 1.0:
        return 1.0
    if confidence >= 1.0:
        return np.inf
    return float(np.log1p(-confidence) / np.log1p(-inlier_share))


def _prefix_spread_order(n: int) -> np.ndarray:
    """A permutation of ``range(n)`` whose every prefix is spread over the whole range: the indices in the order
    of their bit-reversed binary (van der Corput), so that the first 2^j of them are every (n / 2^j)-th."""
    bits = max(int(n - 1).bit_length(), 1)
    idx = np.arange(n)
    rev = np.zeros(n, np.int64)
    for b in range(bits):
        rev |= ((idx >> b) & 1) << (bits - 1 - b)
    return np.argsort(rev, kind="stable")


def prior_m2(p_ned_m: np.ndarray, cov_ned_m2: np.ndarray, prior: PositionPrior | None, floor_m: float) -> float:
    """Squared distance of a position ``p_ned_m`` (covariance ``cov_ned_m2``) from the prior, in units of their
    combined horizontal sigma (0 without a prior). ``floor_m`` is added in quadrature: a filter fed a few biased
    fixes can believe itself to a few centimetres while it is decimetres off, and must not out-vote what the image
    shows."""
    if prior is None:
        return 0.0
    d2 = float(np.sum((p_ned_m[:2] - prior.p_ned_m[:2]) ** 2))
    return d2 / (prior.sigma_h_m**2 + float(np.trace(cov_ned_m2[:2, :2])) / 2.0 + floor_m**2)


@dataclass(frozen=True)
class _Correspondences:
    """Feature-landmark pairs of one frame and what each implies: ``L`` (K, 3) the landmark, NED m; ``d`` (K, 3)
    the feature's unit ray, NED; ``hyp`` (K, 2) the camera's north/east if the pair is right, ``tau`` (K,) how
    far apart two agreeing hypotheses may be, m."""

    feat_i: np.ndarray
    lm_id: np.ndarray
    L: np.ndarray
    d: np.ndarray
    hyp: np.ndarray
    tau: np.ndarray


@dataclass(frozen=True)
class _View:
    """What a frame's readings are checked against: its features and a k-d tree of their pixels, attitude,
    height, and its candidate landmarks turned into camera axes once per frame, ``cand_in_cam_axes_m`` (M, 3) m,
    ``R_cam_ned @ p_ned``: a reading at ``p`` sees them at ``cand_in_cam_axes_m - R_cam_ned @ p``."""

    features: Features
    feature_tree: cKDTree
    R_ned_cam: np.ndarray
    alt_above_origin_m: float
    cand_in_cam_axes_m: np.ndarray
    prior_info: np.ndarray  # (6, 6) what the refinement knows beforehand (height, attitude), 1/m^2 and 1/rad^2
    point_id: np.ndarray  # (N,) per feature: features on one spot of the image (one corner found twice) share it


@dataclass(frozen=True)
class _Fit:
    """What the refinement makes of a hypothesis: position ``p`` (3,) and covariance ``cov`` (3, 3), NED m; the
    inliers it kept ``inl`` (K,); ``attitude_m2``, the squared Mahalanobis distance of its attitude correction
    from the telemetry's; and ``fit_quality``, its inliers each weighed by how well it fits (MSAC: ``1 -
    (error / inlier_px)^2``, so a corner on its prediction counts 1, one at the tolerance 0)."""

    p: np.ndarray
    cov: np.ndarray
    inl: np.ndarray
    attitude_m2: float
    fit_quality: float
    turn_rad: float = 0.0  # the attitude correction's turn about the vertical, rad
    turn_var_rad2: float = np.inf


@dataclass(frozen=True)
class _Reading:
    """One candidate position of a frame: refined position, covariance, inlier mask, score."""

    p: np.ndarray
    cov: np.ndarray
    inl: np.ndarray
    score: float  # its fit quality times ``explained``
    explained: float  # the share of the landmarks it puts well inside the image that have a feature there
    attitude_m2: float  # squared Mahalanobis distance of its attitude correction from the telemetry's
    turn_rad: float = 0.0  # its attitude correction's turn about the vertical, rad, and that turn's variance
    turn_var_rad2: float = np.inf


def _spread_by_rivals(best: _Reading, readings: list[_Reading], ll: np.ndarray) -> _Reading:
    """``best`` with its horizontal covariance grown by where the frame's other readings put the camera: their
    second moment about it, each weighed by its probability among the readings (``exp(ll)``, normalised). A
    rival a few units below the best adds next to nothing; one nearly as probable adds most of its squared
    distance, whatever its inlier count (a small cube seen obliquely, its corners read at the wrong height by
    four inliers against the right reading's three)."""
    w = np.exp(ll - ll.max())
    w /= w.sum()
    d = np.array([r.p[:2] - best.p[:2] for r in readings])
    cov = best.cov.copy()
    cov[:2, :2] += np.einsum("k,ki,kj->ij", w, d, d)
    return replace(best, cov=cov)


class Localiser:
    """Locates frames against a :class:`LandmarkMap`."""

    def __init__(self, cfg, camera: PinholeCamera, R_body_cam: np.ndarray, landmarks: LandmarkMap, stopwatch=None) -> None:
        self.cfg = cfg
        self.camera = camera
        self.R_body_cam = R_body_cam
        self.map = landmarks
        self.stopwatch = stopwatch if stopwatch is not None else null_stopwatch  # instrumentation a benchmark passes in; times nothing here
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=False)
        half_diag = np.hypot(camera.width_px, camera.height_px) / 2.0 / camera.focal_px
        self._footprint_tan = half_diag + 0.3
        noise = cfg.noise
        # What the refinement knows of its unknowns (position, attitude correction) beforehand: the barometer's
        # height and the telemetry's attitude, information 1/m^2 and 1/rad^2.
        # The order seeds are taken from their even spread in (every prefix spread too): it depends on max_seeds
        # alone, so it is made once, not per frame.
        self._seed_order = _prefix_spread_order(cfg.positioning.max_seeds)
        self._refine_prior_info = np.diag(
            [0.0, 0.0, 1.0 / noise.altitude_m**2]
            + [1.0 / np.deg2rad(noise.attitude_deg) ** 2] * 2
            + [1.0 / np.deg2rad(noise.heading_deg) ** 2]
        )

    def locate(self, features: Features, t_s: float, R_ned_body: np.ndarray, alt_above_origin_m: float, prior: PositionPrior | None,
               candidate_ids: np.ndarray | None = None, tilt_sigma_rad: float | None = None,
               heading_sigma_rad: float | None = None) -> LocateResult:
        """Locate one frame. ``R_ned_body`` and ``alt_above_origin_m`` come from the autopilot (attitude, barometer);
        ``tilt_sigma_rad``, ``heading_sigma_rad``: how far its attitude may be off, one sigma (None:
        ``noise.attitude_deg``, ``noise.heading_deg``).

        ``candidate_ids``: what :meth:`candidates` gives for this ``alt_above_origin_m`` and ``prior`` on the map as it is,
        when the caller has it already (it asked for the frame's :meth:`detection_scale`); else it is looked up.
        """
        cfg = self.cfg.positioning
        n_feat = len(features)
        if n_feat < cfg.min_inliers:
            return NoFix(t_s, f"{n_feat} features, fewer than {cfg.min_inliers}", n_features=n_feat)
        if not (np.all(np.isfinite(R_ned_body)) and np.isfinite(alt_above_origin_m)):
            return NoFix(t_s, "attitude or altitude is not finite", n_features=n_feat)

        cand = self.candidates(alt_above_origin_m, prior) if candidate_ids is None else candidate_ids
        if len(cand) < cfg.min_inliers:
            return NoFix(t_s, f"{len(cand)} mapped landmarks near the predicted position", n_features=n_feat)

        R_ned_cam = R_ned_body @ self.R_body_cam
        inlier_px = cfg.inlier_px / features.scale  # a frame detected shrunk locates its corners more coarsely
        rays = self.camera.pixels_to_rays_cam(features.uv_px) @ R_ned_cam.T  # (N, 3) unit, NED
        # The search reaches 3 sigma of the prior, and never less than min_search_radius_m: a small object's
        # corners look alike, and both the right and a shifted reading of them must compete on full support.
        search_m = None
        radius_px = np.inf
        if prior is not None:
            search_m = max(3.0 * prior.sigma_h_m, cfg.min_search_radius_m)
            radius_px = search_m * self.camera.focal_px / max(alt_above_origin_m, 1.0) + inlier_px
        # Tracking (a prior tight enough to tell apart objects, and the symmetric readings of a large one):
        # candidates are the landmarks predicted near each feature. Acquisition (no prior, or a loose one after
        # a long stretch without fixes): candidates come from descriptors alone, and the evidence must be
        # stronger.
        tracking = prior is not None and 3.0 * prior.sigma_h_m <= cfg.max_tracking_search_m
        p_cand_ned_m = self.map.p_ned_m[cand].astype(float)  # (M, 3) m: for the guided match and the readings
        if tracking:
            pose = CameraPose(np.array([prior.p_ned_m[0], prior.p_ned_m[1], -alt_above_origin_m]), R_ned_cam)
            with self.stopwatch("matching"):
                feat_i, lm_id = self._match_guided(features, cand, p_cand_ned_m, pose, radius_px)
            min_inliers, margin = cfg.min_inliers, cfg.ambiguity_margin
        else:
            with self.stopwatch("matching"):
                feat_i, lm_id = self._match(features, cand, cfg.k_best_acquire)
            min_inliers, margin = cfg.min_inliers_acquire, cfg.ambiguity_margin_acquire
        if len(feat_i) < cfg.min_inliers:
            return NoFix(t_s, f"{len(feat_i)} descriptor matches", n_correspondences=len(feat_i), n_features=n_feat)

        # One hypothesis per correspondence: the camera's north/east if this feature is this landmark.
        L = self.map.p_ned_m[lm_id].astype(float)
        d = rays[feat_i]
        cam_down = -alt_above_origin_m
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (L[:, 2] - cam_down) / d[:, 2]
        ok = np.isfinite(t) & (t > 0.5)
        feat_i, lm_id, L, d, t = feat_i[ok], lm_id[ok], L[ok], d[ok], t[ok]
        hyp = L[:, :2] - t[:, None] * d[:, :2]
        if prior is not None:
            gate = search_m + inlier_px / self.camera.focal_px * alt_above_origin_m
            inside = np.linalg.norm(hyp - prior.p_ned_m[:2], axis=1) <= gate
            feat_i, lm_id, L, d, t, hyp = feat_i[inside], lm_id[inside], L[inside], d[inside], t[inside], hyp[inside]
        n_corr = len(feat_i)
        if np.count_nonzero(np.bincount(feat_i, minlength=n_feat)) < cfg.min_inliers:  # features with a correspondence
            return NoFix(t_s, f"{n_corr} correspondences inside the search area", n_correspondences=n_corr, n_features=n_feat)

        corr = _Correspondences(feat_i, lm_id, L, d, hyp, self._agreement_radius_m(d, t, inlier_px))
        seeds, support = self._consensus(corr)
        best_support = int(support.max())
        if best_support < min_inliers:
            return NoFix(t_s, f"best hypothesis has {best_support} supporting features", best_support, n_corr, n_feat)
        # Unbalanced: half the build time of a frame's features, the same nearest distances.
        feature_tree = cKDTree(features.uv_px, balanced_tree=False, compact_nodes=False)
        prior_info = self._prior_info(tilt_sigma_rad, heading_sigma_rad)
        view = _View(features, feature_tree, R_ned_cam, alt_above_origin_m, p_cand_ned_m @ R_ned_cam, prior_info,
                     spots(feature_tree, cfg.same_point_px / features.scale))
        verdict = self._choose(corr, view, prior, seeds, support, min_inliers, margin)
        if isinstance(verdict, tuple):  # ambiguous: the reason and how far apart the rivals are
            return NoFix(t_s, verdict[0], best_support, n_corr, n_feat, rivals_apart_m=verdict[1])
        if isinstance(verdict, str):
            return NoFix(t_s, verdict, best_support, n_corr, n_feat)
        n_inl = int(verdict.inl.sum())
        if not tracking and verdict.explained < cfg.min_explained_acquire:
            return NoFix(t_s, f"acquisition: {verdict.explained:.0%} of the landmarks expected in view are seen", n_inl, n_corr, n_feat)
        return self._fix(t_s, verdict, corr, features.uv_px[corr.feat_i], prior_info, n_corr, n_feat, features.scale, None)

    def locate_followed(self, followed: Followed, t_s: float, R_ned_body: np.ndarray, alt_above_origin_m: float,
                        tilt_sigma_rad: float | None = None, heading_sigma_rad: float | None = None,
                        min_kept: float = 0.5) -> LocateResult:
        """Locate a frame from an earlier fix's inliers, carried into it by optical flow (:mod:`auxgps.core.tracking`).

        They were one reading's inliers, so there is one hypothesis: the median of the pairs'. It is refined as a
        full frame's readings are (:meth:`_refine`: the same model, the same inlier tolerance), over the pairs
        within their agreement radius of it, and is a fix when at least ``min_kept`` of the pairs and
        ``min_inliers`` stay inliers; else the flow lost them and the frame needs a full look.
        """
        cfg = self.cfg.positioning
        n = len(followed.lm_id)
        if n < cfg.min_inliers:
            return NoFix(t_s, f"{n} landmarks followed, fewer than {cfg.min_inliers}", n_features=n)
        if not (np.all(np.isfinite(R_ned_body)) and np.isfinite(alt_above_origin_m)):
            return NoFix(t_s, "attitude or altitude is not finite", n_features=n)
        R_ned_cam = R_ned_body @ self.R_body_cam
        inlier_px = cfg.inlier_px / followed.scale
        d = self.camera.pixels_to_rays_cam(followed.uv_px) @ R_ned_cam.T
        L = self.map.p_ned_m[followed.lm_id].astype(float)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (L[:, 2] + alt_above_origin_m) / d[:, 2]
        ok = np.isfinite(t) & (t > 0.5)
        d, L, t = d[ok], L[ok], t[ok]
        lm_id, uv = followed.lm_id[ok], followed.uv_px[ok]
        hyp = L[:, :2] - t[:, None] * d[:, :2]
        corr = _Correspondences(np.arange(len(lm_id)), lm_id, L, d, hyp, self._agreement_radius_m(d, t, inlier_px))
        p0 = np.array([*np.median(hyp, axis=0), -alt_above_origin_m]) if len(hyp) else np.full(3, np.nan)
        members = np.linalg.norm(hyp - p0[:2], axis=1) <= corr.tau
        prior_info = self._prior_info(tilt_sigma_rad, heading_sigma_rad)
        fit = self._refine(p0, corr, members, alt_above_origin_m, 1.0 / followed.scale, prior_info)
        n_inl = int(fit.inl.sum())
        if n_inl < max(cfg.min_inliers, min_kept * n) or not (np.all(np.isfinite(fit.p)) and np.all(np.isfinite(fit.cov))):
            return NoFix(t_s, f"{n_inl} of {n} followed landmarks stay inliers", n_inl, n, n)
        return self._fix(t_s, fit, corr, uv, prior_info, n, n, followed.scale, followed.from_full_s)

    # -- steps -------------------------------------------------------------------------------------------------

    def _agreement_radius_m(self, d: np.ndarray, t: np.ndarray, inlier_px: float) -> np.ndarray:
        """How far apart (m) two agreeing hypotheses may be, per correspondence of ray ``d`` (K, 3) at ``t`` (K,)
        along it: the pixel tolerance at its range, plus what a barometer error does to an off-nadir ray."""
        range_m = t * np.linalg.norm(d, axis=1)
        tan_off = np.linalg.norm(d[:, :2], axis=1) / np.abs(d[:, 2])
        return inlier_px / self.camera.focal_px * range_m + 2.0 * self.cfg.noise.altitude_m * tan_off

    def _prior_info(self, tilt_sigma_rad: float | None, heading_sigma_rad: float | None) -> np.ndarray:
        """What the refinement knows of its unknowns beforehand, with the frame's own attitude sigmas where given."""
        prior_info = self._refine_prior_info
        if tilt_sigma_rad is not None or heading_sigma_rad is not None:
            prior_info = prior_info.copy()
            if tilt_sigma_rad is not None:
                prior_info[3, 3] = prior_info[4, 4] = 1.0 / max(tilt_sigma_rad, 1e-6) ** 2
            if heading_sigma_rad is not None:
                prior_info[5, 5] = 1.0 / max(heading_sigma_rad, 1e-6) ** 2
        return prior_info

    def _fix(self, t_s: float, reading, corr: _Correspondences, uv_px: np.ndarray, prior_info: np.ndarray, n_corr: int,
             n_feat: int, scale: float, from_full_s: float | None) -> Fix:
        """The :class:`Fix` of a reading (or a fit) over ``corr``, whose pixels are ``uv_px`` (K, 2);
        ``from_full_s``: when the full frame its pairs were followed from was taken (None: it is a full one)."""
        inl = reading.inl
        # The turn as the image alone says it: the posterior's information less the prior's (scalar marginals).
        turn = turn_var = None
        info_image = 1.0 / reading.turn_var_rad2 - prior_info[5, 5] if reading.turn_var_rad2 > 0 else 0.0
        if info_image > 0.1 * prior_info[5, 5]:
            turn_var = 1.0 / info_image
            turn = reading.turn_rad / reading.turn_var_rad2 * turn_var
        ids = corr.lm_id[inl]
        prior_share = float(np.mean(self.map.source[ids] != 0)) if len(ids) else 0.0
        t_first_s = self.map.t_first_s[ids]
        t_first_s = t_first_s[np.isfinite(t_first_s)]
        t_mapped_s = float(np.median(t_first_s)) if len(t_first_s) else np.nan
        return Fix(t_s, reading.p, reading.cov, int(inl.sum()), n_corr, n_feat, turn, turn_var, prior_share, self.map.source_name(ids),
                   t_mapped_s, from_full_s is not None, Followed(uv_px[inl], ids, scale, t_s if from_full_s is None else from_full_s))

    def _choose(self, corr: _Correspondences, view: _View, prior, seeds, support, min_inliers: int, margin: float):
        """The most probable reading of the frame, or a reason (str) why there is none; an ambiguous frame's reason
        comes with how far apart its rivals are (a tuple).

        The best-supported hypotheses that are distinct (more than their agreement radius apart, and from the
        refined positions of the readings taken) are refined into readings, up to ``max_readings``. Each reading
        gets a log-likelihood: its inliers, each weighed by how well it fits (see :meth:`_refine`), times the
        share of the landmarks it puts inside the image that do have a feature there (a wrong position predicts
        corners on bare ground), less half the squared Mahalanobis distances of the attitude correction it needs
        and of its position from the prior. A corner matched to the wrong one of identical cubes, or a small cube
        read off by its height (its bottom corners taken for its top ones), is a reading of its own, and the image
        and the prediction together must choose. Readings with fewer than ``min_inliers`` inliers compete too,
        though they cannot be a fix: when one of them is the most probable, the frame has none (a few corners of a
        small cube fitting the prior within a pixel outweigh six that need a tilt and a shift to fit at all). A
        second distinct reading with enough inliers within ``margin`` of the best makes the frame ambiguous.
        Otherwise the best is the fix, its covariance grown by the other readings' spread about it, each weighed
        by its probability (:func:`_spread_by_rivals`): a reading nearly as probable but with too few inliers to
        be a fix, or too close to call the frame ambiguous, still says how far off the fix may be.
        """
        cfg = self.cfg.positioning
        floor = max(2.0, cfg.rival_min_share * float(support.max()))
        readings: list[_Reading] = []
        lls: list[float] = []
        seed_hyp, seed_tau = corr.hyp[seeds], corr.tau[seeds]
        covered = np.zeros(len(seeds), bool)  # a hypothesis of a reading already taken
        by_support = np.argsort(-support, kind="stable")
        next_at = 0
        while len(readings) < cfg.max_readings:
            # The next seed in falling support that no reading has covered, found in one step: a reading covers
            # most of the seeds, and a loop over them costs more than the test.
            uncovered = np.flatnonzero(~covered[by_support[next_at:]])
            if len(uncovered) == 0:
                break
            s = by_support[next_at + uncovered[0]]
            next_at += int(uncovered[0]) + 1
            if support[s] < floor:
                break
            # A reading's log-likelihood is at most its support (inliers <= support, explained share <= 1), and
            # seeds come in falling support: once one cannot come within the margin of the best, none can.
            if lls and support[s] < max(lls) - margin:
                break
            covered |= np.linalg.norm(seed_hyp - seed_hyp[s], axis=1) <= seed_tau
            members = self._members(corr, view, seeds[s])
            # Its log-likelihood is also at most its members one to one (inliers are some of them): a seed that
            # cannot come within _NEGLIGIBLE_LL of the best read so far is not refined. It could neither make
            # the frame ambiguous nor weigh in its spread. On Seneca these are most of the rivals: a feature's
            # other landmark (mapped twice), a cluster's edge, read 0.05 to 0.6 m from the best and some 100 below.
            if lls and np.count_nonzero(members) < max(lls) - max(margin, _NEGLIGIBLE_LL):
                continue
            r = self._reading(corr, view, seeds[s], members)
            # The seeds whose hypotheses the reading's refined position agrees with are its own as well: their
            # readings would refine to the same place (on the bench they did, a few cm off, at a reading each).
            covered |= np.linalg.norm(seed_hyp - r.p[:2], axis=1) <= seed_tau  # NaN positions cover none
            if int(r.inl.sum()) >= 2 and np.all(np.isfinite(r.p)) and np.all(np.isfinite(r.cov)):
                readings.append(r)
                lls.append(r.score - 0.5 * r.attitude_m2 - 0.5 * prior_m2(r.p, r.cov, prior, cfg.prior_floor_m))
        n_inl = np.array([int(r.inl.sum()) for r in readings], int)
        if not np.any(n_inl >= min_inliers):
            return f"no hypothesis keeps {min_inliers} inliers after refinement"
        ll = np.array(lls)
        order = np.argsort(-ll, kind="stable")
        best = readings[order[0]]
        if n_inl[order[0]] < min_inliers:
            # Too few inliers to be a fix, yet more probable than every reading with enough: those are wrong.
            return f"the most probable reading keeps {n_inl[order[0]]} inliers, fewer than {min_inliers}"
        radius = 2.0 * float(np.median(corr.tau))
        for k in order[1:]:
            if n_inl[k] < min_inliers:
                continue
            apart_m = float(np.linalg.norm(readings[k].p[:2] - best.p[:2]))
            if apart_m > radius and ll[k] >= ll[order[0]] - margin:
                return f"ambiguous: a reading {apart_m:.2f} m away is within {ll[order[0]] - ll[k]:.1f} of the best", apart_m
        return _spread_by_rivals(best, readings, ll)

    def _members(self, corr: _Correspondences, view: _View, seed: int) -> np.ndarray:
        """Boolean (K,): the correspondences whose hypothesis is within their ``tau`` of that of ``seed`` (as
        :meth:`_consensus` counts them), one per spot of the image and one per landmark (:meth:`_one_to_one`)."""
        dist2 = cdist(corr.hyp, corr.hyp[seed][None], "sqeuclidean")[:, 0]
        return self._one_to_one(dist2 <= np.square(corr.tau), view.point_id[corr.feat_i], corr.lm_id, dist2)

    def _reading(self, corr: _Correspondences, view: _View, seed: int, inl: np.ndarray) -> _Reading:
        """Refine the hypothesis of correspondence ``seed`` over its members ``inl`` (one to one, see
        :meth:`_one_to_one`) and score it."""
        fit = self._refine(np.array([*corr.hyp[seed], -view.alt_above_origin_m]), corr, inl, view.alt_above_origin_m, 1.0 / view.features.scale,
                           view.prior_info)
        explained = self._explained_share(fit.p, view)
        return _Reading(fit.p, fit.cov, fit.inl, fit.fit_quality * explained, explained, fit.attitude_m2, fit.turn_rad, fit.turn_var_rad2)

    def detection_scale(self, alt_above_origin_m: float, prior: PositionPrior | None, candidate_ids: np.ndarray | None = None) -> float:
        """The image scale (at most 1) at which to detect a frame so that its descriptors see the landmarks in
        view at about the range the map's descriptors saw them from: a frame from half the mapping range is
        detected at half size. 1 without a prior, without landmarks near it with a known range, or when the
        frame is not much closer than the map's views (the detector's own pyramid covers ``scale_factor``).
        ``candidate_ids``: :meth:`candidates` for this ``alt_above_origin_m`` and ``prior``, when the caller has them (to pass
        on to :meth:`locate`, so that a frame looks them up once)."""
        if prior is None or not np.isfinite(alt_above_origin_m):
            return 1.0
        cand = self.candidates(alt_above_origin_m, prior) if candidate_ids is None else candidate_ids
        range_map_m = self.map.descriptor_range_m[cand].astype(float)
        known = np.isfinite(range_map_m) & (range_map_m > 0)
        if not np.any(known):
            return 1.0
        camera_ned_m = np.array([prior.p_ned_m[0], prior.p_ned_m[1], -alt_above_origin_m])
        range_now_m = np.linalg.norm(self.map.p_ned_m[cand[known]] - camera_ned_m, axis=1)
        scale = float(np.median(range_now_m / range_map_m[known]))
        if scale * self.cfg.detector.scale_factor >= 1.0:
            return 1.0
        return float(np.clip(scale, self.cfg.positioning.min_detection_scale, 1.0))

    def candidates(self, alt_above_origin_m: float, prior: PositionPrior | None, first_seen_before_s: float | None = None) -> np.ndarray:
        """Ids of the usable landmarks within reach of the prior's footprint (all usable ones without a prior);
        with ``first_seen_before_s``, only those first geotagged before then (a mapping frame's self-check)."""
        cfg = self.cfg.positioning
        m = self.cfg.mapping
        if prior is None:
            ids = np.arange(len(self.map))
        else:
            reach = max(alt_above_origin_m, 1.0) * self._footprint_tan + 3.0 * prior.sigma_h_m + cfg.footprint_margin_m
            n, e = prior.p_ned_m[0], prior.p_ned_m[1]
            ids = self.map.ids_in_box((n - reach, n + reach), (e - reach, e + reach))
        if first_seen_before_s is not None:
            ids = ids[self.map.t_first_s[ids] < first_seen_before_s]
        ids = ids[self.map.usable(ids, m.min_seen, m.max_mean_chi2, m.min_found_ratio)]
        # Where the flight has mapped the ground itself, its own landmarks take over from a prior map's: theirs
        # are placed by this flight's GPS to centimetres, a prior map's share its orthophoto's metre-level offset.
        prior = self.map.source[ids] != 0
        if np.any(prior) and np.count_nonzero(~prior) >= cfg.own_landmarks_take_over:
            ids = ids[~prior]
        return ids

    def _match(self, features: Features, cand: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Each feature to every landmark within the Hamming limit, the ``k`` nearest at most.

        Not just the nearest few: with identical objects in the map, every copy must get its correspondences,
        or the copy that happens to win the descriptor lottery wins the position too.
        """
        cfg = self.cfg.positioning
        rows = self._matcher.radiusMatch(features.descriptors, self.map.descriptors[cand], float(cfg.max_hamming) + 0.5)
        fi, ci = [], []
        for row in rows:
            for m in row[:k]:
                fi.append(m.queryIdx)
                ci.append(m.trainIdx)
        return np.array(fi, int), cand[np.array(ci, int)] if ci else np.zeros(0, int)

    def _explained_share(self, p: np.ndarray, view: _View) -> float:
        """Share of the candidate landmarks that a camera at ``p`` puts well inside the image which have a feature
        nearby."""
        uv, front = self.camera.project_cam(view.cand_in_cam_axes_m - view.R_ned_cam.T @ p)
        margin = 2.0 * self.cfg.positioning.inlier_px / view.features.scale
        inside = front & self.camera.in_image(uv, margin)  # NaN pixels (behind the camera) compare False
        if not np.any(inside):
            return 0.0
        # The nearest feature within the margin (bound included, as the tree's bound is exclusive), or none (inf).
        nearest_px, _ = view.feature_tree.query(uv[inside], k=1, distance_upper_bound=np.nextafter(margin, np.inf))
        return float(np.mean(np.isfinite(nearest_px)))

    def _match_guided(self, features: Features, cand: np.ndarray, p_cand_ned_m: np.ndarray, pose: CameraPose, radius_px: float) -> tuple[np.ndarray, np.ndarray]:
        """Every (feature, landmark) pair whose predicted pixel is within ``radius_px`` and whose descriptors
        agree, of the candidates ``cand`` (M,) at ``p_cand_ned_m`` (M, 3) m."""
        uv, front = pose.project(self.camera, p_cand_ned_m)
        keep = front & self.camera.in_image(uv, -radius_px)  # NaN pixels (behind the camera) compare False
        cand, uv = cand[keep], uv[keep]
        if len(cand) == 0:
            return np.zeros(0, int), np.zeros(0, int)
        fi, ci = pairs_within(features.uv_px, uv, radius_px)
        # The candidates' descriptor rows are gathered from the map once, then paired (a few in cache, not
        # thousands of scattered rows of a large map).
        ok = hamming_pairs(features.descriptors, fi, self.map.descriptors[cand], ci) <= self.cfg.positioning.max_hamming
        return fi[ok], cand[ci[ok]]

    def _consensus(self, corr: _Correspondences) -> tuple[np.ndarray, np.ndarray]:
        """Seed indices (S,) and their support in distinct features (S,).

        Correspondence k is a member of seed s when its hypothesis is within its own ``tau`` of the seed's. Every
        correspondence is a seed when there are at most ``max_seeds``; else seeds are taken from an even spread of
        ``max_seeds`` over them, in an order whose every prefix is spread too, until the standard RANSAC bound
        says that a hypothesis with the support a reading needs to be weighed (``rival_min_share`` of the best
        found) would have been seeded with probability ``seed_confidence``: ``n >= log(1 - p) / log(1 - w)``,
        ``w`` that support over the correspondences. The first round seeds what the bound asks if every feature
        supports the best (it cannot ask for fewer); a further round follows only if the best found asks for
        more. A frame whose features mostly agree needs few seeds; one with a weak consensus among many
        correspondences takes all.
        """
        cfg = self.cfg.positioning
        K = len(corr.hyp)
        # Members grouped by feature, for one vote per feature with any member.
        order = np.argsort(corr.feat_i, kind="stable")
        feat_sorted = corr.feat_i[order]
        starts = np.flatnonzero(np.r_[True, feat_sorted[1:] != feat_sorted[:-1]])
        if K <= cfg.max_seeds:
            seeds = np.arange(K)
            return seeds, self._support(corr, seeds, order, starts)
        spread = np.linspace(0, K - 1, cfg.max_seeds).astype(int)[self._seed_order]

        def seeds_for(best_support: float) -> int:
            """Seeds the bound asks for when the best support is ``best_support``, in whole bytes of eight (their
            memberships are packed in bytes: the rest of a byte costs nothing), at most ``max_seeds``."""
            w = max(2.0, cfg.rival_min_share * best_support) / K  # share of correspondences a rival has
            needed = _ransac_seeds(w, cfg.seed_confidence)
            return int(min(cfg.max_seeds, 8 * np.ceil(needed / 8))) if np.isfinite(needed) else cfg.max_seeds

        # No hypothesis has more support than there are features: the first round seeds what that would ask.
        n = max(seeds_for(len(starts)), min(8, cfg.max_seeds))
        support = self._support(corr, spread[:n], order, starts)
        while n < (n_next := seeds_for(float(support.max()))):
            support = np.concatenate([support, self._support(corr, spread[n:n_next], order, starts)])
            n = n_next
        return spread[:n], support

    @staticmethod
    def _support(corr: _Correspondences, seeds: np.ndarray, order: np.ndarray, starts: np.ndarray) -> np.ndarray:
        """Support of ``seeds`` (S,) in distinct features (S,): the memberships are compared squared (no square
        root per pair) and packed eight seeds to a byte as they are measured, a block of correspondences at a time
        (the distances of a block stay in cache; the whole matrix of them would not), so that a feature's vote is
        an OR of its rows of S / 8 bytes. ``order`` sorts the correspondences by feature, ``starts`` marks where
        each feature's run begins in that order."""
        hyp, tau2 = corr.hyp, np.square(corr.tau)
        K = len(hyp)
        seed_hyp = hyp[seeds]
        members_packed = np.empty((K, (len(seeds) + 7) // 8), np.uint8)
        rows = max(_CONSENSUS_BLOCK_PAIRS // max(len(seeds), 1), 1)
        for k0 in range(0, K, rows):
            block = slice(k0, k0 + rows)
            members_packed[block] = np.packbits(cdist(hyp[block], seed_hyp, "sqeuclidean") <= tau2[block, None], axis=1)
        votes = np.bitwise_or.reduceat(members_packed[order], starts, axis=0)  # (features, S / 8)
        return np.unpackbits(votes, axis=1, count=len(seeds)).sum(axis=0)

    @staticmethod
    def _one_to_one(member_row: np.ndarray, point_i: np.ndarray, lm_id: np.ndarray, dist2: np.ndarray) -> np.ndarray:
        """Boolean (K,) keeping the member correspondences closest to the hypothesis (``dist2``: squared distances
        to it), one per image point (``point_i``: a feature's spot, :func:`~auxgps.core.features.spots`) and one per landmark: two
        features on one landmark (a corner found twice, on two pyramid levels) are one measurement of it, not
        two; nor are two landmarks of one corner (mapped twice, from both of its features) seen at one spot."""
        keep = np.zeros(len(point_i), bool)
        idx = np.flatnonzero(member_row)
        order = idx[np.argsort(dist2[idx], kind="stable")]
        keep[order[greedy_one_to_one(point_i[order], lm_id[order])]] = True
        return keep

    def _refine(self, p0: np.ndarray, corr: _Correspondences, inl: np.ndarray, alt_above_origin_m: float, pixel_size: float = 1.0,
                prior_info: np.ndarray | None = None) -> _Fit:
        """Weighted least squares over the inliers for the camera position and a small attitude correction.

        Unknowns: position (3) and a rotation ``dtheta`` (3, NED) of the telemetry attitude, which turns each ray
        ``d`` into ``d + dtheta x d``. Each correspondence says its landmark lies on its ray (2 equations); the
        barometer ties the height and the telemetry ties ``dtheta`` to zero with their sigmas. Where the image
        cannot tell a tilt from a shift (one small object), the attitude prior decides and its uncertainty
        lands in the position covariance; where it can (objects spread over the view), both get better.
        The landmarks' errors are weighed as independent, but their heights share much of theirs (the same views
        triangulated them, docs/missions.md): the position covariance also carries their mean squared height
        error taken as one shared lift, through how far such a lift moves the solution. Inliers around nadir
        do not feel it; inliers all at one side of the image, 30 m off nadir from 40 m, read it as a tilt and a
        shift, and move by most of it where the attitude is known to a degree.
        Inliers are re-selected by reprojection error, and weighed by it in the fit's quality: a small cube read
        off by its height (its top corners taken for its bottom ones) keeps its inliers within the tolerance,
        but 2 to 3 px off where the right reading has them within 1. ``pixel_size``: full-resolution px per
        detection px.

        The normal equations are formed from weighted sums over the correspondences' (K, 3) rows, not from
        (K, 3, 6) Jacobians: with unit rays the projector ``P = I - d d^T`` and ``[d]x`` make every block of
        ``J^T J`` out of ``d d^T`` and ``[d]x`` alone (the same numbers to rounding, a few times faster).
        """
        cfg = self.cfg.positioning
        noise = self.cfg.noise
        f = self.camera.focal_px
        # Only inliers can stay inliers: solve on them alone; ``kept`` marks which of them still are.
        idx = np.flatnonzero(inl)
        L, d = corr.L[idx], corr.d[idx]
        # A landmark's uncertainty across its ray (per axis): off nadir, its height error counts as well.
        lm_var = self.map.variance_across_rays_m2(corr.lm_id[idx], d)
        kept = np.ones(len(idx), bool)
        d_dot_L = np.einsum("ki,ki->k", d, L)
        PL = L - d_dot_L[:, None] * d  # P_k L_k, P_k = I - d_k d_k^T
        d_cross_L = np.cross(d, L)  # d_k x L_k
        prior_info = self._refine_prior_info if prior_info is None else prior_info
        eye3 = np.eye(3)
        p = np.asarray(p0, float)
        dtheta = np.zeros(3)
        cov = np.full((3, 3), np.nan)
        turn_var = np.inf
        err_px = np.full(len(idx), np.inf)  # fewer than two inliers: no fit, no quality
        fit = None  # the last fit's inverse information, weights and [sum w t d]x's down column
        for _ in range(3):
            n_inl = int(kept.sum())
            if n_inl < 2:
                break
            t = d_dot_L - d @ p  # range along each ray, m
            w = np.where(kept, 1.0 / ((t * noise.pixel_px * pixel_size / f) ** 2 + lm_var), 0.0)  # 0 off the inliers
            # Residual r_k = P_k (L_k - p) + t_k [d_k]x dtheta = c_k + J_k z, z = (p, dtheta), J_k = [-P_k, t_k [d_k]x].
            # With unit rays P_k^T P_k = P_k, P_k [d_k]x = [d_k]x and [d_k]x^T [d_k]x = P_k, so
            # sum w J^T J = [[sum w P, -[sum w t d]x], [[sum w t d]x, sum w t^2 P]] and
            # -sum w J^T c = (sum w P L, sum w t d x L): weighted sums of d d^T and of (K, 3) rows.
            wt = w * t
            wtt = wt * t
            A = prior_info.copy()
            A[:3, :3] += w.sum() * eye3 - (d * w[:, None]).T @ d
            A[3:, 3:] += wtt.sum() * eye3 - (d * wtt[:, None]).T @ d
            wtd_x = cross_matrix(wt @ d)
            A[:3, 3:] -= wtd_x
            A[3:, :3] += wtd_x
            b = np.concatenate([w @ PL, wt @ d_cross_L])
            b[2] += -alt_above_origin_m * prior_info[2, 2]
            z = np.linalg.solve(A, b)
            p, dtheta = z[:3], z[3:]
            # Offset of each landmark from its corrected ray, m: P (L - p) + t d x dtheta, with d x dtheta as
            # d @ [dtheta]x (one 3x3 product for all rows: np.cross on (K, 3) costs several times more).
            resid = PL - p + (d @ p)[:, None] * d + t[:, None] * (d @ cross_matrix(dtheta))
            resid2 = np.einsum("ki,ki->k", resid, resid)
            err_px = np.sqrt(resid2) / np.maximum(t, 1e-6) * f
            chi2 = float(w @ resid2)
            dof = max(2 * n_inl - 3, 1)
            A_inv = np.linalg.inv(A)
            cov_all = A_inv * max(1.0, chi2 / dof)
            cov, turn_var = cov_all[:3, :3], float(cov_all[5, 5])
            fit = (A_inv, w, wtd_x[:, 2])
            kept &= err_px <= cfg.inlier_px * pixel_size
        if fit is not None:
            # The inliers' height errors as one they share: moving every landmark 1 m down moves the solved
            # position by g, since the barometer holds the camera's height (the move is read as a shift and a tilt).
            A_inv, w, wtd_x_down = fit
            lift = np.concatenate([-((w * d[:, 2]) @ d), wtd_x_down])
            lift[2] += w.sum()
            g = (A_inv @ lift)[:2]
            cov = cov.copy()
            cov[:2, :2] += np.outer(g, g) * float(np.mean(self.map.height_mse_m2(corr.lm_id[idx[w > 0]])))
        attitude_m2 = float(dtheta @ prior_info[3:, 3:] @ dtheta)
        fit_quality = float(np.sum(np.clip(1.0 - np.square(err_px[kept] / (cfg.inlier_px * pixel_size)), 0.0, 1.0)))
        inl = np.zeros(len(inl), bool)
        inl[idx] = kept
        return _Fit(p, cov, inl, attitude_m2, fit_quality, float(dtheta[2]), turn_var)
