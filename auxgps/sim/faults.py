"""Faults injected into a simulated flight: a YAML list anyone can write, applied to the frames and telemetry the
estimator is given (never to the truth the evaluator scores against).

A fault file (``auxgps eval --faults FILE``)::

    faults:
      - {kind: camera_frozen, at_s: 40, for_s: 3}       # the driver repeats its last frame, fresh timestamps
      - {kind: camera_dark_half, at_s: 60, for_s: 3}    # a strap over half the lens
      - {kind: camera_saturated, at_s: 80, for_s: 3}    # the sun: half the image white
      - {kind: camera_blur, at_s: 100, for_s: 3, blur_sigma_px: 4}
      - {kind: camera_slow, at_s: 120, for_s: 5, fps: 1}  # the frame rate collapses
      - {kind: attitude_stops, at_s: 140, for_s: 3}     # no ATTITUDE
      - {kind: height_stuck, at_s: 160, for_s: 5}       # the height above home repeats one value
      - {kind: telemetry_duplicated, at_s: 180, for_s: 3}  # every message twice
      - {kind: telemetry_reordered, at_s: 200, for_s: 3}   # each step's messages after the next step's
      - {kind: autopilot_reboot, at_s: 220, for_s: 2}    # silent, then its boot clock from 0 (vehicle emulator only)
      - {kind: gps1_drag, flight: mapping, at_s: 30, for_s: 60, speed_m_s: 0.5, bearing_deg: 45}
      - {kind: gps1_inflated, flight: mapping, at_s: 40, for_s: 20, h_acc_m: 5}  # a 3D fix, 5 m accuracy and noise
      - {kind: gps1_dropout, flight: mapping, at_s: 70, for_s: 30, off_s: 1.5, period_s: 5}  # 1.5 s of every 5 s gone

``at_s`` is on the clock of the flight it applies to (``flight``: "positioning", the default, where GPS1 is lost at
``denial.gps_until_s``; or "mapping", the survey), ``for_s`` how long it lasts. A GPS1 drag moves GPS1's reports
away from the truth at ``speed_m_s`` towards ``bearing_deg`` (from north) for ``for_s``, then holds that offset.
An inflated GPS1 keeps its 3D fix but reports ``h_acc_m`` and is that noisy; a GPS1 with dropouts sends nothing for
the first ``off_s`` of every ``period_s``.

The vehicle emulator (``python -m auxgps.sim.emulator --faults FILE``) takes the same file: it applies the GPS1 and
telemetry faults, whatever their ``flight``, at ``at_s`` after take-off (its one flight maps, then positions).
An autopilot reboot is the emulator's alone (``auxgps eval`` has no link and no boot clock; it ignores it): for
``for_s`` the autopilot sends nothing and reads nothing, then its boot clock starts again from 0 and it streams
only its HEARTBEAT, as a copter's SRn_ rates (all 0) leave it, until it is asked for messages again. The vehicle
flies on meanwhile: a real copter would not, but what auxgps must survive is the telemetry.
"""

from __future__ import annotations

from typing import Annotated, Literal

import cv2
import numpy as np
from pydantic import Field
from pydantic.dataclasses import dataclass as config_dataclass

from auxgps.config import _STRICT, NonNegative, Positive, parse_as, read_yaml
from auxgps.core.events import Attitude, Gps1, Position

Kind = Literal["camera_frozen", "camera_dark_half", "camera_saturated", "camera_blur", "camera_slow", "attitude_stops",
               "height_stuck", "telemetry_duplicated", "telemetry_reordered", "autopilot_reboot", "gps1_drag", "gps1_inflated",
               "gps1_dropout"]


@config_dataclass(config=_STRICT, frozen=True)
class Fault:
    kind: Kind
    at_s: NonNegative
    for_s: Positive
    blur_sigma_px: Positive = 4.0  # camera_blur
    fps: Annotated[float, Field(gt=0, le=100)] = 1.0  # camera_slow
    speed_m_s: NonNegative = 0.5  # gps1_drag
    bearing_deg: float = 0.0  # gps1_drag
    h_acc_m: Positive = 5.0  # gps1_inflated: the accuracy reported, and the noise, one sigma
    off_s: Positive = 1.5  # gps1_dropout: nothing for this long ...
    period_s: Positive = 5.0  # ... at the start of every period
    flight: Literal["positioning", "mapping"] = "positioning"

    def active(self, t_s: float) -> bool:
        return self.at_s <= t_s < self.at_s + self.for_s

    def in_effect(self, t_s: float) -> bool:
        """Acting on what is sent at ``t_s``: while active, and a drag's offset for good after it (it holds)."""
        return self.active(t_s) or (self.kind == "gps1_drag" and t_s >= self.at_s)

    def drag_velocity_ne_m_s(self) -> np.ndarray:
        """gps1_drag: the velocity of the drag while it lasts (north, east) m/s."""
        b = np.deg2rad(self.bearing_deg)
        return self.speed_m_s * np.array([np.cos(b), np.sin(b)])

    def drag_ne_m(self, t_s: float) -> np.ndarray:
        """gps1_drag: the offset of GPS1 from the truth at ``t_s`` (north, east) m."""
        return self.drag_velocity_ne_m_s() * float(np.clip(t_s - self.at_s, 0.0, self.for_s))

    def gps1_silent(self, t_s: float) -> bool:
        """gps1_dropout: True while GPS1 sends nothing."""
        return self.active(t_s) and (t_s - self.at_s) % self.period_s < self.off_s


