"""One evaluation run: a mapping survey with GPS, then a different positioning flight without it.

The estimator (detector, :class:`Mapper`, :class:`Localiser`) sees only rendered frames and noisy telemetry;
the truth (true poses, the renderer's 3D points) is used here only to score what it returned.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from auxgps.config import PipelineConfig
from auxgps.core.camera import CameraPose, PinholeCamera, camera_from_config
from auxgps.core.features import FeatureDetector
from auxgps.core.geometry import R_body_cam_from_mount
from auxgps.core.landmarks import LandmarkMap
from auxgps.core.localise import Fix, Localiser, PositionPrior
from auxgps.core.mapping import Mapper
from auxgps.core.nav import NavSample
from auxgps.sim.flight import SimConfig, fly, lawnmower_waypoints, sense
from auxgps.sim.render import Renderer
from auxgps.sim.world import World


@dataclass
class RunRecord:
    """Raw per-landmark and per-frame results of one run (all errors horizontal, m; times ms)."""

    seed: int
    landmark_err_ne_m: np.ndarray  # (L, 2) estimate - truth, landmarks used for positioning
    landmark_seen_err_ne_m: np.ndarray  # (L', 2) the same for every landmark seen more than 10 times
    fix_err_ne_m: np.ndarray  # (F, 2) fix - truth, every fix of the positioning flight
    fix_sigma_h_m: np.ndarray  # (F,) reported one-sigma
    n_eligible_frames: int  # positioning frames with at least one cube entirely in view (or all, without cubes)
    n_eligible_fixed: int
    n_positioning_frames: int
    mapping_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    positioning_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    features_per_frame: np.ndarray = field(default_factory=lambda: np.zeros(0))
    no_fix_reasons: dict[str, int] = field(default_factory=dict)


def _cube_fully_in_view(world: World, camera: PinholeCamera, pose: CameraPose) -> bool:
    if not world.cubes:
        return True
    for cube in world.cubes:
        uv, front = pose.project(camera, cube.vertices_ned())
        if np.all(front) and np.all(camera.in_image(uv)):
            return True
    return False


class FixTracker:
    """Predicts where the next frame will be from the last fixes (constant velocity), to narrow the search.

    A stand-in for the navigation filter of the fusion stage, so that positioning is scored frame by frame.
    Until two fixes give a velocity, the uncertainty grows at ``max_speed_m_s``; then at ``vel_sigma_m_s``.
    """

    def __init__(self, p_ned_m, t_s, sigma_h_m, max_speed_m_s, vel_sigma_m_s: float = 0.5):
        self.p, self.t, self.sigma = np.asarray(p_ned_m, float), t_s, sigma_h_m
        self.v = None
        self.max_speed = max_speed_m_s
        self.vel_sigma = vel_sigma_m_s
        self.coast_s = 1.0

    def predict(self, t_s: float) -> PositionPrior:
        """Constant velocity for up to ``coast_s`` after the last fix; beyond, any motion up to the top speed."""
        dt = t_s - self.t
        if self.v is None:
            return PositionPrior(self.p, self.sigma + self.max_speed * dt)
        coast = min(dt, self.coast_s)
        sigma = self.sigma + self.vel_sigma * coast + self.max_speed * (dt - coast)
        return PositionPrior(self.p + self.v * coast, sigma)

    def update(self, fix: Fix) -> None:
        dt = fix.t_s - self.t
        v = (fix.p_ned_m - self.p) / dt if dt > 0 else None
        if v is not None and np.linalg.norm(v[:2]) <= self.max_speed:
            self.v = v if self.v is None else 0.5 * (self.v + v)
        self.p, self.t, self.sigma = fix.p_ned_m, fix.t_s, fix.sigma_h_m


def run_once(world: World, alt_m: float, fps: float, seed: int, pipeline: PipelineConfig, sim: SimConfig, progress=None) -> RunRecord:
    """Fly the mapping survey, then the positioning flight, over ``world`` at ``alt_m``; score both."""
    seq = np.random.SeedSequence(seed)
    rng_fly_map, rng_fly_pos, rng_tel, rng_img = (np.random.default_rng(s) for s in seq.spawn(4))
    camera = camera_from_config(pipeline.camera)
    m = pipeline.mount
    R_body_cam = R_body_cam_from_mount(*np.deg2rad([m.roll_deg, m.pitch_deg, m.yaw_deg]))
    renderer = Renderer(world, camera)
    effects = sim.image_effects()
    detector = FeatureDetector(pipeline.detector)
    landmarks = LandmarkMap()
    mapper = Mapper(pipeline, camera, R_body_cam, landmarks)
    localiser = Localiser(pipeline, camera, R_body_cam, landmarks)

    def frames(survey, rng_fly):
        traj = fly(lawnmower_waypoints(survey, alt_m), survey.speed_m_s, sim.vehicle, rng_fly, sim.dt_s)
        for t in np.arange(0.0, traj.duration_s, 1.0 / fps):
            i = traj.index_at(t)
            true_pose = CameraPose(traj.p_ned_m[i].copy(), traj.R_ned_body(i) @ R_body_cam)
            frame = renderer.render(true_pose, effects, rng_img)
            yield traj, i, frame

    # Phase 1: mapping with GPS.
    truths_of: dict[int, list[np.ndarray]] = {}
    mapping_ms = []
    for traj, i, frame in frames(sim.mapping, rng_fly_map):
        tel = sense(traj, i, sim.noise, rng_tel)
        nav = NavSample(tel.t_s, tel.p_gps_ned_m, tel.alt_m, tel.R_ned_body)
        t0 = time.perf_counter()
        feats = detector.detect(frame.image_bgr)
        result = mapper.process(feats, nav)
        mapping_ms.append((time.perf_counter() - t0) * 1e3)
        fed = np.flatnonzero(result.landmark_ids >= 0)
        for lid, p in zip(result.landmark_ids[fed], frame.true_points_at(feats.uv_px[fed])):
            truths_of.setdefault(int(lid), []).append(p)
        if progress is not None:
            progress()

    # A landmark's truth is the median of the true points behind the features that fed it. Scored: the
    # landmarks positioning uses (seen more than 10 times, views consistent), and all seen more than 10 times.
    n = len(landmarks)
    seen = np.flatnonzero(landmarks.n_seen[:n] >= pipeline.mapping.min_seen)
    m = pipeline.mapping
    used = seen[landmarks.usable(seen, m.min_seen, m.max_mean_chi2, m.min_found_ratio)]

    def lm_errors(ids):
        return np.array([landmarks.p_ned_m[j, :2] - np.median(truths_of[int(j)], axis=0)[:2] for j in ids]).reshape(-1, 2)

    lm_err, lm_err_seen = lm_errors(used), lm_errors(seen)

    # Phase 2: positioning without GPS, on a different flight. GPS is known only at its start.
    fix_err, fix_sigma, pos_ms, n_feat = [], [], [], []
    reasons: dict[str, int] = {}
    prior = None
    tracker = None
    n_elig = n_elig_fixed = n_frames = 0
    for traj, i, frame in frames(sim.positioning, rng_fly_pos):
        tel = sense(traj, i, sim.noise, rng_tel, gps_ok=(n_frames == 0))
        if tracker is None:
            tracker = FixTracker(np.array([*tel.p_gps_ned_m[:2], -tel.alt_m]), tel.t_s, pipeline.noise.gps_horizontal_m, pipeline.positioning.max_speed_m_s)
        prior = tracker.predict(tel.t_s)
        t0 = time.perf_counter()
        feats = detector.detect(frame.image_bgr)
        res = localiser.locate(feats, tel.t_s, tel.R_ned_body, tel.alt_m, prior)
        pos_ms.append((time.perf_counter() - t0) * 1e3)
        n_feat.append(len(feats))
        eligible = _cube_fully_in_view(world, camera, frame.pose)
        n_frames += 1
        n_elig += eligible
        if isinstance(res, Fix):
            n_elig_fixed += eligible
            fix_err.append(res.p_ned_m[:2] - traj.p_ned_m[i, :2])
            fix_sigma.append(res.sigma_h_m)
            tracker.update(res)
        else:
            key = res.reason.split(":")[0] if res.reason.startswith("ambiguous") else res.reason.split(" ", 1)[-1]
            reasons[key] = reasons.get(key, 0) + 1
        if progress is not None:
            progress()

    return RunRecord(
        seed=seed,
        landmark_err_ne_m=lm_err,
        landmark_seen_err_ne_m=lm_err_seen,
        fix_err_ne_m=np.array(fix_err).reshape(-1, 2),
        fix_sigma_h_m=np.array(fix_sigma),
        n_eligible_frames=n_elig,
        n_eligible_fixed=n_elig_fixed,
        n_positioning_frames=n_frames,
        mapping_ms=np.array(mapping_ms),
        positioning_ms=np.array(pos_ms),
        features_per_frame=np.array(n_feat),
        no_fix_reasons=reasons,
    )
