"""Typed configuration: frozen dataclasses filled from YAML.

Every section is a frozen pydantic dataclass that forbids unknown keys and checks ranges, so a typo or a
negative size is one clear error naming the file and the key (``config/x.yaml: cubes.0.size_m: ...``), never
a silently ignored setting. Angles are degrees in the files and radians inside the package.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import yaml
from pydantic import ConfigDict, Field, TypeAdapter, ValidationError, model_validator
from pydantic.dataclasses import dataclass

from auxgps.errors import ConfigError

_STRICT = ConfigDict(extra="forbid")

Positive = Annotated[float, Field(gt=0)]
NonNegative = Annotated[float, Field(ge=0)]
Probability = Annotated[float, Field(ge=0, le=1)]


@dataclass(config=_STRICT, frozen=True)
class CameraConfig:
    """A pinhole camera: resolution and horizontal field of view, or a full intrinsic matrix.

    ``K`` (3x3, px) overrides ``hfov_deg``; ``dist`` holds OpenCV distortion coefficients (k1 k2 p1 p2 [k3 ...]).
    """

    width_px: Annotated[int, Field(gt=0, le=20000)] = 1280
    height_px: Annotated[int, Field(gt=0, le=20000)] = 720
    hfov_deg: Annotated[float, Field(gt=1, lt=179)] = 90.0
    K: list[list[float]] | None = None
    dist: list[float] = Field(default_factory=list)

    @model_validator(mode="after")
    def _check_matrix(self) -> "CameraConfig":
        if self.K is not None and (len(self.K) != 3 or any(len(row) != 3 for row in self.K)):
            raise ValueError("K must be a 3x3 matrix")
        if len(self.dist) not in (0, 4, 5, 8, 12, 14):
            raise ValueError("dist must hold 0, 4, 5, 8, 12 or 14 OpenCV coefficients")
        return self


@dataclass(config=_STRICT, frozen=True)
class MountConfig:
    """The camera's rotation on the body, relative to straight down with image-up towards the nose."""

    roll_deg: Annotated[float, Field(ge=-180, le=180)] = 0.0
    pitch_deg: Annotated[float, Field(ge=-90, le=90)] = 0.0
    yaw_deg: Annotated[float, Field(ge=-180, le=180)] = 0.0


@dataclass(config=_STRICT, frozen=True)
class DetectorConfig:
    """Feature detector settings (ORB)."""

    kind: Literal["orb"] = "orb"
    n_features: Annotated[int, Field(ge=1, le=100000)] = 600  # at most this many per frame; the cube worlds give far fewer
    fast_threshold: Annotated[int, Field(ge=1, le=255)] = 10
    # Tried first: a frame that fills n_features at this FAST threshold keeps those (its strongest corners, found
    # in less time); one that does not is detected again at the next lower threshold (fast_threshold_rungs), down
    # to fast_threshold. Equal to fast_threshold: one pass.
    fast_threshold_first: Annotated[int, Field(ge=1, le=255)] = 30
    # Thresholds tried, evenly from fast_threshold_first down to fast_threshold (2: those two alone). A frame
    # starts at the one that filled the budget in the frame before.
    fast_threshold_rungs: Annotated[int, Field(ge=2, le=16)] = 3
    n_levels: Annotated[int, Field(ge=1, le=16)] = 2
    scale_factor: Annotated[float, Field(gt=1.0, le=4.0)] = 1.3
    edge_threshold_px: Annotated[int, Field(ge=1, le=200)] = 16
    min_harris: float = 0.0  # keypoints at or below this Harris score lie on edges, not corners
    subpixel_window_px: Annotated[int, Field(ge=0, le=15)] = 2  # half-size of the corner refinement window; 0: off
    north_aligned: bool = True  # descriptors oriented to north with the autopilot's heading, not per keypoint
    # The self-check (a mapping frame located on the map, to judge GPS1 by it) uses only features whose ray is
    # at most this far from straight down (None: all). Far off nadir a tilt error moves a point by the height
    # over cos^2 of its angle, and a multirotor at 8 m/s pitches 15 to 20 deg, so one edge and the corners of a
    # 90 deg lens look out at 50 to 60 deg. Over Seneca at 40 m in the closed loop, self-checks on such points
    # reached 1 to 2 m and stopped mapping as if GPS1 were dragged (docs/missions.md). Mapping and positioning
    # keep every feature: with the limit on them too, a return at 90 m over a map made at 60 m lost a fifth of
    # its fixes, and evaluations moved by more than their noise.
    max_off_nadir_deg: Annotated[float, Field(gt=0.0, lt=90.0)] | None = 45.0

    @model_validator(mode="after")
    def _check_thresholds(self) -> "DetectorConfig":
        if self.fast_threshold_first < self.fast_threshold:
            raise ValueError("fast_threshold_first must not be below fast_threshold")
        return self


