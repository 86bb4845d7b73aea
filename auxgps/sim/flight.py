"""Simulated survey flights of a multirotor, and the telemetry an autopilot would report along them.

The vehicle is a point mass whose thrust vector it tilts to accelerate: the attitude follows from the commanded
acceleration plus drag (so it tilts when it accelerates, brakes, turns or flies into wind), yaw follows the
survey legs at a limited rate, and gusts push it about. Telemetry is the truth plus configurable white noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

import numpy as np
from pydantic import Field
from pydantic.dataclasses import dataclass as config_dataclass

from auxgps.config import _STRICT, NonNegative, Positive, parse_as, read_yaml
from auxgps.core.geometry import LocalFrame, R_ned_body_from_euler, euler_from_R_ned_body
from auxgps.errors import ConfigError
from auxgps.io.mission import AMSL_FRAMES, M, Mission
from auxgps.sim.faults import Fault
from auxgps.sim.render import SUN_AZIMUTH_DEG, SUN_ELEVATION_DEG, ImageEffects, sun_dir_ned

GRAVITY_M_S2 = 9.80665


@config_dataclass(config=_STRICT, frozen=True)
class SurveyConfig:
    """A lawnmower survey over a rectangle of the local frame (metres, NED)."""

    north_min_m: float = -10.0
    north_max_m: float = 10.0
    east_min_m: float = -10.0
    east_max_m: float = 10.0
    spacing_m: Positive = 2.0
    legs: Literal["ns", "ew"] = "ns"
    offset_m: float = 0.0
    speed_m_s: Positive = 1.0


@config_dataclass(config=_STRICT, frozen=True)
class VehicleConfig:
    """The multirotor model."""

    max_accel_m_s2: Positive = 1.5
    velocity_gain_per_s: Positive = 1.5
    drag_per_s: NonNegative = 0.35
    gust_sigma_m_s2: NonNegative = 0.25
    gust_tau_s: Positive = 2.0
    yaw_rate_deg_s: Positive = 45.0
    wind_north_m_s: float = 0.0
    wind_east_m_s: float = 0.0
    waypoint_radius_m: Positive = 0.2


@config_dataclass(config=_STRICT, frozen=True)
class TelemetryNoiseConfig:
    """One-sigma white noise added to the truth to make telemetry."""

    gps_horizontal_m: NonNegative = 0.05
    gps_vertical_m: NonNegative = 0.10
    altitude_m: NonNegative = 0.05
    attitude_deg: NonNegative = 0.2
    heading_deg: NonNegative = 0.2
    # A compass-aided heading is off by a slowly wandering amount, not only by white noise: ArduCopter SITL's EKF is
    # 2 deg off before take-off and drifts from -0.5 to +1.5 deg over two minutes (tools/sitl_telemetry_error.py,
    # docs/missions.md). One sigma of that error (a first-order Gauss-Markov process, drawn per run) and its
    # correlation time; 0 (the default) leaves it out. config/sim/heading_drift.yaml sets what SITL showed.
    heading_error_deg: NonNegative = 0.0
    heading_error_tau_s: Positive = 60.0
    # So is the tilt (roll and pitch, each its own process): ArduCopter SITL's EKF against its truth wanders by 0.12
    # deg RMS per axis, changing by 0.09 deg RMS over 5 s and 0.12 over 10 s (tools/sitl_telemetry_error.py), as a
    # first-order Gauss-Markov process of 0.09 deg over 7 s would; 0 (the default) leaves it out, the white
    # attitude_deg alone. config/sim/tilt_wander.yaml sets what SITL showed.
    tilt_error_deg: NonNegative = 0.0
    tilt_error_tau_s: Positive = 7.0
    accel_noise_m_s2: NonNegative = 0.1  # per IMU sample
    accel_bias_m_s2: NonNegative = 0.1  # one sigma of the constant bias drawn per run, per axis (body)
    imu_rate_hz: Annotated[float, Field(ge=50, le=1000)] = 100.0
    baro_rate_hz: Positive = 10.0
    gps_rate_hz: Positive = 5.0


@config_dataclass(config=_STRICT, frozen=True)
class ExposureShiftConfig:
    """How far the camera's auto-exposure and white balance have moved once GPS1 is lost, relative to the way out
    (the map): a gain, a gain per channel (B, G, R), and a gamma on the 0..1 image (over 1 darkens mid-tones)."""

    gain: Positive = 1.0
    gain_bgr: tuple[Positive, Positive, Positive] = (1.0, 1.0, 1.0)
    gamma: Positive = 1.0


@config_dataclass(config=_STRICT, frozen=True)
class GlareConfig:
    """The sun's glint off the ground: a soft blob where a flat ground mirrors the sun into the camera, fixed
    relative to the sun's direction (it turns in the image as the vehicle turns). ``strength`` is its peak as a
    share of full scale (0: none; 1 saturates its core), ``core_radius_frac`` the core's radius and ``falloff_frac``
    the one sigma of its soft edge, shares of the image width; ``haze`` a veil over the whole frame (the share of
    full scale every pixel is blended towards). The sun stands at ``sun_azimuth_deg`` (from north towards east) and
    ``sun_elevation_deg``. With ``after_gps_loss`` only the frames after GPS1 is lost have it (the map has not)."""

    strength: NonNegative = 0.0
    core_radius_frac: Annotated[float, Field(ge=0, le=1)] = 0.05
    falloff_frac: Annotated[float, Field(gt=0, le=1)] = 0.08
    haze: Annotated[float, Field(ge=0, lt=1)] = 0.0
    sun_azimuth_deg: Annotated[float, Field(ge=-360, le=360)] = SUN_AZIMUTH_DEG
    sun_elevation_deg: Annotated[float, Field(gt=0, le=90)] = SUN_ELEVATION_DEG
    after_gps_loss: bool = True


@config_dataclass(config=_STRICT, frozen=True)
class MotionBlurConfig:
    """The ground's motion in the image while the shutter is open, from the true velocity: a line of
    ground speed x ``exposure_time_s`` / ground sample distance px (0 s: none; 2 ms is a daylight shutter). On the
    whole flight unless ``after_gps_loss``."""

    exposure_time_s: Annotated[float, Field(ge=0, le=0.1)] = 0.0
    after_gps_loss: bool = False


@config_dataclass(config=_STRICT, frozen=True)
class SensorNoiseConfig:
    """Shot noise (variance ``shot_dn`` grey levels squared per grey level of signal) and read noise (one sigma
    ``read_sigma_dn`` grey levels). On the whole flight unless ``after_gps_loss``."""

    shot_dn: NonNegative = 0.0
    read_sigma_dn: NonNegative = 0.0
    after_gps_loss: bool = False


@config_dataclass(config=_STRICT, frozen=True)
class EffectsConfig:
    """What the simulated camera does to its frames (auxgps.sim.render.apply_effects). The defaults do nothing.

    ``noise_sigma`` (white noise, grey levels), ``blur_sigma_px`` (defocus) and ``exposure_gain`` are the whole
    flight's; ``exposure_shift`` applies once GPS1 is lost (in a mission, from the item it is lost at; in the
    survey-then-positioning eval, to the whole positioning flight); the others say when they apply."""

    noise_sigma: NonNegative = 0.0
    blur_sigma_px: NonNegative = 0.0
    exposure_gain: Positive = 1.0
    exposure_shift: ExposureShiftConfig = Field(default_factory=ExposureShiftConfig)
    glare: GlareConfig = Field(default_factory=GlareConfig)
    motion_blur: MotionBlurConfig = Field(default_factory=MotionBlurConfig)
    sensor_noise: SensorNoiseConfig = Field(default_factory=SensorNoiseConfig)


@config_dataclass(config=_STRICT, frozen=True)
class DenialConfig:
    """When the positioning flight loses GPS, and an optional camera blackout during the denial."""

    gps_until_s: NonNegative = 10.0
    blackout_start_s: float | None = None
    blackout_duration_s: NonNegative = 0.0
    fix_latency_s: Annotated[float, Field(ge=0, le=0.25)] = 0.1  # capture to fix, on top of nothing else


@config_dataclass(config=_STRICT, frozen=True)
class SimConfig:
    """How the simulated flights are flown and sensed."""

    mapping: SurveyConfig = Field(default_factory=SurveyConfig)
    positioning: SurveyConfig = Field(default_factory=lambda: SurveyConfig(legs="ew", offset_m=1.0))
    vehicle: VehicleConfig = Field(default_factory=VehicleConfig)
    noise: TelemetryNoiseConfig = Field(default_factory=TelemetryNoiseConfig)
    effects: EffectsConfig = Field(default_factory=EffectsConfig)
    denial: DenialConfig = Field(default_factory=DenialConfig)
    dt_s: Annotated[float, Field(gt=0, le=0.1)] = 0.01
    # Faults injected into the positioning flight (auxgps.sim.faults; `auxgps eval --faults FILE`)
    faults: list[Fault] = Field(default_factory=list)

    def image_effects(self, after_gps_loss: bool = False) -> ImageEffects:
        """The camera's effects on a frame before GPS1 is lost (the way out, the map) or after (the way back)."""
        fx = self.effects
        shift, glare, blur, noise = fx.exposure_shift, fx.glare, fx.motion_blur, fx.sensor_noise
        glare_on = after_gps_loss or not glare.after_gps_loss
        blur_on = after_gps_loss or not blur.after_gps_loss
        noise_on = after_gps_loss or not noise.after_gps_loss
        return ImageEffects(
            noise_sigma=fx.noise_sigma, blur_sigma_px=fx.blur_sigma_px, exposure_gain=fx.exposure_gain,
            shift_gain=shift.gain if after_gps_loss else 1.0,
            shift_gain_bgr=tuple(shift.gain_bgr) if after_gps_loss else (1.0, 1.0, 1.0),
            shift_gamma=shift.gamma if after_gps_loss else 1.0,
            glare_strength=glare.strength if glare_on else 0.0,
            glare_core_frac=glare.core_radius_frac, glare_falloff_frac=glare.falloff_frac,
            glare_haze=glare.haze if glare_on else 0.0,
            sun_dir_ned=tuple(float(x) for x in sun_dir_ned(glare.sun_azimuth_deg, glare.sun_elevation_deg)),
            exposure_time_s=blur.exposure_time_s if blur_on else 0.0,
            shot_noise_dn=noise.shot_dn if noise_on else 0.0,
            read_noise_dn=noise.read_sigma_dn if noise_on else 0.0,
        )


