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
from auxgps.core.geometry import R_body_cam_from_mount, R_ned_body_from_euler
from auxgps.core.landmarks import LandmarkMap
from auxgps.core.localise import Fix, Localiser
from auxgps.core.mapping import Mapper
from auxgps.core.nav import NavSample
from auxgps.core.fusion import ImuSample, NavFilter
from auxgps.sim.flight import SimConfig, fly, imu_bias, lawnmower_waypoints, sense, sense_imu
from auxgps.sim.render import Renderer
from auxgps.sim.world import World


@dataclass
class RunRecord:
    """Raw results of one run (errors horizontal unless said, m; times ms). Positioning figures cover the
    GPS-denied part of the positioning flight only."""

    seed: int
    landmark_err_ne_m: np.ndarray  # (L, 2) estimate - truth, landmarks used for positioning
    landmark_seen_err_ne_m: np.ndarray  # (L', 2) the same for every landmark seen more than 10 times
    fix_err_ne_m: np.ndarray  # (F, 2) fix - truth, every fix while denied
    fix_sigma_h_m: np.ndarray  # (F,) reported one-sigma
    fix_gated: np.ndarray  # (F,) bool, rejected by the filter's gate
    n_eligible_frames: int  # denied frames with at least one cube entirely in view (or all, without cubes)
    n_eligible_fixed: int
    n_positioning_frames: int
    fused_t_s: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (O,) output times while denied
    fused_err_ne_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    fused_cov_ne_m2: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    fused_vel_err_ne_m_s: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (O, 2) velocity - truth
    fix_applied_t_s: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (F,) when the filter got each fix (NaN: never)
    denied_from_s: float = 0.0  # when GPS was lost
    denied_s: float = 0.0
    blackout_s: tuple[float, float] | None = None  # (start, end) of a camera blackout, s
    n_reinit: int = 0
    n_bad_imu: int = 0
    mapping_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    positioning_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    features_per_frame: np.ndarray = field(default_factory=lambda: np.zeros(0))
    no_fix_reasons: dict[str, int] = field(default_factory=dict)

    @property
    def fix_accepted(self) -> np.ndarray:
        """(F,) bool: given to the filter and kept by its gate (a fix captured in a flight's last moments never
        arrives)."""
        return ~self.fix_gated & np.isfinite(self.fix_applied_t_s)


def _cube_fully_in_view(world: World, camera: PinholeCamera, pose: CameraPose) -> bool:
    if not world.cubes:
        return True
    for cube in world.cubes:
        uv, front = pose.project(camera, cube.vertices_ned())
        if np.all(front) and np.all(camera.in_image(uv)):
            return True
    return False


def _reason_key(reason: str) -> str:
    """Group no-fix reasons without their numbers."""
    return reason.split(":")[0] if ":" in reason else " ".join(w for w in reason.split() if not w[0].isdigit())


class _Setup:
    """Everything one run builds once: camera, renderer, detector, map and the estimator's parts."""

    def __init__(self, world: World, pipeline: PipelineConfig, sim: SimConfig, seed: int) -> None:
        seq = np.random.SeedSequence(seed)
        self.rng_fly_map, self.rng_fly_pos, self.rng_tel, self.rng_img, self.rng_imu = (np.random.default_rng(s) for s in seq.spawn(5))
        self.world, self.pipeline, self.sim = world, pipeline, sim
        self.camera = camera_from_config(pipeline.camera)
        m = pipeline.mount
        self.R_body_cam = R_body_cam_from_mount(*np.deg2rad([m.roll_deg, m.pitch_deg, m.yaw_deg]))
        self.renderer = Renderer(world, self.camera)
        self.effects = sim.image_effects()
        self.detector = FeatureDetector(pipeline.detector)
        self.landmarks = LandmarkMap()
        self.mapper = Mapper(pipeline, self.camera, self.R_body_cam, self.landmarks)
        self.localiser = Localiser(pipeline, self.camera, self.R_body_cam, self.landmarks)

    def render(self, traj, i):
        pose = CameraPose(traj.p_ned_m[i].copy(), traj.R_ned_body(i) @ self.R_body_cam)
        return self.renderer.render(pose, self.effects, self.rng_img)