@dataclass(config=_STRICT, frozen=True)
class NoiseModelConfig:
    """What the estimator assumes about its inputs (one sigma). Not the simulator's noise."""

    pixel_px: Positive = 1.0
    attitude_deg: Positive = 0.2
    heading_deg: Positive = 0.5
    gps_horizontal_m: Positive = 0.08
    altitude_m: Positive = 0.08
    # A frame's timestamp against the autopilot's attitude clock, s: while the vehicle turns, the attitude taken
    # for the frame is off by the turn rate times this (a camera's latency known to a frame's readout; in SITL the
    # simulator's unstamped truth, read up to 25 ms late).
    frame_time_s: Positive = 0.02


@dataclass(config=_STRICT, frozen=True)
class MappingConfig:
    """Geotagging landmarks while GPS is good."""

    edge_margin_px: Positive = 12.0  # landmarks predicted this far outside the image are still candidates
    # A feature is matched to a landmark within 3 sigma of the landmark's predicted pixel, and never farther
    # than this: a new landmark, placed on the ground with a loose height, may be far off (the top of a 3 m cube
    # from 10 m moves 14 px more than the ground between frames half a metre apart).
    match_radius_px: Positive = 48.0
    max_hamming: Annotated[int, Field(ge=0, le=256)] = 64
    min_seen: Annotated[int, Field(ge=1)] = 11
    gate_chi2: Positive = 9.21  # 99% for 2 degrees of freedom
    max_mean_chi2: Positive = 4.0  # a landmark whose views disagree more (2 expected) is not used to position
    min_found_ratio: Probability = 0.25  # nor one found in fewer of the frames that should have seen it
    initial_height_sigma_m: Positive = 3.0  # a new landmark's height prior about the ground plane
    # A frame taken less than this after the last mapped one is not mapped (nor self-checked): views a thirtieth
    # of a second apart add little but noise their errors share, and min_seen counts frames, not viewpoints. At 30
    # frames a second, mapping every frame made a worse map (docs/benchmark.md, "Following"). At 10 frames a second
    # or fewer it skips none. 0: every frame is mapped (config/pipeline/no_follow.yaml, for comparison).
    min_interval_s: NonNegative = 0.08


