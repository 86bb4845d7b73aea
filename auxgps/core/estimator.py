"""The estimator: everything auxgps decides, from timestamped events, with no threads, sockets, files or clock.

This is the one place that builds the pipeline (detector, mapper, localiser, filter, supervisor) and the one path
every command runs: ``auxgps run`` feeds it the link's messages and the camera's frames on the process's clock;
``eval``, ``bench`` and ``demo`` feed it a simulator's; ``replay`` feeds it a recording's. The same events in the
same order give bit-identical results.

Inputs (:mod:`auxgps.core.events`):

- :meth:`Estimator.feed` takes telemetry: IMU and attitude drive the filter, the autopilot's height above home
  corrects its height, GPS1 corrects its position and, while the supervisor trusts it, geotags landmarks.
- A camera frame goes through three calls, so that a companion can run the slow middle one without holding the
  lock that its other threads need: :meth:`begin_frame` reads the filter (the prior at the frame's capture time,
  the attitude, whether GPS1 is trusted), :meth:`process_frame` detects, maps or locates (it touches only the map
  and the frame), :meth:`finish_frame` fuses the fix. :meth:`on_frame` is the three in a row.
- :meth:`output` is what GPS_INPUT says at a given time.

Without GPS1 (jammed before take-off, or a restart after a crash mid-flight), a loaded map still gives a start:
each frame is located against the whole map without a prior, and the filter starts once ``acquisition_fixes``
fixes within ``reinit_window_s`` lie on one constant-velocity track (:func:`track_through`; a filter that is lost checks
its fixes against its own dead reckoning instead, :func:`offset_from_dead_reckoning`); until then GPS_INPUT says
no fix. A loaded map that ends further than ``max_map_distance_m`` from GPS1's first fix is of somewhere
else: it is dropped, said so once, and the flight maps afresh.

Prior maps (from an orthophoto, ``auxgps map build --orthophoto``) are loaded like a flight's map and used to
position, never refined: the flight maps its own landmarks beside them, and where it has enough of its own
(``positioning.own_landmarks_take_over``), positioning leaves the prior map's out. A fix says which map it used;
the filter carries the prior map's placement error as an offset state that changes over distance flown.

Heights: ``alt_above_origin_m`` is above the local frame's origin (the map's, or the ground below GPS1's first
fix); the autopilot reports heights above home, and the two differ by home's height above the origin.
"""

from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from auxgps.config import PipelineConfig
from auxgps.core.camera import CameraPose, camera_from_config
from auxgps.core.events import Attitude, Frame, Gps1, Imu, Position
from auxgps.core.features import FeatureDetector, Features, near_nadir, to_gray
from auxgps.core.frame_check import FrameCheck
from auxgps.core.fusion import FusedEstimate, GateDecision, ImuSample, NavFilter
from auxgps.core.geometry import LocalFrame, R_body_cam_from_mount, R_ned_body_from_euler, attitude_between, attitude_turned
from auxgps.core.gps_output import GpsOutput, gps_output
from auxgps.core.heading import HeadingEstimate, HeadingTracker, MotionView, ground_points_ne
from auxgps.core.landmarks import LandmarkMap
from auxgps.core.localise import Fix, Localiser, NoFix, PositionPrior, prior_m2
from auxgps.core.mapping import Mapper, MappingResult
from auxgps.core.nav import NavSample
from auxgps.core.stopwatch import null_stopwatch
from auxgps.core.supervisor import Decision, Gps1Sample, Mode, Supervisor, SupervisorConfig
from auxgps.core.tracking import InlierFlow


@dataclass(frozen=True)
class EstimatorOptions:
    """Timing facts of the vehicle the estimator runs on.

    ``gps_delay_s``: each output describes the vehicle this long before it is asked for (the autopilot's
    ``GPS2_DELAY_MS``); ``gps1_lag_s``: how long before the autopilot gets a GPS1 reading its receiver measured it;
    ``max_map_distance_m``: how far from a loaded map's landmarks GPS1's first fix may be, horizontally.
    """

    gps_delay_s: float = 0.1
    gps1_lag_s: float = 0.1
    max_map_distance_m: float = 5000.0  # a loaded map that ends this far from GPS1's first fix is of somewhere else
    home_ground_radius_m: float = 20.0  # a loaded map's landmarks this near GPS1's first fix give home's ground height
    max_attitude_age_s: float = 0.2  # no fix from a frame, no IMU integration, without an attitude this recent
    height_stuck_s: float = 2.0  # a height above home repeating one value this long while climbing or descending
    height_stuck_min_vd_m_s: float = 0.3  # at this vertical speed or more (the filter's) is stuck: not fused
    supervisor: SupervisorConfig = field(default_factory=SupervisorConfig)


@dataclass(frozen=True)
class FrameJob:
    """A frame with what the estimator knew at its capture time (from :meth:`Estimator.begin_frame`).

    ``mapping``: GPS1 was trusted, so the frame feeds the map and its fix is only a self-check;
    ``p_gps_ned_m``: where the filter, fusing GPS1, puts the camera at the capture time (mapping frames only).
    """

    frame: Frame
    R_ned_body: np.ndarray
    alt_above_origin_m: float
    prior: PositionPrior | None  # None: acquisition, no filter yet
    mapping: bool
    p_gps_ned_m: np.ndarray | None
    speed_h_m_s: float | None = None  # the filter's horizontal speed at the capture (None: no filter)
    heading: HeadingEstimate | None = None  # the autopilot's heading error taken out of R_ned_body (None: not solved)
    rate_ned_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))  # the body's turn rate at the capture, NED axes


@dataclass(frozen=True)
class FrameWork:
    """What :meth:`Estimator.process_frame` found: the features, the map update and the fix."""

    job: FrameJob
    features: Features
    mapped: MappingResult | None
    located: Fix | NoFix
    note: str | None = None  # a line for the events log: a camera fault began or ended, the frame rate fell


@dataclass(frozen=True)
class FrameResult:
    """What auxgps decided about one frame.

    ``kind``: "skipped" (no filter, attitude or height yet), "none" (no fix), "self-check" (a fix while mapping,
    compared with the filter: ``self_check_m``), or "visual" (a fix given to the filter: ``decision``).
    ``mapping``: the frame fed the map (GPS1 was trusted at its capture); ``features``: what was detected in it.
    """

    t_s: float
    kind: str
    reason: str
    mapping: bool = False
    located: Fix | NoFix | None = None
    decision: GateDecision | None = None
    self_check_m: float | None = None
    mapped: MappingResult | None = None
    features: Features | None = None
    note: str | None = None  # a line for the events log (a camera fault began or ended, the frame rate fell)


@dataclass(frozen=True)
class AmbiguousView:
    """The last frame that could not tell two readings apart: when (``t_s``), how far apart its rivals were, where
    the filter had the camera (north, east, m) and half the shorter side of its footprint on the ground, m."""

    t_s: float
    rivals_apart_m: float
    p_ne_m: np.ndarray
    half_side_m: float


@dataclass(frozen=True)
class Output:
    """What auxgps tells the autopilot at ``t_s``: the GPS_INPUT content (None before the local frame is known),
    the supervisor's decision, and the estimate it came from, which describes ``t_described_s``."""

    t_s: float
    t_described_s: float
    gps: GpsOutput | None
    decision: Decision
    estimate: FusedEstimate | None


def _joined(*lines: str | None) -> str | None:
    """Events-log lines said together, in one line (None when there is none)."""
    return "; ".join(line for line in lines if line) or None


@dataclass(frozen=True)
class Track:
    """A constant-velocity track through a run of fixes, at the last one's time: position and velocity (north,
    east) with their covariances."""

    t_s: float
    p_ne_m: np.ndarray
    v_ne_m_s: np.ndarray
    cov_p_m2: np.ndarray
    cov_v_m2_s2: np.ndarray


