"""A vehicle emulator that behaves like ArduPilot copter SITL where auxgps meets it, for fast tests and the demo.

    python -m auxgps.sim.emulator --world one_cube_1m --port 5760 \\
        [--altitude 15] [--speedup 1] [--fail-gps1-at 60] [--gps2-type 14] [--auto-switch 1] [--log out/emu.json]
        [--faults config/faults/FILE.yaml] [--mission M.waypoints --speed-m-s 8 --gps-lost-at-waypoint 3]

It serves MAVLink 2 on TCP 127.0.0.1:PORT (one client at a time; it keeps flying when the client leaves and
accepts the next one), flies the mapping survey of ``SimConfig().mapping`` with ``auxgps.sim.flight``'s
multirotor (or, with ``--mission``, the mission's places at their own heights, GPS1 disabled on reaching item
``--gps-lost-at-waypoint``, and the landing where it ends), takes GPS_INPUT as GPS2 under ArduPilot's rules
(/work/shared/ARDUPILOT.md) and navigates on its own estimate, never on the truth. ``--faults`` takes the fault
file of ``auxgps eval --faults`` (:mod:`auxgps.sim.faults`): its GPS1 faults (drag, inflated accuracy, dropouts)
and telemetry faults (attitude stopping, height stuck, every message twice, a reboot) begin ``at_s`` after take-off; camera
faults and reordering are not emulated here (they are the camera's and the link's, not the autopilot's). Exit
code 0 after landing, 3 after ``--max-seconds``, 130 when interrupted, 1 for a bad argument; the JSON log is
written in every case.

Layout
------
Pure part (no sockets, no clock: every method takes the emulated time ``t_s``)
    ``GpsReading``, ``GpsInstance`` (bookkeeping, health, timeout), ``PrimarySelector`` (AP_GPS::update_primary),
    ``NavEstimator`` (estimate, dead reckoning, failsafe timing), ``prearm_gps_failure``, ``gps_input_to_reading``,
    ``gps_input_stats``, ``StreamScheduler``.
Simulation (no sockets)
    ``VehicleSim``: physics at 100 Hz, mission, GPS1, barometer, the pure parts wired together, events and log.
I/O
    ``TcpServerLink`` (pymavlink's tcpin, made to survive reconnects), ``MavlinkServer`` (pacing, streams,
    handlers), ``main``.

Frames: NED metres about the world's origin (= home, on the ground); body FRD; angles rad inside, degrees and
MAVLink integer units only in the message builders.
"""

from __future__ import annotations

import argparse
import collections
import enum
import json
import logging
import math
import os
import signal
import socket
import sys
import tempfile
import time
from collections import deque
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable, Sequence

os.environ["MAVLINK20"] = "1"  # before pymavlink is imported: MAVLink 2 (GPS_INPUT.gps_id, SIM_STATE.lat_int)

import numpy as np  # noqa: E402
from pymavlink import mavutil  # noqa: E402
from pymavlink.quaternion import QuaternionBase  # noqa: E402

from auxgps.core.geometry import LocalFrame, R_ned_body_from_euler, body_rates_from_euler_rates, euler_step_rad  # noqa: E402
from auxgps.errors import AuxGpsError  # noqa: E402
from auxgps.io.mission import load_mission  # noqa: E402
from auxgps.sim.flight import (  # noqa: E402
    GRAVITY_M_S2,
    Multirotor,
    SimConfig,
    SurveyConfig,
    TelemetryNoiseConfig,
    VehicleConfig,
    WaypointGuidance,
    gps_lost_waypoint,
    imu_bias,
    lawnmower_waypoints,
    mission_waypoints_ned,
)
from auxgps.sim.faults import Fault, load_fault_plan  # noqa: E402
from auxgps.sim.world import load_world  # noqa: E402

if mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":  # pymavlink was imported earlier in this process without MAVLINK20
    mavutil.set_dialect("ardupilotmega")
MAV = mavutil.mavlink

log = logging.getLogger("vehicle_emulator")


def _generators(seed: int) -> list[np.random.Generator]:
    """The emulator's random generators for ``seed``: physics, GPS1, barometer, telemetry, accelerometer bias."""
    return [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(5)]


def emulated_imu_bias(noise: TelemetryNoiseConfig, seed: int) -> np.ndarray:
    """The accelerometer bias (body axes, m/s^2) the emulator flies with for ``seed`` and ``noise``: what an
    analysis of its flight compares the filter's estimate with."""
    return imu_bias(noise, _generators(seed)[4])


class EmulatorError(AuxGpsError):
    """A bad emulator argument, or the port cannot be served."""


# ---------------------------------------------------------------------------------------------------------------
# ArduPilot's numbers (AP_GPS.cpp, AP_GPS_MAV.cpp, AP_Arming.cpp; see /work/shared/ARDUPILOT.md)

FIX_NO_GPS = 0
FIX_NONE = 1  # "NO_FIX": what a MAVLink GPS instance falls back to after the timeout
FIX_3D = 3
GPS_TIMEOUT_S = 4.0
GPS_MAX_GAP_S = 0.245  # 200 ms (5 Hz) + 45 ms
GPS_MAX_MEAN_INTERVAL_S = 0.215
GPS_MAX_LATE_IN_A_ROW = 2  # unhealthy from this many consecutive late messages
GPS_AVERAGE_SKIP_S = 2.0  # ArduPilot leaves intervals this long out of the average
GPS_HEALTH_WINDOW = 10  # intervals: the emulator's sliding window (ArduPilot keeps an exponential average)
GPS_CONSISTENT_M = 50.0
GPS_TYPE_NONE = 0
GPS_TYPE_MAV = 14
GPS_INPUT_IGNORE_ALT = 1
GPS_INPUT_IGNORE_VEL_HORIZ = 8
GPS_INPUT_IGNORE_VEL_VERT = 16
GPS_INPUT_IGNORE_HORIZ_ACCURACY = 64
AUTO_SWITCH_NONE, AUTO_SWITCH_BEST, AUTO_SWITCH_BLEND, AUTO_SWITCH_PRIMARY_IF_3D = 0, 1, 2, 4
SWITCH_1_MORE_SAT_S = 20.0
SWITCH_2_MORE_SATS_S = 5.0

# The emulated vehicle's own choices
DEAD_RECKON_S = 2.0
GPS2_DELAY_MS_DEFAULT = 100  # as config/ardupilot/auxgps-gps2.parm sets it
GPS1_LAG_S = 0.1  # SITL's default SIM_GPS1_LAG_MS: a GPS1 reading describes the vehicle this long before it is sent
FAILSAFE_S = 8.0
GPS_FRESH_S = 0.5  # a fix this old still counts as "gps" in the log's nav state
LAND_SPEED_M_S = 0.5
TAKEOFF_SPEED_M_S = 2.5  # ArduCopter's WPNAV_SPEED_UP default
LAND_POSITION_GAIN_PER_S = 1.0
LAND_MAX_HORIZONTAL_M_S = 0.5
TOUCHDOWN_HEIGHT_M = 0.05
BOOT_S = 1.0  # no arming check before this
PREARM_REPORT_PERIOD_S = 5.0
LINGER_AFTER_LANDING_S = 2.0  # keep serving so a client sees the disarmed heartbeat
GPS1_HEALTHY_SATS, GPS1_FAILED_SATS = 10, 3
GPS1_HEALTHY_FIX, GPS1_FAILED_FIX = 6, 0  # SITL's healthy GPS1 reports RTK fixed; SIM_GPS1_ENABLE=0 gives fix 0
GPS1_VELOCITY_NOISE_M_S = 0.05  # not in TelemetryNoiseConfig: an assumption
BARO_CLIMB_NOISE_M_S = 0.05  # one sigma of the vertical velocity estimate, per barometer sample
SAMPLE_PERIOD_S = 0.1  # log samples


class CopterMode(enum.IntEnum):
    """ArduCopter flight mode numbers (HEARTBEAT.custom_mode)."""

    AUTO = 3
    GUIDED = 4
    RTL = 6
    LAND = 9


class Phase(enum.Enum):
    WAIT_ARM = "wait_arm"
    TAKEOFF = "takeoff"
    SURVEY = "survey"
    RETURN = "return"
    DESCEND = "descend"
    LANDED = "landed"


# ---------------------------------------------------------------------------------------------------------------
# Pure part


@dataclass(frozen=True)
class GpsReading:
    """One GPS solution as the autopilot holds it.

    ``fix_type`` MAVLink GPS_FIX_TYPE (3 = 3D); ``lat_e7``/``lon_e7`` deg * 1e7; ``alt_amsl_m`` m;
    ``p_ned_m`` (3,) m and ``v_ned_m_s`` (3,) m/s in the local frame; ``h_acc_m`` m (one sigma).
    """

    fix_type: int
    lat_e7: int
    lon_e7: int
    alt_amsl_m: float
    p_ned_m: np.ndarray
    v_ned_m_s: np.ndarray
    satellites: int
    h_acc_m: float