@dataclass(config=_STRICT, frozen=True)
class PositioningConfig:
    """Positioning from the map when GPS is lost."""

    max_hamming: Annotated[int, Field(ge=0, le=256)] = 64
    inlier_px: Positive = 4.0
    min_inliers: Annotated[int, Field(ge=2)] = 4
    # Features this close (px at the detection scale) are one spot of the image, and one inlier.
    same_point_px: NonNegative = 1.5
    # A frame is ambiguous when a second distinct reading's log-likelihood (about one unit per inlier) is
    # within this margin of the best one's.
    ambiguity_margin: NonNegative = 3.0
    # Acquisition, without a usable prior: more descriptor candidates, stronger evidence.
    k_best_acquire: Annotated[int, Field(ge=1, le=256)] = 32
    min_inliers_acquire: Annotated[int, Field(ge=2)] = 4
    ambiguity_margin_acquire: NonNegative = 5.0
    min_explained_acquire: Probability = 0.6
    max_seeds: Annotated[int, Field(ge=1)] = 300
    # Past max_seeds correspondences, seeds are added until one of a hypothesis supported by rival_min_share of
    # the best would have been drawn with this probability (the RANSAC bound); 1 takes all max_seeds.
    seed_confidence: Probability = 0.999
    max_tracking_search_m: Positive = 1.5  # a prior looser than this (3 sigma, m) means acquisition
    min_search_radius_m: NonNegative = 1.0
    rival_min_share: Annotated[float, Field(gt=0, le=1)] = 0.3  # readings with less support are not weighed
    max_readings: Annotated[int, Field(ge=1)] = 6  # distinct hypotheses refined and weighed per frame
    prior_floor_m: NonNegative = 0.15  # added in quadrature to the prior's sigma when weighing readings
    footprint_margin_m: NonNegative = 2.0
    # A frame much closer to the ground than the map's views is detected shrunk to their scale, down to this.
    min_detection_scale: Annotated[float, Field(gt=0, le=1)] = 0.2
    # This many of the flight's own usable landmarks in reach, and a prior map's (an orthophoto's) are left out there.
    own_landmarks_take_over: Annotated[int, Field(ge=1)] = 60
    # A positioning frame taken less than this after the last full one (one detected and matched) follows that
    # fix's inliers into itself by optical flow instead (auxgps.core.tracking); 0: every frame is a full one.
    # At 0.08 s, 30 frames a second follow two frames in three, 10 or fewer none (docs/benchmark.md, "Following").
    # config/pipeline/no_follow.yaml turns it and mapping.min_interval_s off, for comparison.
    follow_for_s: NonNegative = 0.08
    # The Lucas-Kanade window and pyramid levels above the image: each point starts where the prior puts its
    # landmark, a few pixels off, so a small window and two levels reach it (a 1280x720 frame's pyramid alone
    # costs 5 ms at 21 px and 3 levels).
    follow_window_px: Annotated[int, Field(ge=5, le=63)] = 11
    follow_levels: Annotated[int, Field(ge=0, le=6)] = 2
    follow_max_points: Annotated[int, Field(ge=4)] = 150  # of a fix's inliers, this many spread over the image are followed
    follow_max_fb_px: Positive = 0.5  # how far the flow run backwards may end from where a point started
    follow_min_kept: Probability = 0.5  # the share of the followed pairs that must stay inliers for a fix