def load_sim_config(path=None) -> SimConfig:
    return SimConfig() if path is None else parse_as(SimConfig, read_yaml(path), path)


def lawnmower_waypoints(survey: SurveyConfig, alt_m: float) -> np.ndarray:
    """(N, 3) NED waypoints of a lawnmower at ``alt_m`` above the origin: legs, then a step, then back."""
    if survey.legs == "ns":
        lo, hi = survey.east_min_m + survey.offset_m, survey.east_max_m
        along = (survey.north_min_m, survey.north_max_m)
    else:
        lo, hi = survey.north_min_m + survey.offset_m, survey.north_max_m
        along = (survey.east_min_m, survey.east_max_m)
    lines = np.arange(lo, hi + 1e-9, survey.spacing_m)
    points = []
    for i, x in enumerate(lines):
        a, b = along if i % 2 == 0 else along[::-1]
        for y in (a, b):
            points.append((y, x) if survey.legs == "ns" else (x, y))
    ne = np.array(points, float)
    return np.column_stack([ne, np.full(len(ne), -alt_m)])


def mission_waypoints_ned(mission: Mission, frame: LocalFrame, alt_m: float | None = None,
                          max_distance_m: float = 20_000.0) -> tuple[np.ndarray, np.ndarray]:
    """The path a multirotor flies for ``mission`` from home at ``frame``'s origin, on the ground: (K, 3) NED
    waypoints and (K,) the mission item each belongs to (its seq; -1 for the start and for the return this adds).

    Take-off climbs where the vehicle is; a waypoint (or loiter) goes to its place at its height; land descends
    where it is told (lat/lon 0: where the vehicle is); return-to-launch flies home at the height it has, then
    lands. A mission that ends elsewhere is given a return and a landing (ArduPilot would hold there; a test flight
    comes home). ``alt_m`` puts every height of the mission at that many metres above home (an evaluation flying
    one path at several heights); otherwise the items' own heights are flown. Items without a place (DO_ and
    CONDITION_ commands) are skipped. ConfigError when a place is over ``max_distance_m`` from home: a mission
    of somewhere else."""
    home_amsl_m = frame.alt_amsl_m
    path: list[tuple[float, float, float]] = [(0.0, 0.0, 0.0)]
    owner = [-1]

    def go(ne, height_m, seq):
        if np.hypot(*ne) > max_distance_m:
            raise ConfigError(f"{mission.source}: item {seq} is {np.hypot(*ne) / 1000:.1f} km from the world's origin "
                              f"(over {max_distance_m / 1000:g} km): a mission of somewhere else")
        path.append((float(ne[0]), float(ne[1]), -float(height_m)))
        owner.append(seq)

    landed = False
    for it in mission.items:
        if not it.has_place:
            continue
        here_ne, here_h = np.array(path[-1][:2]), -path[-1][2]
        height = alt_m if alt_m is not None else (it.alt_m - home_amsl_m if it.frame in AMSL_FRAMES else it.alt_m)
        if it.lat_deg == 0.0 and it.lon_deg == 0.0:
            ne = here_ne
        else:
            ne = frame.to_ned(lat_deg=it.lat_deg, lon_deg=it.lon_deg, alt_amsl_m=home_amsl_m)[:2]
        if it.command == M.MAV_CMD_NAV_TAKEOFF:
            go(here_ne, height, it.seq)
        elif it.command == M.MAV_CMD_NAV_LAND:
            go(ne, here_h, it.seq)
            go(ne, 0.0, it.seq)
            landed = True
            break
        elif it.command == M.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            go((0.0, 0.0), here_h, it.seq)
            go((0.0, 0.0), 0.0, it.seq)
            landed = True
            break
        else:
            if here_h <= 0.0:  # a waypoint before any take-off: ArduPilot takes off to it; climb first
                go(here_ne, height, it.seq)
            go(ne, height, it.seq)
    if not landed:
        go((0.0, 0.0), -path[-1][2], -1)
        go((0.0, 0.0), 0.0, -1)
    return np.array(path), np.array(owner)