class GpsInstance:
    """One GPS instance as AP_GPS keeps it: the latest reading, its arrival times, its health and timeout.

    Health, exactly as emulated (after AP_GPS::update_instance and AP_GPS::is_healthy), at time ``t_s``:

    - the intervals are the differences between the arrival times of the last 11 messages (up to 10 intervals;
      ArduPilot keeps an exponential average of weight 0.02 instead of a window);
    - at least 2 intervals are known (3 messages since the start or since the last timeout);
    - the mean of the intervals shorter than 2 s is under 215 ms (ArduPilot also leaves those out);
    - the most recent intervals do not end in a run of 2 or more over 245 ms (ArduPilot's ``delayed_count``:
      consecutive late messages, reset by one on time);
    - the last message is at most 4 s old.

    A silence shorter than 4 s does not by itself make the instance unhealthy (ArduPilot judges timing when a
    message arrives). After 4 s without a message the instance is reset: fix NO_FIX (1), 0 satellites, no reading
    and no interval history. Arrival times are always used: ArduPilot times a GPS_INPUT with ``fix_type >= 3`` and
    ``time_week > 0`` by its jitter-corrected GPS week time instead, which is not emulated.
    """

    def __init__(self) -> None:
        self._arrivals_t_s: deque[float] = deque(maxlen=GPS_HEALTH_WINDOW + 1)
        self._reading: GpsReading | None = None
        self._last_t_s: float | None = None

    def on_message(self, t_s: float, reading: GpsReading) -> None:
        """Take a reading that arrived at ``t_s`` (emulated s)."""
        if self.timed_out(t_s):
            self._arrivals_t_s.clear()
        self._arrivals_t_s.append(t_s)
        self._reading = reading
        self._last_t_s = t_s

    def timed_out(self, t_s: float) -> bool:
        """True when a message was once received and none for more than 4 s."""
        return self._last_t_s is not None and t_s - self._last_t_s > GPS_TIMEOUT_S

    @property
    def last_fix_t_s(self) -> float | None:
        """When the latest reading arrived (emulated s): ArduPilot's ``last_fix_time_ms``."""
        return self._last_t_s

    def reading(self, t_s: float) -> GpsReading | None:
        """The latest reading, or None before the first message and after a timeout."""
        return None if self.timed_out(t_s) else self._reading

    def fix_type(self, t_s: float) -> int:
        """The fix status: NO_GPS (0) before any message, NO_FIX (1) after a timeout, else the reading's."""
        if self._last_t_s is None:
            return FIX_NO_GPS
        return FIX_NONE if self.timed_out(t_s) else self._reading.fix_type

    def satellites(self, t_s: float) -> int:
        reading = self.reading(t_s)
        return 0 if reading is None else reading.satellites

    def intervals_s(self) -> np.ndarray:
        """(K,) the intervals between the remembered arrivals, s."""
        return np.diff(np.array(self._arrivals_t_s, float))

    def healthy(self, t_s: float) -> bool:
        """The emulated health rule (see the class docstring)."""
        if self._last_t_s is None or self.timed_out(t_s):
            return False
        intervals = self.intervals_s()
        if len(intervals) < 2:
            return False
        counted = intervals[intervals < GPS_AVERAGE_SKIP_S]
        if len(counted) == 0 or counted.mean() >= GPS_MAX_MEAN_INTERVAL_S:
            return False
        return _late_run(intervals) < GPS_MAX_LATE_IN_A_ROW

    def selection_fix(self, t_s: float) -> int:
        """The fix status primary selection sees: an unhealthy instance counts as no fix (the brief's rule)."""
        fix = self.fix_type(t_s)
        return fix if self.healthy(t_s) else min(fix, FIX_NONE)

    def usable(self, t_s: float) -> bool:
        """A 3D fix (or better) from a healthy instance: what the estimate may use."""
        return self.fix_type(t_s) >= FIX_3D and self.healthy(t_s)


def _late_run(intervals_s: np.ndarray) -> int:
    """How many of the most recent intervals in a row are over 245 ms."""
    run = 0
    for dt in intervals_s[::-1]:
        if dt <= GPS_MAX_GAP_S:
            break
        run += 1
    return run


class PrimarySelector:
    """Which GPS instance is primary: AP_GPS::update_primary for two instances.

    ``auto_switch`` (GPS_AUTO_SWITCH): 0 use ``primary_param`` (GPS_PRIMARY); 1 use best: an instance with a
    higher fix status takes over at once, one with an equal status and at least 1 more satellite after 20 s
    since the last switch, or with at least 2 more after 5 s; 2 (blend) is treated as 1; 4 use
    ``primary_param`` while it has a 3D fix, else as 1. A GPS_PRIMARY naming an unconfigured instance means 0.
    The fix statuses given should be ``GpsInstance.selection_fix`` (unhealthy counts as no fix).
    """

    def __init__(self) -> None:
        self.primary = 0
        self.last_swap_t_s = 0.0

    def update(self, t_s: float, fix: Sequence[int], sats: Sequence[int], configured: Sequence[bool],
               auto_switch: int, primary_param: int) -> int:
        """The primary instance (0 or 1) at ``t_s`` (emulated s), given each instance's fix and satellites."""
        if primary_param not in (0, 1) or not configured[primary_param]:
            primary_param = 0
        if auto_switch == AUTO_SWITCH_NONE:
            self.primary = primary_param
            return self.primary
        if auto_switch == AUTO_SWITCH_PRIMARY_IF_3D and fix[primary_param] >= FIX_3D:
            self._swap(primary_param, t_s)
            return self.primary
        for i in (0, 1):
            if i == self.primary:
                continue
            if fix[i] > fix[self.primary]:
                self._swap(i, t_s)
                continue
            if fix[i] == fix[self.primary] and self._more_sats_long_enough(t_s, sats[i], sats[self.primary]):
                self._swap(i, t_s)
        return self.primary

    def _more_sats_long_enough(self, t_s: float, sats_other: int, sats_primary: int) -> bool:
        since_swap_s = t_s - self.last_swap_t_s
        return (sats_other >= sats_primary + 1 and since_swap_s >= SWITCH_1_MORE_SAT_S) or (
            sats_other >= sats_primary + 2 and since_swap_s >= SWITCH_2_MORE_SATS_S
        )

    def _swap(self, instance: int, t_s: float) -> None:
        if instance != self.primary:
            self.primary = instance
            self.last_swap_t_s = t_s


