"""One evaluation run: a mapping survey with GPS, then a different positioning flight without it.

The estimator (:class:`auxgps.core.estimator.Estimator`, the one ``auxgps run`` flies) sees only rendered frames
and noisy telemetry as events; the truth (true poses, the renderer's 3D points) is used here only to score what it
returned.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from auxgps.config import PipelineConfig
from auxgps.core.camera import CameraPose, PinholeCamera, camera_from_config
from auxgps.core.estimator import Estimator, EstimatorOptions, FrameResult
from auxgps.core.events import Frame
from auxgps.core.geometry import R_body_cam_from_mount
from auxgps.io.map_file import load_maps
from auxgps.io.mission import Mission
from auxgps.sim.faults import FaultInjector
from auxgps.sim.flight import SimConfig, fly, gps_lost_waypoint, imu_bias, lawnmower_waypoints, mission_waypoints_ned
from auxgps.sim.render import Renderer
from auxgps.sim.sensors import Sensors
from auxgps.sim.world import World


@dataclass
class RunRecord:
    """Raw results of one run (errors horizontal unless said, m; times ms). Positioning figures cover the
    GPS-denied part of the positioning flight only."""

    seed: int
    landmark_err_ne_m: np.ndarray  # (L, 2) estimate - truth, landmarks used for positioning
    landmark_seen_err_ne_m: np.ndarray  # (L', 2) the same for every landmark seen more than 10 times
    fix_err_ne_m: np.ndarray  # (F, 2) fix - truth, every fix while denied
    fix_sigma_h_rms_m: np.ndarray  # (F,) reported one-sigma, root-mean of the north and east variances
    fix_gated: np.ndarray  # (F,) bool, rejected by the filter's gate
    n_eligible_frames: int  # denied frames with at least one cube entirely in view (or all, without cubes)
    n_eligible_fixed: int
    n_positioning_frames: int
    fused_t_s: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (O,) output times while denied
    fused_err_ne_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    fused_cov_ne_m2: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    fused_vel_err_ne_m_s: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (O, 2) velocity - truth
    fix_applied_t_s: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (F,) when the filter got each fix (NaN: never)
    fix_over_patch: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # (F,) captured over a featureless patch
    fix_followed: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # (F,) from the last fix's inliers by optical flow
    fused_height_agl_m: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (O,) the true height above ground
    fused_over_patch: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # (O,) over a featureless patch
    gps_fix_type: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # (O,) GPS_INPUT's fix_type (0: none sent)
    gps_h_acc_m: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (O,) GPS_INPUT's horiz_accuracy (NaN: none sent)
    denied_from_s: float = 0.0  # when GPS was lost
    denied_s: float = 0.0
    blackout_s: tuple[float, float] | None = None  # (start, end) of a camera blackout, s
    n_reinit: int = 0
    n_bad_imu: int = 0
    mapping_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    positioning_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    features_per_frame: np.ndarray = field(default_factory=lambda: np.zeros(0))
    no_fix_reasons: dict[str, int] = field(default_factory=dict)
    notes: list[tuple[float, str]] = field(default_factory=list)  # the positioning flight's events-log lines (t, line)

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


#: The UTC the simulated flights' clocks start at (only GPS_INPUT's week time reads it), s.
T_UNIX_0_S = 1_800_000_000.0


class _Setup:
    """Everything one run builds once: seeded generators, camera geometry and renderer. The estimator is built by
    :class:`Estimator` alone."""

    def __init__(self, world: World, pipeline: PipelineConfig, sim: SimConfig, seed: int) -> None:
        seq = np.random.SeedSequence(seed)
        self.rng_fly_map, self.rng_fly_pos, self.rng_tel, self.rng_img, self.rng_imu = (np.random.default_rng(s) for s in seq.spawn(5))
        self.world, self.pipeline, self.sim = world, pipeline, sim
        self.options = EstimatorOptions()
        self.camera = camera_from_config(pipeline.camera)
        m = pipeline.mount
        self.R_body_cam = R_body_cam_from_mount(*np.deg2rad([m.roll_deg, m.pitch_deg, m.yaw_deg]))
        self.renderer = Renderer(world, self.camera)
        self.effects_out, self.effects_back = sim.image_effects(after_gps_loss=False), sim.image_effects(after_gps_loss=True)
        self.survey_notes: list[tuple[float, str]] = []  # what the survey's estimator said (with fault injection)

    def render(self, traj, i, after_gps_loss: bool = False):
        """The frame at step ``i``, rendered from the truth with the camera's effects of the way out or back."""
        pose = CameraPose(traj.p_ned_m[i].copy(), traj.R_ned_body(i) @ self.R_body_cam)
        effects = self.effects_back if after_gps_loss else self.effects_out
        return self.renderer.render(pose, effects, self.rng_img, v_ned_m_s=traj.v_ned_m_s[i])

    def sensors(self, traj, bias, denied_from_s: float = np.inf) -> Sensors:
        return Sensors(traj, self.world.frame, self.sim.noise, rng_tel=self.rng_tel, rng_imu=self.rng_imu, bias_body_m_s2=bias,
                       gps1_lag_s=self.options.gps1_lag_s, gps_denied_from_s=denied_from_s)