@dataclass(config=_STRICT, frozen=True)
class FusionConfig:
    """The navigation filter that fuses visual fixes with the IMU."""

    accel_noise_m_s2_sqrt_hz: Positive = 0.02
    accel_bias_sigma_m_s2: Positive = 0.2
    # ArduPilot's EKF3 on copters: EK3_ABIAS_P_NSE 0.02 m/s^3 on its 0.012 s step, i.e. 0.02 * sqrt(0.012) = 0.0022
    # m/s^2/sqrt(s). A real accelerometer's bias drifts with temperature; the simulator's is constant, and a filter
    # told so holds the velocity better across leg ends (README, results), which no flight should count on.
    accel_bias_walk_m_s2_sqrt_s: NonNegative = 0.002
    # The autopilot's roll and pitch are off by a tilt that wanders, and the specific force rotated by it leaves g
    # times that tilt of horizontal acceleration (NED): one sigma per axis and its correlation time. ArduCopter
    # SITL's EKF against its truth: 0.12 deg RMS per axis over Seneca at 8 m/s (config/sim/tilt_wander.yaml), 0.06 to
    # 0.23 deg (0.01 to 0.04 m/s^2, 10 s means) over the cube world's survey, changing leg by leg (docs/sitl.md).
    # 0.1 deg kept stop 53's SITL replays honest through gaps, but not a corner where the autopilot's tilt, aided by
    # auxgps alone, fed back (0.4 deg: 0.2 to 0.5 deg kept that replay inside 3 sigma); 0.2 deg lets the emulator's
    # dragged GPS1 pull the map 1.13 m (docs/sitl.md). GPS1 readings do not teach it (they widen the position and
    # velocity by it, but a taught tilt let the filter follow a slowly dragged GPS1 as an acceleration); visual
    # fixes do.
    tilt_error_deg: NonNegative = 0.1
    tilt_error_tau_s: Positive = 10.0
    # The error visual fixes share for seconds (attitude error, map error): one sigma and correlation time.
    fix_bias_sigma_m: Positive = 0.1
    fix_bias_tau_s: Positive = 10.0
    # A prior map's (an orthophoto's) placement error is not one offset: two mosaics of one field from one day
    # differ by a scale and a turn as much as by a shift (docs/prior_maps.md). It changes over this distance flown.
    prior_map_offset_length_m: Positive = 100.0
    # ... which grows with the height (its sources are angles): 0.6 % of it, over fix_bias_sigma_m from 17 m up. At
    # 40 m over the Seneca orthophoto single fixes are 0.26 m RMS (0.65 %): a constant 0.1 m made the filter
    # over-confident there (NEES 3.1) and a self-check of clean GPS1 call it dragged.
    fix_bias_per_height: NonNegative = 0.006
    gate_chi2: Positive = 9.21  # 99% for the 2 degrees of freedom of a horizontal fix
    # A frame found ambiguous (two readings some distance apart) casts doubt on the fixes of the ground around it
    # for this long, and for as long as the camera stays within half its footprint's shorter side of where it was
    # (a descent at home): theirs is widened by that distance (the ground that looks alike is still in view).
    ambiguity_memory_s: NonNegative = 2.0
    # A visual fix whose sigma is over this many times the filter's own sigma of it (both RMS per axis, the fix's
    # widened as above) is not fused: it would take under 1 / (1 + ratio^2) off the filter's variance (a tenth at
    # 3), and it is the fix a wrong timing or a look-alike has moved furthest. When fixes stay wide (a descent onto
    # plain ground, a high flight) the filter's sigma grows until they help again. 0: every fix is offered to the gate.
    # In a busy emulator flight the fixes over 3 times the filter's are a tenth, their sigma 0.46 m median (over
    # 2: a third, 0.08 m median, ordinary fixes; docs/faults.md).
    max_fix_sigma_ratio: NonNegative = 3.0
    history_s: Annotated[float, Field(gt=0, le=5)] = 0.5
    reinit_count: Annotated[int, Field(ge=2)] = 5
    reinit_window_s: Positive = 3.0
    # ... and, visual fixes, span at least this long: consecutive frames fit the same landmarks with the same
    # errors, so at 10 frames a second five rejected fixes in half a second are one piece of evidence, not five
    # (at 2 frames a second a run of five spans 2 s, as before). GPS readings need none: the supervisor reads
    # their run as a jump or a drag of GPS1, and a later finding leaves more of the drag in the map.
    reinit_min_span_s: NonNegative = 1.5
    reinit_speed_sigma_m_s: Positive = 0.5
    # Without GPS1 or a filter (a restart mid-flight), this many fixes located without a prior, within
    # reinit_window_s, start the filter when they lie on one constant-velocity track no faster than the speed.
    acquisition_fixes: Annotated[int, Field(ge=2)] = 3
    acquisition_max_speed_m_s: Positive = 30.0
    max_specific_force_m_s2: Positive = 160.0  # 16 g: what a flight controller's accelerometer can report
    # IMU samples further apart than this (a link outage) are not integrated across the gap: the state is carried
    # at constant velocity, and an unknown acceleration of this one sigma loosens it (5 s: 12.5 m, 5 m/s).
    max_imu_gap_s: Annotated[float, Field(gt=0, le=5)] = 0.25
    imu_gap_accel_sigma_m_s2: Positive = 1.0
    output_rate_hz: Annotated[float, Field(gt=0, le=100)] = 10.0