def gps_lost_waypoint(mission: Mission, owner: np.ndarray, seq: int) -> int:
    """Index, in the path :func:`mission_waypoints_ned` made (``owner`` its second array), of the waypoint that
    reaches mission item ``seq``: where GPS1 is lost. ConfigError when the item is missing or goes nowhere."""
    item = mission.item(seq)
    hits = np.flatnonzero(owner == seq)
    if not len(hits):
        raise ConfigError(f"{mission.source}: item {seq} ({item.name}) is not a place the vehicle reaches")
    return int(hits[-1])


@dataclass(frozen=True)
class Trajectory:
    """The true motion, sampled every ``dt_s``.

    t_s (T,) s; p_ned_m (T, 3) m; v_ned_m_s (T, 3); a_ned_m_s2 (T, 3); euler_rad (T, 3) roll, pitch, yaw;
    reached_t_s (W,): when each waypoint flown through was reached (the first, the start, at 0).
    """

    t_s: np.ndarray
    p_ned_m: np.ndarray
    v_ned_m_s: np.ndarray
    a_ned_m_s2: np.ndarray
    euler_rad: np.ndarray
    reached_t_s: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1])

    def index_at(self, t_s: float) -> int:
        return int(np.clip(np.rint(t_s / (self.t_s[1] - self.t_s[0])), 0, len(self.t_s) - 1))

    def R_ned_body(self, i: int) -> np.ndarray:
        return R_ned_body_from_euler(*self.euler_rad[i])