def _offset_and_rate(fixes: list[Fix], ref_ne_m: np.ndarray, gate_chi2: float, info_rate: np.ndarray | None = None,
                     shared_sigma_m: float = 0.0) -> tuple[np.ndarray, np.ndarray] | None:
    """Weighted least squares of ``fixes`` less ``ref_ne_m`` (N, 2) as ``b + u (t_i - t_last)`` (north, east):
    ``x = (b, u)`` and its covariance, or None when a fix lies off the fit by more than the gate (squared
    Mahalanobis ``gate_chi2``) or the fit has no solution. ``info_rate``: a prior N(0, its inverse) on ``u``;
    ``shared_sigma_m``: added to each fix's sigma on both axes."""
    t_last = fixes[-1].t_s
    N, b, rows = np.zeros((4, 4)), np.zeros(4), []
    if info_rate is not None:
        N[2:, 2:] = info_rate
    for f, ref in zip(fixes, ref_ne_m):
        A = np.hstack([np.eye(2), np.eye(2) * (f.t_s - t_last)])
        W = np.linalg.inv(f.cov_ned_m2[:2, :2] + np.eye(2) * shared_sigma_m**2)
        d = f.p_ned_m[:2] - ref
        N += A.T @ W @ A
        b += A.T @ W @ d
        rows.append((A, W, d))
    try:
        cov = np.linalg.inv(N)
    except np.linalg.LinAlgError:
        return None  # fixes all at one time and no prior: no rate
    x = cov @ b
    if any(float((d - A @ x) @ W @ (d - A @ x)) > gate_chi2 for A, W, d in rows):
        return None
    return x, cov


def track_through(fixes: list[Fix], gate_chi2: float, max_speed_m_s: float) -> Track | None:
    """The weighted least-squares constant-velocity track through ``fixes`` (each with its covariance), or None
    when any fix lies off it by more than the gate (squared Mahalanobis ``gate_chi2``) or its speed is beyond
    ``max_speed_m_s``: fixes that do not tell one story start no filter."""
    if len(fixes) < 2:
        return None
    fit = _offset_and_rate(fixes, np.zeros((len(fixes), 2)), gate_chi2)
    if fit is None:
        return None
    x, cov = fit
    if float(np.linalg.norm(x[2:])) > max_speed_m_s:
        return None
    return Track(float(fixes[-1].t_s), x[:2], x[2:], cov[:2, :2], cov[2:, 2:])


def offset_from_dead_reckoning(fixes: list[Fix], dr_ne_m: np.ndarray, cov_v_ne: np.ndarray, gate_chi2: float,
                               shared_sigma_m: float = 0.0) -> np.ndarray | None:
    """How far a lost filter's dead reckoning is off (north, east, m, at the last fix's time), as a run of ``fixes``
    says it, or None when they do not tell one story. ``dr_ne_m`` (N, 2): the filter's position at each fix's time,
    taken as the fix came (no fix fused in between: the IMU alone).

    Lost, the filter is off by an offset that drifts with its velocity error, so each fix less the dead reckoning
    says ``d_i = b + u (t_i - t_last)``: ``b`` the offset, ``u`` the velocity error, a priori N(0, ``cov_v_ne``)
    (the filter's own velocity covariance). Weighted least squares for both (:func:`_offset_and_rate`, as
    :func:`track_through` fits a track); None if a fix lies off the fit by more than the gate (squared Mahalanobis
    ``gate_chi2``) or ``u`` is beyond the gate of its prior. Each fix's covariance is taken with ``shared_sigma_m``
    added (the error fixes share, the filter's ``fix_bias_sigma_m``: the map's errors, which change as the view
    moves over it, frame to frame). Unlike a constant-velocity track (for a start without a filter), this holds
    through the vehicle's own turns, braking and descent, which the IMU has followed."""
    if len(fixes) < 2:
        return None
    try:
        info_u = np.linalg.inv(np.asarray(cov_v_ne, float))
    except np.linalg.LinAlgError:
        return None
    fit = _offset_and_rate(fixes, np.asarray(dr_ne_m, float), gate_chi2, info_u, shared_sigma_m)
    if fit is None or float(fit[0][2:] @ info_u @ fit[0][2:]) > gate_chi2:
        return None
    return fit[0][:2]


def prior_map_detector(cfg: PipelineConfig) -> FeatureDetector:
    """The flight's own detector, for maps made before the flight (``auxgps map build --orthophoto``): their
    descriptors are then the ones a frame is matched with."""
    return FeatureDetector(cfg.detector)