@dataclass(config=_STRICT, frozen=True)
class HeadingConfig:
    """The autopilot's heading error, solved from the images rather than taken as it comes (auxgps.core.heading).

    ArduCopter SITL's EKF heading was 2 deg off before take-off and -0.5 to +1.5 deg over a mission; the error is
    followed as a first-order Gauss-Markov process of ``sigma_deg`` and ``tau_s``. On by default: a compass-fed
    heading is off by a degree or two on every autopilot, and over real terrain from 40 m that is the difference
    between coming home and a confident wrong position (the Seneca mission on real SITL: landed 0.36 m from home
    solved, 80 m away with an EKF failsafe not solved; docs/missions.md). Where the heading is exact (the
    emulator) the tracker finds that too (``off_prior``) and takes out next to nothing: a correction following its
    measurements' noise had put the Seneca out-and-back at 40 m over its targets (docs/missions.md).
    ``solve: false`` (config/pipeline/heading_unsolved.yaml) takes the autopilot's heading as it comes.
    """

    solve: bool = True
    sigma_deg: Positive = 2.0
    tau_s: Positive = 300.0
    # The probability, before any evidence, that the heading is off (wandering as above) rather than right within
    # the telemetry's noise; the tracker weighs the two (HeadingTracker) and takes out their mixture's estimate.
    off_prior: Annotated[float, Field(gt=0, lt=1)] = 0.5
    # While mapping: each frame is paired with an earlier one at least min_baseline_m away and at most
    # max_pair_gap_s before it, sharing at least min_shared landmarks; GPS1's error over that interval, across it.
    min_baseline_m: Positive = 8.0
    max_pair_gap_s: Positive = 5.0
    min_shared: Annotated[int, Field(ge=3)] = 15
    gps_relative_m: Positive = 0.05
    # A positioning fix's turn against the map is no better than the map's own heading (what mapping solved it to).
    rotation_floor_deg: Positive = 0.3
    # Evidence of one kind (mapping views, positioning turns) within this long of each other counts as one
    # measurement's worth: consecutive frames fit the same landmarks with the same errors (on the CI SITL flight
    # at 20 frames a second, fix errors correlate 0.87 over 1 s and 0.6 over 4 s), so each is weighed by the
    # number of its kind in the last ``decorrelation_s``. Taken as independent, the tracker claimed 0.1 deg while
    # its estimate swung by 2 deg in 40 s over the cube world, and the fixes it turned were 0.21 m RMS, not 0.15.
    decorrelation_s: Positive = 2.0
    gate_chi2: Positive = 9.0  # 3 sigma on the one degree of freedom
    reset_after: Annotated[int, Field(ge=2)] = 10  # refused in a row: the error has jumped, the estimate reopens
    # The landmarks seen lately can be geotagged again with the error as solved now, each time it has moved
    # turn_step_deg (LandmarkMap.turn): the first ones are mapped while the solver knows little. Lately: within
    # follow_s, and within follow_memory of the tracker's memory clock (HeadingTracker.at: a smoother's reach back,
    # long while the tracker is unsure, a few seconds once it knows the error). Off (follow_s 0) by default: over
    # Seneca it helps where the heading is exact (the emulator: fused 0.237 -> 0.19 m RMS at 40 m) and hurts where it
    # is not (a SITL flight replayed: fixes 0.226 -> 0.303 m RMS; config/sim/heading_drift.yaml: less honest), since
    # every view of a landmark is turned to the one estimate of now and loses the average of its views' estimates.
    # config/pipeline/map_follows_heading.yaml turns it on. docs/missions.md.
    follow_s: NonNegative = 0.0
    follow_memory: Positive = 1.0
    turn_step_deg: Positive = 0.02