@config_dataclass(config=_STRICT, frozen=True)
class FaultPlan:
    faults: list[Fault] = Field(default_factory=list)


def offset_deg(lat_deg: float, d_ne_m: np.ndarray) -> tuple[float, float]:
    """A small (north, east) offset in metres at ``lat_deg`` as (latitude, longitude) degrees (a sphere: the offsets
    faults apply are metres, where its error is micrometres)."""
    dlat = np.rad2deg(d_ne_m[0] / 6_378_137.0)
    dlon = np.rad2deg(d_ne_m[1] / (6_378_137.0 * np.cos(np.deg2rad(lat_deg))))
    return float(dlat), float(dlon)


def load_fault_plan(path) -> FaultPlan:
    return parse_as(FaultPlan, read_yaml(path), path)


class FaultInjector:
    """Applies a :class:`FaultPlan` to one flight's frames (:meth:`frame`) and telemetry (:meth:`events`)."""

    def __init__(self, plan: FaultPlan, flight: str | None = "positioning") -> None:
        self.faults = [f for f in plan.faults if flight is None or f.flight == flight]  # None: a mission's one flight
        self._held_image: dict[int, np.ndarray] = {}  # camera_frozen: the frame the driver repeats
        self._last_passed_t: dict[int, float] = {}  # camera_slow
        self._stuck_alt: dict[int, float] = {}  # height_stuck
        self._held_events: list = []  # telemetry_reordered
        self._rngs: dict[int, np.random.Generator] = {}  # gps1_inflated's noise

    @classmethod
    def for_flight(cls, faults, flight: str | None) -> "FaultInjector | None":
        """The injector of ``faults`` that apply to ``flight`` (None: every one, a mission's one flight), or None
        when none do."""
        injector = cls(FaultPlan(list(faults)), flight) if faults else None
        return injector if injector is not None and injector.faults else None

    def frame(self, t_s: float, image_bgr: np.ndarray) -> np.ndarray | None:
        """The image the estimator gets at ``t_s`` (None: the camera delivered no frame)."""
        for k, f in enumerate(self.faults):
            if not f.active(t_s):
                continue
            if f.kind == "camera_frozen":
                image_bgr = self._held_image.setdefault(k, image_bgr)
            elif f.kind == "camera_dark_half":
                image_bgr = image_bgr.copy()
                image_bgr[:, : image_bgr.shape[1] // 2] = 0
            elif f.kind == "camera_saturated":
                image_bgr = image_bgr.copy()
                image_bgr[:, : image_bgr.shape[1] // 2] = 255
            elif f.kind == "camera_blur":
                image_bgr = cv2.GaussianBlur(image_bgr, (0, 0), f.blur_sigma_px)
            elif f.kind == "camera_slow":
                last = self._last_passed_t.get(k)
                if last is not None and t_s - last < 1.0 / f.fps - 1e-9:
                    return None
                self._last_passed_t[k] = t_s
        return image_bgr

    def events(self, t_s: float, events: list) -> list:
        """The telemetry the estimator gets at simulation time ``t_s`` in place of ``events``."""
        out = list(events)
        for k, f in enumerate(self.faults):
            if f.kind == "attitude_stops" and f.active(t_s):
                out = [e for e in out if not isinstance(e, Attitude)]
            elif f.kind == "height_stuck" and f.active(t_s):
                out = [self._stuck(k, e) if isinstance(e, Position) else e for e in out]
            elif f.kind == "telemetry_duplicated" and f.active(t_s):
                out = [e for e in out for _ in (0, 1)]
            elif f.kind == "gps1_drag" and f.in_effect(t_s):
                out = [self._dragged(f, e) if isinstance(e, Gps1) and e.fix_type >= 3 else e for e in out]
            elif f.kind == "gps1_inflated" and f.active(t_s):
                out = [self._inflated(k, f, e) if isinstance(e, Gps1) and e.fix_type >= 3 else e for e in out]
            elif f.kind == "gps1_dropout" and f.gps1_silent(t_s):
                out = [e for e in out if not isinstance(e, Gps1)]
        reorder = any(f.kind == "telemetry_reordered" and f.active(t_s) for f in self.faults)
        if reorder:
            if not self._held_events:
                self._held_events, out = out, []
            else:
                out, self._held_events = out + self._held_events, []
        elif self._held_events:
            out, self._held_events = self._held_events + out, []
        return out

    @staticmethod
    def _moved(e: Gps1, d_ne_m: np.ndarray, h_acc_m: float | None = None) -> Gps1:
        dlat, dlon = offset_deg(e.lat_deg, d_ne_m)
        return Gps1(e.t_s, e.fix_type, e.satellites, e.lat_deg + dlat, e.lon_deg + dlon, e.alt_amsl_m,
                    e.h_acc_m if h_acc_m is None else h_acc_m)

    def _dragged(self, f: Fault, e: Gps1) -> Gps1:
        return self._moved(e, f.drag_ne_m(e.t_s))

    def _inflated(self, k: int, f: Fault, e: Gps1) -> Gps1:
        rng = self._rngs.setdefault(k, np.random.default_rng(1000 + k))
        return self._moved(e, rng.standard_normal(2) * f.h_acc_m, f.h_acc_m)

    def _stuck(self, k: int, e: Position) -> Position:
        alt = self._stuck_alt.setdefault(k, e.alt_above_home_m)
        return Position(e.t_s, e.lat_deg, e.lon_deg, e.alt_amsl_m, alt)