@dataclass
class _Seen:
    """One processed frame, as the evaluator sees it: the estimator's result, the rendering (truth), the step, and
    the wall time it took (begin, process and finish), ms."""

    i: int
    result: FrameResult
    rendered: object
    blinded: bool
    ms: float


def _fly(est: Estimator, su: _Setup, traj, sensors: Sensors, fps: float, *, latency_s: float, on_frame, on_output=None,
         blackout: tuple[float, float] | None = None, faults: FaultInjector | None = None, notes: list | None = None,
         progress=None, effects_after_s: float = np.inf) -> None:
    """Feed one trajectory to ``est`` as a companion would: telemetry as it comes, each frame begun at its capture
    and finished ``latency_s`` later (its processing time on a vehicle), GPS_INPUT asked for at the output rate.
    ``on_frame(_Seen)`` and ``on_output(i, Output)`` are the evaluator's: only they see the truth. ``faults``
    changes what the estimator is given (frames and telemetry), never the truth; ``notes`` collects the lines
    the estimator has for the events log, with their times. Frames from ``effects_after_s`` on are rendered with
    the camera's effects of the way back (sim config ``effects``: after GPS1 is lost)."""
    dt = traj.t_s[1] - traj.t_s[0]
    frame_every = max(1, int(round(1.0 / (fps * dt))))
    out_every = max(1, int(round(1.0 / (su.pipeline.fusion.output_rate_hz * dt))))
    pending: list[tuple[float, object, int, object, bool, float]] = []

    def finish(item):
        _, work, i, rendered, blinded, ms = item
        t0 = time.perf_counter()
        res = est.finish_frame(work)
        if res.note and notes is not None:
            notes.append((res.t_s, res.note))
        on_frame(_Seen(i, res, rendered, blinded, ms + (time.perf_counter() - t0) * 1e3))

    for i in range(len(traj.t_s)):
        t = float(traj.t_s[i])
        events = sensors.events_at(i)
        for event in (faults.events(t, events) if faults is not None else events):
            note = est.feed(event)
            if note and notes is not None:
                notes.append((t, note))
        while pending and pending[0][0] <= t + 1e-9:
            finish(pending.pop(0))
        if i % frame_every == 0:
            rendered = su.render(traj, i, after_gps_loss=t >= effects_after_s)
            image = rendered.image_bgr
            blinded = blackout is not None and blackout[0] <= t < blackout[1]
            if blinded:
                image = np.zeros_like(image)  # the camera is blinded
            if faults is not None:
                image = faults.frame(t, image)  # None: the camera delivered no frame
            if image is not None:
                t0 = time.perf_counter()
                job = est.begin_frame(Frame(t, image, time_sigma_s=0.0))  # rendered at the very moment it is stamped
                if isinstance(job, FrameResult):
                    if job.note and notes is not None:
                        notes.append((job.t_s, job.note))
                    on_frame(_Seen(i, job, rendered, blinded, (time.perf_counter() - t0) * 1e3))
                else:
                    work = est.process_frame(job)
                    pending.append((t + latency_s, work, i, rendered, blinded, (time.perf_counter() - t0) * 1e3))
            if progress is not None:
                progress()
        if i % out_every == 0 and (on_output is not None or notes is not None):
            # GPS_INPUT at the companion's rate, in the survey too: the supervisor decides there as it does in flight
            # (a GPS1 gone silent is noticed here), and its status lines are the flight's events-log lines.
            out = est.output(t, T_UNIX_0_S + t)
            if notes is not None and out.decision.status:
                notes.append((t, out.decision.status))
            if on_output is not None:
                on_output(i, out)