def _attitude_from_thrust(f_ned: np.ndarray, yaw_rad: float) -> np.ndarray:
    """Body -> NED rotation whose -z axis is along the specific thrust ``f_ned`` with heading ``yaw_rad``."""
    z_b = -f_ned / np.linalg.norm(f_ned)
    x_c = np.array([np.cos(yaw_rad), np.sin(yaw_rad), 0.0])
    y_b = np.cross(z_b, x_c)
    y_b /= np.linalg.norm(y_b)
    x_b = np.cross(y_b, z_b)
    return np.column_stack([x_b, y_b, z_b])


class Multirotor:
    """The vehicle's true motion, one step at a time: it tilts its thrust to follow a velocity command.

    State: ``p_ned_m``, ``v_ned_m_s``, ``yaw_rad`` and a gust (an Ornstein-Uhlenbeck acceleration). The
    controller sees ``v_est`` (its own velocity estimate; the truth when not given).
    """

    def __init__(self, vehicle: VehicleConfig, p_ned_m: np.ndarray, yaw_rad: float, dt_s: float) -> None:
        self.cfg = vehicle
        self.p_ned_m = np.asarray(p_ned_m, float).copy()
        self.v_ned_m_s = np.zeros(3)
        self.yaw_rad = float(yaw_rad)
        self.dt_s = dt_s
        self._gust = np.zeros(3)
        self._wind = np.array([vehicle.wind_north_m_s, vehicle.wind_east_m_s, 0.0])
        self._gust_decay = np.exp(-dt_s / vehicle.gust_tau_s)
        self._gust_kick = vehicle.gust_sigma_m_s2 * np.sqrt(1 - self._gust_decay**2)
        self._max_yaw_step = np.deg2rad(vehicle.yaw_rate_deg_s) * dt_s

    def command(self, v_des_ned_m_s: np.ndarray, yaw_goal_rad: float, rng: np.random.Generator, v_est=None):
        """The acceleration (NED, m/s^2) and attitude (roll, pitch, yaw, rad) for the coming step."""
        cfg = self.cfg
        v_ctrl = self.v_ned_m_s if v_est is None else np.asarray(v_est, float)
        a_cmd = cfg.velocity_gain_per_s * (np.asarray(v_des_ned_m_s, float) - v_ctrl)
        n_a = np.linalg.norm(a_cmd)
        if n_a > cfg.max_accel_m_s2:
            a_cmd *= cfg.max_accel_m_s2 / n_a
        # Thrust provides the commanded acceleration, holds against gravity and cancels the drag it expects.
        drag = -cfg.drag_per_s * (self.v_ned_m_s - self._wind)
        f_thrust = a_cmd - np.array([0.0, 0.0, GRAVITY_M_S2]) - drag
        dyaw = (yaw_goal_rad - self.yaw_rad + np.pi) % (2 * np.pi) - np.pi
        self.yaw_rad += float(np.clip(dyaw, -self._max_yaw_step, self._max_yaw_step))
        R = _attitude_from_thrust(f_thrust, self.yaw_rad)
        self._gust = self._gust_decay * self._gust + self._gust_kick * rng.standard_normal(3) * np.array([1.0, 1.0, 0.3])
        return a_cmd + self._gust, np.array(euler_from_R_ned_body(R))

    def advance(self, a_ned_m_s2: np.ndarray) -> None:
        """Integrate one step with the acceleration ``command`` returned (semi-implicit Euler). The ground (the
        plane of home, down 0) stops it: a landing stands there."""
        self.v_ned_m_s = self.v_ned_m_s + a_ned_m_s2 * self.dt_s
        self.p_ned_m = self.p_ned_m + self.v_ned_m_s * self.dt_s
        if self.p_ned_m[2] > 0.0:
            self.p_ned_m[2] = 0.0
            self.v_ned_m_s[2] = 0.0