def _map_flight(su: _Setup, alt_m: float, fps: float, progress) -> tuple[np.ndarray, np.ndarray, list]:
    """Phase 1: the mapping survey with GPS. Returns landmark errors (used, seen > 10) and frame times."""
    sim, pipeline = su.sim, su.pipeline
    traj = fly(lawnmower_waypoints(sim.mapping, alt_m), sim.mapping.speed_m_s, sim.vehicle, su.rng_fly_map, sim.dt_s)
    truths_of: dict[int, list[np.ndarray]] = {}
    mapping_ms = []
    for t in np.arange(0.0, traj.duration_s, 1.0 / fps):
        i = traj.index_at(t)
        frame = su.render(traj, i)
        tel = sense(traj, i, sim.noise, su.rng_tel)
        nav = NavSample(tel.t_s, tel.p_gps_ned_m, tel.alt_m, tel.R_ned_body)
        t0 = time.perf_counter()
        feats = su.detector.detect(frame.image_bgr, tel.R_ned_body @ su.R_body_cam)
        result = su.mapper.process(feats, nav)
        mapping_ms.append((time.perf_counter() - t0) * 1e3)
        fed = np.flatnonzero(result.landmark_ids >= 0)
        for lid, p in zip(result.landmark_ids[fed], frame.true_points_at(feats.uv_px[fed])):
            truths_of.setdefault(int(lid), []).append(p)
        if progress is not None:
            progress()
    # A landmark's truth is the median of the true points behind the features that fed it. Scored: the
    # landmarks positioning uses (seen more than 10 times, views consistent), and all seen more than 10 times.
    lm = su.landmarks
    m = pipeline.mapping
    seen = np.flatnonzero(lm.n_seen[: len(lm)] >= m.min_seen)
    used = seen[lm.usable(seen, m.min_seen, m.max_mean_chi2, m.min_found_ratio)]

    def errors(ids):
        return np.array([lm.p_ned_m[j, :2] - np.median(truths_of[int(j)], axis=0)[:2] for j in ids]).reshape(-1, 2)

    return errors(used), errors(seen), mapping_ms