class _MapTruth:
    """The truth behind the landmarks a flight maps: the true points behind the features that fed each one."""

    def __init__(self) -> None:
        self.truths_of: dict[int, list[np.ndarray]] = {}
        self.mapping_ms: list[float] = []

    def on_frame(self, seen: _Seen) -> None:
        mapped = seen.result.mapped
        if mapped is None:
            return
        self.mapping_ms.append(seen.ms)
        fed = np.flatnonzero(mapped.landmark_ids >= 0)
        for lid, p in zip(mapped.landmark_ids[fed], seen.rendered.true_points_at(seen.result.features.uv_px[fed])):
            self.truths_of.setdefault(int(lid), []).append(p)

    def errors(self, est: Estimator, pipeline: PipelineConfig) -> tuple[np.ndarray, np.ndarray]:
        """Landmark errors (estimate - truth, north/east, m): those positioning uses (seen more than 10 times, views
        consistent), and all seen more than 10 times. A landmark's truth is the median of its true points. The
        flight's own landmarks only: a prior map's are not seen by the flight as landmarks."""
        lm = est.landmarks
        m = pipeline.mapping
        seen = np.flatnonzero((lm.n_seen[: len(lm)] >= m.min_seen) & (lm.source[: len(lm)] == 0))
        used = seen[lm.usable(seen, m.min_seen, m.max_mean_chi2, m.min_found_ratio)]

        def err(ids):
            return np.array([lm.p_ned_m[j, :2] - np.median(self.truths_of[int(j)], axis=0)[:2] for j in ids]).reshape(-1, 2)

        return err(used), err(seen)


def _map_flight(su: _Setup, alt_m: float, fps: float, progress) -> tuple[Estimator, _MapTruth]:
    """Phase 1: the mapping survey with GPS. Returns the estimator that flew it (its map) and its map's truth."""
    sim, pipeline = su.sim, su.pipeline
    traj = fly(lawnmower_waypoints(sim.mapping, alt_m), sim.mapping.speed_m_s, sim.vehicle, su.rng_fly_map, sim.dt_s)
    est = Estimator(pipeline, su.options, frame=su.world.frame)
    truth = _MapTruth()
    _fly(est, su, traj, su.sensors(traj, imu_bias(sim.noise, su.rng_imu)), fps, latency_s=sim.denial.fix_latency_s,
         on_frame=truth.on_frame, faults=FaultInjector.for_flight(sim.faults, "mapping"), notes=su.survey_notes,
         progress=progress)
    return est, truth