class WaypointGuidance:
    """Velocity and heading commands that take a vehicle through waypoints, braking into each one.

    Heading follows long legs (5 m or more) and is kept on short steps, as a survey drone's would be.
    """

    def __init__(self, waypoints_ned_m: np.ndarray, speed_m_s: float, vehicle: VehicleConfig) -> None:
        self.wps = np.asarray(waypoints_ned_m, float)
        self.speed = speed_m_s
        self.cfg = vehicle
        self.target = 1
        leg = self.wps[1] - self.wps[0] if len(self.wps) > 1 else np.array([1.0, 0.0, 0.0])
        self.yaw_goal_rad = float(np.arctan2(leg[1], leg[0]))

    @property
    def done(self) -> bool:
        return self.target >= len(self.wps)

    def command(self, p_ned_m: np.ndarray) -> np.ndarray:
        """Velocity command (NED, m/s) from the position ``p_ned_m`` the vehicle believes it is at."""
        brake = 0.6 * self.cfg.max_accel_m_s2
        while self.target < len(self.wps):
            d = self.wps[self.target] - p_ned_m
            dist = np.linalg.norm(d)
            if dist >= self.cfg.waypoint_radius_m:
                return d / dist * min(self.speed, np.sqrt(2 * brake * dist))
            self.target += 1
            if self.target < len(self.wps):
                seg = self.wps[self.target] - self.wps[self.target - 1]
                if np.linalg.norm(seg[:2]) >= 5.0:
                    self.yaw_goal_rad = float(np.arctan2(seg[1], seg[0]))
        return np.clip(self.wps[-1] - p_ned_m, -0.5, 0.5)