def run_once(
    world: World, alt_m: float, fps: float, seed: int, pipeline: PipelineConfig, sim: SimConfig, progress=None, mapping_fps: float | None = None
) -> RunRecord:
    """Fly the mapping survey, then the positioning flight, over ``world`` at ``alt_m``; score both.

    ``fps`` is the positioning flight's frame rate; the survey is mapped at ``mapping_fps`` (default ``fps``):
    a camera at 30 frames a second need not feed the mapper every frame, whose landmarks want a dozen views.

    The positioning flight has GPS for its first ``sim.denial.gps_until_s`` seconds, then none. The filter is
    driven by the IMU at its rate, the barometer and (while it lasts) GPS; every frame is located against the
    map with the filter's prediction as the search prior, and its fix reaches the filter ``fix_latency_s`` after
    the frame was captured. Only this function sees the truth, to score.
    """
    su = _Setup(world, pipeline, sim, seed)
    lm_err, lm_err_seen, mapping_ms = _map_flight(su, alt_m, mapping_fps or fps, progress)

    traj = fly(lawnmower_waypoints(sim.positioning, alt_m), sim.positioning.speed_m_s, sim.vehicle, su.rng_fly_pos, sim.dt_s)
    noise, den = sim.noise, sim.denial
    dt = traj.t_s[1] - traj.t_s[0]
    every = lambda rate_hz: max(1, int(round(1.0 / (rate_hz * dt))))  # noqa: E731
    imu_every, baro_every, gps_every = every(noise.imu_rate_hz), every(noise.baro_rate_hz), every(noise.gps_rate_hz)
    frame_every, out_every = every(fps), every(pipeline.fusion.output_rate_hz)
    bias = imu_bias(noise, su.rng_imu)
    nav = NavFilter(pipeline.fusion, 0.0, traj.p_ned_m[0] + su.rng_tel.standard_normal(3) * noise.gps_horizontal_m, np.zeros(3), noise.gps_horizontal_m * 2, 0.1)

    pending: list[tuple[float, Fix, int]] = []  # (delivery time, fix, its index in fix_err)
    fix_applied, fix_err, fix_sigma, fix_gated, pos_ms, n_feat = [], [], [], [], [], []
    fused_t, fused_err, fused_cov, fused_vel_err = [], [], [], []
    reasons: dict[str, int] = {}
    n_elig = n_elig_fixed = n_frames = 0
    blackout = (den.blackout_start_s, (den.blackout_start_s or 0.0) + den.blackout_duration_s)
    for i in range(len(traj.t_s)):
        t = float(traj.t_s[i])
        denied = t >= den.gps_until_s
        if i % imu_every == 0:
            t_imu, f_body, euler = sense_imu(traj, i, noise, bias, su.rng_imu)
            nav.propagate(ImuSample(t_imu, f_body, R_ned_body_from_euler(*euler)))
        if i % baro_every == 0:
            nav.update_altitude(t, -traj.p_ned_m[i, 2] + noise.altitude_m * su.rng_tel.standard_normal(), pipeline.noise.altitude_m)
        if not denied and i % gps_every == 0:
            gps = traj.p_ned_m[i, :2] + su.rng_tel.standard_normal(2) * noise.gps_horizontal_m
            nav.update_position(t, gps, np.eye(2) * pipeline.noise.gps_horizontal_m**2)
        while pending and pending[0][0] <= t:
            _, fix, k = pending.pop(0)
            decision = nav.update_position(fix.t_s, fix.p_ned_m[:2], fix.cov_ned_m2[:2, :2], visual=True)
            fix_gated[k] = not decision.accepted
            fix_applied[k] = t
        if i % frame_every == 0 and denied:
            tel = sense(traj, i, noise, su.rng_tel, gps_ok=False)
            frame = su.render(traj, i)
            image = frame.image_bgr
            if blackout[0] is not None and blackout[0] <= t < blackout[1]:
                image = np.zeros_like(image)  # the camera is blinded
            t0 = time.perf_counter()
            prior = nav.prior(t)
            cand = su.localiser.candidates(tel.alt_m, prior)
            feats = su.detector.detect(image, tel.R_ned_body @ su.R_body_cam, su.localiser.detection_scale(tel.alt_m, prior, cand))
            res = su.localiser.locate(feats, t, tel.R_ned_body, tel.alt_m, prior, cand)
            pos_ms.append((time.perf_counter() - t0) * 1e3)
            n_feat.append(len(feats))
            eligible = _cube_fully_in_view(world, su.camera, frame.pose) and image is frame.image_bgr
            n_frames += 1
            n_elig += eligible
            if isinstance(res, Fix):
                n_elig_fixed += eligible
                err = res.p_ned_m[:2] - traj.p_ned_m[i, :2]
                fix_applied.append(np.nan)
                fix_err.append(err)
                fix_sigma.append(res.sigma_h_m)
                fix_gated.append(False)
                pending.append((t + den.fix_latency_s, res, len(fix_err) - 1))
            else:
                key = _reason_key(res.reason)
                reasons[key] = reasons.get(key, 0) + 1
            if progress is not None:
                progress()
        if i % out_every == 0 and denied:
            est = nav.estimate()
            fused_t.append(t)
            fused_err.append(est.p_ned_m[:2] - traj.p_ned_m[i, :2])
            fused_cov.append(est.cov_p_m2[:2, :2])
            fused_vel_err.append(est.v_ned_m_s[:2] - traj.v_ned_m_s[i, :2])

    return RunRecord(
        seed=seed,
        landmark_err_ne_m=lm_err,
        landmark_seen_err_ne_m=lm_err_seen,
        fix_err_ne_m=np.array(fix_err).reshape(-1, 2),
        fix_sigma_h_m=np.array(fix_sigma),
        fix_gated=np.array(fix_gated, bool),
        n_eligible_frames=n_elig,
        n_eligible_fixed=n_elig_fixed,
        n_positioning_frames=n_frames,
        fused_t_s=np.array(fused_t),
        fused_err_ne_m=np.array(fused_err).reshape(-1, 2),
        fused_cov_ne_m2=np.array(fused_cov).reshape(-1, 2, 2),
        fused_vel_err_ne_m_s=np.array(fused_vel_err).reshape(-1, 2),
        fix_applied_t_s=np.array(fix_applied, float),
        denied_from_s=float(den.gps_until_s),
        denied_s=float(traj.duration_s - den.gps_until_s),
        blackout_s=(blackout[0], blackout[1]) if blackout[0] is not None else None,
        n_reinit=nav.n_reinit,
        n_bad_imu=nav.n_bad_imu,
        mapping_ms=np.array(mapping_ms),
        positioning_ms=np.array(pos_ms),
        features_per_frame=np.array(n_feat),
        no_fix_reasons=reasons,
    )