@dataclass(config=_STRICT, frozen=True)
class PipelineConfig:
    """Everything the estimator needs: camera, mount, detector, noise model, mapping and positioning."""

    camera: CameraConfig = Field(default_factory=CameraConfig)
    mount: MountConfig = Field(default_factory=MountConfig)
    detector: DetectorConfig = Field(default_factory=DetectorConfig)
    noise: NoiseModelConfig = Field(default_factory=NoiseModelConfig)
    mapping: MappingConfig = Field(default_factory=MappingConfig)
    positioning: PositioningConfig = Field(default_factory=PositioningConfig)
    fusion: FusionConfig = Field(default_factory=FusionConfig)
    heading: HeadingConfig = Field(default_factory=HeadingConfig)


@dataclass(config=_STRICT, frozen=True)
class PhotoCameraConfig:
    """A photo camera's intrinsics, for photos of ``width_px`` x ``height_px`` (or any size, when absent).

    Either ``K`` (3x3, full-resolution px), or the focal length and the sensor width (mm): the focal length in
    pixels is ``focal_mm / sensor_width_mm * width``; without ``focal_mm`` the photo's EXIF focal length is used.
    The principal point is the image centre. ``dist``: OpenCV distortion coefficients. Map building refines the
    focal length and two radial terms and stores them in the map.
    """

    focal_mm: Positive | None = None
    sensor_width_mm: Positive | None = None
    width_px: Annotated[int, Field(gt=0, le=100000)] | None = None
    height_px: Annotated[int, Field(gt=0, le=100000)] | None = None
    K: list[list[float]] | None = None
    dist: list[float] = Field(default_factory=list)
    description: str = ""

    @model_validator(mode="after")
    def _check(self) -> "PhotoCameraConfig":
        if self.K is not None and (len(self.K) != 3 or any(len(row) != 3 for row in self.K)):
            raise ValueError("K must be a 3x3 matrix")
        if self.K is None and self.sensor_width_mm is None:
            raise ValueError("give K, or sensor_width_mm (with focal_mm, or the photos' EXIF focal length)")
        if len(self.dist) not in (0, 4, 5, 8, 12, 14):
            raise ValueError("dist must hold 0, 4, 5, 8, 12 or 14 OpenCV coefficients")
        return self


@dataclass(config=_STRICT, frozen=True)
class PhotoMapConfig:
    """Building a landmark map from geotagged photos."""

    ratio: Annotated[float, Field(gt=0, le=1)] = 0.8  # Lowe's ratio test
    min_pair_inliers: Annotated[int, Field(ge=8)] = 40
    pair_ransac_px: Positive = 4.0  # fundamental-matrix inlier distance, full-resolution px
    pixel_sigma_px: Positive = 1.0  # a feature's position noise, full-resolution px (scaled up for large blobs)
    gps_sigma_h_m: Positive = 1.0  # a consumer receiver's horizontal error, per axis
    gps_sigma_floor_m: Positive = 0.5  # the receivers' noise is taken as at least this, however well they agree
    # An offset common to a whole pass, which averaging photos cannot remove: at Brighton Beach the middle pass's GPS
    # sits 0.7 to 1.1 m from where the outer passes' GPS puts the same ground (tools/gps_consistency.py;
    # the figure moves with the focal length the block finds).
    gps_bias_sigma_m: NonNegative = 0.5
    height_sigma_m: Positive = 0.5  # height above take-off (DJI RelativeAltitude)
    # A photo without a height above take-off: its GPS altitude, to this one sigma, holds the block level (the
    # GPS's horizontal positions hardly tell a tilted block from a level one: Seneca's came out 10 degrees off).
    gps_alt_sigma_m: Positive = 5.0
    refine_intrinsics: bool = True  # focal length and two radial distortion terms per camera
    # How well the focal length is known (one sigma, relative) from the camera file, or else from EXIF. Photos of
    # flat ground flown one way can hardly tell it from the ground's height: refined freely, the two outer
    # Brighton Beach passes put it at 2220 px, 5 % under the camera file's 2340 px (and a block of all three
    # passes, the middle one flown the other way, at 2664 px). Held to the camera's value within 2 %, their map
    # puts it at 2321 px and the middle pass 1.23 m from its GPS, against 1.33 m.
    focal_sigma_rel: Positive = 0.02
    max_ba_points: Annotated[int, Field(ge=50)] = 4000
    max_ba_evaluations: Annotated[int, Field(ge=5)] = 100
    init_outlier_sigma: Positive = 20.0  # tracks worse than this with the first-guess poses are left out
    max_point_sigma_m: Positive = 0.5  # a point placed worse than this (horizontal, one sigma) is not kept
    max_heading_disagreement_deg: Positive = 20.0  # metadata further off than this is reported