def fly(waypoints_ned_m: np.ndarray, speed_m_s: float, vehicle: VehicleConfig, rng: np.random.Generator, dt_s: float = 0.01) -> Trajectory:
    """Fly through ``waypoints_ned_m`` in order, starting at rest at the first one, and hover 1 s at the last."""
    guide = WaypointGuidance(waypoints_ned_m, speed_m_s, vehicle)
    craft = Multirotor(vehicle, guide.wps[0], guide.yaw_goal_rad, dt_s)
    ts, ps, vs, accs, eulers = [], [], [], [], []
    reached = [0.0]
    settled = 0
    t = 0.0
    while settled <= int(1.0 / dt_s):
        v_des = guide.command(craft.p_ned_m)
        reached += [t] * (min(guide.target, len(guide.wps)) - len(reached))
        settled += guide.done
        a, euler = craft.command(v_des, guide.yaw_goal_rad, rng)
        ts.append(t)
        ps.append(craft.p_ned_m.copy())
        vs.append(craft.v_ned_m_s.copy())
        accs.append(a)
        eulers.append(euler)
        craft.advance(a)
        t += dt_s
    return Trajectory(np.array(ts), np.array(ps), np.array(vs), np.array(accs), np.array(eulers), np.array(reached))


@dataclass(frozen=True)
class Telemetry:
    """What the autopilot reports at one instant. Angles rad, lengths m, NED about the local origin.

    ``p_gps_ned_m`` is the GPS position (None while GPS is denied); ``alt_above_origin_m`` the barometric height above the
    origin; ``euler_rad`` the attitude estimate (roll, pitch, yaw).
    """

    t_s: float
    p_gps_ned_m: np.ndarray | None
    alt_above_origin_m: float
    euler_rad: np.ndarray

    @property
    def R_ned_body(self) -> np.ndarray:
        return R_ned_body_from_euler(*self.euler_rad)


def sense(traj: Trajectory, i: int, noise: TelemetryNoiseConfig, rng: np.random.Generator, gps_ok: bool = True) -> Telemetry:
    """Telemetry at sample ``i``: the truth plus white noise from ``rng``."""
    p = traj.p_ned_m[i]
    sig = np.array([noise.gps_horizontal_m, noise.gps_horizontal_m, noise.gps_vertical_m])
    gps = p + rng.standard_normal(3) * sig
    alt = -p[2] + noise.altitude_m * rng.standard_normal()
    att_sig = np.deg2rad([noise.attitude_deg, noise.attitude_deg, noise.heading_deg])
    euler = traj.euler_rad[i] + rng.standard_normal(3) * att_sig
    return Telemetry(float(traj.t_s[i]), gps if gps_ok else None, float(alt), euler)


def imu_bias(noise: TelemetryNoiseConfig, rng: np.random.Generator) -> np.ndarray:
    """A constant accelerometer bias for one run, body frame, m/s^2."""
    return rng.standard_normal(3) * noise.accel_bias_m_s2


def sense_imu(traj: Trajectory, i: int, noise: TelemetryNoiseConfig, bias_body_m_s2: np.ndarray, rng: np.random.Generator):
    """IMU sample at trajectory sample ``i``: specific force (body, with bias and noise) and noisy attitude.

    Returns ``(t_s, f_body_m_s2, euler_rad)``. The specific force is the acceleration that carries the vehicle
    from sample ``i`` to ``i + 1``, less gravity, in the true body frame.
    """
    R = traj.R_ned_body(i)
    f_true = R.T @ (traj.a_ned_m_s2[i] - np.array([0.0, 0.0, GRAVITY_M_S2]))
    f = f_true + bias_body_m_s2 + rng.standard_normal(3) * noise.accel_noise_m_s2
    att_sig = np.deg2rad([noise.attitude_deg, noise.attitude_deg, noise.heading_deg])
    return float(traj.t_s[i]), f, traj.euler_rad[i] + rng.standard_normal(3) * att_sig