class Estimator:
    """auxgps's decisions from events. ``landmarks`` and ``frame``: a map to start from (with its local frame),
    or a local frame alone (an empty map about a known origin); without a frame, GPS1's first 3D fix anchors one."""

    def __init__(self, cfg: PipelineConfig, options: EstimatorOptions | None = None, *, landmarks: LandmarkMap | None = None,
                 frame: LocalFrame | None = None, stopwatch=None) -> None:
        if landmarks is not None and frame is None:
            raise ValueError("a map needs its local frame")
        self.cfg = cfg
        self.options = options or EstimatorOptions()
        self.stopwatch = stopwatch if stopwatch is not None else null_stopwatch
        self.camera = camera_from_config(cfg.camera)
        m = cfg.mount
        self.R_body_cam = R_body_cam_from_mount(*np.deg2rad([m.roll_deg, m.pitch_deg, m.yaw_deg]))
        self.frame = frame
        self.landmarks = landmarks if landmarks is not None else LandmarkMap()
        self.detector = FeatureDetector(cfg.detector)
        self.mapper = Mapper(cfg, self.camera, self.R_body_cam, self.landmarks, self.stopwatch)
        self.localiser = Localiser(cfg, self.camera, self.R_body_cam, self.landmarks, self.stopwatch)
        pos = cfg.positioning
        self.flow = InlierFlow(pos.follow_window_px, pos.follow_levels, pos.follow_max_fb_px, pos.follow_max_points)  # the last fix's inliers
        self.supervisor = Supervisor(self.options.supervisor)
        self.heading = HeadingTracker(cfg.heading) if cfg.heading.solve else None
        self._map_turned_to: float | None = None  # the heading error the map was last geotagged again with
        # What the heading solver knew when the map was made, at most every half second of mapping frames (a few kB
        # an hour): times, and (its estimate if the heading is off, that estimate's one sigma, the correction taken
        # out), rad. See _map_heading_sigma_m.
        self._mapped_t_s: list[float] = []
        self._mapped_heading: list[tuple[float, float, float]] = []
        self._mapped_frame_t_s = -np.inf  # when the last frame to be mapped was taken (mapping.min_interval_s)
        # The RMS distance of a point of the footprint from its centre, per metre of height (a camera constant).
        cam = self.camera
        self._footprint_rms_per_m = float(np.sqrt((cam.width_px**2 + cam.height_px**2) / 12.0)) / cam.focal_px
        self.landmarks.keep_journal(self.supervisor.cfg.undo_span_s)
        self._undo_found_at_s: float | None = None  # GPS1 found dragged by the gate: the map is to be undone
        self.filter: NavFilter | None = None
        self._attitudes: deque[Attitude] = deque(maxlen=200)
        # Home's height above the origin: 0 for an origin found below GPS1's first fix, and taken as 0 for a loaded
        # map's (the vehicle arms where it mapped from).
        self._home_above_origin_m: float | None = 0.0 if frame is not None else None
        self._alt_above_home_m: float | None = None
        self._gps1_sats: int | None = None
        self.last_correction_t_s: float | None = None
        self._last_disagreement: str | None = None
        self._map_loaded = landmarks is not None and len(landmarks) > 0  # not yet checked against GPS1
        # The placement error of the prior maps (orthophotos) loaded, the largest: the filter's offset state for them.
        self._map_offset_sigma_m = max((src.georef_sigma_h_m for src in self.landmarks.sources[1:]), default=0.0)
        self._acquiring: list[Fix] = []  # fixes located without a prior, while there is no filter
        # Fixes held back while the filter is lost, each with the filter's dead reckoning at its time (see _held_back)
        self._reacquiring: list[tuple[Fix, np.ndarray]] = []
        self.frame_check = FrameCheck()
        self._last_t_of: dict[type, float] = {}  # the newest time of each telemetry kind (duplicates, order)
        self._telemetry_fault_t: dict[str, float] = {}  # fault -> when last seen, for one events line per episode
        # (value, since when, vertical speed then) of the latest height; and whether it now repeats while the vehicle
        # was climbing or descending when it came (a height that cannot be right: not fused, frames take the filter's)
        self._height_same_since: tuple[float, float, float] | None = None
        self._height_suspect = False
        self._attitude_lost = False
        self._pending_note: str | None = None  # said with the next finished frame
        self._frame_fault: str | None = None  # the camera fault in force (its kind), for the events log
        self._featureless = False  # frames have had too few features to locate from (water, a bare field)
        self._featureless_flip_t_s: float | None = None  # since when frames have said otherwise
        self._ambiguous: AmbiguousView | None = None  # the last frame that found its ground ambiguous

    # -- telemetry -----------------------------------------------------------------------------------------

    def feed(self, event) -> str | None:
        """Take one telemetry record; return a line for the events log when it says something new (a GPS1
        disagreement, a telemetry fault beginning), else None. Records of other kinds are ignored.

        A record with the same kind and time as the newest of its kind is a duplicate (dropped); an IMU sample
        older than the newest cannot be integrated (dropped); either is said once per episode."""
        kind = type(event)
        if kind not in (Imu, Attitude, Position, Gps1):
            return None
        t_last = self._last_t_of.get(kind)
        if t_last is not None and event.t_s == t_last and kind is not Gps1:
            # (GPS1 is exempt: ArduPilot re-sends its last fix, with that fix's time, until a new one comes.)
            return self._telemetry_fault("duplicated telemetry: repeats dropped", event.t_s)
        if kind is Imu and t_last is not None and event.t_s < t_last:
            return self._telemetry_fault("telemetry out of time order: late IMU samples dropped", event.t_s)
        self._last_t_of[kind] = max(event.t_s, t_last if t_last is not None else -np.inf)
        if kind is Imu:
            self._on_imu(event)
        elif kind is Attitude:
            atts = self._attitudes
            if atts and event.t_s < atts[-1].t_s:  # out of time order (a clock step): kept in order
                if len(atts) == atts.maxlen:
                    atts.popleft()
                atts.insert(bisect.bisect_right(atts, event.t_s, key=lambda a: a.t_s), event)
            else:
                atts.append(event)
        elif kind is Position:
            return self._on_position(event)
        else:
            return self._on_gps1(event)
        return None

    def _telemetry_fault(self, what: str, t_s: float, episode_gap_s: float = 5.0) -> str | None:
        """``what`` for the events log when it begins an episode (not seen for ``episode_gap_s``), else None."""
        last = self._telemetry_fault_t.get(what)
        self._telemetry_fault_t[what] = t_s
        return what if last is None or abs(t_s - last) > episode_gap_s else None

    @property
    def alt_above_origin_m(self) -> float | None:
        """The latest height above the local origin, m (None before a height and an origin are known); the
        filter's own while the autopilot's is stuck (repeating while the vehicle climbs or descends)."""
        if self._alt_above_home_m is None or self._home_above_origin_m is None:
            return None
        if self._height_suspect and self.filter is not None:
            return -float(self.filter.estimate().p_ned_m[2])
        return self._alt_above_home_m + self._home_above_origin_m

    def _on_imu(self, rec: Imu) -> None:
        # Without a recent attitude, a sample cannot be rotated into NED: it is not integrated, and the filter
        # crosses the gap at constant velocity with its covariance loosened when samples are usable again.
        if self.filter is None or not self._attitudes:
            return
        att = self._nearest_attitude(rec.t_s)
        if abs(att.t_s - rec.t_s) <= self.options.max_attitude_age_s:
            self.filter.propagate(ImuSample(rec.t_s, rec.f_body_m_s2, self._R_ned_body(att.euler_rad, self._heading_at(rec.t_s))))

    def _attitude_age_s(self, t_s: float) -> float:
        """How far the nearest attitude sample is from ``t_s``, s (inf without one)."""
        return abs(self._nearest_attitude(t_s).t_s - t_s) if self._attitudes else np.inf

    def _on_position(self, rec: Position) -> str | None:
        if not np.isfinite(rec.alt_above_home_m):
            return None
        same = self._height_same_since
        if same is not None and rec.alt_above_home_m == same[0]:
            # The autopilot's height is its EKF's, which holds one value to the millimetre in a steady hover: a
            # repeat is a fault only when the vehicle was climbing or descending as the value came (0.3 m/s is 6 mm
            # between two messages at 50 Hz). Judged on the speed then, not now: a stuck height fused for a second
            # would have slowed the filter's own vertical speed below the threshold, and the fault would pass.
            if abs(same[2]) > self.options.height_stuck_min_vd_m_s:
                self._height_suspect = True
                if rec.t_s - same[1] >= self.options.height_stuck_s:
                    return self._telemetry_fault(f"height above home stuck at {same[0]:.2f} m for "
                                                 f"{self.options.height_stuck_s:g} s: not fused", rec.t_s)
                return None
        else:
            vd = float(self.filter.estimate().v_ned_m_s[2]) if self.filter is not None else 0.0
            self._height_same_since = (rec.alt_above_home_m, rec.t_s, vd)
            self._height_suspect = False
        self._alt_above_home_m = rec.alt_above_home_m
        alt = self.alt_above_origin_m
        if self.filter is not None and alt is not None:
            self.filter.update_altitude(rec.t_s, alt, self.cfg.noise.altitude_m)
        return None

    def _on_gps1(self, rec: Gps1) -> str | None:
        if self.frame is None:
            # No map: anchor the local frame at the first 3D fix, on the ground below it (the autopilot's height
            # above home says how far up it is). Not at the autopilot's own position: before its EKF has an
            # origin, GLOBAL_POSITION_INT's altitude reads 0.
            if rec.fix_type < 3 or self._alt_above_home_m is None or not np.isfinite([rec.lat_deg, rec.lon_deg, rec.alt_amsl_m]).all():
                return None
            self.frame = LocalFrame(rec.lat_deg, rec.lon_deg, rec.alt_amsl_m - self._alt_above_home_m)
            self._home_above_origin_m = 0.0
        p = self.frame.to_ned(lat_deg=rec.lat_deg, lon_deg=rec.lon_deg, alt_amsl_m=rec.alt_amsl_m)
        refused = None
        if self._map_loaded and rec.fix_type >= 3 and np.all(np.isfinite(p)):
            self._map_loaded = False  # checked once, at GPS1's first 3D fix
            p_lm = self.landmarks.p_ned_m[: len(self.landmarks), :2]
            d_m = float(np.hypot(*np.maximum(np.maximum(p_lm.min(axis=0) - p[:2], p[:2] - p_lm.max(axis=0)), 0.0)))
            if d_m > self.options.max_map_distance_m and self.filter is None:
                refused = (f"map refused: it ends {d_m / 1000:.1f} km from GPS1 (more than "
                           f"{self.options.max_map_distance_m / 1000:g} km), a map of somewhere else; mapping afresh")
                self.landmarks.clear()
                self._map_offset_sigma_m = 0.0
                self.frame = None
                return self._on_gps1(rec) or refused
            # Home's height above a prior map's origin (its orthophoto's centre, not where the vehicle takes off):
            # the ground the map has under GPS1. A map a flight made is anchored below its own home (0).
            near = np.flatnonzero(np.hypot(p_lm[:, 0] - p[0], p_lm[:, 1] - p[1]) <= self.options.home_ground_radius_m)
            if len(near) >= 3 and not np.any(self.landmarks.source[: len(self.landmarks)] == 0):
                self._home_above_origin_m = -float(np.median(self.landmarks.p_ned_m[near, 2]))
        t_meas = rec.t_s - self.options.gps1_lag_s  # when the receiver measured it
        est = self.filter.estimate_at(t_meas) if self.filter is not None else None
        sup = self.supervisor
        sup.gps1(Gps1Sample(t_meas, rec.fix_type, rec.satellites, p, rec.h_acc_m),
                 est.p_ned_m if est is not None else None, est.cov_p_m2[:2, :2] if est is not None else None)
        # Said as a disagreement begins, not at every report while it lasts (the distance changes at each one).
        note = sup.disagreement if sup.disagreement and self._last_disagreement is None else None
        self._last_disagreement = sup.disagreement
        if not sup.gps1_trusted:
            self._gps1_sats = None
            return note
        self._gps1_sats = rec.satellites
        sigma = max(rec.h_acc_m, self.cfg.noise.gps_horizontal_m)
        if self.filter is None:
            self.filter = NavFilter(self.cfg.fusion, t_meas, p, np.zeros(3), sigma, 1.0, self._map_offset_sigma_m)
        else:
            # Just trusted (again), the filter may be put onto GPS1; once GPS1 has been mapped from, a run of its
            # reports the filter's gate rejects is a jump or a fast drag, and the map knows better than GPS1 where
            # the vehicle is.
            settled = len(self.landmarks) > 0 and sup.trusted_since_s is not None and t_meas - sup.trusted_since_s >= sup.cfg.rejoin_s
            decision = self.filter.update_position(t_meas, p[:2], np.eye(2) * sigma**2, reinit=not settled)
            if decision.rejected_run and settled:
                self._gps1_sats = None
                line = sup.gps1_rejected(t_meas, float(np.linalg.norm(p[:2] - est.p_ned_m[:2])))
                if line:
                    # Undone by the next finish_frame: the thread that maps (a companion's telemetry arrives on
                    # another), and after the frame in hand, which may have mapped from this GPS1 already.
                    self._undo_found_at_s = t_meas
                return _joined(note, line)
        self.last_correction_t_s = t_meas
        return note

    def _nearest_attitude(self, t_s: float) -> Attitude:
        """The attitude sample nearest to ``t_s`` (the earlier of two as near). Samples are kept in time order."""
        atts = self._attitudes
        k = bisect.bisect_left(atts, t_s, key=lambda a: a.t_s)
        if k == len(atts) or (k > 0 and t_s - atts[k - 1].t_s <= atts[k].t_s - t_s):
            k -= 1
        return atts[k]

    def _attitudes_around(self, t_s: float) -> tuple[Attitude, Attitude] | None:
        """The samples just before and at or after ``t_s``, when both exist and are at most
        ``2 * max_attitude_age_s`` apart (the span an attitude is interpolated across); else None."""
        atts = self._attitudes
        k = bisect.bisect_left(atts, t_s, key=lambda a: a.t_s)
        if 0 < k < len(atts) and 0.0 < atts[k].t_s - atts[k - 1].t_s <= 2.0 * self.options.max_attitude_age_s:
            return atts[k - 1], atts[k]
        return None

    def _attitude_at(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The attitude at ``t_s`` (ZYX Euler, rad) and the body's turn rate then (rad/s, NED axes).

        Between two samples at most ``2 * max_attitude_age_s`` apart, interpolated; past the newest (a frame
        comes before the attitude after it), the newest turned on at its own body rates for up to
        ``max_attitude_age_s``; else the nearest sample. The rate is the nearest sample's own (the autopilot's
        gyros, not a difference of two attitudes, whose noise would pass for a turn); zero without one."""
        near = self._nearest_attitude(t_s)
        around = self._attitudes_around(t_s)
        rate_body = near.rate_body_rad_s if near.rate_body_rad_s is not None else np.zeros(3)
        if around is not None:
            a, b = around
            euler = attitude_between(t_s, a.t_s, a.euler_rad, b.t_s, b.euler_rad)
        elif t_s > near.t_s:
            euler = attitude_turned(near.euler_rad, rate_body, min(t_s - near.t_s, self.options.max_attitude_age_s))
        else:
            euler = near.euler_rad
        return euler, R_ned_body_from_euler(*euler) @ rate_body

    def _attitude_step_rad(self, t_s: float) -> float:
        """How far the tilt of the attitude sample after ``t_s`` is from the one before it turned on at their gyro
        rates, rad: a change the rates do not explain (a vehicle jolted, a message lost between them), so the frame's
        tilt between the two is not known to the telemetry's noise. 0 without two samples about ``t_s`` with rates."""
        around = self._attitudes_around(t_s)
        if around is None or around[0].rate_body_rad_s is None or around[1].rate_body_rad_s is None:
            return 0.0
        a, b = around
        dt_s = b.t_s - a.t_s
        carried = attitude_turned(a.euler_rad, 0.5 * (a.rate_body_rad_s + b.rate_body_rad_s), dt_s)
        R = R_ned_body_from_euler(*carried).T @ R_ned_body_from_euler(*b.euler_rad)  # the rest of the turn, body axes
        return float(np.hypot(R[2, 1] - R[1, 2], R[0, 2] - R[2, 0]) / 2.0)  # its roll and pitch parts (small angles)

    def _attitude_stepped(self, t_s: float) -> str | None:
        """Why a frame at ``t_s`` is not used because its attitude is unknown between two samples, or None.

        Two samples each off by ``noise.attitude_deg`` differ by up to 3 sqrt(2) times that without a cause;
        beyond, the frame's tilt could be either sample's (a 1.7 deg error is 0.45 m on the ground from 15 m, at
        any inlier count: the busy emulator flight whose copter's tilt stepped 3.65 deg in 20 ms made such a fix)."""
        step_deg = float(np.rad2deg(self._attitude_step_rad(t_s)))
        limit_deg = 3.0 * np.sqrt(2.0) * self.cfg.noise.attitude_deg
        if step_deg <= limit_deg:
            return None
        return (f"the attitude stepped {step_deg:.1f} deg between the telemetry samples around the frame, beyond their "
                f"gyro rates and their noise ({limit_deg:.2f} deg): its tilt is unknown; not used")

    def _attitude_sigmas(self, job: FrameJob) -> dict[str, float]:
        """How far a frame's attitude may be off, one sigma, rad (``tilt_sigma_rad``, ``heading_sigma_rad``): the
        telemetry's own noise, the heading solver's uncertainty, and what the frame's timestamp uncertainty
        (``noise.frame_time_s``) makes of the body's turn rate: turning at 60 deg/s, 20 ms is 1.2 deg, 0.2 m on
        the ground 10 m from the camera."""
        noise = self.cfg.noise
        rate = job.rate_ned_rad_s
        tilt = np.hypot(np.deg2rad(noise.attitude_deg), np.hypot(rate[0], rate[1]) * self._frame_time_s(job.frame))
        heading_var = self._heading_noise_var(job)
        if job.heading is not None:
            heading_var += job.heading.sigma_rad**2
        return {"tilt_sigma_rad": float(tilt), "heading_sigma_rad": float(np.sqrt(heading_var))}

    def _frame_time_s(self, frame: Frame) -> float:
        """How far the frame's timestamp may be from the autopilot's clock, one sigma, s."""
        return self.cfg.noise.frame_time_s if frame.time_sigma_s is None else frame.time_sigma_s

    def _turning_too_fast(self, frame: Frame, rate_ned_rad_s: np.ndarray) -> str | None:
        """Why a frame taken turning at ``rate_ned_rad_s`` is not located, or None. Past ``noise.heading_deg /
        noise.frame_time_s`` (25 deg/s) the frame's timing makes its heading less certain than the telemetry's
        noise does, and that error is the same for every frame of the turn (a camera's latency, a starved reader):
        their fixes, each honest alone, would pull the filter together. A copter turns to its next leg at 45 to
        70 deg/s for a second or two; the IMU carries it through. Mapping frames are mapped (their rays less
        trusted): GPS1 places them."""
        heading_deg = self.cfg.noise.heading_deg
        rate_deg_s = abs(float(np.rad2deg(rate_ned_rad_s[2])))
        dt_s = self._frame_time_s(frame)
        if rate_deg_s * dt_s <= heading_deg:
            return None
        return (f"turning at {rate_deg_s:.0f} deg/s: the frame's timing ({dt_s * 1e3:g} ms) leaves its heading "
                f"{rate_deg_s * dt_s:.1f} deg uncertain, more than the telemetry's {heading_deg:g}; not located")

    def _heading_noise_var(self, job: FrameJob) -> float:
        """The frame's heading noise, rad^2: the telemetry's, and what the frame's timing makes of the turn rate
        (what differs from frame to frame; the heading solver's uncertainty is not in it)."""
        return float(np.deg2rad(self.cfg.noise.heading_deg) ** 2 + self._timing_heading_var(job))

    def _timing_heading_var(self, job: FrameJob) -> float:
        """What the frame's timestamp uncertainty makes of the heading's turn rate, rad^2."""
        return float((job.rate_ned_rad_s[2] * self._frame_time_s(job.frame)) ** 2)

    def _heading_at(self, t_s: float) -> HeadingEstimate | None:
        return self.heading.at(t_s) if self.heading is not None else None

    @staticmethod
    def _R_ned_body(euler_rad: np.ndarray, heading: HeadingEstimate | None) -> np.ndarray:
        """The attitude with the autopilot's heading error taken out."""
        roll, pitch, yaw = euler_rad
        return R_ned_body_from_euler(roll, pitch, yaw - (heading.offset_rad if heading is not None else 0.0))

    # -- frames --------------------------------------------------------------------------------------------

    def begin_frame(self, frame: Frame) -> FrameJob | FrameResult:
        """What the estimator knows at the frame's capture time; a "skipped" result when it cannot use the frame,
        a "none" one when its attitude is missing."""
        alt = self.alt_above_origin_m
        rate = self.frame_check.rate_note(frame.t_s)
        if rate:
            self._pending_note = _joined(self._pending_note, rate)
        age = self._attitude_age_s(frame.t_s)
        if self._attitudes and age > self.options.max_attitude_age_s:
            note = None if self._attitude_lost else "attitude stream stopped: no fix until it is back"
            self._attitude_lost = True
            return FrameResult(frame.t_s, "none", f"no attitude within {self.options.max_attitude_age_s:g} s of the frame "
                               f"(nearest {age:.1f} s away)", note=note)
        if self._attitude_lost and self._attitudes:
            self._attitude_lost = False
            self._pending_note = _joined(self._pending_note, "attitude stream back")
        heading = self._heading_at(frame.t_s)
        if not self._attitudes or alt is None or (self.filter is None and (not len(self.landmarks) or self.supervisor.gps1_trusted)):
            missing = "filter (no GPS1 fix yet)" if self.filter is None else "attitude" if not self._attitudes else "height"
            return FrameResult(frame.t_s, "skipped", f"no {missing}")
        stepped = self._attitude_stepped(frame.t_s)
        if stepped is not None:
            return FrameResult(frame.t_s, "none", stepped)
        euler, rate_ned = self._attitude_at(frame.t_s)
        R = self._R_ned_body(euler, heading)
        turning = None if self.supervisor.gps1_trusted else self._turning_too_fast(frame, rate_ned)
        if turning is not None:
            return FrameResult(frame.t_s, "none", turning)
        if self.filter is None:
            # No filter, no GPS1, a map: locate without a prior, to start the filter (acquisition)
            return FrameJob(frame, R, alt, None, False, None, heading=heading, rate_ned_rad_s=rate_ned)
        mapping = self.supervisor.gps1_trusted
        if mapping:
            since_s = frame.t_s - self._mapped_frame_t_s
            if 0.0 <= since_s < self.cfg.mapping.min_interval_s:
                return FrameResult(frame.t_s, "skipped", f"not mapped: {since_s:.3f} s after the last mapped frame")
            self._mapped_frame_t_s = frame.t_s
        # Where GPS1 puts the camera at the frame's time: the filter, which fuses GPS1 at its measurement time with
        # the IMU, interpolates between GPS1's readings and carries its lag.
        est = self.filter.estimate_at(frame.t_s)
        p_gps = est.p_ned_m if mapping else None
        return FrameJob(frame, R, alt, PositionPrior(est.p_ned_m, est.sigma_h_worst_m), mapping, p_gps,
                        float(np.hypot(est.v_ned_m_s[0], est.v_ned_m_s[1])), heading, rate_ned)

    def _check_frame(self, job: FrameJob, grey: np.ndarray) -> tuple[str | None, str | None]:
        """The frame's fault (None: fit to locate from) and a line for the events log when a fault begins or ends
        or the frame rate falls."""
        t = job.frame.t_s
        # The image's apparent speed at its centre, px/s (None: unknown, no filter)
        gsd_m = max(job.alt_above_origin_m, 1.0) / self.camera.focal_px
        px_per_s = job.speed_h_m_s / gsd_m if job.speed_h_m_s is not None else None
        fault = self.frame_check.check(t, grey, px_per_s)
        # The fault's kind, without its figures: a strap sliding over the lens is one fault, not one a frame
        kind = " ".join(w for w in fault.split(":")[0].split(" (")[0].split() if not any(c.isdigit() for c in w)) if fault else None
        note = None
        if kind != self._frame_fault:
            note = f"camera fault: {fault}; no fix from such frames" if fault else f"camera fault over ({self._frame_fault})"
            self._frame_fault = kind
        return fault, note

    #: Frames must say the ground has turned featureless (or textured again) this long before the events log does:
    #: over a cube world's plain ground the count hovers about the limit, and each line is a STATUSTEXT too.
    FEATURELESS_HOLD_S = 1.0

    def _featureless_note(self, t_s: float, n_features: int) -> str | None:
        """A line for the events log when frames begin or stop having too few features to locate from, for
        :attr:`FEATURELESS_HOLD_S` at least."""
        least = self.cfg.positioning.min_inliers
        if (n_features < least) == self._featureless:
            self._featureless_flip_t_s = None
            return None
        if self._featureless_flip_t_s is None:
            self._featureless_flip_t_s = t_s
        if t_s - self._featureless_flip_t_s < self.FEATURELESS_HOLD_S:
            return None
        self._featureless, self._featureless_flip_t_s = not self._featureless, None
        if self._featureless:
            return f"featureless ground: {n_features} features, fewer than {least}; no fix from such frames"
        return f"featureless ground over ({n_features} features)"

    def process_frame(self, job: FrameJob) -> FrameWork:
        """Check the frame, detect, then map (while GPS1 is trusted) and locate. Reads and changes only the map,
        the frame and the frame check's memory."""
        sw = self.stopwatch
        with sw("checking"):
            grey = to_gray(job.frame.image_bgr)  # once for the check and the detector; a malformed frame is named here
            fault, note = self._check_frame(job, grey)
        if fault is not None or job.mapping:
            self.flow.forget()
        elif self._may_follow(job):
            followed = self._follow(job, grey, note)
            if followed is not None:
                return followed
        if fault is not None:
            nothing = Features(np.zeros((0, 2)), np.zeros((0, self.landmarks.descriptors.shape[1]), np.uint8), np.zeros(0, int))
            return FrameWork(job, nothing, None, NoFix(job.frame.t_s, fault), note)
        # Mapping frames keep full resolution; positioning frames from closer than the map are shrunk to its
        # scale. A positioning frame looks its candidate landmarks up once. A mapping frame is checked before it is
        # mapped, on landmarks first geotagged self_check_age_s before it: never on those it or the frames just
        # before added (over new ground they carry whatever drag GPS1 has now, and would agree with it).
        with sw("matching"):
            old_enough_s = job.frame.t_s - self.supervisor.cfg.self_check_age_s if job.mapping else None
            cand = self.localiser.candidates(job.alt_above_origin_m, job.prior, old_enough_s)
        # The flight's own landmarks and a prior map's are not mixed in one reading (the prior map's are metres off
        # together, the flight's centimetres): its own first, the prior map's where its own give no fix.
        prior_cand = cand[self.landmarks.source[cand] != 0]
        if len(prior_cand):
            cand = cand[self.landmarks.source[cand] == 0]
        scale = 1.0 if job.mapping else self.localiser.detection_scale(job.alt_above_origin_m, job.prior, cand if len(cand) else prior_cand)
        R_ned_cam = job.R_ned_body @ self.R_body_cam
        with sw("detection"):
            feats = self.detector.detect(grey, R_ned_cam, scale)
        note = _joined(note, self._featureless_note(job.frame.t_s, len(feats)))
        mapped = None
        sigmas = self._attitude_sigmas(job)
        # The self-check, which judges GPS1 by the map, locates on features near nadir only (see
        # DetectorConfig.max_off_nadir_deg); the mapper and positioning take every feature.
        locating = near_nadir(feats, self.camera, R_ned_cam, self.cfg.detector.max_off_nadir_deg) if job.mapping else feats
        with sw("locating"):
            located = self.localiser.locate(locating, job.frame.t_s, job.R_ned_body, job.alt_above_origin_m, job.prior, cand, **sigmas) \
                if len(cand) or not len(prior_cand) else None
            if len(prior_cand) and not isinstance(located, Fix):
                prior_scale = 1.0 if job.mapping else self.localiser.detection_scale(job.alt_above_origin_m, job.prior, prior_cand)
                prior_feats = feats
                if abs(np.log(prior_scale / scale)) > np.log(self.cfg.detector.scale_factor):  # another scale: detected again
                    with sw("detection"):
                        prior_feats = self.detector.detect(grey, job.R_ned_body @ self.R_body_cam, prior_scale)
                on_prior = self.localiser.locate(prior_feats, job.frame.t_s, job.R_ned_body, job.alt_above_origin_m, job.prior,
                                                 prior_cand, **sigmas)
                if located is None or isinstance(on_prior, Fix):
                    located = on_prior
        if not job.mapping:
            if isinstance(located, Fix) and self._agrees_with_prior(located, job.prior):
                self.flow.remember(grey, located.inliers)
            else:
                self.flow.forget()
        if job.mapping:
            # The mapper takes the tilt's sigma for the direction of every ray, and the heading's across it, where a
            # turn moves the ray's far end: the telemetry's noise and the frame's timing's, which differ from view to
            # view. Not the heading solver's uncertainty: one error for every view of the moment, it turns the map's
            # part seen then as a whole, and counted per view it widened the landmarks beside the track (the
            # textured world at 15 m, landmark RMS 0.084 -> 0.135 m).
            heading_noise = float(np.sqrt(self._heading_noise_var(job)))
            with sw("mapping"):
                retag = self.cfg.heading.follow_s > 0  # keep what turning the views again needs
                mapped = self.mapper.process(feats, NavSample(job.frame.t_s, job.p_gps_ned_m, job.alt_above_origin_m, job.R_ned_body,
                                                              job.heading if retag else None, sigmas["tilt_sigma_rad"],
                                                              heading_noise))
        return FrameWork(job, feats, mapped, located, note)

    def _may_follow(self, job: FrameJob) -> bool:
        """Whether a positioning frame may follow the last fix's inliers instead of being a full one: there are
        some, their full frame was taken less than ``follow_for_s`` before this one, and the filter knows where
        the vehicle is well enough to track (see :meth:`Localiser.locate`)."""
        cfg = self.cfg.positioning
        pairs = self.flow.pairs
        return (pairs is not None and job.prior is not None and 0.0 < job.frame.t_s - pairs.from_full_s < cfg.follow_for_s
                and 3.0 * job.prior.sigma_h_m <= cfg.max_tracking_search_m)

    def _follow(self, job: FrameJob, grey: np.ndarray, note: str | None) -> FrameWork | None:
        """The frame located from the last fix's inliers carried into it by optical flow, each started where the
        prior puts its landmark; None when that gives no fix the prior agrees with (the frame is then a full one)."""
        sw = self.stopwatch
        ids = self.flow.pairs.lm_id
        if np.any(ids >= len(self.landmarks)):  # the map was rolled back under them
            self.flow.forget()
            return None
        with sw("tracking"):
            R_ned_cam = job.R_ned_body @ self.R_body_cam
            pose = CameraPose(np.array([job.prior.p_ned_m[0], job.prior.p_ned_m[1], -job.alt_above_origin_m]), R_ned_cam)
            guess_uv, front = pose.project(self.camera, self.landmarks.p_ned_m[ids].astype(float))
            guess_uv[~front] = np.nan
            followed = self.flow.follow(grey, guess_uv)
        with sw("locating"):
            fix = self.localiser.locate_followed(followed, job.frame.t_s, job.R_ned_body, job.alt_above_origin_m,
                                                 **self._attitude_sigmas(job), min_kept=self.cfg.positioning.follow_min_kept)
        if not isinstance(fix, Fix) or not self._agrees_with_prior(fix, job.prior):
            self.flow.forget()
            return None
        self.flow.remember(grey, fix.inliers)
        feats = Features(followed.uv_px, self.landmarks.descriptors[followed.lm_id], np.zeros(len(followed.lm_id), int), followed.scale)
        return FrameWork(job, feats, None, fix, note)

    def _agrees_with_prior(self, fix: Fix, prior: PositionPrior | None) -> bool:
        """Whether ``fix`` is within the filter's gate of ``prior``: only such a fix's inliers are followed into the
        next frames (a fix the filter refuses must not be taken again from its own pairs)."""
        return prior is not None and prior_m2(fix.p_ned_m, fix.cov_ned_m2, prior, self.cfg.positioning.prior_floor_m) <= self.cfg.fusion.gate_chi2

    def finish_frame(self, work: FrameWork) -> FrameResult:
        """Fuse the frame's fix (positioning) or compare it with the filter (mapping)."""
        job, res = work.job, work.located
        t = job.frame.t_s
        note = _joined(self._pending_note, work.note)
        self._pending_note = None
        if self._undo_found_at_s is not None:  # GPS1 found off track by the filter's gate
            note = _joined(note, self._found_dragged(self._undo_found_at_s))
            self._undo_found_at_s = None
        common = dict(mapping=job.mapping, located=res, mapped=work.mapped, features=work.features, note=note)
        if job.mapping and work.mapped is not None:
            if job.heading is not None and (not self._mapped_t_s or t >= self._mapped_t_s[-1] + 0.5):
                off = self.heading.if_off(t)
                self._mapped_t_s.append(t)
                self._mapped_heading.append((off.offset_rad, off.sigma_rad, job.heading.offset_rad))
            self._heading_from_view(job, work)
            if job.heading is not None:
                self._turn_map(t, job.heading.offset_rad)
        if not isinstance(res, Fix):
            if res.rivals_apart_m is not None and not job.mapping and self.filter is not None:
                half_side_m = max(job.alt_above_origin_m, 0.0) * min(self.camera.width_px, self.camera.height_px) / (2.0 * self.camera.focal_px)
                self._ambiguous = AmbiguousView(t, res.rivals_apart_m, self.filter.estimate_at(t).p_ned_m[:2].copy(), half_side_m)
            return FrameResult(t, "none", res.reason, **common)
        if self.filter is None:
            return self._acquire(res, common)
        if self.heading is not None and np.isfinite(res.t_mapped_s):  # the error fixes on that part of the map share
            self.filter.set_map_heading_sigma(self._map_heading_sigma_m(res.t_mapped_s, job.alt_above_origin_m, self.heading.at(t).p_off))
        if job.mapping:
            est = self.filter.estimate_at(res.t_s)
            d_ne = res.p_ned_m[:2] - est.p_ned_m[:2]
            d = float(np.linalg.norm(d_ne))
            # A prior map's fix is off by the map's offset: checked against GPS1 less the offset the filter has
            # learnt so far, within what it does not know of it; and, if GPS1 holds, teaching it more.
            s = res.prior_share
            b_ne, cov_b = self.filter.map_offset()
            shared = np.eye(2) * self.filter.fix_bias_sigma_m**2 + s**2 * cov_b
            drag = self.supervisor.visual_check(res.t_s, d_ne - s * b_ne, res.cov_ned_m2[:2, :2] + est.cov_p_m2[:2, :2], shared)
            if drag:
                common["note"] = _joined(common["note"], drag, self._found_dragged(res.t_s))
            elif s > 0:
                self.filter.learn_map_offset(res.t_s, res.p_ned_m[:2], res.cov_ned_m2[:2, :2], s)
            return FrameResult(t, "self-check", f"{d:.3f} m", self_check_m=d, **common)
        held = self._held_back(res)
        if held is not None:
            return FrameResult(t, "visual", held, decision=GateDecision(res.t_s, False, np.nan, held), **common)
        cov_ne = res.cov_ned_m2[:2, :2]
        if self._in_doubt(t):
            cov_ne = cov_ne + np.eye(2) * self._ambiguous.rivals_apart_m ** 2  # a neighbour frame could not tell two readings this far apart
        with self.stopwatch("filtering"):
            decision = self.filter.update_position(res.t_s, res.p_ned_m[:2], cov_ne, visual=True, prior_share=res.prior_share)
        if decision.accepted:
            self.last_correction_t_s = max(res.t_s, self.last_correction_t_s or -np.inf)
            if self.heading is not None and job.heading is not None and res.heading_turn_rad is not None:
                self.heading.observe_turn(res.t_s, res.heading_turn_rad, res.heading_turn_var_rad2 + self._timing_heading_var(job),
                                          job.heading.offset_rad)
        elif decision.reason.endswith("older than the history"):  # a frame held up longer than the filter remembers
            common["note"] = _joined(common["note"], self._telemetry_fault(
                f"visual fix refused: {decision.reason} ({self.cfg.fusion.history_s:g} s); frames are late", t))
        return FrameResult(t, "visual", decision.reason, decision=decision, **common)

    def _in_doubt(self, t: float) -> bool:
        """Whether the last ambiguous frame still casts doubt on a fix at ``t``: for ``fusion.ambiguity_memory_s``
        after it, and for as long as the camera stays within half its footprint's shorter side of where that frame
        was taken (hovering or descending over it, the ground that looked alike is still what it sees)."""
        amb = self._ambiguous
        if amb is None or t < amb.t_s:
            return False
        if t - amb.t_s <= self.cfg.fusion.ambiguity_memory_s:
            return True
        moved_m = float(np.linalg.norm(self.filter.estimate_at(t).p_ned_m[:2] - amb.p_ne_m))
        return moved_m < 0.5 * amb.half_side_m

    def _held_back(self, fix: Fix) -> str | None:
        """Why ``fix`` is held back from a lost filter (one the supervisor does not believe: GPS_INPUT says no fix),
        or None to fuse it. Lost, the filter's gate is wide, and over alike ground (crop rows a few metres apart) a
        wrong reading passes it: so a fix is fused only once the fixes of the last ``reinit_window_s``, at least
        ``acquisition_fixes`` of them spanning ``reinit_min_span_s``, tell one story with the filter's own dead
        reckoning (:func:`offset_from_dead_reckoning`): one offset, drifting no faster than the filter's velocity
        may be off. A constant-velocity track would refuse the right fixes while the vehicle brakes and descends
        at home (a lake crossed on the way back: 13 s of fixes 0.1 m off held back, to the touchdown)."""
        est = self.filter.estimate_at(fix.t_s)
        lost = not self.supervisor.believes(fix.t_s, sigma_h_worst_m=est.sigma_h_worst_m,
                                            last_correction_t_s=self.last_correction_t_s)  # GPS_INPUT says no fix
        if not lost:
            self._reacquiring = []
            return None
        fusion = self.cfg.fusion
        run = [(f, dr) for f, dr in self._reacquiring if fix.t_s - fusion.reinit_window_s <= f.t_s < fix.t_s]
        run.append((fix, est.p_ned_m[:2].copy()))
        self._reacquiring = run
        span_s = run[-1][0].t_s - run[0][0].t_s
        if (len(run) >= fusion.acquisition_fixes and span_s >= fusion.reinit_min_span_s
                and offset_from_dead_reckoning([f for f, _ in run], np.array([dr for _, dr in run]), est.cov_v_m2_s2[:2, :2],
                                               fusion.gate_chi2, self.filter.fix_bias_sigma_m) is not None):
            self._reacquiring = []
            return None
        return (f"re-acquiring: {len(run)} fixes over {span_s:.1f} s, not yet one story with the dead reckoning over "
                f"{fusion.reinit_min_span_s:g} s")

    def _turn_map(self, t_s: float, b_mapped: float) -> None:
        """Geotag the landmarks mapped lately again with the heading error as solved now, once it has moved
        ``heading.turn_step_deg`` since the last time: the first landmarks of a flight are mapped while the solver
        still knows little, and a map turned by what it then believed stays turned for the return. Lately: within
        ``heading.follow_s`` and ``heading.follow_memory`` of the tracker's memory clock (what a smoother would
        still correct: long while the tracker was unsure, a few seconds once it knows the error)."""
        cfg = self.cfg.heading
        if self.heading is None or cfg.follow_s <= 0:
            return
        now = self.heading.at(t_s)
        b = now.offset_rad
        if self._map_turned_to is None:
            self._map_turned_to = b_mapped  # what the views so far were geotagged with
        since = (t_s - cfg.follow_s, now.memory - cfg.follow_memory)
        with self.stopwatch("mapping"):
            if abs(b - self._map_turned_to) >= np.deg2rad(cfg.turn_step_deg):
                self.landmarks.turn(b, self._map_turned_to, *since)
                self._map_turned_to = b
            else:
                self.landmarks.recent_views.forget_before(*since, lazily=True)

    def _heading_from_view(self, job: FrameJob, work: FrameWork) -> None:
        """Give the heading tracker a mapping frame's view: each landmark the frame fed, its ray put on the ground
        (at the landmark's height) with the telemetry's own heading (the correction in use turned back)."""
        if self.heading is None or job.heading is None or job.p_gps_ned_m is None:
            return
        ids = work.mapped.landmark_ids
        sel = np.flatnonzero(ids >= 0)
        if len(sel) < self.cfg.heading.min_shared:
            return
        c = np.array([job.p_gps_ned_m[0], job.p_gps_ned_m[1], -job.alt_above_origin_m])
        rays = self.camera.pixels_to_rays_cam(work.features.uv_px[sel]) @ (job.R_ned_body @ self.R_body_cam).T
        g = ground_points_ne(c, rays, self.landmarks.p_ned_m[ids[sel], 2].astype(float)) - c[:2]
        a = job.heading.offset_rad  # back to the telemetry's heading: turn by the correction that was taken out
        g = c[:2] + np.column_stack([g[:, 0] * np.cos(a) - g[:, 1] * np.sin(a), g[:, 0] * np.sin(a) + g[:, 1] * np.cos(a)])
        order = np.argsort(ids[sel])
        # What moves every landmark of a pair alike, across: GPS1's error over the interval and the tilt error
        # of each frame's attitude at its height; and the heading's own noise from frame to frame.
        noise = self.cfg.noise
        tilt_m = job.alt_above_origin_m * np.deg2rad(noise.attitude_deg)
        shift_sigma_m = float(np.sqrt(self.cfg.heading.gps_relative_m**2 + 2.0 * tilt_m**2))
        self.heading.observe_view(MotionView(job.frame.t_s, c[:2], ids[sel][order], g[order]), shift_sigma_m,
                                  0.5 * np.deg2rad(noise.heading_deg) ** 2 + self._timing_heading_var(job))

    def _map_heading_sigma_m(self, t_mapped_s: float, alt_above_origin_m: float, p_off_now: float) -> float:
        """What the heading's error left in the landmarks geotagged at ``t_mapped_s``, one sigma per axis, m; the
        same for every fix on them, so shared. A view turned by a heading error puts each of its landmarks off
        across by the turn times its horizontal distance from the camera, taken here as the RMS distance of a point
        of the footprint from its centre at ``alt_above_origin_m``. The turn is the error then less the correction
        taken out then (of the last mapping frame at or before ``t_mapped_s``, else the first's): if the heading
        is off (the solver's estimate then, its sigma then), or right (zero), weighed by the probability the solver
        gives "off" now (``p_off_now``; what it has learnt since says which it was). So over an exact heading
        (the emulator) the first seconds' map, made before the solver knew anything, costs little once it has
        found the heading right. Where the heading wanders 1.5 deg (config/sim/heading_drift.yaml) that map was
        1.2 to 1.7 deg off; without this, a self-check 10 s later (it judges by landmarks that old) said GPS1 had
        drifted 1.0 m, mapping stopped at 18 s and the flight never came home."""
        if not self._mapped_t_s:
            return 0.0
        i = max(bisect.bisect_right(self._mapped_t_s, t_mapped_s) - 1, 0)
        b_rad, sigma_rad, taken_rad = self._mapped_heading[i]
        p = float(np.clip(p_off_now, 0.0, 1.0))
        turn_var_rad2 = p * (sigma_rad**2 + (b_rad - taken_rad) ** 2) + (1.0 - p) * taken_rad**2
        return float(np.sqrt(turn_var_rad2) * max(alt_above_origin_m, 0.0) * self._footprint_rms_per_m)

    def _found_dragged(self, t_s: float) -> str | None:
        """GPS1 found dragged at ``t_s``, by the self-checks or by the filter's gate: the map undone and the filter
        loosened by what it followed, alike either way. The line for the events log."""
        line = self._undo_unverified(t_s)
        self._loosen_by_drag(t_s)
        return line

    def _loosen_by_drag(self, t_s: float) -> None:
        """GPS1 found dragged at ``t_s``: the filter followed it, so it is off by what the self-checks saw (in
        position) and by that over the time since GPS1 last agreed with the map (in velocity). Its covariance is
        widened by as much: GPS_INPUT says so, and the map's fixes bring it back at once, not after a run of
        them rejected by its gate."""
        seen = self.supervisor.drag_seen_ne_m
        if seen is None:
            return
        since = self.supervisor.last_agreement_t_s
        span_s = float(np.clip(t_s - since, 1.0, 30.0)) if since is not None else 30.0
        self.filter.loosen(t_s, np.outer(seen, seen), np.outer(seen, seen) / span_s**2)

    def _undo_unverified(self, t_s: float) -> str | None:
        """GPS1 found dragged at ``t_s``: put the map back as it was when the last agreeing self-check could vouch
        for it. Landmarks geotagged since are taken out of use, older ones seen since get their earlier position
        back (they may carry the drag either way). The line for the events log."""
        since = self.supervisor.unverified_since_s()
        restored, dropped, complete = self.landmarks.roll_back(since)
        if not len(restored) and not len(dropped):
            return None
        span = f"the last {t_s - since:.0f} s" if np.isfinite(since) else "this flight"
        line = f"map of {span} undone: {len(dropped)} landmarks out of use, {len(restored)} put back"
        return line if complete else f"{line} (changes older than {self.supervisor.cfg.undo_span_s:g} s stay)"

    def _acquire(self, fix: Fix, common: dict) -> FrameResult:
        """Start the filter on a run of fixes located without a prior that lie on one track."""
        fusion = self.cfg.fusion
        run = [f for f in self._acquiring if f.t_s >= fix.t_s - fusion.reinit_window_s and f.t_s < fix.t_s] + [fix]
        self._acquiring = run[-fusion.acquisition_fixes:]
        track = track_through(self._acquiring, fusion.gate_chi2, fusion.acquisition_max_speed_m_s) \
            if len(self._acquiring) == fusion.acquisition_fixes else None
        if track is None:
            reason = f"acquiring: {len(self._acquiring)} of {fusion.acquisition_fixes} fixes on one track"
            return FrameResult(fix.t_s, "visual", reason, decision=GateDecision(fix.t_s, False, np.nan, reason), **common)
        sigma_p = float(np.sqrt(np.linalg.eigvalsh(track.cov_p_m2).max()))
        sigma_v = float(np.hypot(np.sqrt(np.linalg.eigvalsh(track.cov_v_m2_s2).max()), fusion.reinit_speed_sigma_m_s))
        p = np.array([track.p_ne_m[0], track.p_ne_m[1], -self.alt_above_origin_m])
        self.filter = NavFilter(fusion, track.t_s, p, np.array([track.v_ne_m_s[0], track.v_ne_m_s[1], 0.0]), sigma_p, sigma_v,
                                self._map_offset_sigma_m)
        self._acquiring = []
        self.last_correction_t_s = track.t_s
        reason = f"acquired without a prior on {fusion.acquisition_fixes} fixes: filter started (sigma {sigma_p:.2f} m)"
        return FrameResult(fix.t_s, "visual", reason, decision=GateDecision(fix.t_s, True, np.nan, reason), **common)

    def on_frame(self, frame: Frame) -> FrameResult:
        """A frame processed at once: :meth:`begin_frame`, :meth:`process_frame`, :meth:`finish_frame`."""
        job = self.begin_frame(frame)
        if isinstance(job, FrameResult):
            return job
        return self.finish_frame(self.process_frame(job))

    # -- output --------------------------------------------------------------------------------------------

    def output(self, t_s: float, t_unix_s: float) -> Output:
        """What GPS_INPUT says when sent at ``t_s`` (the clock of the events) and ``t_unix_s`` (UTC, for the GPS
        week time): the vehicle ``gps_delay_s`` earlier, with a fix only while auxgps believes it."""
        t_described = t_s - self.options.gps_delay_s
        est = self.filter.estimate_at(t_described) if self.filter is not None else None
        decision = self.supervisor.decide(t_s, sigma_h_worst_m=est.sigma_h_worst_m if est is not None else None,
                                          last_correction_t_s=self.last_correction_t_s)
        if self.frame is None:
            return Output(t_s, t_described, None, decision, est)
        sats = self._gps1_sats if decision.gps1_trusted else None
        gps = gps_output(est, self.frame, t_unix_s - self.options.gps_delay_s, believed=decision.mode != Mode.NO_FIX,
                         gps1_sats=sats, max_sigma_h_m=self.supervisor.cfg.max_sigma_h_m)
        return Output(t_s, t_described, gps, decision, est)