@dataclass(config=_STRICT, frozen=True)
class PhotoLocateConfig:
    """Locating a photo against a photo map."""

    ratio: Annotated[float, Field(gt=0, le=1)] = 0.8
    min_inliers: Annotated[int, Field(ge=6)] = 30
    min_inlier_share: Probability = 0.1  # of the descriptor matches
    min_inlier_spread: Probability = 0.02  # share of the photo's area the inliers' bounding box covers
    ransac_px: Positive = 3.0  # PnP inlier distance for the smallest features, full-resolution px
    ransac_iterations: Annotated[int, Field(ge=100)] = 5000
    pixel_sigma_px: Positive = 1.0
    max_accuracy_m: Positive = 5.0  # a fix less certain than this (one sigma) is no fix
    max_outside_map_m: NonNegative = 50.0
    max_heading_disagreement_deg: Positive = 20.0


@dataclass(config=_STRICT, frozen=True)
class PhotoConfig:
    """The photo workflow (``auxgps map build`` and ``auxgps locate``)."""

    max_side_px: Annotated[int, Field(ge=0, le=100000)] = 1200  # photos are reduced to this (0: full resolution)
    n_features: Annotated[int, Field(ge=100, le=200000)] = 20000
    # Fewer features than this at SIFT's contrast threshold, and it is lowered once (bare soil, sand, snow).
    min_features: Annotated[int, Field(ge=0, le=200000)] = 2000
    map: PhotoMapConfig = Field(default_factory=PhotoMapConfig)
    locate: PhotoLocateConfig = Field(default_factory=PhotoLocateConfig)


T = TypeVar("T")


def _format_validation_error(path: Path | str, err: ValidationError) -> str:
    parts = []
    for item in err.errors():
        key = ".".join(str(x) for x in item["loc"]) or "(top level)"
        msg = item["msg"]
        if item["type"] in ("extra_forbidden", "unexpected_keyword_argument"):
            msg = "unknown key"
        parts.append(f"{key}: {msg}")
    return f"{path}: " + "; ".join(parts)


def parse_as(cls: type[T], data: Any, source: Path | str) -> T:
    """Validate plain data (from YAML) into ``cls``; raise :class:`ConfigError` naming ``source`` and the key."""
    try:
        return TypeAdapter(cls).validate_python(data if data is not None else {})
    except ValidationError as err:
        raise ConfigError(_format_validation_error(source, err)) from None


def read_yaml(path: Path | str) -> Any:
    """Read one YAML file; a missing or malformed file is a :class:`ConfigError` naming it."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"{path}: cannot read: {err.strerror or err}") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML: {err}".replace("\n", " ")) from None


def load_pipeline_config(path: Path | str | None = None) -> PipelineConfig:
    """Load a pipeline config from YAML, or the defaults when ``path`` is None."""
    if path is None:
        return PipelineConfig()
    return parse_as(PipelineConfig, read_yaml(path), path)


def load_photo_config(path: Path | str | None = None) -> PhotoConfig:
    """Load the photo workflow's settings from YAML, or the defaults when ``path`` is None."""
    if path is None:
        return PhotoConfig()
    return parse_as(PhotoConfig, read_yaml(path), path)


def load_photo_camera(path: Path | str) -> PhotoCameraConfig:
    """Load a photo camera file (``config/cameras/*.yaml``)."""
    return parse_as(PhotoCameraConfig, read_yaml(path), path)