class _Scored:
    """What the evaluator scores of a flight once GPS1 is lost at ``denied_from_s``: each fix, each output, and why
    frames gave none. Only this sees the truth."""

    def __init__(self, su: _Setup, traj, denied_from_s: float) -> None:
        self.su, self.traj, self.denied_from = su, traj, float(denied_from_s)
        self.dt = traj.t_s[1] - traj.t_s[0]
        self.fix_applied, self.fix_err, self.fix_sigma, self.fix_gated, self.pos_ms, self.n_feat = [], [], [], [], [], []
        self.fix_over_patch, self.fix_followed = [], []
        self.fused_t, self.fused_err, self.fused_cov, self.fused_vel_err = [], [], [], []
        self.height_agl, self.over_patch, self.fix_type, self.h_acc = [], [], [], []
        self.reasons: dict[str, int] = {}
        self.counts = {"eligible": 0, "eligible_fixed": 0, "frames": 0}

    def on_frame(self, seen: _Seen) -> None:
        res, traj, latency_s = seen.result, self.traj, self.su.sim.denial.fix_latency_s
        t_capture = float(traj.t_s[seen.i])
        if res.kind == "skipped" or res.mapping or t_capture < self.denied_from:
            return
        self.pos_ms.append(seen.ms)
        self.n_feat.append(len(res.features) if res.features is not None else 0)
        eligible = _cube_fully_in_view(self.su.world, self.su.camera, seen.rendered.pose) and not seen.blinded
        self.counts["frames"] += 1
        self.counts["eligible"] += eligible
        if res.kind == "visual":
            self.counts["eligible_fixed"] += eligible
            self.fix_err.append(res.located.p_ned_m[:2] - traj.p_ned_m[seen.i, :2])
            self.fix_sigma.append(res.located.sigma_h_rms_m)
            self.fix_gated.append(not res.decision.accepted)
            self.fix_applied.append(t_capture + latency_s)
            self.fix_over_patch.append(self._over_patch(seen.i))
            self.fix_followed.append(bool(res.located.followed))
        else:
            key = _reason_key(res.reason)
            self.reasons[key] = self.reasons.get(key, 0) + 1

    def on_output(self, i: int, out) -> None:
        if out.estimate is None or out.t_described_s < self.denied_from:
            return
        traj = self.traj
        k = min(max(int(round(out.t_described_s / self.dt)), 0), len(traj.t_s) - 1)
        self.fused_t.append(out.t_described_s)
        self.fused_err.append(out.estimate.p_ned_m[:2] - traj.p_ned_m[k, :2])
        self.fused_cov.append(out.estimate.cov_p_m2[:2, :2])
        self.fused_vel_err.append(out.estimate.v_ned_m_s[:2] - traj.v_ned_m_s[k, :2])
        self.height_agl.append(float(self.su.world.ground_down_m(traj.p_ned_m[k, :2])) - traj.p_ned_m[k, 2])
        self.over_patch.append(self._over_patch(k))
        self.fix_type.append(out.gps.fix_type if out.gps is not None else 0)
        self.h_acc.append(out.gps.horiz_accuracy_m if out.gps is not None else np.nan)

    def _over_patch(self, i: int) -> bool:
        """Whether the vehicle is over one of the world's featureless patches at step ``i``."""
        return bool(self.su.world.patches) and bool(self.su.world.patch_at(self.traj.p_ned_m[i : i + 1, :2])[0] >= 0)

    def record(self, seed: int, est: Estimator, landmark_errors: tuple[np.ndarray, np.ndarray], mapping_ms: list, blackout,
               notes) -> RunRecord:
        """The run's record; ``landmark_errors`` from :meth:`_MapTruth.errors` of the map the flight positioned on."""
        # A fix captured in the flight's last moments never reaches the filter.
        t_end = float(self.traj.t_s[-1])
        fix_applied = [t if t <= t_end + 1e-9 else np.nan for t in self.fix_applied]
        lm_err, lm_err_seen = landmark_errors
        return RunRecord(
            seed=seed,
            landmark_err_ne_m=lm_err,
            landmark_seen_err_ne_m=lm_err_seen,
            fix_err_ne_m=np.array(self.fix_err).reshape(-1, 2),
            fix_sigma_h_rms_m=np.array(self.fix_sigma),
            fix_gated=np.array(self.fix_gated, bool),
            n_eligible_frames=self.counts["eligible"],
            n_eligible_fixed=self.counts["eligible_fixed"],
            n_positioning_frames=self.counts["frames"],
            fused_t_s=np.array(self.fused_t),
            fused_err_ne_m=np.array(self.fused_err).reshape(-1, 2),
            fused_cov_ne_m2=np.array(self.fused_cov).reshape(-1, 2, 2),
            fused_vel_err_ne_m_s=np.array(self.fused_vel_err).reshape(-1, 2),
            fix_applied_t_s=np.array(fix_applied, float),
            fix_over_patch=np.array(self.fix_over_patch, bool),
            fix_followed=np.array(self.fix_followed, bool),
            fused_height_agl_m=np.array(self.height_agl),
            fused_over_patch=np.array(self.over_patch, bool),
            gps_fix_type=np.array(self.fix_type, int),
            gps_h_acc_m=np.array(self.h_acc, float),
            denied_from_s=self.denied_from,
            denied_s=float(self.traj.duration_s - self.denied_from),
            blackout_s=blackout,
            n_reinit=est.filter.n_reinit if est.filter is not None else 0,
            n_bad_imu=est.filter.n_bad_imu if est.filter is not None else 0,
            mapping_ms=np.array(mapping_ms),
            positioning_ms=np.array(self.pos_ms),
            features_per_frame=np.array(self.n_feat),
            no_fix_reasons=self.reasons,
            notes=notes,
        )