class NavEstimator:
    """The horizontal position and velocity the vehicle navigates on, from the primary GPS's usable fixes.

    Exactly: with the last usable fix (``p``, ``v``) taken at ``t_fix``, the estimate at ``t_s`` is
    ``p + v * min(t_s - t_fix, 2 s)`` with velocity ``v`` while ``t_s - t_fix <= 2 s`` (between fixes this is a
    short extrapolation, after a loss it is dead reckoning on the last velocity), then frozen at
    ``p + 2 s * v`` with zero velocity. The EKF failsafe is due when ``t_s - t_fix >= 8 s``. A new usable fix
    replaces the estimate at once (a reset, as the EKF does on a GPS that returns). The vertical channel is
    the barometer's and is not kept here.
    """

    def __init__(self) -> None:
        self._t_fix_s: float | None = None
        self._p_ne_m = np.zeros(2)
        self._v_ne_m_s = np.zeros(2)

    def on_fix(self, t_s: float, p_ne_m: np.ndarray, v_ne_m_s: np.ndarray) -> None:
        """A usable fix from the primary GPS taken at ``t_s``: ``p_ne_m`` (2,) m, ``v_ne_m_s`` (2,) m/s."""
        self._t_fix_s = t_s
        self._p_ne_m = np.asarray(p_ne_m, float)[:2].copy()
        self._v_ne_m_s = np.asarray(v_ne_m_s, float)[:2].copy()

    def age_s(self, t_s: float) -> float:
        """Seconds since the last usable fix (inf before the first)."""
        return math.inf if self._t_fix_s is None else t_s - self._t_fix_s

    def horizontal(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(p_ne_m (2,), v_ne_m_s (2,)) at ``t_s``."""
        age_s = self.age_s(t_s)
        if self._t_fix_s is None:
            return np.zeros(2), np.zeros(2)
        p = self._p_ne_m + self._v_ne_m_s * min(age_s, DEAD_RECKON_S)
        v = self._v_ne_m_s.copy() if age_s <= DEAD_RECKON_S else np.zeros(2)
        return p, v

    def has_reference(self, t_s: float) -> bool:
        """True while the estimate still follows a fix (at most 2 s old)."""
        return self.age_s(t_s) <= DEAD_RECKON_S

    def failsafe_due(self, t_s: float) -> bool:
        """True once a fix was had and none for 8 s."""
        return self._t_fix_s is not None and self.age_s(t_s) >= FAILSAFE_S

    def state(self, t_s: float) -> str:
        """"none", "gps", "dead_reckoning" or "frozen", for the log."""
        age_s = self.age_s(t_s)
        if math.isinf(age_s):
            return "none"
        if age_s <= GPS_FRESH_S:
            return "gps"
        return "dead_reckoning" if age_s <= DEAD_RECKON_S else "frozen"


def prearm_gps_failure(gps: Sequence[GpsInstance], configured: Sequence[bool], t_s: float) -> str | None:
    """The first GPS arming failure (AP_Arming::gps_checks) at ``t_s``, or None when every check passes.

    Every configured instance must have a 3D fix ("GPS n: Bad fix") and be healthy ("GPS n: not healthy");
    with two configured, their 3D positions must be under 50 m apart ("GPS positions differ by x.xm").
    """
    for i, instance in enumerate(gps):
        if not configured[i]:
            continue
        if instance.fix_type(t_s) < FIX_3D:
            return f"GPS {i + 1}: Bad fix"
        if not instance.healthy(t_s):
            return f"GPS {i + 1}: not healthy"
    if all(configured):
        distance_m = float(np.linalg.norm(gps[0].reading(t_s).p_ned_m - gps[1].reading(t_s).p_ned_m))
        if distance_m >= GPS_CONSISTENT_M:
            return f"GPS positions differ by {distance_m:4.1f}m"
    return None


def gps_input_to_reading(msg: Any, frame: LocalFrame, previous: GpsReading | None) -> GpsReading:
    """A GPS_INPUT message as AP_GPS_MAV takes it (``gps_id`` is checked by the caller).

    lat/lon deg * 1e7 and alt m AMSL go through ``frame``; with the ALT flag ignored the altitude is 0 m AMSL
    (ArduPilot zeroes it); with VEL_HORIZ ignored the velocity stays the previous one (zero at first), with
    VEL_VERT ignored only the vertical part is zero; with HORIZ_ACCURACY ignored the accuracy is unknown (NaN).
    """
    flags = int(msg.ignore_flags)
    alt_amsl_m = 0.0 if flags & GPS_INPUT_IGNORE_ALT else float(msg.alt)
    lat_deg, lon_deg = msg.lat * 1e-7, msg.lon * 1e-7
    p_ned_m = frame.to_ned(lat_deg=lat_deg, lon_deg=lon_deg, alt_amsl_m=alt_amsl_m)
    if flags & GPS_INPUT_IGNORE_VEL_HORIZ:
        v_ned_m_s = np.zeros(3) if previous is None else previous.v_ned_m_s.copy()
    else:
        vd = 0.0 if flags & GPS_INPUT_IGNORE_VEL_VERT else float(msg.vd)
        v_ned_m_s = np.array([float(msg.vn), float(msg.ve), vd])
    h_acc_m = math.nan if flags & GPS_INPUT_IGNORE_HORIZ_ACCURACY else float(msg.horiz_accuracy)
    return GpsReading(int(msg.fix_type), int(msg.lat), int(msg.lon), alt_amsl_m, p_ned_m, v_ned_m_s,
                      int(msg.satellites_visible), h_acc_m)


def gps_input_stats(arrivals_t_s: Sequence[float]) -> dict[str, float | int | None]:
    """Mean and largest interval (ms) between arrivals, and the longest run of consecutive gaps over 245 ms."""
    intervals = np.diff(np.asarray(arrivals_t_s, float))
    if len(intervals) == 0:
        return {"mean_interval_ms": None, "max_interval_ms": None, "consecutive_gaps_over_245ms": 0}
    longest = run = 0
    for late in intervals > GPS_MAX_GAP_S:
        run = run + 1 if late else 0
        longest = max(longest, run)
    return {
        "mean_interval_ms": float(intervals.mean() * 1e3),
        "max_interval_ms": float(intervals.max() * 1e3),
        "consecutive_gaps_over_245ms": int(longest),
    }


DEFAULT_RATES_HZ = {
    "HEARTBEAT": 1.0,
    "SYSTEM_TIME": 1.0,
    "ATTITUDE": 50.0,
    "SCALED_IMU": 50.0,
    "GLOBAL_POSITION_INT": 10.0,
    "GPS_RAW_INT": 5.0,
    "GPS2_RAW": 5.0,
    "SIMSTATE": 20.0,
    "SIM_STATE": 20.0,
}

# REQUEST_DATA_STREAM groups, as ArduPilot files these messages
DATA_STREAMS = {
    MAV.MAV_DATA_STREAM_RAW_SENSORS: ("SCALED_IMU",),
    MAV.MAV_DATA_STREAM_EXTENDED_STATUS: ("GPS_RAW_INT", "GPS2_RAW"),
    MAV.MAV_DATA_STREAM_POSITION: ("GLOBAL_POSITION_INT",),
    MAV.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE", "SIMSTATE", "SIM_STATE"),
    MAV.MAV_DATA_STREAM_EXTRA3: ("SYSTEM_TIME",),
}


class StreamScheduler:
    """When each telemetry message is due. Intervals in emulated seconds; None means off."""

    def __init__(self, rates_hz: dict[str, float]) -> None:
        self.default_interval_s = {name: 1.0 / hz for name, hz in rates_hz.items()}
        self.interval_s: dict[str, float | None] = dict(self.default_interval_s)
        self._next_t_s = {name: 0.0 for name in rates_hz}

    def set_interval(self, name: str, interval_s: float | None, t_s: float) -> None:
        """Send ``name`` every ``interval_s`` from ``t_s`` on (None: stop)."""
        self.interval_s[name] = interval_s
        self._next_t_s[name] = t_s

    def due(self, t_s: float) -> list[str]:
        """The messages due at ``t_s``; each is then scheduled one interval on."""
        names = []
        for name, interval_s in self.interval_s.items():
            if interval_s is None or t_s + 1e-9 < self._next_t_s[name]:
                continue
            names.append(name)
            self._next_t_s[name] = max(self._next_t_s[name] + interval_s, t_s + 0.5 * interval_s)
        return names


def _wrap_pi(angle_rad: float | np.ndarray) -> float | np.ndarray:
    return (angle_rad + np.pi) % (2 * np.pi) - np.pi


# ---------------------------------------------------------------------------------------------------------------
# Simulation (no sockets)


@dataclass(frozen=True)
class EmulatorOptions:
    """What the command line sets. Times are emulated seconds, lengths metres."""

    altitude_m: float = 15.0
    fail_gps1_at_s: float | None = None  # after take-off
    gps2_type: int = GPS_TYPE_MAV
    auto_switch: int = AUTO_SWITCH_BEST
    gps_primary: int = 0
    survey_size_m: float | None = None  # side of a square survey about home; None: SimConfig().mapping
    seed: int = 1
    max_seconds: float = 1800.0
    faults: tuple[Fault, ...] = ()  # GPS1 and telemetry faults, at_s after take-off (see the module's docstring)
    # A mission flown instead of the survey (--mission): its path from home, (K, 3) NED m as
    # auxgps.sim.flight.mission_waypoints_ned makes it (home, the take-off's top, ..., the landing on the ground),
    # its speed, and the index in it of the waypoint on reaching which GPS1 is disabled (None: --fail-gps1-at).
    mission_path_ned_m: tuple[tuple[float, float, float], ...] | None = None
    mission_speed_m_s: float = 5.0
    fail_gps1_at_index: int | None = None

    def validate(self) -> "EmulatorOptions":
        if not 0.5 <= self.altitude_m <= 120.0:
            raise EmulatorError(f"--altitude {self.altitude_m}: give 0.5 to 120 m")
        if self.fail_gps1_at_s is not None and self.fail_gps1_at_s < 0:
            raise EmulatorError(f"--fail-gps1-at {self.fail_gps1_at_s}: must not be negative")
        if self.mission_path_ned_m is not None and (len(self.mission_path_ned_m) < 4 or self.mission_path_ned_m[1][2] >= 0.0):
            raise EmulatorError("--mission: give a mission that takes off and goes somewhere")
        if self.fail_gps1_at_index is not None and self.fail_gps1_at_s is not None:
            raise EmulatorError("--fail-gps1-at and --gps-lost-at-waypoint: give one")
        if not 0.5 <= self.mission_speed_m_s <= 20.0:
            raise EmulatorError(f"--speed-m-s {self.mission_speed_m_s}: give 0.5 to 20 m/s")
        if self.survey_size_m is not None and not 0.5 <= self.survey_size_m <= 1000.0:
            raise EmulatorError(f"--survey-size {self.survey_size_m}: give 0.5 to 1000 m")
        if self.gps2_type not in (GPS_TYPE_NONE, GPS_TYPE_MAV):
            raise EmulatorError(f"--gps2-type {self.gps2_type}: give 0 or 14")
        if self.auto_switch not in (0, 1, 2, 4):
            raise EmulatorError(f"--auto-switch {self.auto_switch}: give 0, 1, 2 or 4")
        if self.gps_primary not in (0, 1):
            raise EmulatorError(f"--gps-primary {self.gps_primary}: give 0 or 1")
        if self.max_seconds <= 0:
            raise EmulatorError(f"--max-seconds {self.max_seconds}: must be positive")
        return self


def survey_config(options: EmulatorOptions, base: SurveyConfig) -> SurveyConfig:
    """``base`` (``SimConfig().mapping``), or a square of ``survey_size_m`` about home with the same legs."""
    if options.survey_size_m is None:
        return base
    half_m = options.survey_size_m / 2.0
    return SurveyConfig(north_min_m=-half_m, north_max_m=half_m, east_min_m=-half_m, east_max_m=half_m,
                        spacing_m=min(base.spacing_m, options.survey_size_m), legs=base.legs,
                        offset_m=0.0, speed_m_s=base.speed_m_s)


class VehicleSim:
    """The emulated copter: true motion, sensors, GPS instances, estimate, mission, events and log.

    Call ``step`` every ``dt_s`` of emulated time and ``handle_gps_input`` / ``set_param`` between steps.
    STATUSTEXTs to send collect in ``outbox`` as (severity, text).
    """

    def __init__(self, frame: LocalFrame, options: EmulatorOptions, sim_config: SimConfig | None = None) -> None:
        cfg = sim_config or SimConfig()
        self.frame = frame
        self.options = options
        self.vehicle: VehicleConfig = cfg.vehicle
        self.noise: TelemetryNoiseConfig = cfg.noise
        self.dt_s = cfg.dt_s
        self.survey = survey_config(options, cfg.mapping)
        self._rng_physics, self._rng_gps1, self._rng_baro, self.rng_telemetry, rng_bias = _generators(options.seed)
        self.imu_bias_body_m_s2 = imu_bias(self.noise, rng_bias)
        self.step_index = 0
        self.craft = Multirotor(self.vehicle, np.zeros(3), 0.0, self.dt_s)
        self.a_ned_m_s2 = np.zeros(3)
        self.euler_rad = np.zeros(3)
        self.rates_body_rad_s = np.zeros(3)
        self.params: dict[str, float] = {
            "SIM_GPS1_ENABLE": 1, "GPS2_TYPE": options.gps2_type,
            "GPS_AUTO_SWITCH": options.auto_switch, "GPS_PRIMARY": options.gps_primary,
            "GPS2_DELAY_MS": GPS2_DELAY_MS_DEFAULT,
            "EK3_SRC1_POSXY": 3, "EK3_SRC1_VELXY": 3,  # ArduPilot's defaults: GPS
        }
        self.gps = (GpsInstance(), GpsInstance())
        self.selector = PrimarySelector()
        self.estimator = NavEstimator()
        self.baro_height_m = 0.0
        self.baro_climb_m_s = 0.0
        self.phase = Phase.WAIT_ARM
        self.mode = CopterMode.GUIDED
        self.armed = False
        self.failsafe = False
        self.yaw_goal_rad = 0.0
        self._guide: WaypointGuidance | None = None
        self._land_target_ne_m = np.zeros(2)
        self._gps1_period_steps = max(1, round(1.0 / (self.noise.gps_rate_hz * self.dt_s)))
        self._motion_history: collections.deque = collections.deque(maxlen=max(1, round(GPS1_LAG_S / self.dt_s)) + 1)
        self._baro_period_steps = max(1, round(1.0 / (self.noise.baro_rate_hz * self.dt_s)))
        self._sample_period_steps = max(1, round(SAMPLE_PERIOD_S / self.dt_s))
        self._last_prearm_report_t_s: float | None = None
        self._gps2_announced = False
        self.outbox: list[tuple[int, str]] = []
        self.events: list[dict[str, Any]] = []
        self.samples: list[dict[str, Any]] = []
        self.gps_input_arrivals_t_s: list[float] = []
        self.gps_input_dropped = 0
        self.takeoff_t_s: float | None = None
        self.failure_t_s: float | None = None
        self.switch_to_gps2_t_s: float | None = None
        self.landed_t_s: float | None = None
        self.landing_error_m: float | None = None
        self._faults_said: set[int] = set()

    # -- injected faults -------------------------------------------------------------------------------------

    def faults_active(self, kind: str) -> list[Fault]:
        """The faults of ``kind`` under way now (their times count from take-off)."""
        if self.takeoff_t_s is None:
            return []
        t = self.t_s - self.takeoff_t_s
        return [f for f in self.options.faults if f.kind == kind and f.in_effect(t)]

    def _announce_faults(self, t_s: float) -> None:
        if self.takeoff_t_s is None:
            return
        for k, f in enumerate(self.options.faults):
            if k not in self._faults_said and t_s - self.takeoff_t_s >= f.at_s:
                self._faults_said.add(k)
                self.add_event("fault", kind=f.kind, for_s=f.for_s)
                self._say(MAV.MAV_SEVERITY_INFO, f"EMU: fault {f.kind} for {f.for_s:g} s")

    # -- time and configuration -----------------------------------------------------------------------------

    @property
    def t_s(self) -> float:
        """Emulated time since boot, s."""
        return self.step_index * self.dt_s

    @property
    def finished(self) -> bool:
        return self.landed_t_s is not None and self.t_s >= self.landed_t_s + LINGER_AFTER_LANDING_S

    def configured(self) -> tuple[bool, bool]:
        """Which GPS instances are configured (GPS1 is SITL's, always; GPS2 when GPS2_TYPE is not 0)."""
        return True, int(self.params["GPS2_TYPE"]) != GPS_TYPE_NONE

    def set_param(self, name: str, value: float) -> float:
        """PARAM_SET: store ``value`` (unknown names are kept and echoed, without effect); return the new value."""
        old = self.params.get(name)
        self.params[name] = int(value) if name in ("SIM_GPS1_ENABLE", "GPS2_TYPE", "GPS_AUTO_SWITCH", "GPS_PRIMARY", "GPS2_DELAY_MS") \
            else float(value)
        if name == "SIM_GPS1_ENABLE" and old != self.params[name]:
            self._gps1_enable_changed(bool(self.params[name]))
        return self.params[name]

    def _gps1_enable_changed(self, enabled: bool) -> None:
        if enabled:
            self.add_event("gps1_restored")
            self._say(MAV.MAV_SEVERITY_INFO, "EMU: SIM_GPS1_ENABLE=1, GPS 1 back")
            return
        if self.failure_t_s is None:
            self.failure_t_s = self.t_s
        self.add_event("gps1_failed")
        self._say(MAV.MAV_SEVERITY_WARNING, "EMU: SIM_GPS1_ENABLE=0, GPS 1 lost fix")

    # -- GPS ---------------------------------------------------------------------------------------------------

    def handle_gps_input(self, msg: Any) -> bool:
        """A GPS_INPUT that arrived now. Returns True when GPS2 took it (GPS2_TYPE 14 and ``gps_id`` 1)."""
        if int(self.params["GPS2_TYPE"]) != GPS_TYPE_MAV or int(msg.gps_id) != 1:
            self.gps_input_dropped += 1
            return False
        t_s = self.t_s
        reading = gps_input_to_reading(msg, self.frame, self.gps[1].reading(t_s))
        self.gps_input_arrivals_t_s.append(t_s)
        if not self._gps2_announced:
            self._gps2_announced = True
            self._say(MAV.MAV_SEVERITY_INFO, "GPS 2: detected MAV")
        self._on_gps_reading(1, reading, t_s)
        return True

    def _on_gps_reading(self, instance: int, reading: GpsReading, t_s: float) -> None:
        self.gps[instance].on_message(t_s, reading)
        self._update_primary(t_s)
        if instance == self.selector.primary and self.gps[instance].usable(t_s):
            # The EKF fuses a GPS reading against its state ``lag`` ago and carries it forward (GPS2_DELAY_MS;
            # 0 means ArduPilot's 200 ms; GPS1's lag is known to it from the receiver type).
            lag_s = GPS1_LAG_S if instance == 0 else (int(self.params["GPS2_DELAY_MS"]) or 200) / 1000.0
            self.estimator.on_fix(t_s - lag_s, reading.p_ned_m, reading.v_ned_m_s)

    def _update_primary(self, t_s: float) -> None:
        before = self.selector.primary
        fix = [g.selection_fix(t_s) for g in self.gps]
        sats = [g.satellites(t_s) for g in self.gps]
        after = self.selector.update(t_s, fix, sats, self.configured(), int(self.params["GPS_AUTO_SWITCH"]),
                                     int(self.params["GPS_PRIMARY"]))
        if after == before:
            return
        self.add_event("primary_changed", **{"from": before, "to": after})
        self._say(MAV.MAV_SEVERITY_INFO, f"EMU: GPS primary now GPS {after + 1}")
        if after == 1 and self.failure_t_s is not None and self.switch_to_gps2_t_s is None:
            self.switch_to_gps2_t_s = t_s

    def _gps1_tick(self, t_s: float) -> None:
        self._motion_history.append((self.craft.p_ned_m.copy(), self.craft.v_ned_m_s.copy()))
        if self.step_index % self._gps1_period_steps == 0:
            reading = self._gps1_reading()
            t_fault = t_s - self.takeoff_t_s if self.takeoff_t_s is not None else None
            if not any(f.gps1_silent(t_fault) for f in self.faults_active("gps1_dropout")):
                self._on_gps_reading(0, reading, t_s)

    def _gps1_reading(self) -> GpsReading:
        """SITL's GPS1: the truth ``GPS1_LAG_S`` ago plus white noise; fix 6 and 10 satellites, or fix 0 and 3
        when disabled."""
        sigma_m = np.array([self.noise.gps_horizontal_m, self.noise.gps_horizontal_m, self.noise.gps_vertical_m])
        p_then, v_then = self._motion_history[0]  # GPS1_LAG_S ago (or the start)
        p_ned_m = p_then + self._rng_gps1.standard_normal(3) * sigma_m
        v_ned_m_s = v_then + self._rng_gps1.standard_normal(3) * GPS1_VELOCITY_NOISE_M_S
        h_acc_m = self.noise.gps_horizontal_m
        t_fault = self.t_s - self.takeoff_t_s if self.takeoff_t_s is not None else 0.0
        for f in self.faults_active("gps1_drag"):
            p_ned_m[:2] += f.drag_ne_m(t_fault)
            if t_fault < f.at_s + f.for_s:
                v_ned_m_s[:2] += f.drag_velocity_ne_m_s()  # a drag is a velocity too (it fools a velocity check)
        for f in self.faults_active("gps1_inflated"):
            p_ned_m[:2] += self._rng_gps1.standard_normal(2) * f.h_acc_m
            h_acc_m = max(h_acc_m, f.h_acc_m)
        lat_deg, lon_deg, alt_m = self.frame.to_geodetic(p_ned_m)
        enabled = bool(self.params["SIM_GPS1_ENABLE"])
        return GpsReading(GPS1_HEALTHY_FIX if enabled else GPS1_FAILED_FIX, int(round(float(lat_deg) * 1e7)),
                          int(round(float(lon_deg) * 1e7)), float(alt_m), p_ned_m, v_ned_m_s,
                          GPS1_HEALTHY_SATS if enabled else GPS1_FAILED_SATS, h_acc_m)

    def _baro_tick(self) -> None:
        """The vertical channel (barometer with the IMU): height and climb rate, sampled and held."""
        if self.step_index % self._baro_period_steps == 0:
            self.baro_height_m = -self.craft.p_ned_m[2] + self.noise.altitude_m * self._rng_baro.standard_normal()
            self.baro_climb_m_s = -self.craft.v_ned_m_s[2] + BARO_CLIMB_NOISE_M_S * self._rng_baro.standard_normal()

    def estimate_ned(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The vehicle's own estimate: (p_ned_m (3,), v_ned_m_s (3,)); horizontal from GPS, vertical from baro."""
        p_ne_m, v_ne_m_s = self.estimator.horizontal(t_s)
        return np.array([*p_ne_m, -self.baro_height_m]), np.array([*v_ne_m_s, -self.baro_climb_m_s])

    # -- the step ----------------------------------------------------------------------------------------------

    def step(self) -> None:
        """Advance one ``dt_s``: sensors, GPS selection, mission and physics, then the log sample."""
        t_s = self.t_s
        self._inject_scheduled_failure(t_s)
        self._announce_faults(t_s)
        self._gps1_tick(t_s)
        self._baro_tick()
        self._update_primary(t_s)
        if self.phase is Phase.WAIT_ARM:
            self._wait_for_arming(t_s)
        elif self.phase is not Phase.LANDED:
            self._fly(t_s)
        if self.step_index % self._sample_period_steps == 0:
            self._record(t_s)
        self.step_index += 1

    def _inject_scheduled_failure(self, t_s: float) -> None:
        at_s, at_index = self.options.fail_gps1_at_s, self.options.fail_gps1_at_index
        if self.takeoff_t_s is None or self.failure_t_s is not None:
            return
        if (at_s is not None and t_s >= self.takeoff_t_s + at_s - 1e-9) or (at_index is not None and self._reached_index() >= at_index):
            self.set_param("SIM_GPS1_ENABLE", 0)

    def _reached_index(self) -> int:
        """With a mission: the index in its path of the last waypoint reached (0, home, until the take-off's top)."""
        if self.phase is Phase.TAKEOFF:
            return 1 if self._guide is not None and self._guide.done else 0
        if self.phase is Phase.SURVEY:
            return self._guide.target  # the survey's waypoint j is the path's j + 1; target j + 1 once it is reached
        return len(self.options.mission_path_ned_m or ()) - 2 if self.phase is not Phase.WAIT_ARM else 0

    def _wait_for_arming(self, t_s: float) -> None:
        if t_s < BOOT_S:
            return
        failure = prearm_gps_failure(self.gps, self.configured(), t_s)
        if failure is None and self.estimator.age_s(t_s) > GPS_FRESH_S:
            failure = "Need Position Estimate"
        if failure is not None:
            if self._last_prearm_report_t_s is None or t_s - self._last_prearm_report_t_s >= PREARM_REPORT_PERIOD_S:
                self._last_prearm_report_t_s = t_s
                self._say(MAV.MAV_SEVERITY_CRITICAL, f"PreArm: {failure}")
            return
        self._arm_and_take_off(t_s)

    def _arm_and_take_off(self, t_s: float) -> None:
        self.armed = True
        self.takeoff_t_s = t_s
        p_est, _ = self.estimate_ned(t_s)
        path = self.options.mission_path_ned_m
        height_m = -path[1][2] if path is not None else self.options.altitude_m
        top = np.array([p_est[0], p_est[1], -height_m])
        self._guide = WaypointGuidance(np.vstack([p_est, top]), TAKEOFF_SPEED_M_S, self.vehicle)
        self._enter(Phase.TAKEOFF, CopterMode.GUIDED)
        self.add_event("takeoff")
        self._say(MAV.MAV_SEVERITY_INFO, f"EMU: armed, taking off to {height_m:.1f} m")

    def _enter(self, phase: Phase, mode: CopterMode) -> None:
        self.phase = phase
        if mode != self.mode:
            self.mode = mode
            self.add_event("mode", mode=mode.name)

    def _fly(self, t_s: float) -> None:
        self._check_failsafe(t_s)
        p_est, v_est = self.estimate_ned(t_s)
        v_des = self._mission_command(p_est)
        blind = not self.estimator.has_reference(t_s)
        if blind:
            v_des[:2] = v_est[:2]  # no horizontal reference: no horizontal correction at all
        a_ned, euler = self.craft.command(v_des, self.yaw_goal_rad, self._rng_physics, v_est=v_est)
        if blind:
            a_ned = a_ned + self._uncancelled_drag()
        self.craft.advance(a_ned)
        self._ground_contact()
        self._set_motion(a_ned, np.asarray(euler))
        if self.phase is Phase.DESCEND and -self.craft.p_ned_m[2] < TOUCHDOWN_HEIGHT_M:
            self._touch_down(t_s)

    def _uncancelled_drag(self) -> np.ndarray:
        """Blind, the thrust stays level: the model's drag, which its thrust would cancel, acts (horizontal)."""
        cfg = self.vehicle
        wind = np.array([cfg.wind_north_m_s, cfg.wind_east_m_s, 0.0])
        drag = -cfg.drag_per_s * (self.craft.v_ned_m_s - wind)
        drag[2] = 0.0
        return drag

    def _set_motion(self, a_ned_m_s2: np.ndarray, euler_rad: np.ndarray) -> None:
        self.rates_body_rad_s = body_rates_from_euler_rates(euler_rad, euler_step_rad(self.euler_rad, euler_rad) / self.dt_s)
        self.a_ned_m_s2, self.euler_rad = a_ned_m_s2, euler_rad

    def _ground_contact(self) -> None:
        if self.craft.p_ned_m[2] > 0.0:
            self.craft.p_ned_m[2] = 0.0
            self.craft.v_ned_m_s = np.array([*self.craft.v_ned_m_s[:2], min(self.craft.v_ned_m_s[2], 0.0)])

    def _check_failsafe(self, t_s: float) -> None:
        if self.mode is CopterMode.LAND or not self.estimator.failsafe_due(t_s):
            return
        self._land_target_ne_m = self.estimator.horizontal(t_s)[0]
        self._enter(Phase.DESCEND, CopterMode.LAND)
        self.failsafe = True
        self.add_event("failsafe")
        self._say(MAV.MAV_SEVERITY_CRITICAL, "EKF Failsafe: changed to LAND Mode")

    def _mission_command(self, p_est_ned_m: np.ndarray) -> np.ndarray:
        """The velocity command (NED, m/s) for the current phase, from the estimated position; moves phases on."""
        if self.phase is Phase.DESCEND:
            return self._descent_command(p_est_ned_m)
        v_des = self._guide.command(p_est_ned_m)
        if self.phase is not Phase.TAKEOFF:
            self.yaw_goal_rad = self._guide.yaw_goal_rad
        if self._guide.done:
            self._next_phase(p_est_ned_m)
        return v_des

    def _descent_command(self, p_est_ned_m: np.ndarray) -> np.ndarray:
        v_ne = LAND_POSITION_GAIN_PER_S * (self._land_target_ne_m - p_est_ned_m[:2])
        speed = np.linalg.norm(v_ne)
        if speed > LAND_MAX_HORIZONTAL_M_S:
            v_ne *= LAND_MAX_HORIZONTAL_M_S / speed
        return np.array([*v_ne, LAND_SPEED_M_S])

    def _next_phase(self, p_est_ned_m: np.ndarray) -> None:
        alt_m = self.options.altitude_m
        path = self.options.mission_path_ned_m
        if path is not None:  # the mission's places, then its landing (at home after a return to launch)
            if self.phase is Phase.TAKEOFF:
                self._guide = WaypointGuidance(np.vstack([p_est_ned_m, np.array(path[2:-1])]), self.options.mission_speed_m_s,
                                               self.vehicle)
                self._enter(Phase.SURVEY, CopterMode.AUTO)
            elif self.phase is Phase.SURVEY:
                self._land_target_ne_m = np.array(path[-1][:2])
                self._enter(Phase.DESCEND, CopterMode.RTL if np.allclose(path[-1], 0.0) else CopterMode.LAND)
            return
        if self.phase is Phase.TAKEOFF:
            wps = np.vstack([p_est_ned_m, lawnmower_waypoints(self.survey, alt_m)])
            self._guide = WaypointGuidance(wps, self.survey.speed_m_s, self.vehicle)
            self._enter(Phase.SURVEY, CopterMode.AUTO)
        elif self.phase is Phase.SURVEY:
            wps = np.vstack([p_est_ned_m, [0.0, 0.0, -alt_m]])
            self._guide = WaypointGuidance(wps, self.survey.speed_m_s, self.vehicle)
            self._enter(Phase.RETURN, CopterMode.RTL)
        elif self.phase is Phase.RETURN:
            self._land_target_ne_m = np.zeros(2)
            self._enter(Phase.DESCEND, CopterMode.RTL)

    def _touch_down(self, t_s: float) -> None:
        self.craft.p_ned_m[2] = 0.0
        self.craft.v_ned_m_s = np.zeros(3)
        self._set_motion(np.zeros(3), np.array([0.0, 0.0, self.euler_rad[2]]))
        self.armed = False
        self.phase = Phase.LANDED
        self.landed_t_s = t_s
        self.landing_error_m = float(np.linalg.norm(self.craft.p_ned_m[:2]))
        self.add_event("landed", landing_error_m=self.landing_error_m)
        self._say(MAV.MAV_SEVERITY_INFO, f"EMU: landed {self.landing_error_m:.2f} m from home, disarmed")

    # -- events and log ----------------------------------------------------------------------------------------

    def _say(self, severity: int, text: str) -> None:
        log.info("%.2f s: %s", self.t_s, text)
        self.outbox.append((severity, text))

    def add_event(self, name: str, **fields: Any) -> None:
        self.events.append({"t_s": round(self.t_s, 3), "event": name, **fields})

    def _record(self, t_s: float) -> None:
        p_est, _ = self.estimate_ned(t_s)
        self.samples.append({
            "t_s": round(t_s, 3),
            "truth_ned_m": [round(float(x), 4) for x in self.craft.p_ned_m],
            "estimate_ned_m": [round(float(x), 4) for x in p_est],
            "gps2_ned_m": None if (r2 := self.gps[1].reading(t_s)) is None else [round(float(x), 4) for x in r2.p_ned_m],
            "gps2_h_acc_m": None if r2 is None else round(float(r2.h_acc_m), 4),
            "primary": self.selector.primary if any(g.fix_type(t_s) > FIX_NO_GPS for g in self.gps) else None,
            "gps1_fix": self.gps[0].fix_type(t_s),
            "gps2_fix": self.gps[1].fix_type(t_s),
            "gps2_healthy": self.gps[1].healthy(t_s),
            "mode": self.mode.name,
            "phase": self.phase.value,
            "armed": self.armed,
            "nav": self.estimator.state(t_s),
        })

    def log_dict(self, exit_reason: str, link_stats: dict[str, int] | None = None,
                 clock_pairs: list[tuple[float, float]] | None = None) -> dict[str, Any]:
        """Everything the JSON log holds."""
        return {
            "exit_reason": exit_reason,
            "options": asdict(self.options),
            "origin": asdict(self.frame),
            "end_t_s": round(self.t_s, 3),
            "samples": self.samples,
            "gps_input_arrivals_t_s": [round(t, 4) for t in self.gps_input_arrivals_t_s],
            "gps_input_dropped": self.gps_input_dropped,
            "events": self.events,
            "landing_error_m": self.landing_error_m,
            "failure_t_s": self.failure_t_s,
            "switch_to_gps2_t_s": self.switch_to_gps2_t_s,
            "gps_input": gps_input_stats(self.gps_input_arrivals_t_s),
            "link": link_stats or {},
            "monotonic_clock": clock_pairs or [],  # (emulated s, monotonic s) pairs
        }

    # -- sensors the streams report ----------------------------------------------------------------------------

    def specific_force_body_m_s2(self) -> np.ndarray:
        """True specific force in the body frame (FRD), m/s^2: what an ideal accelerometer reads."""
        R_ned_body = R_ned_body_from_euler(*self.euler_rad)
        return R_ned_body.T @ (self.a_ned_m_s2 - np.array([0.0, 0.0, GRAVITY_M_S2]))

    def imu_sample(self) -> np.ndarray:
        """Accelerometer reading (body FRD, m/s^2): specific force + the run's constant bias + white noise."""
        noise = self.rng_telemetry.standard_normal(3) * self.noise.accel_noise_m_s2
        return self.specific_force_body_m_s2() + self.imu_bias_body_m_s2 + noise

    def attitude_sample(self) -> np.ndarray:
        """Attitude estimate (roll, pitch, yaw rad): the truth plus white noise."""
        sigma = np.deg2rad([self.noise.attitude_deg, self.noise.attitude_deg, self.noise.heading_deg])
        return self.euler_rad + self.rng_telemetry.standard_normal(3) * sigma


def write_log_atomic(path: Path, data: dict[str, Any]) -> None:
    """Write ``data`` as JSON to ``path`` through a temporary file in the same directory and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=1)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


# ---------------------------------------------------------------------------------------------------------------
# I/O


class TcpServerLink(mavutil.mavtcpin):
    """pymavlink's ``tcpin`` server (127.0.0.1 only), changed where a vehicle that outlives its client needs it.

    pymavlink's own never notices an orderly disconnect (``recv`` returns b'' for ever) and can cut a message
    in half on a full non-blocking send. Here a disconnect drops the client and the next connection is accepted
    with a fresh parser; output is queued and sent whole, and dropped while more than 256 kB are queued.
    """

    MAX_QUEUED_BYTES = 256 * 1024

    def __init__(self, port: int) -> None:
        super().__init__(f"127.0.0.1:{port}", source_system=1, source_component=1)
        self._out = bytearray()
        self.dropped_bytes = 0
        self.connections = 0

    @property
    def connected(self) -> bool:
        return self.port is not None

    def recv(self, n: int | None = None) -> bytes:
        if self.port is None and not self._accept():
            return b""
        try:
            data = self.port.recv(4096)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            self._drop_client(f"receive failed: {exc}")
            return b""
        if not data:
            self._drop_client("client closed the connection")
        return data

    def write(self, buf: bytes) -> None:
        if self.port is None:
            return
        if len(self._out) + len(buf) > self.MAX_QUEUED_BYTES:
            self.dropped_bytes += len(buf)
            return
        self._out += buf
        self.flush()

    def flush(self) -> None:
        """Send what the socket takes now; keep the rest queued."""
        while self._out and self.port is not None:
            try:
                sent = self.port.send(self._out)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                self._drop_client(f"send failed: {exc}")
                return
            del self._out[:sent]

    def _accept(self) -> bool:
        try:
            self.port, address = self.listen.accept()
        except (BlockingIOError, InterruptedError):
            return False
        self.port.setblocking(False)
        self.port.setsockopt(socket.SOL_TCP, socket.TCP_NODELAY, 1)
        mavutil.set_close_on_exec(self.port.fileno())
        self.fd = self.port.fileno()
        self._out.clear()
        self.mav = MAV.MAVLink(self, srcSystem=self.source_system, srcComponent=self.source_component)
        self.mav.robust_parsing = True
        self.connections += 1
        log.info("client connected from %s:%d", *address)
        return True

    def _drop_client(self, why: str) -> None:
        log.info("client gone (%s); waiting for the next one", why)
        self.port.close()
        self.port = None
        self.fd = self.listen.fileno()
        self._out.clear()


def open_link(port: int) -> TcpServerLink:
    try:
        return TcpServerLink(port)
    except OSError as exc:
        raise EmulatorError(f"cannot serve MAVLink on 127.0.0.1:{port}: {exc}") from exc


PARAM_TYPES = {name: MAV.MAV_PARAM_TYPE_INT8 for name in ("SIM_GPS1_ENABLE", "GPS2_TYPE", "GPS_AUTO_SWITCH",
                                                          "GPS_PRIMARY")} | {"GPS2_DELAY_MS": MAV.MAV_PARAM_TYPE_INT16}
MAX_MESSAGES_PER_POLL = 200
FIRMWARE_VERSION = (4, 7, 0)  # what AUTOPILOT_VERSION reports: the SITL build beside the project
MAX_LAG_S = 0.25  # emulated s the loop may run behind the wall clock; beyond, the clock slips (a stalled
# process would otherwise catch up in a burst and open gaps in the GPS_INPUT it receives)
SYSTEM_ID = 1


class MavlinkServer:
    """Runs a ``VehicleSim`` on the wall clock times ``speedup`` and speaks MAVLink for it over ``link``."""

    def __init__(self, sim: VehicleSim, link: TcpServerLink, speedup: float) -> None:
        self.sim = sim
        self.link = link
        self.speedup = speedup
        self.streams = StreamScheduler(DEFAULT_RATES_HZ)
        self.unix_t0_s = time.time()
        self.link_errors = 0
        self.clock_slips = 0
        self._stuck_alt_mm: int | None = None  # height_stuck: the relative altitude that repeats
        self.boot_t0_s = 0.0  # emulated time the boot clock read 0 at (moved by an injected autopilot_reboot)
        self._rebooting = False
        # (emulated s, this machine's monotonic s) once an emulated second: to put the companion's logs, stamped
        # on the same monotonic clock, beside the truth
        self.clock_pairs: list[tuple[float, float]] = []
        self._senders: dict[str, Callable[[], None]] = {
            name: getattr(self, f"_send_{name}") for name in DEFAULT_RATES_HZ
        }
        self._senders["AUTOPILOT_VERSION"] = self._send_AUTOPILOT_VERSION  # on request only
        self._handlers: dict[str, Callable[[Any], None]] = {
            "GPS_INPUT": self.sim.handle_gps_input,
            "PARAM_SET": self._on_param_set,
            "PARAM_REQUEST_READ": self._on_param_request_read,
            "PARAM_REQUEST_LIST": self._on_param_request_list,
            "COMMAND_LONG": self._on_command_long,
            "REQUEST_DATA_STREAM": self._on_request_data_stream,
            "STATUSTEXT": self._on_statustext,
        }

    # -- the loop ----------------------------------------------------------------------------------------------

    def run(self) -> str:
        """Serve until the vehicle has landed ("landed") or ``max_seconds`` of emulated time ("max_seconds")."""
        sim = self.sim
        wall0_s = time.monotonic()
        while not sim.finished:
            if sim.t_s >= sim.options.max_seconds:
                sim.add_event("max_seconds")
                return "max_seconds"
            target_t_s = (time.monotonic() - wall0_s) * self.speedup
            if sim.t_s > target_t_s:
                time.sleep(min((sim.t_s - target_t_s) / self.speedup, 0.01))
                continue
            if target_t_s - sim.t_s > MAX_LAG_S:
                wall0_s += (target_t_s - sim.t_s - MAX_LAG_S) / self.speedup
                self.clock_slips += 1
            rebooting = self._reboot_tick()
            self._poll_link(handle=not rebooting)
            if sim.step_index % round(1.0 / sim.dt_s) == 0:
                self.clock_pairs.append((round(sim.t_s, 3), round(time.monotonic(), 4)))
            sim.step()
            if rebooting:
                sim.outbox.clear()
                self.streams.due(sim.t_s)
            else:
                self._send_due()
        return "landed"

    def _reboot_tick(self) -> bool:
        """True while an injected ``autopilot_reboot`` keeps the autopilot silent and deaf. As it ends, the boot
        clock starts again from 0 and every stream but HEARTBEAT is off: message intervals asked for are not kept
        over a restart, and a copter's SRn_ rates are all 0 (GCS_MAVLink_Parameters.cpp)."""
        rebooting = bool(self.sim.faults_active("autopilot_reboot"))
        if self._rebooting and not rebooting:
            self.boot_t0_s = self.sim.t_s
            for name in self.streams.interval_s:
                if name != "HEARTBEAT":
                    self.streams.set_interval(name, None, self.sim.t_s)
            self.sim.add_event("rebooted")
        self._rebooting = rebooting
        return rebooting

    def link_stats(self) -> dict[str, int]:
        return {"connections": self.link.connections, "errors": self.link_errors,
                "dropped_bytes": self.link.dropped_bytes, "clock_slips": self.clock_slips}

    def _poll_link(self, handle: bool = True) -> None:
        """Read what has come in; handle it unless ``handle`` is False (a rebooting autopilot hears nothing)."""
        for _ in range(MAX_MESSAGES_PER_POLL):
            try:
                msg = self.link.recv_msg()
                if msg is None:
                    return
                if handle:
                    self._handle(msg)
            except Exception:  # one bad message must not stop the vehicle: log it and go on
                self.link_errors += 1
                log.exception("error while reading or handling a MAVLink message; ignored")

    def _handle(self, msg: Any) -> None:
        handler = self._handlers.get(msg.get_type())
        if handler is None:  # BAD_DATA, HEARTBEATs of other systems, anything else: nothing to do
            return
        if hasattr(msg, "target_system") and msg.target_system not in (0, SYSTEM_ID):
            return
        handler(msg)

    def _send_due(self) -> None:
        self.link.flush()
        while self.sim.outbox:
            severity, text = self.sim.outbox.pop(0)
            if self.link.connected:
                self.link.mav.statustext_send(severity, text.encode()[:50])
        if not self.link.connected:
            self.streams.due(self.sim.t_s)  # keep the schedule moving without encoding anything
            return
        twice = bool(self.sim.faults_active("telemetry_duplicated"))
        for name in self.streams.due(self.sim.t_s):
            if name == "ATTITUDE" and self.sim.faults_active("attitude_stops"):
                continue
            self._senders[name]()
            if twice and name in ("ATTITUDE", "SCALED_IMU", "GLOBAL_POSITION_INT"):
                self._senders[name]()

    # -- handlers ----------------------------------------------------------------------------------------------

    def _on_statustext(self, msg: Any) -> None:
        """A companion's STATUSTEXT: logged, as ArduPilot's dataflash log keeps them (and routes them to the GCS)."""
        text = msg.text.decode(errors="replace") if isinstance(msg.text, bytes) else str(msg.text)
        self.sim.add_event("statustext", severity=int(msg.severity), text=text.rstrip("\x00"))

    def _on_param_set(self, msg: Any) -> None:
        name = _param_name(msg.param_id)
        value = self.sim.set_param(name, msg.param_value)
        self._send_param(name, value, param_type=msg.param_type)

    def _on_param_request_read(self, msg: Any) -> None:
        names = list(self.sim.params)
        name = _param_name(msg.param_id)
        if msg.param_index >= 0:
            name = names[msg.param_index] if msg.param_index < len(names) else ""
        if name in self.sim.params:
            self._send_param(name, self.sim.params[name])

    def _on_param_request_list(self, msg: Any) -> None:
        for name, value in self.sim.params.items():
            self._send_param(name, value)

    def _send_param(self, name: str, value: float, param_type: int | None = None) -> None:
        names = list(self.sim.params)
        ptype = PARAM_TYPES.get(name, param_type or MAV.MAV_PARAM_TYPE_REAL32)
        self.link.mav.param_value_send(name.encode(), float(value), ptype, len(names), names.index(name))

    def _on_command_long(self, msg: Any) -> None:
        if msg.command == MAV.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self._set_message_interval(int(msg.param1), msg.param2)
        elif msg.command == MAV.MAV_CMD_REQUEST_MESSAGE:
            name = _message_name(int(msg.param1))
            result = MAV.MAV_RESULT_ACCEPTED if name in self._senders else MAV.MAV_RESULT_DENIED
            if name in self._senders:
                self._senders[name]()
        else:
            result = MAV.MAV_RESULT_UNSUPPORTED
        self.link.mav.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())

    def _set_message_interval(self, msg_id: int, interval_us: float) -> int:
        """MAV_CMD_SET_MESSAGE_INTERVAL: -1 stops the message, 0 restores its default rate."""
        name = _message_name(msg_id)
        if name not in self._senders:
            return MAV.MAV_RESULT_DENIED
        if interval_us < 0:
            interval_s = None
        elif interval_us == 0:
            interval_s = self.streams.default_interval_s[name]
        else:
            interval_s = max(interval_us * 1e-6, self.sim.dt_s)
        self.streams.set_interval(name, interval_s, self.sim.t_s)
        return MAV.MAV_RESULT_ACCEPTED

    def _on_request_data_stream(self, msg: Any) -> None:
        if msg.req_stream_id == MAV.MAV_DATA_STREAM_ALL:
            names = [n for group in DATA_STREAMS.values() for n in group]
        else:
            names = list(DATA_STREAMS.get(msg.req_stream_id, ()))
        on = msg.start_stop and msg.req_message_rate > 0
        for name in names:
            self.streams.set_interval(name, 1.0 / msg.req_message_rate if on else None, self.sim.t_s)

    # -- telemetry ---------------------------------------------------------------------------------------------

    def _time_boot_ms(self) -> int:
        return int(round((self.sim.t_s - self.boot_t0_s) * 1e3))

    def _send_HEARTBEAT(self) -> None:
        sim = self.sim
        base_mode = MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (MAV.MAV_MODE_FLAG_SAFETY_ARMED if sim.armed else 0)
        if sim.failsafe and sim.armed:
            status = MAV.MAV_STATE_CRITICAL
        else:
            status = MAV.MAV_STATE_ACTIVE if sim.armed else MAV.MAV_STATE_STANDBY
        self.link.mav.heartbeat_send(MAV.MAV_TYPE_QUADROTOR, MAV.MAV_AUTOPILOT_ARDUPILOTMEGA, base_mode,
                                     int(sim.mode), status)

    def _send_AUTOPILOT_VERSION(self) -> None:
        major, minor, patch = FIRMWARE_VERSION
        version = (major << 24) | (minor << 16) | (patch << 8) | 0  # FIRMWARE_VERSION_TYPE_DEV
        self.link.mav.autopilot_version_send(MAV.MAV_PROTOCOL_CAPABILITY_MAVLINK2, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0)

    def _send_SYSTEM_TIME(self) -> None:
        self.link.mav.system_time_send(int((self.unix_t0_s + self.sim.t_s) * 1e6), self._time_boot_ms())

    def _send_ATTITUDE(self) -> None:
        roll, pitch, yaw = self.sim.attitude_sample()
        p, q, r = self.sim.rates_body_rad_s
        self.link.mav.attitude_send(self._time_boot_ms(), roll, pitch, float(_wrap_pi(yaw)), p, q, r)

    def _send_SCALED_IMU(self) -> None:
        acc_mg = np.clip(np.rint(self.sim.imu_sample() / GRAVITY_M_S2 * 1e3), -32768, 32767).astype(int)
        gyro_mrad_s = np.clip(np.rint(self.sim.rates_body_rad_s * 1e3), -32768, 32767).astype(int)
        self.link.mav.scaled_imu_send(self._time_boot_ms(), *acc_mg.tolist(), *gyro_mrad_s.tolist(), 0, 0, 0, 4500)

    def _send_GLOBAL_POSITION_INT(self) -> None:
        sim = self.sim
        p_ned_m, v_ned_m_s = sim.estimate_ned(sim.t_s)
        lat_deg, lon_deg, alt_m = sim.frame.to_geodetic(p_ned_m)
        heading_deg = math.degrees(float(sim.attitude_sample()[2])) % 360.0
        vx, vy, vz = (int(round(v * 100)) for v in v_ned_m_s)
        relative_alt_mm = int(round(-p_ned_m[2] * 1e3))
        if sim.faults_active("height_stuck"):
            if self._stuck_alt_mm is None:
                self._stuck_alt_mm = relative_alt_mm
            relative_alt_mm = self._stuck_alt_mm
        else:
            self._stuck_alt_mm = None
        self.link.mav.global_position_int_send(
            self._time_boot_ms(), _e7(lat_deg), _e7(lon_deg), int(round(float(alt_m) * 1e3)),
            relative_alt_mm, vx, vy, vz, int(round(heading_deg * 100)) % 36000)

    def _send_GPS_RAW_INT(self) -> None:
        fields = self._gps_fields(0)
        self.link.mav.gps_raw_int_send(*fields[:10], 0, fields[10])

    def _send_GPS2_RAW(self) -> None:
        if not self.sim.configured()[1]:
            return
        fields = self._gps_fields(1)
        self.link.mav.gps2_raw_send(*fields[:10], 0, 0, 0, 0, fields[10])

    def _gps_fields(self, instance: int) -> tuple:
        """time_usec, fix, lat, lon, alt mm, eph, epv, vel cm/s, cog cdeg, sats, h_acc mm of one instance.

        ``time_usec`` is the boot time of the latest fix, as AP_GPS::send_mavlink_gps_raw sends it
        (``last_fix_time_ms * 1000``): the stream may send a reading up to one GPS period after it arrived.
        """
        t_s = self.sim.t_s
        gps = self.sim.gps[instance]
        reading = gps.reading(t_s)
        fix = gps.fix_type(t_s)
        if reading is None:
            return int((t_s - self.boot_t0_s) * 1e6), fix, 0, 0, 0, 65535, 65535, 0, 0, 0, 0
        t_fix_s = gps.last_fix_t_s if gps.last_fix_t_s is not None else t_s
        v = reading.v_ned_m_s
        cog_cdeg = int(round(math.degrees(math.atan2(v[1], v[0])) % 360.0 * 100)) % 36000
        h_acc_mm = 0 if math.isnan(reading.h_acc_m) else int(round(reading.h_acc_m * 1e3))
        eph = 121 if fix >= FIX_3D else 9999
        return (int(round(max(t_fix_s - self.boot_t0_s, 0.0) * 1e6)), fix, reading.lat_e7, reading.lon_e7, int(round(reading.alt_amsl_m * 1e3)), eph, 200,
                int(round(math.hypot(v[0], v[1]) * 100)), cog_cdeg, reading.satellites, h_acc_mm)

    def _truth_geodetic(self) -> tuple[int, int, float]:
        lat_deg, lon_deg, alt_m = self.sim.frame.to_geodetic(self.sim.craft.p_ned_m)
        return _e7(lat_deg), _e7(lon_deg), float(alt_m)

    def _send_SIMSTATE(self) -> None:
        sim = self.sim
        lat_e7, lon_e7, _ = self._truth_geodetic()
        roll, pitch, yaw = sim.euler_rad
        self.link.mav.simstate_send(roll, pitch, float(_wrap_pi(yaw)), *sim.specific_force_body_m_s2(),
                                    *sim.rates_body_rad_s, lat_e7, lon_e7)

    def _send_SIM_STATE(self) -> None:
        """The truth. As SITL does, the float lat/lon carry deg * 1e7 too (ARDUPILOT.md): read lat_int/lon_int."""
        sim = self.sim
        lat_e7, lon_e7, alt_m = self._truth_geodetic()
        roll, pitch, yaw = (float(x) for x in sim.euler_rad)
        q = QuaternionBase([roll, pitch, yaw]).q
        vn, ve, vd = (float(v) for v in sim.craft.v_ned_m_s)
        self.link.mav.sim_state_send(*(float(x) for x in q), roll, pitch, float(_wrap_pi(yaw)),
                                     *sim.specific_force_body_m_s2(), *sim.rates_body_rad_s,
                                     float(lat_e7), float(lon_e7), alt_m, 0.0, 0.0, vn, ve, vd, lat_e7, lon_e7)


def _e7(angle_deg: float | np.ndarray) -> int:
    return int(round(float(angle_deg) * 1e7))


def _param_name(param_id: str | bytes) -> str:
    if isinstance(param_id, bytes):
        param_id = param_id.decode("ascii", "replace")
    return param_id.rstrip("\x00")


def _message_name(msg_id: int) -> str:
    cls = MAV.mavlink_map.get(msg_id)
    return "" if cls is None else cls.msgname


# ---------------------------------------------------------------------------------------------------------------
# Command line


EXIT_CODES = {"landed": 0, "max_seconds": 3, "interrupted": 130}


def run_emulator(frame: LocalFrame, options: EmulatorOptions, *, port: int, speedup: float,
                 log_path: Path | None) -> int:
    """Serve one flight; write the log (also when interrupted); return the exit code."""
    sim = VehicleSim(frame, options)
    link = open_link(port)
    server = MavlinkServer(sim, link, speedup)
    log.info("serving MAVLink 2 on 127.0.0.1:%d, speedup %g", port, speedup)
    reason = "interrupted"
    try:
        reason = server.run()
    except KeyboardInterrupt:
        log.info("interrupted at %.2f s", sim.t_s)
    finally:
        link.close()
        if log_path is not None:
            write_log_atomic(log_path, sim.log_dict(reason, server.link_stats(), server.clock_pairs))
    return EXIT_CODES[reason]


def _raise_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--port", type=int, default=5760, help="TCP port on 127.0.0.1 (default 5760)")
    ap.add_argument("--world", required=True, help="world YAML; its origin is home")
    ap.add_argument("--altitude", type=float, default=15.0, help="survey height above home, m (default 15)")
    ap.add_argument("--speedup", type=float, default=1.0, help="emulated seconds per wall second (default 1)")
    ap.add_argument("--fail-gps1-at", type=float, help="seconds after take-off to set SIM_GPS1_ENABLE=0")
    ap.add_argument("--gps2-type", type=int, choices=(0, 14), default=14, help="GPS2_TYPE: 14 MAVLink GPS, 0 none")
    ap.add_argument("--auto-switch", type=int, choices=(0, 1, 2, 4), default=1, help="GPS_AUTO_SWITCH (2 acts as 1)")
    ap.add_argument("--gps-primary", type=int, choices=(0, 1), default=0, help="GPS_PRIMARY (default 0)")
    ap.add_argument("--survey-size", type=float, help="side of a square survey about home, m (default: the "
                                                      "mapping survey of SimConfig)")
    ap.add_argument("--mission", type=Path, help="fly this mission (.waypoints or .plan) instead of the survey, at its "
                                                 "own heights, then land where it ends (home after a return)")
    ap.add_argument("--speed-m-s", type=float, default=5.0, help="with --mission: its speed, m/s (default 5)")
    ap.add_argument("--gps-lost-at-waypoint", type=int, help="with --mission: disable GPS1 on reaching this item (its "
                                                             "number in the file)")
    ap.add_argument("--log", type=Path, help="JSON log, written at the end")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--max-seconds", type=float, default=1800.0, help="hard stop, emulated s (default 1800)")
    ap.add_argument("--faults", type=Path, help="fault file (auxgps eval --faults): its GPS1 and telemetry faults, "
                                                "at_s after take-off")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s vehicle_emulator %(levelname)s %(message)s")
    # SIGINT too: a process started in the background by a non-interactive shell inherits SIGINT ignored, and
    # Python then installs no KeyboardInterrupt for it.
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, _raise_interrupt)
    try:
        if not 1024 <= args.port <= 65535:
            raise EmulatorError(f"--port {args.port}: give 1024 to 65535")
        if not 0 < args.speedup <= 100:
            raise EmulatorError(f"--speedup {args.speedup}: give more than 0, at most 100")
        options = EmulatorOptions(altitude_m=args.altitude, fail_gps1_at_s=args.fail_gps1_at,
                                  gps2_type=args.gps2_type, auto_switch=args.auto_switch,
                                  gps_primary=args.gps_primary, survey_size_m=args.survey_size, seed=args.seed,
                                  max_seconds=args.max_seconds,
                                  faults=tuple(load_fault_plan(args.faults).faults) if args.faults else ()).validate()
        frame = load_world(args.world).frame
        if args.mission is not None:
            mission = load_mission(args.mission)
            path, owner = mission_waypoints_ned(mission, frame)
            lost = gps_lost_waypoint(mission, owner, args.gps_lost_at_waypoint) if args.gps_lost_at_waypoint is not None else None
            options = replace(options, mission_path_ned_m=tuple(map(tuple, path.tolist())),
                                          mission_speed_m_s=args.speed_m_s, fail_gps1_at_index=lost).validate()
        elif args.gps_lost_at_waypoint is not None:
            raise EmulatorError("--gps-lost-at-waypoint goes with --mission")
        return run_emulator(frame, options, port=args.port, speedup=args.speedup, log_path=args.log)
    except AuxGpsError as exc:
        print(f"vehicle_emulator: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