def run_once(
    world: World, alt_m: float, fps: float, seed: int, pipeline: PipelineConfig, sim: SimConfig, progress=None, mapping_fps: float | None = None
) -> RunRecord:
    """Fly the mapping survey, then the positioning flight, over ``world`` at ``alt_m``; score both.

    ``fps`` is the positioning flight's frame rate; the survey is mapped at ``mapping_fps`` (default ``fps``):
    a camera at 30 frames a second need not feed the mapper every frame, whose landmarks want a dozen views.

    Both flights go through :class:`Estimator`, as ``auxgps run`` does: the survey from an empty map about the
    world's origin, the positioning flight from the survey's map (as ``--map``). The positioning flight has GPS1
    for its first ``sim.denial.gps_until_s`` seconds (it maps on), then GPS1 reports no fix. Each frame is begun
    at its capture and finished ``fix_latency_s`` later; GPS_INPUT is asked for at the output rate and scored at
    the time it describes. The whole positioning flight has the camera's effects of the way back (an appearance
    shift relative to the survey's). Only this function sees the truth, to score.
    """
    su = _Setup(world, pipeline, sim, seed)
    map_est, map_truth = _map_flight(su, alt_m, mapping_fps or fps, progress)
    landmark_errors = map_truth.errors(map_est, pipeline)  # the survey's map, before the positioning flight adds to it

    traj = fly(lawnmower_waypoints(sim.positioning, alt_m), sim.positioning.speed_m_s, sim.vehicle, su.rng_fly_pos, sim.dt_s)
    den = sim.denial
    denied_from = float(den.gps_until_s)
    est = Estimator(pipeline, su.options, landmarks=map_est.landmarks, frame=world.frame)
    blackout = (den.blackout_start_s, den.blackout_start_s + den.blackout_duration_s) if den.blackout_start_s is not None else None
    scored = _Scored(su, traj, denied_from)
    sensors = su.sensors(traj, imu_bias(sim.noise, su.rng_imu), denied_from_s=denied_from)
    notes: list[tuple[float, str]] = []
    _fly(est, su, traj, sensors, fps, latency_s=den.fix_latency_s, on_frame=scored.on_frame, on_output=scored.on_output,
         blackout=blackout, faults=FaultInjector.for_flight(sim.faults, "positioning"), notes=notes, progress=progress, effects_after_s=-np.inf)
    return scored.record(seed, est, landmark_errors, map_truth.mapping_ms, blackout,
                         [(t, f"survey: {line}") for t, line in su.survey_notes] + notes)


def run_mission(
    world: World, mission: Mission, alt_m: float | None, speed_m_s: float, gps_lost_at_seq: int, fps: float, seed: int,
    pipeline: PipelineConfig, sim: SimConfig, progress=None, maps: tuple[str, ...] = (),
) -> RunRecord:
    """Fly ``mission`` once over ``world`` from home at its origin, every height at ``alt_m`` (None: the mission's own
    heights) and at ``speed_m_s``: mapping while GPS1 is good, GPS1 lost (no fix) on reaching mission item
    ``gps_lost_at_seq`` (its number in the file), the rest flown and scored as :func:`run_once` scores its
    positioning flight. One estimator, as in a real flight: the map it positions on is the one it made on the way
    out. Faults apply at ``at_s`` after take-off; the camera's effects of the way back from the moment GPS1 is lost.
    ``maps``: map files the estimator starts from (prior maps), moved into the world's frame."""
    path_ned, owner = mission_waypoints_ned(mission, world.frame, alt_m)
    k = gps_lost_waypoint(mission, owner, gps_lost_at_seq)
    su = _Setup(world, pipeline, sim, seed)
    traj = fly(path_ned, speed_m_s, sim.vehicle, su.rng_fly_map, sim.dt_s)
    denied_from = float(traj.reached_t_s[k])
    landmarks = load_maps(list(maps), world.frame)[0] if maps else None
    est = Estimator(pipeline, su.options, landmarks=landmarks, frame=world.frame)
    map_truth, scored = _MapTruth(), _Scored(su, traj, denied_from)

    def on_frame(seen: _Seen) -> None:
        map_truth.on_frame(seen)
        scored.on_frame(seen)

    notes: list[tuple[float, str]] = []
    _fly(est, su, traj, su.sensors(traj, imu_bias(sim.noise, su.rng_imu), denied_from_s=denied_from), fps,
         latency_s=sim.denial.fix_latency_s, on_frame=on_frame, on_output=scored.on_output,
         faults=FaultInjector.for_flight(sim.faults, None), notes=notes,
         progress=progress, effects_after_s=denied_from)
    return scored.record(seed, est, map_truth.errors(est, pipeline), map_truth.mapping_ms, None, notes)
